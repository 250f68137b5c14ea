"""Thermal drift: offset and gain approaching new values exponentially in time."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ...validation import Settings
from .base import Link, StageParameters, StageSwitch, spec


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


@dataclass(frozen=True)
class DriftSettings(Settings):
    drift_offset_um: float         # [um]
    drift_gain_change: float       # [-]
    drift_time_constant_s: float   # [s]
    drift_start_s: float           # [s]

    def problems(self) -> list[str]:
        return [] if self.drift_time_constant_s > 0 else [
            f"sim.drift_time_constant_s must be > 0, got {self.drift_time_constant_s}"]

    def apply(self, config, sample_period_s: float):
        return replace(config, drift=replace(config.drift, offset_um=self.drift_offset_um,
                                             gain_change=self.drift_gain_change,
                                             time_constant_s=self.drift_time_constant_s, start_s=self.drift_start_s))


PARAMETERS = StageParameters(
    (spec("drift_offset_um", DriftParams().offset_um, "thermal drift: offset it approaches [um]"),
     spec("drift_gain_change", DriftParams().gain_change, "thermal drift: gain change it approaches [-]"),
     spec("drift_time_constant_s", DriftParams().time_constant_s, "thermal drift: time constant [s]"),
     spec("drift_start_s", 0.0, "thermal drift: sets in this long after the backend opens [s] (a drift that appears "
                                "during operation)", low=0.0)),
    DriftSettings)
