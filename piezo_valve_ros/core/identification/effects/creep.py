"""Creep: the slow approach of the output after a step or reversal, log-like in time.

Terms ``lag_tau[H] - H`` for time constants a factor 3 apart from 0.05 s to 50 s (as many as the
record can show): a sum of first-order elements with log-spaced time constants is the usual linear
model of a logarithmic creep, and it is exactly invertible in the controller's feedforward path.
Real creep also depends on the direction of the move and on the operating point, so for time
constants up to ``SHAPED_UP_TO_S`` the terms come again split by direction (rising minus falling
changes of the slow motion, H through the fastest creep lag: creep does not follow fast cycling) and
times the normalised output.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ...control.terms.creep import CreepModel
from ...model.dynamics import lag_poles
from ...model.iir import creep_lag_rows
from ..records import Record
from .base import Effect

__all__ = ["Creep", "CREEP_TIME_CONSTANTS_S", "SHAPED_UP_TO_S"]

CREEP_TIME_CONSTANTS_S = (0.05, 0.15, 0.5, 1.5, 5.0, 15.0, 50.0)
SHAPED_UP_TO_S = 15.0   # direction- and level-dependent terms for time constants up to this [s]


@dataclass(frozen=True)
class Creep(Effect):
    name = "creep"
    simulated_by = ("creep",)
    compensated_by = ("creep",)
    telling_experiment = ("holds of several seconds after steps of different sizes in both directions: creep keeps "
                          "moving towards the step, by a share of its size, slower and slower")
    signature = ("slow approach after steps and reversals: the residual follows slow lags (0.05-50 s) of the "
                 "model output, possibly different for rising and falling moves and with the level")
    time_constants_s: tuple[float, ...] = CREEP_TIME_CONSTANTS_S
    centre_um: float = 0.0
    half_range_um: float = 1.0

    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> Optional["Creep"]:
        dur = train.duration_s
        taus = tuple(t for t in CREEP_TIME_CONSTANTS_S if 3 * train.dt <= t <= dur / 2)
        lo, hi = float(np.min(H)), float(np.max(H))
        return cls(taus, 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9)) if taus else None

    @property
    def shaped(self) -> tuple[float, ...]:
        return tuple(t for t in self.time_constants_s if t <= SHAPED_UP_TO_S)

    def design_rows(self, ctx) -> np.ndarray:
        """The terms as rows (k, N): plain, then rising minus falling, then times the level (``columns``); in one
        pass over the record (``iir.creep_lag_rows``).  Creep follows the slow motion, not fast cycling: the
        direction terms take the changes of H through the fastest lag."""
        return creep_lag_rows(ctx.H, ctx.H_before, lag_poles(self.time_constants_s, ctx.dt), len(self.shaped),
                              self.centre_um, self.half_range_um)

    def columns(self, ctx) -> np.ndarray:
        return self.design_rows(ctx).T

    def rest_columns(self, ctx, columns) -> np.ndarray:
        """Every term is a lag of H minus H (or that times the level): zero once the valve has rested."""
        return np.zeros(columns.shape[1])

    def describe(self, model, coefs) -> dict:
        n, k = len(self.time_constants_s), len(self.shaped)
        return {"time_constants_s": list(self.time_constants_s), "gains": [float(c) for c in coefs[:n]],
                "direction_time_constants_s": list(self.shaped),
                "rising_minus_falling_gains": [float(c) for c in coefs[n:n + k]],
                "level_gains": [float(c) for c in coefs[n + k:n + 2 * k]]}

    def plot_axis(self, ctx):
        t, v = ctx.record.time_s, ctx.v
        moving = np.flatnonzero(np.abs(np.diff(v)) > 1e-9 * (1 + np.abs(v[1:])))
        last = np.full(t.size, t[0])
        if moving.size:
            idx = np.searchsorted(moving + 1, np.arange(t.size), side="right") - 1
            ok = idx >= 0
            last[ok] = t[moving[idx[ok]] + 1]
        return np.maximum(t - last, 1e-4), "time since the input last moved [s]", True

    def compensation(self, model, coefs) -> dict:
        """The controller's creep compensator inverts the plain terms (its exact inverse); the direction- and
        level-dependent parts are left to the feedback."""
        return {"creep": CreepModel(tuple(float(x) for x in self.time_constants_s),
                                    tuple(float(c) for c in coefs[:len(self.time_constants_s)]))}
