"""Saturation: the loop ends flattened by friction or an end stop, on one side or both.

Terms: a static map of the model output that bends its ends, the same on both branches: the square
and the cube of the output normalised to [-1, 1] over the training range (a compression off the centre
or of both ends) and squared hinges ``max(+-h - k, 0)^2`` at knots k = 0.4, 0.6, 0.8 on each side (one
end or both, soft or sharp stops).  All of it is flat at the centre of the range (no slope there, which
the GPIM owns): a dead zone there is not saturation.
A GPIM with nonnegative weights cannot flatten its own loop ends (its branches steepen away from a
reversal), so this is structure the baseline cannot take.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..records import Record
from .base import Effect, normalised

__all__ = ["Saturation", "KNOTS"]

KNOTS = (0.4, 0.6, 0.8)


@dataclass(frozen=True)
class Saturation(Effect):
    name = "saturation"
    signature = ("loop ends flattened: the residual is a static function of the model output bending the ends of "
                 "its range (square, cube and end hinges)")
    centre_um: float = 0.0
    half_range_um: float = 1.0

    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> Optional["Saturation"]:
        lo, hi = float(np.min(H)), float(np.max(H))
        return cls(0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9))

    def columns(self, ctx) -> np.ndarray:
        h = normalised(ctx.H, self.centre_um, self.half_range_um)
        return np.column_stack([h ** 2, h ** 3] + [np.maximum(s * h - k, 0.0) ** 2 for s in (1.0, -1.0) for k in KNOTS])

    def describe(self, model, coefs) -> dict:
        return {"terms": ["h^2", "h^3"] + [f"max({s}h-{k},0)^2" for s in ("+", "-") for k in KNOTS],
                "coefficients_um": [float(c) for c in coefs], "centre_um": self.centre_um,
                "half_range_um": self.half_range_um}
