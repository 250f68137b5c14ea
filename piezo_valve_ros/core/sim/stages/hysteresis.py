"""The GPIM hysteresis of the input-equivalent voltage; asymmetry: a descending envelope of its own."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ...model.hysteresis import GPIM, GPIM_PARAMS_KEYS, PAPER_GPIM
from ...validation import Settings, from_parameter
from .base import Link, StageParameters, StageSwitch, spec

ASYMMETRIC_ENVELOPE = (0.95, 0.2)   # (b0, b1) of the descending envelope when the asymmetry switch is on


class Hysteresis:
    """The GPIM [um] of the input-equivalent voltage (its operators' state carried).

    A play operator fed the input it had at the sample before stays where it is, so ``step`` at an unchanged
    input returns the last output as it is (bit for bit what the bank gives): a rig samples several times per
    control period at one command, and outside a slew the bender sees that one voltage."""

    def __init__(self, model: GPIM, v0: float):
        self.stream = model.stream(v0=v0)
        self._last_v, self._last_y = math.nan, math.nan   # the last sample's input [V] and output [um]

    def step(self, v: float, k: int) -> float:
        if v == self._last_v:   # never true after a run or at the start (NaN)
            return self._last_y
        self._last_y = self.stream.step(v)
        self._last_v = v
        return self._last_y

    def run(self, v: np.ndarray, k0: int) -> np.ndarray:
        self._last_v = math.nan   # the next step computes its output as a step does
        return self.stream.run(v)


SWITCH = StageSwitch("asymmetry", "asymmetry", lambda c: c.descending_envelope is not None,
                     lambda c, on: replace(c, descending_envelope=ASYMMETRIC_ENVELOPE if on else None))


def _build(config, v0: float):
    stage = Hysteresis(config.hysteresis_model(), v0)
    return stage, stage.stream.model.output_from_state(stage.stream.state)


LINK = Link("hysteresis", _build)


@dataclass(frozen=True)
class HysteresisSettings(Settings):
    a0: float = from_parameter("gpim.a0")
    a1: float = from_parameter("gpim.a1")
    alpha: float = from_parameter("gpim.alpha")
    rho: float = from_parameter("gpim.rho")
    tau: float = from_parameter("gpim.tau")
    n: int = from_parameter("gpim.n")
    offset_um: float = from_parameter("gpim.offset_um")

    def apply(self, config, sample_period_s: float):
        gpim = replace(config.gpim, **{k: getattr(self, k) for k in GPIM_PARAMS_KEYS})
        try:
            gpim.model()
        except ValueError as exc:
            raise ValueError(f"sim.gpim: {exc}") from None
        return replace(config, gpim=gpim)


PARAMETERS = StageParameters(tuple(spec(f"gpim.{k}", getattr(PAPER_GPIM, k), "the valve's own GPIM (paper units)")
                                   for k in GPIM_PARAMS_KEYS), HysteresisSettings)
