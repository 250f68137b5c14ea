"""Timing of the control loop as the hardware sees it (ROS-free, allocation-free per period).

Each control period the hardware publishes a position (:meth:`LoopTiming.measured`) and the
controller answers with a command (:meth:`LoopTiming.commanded`).  The *latency* of a period is
the time from publishing the position to receiving the first command after it; the command is
*in time* when that latency is at most one control period, i.e. it is applied from the next
period on as the loop assumes.  A period whose measurement gets no command before the next one
goes out is *unanswered*; a command that arrives when no measurement awaits one is *late* (it
answers an earlier measurement).  A real-time loop can also lose periods when the tick itself is
late (the valve ran on for more than one period on the old command), so the in-time share is
taken over the periods that *should* have elapsed, ``max(periods, elapsed / period + 1)``.
Latencies are kept in a preallocated ring (the most recent ``capacity`` periods); counters cover
the whole run.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

__all__ = ["LoopTiming", "LoopSummary"]


@dataclass(frozen=True)
class LoopSummary:
    """Loop figures over a run (times in seconds, rates in Hz)."""
    periods: int
    elapsed_s: float
    nominal_rate_hz: float
    achieved_rate_hz: float
    answered: int
    in_time: int
    unanswered: int
    late: int
    in_time_share: float
    latency_p50_s: float
    latency_p99_s: float
    latency_max_s: float
    interval_p99_s: float  # gap between successive measurements (timer jitter)
    stalls: int            # gaps between measurements longer than two periods
    longest_gap_s: float

    def line(self) -> str:
        """One human-readable line (ms / %)."""
        return (f"{self.periods} periods in {self.elapsed_s:.2f} s = {self.achieved_rate_hz:.0f} Hz "
                f"(nominal {self.nominal_rate_hz:.0f} Hz); commands in time {100 * self.in_time_share:.2f} %, "
                f"unanswered {self.unanswered}, late {self.late}; latency p50 {self.latency_p50_s * 1e3:.3f} ms, "
                f"p99 {self.latency_p99_s * 1e3:.3f} ms, max {self.latency_max_s * 1e3:.3f} ms; "
                f"interval p99 {self.interval_p99_s * 1e3:.3f} ms, {self.stalls} stalls > 2 periods "
                f"(longest {self.longest_gap_s * 1e3:.2f} ms)")

    def lockstep_line(self) -> str:
        """The same run in lockstep, where time is simulated: deadlines and stalls mean nothing there; what
        counts is how fast the rig stepped and how long a command took to come back (ms)."""
        sim_s = self.periods / self.nominal_rate_hz if self.nominal_rate_hz else float("nan")
        return (f"lockstep: {self.periods} periods ({sim_s:.3f} s simulated) in {self.elapsed_s:.2f} s wall "
                f"= {self.periods / self.elapsed_s if self.elapsed_s > 0 else 0.0:.0f} periods/s; "
                f"{self.answered} commands answered positions, round trip p50 {self.latency_p50_s * 1e3:.3f} ms, "
                f"p99 {self.latency_p99_s * 1e3:.3f} ms")

    def as_dict(self) -> dict:
        return asdict(self)


class LoopTiming:
    """Counts periods, answers and latencies; ``clock`` returns seconds (monotonic)."""

    def __init__(self, control_period_s: float, capacity: int = 1 << 18,
                 clock: Callable[[], float] = time.perf_counter):
        if not control_period_s > 0:
            raise ValueError("control_period_s must be positive")
        self.control_period_s = float(control_period_s)
        self.clock = clock
        self._latency = np.empty(int(capacity))
        self._interval = np.empty(int(capacity))
        self.reset()

    def reset(self) -> None:
        """Start counting afresh (e.g. after a warm-up)."""
        self.periods = 0
        self.answered = 0
        self.in_time = 0
        self.unanswered = 0
        self.late = 0
        self._n_latency = 0
        self._n_interval = 0
        self._t_measured = None
        self._t_first = None
        self._waiting = False

    def measured(self, t: float | None = None) -> None:
        """A position went out (call right after publishing it)."""
        t = self.clock() if t is None else t
        if self._t_measured is None:
            self._t_first = t
        else:
            k = self._n_interval % self._interval.size
            self._interval[k] = t - self._t_measured
            self._n_interval += 1
        if self._waiting:
            self.unanswered += 1
        self.periods += 1
        self._t_measured = t
        self._waiting = True

    def commanded(self, t: float | None = None) -> bool | None:
        """A valid command arrived (only the first one after a measurement counts).  Returns whether it came
        within a period of its measurement; None for a command that answers no measurement."""
        if not self._waiting:
            self.late += 1
            return None
        t = self.clock() if t is None else t
        latency = t - self._t_measured
        self._waiting = False
        self.answered += 1
        in_time = latency <= self.control_period_s
        if in_time:
            self.in_time += 1
        self._latency[self._n_latency % self._latency.size] = latency
        self._n_latency += 1
        return in_time

    def summary(self) -> LoopSummary:
        lat = self._latency[:min(self._n_latency, self._latency.size)]
        gaps = self._interval[:min(self._n_interval, self._interval.size)]
        elapsed = (self._t_measured - self._t_first) if self.periods > 1 else 0.0
        q = (lambda a, p: float(np.percentile(a, p)) if a.size else float("nan"))
        due = max(self.periods, int(elapsed / self.control_period_s + 0.5) + 1) if self.periods else 0
        return LoopSummary(
            periods=self.periods, elapsed_s=elapsed, nominal_rate_hz=1.0 / self.control_period_s,
            achieved_rate_hz=(self.periods - 1) / elapsed if elapsed > 0 else float("nan"),
            answered=self.answered, in_time=self.in_time, unanswered=self.unanswered, late=self.late,
            in_time_share=self.in_time / due if due else float("nan"),
            latency_p50_s=q(lat, 50), latency_p99_s=q(lat, 99),
            latency_max_s=float(lat.max()) if lat.size else float("nan"), interval_p99_s=q(gaps, 99),
            stalls=int(np.count_nonzero(gaps > 2 * self.control_period_s)),
            longest_gap_s=float(gaps.max()) if gaps.size else float("nan"))
