"""What the benches share: busy loops beside a measurement, the host's own speed (a yardstick measured beside
every timing page), and printed lines kept for a results page.

Benches import it as ``harness`` (run as ``python bench/NAME.py``, this folder is on the path).  Not part of the
package: nothing under ``piezo_valve_ros`` imports it.
"""
from __future__ import annotations

import builtins
import contextlib
import multiprocessing
import sys
import timeit
from dataclasses import dataclass

BUSY_LOOPS = 2   # this machine has two cores: two busy loops keep both busy


def _burn(stop) -> None:
    while not stop.is_set():
        pass


@contextlib.contextmanager
def busy_loops(count: int = BUSY_LOOPS):
    """Run ``count`` busy loops (processes) for the duration of the ``with`` block."""
    stop = multiprocessing.Event()
    burners = [multiprocessing.Process(target=_burn, args=(stop,), daemon=True) for _ in range(count)]
    for b in burners:
        b.start()
    try:
        yield
    finally:
        stop.set()
        for b in burners:
            b.join()


def loaded(fn):
    """``fn()`` with ``BUSY_LOOPS`` busy loops running beside it."""
    with busy_loops():
        return fn()


YARDSTICK_PYTHON = "sum(range(1000))"   # the interpreter's speed: what the per-sample and per-period paths run on
YARDSTICK_GRAM_SHAPE = (40, 125_000)    # ... and BLAS's on one thread: the Gram product of a 2 kHz analysis's solve


@dataclass(frozen=True)
class Yardstick:
    """The host's speed at one moment: this shared machine's CPU time per unit of work drifts by a fifth within a
    day, so a timing page gives its yardstick, and two pages' seconds compare only as far as their yardsticks do."""
    python_us: float   # one sum(range(1000)) [us], best of 7
    gram_ms: float     # one (40 x 125000) Gram product on one BLAS thread [ms], best of 5

    def __str__(self) -> str:
        return f"{YARDSTICK_PYTHON} {self.python_us:.1f} us, a 40 x 125000 Gram product {self.gram_ms:.1f} ms"


def host_yardstick() -> Yardstick:
    """The host's speed now (about a second): a pure-Python loop and a one-thread BLAS product, best of a few."""
    import numpy as np
    from threadpoolctl import threadpool_limits
    python_us = min(timeit.repeat(YARDSTICK_PYTHON, number=2000, repeat=7)) / 2000 * 1e6
    rows = np.random.default_rng(0).standard_normal(YARDSTICK_GRAM_SHAPE)
    with threadpool_limits(1):
        gram_ms = min(timeit.repeat(lambda: rows @ rows.T, number=3, repeat=5)) / 3 * 1e3
    return Yardstick(python_us, gram_ms)


class Lines:
    """Prints each line at once and keeps it, for a results page written at the end."""

    def __init__(self, timing: bool = False):
        """``timing``: a page of timings, which gives the host's yardstick as the bench started and as it ended."""
        self.lines: list[str] = []
        self.started = host_yardstick() if timing else None

    def __call__(self, *parts, sep: str = " ", **_ignored) -> None:
        """As ``print`` (its ``flush`` and ``end`` are ignored: every line is flushed and ends the line)."""
        text = sep.join(str(p) for p in parts)
        builtins.print(text, flush=True)
        self.lines.extend(text.split("\n"))

    def write_markdown(self, path: str, bench: str, note: str = "") -> None:
        """``path``: the command that wrote it (``bench`` and this run's arguments), ``note``, on a timing page the
        host's yardstick at the start and now, the lines."""
        speed = "" if self.started is None else yardstick_note(self.started, host_yardstick()) + "\n\n"
        with open(path, "w") as fh:
            fh.write(f"Output of `python {bench} {' '.join(sys.argv[1:])}`{note}:\n\n{speed}```\n"
                     + "\n".join(self.lines) + "\n```\n")


def yardstick_note(started: Yardstick, ended: Yardstick) -> str:
    """The line a timing page gives its host's speed in (``Yardstick``)."""
    return (f"Host yardstick (``bench/harness.py``: lower is faster; compare a page's seconds with another's only "
            f"as far as their yardsticks agree): at the start {started}; at the end {ended}.")
