"""Backlash: play on the spool's path after the actuator (a clearance in the linkage, a dead zone the spool
crosses at every reversal).

Structure: one play operator of half-width ``r`` [um] on G's output x: the spool follows x once x has moved
``r`` past it, and holds while x crosses the clearance after a reversal.  The hold lasts as long as the input
takes to travel 2r, whatever the rate or amplitude: a lag's delay grows with the rate, a hysteresis operator's
hold is a voltage, not a position.  For a given pattern of contacts the position is ``x[last contact] + side * r``,
linear in the weights (through x) and in r, so a fit solves r with the weights and takes the contacts again
from the result until both settle.  (A play on the drive before the hysteresis needs nothing: a play before a
PI model is a PI model with every threshold larger.)

Compensation: the controller adds ``r`` in the direction the reference last moved (the play's right inverse),
before the inverse hysteresis.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...control.terms.backlash import BacklashModel
from ...model.hysteresis import output_play
from .base import Effect

__all__ = ["Backlash", "SEARCH_WIDTHS"]

SEARCH_WIDTHS = (0.002, 0.005, 0.01, 0.02, 0.04)   # the search's play half-widths, as shares of G's output span


@dataclass(frozen=True)
class Backlash(Effect):
    name = "backlash"
    simulated_by = ("backlash",)
    compensated_by = ("backlash",)
    telling_experiment = ("small reversals at two rates: after each reversal the position holds while the drive "
                          "moves the same distance at any rate (a lag's hold grows with the rate)")
    signature = ("a flat step after every reversal: the position holds while the drive crosses a fixed clearance, "
                 "then follows it offset by that clearance")
    after_dynamics = 1
    coefficient_floor = 0.0
    span_um: float = 1.0     # the training record's output span [um]: the search's widths are shares of it

    @classmethod
    def prepare(cls, train, H) -> "Backlash":
        return cls(max(float(np.ptp(H)), 1e-9))

    def output(self, x, coefs) -> np.ndarray:
        return output_play(x, self.width_um(coefs), compiled=True)[0]

    def output_linear(self, x, coefs) -> tuple[np.ndarray, np.ndarray]:
        _, index, side = output_play(x, self.width_um(coefs), compiled=True)
        return index, side[:, None]

    def frees_poles(self, coefs) -> bool:
        """A clearance of at least the search's narrowest width: G_v's poles are refitted with it (its holds made the
        baseline's G look slow); a narrower one is not a clearance, and freed poles would take other structure."""
        return self.width_um(coefs) >= SEARCH_WIDTHS[0] * self.span_um

    def output_search_columns(self, x) -> np.ndarray:
        """The holds of plays of ``SEARCH_WIDTHS`` shares of the training output's span: ``play(x, r_k) - x`` (the
        first-order column at r = 0, the direction of motion, has no hold in it, which is most of what a clearance
        leaves)."""
        return np.column_stack([output_play(x, share * self.span_um, compiled=True)[0] - x for share in SEARCH_WIDTHS])

    @staticmethod
    def width_um(coefs) -> float:
        """The play's half-width [um] (0 before a fit)."""
        return float(coefs[0]) if np.size(coefs) else 0.0

    def describe(self, model, coefs) -> dict:
        return {"width_um": self.width_um(coefs)}

    def plot_axis(self, ctx):
        return np.gradient(ctx.H, ctx.dt), "model output rate [um/s]", False

    def compensation(self, model, coefs) -> dict:
        return {"backlash": BacklashModel(self.width_um(coefs))}
