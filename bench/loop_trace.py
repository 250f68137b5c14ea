"""Where a real-time loop's missed periods go: what the spin loop's thread was doing when a tick came late.

A :class:`LoopTrace` records, on the loop's clock (``time.perf_counter``), every tick of the pacing, every wait of
the executor (``spin_once`` with its timeout), every node callback (timers and subscriptions of the nodes built while
it is installed) and every garbage collection.  :func:`attribute_misses` then takes each gap between two ticks of
more than one and a half periods and names what filled the time after the tick was due, in this order:

* ``garbage collection``: a collection ran then;
* ``the tick itself``: the tick before ran past the next one's due time (the hardware read, the direct link to the
  controller, publishing, a samples flush);
* ``callbacks``: node callbacks ran then (each by name);
* ``woke late``: the loop slept in the executor and woke more than ``WOKE_LATE_S`` after its timeout, no callback
  run: the kernel's timer, or the virtual machine's host not running the CPU (at real-time priority no thread of
  normal priority can delay the wake-up);
* ``unaccounted``: none of these: the thread was preempted or stalled outside Python while it ran.

It costs about a microsecond per tick and per wait (the wrappers), so a traced run is not a headline run.
Nothing here imports ROS; ``time_callbacks_of`` patches the rclpy ``Node`` class it is given.
"""
from __future__ import annotations

import gc
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

WOKE_LATE_S = 5e-5          # a wait that ends this long after its timeout woke late
LATE_GAP_PERIODS = 1.5      # a gap between ticks longer than this many periods is a miss
CAUSES = ("garbage collection", "the tick itself", "callbacks", "woke late", "unaccounted")


@dataclass
class LoopTrace:
    """Intervals (start [s], duration [s]) of what the loop thread did; see the module's docstring."""
    ticks: list[tuple[float, float]] = field(default_factory=list)
    waits: list[tuple[float, float, float]] = field(default_factory=list)      # start, duration, timeout
    callbacks: list[tuple[float, float, str]] = field(default_factory=list)    # start, duration, name
    collections: list[tuple[float, float]] = field(default_factory=list)
    clock: Callable[[], float] = time.perf_counter
    _gc_start: float = 0.0

    def clear(self) -> None:
        """Forget what was recorded so far (e.g. after a warm-up)."""
        for intervals in (self.ticks, self.waits, self.callbacks, self.collections):
            intervals.clear()

    def tick(self, tick: Callable[[], None]) -> Callable[[], None]:
        """``tick``, timed."""
        def traced():
            t0 = self.clock()
            tick()
            self.ticks.append((t0, self.clock() - t0))
        return traced

    def executor(self, executor):
        """``executor`` with its ``spin_once`` timed (its other attributes as they are)."""
        trace = self

        class Traced:
            def __getattr__(self, name):
                return getattr(executor, name)

            def spin_once(self, timeout_sec=None):
                t0 = trace.clock()
                executor.spin_once(timeout_sec=timeout_sec)
                trace.waits.append((t0, trace.clock() - t0, timeout_sec or 0.0))
        return Traced()

    def callback(self, callback: Callable, name: str) -> Callable:
        """``callback``, timed under ``name``."""
        def traced(*args, **kwargs):
            t0 = self.clock()
            try:
                return callback(*args, **kwargs)
            finally:
                self.callbacks.append((t0, self.clock() - t0, name))
        return traced

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_start = self.clock()
        else:
            self.collections.append((self._gc_start, self.clock() - self._gc_start))

    def time_callbacks_of(self, node_class) -> Callable[[], None]:
        """Time the callbacks of ``node_class`` nodes created from now on (timers and subscriptions); returns the
        function that stops it for nodes created later."""
        create_timer, create_subscription = node_class.create_timer, node_class.create_subscription
        trace = self

        def timed_timer(node, period, callback, *args, **kwargs):
            name = f"{node.get_name()}: {getattr(callback, '__qualname__', 'timer')}"
            return create_timer(node, period, trace.callback(callback, name), *args, **kwargs)

        def timed_subscription(node, msg_type, topic, callback, *args, **kwargs):
            name = f"{node.get_name()}: {topic}"
            return create_subscription(node, msg_type, topic, trace.callback(callback, name), *args, **kwargs)
        node_class.create_timer, node_class.create_subscription = timed_timer, timed_subscription

        def undo():
            node_class.create_timer, node_class.create_subscription = create_timer, create_subscription
        return undo

    def time_collections(self) -> Callable[[], None]:
        """Time every garbage collection from now on; returns the function that stops it."""
        gc.callbacks.append(self._on_gc)

        def undo():
            if self._on_gc in gc.callbacks:
                gc.callbacks.remove(self._on_gc)
        return undo


@dataclass(frozen=True)
class Misses:
    """Missed periods of a traced run by cause (``CAUSES``) and the callbacks' share by name."""
    late_ticks: int                 # gaps between ticks longer than LATE_GAP_PERIODS periods
    periods: dict[str, int]         # periods missed, by cause
    excess_s: dict[str, float]      # time past the due tick, by cause [s]
    by_callback: dict[str, int]     # periods missed to callbacks, by callback

    def line(self) -> str:
        total = sum(self.periods.values())
        parts = [f"{cause} {n}" + (" (" + ", ".join(f"{k} {v}" for k, v in sorted(
            self.by_callback.items(), key=lambda kv: -kv[1])[:3]) + ")" if cause == "callbacks" and n else "")
                 for cause, n in self.periods.items() if n]
        return f"{total} periods missed in {self.late_ticks} late ticks: " + (", ".join(parts) or "none")


def _overlapping(intervals: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Indices of (start, duration) rows that overlap [lo, hi]."""
    if intervals.size == 0:
        return np.zeros(0, int)
    return np.flatnonzero((intervals[:, 0] < hi) & (intervals[:, 0] + intervals[:, 1] > lo))


def attribute_misses(trace: LoopTrace, period_s: float) -> Misses:
    """Each gap between ticks longer than LATE_GAP_PERIODS periods, its missed periods (the gap in whole periods,
    less the one it should have been) given to the first cause of ``CAUSES`` found in the time after the tick was
    due (see the module's docstring)."""
    ticks = np.array(trace.ticks, float).reshape(-1, 2)
    waits = np.array([(s, d) for s, d, _ in trace.waits], float).reshape(-1, 2)
    timeouts = np.array([t for _, _, t in trace.waits], float)
    calls = np.array([(s, d) for s, d, _ in trace.callbacks], float).reshape(-1, 2)
    names = [n for _, _, n in trace.callbacks]
    gcs = np.array(trace.collections, float).reshape(-1, 2)
    periods, excess, by_callback = Counter(), Counter(), Counter()
    late = 0
    for k in range(1, len(ticks)):
        gap = ticks[k, 0] - ticks[k - 1, 0]
        if gap <= LATE_GAP_PERIODS * period_s:
            continue
        late += 1
        due, missed = ticks[k - 1, 0] + period_s, max(1, int(round(gap / period_s)) - 1)
        window = (due, ticks[k, 0])
        in_calls = _overlapping(calls, *window)
        woke_late = [i for i in _overlapping(waits, *window) if timeouts[i] > 0
                     and waits[i, 1] > timeouts[i] + WOKE_LATE_S]
        if _overlapping(gcs, *window).size:
            cause = "garbage collection"
        elif ticks[k - 1, 0] + ticks[k - 1, 1] > due:
            cause = "the tick itself"
        elif in_calls.size:
            cause = "callbacks"
            by_callback[names[in_calls[np.argmax(calls[in_calls, 1])]]] += missed
        elif woke_late:
            cause = "woke late"
        else:
            cause = "unaccounted"
        periods[cause] += missed
        excess[cause] += gap - period_s
    return Misses(late, {c: periods[c] for c in CAUSES}, {c: float(excess[c]) for c in CAUSES}, dict(by_callback))
