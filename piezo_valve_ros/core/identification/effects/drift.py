"""Drift: a slow change of offset and gain (thermal), not tied to the hysteresis' memory.

Terms: offset and gain (times the normalised output) multiplied by slow functions of
* the time since the record started (ambient drift): linear, and exponential approaches over 0.3 and 1 times the
  training record's length, and over 0.03 and 0.1 times it (a warm-up of a few seconds);
* the drive's activity (self-heating): the input rate |dv/dt| through first-order lags of 10 s and 40 s,
  normalised by its mean over the training record;
* a slow wander of any shape the record resolves: half-cosines of the time over the training record's length
  (``WANDER_TERMS`` of them, held at their end beyond it).
Four nested forms, chosen on held-out data (``held_out_forms``): "linear" (the time alone), "all" (the time, the
slow exponentials and the heating), "fast" (and the fast exponentials) and "wander" (all of it).  A fifth, "whole",
is a long record's trend (``whole_record``): cubic B-splines on ``trend_terms`` intervals of the whole record.  A richer one always fits the training record better; where
the drift is linear the exponentials and heating terms fit a share of the hysteresis' own slow misfit and bend the
extrapolated slope.  So a smooth trend in time, whatever its shape, is drift, and creep (tied to the input's
history) is not needed for it.
A separate validation record starts its own clock and its own heating (the same initial state).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from ...model.dynamics import lag_bank
from ..records import Record
from .base import Effect, NotCompensable, normalised

__all__ = ["Drift", "TIME_SCALES", "FAST_TIME_SCALES", "HEATING_TIME_CONSTANTS_S", "WANDER_TERMS", "FORMS"]

TIME_SCALES = (0.3, 1.0)                # exponential approaches, as shares of the training record's length
FAST_TIME_SCALES = (0.03, 0.1)          # ... and those of the "fast" and "wander" forms
HEATING_TIME_CONSTANTS_S = (10.0, 40.0)
WANDER_TERMS = 3                        # half-cosines cos(pi k t / T) - 1, k = 1..3, of the "wander" form
FORMS = ("linear", "all", "fast", "wander")   # see Drift.held_out_forms: the simplest first, each in the next
_SLOW: dict = {}       # (record, t0, form, T, rate) -> (the record's times, its slow functions): see slow_rows
_SLOW_KEPT = 16


@dataclass(frozen=True)
class Drift(Effect):
    name = "drift"
    simulated_by = ("drift",)
    compensated_by = ()
    telling_experiment = ("the same cycle repeated before and after a long hold: drift moves with the time since the "
                          "start whatever the input did, creep and hysteresis do not")
    signature = ("slow change of offset or gain: the residual trends with the time since the start or with how "
                 "hard the valve has been driven (self-heating)")
    duration_s: float = 1.0
    centre_um: float = 0.0
    half_range_um: float = 1.0
    mean_rate_v_s: float = 1.0
    form: str = "all"   # "linear" (t/T alone) or "all" (see FORMS), or "whole"
    trend_terms: int = 0   # the "whole" form's spline intervals
    trend_from_s: float = 0.0   # ... and where its trend starts (after t0) [s]

    def whole(self, duration_s: float, trend_terms: int, from_s: float = 0.0) -> "Drift":
        """The "whole" form over ``duration_s`` [s] in ``trend_terms`` spline intervals (a long record's trend),
        starting ``from_s`` [s] after t0 (zero before: the stretch a model was fitted and judged on)."""
        return replace(self, duration_s=duration_s, form="whole", trend_terms=trend_terms, trend_from_s=from_s)

    def time_rows(self, t: np.ndarray) -> np.ndarray:
        """(k, N) the "whole" form's functions of the time since the model's t0 [s]: cubic B-splines on
        ``trend_terms`` equal intervals from ``trend_from_s`` to the record's length T, less those not zero at their
        start (the first; and the second, its slope, where the trend starts after t0: it goes on smoothly from the
        flat stretch before it), so the trend starts at zero, and one that sets in late is zero until it does (each
        spline is zero outside four intervals); held at their value at T beyond it."""
        from scipy.interpolate import BSpline
        k = max(int(self.trend_terms), 1)
        knots = np.concatenate(([0.0] * 3, np.linspace(0.0, 1.0, k + 1), [1.0] * 3))
        start = self.trend_from_s
        x = np.clip((np.asarray(t, float) - start) / (self.duration_s - start), 0.0, 1.0)
        rows = BSpline.design_matrix(x, knots, 3).T.toarray()
        return np.ascontiguousarray(rows[2:] if start > 0 else rows[1:])
    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> Optional["Drift"]:
        lo, hi = float(np.min(H)), float(np.max(H))
        rate = float(np.mean(np.abs(np.gradient(train.voltage_v, train.dt))))
        return cls(train.duration_s, 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9), max(rate, 1e-12))

    def held_out_forms(self) -> list["Drift"]:
        return [replace(self, form=f) for f in FORMS]

    def slow_rows(self, ctx) -> np.ndarray:
        """(k, N) functions of time and activity this form multiplies offset and gain by, one per row: the same for
        every model on the record, so kept (``_SLOW_KEPT`` of them) for the refits that build them again and again."""
        key = (id(ctx.record.time_s), len(ctx.record), float(ctx.t0), self.form, self.duration_s, self.mean_rate_v_s)
        kept = _SLOW.get(key)
        if kept is not None and kept[0] is ctx.record.time_s:
            return kept[1]
        out = self._slow_rows(ctx)
        out.setflags(write=False)
        while len(_SLOW) >= _SLOW_KEPT:
            _SLOW.pop(next(iter(_SLOW)), None)
        _SLOW[key] = (ctx.record.time_s, out)
        return out

    def _slow_rows(self, ctx) -> np.ndarray:
        t, T = ctx.t, self.duration_s
        if self.form == "linear":
            return (t / T)[None, :]
        if self.form == "whole":
            return self.time_rows(t)
        activity = np.abs(np.gradient(ctx.v, ctx.dt)) / self.mean_rate_v_s
        heating = lag_bank(activity, HEATING_TIME_CONSTANTS_S, ctx.dt).T   # (k, N), contiguous
        heating -= heating[:, :1]
        rows = [t / T] + [1.0 - np.exp(-t / (f * T)) for f in self.time_scales] + list(heating)
        if self.form == "wander":
            held = np.minimum(t / T, 1.0)
            rows += [np.cos(np.pi * k * held) - 1.0 for k in range(1, WANDER_TERMS + 1)]
        return np.stack(rows)

    @property
    def time_scales(self) -> tuple[float, ...]:
        """The exponential approaches of this form, as shares of the training record's length."""
        return TIME_SCALES + (FAST_TIME_SCALES if self.form in ("fast", "wander") else ())

    def design_rows(self, ctx) -> np.ndarray:
        k = self.slow_rows(ctx)
        rows = np.empty((2 * k.shape[0], k.shape[1]))
        rows[:k.shape[0]] = k
        np.multiply(k, normalised(ctx.H, self.centre_um, self.half_range_um)[None, :], out=rows[k.shape[0]:])
        return rows

    def columns(self, ctx) -> np.ndarray:
        return self.design_rows(ctx).T

    def describe(self, model, coefs) -> dict:
        if self.form == "whole":
            first = 3 if self.trend_from_s > 0 else 2
            names = [f"spline_{j}_of_{self.trend_terms}_from_{self.trend_from_s:g}s"
                     for j in range(first, max(self.trend_terms, 1) + 4)]
        else:
            names = ["t/T"] + ([] if self.form == "linear" else [f"1-exp(-t/({f}T))" for f in self.time_scales]
                               + [f"heating_{int(t)}s" for t in HEATING_TIME_CONSTANTS_S]) + (
                [f"cos({k} pi min(t/T, 1))-1" for k in range(1, WANDER_TERMS + 1)] if self.form == "wander" else [])
        n = len(names)
        return {"form": self.form, "functions": names, "T_s": self.duration_s, "offset_um": [float(c) for c in coefs[:n]],
                "gain_um": [float(c) for c in coefs[n:]]}

    def plot_axis(self, ctx):
        return ctx.t, "time since start [s]", False

    def compensation(self, model, coefs) -> dict:
        raise NotCompensable("drift: left to the feedback (an integrator absorbs a slow offset)")
