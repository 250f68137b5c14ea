"""Backlash: a clearance on the spool's path after G_v (a play)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ...model.hysteresis import PlayOperatorBank
from ...validation import Settings
from .base import Link, StageParameters, StageSwitch, spec


@dataclass(frozen=True)
class BacklashParams:
    """Backlash on the spool's path: a clearance of ``width_um`` either side [um] (a play of that half-width) between
    the actuator and the spool."""

    enabled: bool = False
    width_um: float = 0.5


class Backlash:
    """A play of half-width ``width_um`` [um]: the spool moves once the actuator has taken up the clearance."""

    def __init__(self, p: BacklashParams, y0: float):
        if not (p.width_um >= 0 and math.isfinite(p.width_um)):
            raise ValueError(f"backlash width_um must be a finite width >= 0, got {p.width_um}")
        self.play = PlayOperatorBank([p.width_um], [y0])

    def step(self, x: float, k: int) -> float:
        return float(self.play.step(x, x)[0])

    def run(self, x: np.ndarray, k0: int) -> np.ndarray:
        return self.play.run(x, x)[:, 0]


SWITCH = StageSwitch("backlash", "backlash on the spool's path", lambda c: c.backlash.enabled,
                     lambda c, on: replace(c, backlash=replace(c.backlash, enabled=on)))


def _build(config, y0: float):
    return (Backlash(config.backlash, y0) if config.backlash.enabled else None), y0


LINK = Link("backlash", _build)


@dataclass(frozen=True)
class BacklashSettings(Settings):
    backlash_width_um: float   # [um]

    def apply(self, config, sample_period_s: float):
        return replace(config, backlash=replace(config.backlash, width_um=self.backlash_width_um))


PARAMETERS = StageParameters(
    (spec("backlash_width_um", BacklashParams().width_um, "backlash: clearance either side of the spool [um] (a play "
                                                          "of this half-width)", low=0.0),),
    BacklashSettings)
