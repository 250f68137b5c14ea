"""Creep: slow first-order elements of unity DC gain after the hysteresis."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...model.dynamics import first_order_lag
from .base import Link, StageSwitch


@dataclass(frozen=True)
class CreepParams:
    """Creep: y += sum_i c_i (lag_{tau_i}(y) - y); log-like in time for log-spaced tau_i."""

    enabled: bool = True
    gains: tuple[float, ...] = (0.015, 0.015, 0.015, 0.015)
    time_constants_s: tuple[float, ...] = (0.03, 0.3, 3.0, 30.0)


class Creep:
    """y + sum g_i (lag_i[y] - y): slow first-order elements, unity DC gain."""

    def __init__(self, p: CreepParams, dt: float, y0: float):
        self.gains = p.gains
        self.lags = [first_order_lag(tau, dt) for tau in p.time_constants_s]
        for f in self.lags:
            f.reset(y0)

    def step(self, y: float, k: int) -> float:
        y_h = y
        for gain, f in zip(self.gains, self.lags):
            y += gain * (f.step(y_h) - y_h)
        return y

    def run(self, y_h: np.ndarray, k0: int) -> np.ndarray:
        y = y_h.copy()
        for gain, f in zip(self.gains, self.lags):
            y += gain * (f.run(y_h) - y_h)
        return y


SWITCH = StageSwitch("creep", "creep", lambda c: c.creep.enabled,
                     lambda c, on: replace(c, creep=replace(c.creep, enabled=on)))


def _build(config, y0: float):
    return (Creep(config.creep, config.dt, y0) if config.creep.enabled else None), y0


LINK = Link("creep", _build)
