"""Rate dependence: part of the output through a fast lag (a loop that widens with the input rate)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...model.dynamics import first_order_lag
from .base import Link, StageSwitch


@dataclass(frozen=True)
class RateDependenceParams:
    """Rate dependence: a share of the output follows a fast lag (loop widens with frequency)."""

    enabled: bool = False
    share: float = 0.15
    time_constant_s: float = 0.02


class RateDependence:
    """Part of the output through a fast lag: a loop that widens with the input rate."""

    def __init__(self, p: RateDependenceParams, dt: float, y0: float):
        self.share = p.share
        self.lag = first_order_lag(p.time_constant_s, dt)
        self.lag.reset(y0)

    def step(self, y: float, k: int) -> float:
        return y + self.share * (self.lag.step(y) - y)

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        return y + self.share * (self.lag.run(y) - y)


SWITCH = StageSwitch("rate_dependence", "rate dependence", lambda c: c.rate.enabled,
                     lambda c, on: replace(c, rate=replace(c.rate, enabled=on)))


def _build(config, y0: float):
    return (RateDependence(config.rate, config.dt, y0) if config.rate.enabled else None), y0


LINK = Link("rate_dependence", _build)
