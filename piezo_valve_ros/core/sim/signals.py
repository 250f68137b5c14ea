"""Excitation and test signals of the paper (and the extra ones identification needs).

All return sampled arrays for a sampling period ``dt`` [s].  Voltages in V (amplifier input),
positions in m unless a name says ``_um``.
"""
from __future__ import annotations


import numpy as np

from ..model.drive import CENTRE_VOLTAGE_V, HALF_SPAN_V

__all__ = ["time_base", "synchronising_sine", "training_voltage", "validation_shape", "validation_reference_m",
           "PAPER_STEPS_UM", "step_reference_m", "stepped_sine_reference_m", "step_and_hold_voltage",
           "multisine_voltage", "identification_voltage", "validation_voltage", "joined", "ReferenceRamp",
           "IDENTIFICATION_STEPS_V", "IDENTIFICATION_MULTISINE_HZ", "ramp_profile", "sine_profile", "load_profile",
           "rig_training_voltage"]


def time_base(duration_s: float, dt: float) -> np.ndarray:
    return np.arange(int(round(duration_s / dt))) * dt


def synchronising_sine(dt: float, duration_s: float = 2.0, frequency_hz: float = 2.0,
                       centre_v: float = CENTRE_VOLTAGE_V, amplitude_v: float = HALF_SPAN_V) -> np.ndarray:
    """Damped sine that ends at ``centre_v``: puts the actuator in a known (near-virgin) state."""
    t = time_base(duration_s, dt)
    return centre_v + amplitude_v * (1.0 - t / duration_s) * np.sin(2 * np.pi * frequency_hz * t)


def training_voltage(dt: float, duration_s: float = 60.0, synchronise: bool = True) -> np.ndarray:
    """Eq. 11: 5 V to 1.25 s, then 5 + 5 sin(2 pi 0.2 (t-1.25)); from 10 s damped by (1 - 0.02 (t-10)).

    With ``synchronise`` the damped synchronising sine is prepended.
    """
    t = time_base(duration_s, dt)
    sine = 5.0 * np.sin(2 * np.pi * 0.2 * (t - 1.25))
    damping = np.where(t >= 10.0, np.maximum(1.0 - 0.02 * (t - 10.0), 0.0), 1.0)
    v = np.where(t < 1.25, 5.0, 5.0 + sine * damping)
    return np.concatenate((synchronising_sine(dt), v)) if synchronise else v


def validation_shape(t: np.ndarray) -> np.ndarray:
    """Eq. 12: F(t) = sin(2 pi 0.35 t) + 2 cos(2 pi 0.2 t + pi/2) + 2 sin(2 pi 0.3 t + pi/2)."""
    return (np.sin(2 * np.pi * 0.35 * t) + 2 * np.cos(2 * np.pi * 0.2 * t + np.pi / 2)
            + 2 * np.sin(2 * np.pi * 0.3 * t + np.pi / 2))


def validation_reference_m(dt: float, duration_s: float = 53.0, amplitude_um: float = 60.0) -> np.ndarray:
    """Eq. 12 as a position demand: v(t) = F(t + 8), scaled so its peak is ``amplitude_um``."""
    t = time_base(duration_s, dt)
    f = validation_shape(t + 8.0)
    return f / np.max(np.abs(f)) * amplitude_um * 1e-6


# (start, end) of the paper's three step tests [um]
PAPER_STEPS_UM = ((0.0, 17.5), (-17.5, 35.0), (-52.5, 35.0))


def step_reference_m(dt: float, start_um: float, end_um: float, hold_before_s: float = 0.1,
                     hold_after_s: float = 0.1, ramp_s: float = 2e-3) -> tuple[np.ndarray, int]:
    """Hold ``start_um``, ramp to ``end_um`` in ``ramp_s`` (the paper's 2 ms), hold.

    Returns (reference [m], index where the ramp starts).
    """
    n_before = int(round(hold_before_s / dt))
    n_ramp = max(int(round(ramp_s / dt)), 1)
    n_after = int(round(hold_after_s / dt))
    ramp = start_um + (end_um - start_um) * np.arange(1, n_ramp + 1) / n_ramp
    ref = np.concatenate((np.full(n_before, start_um), ramp, np.full(n_after, end_um)))
    return ref * 1e-6, n_before


def stepped_sine_reference_m(dt: float, frequency_hz: float, amplitude_um: float, periods: int = 6,
                             settle_periods: int = 2, min_duration_s: float = 0.05) -> tuple[np.ndarray, int]:
    """Sine demand about 0 um for one point of a frequency response.

    Returns (reference [m], index from which the response is analysed).
    """
    total_periods = periods + settle_periods
    duration = max(total_periods / frequency_hz, min_duration_s)
    n = int(round(duration / dt))
    t = np.arange(n) * dt
    ref = amplitude_um * np.sin(2 * np.pi * frequency_hz * t) * 1e-6
    analyse_from = n - int(round(periods / frequency_hz / dt))
    return ref, analyse_from


def step_and_hold_voltage(dt: float, levels_v=(7.5, 2.5, 8.5, 5.0, 1.5, 6.0), hold_s: float = 2.0,
                          ramp_s: float = 2e-3) -> np.ndarray:
    """Voltage steps (2 ms ramps) with long holds: exposes creep and drift."""
    parts = []
    prev = CENTRE_VOLTAGE_V
    n_ramp = max(int(round(ramp_s / dt)), 1)
    n_hold = int(round(hold_s / dt))
    for level in levels_v:
        parts.append(prev + (level - prev) * np.arange(1, n_ramp + 1) / n_ramp)
        parts.append(np.full(n_hold, level))
        prev = level
    return np.concatenate(parts)


def multisine_voltage(dt: float, duration_s: float = 8.0, frequencies_hz=(0.5, 2.0, 8.0, 20.0),
                      amplitude_v: float = 4.0) -> np.ndarray:
    """Sequential sines of rising frequency (about 5 V): exposes rate dependence and dynamics."""
    seg = duration_s / len(frequencies_hz)
    parts = []
    for f in frequencies_hz:
        t = time_base(seg, dt)
        ramp_in = np.minimum(t / min(0.25, seg / 4), 1.0)
        parts.append(CENTRE_VOLTAGE_V + amplitude_v * ramp_in * np.sin(2 * np.pi * f * t))
    return np.concatenate(parts)


IDENTIFICATION_STEPS_V = ((7.5, 2.5, 8.5), (5.0, 1.5, 6.0))   # step-and-hold levels before / after eq. 11
IDENTIFICATION_MULTISINE_HZ = ((0.5, 2.0, 8.0, 20.0), (1.0, 4.0, 12.0, 25.0))


def identification_voltage(dt: float, training_s: float = 30.0) -> np.ndarray:
    """A full identification experiment [V]: synchronisation, step-and-hold and multisine segments (creep,
    drift, dynamics), the paper's training signal (eq. 11), then step-and-hold and multisine segments
    again at other levels and frequencies, and a hold at 5 V.

    Every kind of excitation appears before and after the training signal, so a held-out last part of
    the record (the analyser's default, 30 %) shows what the fit part shows.
    """
    return joined(dt, synchronising_sine(dt),
                  step_and_hold_voltage(dt, IDENTIFICATION_STEPS_V[0]),
                  multisine_voltage(dt, 4.0, IDENTIFICATION_MULTISINE_HZ[0]),
                  training_voltage(dt, training_s, synchronise=False),
                  step_and_hold_voltage(dt, IDENTIFICATION_STEPS_V[1]),
                  multisine_voltage(dt, 4.0, IDENTIFICATION_MULTISINE_HZ[1]),
                  np.full(int(round(0.5 / dt)), 5.0))


def joined(dt: float, *segments: np.ndarray, ramp_s: float = 2e-3) -> np.ndarray:
    """Segments one after another, each jump between them replaced by a ``ramp_s`` ramp (the paper's 2 ms:
    an ideal step hits the amplifier's current limit)."""
    n_ramp = max(int(round(ramp_s / dt)), 1)
    parts = [segments[0]]
    for seg in segments[1:]:
        a, b = float(parts[-1][-1]), float(seg[0])
        if a != b:
            parts.append(a + (b - a) * np.arange(1, n_ramp) / n_ramp)
        parts.append(seg)
    return np.concatenate(parts)


def rig_training_voltage(period_s: float, training_s: float = 30.0, time_scale: float = 1.0) -> np.ndarray:
    """The identification node's training experiment, one voltage [V] per control period ``period_s`` [s]:
    :func:`identification_voltage`, then a damped sine that leaves the valve synchronised at the centre and a
    0.3 s hold there; ``time_scale`` < 1 compresses the signals in time (faster tests)."""
    dt = period_s / time_scale  # the signals' own time axis
    return joined(dt, identification_voltage(dt, training_s), synchronising_sine(dt),
                  np.full(max(int(0.3 / period_s), 1), CENTRE_VOLTAGE_V))


def validation_voltage(dt: float, duration_s: float = 30.0, amplitude_v: float = 4.5) -> np.ndarray:
    """A validation experiment unlike the training one: synchronisation, eq. 12 as a voltage about 5 V,
    step-and-hold at other levels, multisine at other frequencies."""
    f = validation_shape(time_base(duration_s, dt) + 8.0)
    return joined(dt, synchronising_sine(dt), CENTRE_VOLTAGE_V + amplitude_v * f / np.max(np.abs(f)),
                  step_and_hold_voltage(dt, levels_v=(8.0, 3.0, 6.5, 2.0, 5.5), hold_s=1.5),
                  multisine_voltage(dt, 4.0, (1.0, 5.0, 12.0, 25.0), 3.5),
                  np.full(int(round(0.5 / dt)), CENTRE_VOLTAGE_V))


class ReferenceRamp:
    """Turns reference changes into ramps of fixed duration (the paper's 2 ms steps).

    ``set_target`` starts a ramp from the present value; ``step`` returns the value for the
    next control period: start + (target - start) * i / n for i = 1..n, as ``step_reference_m``.
    """

    def __init__(self, value: float = 0.0, ramp_s: float = 0.0, dt: float = 1e-4):
        self.value = float(value)
        self.set_ramp(ramp_s, dt)
        self._start = self._target = self.value
        self._i = self._n

    def set_ramp(self, ramp_s: float, dt: float) -> None:
        self._n = max(int(round(ramp_s / dt)), 1) if ramp_s > 0 else 1

    def hold(self, value: float) -> None:
        """Jump to ``value`` and stay there (no ramp)."""
        self.value = self._start = self._target = float(value)
        self._i = self._n

    def set_target(self, target: float) -> None:
        self._start, self._target, self._i = self.value, float(target), 0

    def step(self) -> float:
        if self._i < self._n:
            self._i += 1
            self.value = self._start + (self._target - self._start) * self._i / self._n
        return self.value


# ---------------------------------------------------------------------------- reference profiles
# What an operator sends to a running rig (``valve_command``): times [s] from the start and positions [m].
MAX_PROFILE_RATE_HZ = 10_000.0


def _profile_times(duration_s: float, rate_hz: float) -> np.ndarray:
    if not (np.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration must be > 0 s, got {duration_s}")
    if not (np.isfinite(rate_hz) and 0 < rate_hz <= MAX_PROFILE_RATE_HZ):
        raise ValueError(f"rate must lie in (0, {MAX_PROFILE_RATE_HZ:g}] Hz, got {rate_hz}")
    n = int(np.floor(duration_s * rate_hz + 1e-9))
    return np.append(np.arange(n) / rate_hz, duration_s) if n / rate_hz < duration_s else np.arange(n + 1) / rate_hz


def ramp_profile(start_m: float, end_m: float, duration_s: float, rate_hz: float = 100.0):
    """A straight line from ``start_m`` to ``end_m`` [m] over ``duration_s``; (times [s], positions [m])."""
    t = _profile_times(duration_s, rate_hz)
    return t, start_m + (end_m - start_m) * t / duration_s


def sine_profile(amplitude_m: float, frequency_hz: float, duration_s: float, offset_m: float = 0.0,
                 rate_hz: float = 200.0):
    """``offset_m + amplitude_m * sin(2 pi f t)``, ending back at the offset when the duration is a whole
    number of periods; (times [s], positions [m])."""
    if not (np.isfinite(frequency_hz) and 0 < frequency_hz < rate_hz / 2):
        raise ValueError(f"frequency must lie in (0, rate/2 = {rate_hz / 2:g}) Hz, got {frequency_hz}")
    if not np.isfinite(amplitude_m):
        raise ValueError(f"amplitude must be finite, got {amplitude_m}")
    t = _profile_times(duration_s, rate_hz)
    return t, offset_m + amplitude_m * np.sin(2 * np.pi * frequency_hz * t)


PROFILE_UNITS = {"position_m": 1.0, "position_mm": 1e-3, "position_um": 1e-6}   # header name -> metres per unit


def load_profile(path) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``time_s, position_m`` (comma or white space separated, ``#`` comments) from a text file, as
    (times [s], positions [m]); an optional header names the position's unit (``position_m``,
    ``position_mm`` or ``position_um``; without one: metres).  Times from 0 or later and never decreasing.
    ValueError naming the problem (also a header that names no unit: the file's numbers would be guessed)."""
    rows = []
    first = True
    scale = 1.0
    with open(path, encoding="utf8") as f:
        for number, line in enumerate(f, 1):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            try:
                values = [float(x) for x in text.replace(",", " ").split()]
            except ValueError:
                if first:  # a header line: it says the unit
                    first = False
                    names = text.replace(",", " ").split()
                    if len(names) != 2 or names[1] not in PROFILE_UNITS:
                        raise ValueError(f"{path}:{number}: header {text!r}: expected 'time_s, position_m' "
                                         f"(or position_mm, position_um)") from None
                    scale = PROFILE_UNITS[names[1]]
                    continue
                raise ValueError(f"{path}:{number}: not two numbers: {text!r}") from None
            first = False
            if len(values) != 2 or not all(np.isfinite(values)):
                raise ValueError(f"{path}:{number}: expected 'time_s, position_m', got {text!r}")
            rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no 'time_s, position_m' rows")
    a = np.asarray(rows)
    if a[0, 0] < 0 or np.any(np.diff(a[:, 0]) < 0):
        raise ValueError(f"{path}: times must start at 0 s or later and never decrease")
    return a[:, 0], a[:, 1] * scale
