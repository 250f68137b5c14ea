"""The dead band as the identification sees it: an output map of G's output, the position ``x - w sign(x - c)``
outside the band (linear in the half-width w) and ``c`` within it, with ``c`` the middle of
the training output's range."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from piezo_valve_ros.core.identification.effects import Effect

from .term import DeadBandModel


@dataclass(frozen=True)
class DeadBand(Effect):
    name = "deadband"
    simulated_by = ("deadband",)
    compensated_by = ("deadband",)
    signature = "the position stops at the spool's centre while the drive crosses it"
    telling_experiment = "slow crossings of the centre position"
    after_dynamics = 1
    coefficient_floor = 0.0
    centre_um: float = 0.0

    @classmethod
    def prepare(cls, train, H) -> "DeadBand":
        return cls(0.5 * (float(np.min(H)) + float(np.max(H))))

    @staticmethod
    def width_um(coefs) -> float:
        return float(coefs[0]) if np.size(coefs) else 0.0

    def output(self, x, coefs) -> np.ndarray:
        d = x - self.centre_um
        return self.centre_um + np.sign(d) * np.maximum(np.abs(d) - self.width_um(coefs), 0.0)

    def output_linear(self, x, coefs):
        """Outside the band ``x - w sign(x - c)``; within it the position is c, ``x - w (x - c) / w`` at the width
        the structure has (exact there, as an output map's form is for the structure it is taken at)."""
        d, w = x - self.centre_um, self.width_um(coefs)
        inside = np.abs(d) <= w
        column = -np.sign(d)
        if w > 0.0:
            column[inside] = -d[inside] / w
        return np.arange(x.size), column[:, None]

    def output_search_columns(self, x) -> np.ndarray:
        """The search's column, every row: the dead band's first order at w = 0."""
        return -np.sign(x - self.centre_um)[:, None]

    def describe(self, model, coefs) -> dict:
        return {"width_um": self.width_um(coefs), "centre_um": self.centre_um}

    def compensation(self, model, coefs) -> dict:
        return {"deadband": DeadBandModel(self.width_um(coefs), self.centre_um)}
