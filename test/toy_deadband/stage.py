"""The dead band's stage of the simulated valve: the spool rests at ``centre_um`` while G's output stays within
``width_um`` of it, and follows it offset by the width outside (a detent at the spool's centre)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from piezo_valve_ros.core.sim.stages import Link, StageSwitch

NAME = "deadband"


@dataclass(frozen=True)
class DeadBandParams:
    enabled: bool = True
    centre_um: float = 0.0
    width_um: float = 1.0     # half-width [um]


class DeadBand:
    def __init__(self, p: DeadBandParams):
        self.centre, self.width = float(p.centre_um), float(p.width_um)

    def step(self, x: float, k: int) -> float:
        d = x - self.centre
        return self.centre + (d - self.width if d > self.width else d + self.width if d < -self.width else 0.0)

    def run(self, x: np.ndarray, k0: int) -> np.ndarray:
        d = x - self.centre
        return self.centre + np.sign(d) * np.maximum(np.abs(d) - self.width, 0.0)


def _build(config, x0: float):
    params = config.added_params(NAME)
    if params is None or not params.enabled:
        return None, x0
    stage = DeadBand(params)
    return stage, stage.step(x0, 0)


def _set(config, on: bool):
    params = replace(config.added_params(NAME, DeadBandParams()), enabled=on)
    return replace(config, added=tuple((n, p) for n, p in config.added if n != NAME) + ((NAME, params),))


LINK = Link(NAME, _build)
SWITCH = StageSwitch(NAME, "a dead band at the spool's centre", lambda c: bool(getattr(c.added_params(NAME), "enabled",
                                                                                          False)), _set)
