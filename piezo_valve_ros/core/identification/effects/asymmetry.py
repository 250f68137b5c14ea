"""Asymmetry: ascending and descending branches follow different envelopes.

Structure: every operator's descending envelope gets its own shift, slope and curvature about the
centre of the input range, ``gamma_desc(v) = v + beta0 + beta1 (v - v_c) + beta2 (v - v_c)^2 / h``
(``gamma_asc(v) = v``, h the half span): the generalized PI model with different envelope functions (Al
Janaideh, Rakheja, Su), fitted by Gauss-Newton on the exact sensitivity of the operators to their upper
bound.  The shift alone is no asymmetry: it is the same loop as a symmetric GPIM on thresholds moved by half of it
(``symmetric_thresholds``), which the residual loop tries before it names the effect (``residual``'s
``revisit_placement``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from ...model.hysteresis import GPIM, inverse_problems
from ..records import Record
from .base import Effect, NotCompensable

__all__ = ["Asymmetry", "MAX_SLOPE_CHANGE", "MAX_SHIFT_SHARE"]

MAX_SLOPE_CHANGE = 0.5  # |beta1|, |beta2| <= 0.5: the descending envelope stays monotone over the range
MAX_SHIFT_SHARE = 0.2   # |beta0| <= 0.2 of the half span
MIN_SLOPE_SHARE = 0.2   # the descending envelope's slope stays >= 0.2 of the ascending one's, from 0 V to the range's end
PLACED_THRESHOLD_FLOOR_V = 1e-6   # a threshold moved to this or below is the zero-threshold operator


@dataclass(frozen=True)
class Asymmetry(Effect):
    name = "asymmetry"
    simulated_by = ("asymmetry",)
    compensated_by = ("gpim",)
    telling_experiment = ("slow full cycles and minor loops at both ends of the range: asymmetric envelopes bend one "
                          "branch more than the other, at any rate and level")
    signature = ("ascending and descending branches differ: the residual follows the operators' sensitivity to a "
                 "descending envelope of another shift, slope and curvature")
    centre_v: float = 5.0
    half_span_v: float = 5.0

    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> Optional["Asymmetry"]:
        lo, hi = float(np.min(train.voltage_v)), float(np.max(train.voltage_v))
        return cls(0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9))

    def betas(self, gpim: GPIM) -> tuple[float, float, float]:
        """(beta0 [V], beta1, beta2) of a GPIM's descending envelope relative to its ascending one (a0 = 1, a1 = 0)."""
        if gpim.b0 is None:
            return 0.0, 0.0, 0.0
        c, h, a0 = self.centre_v, self.half_span_v, gpim.a0
        beta2 = float(gpim.b2) * h / a0
        beta1 = float(gpim.b0) / a0 - 1.0 + 2.0 * beta2 * c / h
        beta0 = (float(gpim.b0) * c + float(gpim.b1) + float(gpim.b2) * c * c - (a0 * c + gpim.a1)) / a0
        return beta0, beta1, beta2

    def symmetric_thresholds(self, gpim: GPIM) -> np.ndarray:
        """Thresholds [V] of the symmetric GPIM that is ``gpim``'s loop with its descending envelope's shift beta0
        alone (no slope or curvature change): an operator's bounds ``v - r`` and ``v + beta0 + r`` are a play of
        threshold ``r + beta0 / 2`` on the input shifted by beta0 / 2, which only shifts its output (the GPIM's
        offset takes it).  A shift is therefore no asymmetry but the thresholds' placement.  An operator moved to
        zero or below is the zero-threshold one (its bounds cross: the input plus a constant); zero is always kept
        (a widening moves the first operator off it).  Sorted, distinct, (n',)."""
        moved = np.asarray(gpim.thresholds, float) + self.threshold_move(gpim)
        return np.concatenate(([0.0], np.unique(moved[moved > PLACED_THRESHOLD_FLOOR_V])))

    def threshold_move(self, gpim: GPIM) -> float:
        """How far [V, the thresholds' units] ``symmetric_thresholds`` moves each threshold: half the descending
        envelope's shift (beta0 is in input V, the thresholds in the envelope's: a0 beta0)."""
        return 0.5 * gpim.a0 * self.betas(gpim)[0]

    def shift_share(self, gpim: GPIM) -> float:
        """The shift's share of the descending envelope's departure from the ascending one over the range:
        ``|beta0| / (|beta0| + max |beta1 (v - v_c) + beta2 (v - v_c)^2 / h|)`` for v over the centre +- the half span
        (0 for a symmetric GPIM).  Where it is the larger part, the branches may not differ at all
        (``symmetric_thresholds``)."""
        beta0, beta1, beta2 = self.betas(gpim)
        d = np.array([-1.0, 1.0]) * self.half_span_v
        if beta2 != 0.0 and abs(beta1 * self.half_span_v / (2.0 * beta2)) < self.half_span_v:
            d = np.append(d, -beta1 * self.half_span_v / (2.0 * beta2))   # the parabola's vertex inside the range
        shape = float(np.max(np.abs(beta1 * d + beta2 * d * d / self.half_span_v)))
        return abs(beta0) / (abs(beta0) + shape) if beta0 else 0.0

    def with_betas(self, gpim: GPIM, beta0: float, beta1: float, beta2: float) -> GPIM:
        c, h, a0 = self.centre_v, self.half_span_v, gpim.a0
        b2 = a0 * beta2 / h
        b0 = a0 * (1.0 + beta1) - 2.0 * b2 * c
        b1 = gpim.a1 + a0 * (beta0 - beta1 * c) + b2 * c * c
        return GPIM(gpim.thresholds, gpim.weights, gpim.a0, gpim.a1, gpim.offset_um, float(b0), float(b1), float(b2))

    def switch_on(self, model):
        g = model.gpim
        return model if g.b0 is not None else replace(model, gpim=self.with_betas(g, 0.0, 0.0, 0.0))

    def carry(self, source, target):
        if source.term(self.name) is None:
            return target
        return replace(target, gpim=self.with_betas(target.gpim, *self.betas(source.gpim)))

    def sensitivities(self, ctx) -> np.ndarray:
        a0 = ctx.model.gpim.a0
        dv = ctx.v - self.centre_v
        return ctx.bound_sensitivity(None, a0 * np.column_stack((np.ones(dv.size), dv, dv * dv / self.half_span_v)))

    def step(self, model, delta):
        limits = (MAX_SHIFT_SHARE * self.half_span_v, MAX_SLOPE_CHANGE, MAX_SLOPE_CHANGE)
        beta0, beta1, beta2 = [float(np.clip(b + float(d), -lim, lim))
                               for b, d, lim in zip(self.betas(model.gpim), delta, limits)]
        return replace(model, gpim=self.with_betas(model.gpim, beta0, beta1, self.rising_curvature(beta1, beta2)))

    def rising_curvature(self, beta1: float, beta2: float) -> float:
        """``beta2`` limited so the descending envelope's slope, ``a0 (1 + beta1 + 2 beta2 (v - v_c) / h)``, stays
        at least MIN_SLOPE_SHARE of a0 for every v from 0 V (where the GPIM's ``b0`` is that slope) to the end of
        the range: a record that drove only part of 0..10 V has its centre far from 0 V, where an unlimited
        curvature would turn the envelope down."""
        c, h = self.centre_v, self.half_span_v
        for v in (min(0.0, c - h), c + h):
            s = 2.0 * (v - c) / h
            if 1.0 + beta1 + beta2 * s < MIN_SLOPE_SHARE:
                beta2 = (MIN_SLOPE_SHARE - 1.0 - beta1) / s
        return float(beta2)

    def describe(self, model, coefs) -> dict:
        g = model.gpim
        b0_, b1_, b2_ = self.betas(g)
        return {"descending_shift_v": b0_, "descending_slope_change": b1_, "descending_curvature": b2_,
                "b0": g.b0, "b1": g.b1, "b2": g.b2, "centre_v": self.centre_v, "half_span_v": self.half_span_v}

    def compensation(self, model, coefs) -> dict:
        """The controller inverts the asymmetric GPIM exactly when its descending envelope rises and stays at or
        above the ascending one over the drive range (``InverseGPIM``); otherwise NotCompensable with where not."""
        g = model.gpim
        if g.b0 is None:
            return {}
        envelope_problems = [x for x in inverse_problems(g) if "envelope" in x]
        if envelope_problems:
            raise NotCompensable(f"asymmetry: {'; '.join(envelope_problems)}")
        return {"gpim": g}

    def plot_axis(self, ctx):
        return ctx.v, "voltage [V]", False
