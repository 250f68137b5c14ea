"""Simulated piezo valve: the paper's valve with the effects a real one has.

Signal chain (each stage has its own switch and parameters)::

    v_cmd [V, 0..10] -> amplifier (x20 - 100 V, slew limit I_max/C) -> v_eff [V input-equivalent]
      -> GPIM hysteresis [um] (asymmetry: separate descending envelope)
      -> creep (sum of slow first-order elements, unity DC gain)
      -> rate dependence (part of the output through a fast lag)
      -> loop-end flattening (friction/end stop, s*tanh(y/s))
      -> G_v(s) (exact ZOH)  -> thermal drift (offset and gain, exponential in time)
      -> LVDT noise and quantisation -> position [m]

``step`` (per sample) and ``run`` (a whole record, vectorised) give the same result, and a
run repeats bit for bit from ``seed``.  Default effects: slew limit, creep, flattening,
noise, quantisation.  Off by default (for identification work): asymmetry, rate
dependence, drift.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from ..model.dynamics import PAPER_VALVE_MODEL, ContinuousTF, first_order_lag
from ..model.hysteresis import GPIM, GPIMParams, PAPER_GPIM
from ..model.drive import CENTRE_VOLTAGE_V

__all__ = [
    "AmplifierParams",
    "CreepParams",
    "RateDependenceParams",
    "SaturationParams",
    "DriftParams",
    "SensorParams",
    "ValveSimConfig",
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
    sensor: SensorParams = SensorParams()
    initial_voltage_v: float = CENTRE_VOLTAGE_V

    def ideal(self) -> "ValveSimConfig":
        """Only hysteresis (and G_v if enabled): no creep, flattening, noise, slew, drift."""
        return replace(self, amplifier=replace(self.amplifier, enabled=False),
                       creep=replace(self.creep, enabled=False),
                       rate=replace(self.rate, enabled=False),
                       saturation=replace(self.saturation, enabled=False),
                       drift=replace(self.drift, enabled=False),
                       sensor=SensorParams(noise_enabled=False, quantisation_enabled=False),
                       descending_envelope=None)

    def hysteresis_model(self) -> GPIM:
        m = self.gpim.model()
        if self.descending_envelope is not None:
            b0, b1 = self.descending_envelope
            m = GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, float(b0), float(b1))
        return m


class SimulatedValve:
    """The valve as a sampled system: ``step(v) -> position [m]`` once per ``dt``."""

    def __init__(self, config: ValveSimConfig = ValveSimConfig()):
        if not (config.dt > 0 and math.isfinite(config.dt)):
            raise ValueError(f"dt must be a positive finite time, got {config.dt}")
        self.config = config
        self.hysteresis = config.hysteresis_model()
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        c = self.config
        v0 = float(np.clip(c.initial_voltage_v, c.amplifier.input_min_v, c.amplifier.input_max_v))
        self.time_s = 0.0
        self.sample_index = 0
        self._rng = np.random.default_rng(c.seed)
        self._noise = np.empty(0)
        self._noise_pos = 0
        self._electrode_v = c.amplifier.gain * v0 + c.amplifier.output_offset_v
        self._gpim = self.hysteresis.stream(v0=v0)
        y0 = self._gpim.model.output_from_state(self._gpim.state)
        self._creep = [first_order_lag(tau, c.dt) for tau in c.creep.time_constants_s]
        for f in self._creep:
            f.reset(y0)
        self._rate = first_order_lag(c.rate.time_constant_s, c.dt)
        self._rate.reset(y0)
        self._gv = c.valve_model.discretise(c.dt)
        self._gv.reset(self._static(y0))
        self.last_voltage_v = v0
        d = int(c.sensor.delay_samples)
        if d < 0:
            raise ValueError(f"sensor delay_samples must be >= 0, got {d}")
        self._delay_line = np.full(d, self._static(y0))  # the spool's last d positions, oldest first
        self._delay_pos = 0
        self._spool_um = self._static(y0)

    def _static(self, y_um: float) -> float:
        s = self.config.saturation
        if not s.enabled:
            return y_um
        return s.centre_um + s.scale_um * math.tanh((y_um - s.centre_um) / s.scale_um)

    def _noise_block(self) -> np.ndarray:
        return self._rng.standard_normal(NOISE_BLOCK)

    # ------------------------------------------------------------------ per sample
    def step(self, voltage_v: float) -> float:
        """Apply ``voltage_v`` [V, amplifier input] for one sample; return the measured position [m]."""
        c = self.config
        amp = c.amplifier
        if not math.isfinite(voltage_v):
            raise ValueError(f"non-finite voltage command {voltage_v!r}")
        v = min(max(voltage_v, amp.input_min_v), amp.input_max_v)
        self.last_voltage_v = v
        target = amp.gain * v + amp.output_offset_v
        if amp.enabled:
            limit = amp.slew_v_per_s * c.dt
            delta = min(max(target - self._electrode_v, -limit), limit)
            self._electrode_v += delta
        else:
            self._electrode_v = target
        v_eff = (self._electrode_v - amp.output_offset_v) / amp.gain
        y = self._gpim.step(v_eff)
        if c.creep.enabled:
            y_h = y
            for gain, f in zip(c.creep.gains, self._creep):
                y += gain * (f.step(y_h) - y_h)
        if c.rate.enabled:
            y += c.rate.share * (self._rate.step(y) - y)
        y = self._static(y)
        if c.dynamics_enabled:
            y = self._gv.step(y)
        t = self.time_s
        y = self._drift_scalar(y, t)
        self._spool_um = y
        if self._delay_line.size:
            line, k = self._delay_line, self._delay_pos
            y, line[k] = float(line[k]), y
            self._delay_pos = (k + 1) % line.size
        y = self._sensor_scalar(y)
        self.sample_index += 1
        self.time_s = self.sample_index * c.dt
        return y * 1e-6

    def _drift_scalar(self, y: float, t: float) -> float:
        d = self.config.drift
        if not d.enabled:
            return y
        if t <= d.start_s:
            return y
        k = 1.0 - math.exp(-(t - d.start_s) / d.time_constant_s)
        return y * (1.0 + d.gain_change * k) + d.offset_um * k

    def _sensor_scalar(self, y: float) -> float:
        s = self.config.sensor
        if s.noise_enabled:
            if self._noise_pos >= self._noise.size:
                self._noise = self._noise_block()
                self._noise_pos = 0
            y += s.noise_rms_um * float(self._noise[self._noise_pos])
            self._noise_pos += 1
        if s.quantisation_enabled:
            y = s.quantum_um * round(y / s.quantum_um)
        return y

    # ------------------------------------------------------------------ batch
    def run(self, voltages_v: np.ndarray) -> np.ndarray:
        """Apply a whole record of commands (one per sample); returns positions [m].

        Same result as calling ``step`` for each sample, state carried over either way.
        """
        c = self.config
        amp = c.amplifier
        v = np.asarray(voltages_v, dtype=float)
        if v.ndim != 1:
            raise ValueError("voltages must be a 1-D array")
        if not np.all(np.isfinite(v)):
            raise ValueError("non-finite voltage command in record")
        n = v.size
        if n == 0:
            return np.zeros(0)
        v = np.clip(v, amp.input_min_v, amp.input_max_v)
        self.last_voltage_v = float(v[-1])
        target = amp.gain * v + amp.output_offset_v
        electrode = self._slew_limit(target) if amp.enabled else target
        self._electrode_v = float(electrode[-1])
        v_eff = (electrode - amp.output_offset_v) / amp.gain
        y = self._gpim.run(v_eff)
        if c.creep.enabled:
            y_h = y
            y = y_h.copy()
            for gain, f in zip(c.creep.gains, self._creep):
                y += gain * (f.run(y_h) - y_h)
        if c.rate.enabled:
            y = y + c.rate.share * (self._rate.run(y) - y)
        if c.saturation.enabled:
            s = c.saturation
            y = s.centre_um + s.scale_um * np.tanh((y - s.centre_um) / s.scale_um)
        if c.dynamics_enabled:
            y = self._gv.run(y)
        t = (self.sample_index + np.arange(n)) * c.dt
        if c.drift.enabled:
            d = c.drift
            k = 1.0 - np.exp(-np.maximum(t - d.start_s, 0.0) / d.time_constant_s)
            y = y * (1.0 + d.gain_change * k) + d.offset_um * k
        self._spool_um = float(y[-1])
        if self._delay_line.size:
            line = np.roll(self._delay_line, -self._delay_pos)  # oldest first
            both = np.concatenate((line, y))
            y, self._delay_line, self._delay_pos = both[:n], both[n:].copy(), 0
        s = c.sensor
        if s.noise_enabled:
            y = y + s.noise_rms_um * self._take_noise(n)
        if s.quantisation_enabled:
            y = s.quantum_um * np.round(y / s.quantum_um)
        self.sample_index += n
        self.time_s = self.sample_index * c.dt
        return y * 1e-6

    def _take_noise(self, n: int) -> np.ndarray:
        parts = []
        need = n
        while need > 0:
            if self._noise_pos >= self._noise.size:
                self._noise = self._noise_block()
                self._noise_pos = 0
            take = min(need, self._noise.size - self._noise_pos)
            parts.append(self._noise[self._noise_pos:self._noise_pos + take])
            self._noise_pos += take
            need -= take
        return np.concatenate(parts)

    def _slew_limit(self, target: np.ndarray) -> np.ndarray:
        """Rate limiter u_k = u_{k-1} + clip(target_k - u_{k-1}, +-S dt), loop only where it binds."""
        limit = self.config.amplifier.slew_v_per_s * self.config.dt
        out = target.copy()
        prev = self._electrode_v
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

    # ------------------------------------------------------------------ helpers
    @property
    def spool_position_m(self) -> float:
        """The spool's true position [m] after the last sample: what the sensor reads before its delay,
        noise and quantisation (a simulator's privilege, for judging tracking beneath the noise floor)."""
        return self._spool_um * 1e-6

    def position_um(self) -> float:
        """Noise-free present hysteresis output [um] (for diagnostics)."""
        return self._gpim.model.output_from_state(self._gpim.state)
