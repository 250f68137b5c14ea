"""G_v(s), the valve's linear dynamics, exact zero-order hold."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...model.dynamics import ContinuousTF
from .base import Link, StageSwitch


class Dynamics:
    """G_v(s), exact ZOH."""

    def __init__(self, tf: ContinuousTF, dt: float, y0: float):
        self.filter = tf.discretise(dt)
        self.filter.reset(y0)

    def step(self, y: float, k: int) -> float:
        return self.filter.step(y)

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        return self.filter.run(y)


SWITCH = StageSwitch("dynamics", "G_v(s)", lambda c: c.dynamics_enabled,
                     lambda c, on: replace(c, dynamics_enabled=on))


def _build(config, y0: float):
    return (Dynamics(config.valve_model, config.dt, y0) if config.dynamics_enabled else None), y0


LINK = Link("dynamics", _build)
