"""Saturation: the loop ends flattened by friction or an end stop, on one side or both.

Terms: a static map of the model output that bends its ends, the same on both branches: the square
and the cube of the output normalised to [-1, 1] over the training range (a compression off the centre
or of both ends) and squared hinges ``max(+-h - k, 0)^2`` at knots k = 0.4, 0.6, 0.8 on each side (one
end or both, soft or sharp stops).  All of it is flat at the centre of the range (no slope there, which
the GPIM owns): a dead zone there is not saturation.
A GPIM with nonnegative weights cannot flatten its own loop ends (its branches steepen away from a
reversal), so this is structure the baseline cannot take.

Compensation: the map ``S = H + terms(H) @ c`` is static, so the controller inverts it exactly where it
rises (:class:`OutputMap`, checked over the drive's output range with a margin) and composes that with the
inverse GPIM.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ...model.output_map import KNOTS, OutputMap, term_rows, terms
from ..records import Record
from .base import Effect, NotCompensable, normalised

__all__ = ["Saturation"]

@dataclass(frozen=True)
class Saturation(Effect):
    name = "saturation"
    simulated_by = ("saturation",)
    compensated_by = ("output_map",)
    telling_experiment = ("slow sweeps to each end of the range and back: the flattening grows towards the ends, the "
                          "same on both branches and at every rate")
    signature = ("loop ends flattened: the residual is a static function of the model output bending the ends of "
                 "its range (square, cube and end hinges)")
    centre_um: float = 0.0
    half_range_um: float = 1.0

    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> Optional["Saturation"]:
        lo, hi = float(np.min(H)), float(np.max(H))
        return cls(0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9))

    def columns(self, ctx) -> np.ndarray:
        return terms(normalised(ctx.H, self.centre_um, self.half_range_um))

    def design_rows(self, ctx) -> np.ndarray:
        return term_rows(normalised(ctx.H, self.centre_um, self.half_range_um))

    def describe(self, model, coefs) -> dict:
        return {"terms": ["h^2", "h^3"] + [f"max({s}h-{k},0)^2" for s in ("+", "-") for k in KNOTS],
                "coefficients_um": [float(c) for c in coefs], "centre_um": self.centre_um,
                "half_range_um": self.half_range_um}

    def output_map(self, coefs) -> OutputMap:
        return OutputMap(self.centre_um, self.half_range_um, tuple(float(c) for c in coefs))

    def compensation(self, model, coefs) -> dict:
        """The controller inverts the static map where it rises over the model's output range
        (:class:`OutputMap`); NotCompensable says where it does not."""
        lo, hi = model.gpim.output_range()
        out_map = self.output_map(coefs)
        problems = out_map.problems(lo, hi)
        if problems:
            raise NotCompensable("; ".join(problems))
        return {"output_map": out_map}
