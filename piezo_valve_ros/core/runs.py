"""A recorded closed-loop run (samples and the references sent): the reference on the sample grid, the
steps in it and their metrics.  ROS-free; ``valve_plot`` is its command-line face."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .metrics import step_metrics

STEP_MIN_JUMP_M = 1e-6      # a reference change of at least 1 um ...
STEP_MIN_HOLD_S = 0.05      # ... held at least this long after it (and before the next change) is a step


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
