"""Loop-end flattening by friction or an end stop."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .base import Link, StageSwitch


@dataclass(frozen=True)
class SaturationParams:
    """Loop-end flattening by friction / end stop: y -> centre + s * tanh((y - centre)/s)."""

    enabled: bool = True
    scale_um: float = 400.0
    centre_um: float = 0.0


class Saturation:
    """Loop-end flattening s tanh((y - c) / s) + c."""

    def __init__(self, p: SaturationParams):
        self.p = p

    def step(self, y: float, k: int) -> float:
        p = self.p
        return p.centre_um + p.scale_um * math.tanh((y - p.centre_um) / p.scale_um)

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        p = self.p
        return p.centre_um + p.scale_um * np.tanh((y - p.centre_um) / p.scale_um)


SWITCH = StageSwitch("saturation", "loop-end flattening", lambda c: c.saturation.enabled,
                     lambda c, on: replace(c, saturation=replace(c.saturation, enabled=on)))


def _build(config, y0: float):
    if not config.saturation.enabled:
        return None, y0
    stage = Saturation(config.saturation)
    return stage, stage.step(y0, 0)


LINK = Link("saturation", _build)
