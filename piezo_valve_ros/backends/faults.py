"""What a data-acquisition card does wrong, named: the hardware node's latched fault and the checks that find one.

A fault is latched by ``valve_hardware`` (safe voltage applied, ERROR on /diagnostics naming it and when it
first occurred) and left only when told (its ``~/reset`` service, ``valve_command reset``).  The kinds:

``read_failed``       the backend raised while reading (a transient error is retried once within the period)
``write_failed``      the backend raised while writing a voltage
``non_finite_sample`` a sample's time, command or position is NaN or infinite
``implausible_sample`` a position beyond ``fault.position_limit_m`` (no spool travels that far)
``stuck_sensor``      the position has not changed at all for ``fault.stuck_time_s`` since the command moved over
                      ``fault.stuck_command_span_v`` with the reading unchanged (a frozen reading; any live
                      sensor's noise, or the spool's answer to a volt within milliseconds, changes it; a noise-free
                      sensor at rest repeats its reading until the command moves, and answers at once when it does)
``no_samples``        the backend returned no samples for ``fault.missing_samples_s`` on the wall clock

No ROS import: the checks run on the rows a backend returns (time [s], command [V], position [m]).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ["FAULT_KINDS", "Fault", "FaultLimits", "SampleCheck"]

FAULT_KINDS = ("read_failed", "write_failed", "non_finite_sample", "implausible_sample", "stuck_sensor", "no_samples")


@dataclass(frozen=True)
class Fault:
    """A latched fault: its kind (one of FAULT_KINDS), what was seen, and when it first occurred (monotonic wall
    time [s]); ``count``: occurrences since (repeated reads or writes that fail, further bad samples)."""
    kind: str
    detail: str
    first_at_s: float
    count: int = 1

    def text(self, now_s: float) -> str:
        return f"{self.kind}: {self.detail} (first {now_s - self.first_at_s:.1f} s ago, {self.count} time(s))"


@dataclass(frozen=True)
class FaultLimits:
    """The plausibility limits (the node's ``fault.*`` parameters).  Defaults that never trip on a healthy valve:
    a spool moves a few hundred um at most; a live sensor's reading changes within a sample or two when the
    command moves by a volt; a DAQ delivers samples every period."""
    position_limit_m: float = 1e-3
    stuck_time_s: float = 0.5
    stuck_command_span_v: float = 1.0
    missing_samples_s: float = 0.5

    def problems(self) -> list[str]:
        out = []
        for name, low, high in (("position_limit_m", 1e-5, 1.0), ("stuck_time_s", 0.05, 10.0),
                                ("stuck_command_span_v", 0.05, 100.0), ("missing_samples_s", 0.05, 10.0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and low <= value <= high):
                out.append(f"fault.{name} must lie in [{low:g}, {high:g}], got {value!r}")
        return out


class SampleCheck:
    """The checks on each period's rows; ``check`` returns (kind, detail) of the first problem, or None.  Keeps
    a few scalars (the last position and how long it has not changed, the command's span since), so a period's
    check allocates only what numpy's reductions do."""

    def __init__(self, limits: FaultLimits):
        problems = limits.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self.limits = limits
        self.reset()

    def reset(self) -> None:
        self._last_position = math.nan
        self._unchanged_since_s = math.nan      # sample time the position last changed
        self._command_lo = math.inf
        self._command_hi = -math.inf
        self._moved_at_s = math.nan             # sample time the command had moved over the span, reading unchanged

    def check(self, rows: np.ndarray) -> Optional[tuple[str, str]]:
        """Rows (k, 3) of time [s], command [V], position [m] from one read.  A few microseconds per period: the
        usual period (the reading changed at its last sample) costs three numpy reductions."""
        n = rows.shape[0]
        if n == 0:
            return None
        if not math.isfinite(float(rows.sum())):
            bad = rows[~np.isfinite(rows).all(axis=1)][0]
            return "non_finite_sample", f"sample (time, command, position) = ({bad[0]:g}, {bad[1]:g}, {bad[2]:g})"
        position = rows[:, 2]
        lo, hi = float(position.min()), float(position.max())
        if max(-lo, hi) > self.limits.position_limit_m:
            worst = max(-lo, hi)
            return "implausible_sample", (f"position {1e6 * worst:.1f} um beyond fault.position_limit_m "
                                          f"{1e6 * self.limits.position_limit_m:.0f} um")
        last = float(position[-1])
        before = float(position[-2]) if n > 1 else self._last_position
        if last != before:                     # changed at the last sample (a live sensor's usual period)
            self._unchanged_since_s = float(rows[-1, 0])
            self._command_lo = self._command_hi = float(rows[-1, 1])
            self._moved_at_s = math.nan
        elif lo != hi or (last != self._last_position and not math.isnan(self._last_position)):
            k = int(np.flatnonzero(np.diff(position))[-1]) + 1 if lo != hi else 0   # the row it last changed at
            self._unchanged_since_s = float(rows[k, 0])
            tail = rows[k:, 1]
            self._command_lo, self._command_hi = float(tail.min()), float(tail.max())
            self._moved_at_s = math.nan
        else:                                  # the same reading all through (or the first read)
            if math.isnan(self._unchanged_since_s):
                self._unchanged_since_s = float(rows[0, 0])
            command = rows[:, 1]
            self._command_lo = min(self._command_lo, float(command.min()))
            self._command_hi = max(self._command_hi, float(command.max()))
        self._last_position = last
        now_s = float(rows[-1, 0])
        span = self._command_hi - self._command_lo
        if span >= self.limits.stuck_command_span_v and math.isnan(self._moved_at_s):
            self._moved_at_s = now_s
        frozen_s = now_s - self._moved_at_s    # frozen since the command moved (NaN: it has not)
        if frozen_s >= self.limits.stuck_time_s and span >= self.limits.stuck_command_span_v:
            return "stuck_sensor", (f"position frozen at {1e6 * last:.3f} um for {now_s - self._unchanged_since_s:.2f} s, "
                                    f"{frozen_s:.2f} s of it since the command moved over {span:.2f} V")
        return None
