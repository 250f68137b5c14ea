"""Simulated valves with undeclared effects, for judging the residual loop (kept in the tests on purpose).

Every valve is the paper's GPIM followed by G_v, with LVDT noise; each effect is written in a form
*unlike* the regressors of the catalogue (``piezo_valve_ros/core/identification/effects``):

* creep: a logarithmic kernel (convolution of the output's changes with log(1 + t/t_c)) whose size
  depends on the level, or whose speed depends on the direction of the move (the catalogue: sums of
  first-order lags);
* dynamics: a third-order response (a pole and a spool mode), the paper's G_v with a lightly damped
  spool mode, a transport delay (the catalogue: a second pole pair fitted freely), and Al Janaideh's
  rate-dependent thresholds r_j + beta |dv/dt| through a trailing moving average with a cap (the
  catalogue: thresholds affine in the log of the rate through a first-order lag);
* asymmetry: a curved descending envelope (the catalogue: a straight one of another slope);
* drift: offset and gain following a slow temperature swing through a play operator (a drift with its
  own hysteresis), a gain drift (the catalogue: time functions and lags of the drive's activity);
* saturation: a one-sided soft end stop and an off-centre tanh (the catalogue: polynomials of the output);
* another drive range: a +-150 V amplifier (30x the paper's volts) on a valve warming up (an S-shaped
  temperature rise moving offset and gain);
* outside the catalogue: an output dead zone and a backlash of about a micrometre, a mechanical hum.
Nothing here is imported by the package.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np
from scipy import signal

from piezo_valve_ros.core.model import PAPER_VALVE_MODEL, ContinuousTF
from piezo_valve_ros.core.model import PAPER_GPIM, play_batch
from piezo_valve_ros.core.sim import identification_voltage, validation_voltage

DT = 5e-4            # 2 kHz: fast enough for G_v's poles, small enough for a quick suite
NOISE_UM = 0.05
QUANTUM_UM = 0.005


@dataclass(frozen=True)
class Valve:
    """One simulated valve: the paper's chain with optional stages (each a callable of the tests)."""

    descending: Optional[Callable[[np.ndarray], np.ndarray]] = None    # descending envelope gamma_d(v) [V]
    threshold_scale: Optional[Callable[[np.ndarray, float], np.ndarray]] = None  # (v, dt) -> factor on thresholds
    threshold_add: Optional[Callable[[np.ndarray, float], np.ndarray]] = None    # (v, dt) -> added to thresholds [V]
    creep: Optional[Callable[[np.ndarray, float], np.ndarray]] = None  # (H, dt) -> added [um]
    static: Optional[Callable[[np.ndarray], np.ndarray]] = None        # y -> y before G
    dynamics: ContinuousTF = PAPER_VALVE_MODEL
    after: Optional[Callable[[np.ndarray, np.ndarray, float], np.ndarray]] = None  # (y, v, dt) -> y after G
    noise_um: float = NOISE_UM
    effects: tuple[str, ...] = ()
    notes: dict = field(default_factory=dict)
    drive: Optional[Callable[[np.ndarray], np.ndarray]] = None  # the record's voltage [V] -> the paper's 0-10 V


    def positions(self, voltage: np.ndarray, seed: int, dt: float = DT) -> np.ndarray:
        """Measured positions [um] for the applied voltages (one per sample)."""
        g = PAPER_GPIM.model()
        r = g.thresholds
        v = np.asarray(voltage, float) if self.drive is None else self.drive(np.asarray(voltage, float))
        lower = g.ascending_envelope(v)
        upper = self.descending(v) * g.a0 + g.a1 if self.descending is not None else lower
        z0 = g.virgin_state(float(v[0]))
        if self.threshold_scale is None and self.threshold_add is None:
            H, _ = play_batch(lower, upper, r, z0, g.weights)
        else:  # a sample-by-sample recursion of the play operators (written out, unlike the package's scan)
            k = self.threshold_scale(v, dt) if self.threshold_scale is not None else np.ones(v.size)
            w = self.threshold_add(v, dt) if self.threshold_add is not None else np.zeros(v.size)
            z = z0.copy()
            H = np.empty(v.size)
            for i in range(v.size):
                lo = lower[i] - r * k[i] - w[i]
                z = np.minimum(np.maximum(z, lo), np.maximum(upper[i] + r * k[i] + w[i], lo))
                H[i] = z @ g.weights
        H = H + g.offset_um
        y = H + (self.creep(H, dt) if self.creep is not None else 0.0)
        if self.static is not None:
            y = self.static(y)
        b, a, _ = signal.cont2discrete((self.dynamics.num, self.dynamics.den), dt, method="zoh")
        b = np.atleast_1d(np.squeeze(b))
        y = signal.lfilter(b, a, y, zi=signal.lfilter_zi(b, a) * y[0])[0]
        if self.after is not None:
            y = self.after(y, np.asarray(voltage, float), dt)
        rng = np.random.default_rng(seed)
        y = y + self.noise_um * rng.standard_normal(y.size)
        return QUANTUM_UM * np.round(y / QUANTUM_UM)

    def rows(self, voltage: np.ndarray, seed: int, dt: float = DT) -> np.ndarray:
        """``samples`` rows: time [s], voltage [V], position [m]."""
        return np.column_stack((np.arange(voltage.size) * dt, voltage, self.positions(voltage, seed, dt) * 1e-6))


def training_voltage(dt: float = DT) -> np.ndarray:
    return identification_voltage(dt, 30.0)


def validation_voltage_(dt: float = DT) -> np.ndarray:
    return validation_voltage(dt)


# ---------------------------------------------------------------------------- effect forms
def log_creep(size: float, t_c: float = 0.02, level_slope: float = 0.0, t_c_falling: Optional[float] = None,
              settle_s: float = 10.0):
    """Creep after every change of H: size * dH * log(1 + t/t_c) / log(1 + settle/t_c), settled (1) after
    ``settle_s``; larger at high output (level_slope per um from the centre), or with its own speed after
    falling moves (t_c_falling)."""
    def kernel(n, dt, tc):
        t = np.arange(n) * dt
        return np.minimum(np.log1p(t / tc) / np.log1p(settle_s / tc), 1.0)

    def creep(H, dt):
        n = H.size
        if t_c_falling is None:
            dH = np.diff(H, prepend=H[0])
            c = signal.fftconvolve(dH, kernel(n, dt, t_c))[:n]
        else:  # the direction of the slow motion (creep does not follow fast cycling)
            w = max(int(round(0.05 / dt)), 1)
            slow = np.convolve(np.concatenate((np.full(w - 1, H[0]), H)), np.ones(w) / w, mode="valid")
            dH = np.diff(slow, prepend=slow[0])
            c = (signal.fftconvolve(np.maximum(dH, 0), kernel(n, dt, t_c))[:n]
                 + signal.fftconvolve(np.minimum(dH, 0), kernel(n, dt, t_c_falling))[:n])
        return size * c * (1.0 + level_slope * H)
    return creep


def pole(omega_rad_s: float) -> ContinuousTF:
    return ContinuousTF((omega_rad_s,), (1.0, omega_rad_s))


def times(a: ContinuousTF, b: ContinuousTF) -> ContinuousTF:
    return ContinuousTF(tuple(np.polymul(a.num, b.num)), tuple(np.polymul(a.den, b.den)))


def mode(omega_rad_s: float, zeta: float) -> ContinuousTF:
    return ContinuousTF((omega_rad_s ** 2,), (1.0, 2 * zeta * omega_rad_s, omega_rad_s ** 2))


def delay(seconds: float) -> ContinuousTF:
    """A transport delay (Pade 2/2), e.g. the DAQ's and amplifier's latency."""
    T = seconds
    return ContinuousTF((T * T / 12, -T / 2, 1.0), (T * T / 12, T / 2, 1.0))


def rate_dependent_thresholds(beta_s: float, cap_v: float, window_s: float = 0.04):
    """Al Janaideh's rate-dependent PI: every threshold grows by beta * |dv/dt| (a trailing moving average
    over window_s), capped at cap_v."""
    def add(v, dt):
        rate = np.abs(np.gradient(v, dt))
        n = max(int(round(window_s / dt)), 1)
        return np.minimum(beta_s * np.convolve(rate, np.ones(n) / n)[:rate.size], cap_v)
    return add


def rate_widening(extra: float, rate0_v_s: float = 100.0, window_s: float = 0.04):
    """Thresholds scaled by 1 + extra * rho / (rho + rate0): the loop widens with the input rate and
    levels off (rho = |dv/dt| through a moving average over window_s)."""
    def scale(v, dt):
        rate = np.abs(np.gradient(v, dt))
        n = max(int(round(window_s / dt)), 1)
        rho = np.convolve(rate, np.ones(n) / n)[:rate.size]  # trailing (causal) window
        return 1.0 + extra * rho / (rho + rate0_v_s)
    return scale


def mild_rate_widening(widening_v: float, rate0_v_s: float = 20.0, window_s: float = 0.04):
    """Every threshold grows by widening_v * rho / (rho + rate0) [V] (rho = |dv/dt| through a trailing
    moving average): a loop a few per cent wider at the training rates, levelling off."""
    def add(v, dt):
        rate = np.abs(np.gradient(v, dt))
        n = max(int(round(window_s / dt)), 1)
        rho = np.convolve(rate, np.ones(n) / n)[:rate.size]
        return widening_v * rho / (rho + rate0_v_s)
    return add


def self_heating(offset_um: float, gain_change: float, tau_core_s: float = 8.0, tau_case_s: float = 30.0):
    """Dissipated power ~ (dv/dt)^2 heats a core that heats a case (two thermal time constants); offset and
    gain follow the case temperature."""
    def after(y, v, dt):
        power = (np.gradient(v, dt) / 100.0) ** 2  # about 1 while the multisine runs
        a1, a2 = np.exp(-dt / tau_core_s), np.exp(-dt / tau_case_s)
        core = signal.lfilter([1 - a1], [1, -a1], power)
        case = signal.lfilter([1 - a2], [1, -a2], core)
        return y * (1.0 + gain_change * case) + offset_um * case
    return after


def thermal_drift_with_hysteresis(offset_um_per_k: float, gain_per_k: float, swing_k: float = 2.0,
                                  period_s: float = 120.0, play_k: float = 0.3):
    """A slow temperature swing (half a sine over ``period_s``) moves offset and gain through a play
    operator (the mount's stick-slip): a drift with its own hysteresis."""
    def after(y, v, dt):
        t = np.arange(y.size) * dt
        temp = swing_k * np.sin(np.pi * t / period_s)
        seen, _ = play_batch(temp, temp, np.array([play_k]), np.array([0.0]))
        k = seen[:, 0]
        return y * (1.0 + gain_per_k * k) + offset_um_per_k * k
    return after


def warm_up(offset_um: float, gain_change: float, tau_s: float = 40.0, lag_s: float = 15.0):
    """A valve warming up after switch-on: offset and gain follow a temperature that rises as a second-order
    step (a lag of ``lag_s`` behind one of ``tau_s``: an S-shaped start, unlike a first-order time function)."""
    def after(y, v, dt):
        t = np.arange(y.size) * dt
        rise = 1.0 - (tau_s * np.exp(-t / tau_s) - lag_s * np.exp(-t / lag_s)) / (tau_s - lag_s)
        return y * (1.0 + gain_change * rise) + offset_um * rise
    return after


def gain_drift(change: float, tau_s: float = 25.0):
    def after(y, v, dt):
        t = np.arange(y.size) * dt
        return y * (1.0 + change * (1.0 - np.exp(-t / tau_s)))
    return after


def one_sided_stop(top_um: float, softness_um: float):
    def static(y):
        return top_um - softness_um * np.logaddexp(0.0, (top_um - y) / softness_um)
    return static


def off_centre_tanh(centre_um: float, scale_um: float):
    def static(y):
        return centre_um + scale_um * np.tanh((y - centre_um) / scale_um)
    return static


def dead_zone(half_width_um: float):
    def after(y, v, dt):
        return np.sign(y) * np.maximum(np.abs(y) - half_width_um, 0.0)
    return after


def backlash(half_width_um: float):
    def after(y, v, dt):
        out, _ = play_batch(y, y, np.array([half_width_um]), np.array([y[0]]))
        return out[:, 0]
    return after


def hum(amplitude_um: float, frequency_hz: float):
    def after(y, v, dt):
        return y + amplitude_um * np.sin(2 * np.pi * frequency_hz * np.arange(y.size) * dt)
    return after


def combine(*stages):
    def after(y, v, dt):
        for s in stages:
            y = s(y, v, dt)
        return y
    return after


# ---------------------------------------------------------------------------- the battery
NOMINAL = Valve()
BATTERY: dict[str, Valve] = {
    "nominal": NOMINAL,
    "creep, level-dependent log kernel": replace(NOMINAL, creep=log_creep(0.05, level_slope=0.006), effects=("creep",)),
    "creep, direction-dependent log kernel": replace(NOMINAL, creep=log_creep(0.04, t_c=0.01, t_c_falling=0.3),
                                                     effects=("creep",)),
    "dynamics, third order: a pole and a spool mode": replace(NOMINAL, dynamics=times(pole(300.0), mode(2 * np.pi * 250, 0.3)),
                                                              effects=("dynamics",)),
    "dynamics, lightly damped spool mode": replace(NOMINAL, dynamics=times(PAPER_VALVE_MODEL, mode(2 * np.pi * 180, 0.12)),
                                                   effects=("dynamics",)),
    "dynamics, loop width growing with the input rate": replace(
        NOMINAL, threshold_add=rate_dependent_thresholds(2e-3, 1.0), effects=("dynamics",)),
    "asymmetry, curved descending envelope": replace(
        NOMINAL, descending=lambda v: v + 0.10 * (v - 5.0) + 0.012 * (v - 5.0) ** 2, effects=("asymmetry",)),
    "drift with its own hysteresis (temperature through a play)": replace(
        NOMINAL, after=thermal_drift_with_hysteresis(1.5, 0.01), effects=("drift",)),
    "saturation, one-sided soft end stop": replace(NOMINAL, static=one_sided_stop(52.0, 6.0), effects=("saturation",)),
    "saturation, off-centre tanh": replace(NOMINAL, static=off_centre_tanh(25.0, 110.0), effects=("saturation",)),
    "masking pair: gain drift + transport delay": replace(NOMINAL, dynamics=times(PAPER_VALVE_MODEL, delay(5e-4)),
                                                          after=gain_drift(0.015), effects=("dynamics", "drift")),
    "masking pair: creep + drift": replace(NOMINAL, creep=log_creep(0.02), after=gain_drift(0.012),
                                           effects=("creep", "drift")),
}
OUTSIDE: dict[str, Valve] = {
    "dead zone, 1 um": replace(NOMINAL, after=dead_zone(0.5)),
    "backlash, 1 um": replace(NOMINAL, after=backlash(0.5)),
    "mechanical hum, 7.3 Hz": replace(NOMINAL, after=hum(1.5, 7.3)),
}

# ---------------------------------------------------------------------------- another drive range
WIDE_DRIVE_V_PER_V = 30.0   # a +-150 V amplifier: the paper's 0-10 V span at 30 V per V around its centre


def wide_drive(model_voltage: np.ndarray) -> np.ndarray:
    """The paper's 0-10 V signal as a +-150 V drive [V]."""
    return WIDE_DRIVE_V_PER_V * (np.asarray(model_voltage, float) - 5.0)


WIDE: dict[str, Valve] = {
    # recorded in the drive's own volts: thresholds, rates and ranges all 30x the paper's
    "+-150 V drive, nominal": replace(NOMINAL, drive=lambda v: 5.0 + v / WIDE_DRIVE_V_PER_V),
    "+-150 V drive, warming up (offset 2 um, gain +1.5 %, S-shaped over a minute)": replace(
        NOMINAL, drive=lambda v: 5.0 + v / WIDE_DRIVE_V_PER_V, after=warm_up(2.0, 0.015), effects=("drift",)),
}


# ---------------------------------------------------------------------------- records that start off the loop
PRE_HISTORIES: dict[str, np.ndarray] = {
    # driven before the record starts (not recorded), then held at the centre for 1 s at DT
    "to 9 V, 1.5 V and back": np.concatenate((np.linspace(5.0, 9.0, 400), np.linspace(9.0, 1.5, 800),
                                               np.linspace(1.5, 5.0, 400), np.full(2000, 5.0))),
    "to 10 V and back": np.concatenate((np.linspace(5.0, 10.0, 400), np.linspace(10.0, 5.0, 400),
                                        np.full(2000, 5.0))),
}


def rows_after(valve: Valve, pre_history: np.ndarray, voltage: np.ndarray, seed: int, dt: float = DT) -> np.ndarray:
    """``samples`` rows of ``voltage`` for a valve that was driven through ``pre_history`` before the record
    (the valve remembers it; the record does not show it)."""
    return valve.rows(np.concatenate((pre_history, voltage)), seed, dt)[pre_history.size:]


# ---------------------------------------------------------------------------- closed-loop operating records
def staircase_and_sines_um(seed: int, dt: float, seconds: float = 60.0) -> np.ndarray:
    """What a valve under feedback follows in operation: 2 s levels for half the time, then half-size levels
    with two slow sines on top [um]."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(seconds / dt))) * dt
    stair = np.repeat(rng.uniform(-55.0, 55.0, int(seconds / 2.0) + 1), int(round(2.0 / dt)))[:t.size]
    half = t >= 0.5 * seconds
    sines = 25.0 * np.sin(2 * np.pi * 0.13 * t) + 15.0 * np.sin(2 * np.pi * 0.31 * t + 1.0) * (t >= 0.67 * seconds)
    return np.clip(np.where(half, 0.5 * stair + sines, stair), -65.0, 65.0)


def closed_loop_rows(sim_config, strategy: str, gains, seed: int) -> np.ndarray:
    """``samples`` rows of the package's simulated valve (``sim_config``, seeded) under the package's
    controller (``strategy``, ``gains``, the paper's model) following ``staircase_and_sines_um``: the
    voltage is the controller's output, not a designed signal."""
    from dataclasses import replace as _replace
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.sim import run_closed_loop
    from piezo_valve_ros.core.sim import SimulatedValve
    from piezo_valve_ros.core.control import ControllerConfig, ValveController
    dt = sim_config.dt
    valve = SimulatedValve(_replace(sim_config, seed=seed))
    controller = ValveController(ControllerConfig(strategy=strategy, gains=gains, dt=dt), CompensationModel())
    controller.reset(5.0)
    rec = run_closed_loop(valve, controller, staircase_and_sines_um(seed, dt) * 1e-6)
    # sample k: the command applied during it and the position measured at its end
    return np.column_stack((np.arange(rec.command_v.size - 1) * dt, rec.command_v[:-1], rec.position_m[1:]))
