"""What the benches share: busy loops beside a measurement, and printed lines kept for a results page.

Benches import it as ``harness`` (run as ``python bench/NAME.py``, this folder is on the path).  Not part of the
package: nothing under ``piezo_valve_ros`` imports it.
"""
from __future__ import annotations

import builtins
import contextlib
import multiprocessing
import sys

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


class Lines:
    """Prints each line at once and keeps it, for a results page written at the end."""

    def __init__(self):
        self.lines: list[str] = []

    def __call__(self, *parts, sep: str = " ", **_ignored) -> None:
        """As ``print`` (its ``flush`` and ``end`` are ignored: every line is flushed and ends the line)."""
        text = sep.join(str(p) for p in parts)
        builtins.print(text, flush=True)
        self.lines.extend(text.split("\n"))

    def write_markdown(self, path: str, bench: str, note: str = "") -> None:
        """``path``: the command that wrote it (``bench`` and this run's arguments), ``note``, the lines."""
        with open(path, "w") as fh:
            fh.write(f"Output of `python {bench} {' '.join(sys.argv[1:])}`{note}:\n\n```\n"
                     + "\n".join(self.lines) + "\n```\n")
