"""Simulated piezo valve: the paper's valve with the effects a real one has.

Signal chain (each stage has its own switch and parameters)::

    v_cmd [V, 0..10] -> amplifier (x20 - 100 V, slew limit I_max/C) -> v_eff [V input-equivalent]
      -> GPIM hysteresis [um] (asymmetry: separate descending envelope)
      -> creep (sum of slow first-order elements, unity DC gain)
      -> rate dependence (part of the output through a fast lag)
      -> loop-end flattening (friction/end stop, s*tanh(y/s))
      -> G_v(s) (exact ZOH)  -> backlash (a play on the spool's path)
      -> thermal drift (offset and gain, exponential in time)
      -> LVDT noise and quantisation -> position [m]

Each stage is a small class with ``step`` (per sample) and ``run`` (a whole record, vectorised) on one
state, in its own module under ``stages/`` with its parameters, its link and its switch; ``SimulatedValve`` folds the
chain of links (``stages.CHAIN``) over its config, keeping the stages that are switched on, so ``step`` and ``run`` go
through the same chain and give the same result, and a run repeats bit for bit from ``seed``.  Default effects: slew limit, creep, flattening,
noise, quantisation.  Off by default (for identification work): asymmetry, rate
dependence, backlash, drift.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Optional

import numpy as np

from ..model.dynamics import PAPER_VALVE_MODEL, ContinuousTF
from ..model.hysteresis import GPIM, GPIMParams, PAPER_GPIM
from ..model.drive import CENTRE_VOLTAGE_V
from . import stages as _stages
from .stages import CHAIN, STAGE_SWITCHES, StageSwitch
from .stages.amplifier import Amplifier, AmplifierParams
from .stages.backlash import BacklashParams
from .stages.creep import CreepParams
from .stages.drift import DriftParams
from .stages.hysteresis import ASYMMETRIC_ENVELOPE, Hysteresis
from .stages.rate_dependence import RateDependenceParams
from .stages.saturation import SaturationParams
from .stages.sensor import SensorParams

__all__ = [
    "AmplifierParams",
    "CreepParams",
    "RateDependenceParams",
    "SaturationParams",
    "DriftParams",
    "BacklashParams",
    "SensorParams",
    "ValveSimConfig",
    "StageSwitch",
    "STAGE_SWITCHES",
    "CHAIN",
    "ASYMMETRIC_ENVELOPE",
    "SimulatedValve",
]


@dataclass(frozen=True)
class ValveSimConfig:
    """Everything that defines a simulated valve.  ``dt`` [s] is the sampling period."""

    dt: float = 1e-4
    seed: int = 0
    gpim: GPIMParams = PAPER_GPIM
    descending_envelope: Optional[tuple[float, float]] = None  # (b0, b1): asymmetry effect
    valve_model: ContinuousTF = PAPER_VALVE_MODEL
    dynamics_enabled: bool = True
    amplifier: AmplifierParams = AmplifierParams()
    creep: CreepParams = CreepParams()
    rate: RateDependenceParams = RateDependenceParams()
    saturation: SaturationParams = SaturationParams()
    drift: DriftParams = DriftParams()
    backlash: BacklashParams = BacklashParams()
    sensor: SensorParams = SensorParams()
    initial_voltage_v: float = CENTRE_VOLTAGE_V
    added: tuple[tuple[str, Any], ...] = ()   # (link name, parameters) of stages added to the chain beyond these

    def added_params(self, name: str, default: Any = None) -> Any:
        """The parameters of the added stage ``name`` (``added``), or ``default`` where the config has none."""
        return next((params for link, params in self.added if link == name), default)

    def ideal(self) -> "ValveSimConfig":
        """Only hysteresis (and G_v if enabled): no creep, flattening, noise, slew, drift."""
        return replace(self, amplifier=replace(self.amplifier, enabled=False),
                       creep=replace(self.creep, enabled=False),
                       rate=replace(self.rate, enabled=False),
                       saturation=replace(self.saturation, enabled=False),
                       drift=replace(self.drift, enabled=False),
                       backlash=replace(self.backlash, enabled=False),
                       sensor=SensorParams(noise_enabled=False, quantisation_enabled=False),
                       descending_envelope=None)

    def hysteresis_model(self) -> GPIM:
        m = self.gpim.model()
        if self.descending_envelope is not None:
            b0, b1 = self.descending_envelope
            m = GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, float(b0), float(b1))
        return m


class _Spool:
    """Not a filter: remembers the spool's true position [um], before the sensor."""

    def __init__(self, y0: float):
        self.y_um = y0

    def step(self, y: float, k: int) -> float:
        self.y_um = y
        return y

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        self.y_um = float(y[-1])
        return y


class SimulatedValve:
    """The valve as a sampled system: ``step(v) -> position [m]`` once per ``dt``, or ``run(v)`` over a whole
    record.  Both go through one chain of stages (the module docstring's), each with its ``step`` and ``run``
    on one state; a stage that is switched off is not in the chain."""

    def __init__(self, config: ValveSimConfig = ValveSimConfig()):
        if not (config.dt > 0 and math.isfinite(config.dt)):
            raise ValueError(f"dt must be a positive finite time, got {config.dt}")
        self.config = config
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Every stage at rest at the config's initial voltage: the chain (``stages.CHAIN``, then the spool, then
        ``stages.SENSING``) folded over the config, each link building its stage (none where it is switched off)
        at rest at the value the stages before it pass on."""
        c = self.config
        self.time_s = 0.0
        self.sample_index = 0
        x = float(np.clip(c.initial_voltage_v, c.amplifier.input_min_v, c.amplifier.input_max_v))
        stages = []
        for link in _stages.CHAIN:   # (read here: a chain extended after import is folded too)
            stage, x = link.build(c, x)
            stages.append(stage)
        self._spool = _Spool(x)
        stages.append(self._spool)
        for link in _stages.SENSING:
            stage, x = link.build(c, x)
            stages.append(stage)
        self._stages = [st for st in stages if st is not None]
        self._amplifier = next(st for st in self._stages if isinstance(st, Amplifier))
        self._hysteresis = next(st for st in self._stages if isinstance(st, Hysteresis))
        self.hysteresis = self._hysteresis.stream.model   # the valve's GPIM

    @property
    def electrode_v(self) -> float:
        """The amplifier's output [V] after the last sample (its slew limit follows the command)."""
        return self._amplifier.electrode_v

    @property
    def last_voltage_v(self) -> float:
        """The last command applied [V, amplifier input, after its clip]."""
        return self._amplifier.last_voltage_v

    # ------------------------------------------------------------------ per sample
    def step(self, voltage_v: float) -> float:
        """Apply ``voltage_v`` [V, amplifier input] for one sample; return the measured position [m]."""
        if not math.isfinite(voltage_v):
            raise ValueError(f"non-finite voltage command {voltage_v!r}")
        k, x = self.sample_index, voltage_v
        for stage in self._stages:
            x = stage.step(x, k)
        self.sample_index = k + 1
        self.time_s = self.sample_index * self.config.dt
        return x * 1e-6

    # ------------------------------------------------------------------ batch
    def run(self, voltages_v: np.ndarray) -> np.ndarray:
        """Apply a whole record of commands (one per sample); returns positions [m].

        Same result as calling ``step`` for each sample, state carried over either way.
        """
        v = np.asarray(voltages_v, dtype=float)
        if v.ndim != 1:
            raise ValueError("voltages must be a 1-D array")
        if not np.all(np.isfinite(v)):
            raise ValueError("non-finite voltage command in record")
        if v.size == 0:
            return np.zeros(0)
        k0, x = self.sample_index, v
        for stage in self._stages:
            x = stage.run(x, k0)
        self.sample_index = k0 + v.size
        self.time_s = self.sample_index * self.config.dt
        return x * 1e-6

    # ------------------------------------------------------------------ helpers
    @property
    def spool_position_m(self) -> float:
        """The spool's true position [m] after the last sample: what the sensor reads before its delay,
        noise and quantisation (a simulator's privilege, for judging tracking beneath the noise floor)."""
        return self._spool.y_um * 1e-6

    def position_um(self) -> float:
        """Noise-free present hysteresis output [um] (for diagnostics)."""
        stream = self._hysteresis.stream
        return stream.model.output_from_state(stream.state)
