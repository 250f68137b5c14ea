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
state; ``SimulatedValve`` chains the stages that are switched on, so ``step`` and ``run`` go through the
same chain and give the same result, and a run repeats bit for bit from ``seed``.  Default effects: slew limit, creep, flattening,
noise, quantisation.  Off by default (for identification work): asymmetry, rate
dependence, backlash, drift.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from ..model.dynamics import PAPER_VALVE_MODEL, ContinuousTF, first_order_lag
from ..model.hysteresis import GPIM, GPIMParams, PAPER_GPIM, PlayOperatorBank
from ..model.drive import CENTRE_VOLTAGE_V

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
    "ASYMMETRIC_ENVELOPE",
    "SimulatedValve",
]

NOISE_BLOCK = 4096  # noise is drawn in fixed blocks so step() and run() consume the RNG alike


@dataclass(frozen=True)
class AmplifierParams:
    """Noliac NDR6220-like amplifier: input 0..10 V -> -100..+100 V on the control electrode.

    Slew limit = current limit / actuator capacitance.  ``capacitance_f`` = 3 uF is our
    assumption for the CMBR08 control electrode (the paper gives none): 1.5 A / 3 uF = 500 V/ms,
    so an ideal full step is rate limited (0.4 ms for 200 V) while the paper's 2 ms ramps are not.
    """

    enabled: bool = True
    input_min_v: float = 0.0
    input_max_v: float = 10.0
    gain: float = 20.0  # V out per V in
    output_offset_v: float = -100.0
    current_limit_a: float = 1.5
    capacitance_f: float = 3.0e-6

    @property
    def slew_v_per_s(self) -> float:
        return self.current_limit_a / self.capacitance_f


@dataclass(frozen=True)
class CreepParams:
    """Creep: y += sum_i c_i (lag_{tau_i}(y) - y); log-like in time for log-spaced tau_i."""

    enabled: bool = True
    gains: tuple[float, ...] = (0.015, 0.015, 0.015, 0.015)
    time_constants_s: tuple[float, ...] = (0.03, 0.3, 3.0, 30.0)


@dataclass(frozen=True)
class RateDependenceParams:
    """Rate dependence: a share of the output follows a fast lag (loop widens with frequency)."""

    enabled: bool = False
    share: float = 0.15
    time_constant_s: float = 0.02


@dataclass(frozen=True)
class SaturationParams:
    """Loop-end flattening by friction / end stop: y -> centre + s * tanh((y - centre)/s)."""

    enabled: bool = True
    scale_um: float = 400.0
    centre_um: float = 0.0


@dataclass(frozen=True)
class DriftParams:
    """Thermal drift: offset and gain approach new values exponentially with the time since ``start_s`` [s]
    (before it: none; a drift that sets in during operation)."""

    enabled: bool = False
    offset_um: float = 4.0
    gain_change: float = 0.03
    time_constant_s: float = 20.0
    start_s: float = 0.0


@dataclass(frozen=True)
class BacklashParams:
    """Backlash on the spool's path: a clearance of ``width_um`` either side [um] (a play of that half-width) between
    the actuator and the spool."""

    enabled: bool = False
    width_um: float = 0.5


@dataclass(frozen=True)
class SensorParams:
    """LVDT: white noise and quantisation; optionally a transport delay (a conditioning filter or a DAQ
    pipeline: the position read at sample k is the spool's at sample k - delay_samples)."""

    noise_enabled: bool = True
    noise_rms_um: float = 0.05
    quantisation_enabled: bool = True
    quantum_um: float = 0.005
    delay_samples: int = 0


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


@dataclass(frozen=True)
class StageSwitch:
    """A stage of the chain that can be switched on and off, in one place: the simulated backend's parameter
    ``sim.<name>`` and its description, whether a config has it on, and a config with it on or off."""

    name: str
    description: str
    is_on: Callable[[ValveSimConfig], bool]
    set: Callable[[ValveSimConfig, bool], ValveSimConfig]


ASYMMETRIC_ENVELOPE = (0.95, 0.2)   # (b0, b1) of the descending envelope when the asymmetry switch is on

STAGE_SWITCHES: tuple[StageSwitch, ...] = (
    StageSwitch("slew_limit", "amplifier current limit", lambda c: c.amplifier.enabled,
                lambda c, on: replace(c, amplifier=replace(c.amplifier, enabled=on))),
    StageSwitch("creep", "creep", lambda c: c.creep.enabled, lambda c, on: replace(c, creep=replace(c.creep, enabled=on))),
    StageSwitch("saturation", "loop-end flattening", lambda c: c.saturation.enabled,
                lambda c, on: replace(c, saturation=replace(c.saturation, enabled=on))),
    StageSwitch("noise", "LVDT noise", lambda c: c.sensor.noise_enabled,
                lambda c, on: replace(c, sensor=replace(c.sensor, noise_enabled=on))),
    StageSwitch("dynamics", "G_v(s)", lambda c: c.dynamics_enabled, lambda c, on: replace(c, dynamics_enabled=on)),
    StageSwitch("rate_dependence", "rate dependence", lambda c: c.rate.enabled,
                lambda c, on: replace(c, rate=replace(c.rate, enabled=on))),
    StageSwitch("drift", "thermal drift", lambda c: c.drift.enabled, lambda c, on: replace(c, drift=replace(c.drift, enabled=on))),
    StageSwitch("backlash", "backlash on the spool's path", lambda c: c.backlash.enabled,
                lambda c, on: replace(c, backlash=replace(c.backlash, enabled=on))),
    StageSwitch("asymmetry", "asymmetry", lambda c: c.descending_envelope is not None,
                lambda c, on: replace(c, descending_envelope=ASYMMETRIC_ENVELOPE if on else None)),
)


class _Amplifier:
    """Input clip, gain and offset, current (slew) limit; out: the input-equivalent voltage [V] the bender sees."""

    def __init__(self, p: AmplifierParams, dt: float, v0: float):
        self.p, self.limit = p, p.slew_v_per_s * dt
        self.electrode_v = p.gain * v0 + p.output_offset_v
        self.last_voltage_v = v0

    def step(self, v: float, k: int) -> float:
        p = self.p
        v = min(max(v, p.input_min_v), p.input_max_v)
        self.last_voltage_v = v
        target = p.gain * v + p.output_offset_v
        if p.enabled:
            self.electrode_v += min(max(target - self.electrode_v, -self.limit), self.limit)
        else:
            self.electrode_v = target
        return (self.electrode_v - p.output_offset_v) / p.gain

    def run(self, v: np.ndarray, k0: int) -> np.ndarray:
        p = self.p
        v = np.clip(v, p.input_min_v, p.input_max_v)
        self.last_voltage_v = float(v[-1])
        target = p.gain * v + p.output_offset_v
        electrode = self._slew_limit(target) if p.enabled else target
        self.electrode_v = float(electrode[-1])
        return (electrode - p.output_offset_v) / p.gain

    def _slew_limit(self, target: np.ndarray) -> np.ndarray:
        """Rate limiter u_k = u_{k-1} + clip(target_k - u_{k-1}, +-S dt), loop only where it binds."""
        limit = self.limit
        out = target.copy()
        prev = self.electrode_v
        k = 0
        n = target.size
        while k < n:
            # follow the target exactly while every step is within the limit
            steps = np.abs(np.diff(np.concatenate(([prev], target[k:]))))
            bad = np.flatnonzero(steps > limit)
            if bad.size == 0:
                return out
            k += int(bad[0])
            prev = float(out[k - 1]) if k > 0 else prev
            # limited stretch: integrate sample by sample until the output meets the target
            while k < n:
                delta = min(max(target[k] - prev, -limit), limit)
                prev += delta
                out[k] = prev
                k += 1
                if prev == target[k - 1]:
                    break
        return out


class _Hysteresis:
    """The GPIM [um] of the input-equivalent voltage (its operators' state carried)."""

    def __init__(self, model: GPIM, v0: float):
        self.stream = model.stream(v0=v0)

    def step(self, v: float, k: int) -> float:
        return self.stream.step(v)

    def run(self, v: np.ndarray, k0: int) -> np.ndarray:
        return self.stream.run(v)


class _Creep:
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


class _RateDependence:
    """Part of the output through a fast lag: a loop that widens with the input rate."""

    def __init__(self, p: RateDependenceParams, dt: float, y0: float):
        self.share = p.share
        self.lag = first_order_lag(p.time_constant_s, dt)
        self.lag.reset(y0)

    def step(self, y: float, k: int) -> float:
        return y + self.share * (self.lag.step(y) - y)

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        return y + self.share * (self.lag.run(y) - y)


class _Saturation:
    """Loop-end flattening s tanh((y - c) / s) + c."""

    def __init__(self, p: SaturationParams):
        self.p = p

    def step(self, y: float, k: int) -> float:
        p = self.p
        return p.centre_um + p.scale_um * math.tanh((y - p.centre_um) / p.scale_um)

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        p = self.p
        return p.centre_um + p.scale_um * np.tanh((y - p.centre_um) / p.scale_um)


class _Dynamics:
    """G_v(s), exact ZOH."""

    def __init__(self, tf: ContinuousTF, dt: float, y0: float):
        self.filter = tf.discretise(dt)
        self.filter.reset(y0)

    def step(self, y: float, k: int) -> float:
        return self.filter.step(y)

    def run(self, y: np.ndarray, k0: int) -> np.ndarray:
        return self.filter.run(y)


class _Backlash:
    """A play of half-width ``width_um`` [um]: the spool moves once the actuator has taken up the clearance."""

    def __init__(self, p: BacklashParams, y0: float):
        if not (p.width_um >= 0 and math.isfinite(p.width_um)):
            raise ValueError(f"backlash width_um must be a finite width >= 0, got {p.width_um}")
        self.play = PlayOperatorBank([p.width_um], [y0])

    def step(self, x: float, k: int) -> float:
        return float(self.play.step(x, x)[0])

    def run(self, x: np.ndarray, k0: int) -> np.ndarray:
        return self.play.run(x, x)[:, 0]


class _Drift:
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


class _SensorDelay:
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


class _Sensor:
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


class SimulatedValve:
    """The valve as a sampled system: ``step(v) -> position [m]`` once per ``dt``, or ``run(v)`` over a whole
    record.  Both go through one chain of stages (the module docstring's), each with its ``step`` and ``run``
    on one state; a stage that is switched off is not in the chain."""

    def __init__(self, config: ValveSimConfig = ValveSimConfig()):
        if not (config.dt > 0 and math.isfinite(config.dt)):
            raise ValueError(f"dt must be a positive finite time, got {config.dt}")
        self.config = config
        self.hysteresis = config.hysteresis_model()
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        c = self.config
        d = int(c.sensor.delay_samples)
        if d < 0:
            raise ValueError(f"sensor delay_samples must be >= 0, got {d}")
        v0 = float(np.clip(c.initial_voltage_v, c.amplifier.input_min_v, c.amplifier.input_max_v))
        self.time_s = 0.0
        self.sample_index = 0
        self._amplifier = _Amplifier(c.amplifier, c.dt, v0)
        self._hysteresis = _Hysteresis(self.hysteresis, v0)
        y0 = self.hysteresis.output_from_state(self._hysteresis.stream.state)
        saturation = _Saturation(c.saturation) if c.saturation.enabled else None
        y_static = saturation.step(y0, 0) if saturation else y0
        self._spool = _Spool(y_static)
        stages = [self._amplifier, self._hysteresis,
                  _Creep(c.creep, c.dt, y0) if c.creep.enabled else None,
                  _RateDependence(c.rate, c.dt, y0) if c.rate.enabled else None,
                  saturation,
                  _Dynamics(c.valve_model, c.dt, y_static) if c.dynamics_enabled else None,
                  _Backlash(c.backlash, y_static) if c.backlash.enabled else None,
                  _Drift(c.drift, c.dt) if c.drift.enabled else None,
                  self._spool,
                  _SensorDelay(d, y_static) if d else None,
                  _Sensor(c.sensor, c.seed)]
        self._stages = [st for st in stages if st is not None]

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
