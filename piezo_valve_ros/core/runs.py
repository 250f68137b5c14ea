"""A recorded closed-loop run (samples and the references sent): a window of a long run, the reference on the
sample grid, the steps in it and their metrics.  ROS-free; ``valve_plot`` is its command-line face."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .errors import PiezoValveError

from .metrics import step_metrics

STEP_MIN_JUMP_M = 1e-6      # a reference change of at least 1 um ...
STEP_MIN_HOLD_S = 0.05      # ... held at least this long after it (and before the next change) is a step
ALIGN_WINDOW_S = 1.0        # a jump of the reference is moved to the command's reaction within this of its receive time
ALIGN_MIN_RATIO = 10.0      # ... a command change this many times the window's median change (a clear reaction)
BURST_S = 0.02              # ... and the references received within this of it move with it


class WindowError(PiezoValveError, ValueError):
    """A window of a record that is malformed or holds no samples (one-line message)."""


@dataclass(frozen=True)
class TimeWindow:
    """A stretch of a long record: from ``from_s`` to ``to_s`` [s] (either open), counted from the record's first
    sample, or on the samples' own time axis (``on_stamps``: the times the hardware stamped them with)."""

    from_s: Optional[float] = None
    to_s: Optional[float] = None
    on_stamps: bool = False

    def problems(self) -> list[str]:
        out = []
        for name, value in (("from", self.from_s), ("to", self.to_s)):
            if value is not None and not math.isfinite(value):
                out.append(f"--{name} must be a finite time [s], not {value}")
            elif value is not None and value < 0 and not self.on_stamps:
                out.append(f"--{name} {value:g} s is before the record's start (seconds from its first sample)")
        if not out and self.from_s is not None and self.to_s is not None and self.to_s <= self.from_s:
            out.append(f"--to {self.to_s:g} s must come after --from {self.from_s:g} s")
        return out

    @property
    def whole(self) -> bool:
        return self.from_s is None and self.to_s is None

    def bounds(self, first_time_s: float) -> tuple[float, float]:
        """The window on the samples' time axis [s] for a record whose first sample is at ``first_time_s``."""
        origin = 0.0 if self.on_stamps else first_time_s
        return (-math.inf if self.from_s is None else origin + self.from_s,
                math.inf if self.to_s is None else origin + self.to_s)

    def rows(self, rows: np.ndarray, first_time_s: float) -> np.ndarray:
        """The rows (time [s] first) inside the window."""
        lo, hi = self.bounds(first_time_s)
        return rows[(rows[:, 0] >= lo) & (rows[:, 0] <= hi)]

    def describe(self) -> str:
        axis = "s on the samples' own time axis" if self.on_stamps else "s from the record's first sample"
        lo = "its start" if self.from_s is None else f"{self.from_s:g}"
        hi = "its end" if self.to_s is None else f"{self.to_s:g}"
        return f"{lo} to {hi} {axis}"

    def as_dict(self) -> dict:
        return {"from_s": self.from_s, "to_s": self.to_s, "axis": "stamps" if self.on_stamps else "record_start"}


WHOLE_RECORD = TimeWindow()


@dataclass(frozen=True)
class RunStep:
    """One step of the reference: at ``time_s``, ``start_um`` -> ``end_um``; settling (5 % band) [s] and
    overshoot [%] of the measured position until the next change of the reference."""

    time_s: float
    start_um: float
    end_um: float
    settling_time_s: float
    overshoot_pct: float
    hold_s: float


def receive_to_sample_time(stamps_s: np.ndarray, sample_times_s: np.ndarray):
    """A map from receive times [s] (a recorder's clock) onto the samples' time axis [s], from pairs of a message's
    receive time and the sample time it carried: piecewise linear between the pairs (so it follows a rig whose
    simulated time runs at a varying share of the wall clock, as a lockstep rig's does), the nearest pair's offset
    beyond them.  Pairs are taken in receive order, and the sample times made non-decreasing (a message that
    arrived late does not fold the axis back).  Returns a function of an array of receive times."""
    stamps = np.asarray(stamps_s, float)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    times = np.maximum.accumulate(np.asarray(sample_times_s, float)[order])
    if stamps.size == 0:
        raise ValueError("no message pairs a receive time with a sample time")

    def to_sample_time(received_s) -> np.ndarray:
        r = np.asarray(received_s, float)
        out = np.interp(r, stamps, times)
        out = np.where(r < stamps[0], times[0] + (r - stamps[0]), out)
        return np.where(r > stamps[-1], times[-1] + (r - stamps[-1]), out)
    return to_sample_time


def align_jumps(time_s: np.ndarray, command_v: np.ndarray, ref_time_s: np.ndarray, ref_m: np.ndarray,
                min_jump_m: float = STEP_MIN_JUMP_M, window_s: float = ALIGN_WINDOW_S) -> np.ndarray:
    """Reference times [s] with each jump of the reference (a change of at least ``min_jump_m`` held, as a step is,
    at least ``STEP_MIN_HOLD_S`` before and after it: a sine or a ramp sent as many small changes has none, and
    moving each of its changes to a "reaction" turned a tracked sine into a staircase) moved to the sample
    where the command reacted to it: within ``window_s`` of its time and after the sample the jump before it was
    moved to, the first sample whose command change in the jump's direction is at least half the largest such
    change there and ``ALIGN_MIN_RATIO`` times the window's median change; the references after it that came in the
    same burst (received within ``BURST_S``) move with it.  Receive times place a reference within the recorder's
    delivery delay, which on a loaded machine, on a lockstep rig whose time runs in bursts, reaches tenths of a
    second of the rig's time; the command shows when the controller applied it.  Two jumps sent close together
    each find their own reaction (a step back down the loop's other branch moves the command more than twice as
    far as the step before it).  A jump with no clear reaction (a strategy without proportional action, a rail)
    keeps its time."""
    t = np.asarray(time_s, float)
    v = np.asarray(command_v, float)
    received = np.asarray(ref_time_s, float)
    values = np.asarray(ref_m, float)
    signed = np.diff(v, prepend=v[:1])
    change = np.abs(signed)
    steps = np.diff(values, prepend=np.nan)
    changed = np.flatnonzero(steps != 0)                 # (the first reference counts as a change: NaN before it)
    since = np.diff(received[changed], prepend=-np.inf)  # held before each change, and after it until the next
    until = np.append(np.diff(received[changed]), np.inf)
    held = changed[(since >= STEP_MIN_HOLD_S) & (until >= STEP_MIN_HOLD_S)]
    jumps = held[np.abs(steps[held]) >= min_jump_m]
    shift = np.zeros(received.size)
    after = 0   # the first sample a jump's reaction may be at: after the reaction the jump before it was moved to
    for j, end in zip(jumps, np.append(jumps[1:], received.size)):
        lo = max(int(np.searchsorted(t, received[j] - window_s)), after)
        hi = int(np.searchsorted(t, received[j] + window_s))
        if hi - lo < 3:
            continue
        toward = np.sign(steps[j]) * signed[lo:hi]   # the command's changes in the jump's direction
        largest = float(np.max(toward))
        if largest <= 0 or largest < ALIGN_MIN_RATIO * float(np.median(change[lo:hi])):
            continue
        reaction = lo + int(np.argmax(toward >= 0.5 * largest))
        burst = j + np.flatnonzero(received[j:end] <= received[j] + BURST_S)
        shift[burst] = t[reaction] - received[j]
        after = reaction + 1
    return np.maximum.accumulate(received + shift)


def reference_on_samples(time_s: np.ndarray, ref_time_s: np.ndarray, ref_m: np.ndarray) -> np.ndarray:
    """The reference in force at each sample time [m] (the last one received; NaN before the first)."""
    t = np.asarray(time_s, float)
    if len(ref_m) == 0:
        return np.full(t.shape, np.nan)
    k = np.searchsorted(np.asarray(ref_time_s, float), t, side="right") - 1
    out = np.asarray(ref_m, float)[np.maximum(k, 0)]
    out[k < 0] = np.nan
    return out


def find_steps(time_s: np.ndarray, position_m: np.ndarray, reference_m: np.ndarray,
               min_jump_m: float = STEP_MIN_JUMP_M, min_hold_s: float = STEP_MIN_HOLD_S) -> list[RunStep]:
    """Steps of ``reference_m`` (on the sample grid): a change of at least ``min_jump_m`` held for at least
    ``min_hold_s``, from a value held as long before (a sine or a ramp sent as many small changes gives
    none); their settling and overshoot."""
    t, y, r = (np.asarray(a, float) for a in (time_s, position_m, reference_m))
    valid = np.isfinite(r)
    change = np.flatnonzero(valid[1:] & valid[:-1] & (r[1:] != r[:-1])) + 1
    if change.size == 0 or t.size < 2:
        return []
    dt = float(np.median(np.diff(t)))
    bounds = np.concatenate((change, [t.size]))
    first_valid = int(np.argmax(valid))
    steps = []
    for j, k in enumerate(change):
        before_start = change[j - 1] if j else first_valid
        held_before = t[k - 1] - t[before_start]
        hold = t[bounds[j + 1] - 1] - t[k]
        start_m, end_m = r[k - 1], r[k]
        if abs(end_m - start_m) < min_jump_m or hold < min_hold_s or held_before < min_hold_s:
            continue
        m = step_metrics(y[k:bounds[j + 1]], 0, start_m * 1e6, end_m * 1e6, dt)
        steps.append(RunStep(float(t[k]), float(start_m * 1e6), float(end_m * 1e6), m.settling_time_s,
                             m.overshoot_pct, float(hold)))
    return steps
