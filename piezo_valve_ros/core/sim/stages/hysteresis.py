"""The GPIM hysteresis of the input-equivalent voltage; asymmetry: a descending envelope of its own."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...model.hysteresis import GPIM
from .base import StageSwitch

ASYMMETRIC_ENVELOPE = (0.95, 0.2)   # (b0, b1) of the descending envelope when the asymmetry switch is on


class Hysteresis:
    """The GPIM [um] of the input-equivalent voltage (its operators' state carried)."""

    def __init__(self, model: GPIM, v0: float):
        self.stream = model.stream(v0=v0)

    def step(self, v: float, k: int) -> float:
        return self.stream.step(v)

    def run(self, v: np.ndarray, k0: int) -> np.ndarray:
        return self.stream.run(v)


SWITCH = StageSwitch("asymmetry", "asymmetry", lambda c: c.descending_envelope is not None,
                     lambda c, on: replace(c, descending_envelope=ASYMMETRIC_ENVELOPE if on else None))
