"""Thermal drift: offset and gain approaching new values exponentially in time."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .base import Link, StageSwitch


@dataclass(frozen=True)
class DriftParams:
    """Thermal drift: offset and gain approach new values exponentially with the time since ``start_s`` [s]
    (before it: none; a drift that sets in during operation)."""

    enabled: bool = False
    offset_um: float = 4.0
    gain_change: float = 0.03
    time_constant_s: float = 20.0
    start_s: float = 0.0


class Drift:
    """Offset and gain approaching new values exponentially from ``start_s`` (time = sample index x dt)."""

    def __init__(self, p: DriftParams, dt: float):
        self.p, self.dt = p, dt

    def step(self, y: float, k: int) -> float:
        p, t = self.p, k * self.dt
        if t <= p.start_s:
            return y
        w = 1.0 - math.exp(-(t - p.start_s) / p.time_constant_s)
        return y * (1.0 + p.gain_change * w) + p.offset_um * w

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        p = self.p
        t = (k0 + np.arange(y.size)) * self.dt
        w = 1.0 - np.exp(-np.maximum(t - p.start_s, 0.0) / p.time_constant_s)
        return y * (1.0 + p.gain_change * w) + p.offset_um * w


SWITCH = StageSwitch("drift", "thermal drift", lambda c: c.drift.enabled,
                     lambda c, on: replace(c, drift=replace(c.drift, enabled=on)))


def _build(config, y0: float):
    return (Drift(config.drift, config.dt) if config.drift.enabled else None), y0


LINK = Link("drift", _build)
