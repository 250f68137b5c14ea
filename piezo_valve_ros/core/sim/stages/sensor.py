"""The position sensor (LVDT): a transport delay, white noise and quantisation."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...validation import Settings, whole_periods
from .base import Link, StageParameters, StageSwitch, spec


NOISE_BLOCK = 4096  # noise is drawn in fixed blocks so step() and run() consume the RNG alike


@dataclass(frozen=True)
class SensorParams:
    """LVDT: white noise and quantisation; optionally a transport delay (a conditioning filter or a DAQ
    pipeline: the position read at sample k is the spool's at sample k - delay_samples)."""

    noise_enabled: bool = True
    noise_rms_um: float = 0.05
    quantisation_enabled: bool = True
    quantum_um: float = 0.005
    delay_samples: int = 0


class SensorDelay:
    """The position read at sample k is the spool's at sample k - delay_samples."""

    def __init__(self, delay_samples: int, y0: float):
        self.line = np.full(delay_samples, y0)  # the spool's last d positions, oldest first
        self.pos = 0

    def step(self, y: float, k: int) -> float:
        line, i = self.line, self.pos
        y, line[i] = float(line[i]), y
        self.pos = (i + 1) % line.size
        return y

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        n = y.size
        both = np.concatenate((np.roll(self.line, -self.pos), y))
        self.line, self.pos = both[n:].copy(), 0
        return both[:n]


class Sensor:
    """LVDT noise (drawn in fixed blocks, so step and run consume the generator alike) and quantisation."""

    def __init__(self, p: SensorParams, seed: int):
        self.p = p
        self.rng = np.random.default_rng(seed)
        self.noise = np.empty(0)
        self.pos = 0

    def step(self, y: float, k: int) -> float:
        p = self.p
        if p.noise_enabled:
            if self.pos >= self.noise.size:
                self.noise, self.pos = self.rng.standard_normal(NOISE_BLOCK), 0
            y += p.noise_rms_um * float(self.noise[self.pos])
            self.pos += 1
        if p.quantisation_enabled:
            y = p.quantum_um * round(y / p.quantum_um)
        return y

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        p = self.p
        if p.noise_enabled:
            y = y + p.noise_rms_um * self._take(y.size)
        if p.quantisation_enabled:
            y = p.quantum_um * np.round(y / p.quantum_um)
        return y

    def _take(self, n: int) -> np.ndarray:
        parts, need = [], n
        while need > 0:
            if self.pos >= self.noise.size:
                self.noise, self.pos = self.rng.standard_normal(NOISE_BLOCK), 0
            take = min(need, self.noise.size - self.pos)
            parts.append(self.noise[self.pos:self.pos + take])
            self.pos += take
            need -= take
        return np.concatenate(parts)


SWITCH = StageSwitch("noise", "LVDT noise", lambda c: c.sensor.noise_enabled,
                     lambda c, on: replace(c, sensor=replace(c.sensor, noise_enabled=on)))


def _build_delay(config, y0: float):
    d = int(config.sensor.delay_samples)
    if d < 0:
        raise ValueError(f"sensor delay_samples must be >= 0, got {d}")
    return (SensorDelay(d, y0) if d else None), y0


def _build(config, y0: float):
    return Sensor(config.sensor, config.seed), y0


DELAY_LINK = Link("sensor_delay", _build_delay)
LINK = Link("sensor", _build)


MAX_SENSOR_DELAY_S = 0.1   # [s]


@dataclass(frozen=True)
class SensorSettings(Settings):
    sensor_delay_s: float   # [s], whole sample periods

    def apply(self, config, sample_period_s: float):
        delay = whole_periods(self.sensor_delay_s, sample_period_s)
        if delay is None:
            raise ValueError(f"sim.sensor_delay_s must be a whole number of sample periods ({sample_period_s} s), "
                             f"got {self.sensor_delay_s}")
        return replace(config, sensor=replace(config.sensor, delay_samples=int(delay)))


PARAMETERS = StageParameters(
    (spec("sensor_delay_s", 0.0, "LVDT transport delay [s] (whole samples; e.g. a conditioning filter)", low=0.0,
          high=MAX_SENSOR_DELAY_S),),
    SensorSettings)
