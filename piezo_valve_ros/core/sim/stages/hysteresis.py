"""The GPIM hysteresis of the input-equivalent voltage; asymmetry: a descending envelope of its own."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...model.hysteresis import GPIM
from .base import StageSwitch

ASYMMETRIC_ENVELOPE = (0.95, 0.2)   # (b0, b1) of the descending envelope when the asymmetry switch is on


class Hysteresis:
    """The GPIM [um] of the input-equivalent voltage (its operators' state carried).

    A play operator fed the input it had at the sample before stays where it is, so ``step`` at an unchanged
    input returns the last output as it is (bit for bit what the bank gives): a rig samples several times per
    control period at one command, and outside a slew the bender sees that one voltage."""

    def __init__(self, model: GPIM, v0: float):
        self.stream = model.stream(v0=v0)
        self._last: tuple[float, float] | None = None   # (input [V], output [um]) of the last sample

    def step(self, v: float, k: int) -> float:
        last = self._last
        if last is not None and last[0] == v:
            return last[1]
        y = self.stream.step(v)
        self._last = (v, y)
        return y

    def run(self, v: np.ndarray, k0: int) -> np.ndarray:
        self._last = None   # the next step computes its output as a step does
        return self.stream.run(v)


SWITCH = StageSwitch("asymmetry", "asymmetry", lambda c: c.descending_envelope is not None,
                     lambda c, on: replace(c, descending_envelope=ASYMMETRIC_ENVELOPE if on else None))
