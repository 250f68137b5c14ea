"""Metrics exactly as the paper defines them, plus tracking error figures.

Step: settling time = last time outside +-5 % of the step amplitude around the target
(measured from the start of the ramp); overshoot = peak beyond the target as % of the amplitude.
The band exit time is the settling time resolved below the sample period (the last crossing into the band,
interpolated between the samples around it): the tuner ranks by it, where the paper's settling time moves
in whole periods and leaves a search on flat steps.
Frequency response: gain and phase of the fundamental (correlation over whole periods);
-3 dB and -90 deg frequencies (first crossing, log-interpolated); resonant peak = max gain in dB
(0 when the gain never exceeds the low-frequency gain).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["rms", "StepMetrics", "step_metrics", "fundamental", "BandwidthMetrics", "bandwidth_metrics",
           "ErrorFigures", "error_figures"]


@dataclass(frozen=True)
class StepMetrics:
    settling_time_s: float
    overshoot_pct: float
    final_error_um: float
    band_exit_s: float = math.nan   # the last entry into the band, interpolated between samples [s]


def step_metrics(y_m: np.ndarray, start_index: int, start_um: float, end_um: float, dt: float,
                 band: float = 0.05) -> StepMetrics:
    """Settling time [s], overshoot [%] and band exit time [s] of a step response ``y_m`` [m] whose ramp starts at
    ``start_index``."""
    y = np.asarray(y_m, float)[start_index:] * 1e6
    amplitude = end_um - start_um
    if amplitude == 0:
        raise ValueError("step amplitude is zero")
    beyond_band = np.abs(y - end_um) - band * abs(amplitude)       # > 0: outside [um]
    outside = np.flatnonzero(beyond_band > 0)
    if outside.size == 0:
        settling = exit_s = 0.0
    else:
        last = int(outside[-1])
        settling = (last + 1) * dt
        exit_s = settling
        if last + 1 < y.size:       # crossed into the band between samples last and last + 1
            a, b = beyond_band[last], beyond_band[last + 1]
            exit_s = (last + a / (a - b)) * dt
    beyond = (y - end_um) * np.sign(amplitude)
    overshoot = max(float(beyond.max()), 0.0) / abs(amplitude) * 100.0
    return StepMetrics(float(settling), overshoot, float(y[-1] - end_um), float(exit_s))


def fundamental(x: np.ndarray, frequency_hz: float, dt: float) -> complex:
    """Complex amplitude of the component at ``frequency_hz`` (x should span whole periods)."""
    x = np.asarray(x, float)
    t = np.arange(x.size) * dt
    basis = np.exp(-2j * np.pi * frequency_hz * t)
    return complex(2.0 * np.mean((x - x.mean()) * basis))


@dataclass(frozen=True)
class BandwidthMetrics:
    f_3db_hz: float
    f_90deg_hz: float
    resonant_peak_db: float


def _crossing(freqs: np.ndarray, values: np.ndarray, level: float) -> float:
    below = np.flatnonzero(values < level)
    if below.size == 0:
        return float("nan")
    k = int(below[0])
    if k == 0:
        return float(freqs[0])
    f0, f1 = np.log(freqs[k - 1]), np.log(freqs[k])
    v0, v1 = values[k - 1], values[k]
    frac = (v0 - level) / (v0 - v1)
    return float(np.exp(f0 + frac * (f1 - f0)))


def bandwidth_metrics(freqs_hz: np.ndarray, response: np.ndarray) -> BandwidthMetrics:
    """From a complex frequency response (output/demand), lowest frequency first."""
    freqs = np.asarray(freqs_hz, float)
    h = np.asarray(response, complex)
    gain_db = 20 * np.log10(np.abs(h) / np.abs(h[0]))
    phase = np.degrees(np.unwrap(np.angle(h)))
    phase -= 360.0 * np.round(phase[0] / 360.0)
    return BandwidthMetrics(_crossing(freqs, gain_db, -3.0), _crossing(freqs, phase, -90.0),
                            max(float(gain_db.max()), 0.0))


def rms(e: np.ndarray) -> float:
    """Root mean square of ``e`` (0 for an empty array)."""
    return float(np.sqrt(np.mean(e * e))) if e.size else 0.0


@dataclass(frozen=True)
class ErrorFigures:
    """The error of a prediction (a model against a record) or of a tracking run (the position against its
    reference): RMS and peak [um], the peak as % of a range, and the fit as NRMSE % (MATLAB ``compare``'s:
    100 (1 - |e| / |y - mean y|), 100 = perfect, 0 = no better than the mean)."""

    rms_um: float = field(metadata={"doc": "RMS of the error [um]"})
    peak_um: float = field(metadata={"doc": "largest |error| [um]"})
    peak_pct: float = field(metadata={"doc": "peak_um as % of the range"})
    fit_pct: float = field(metadata={"doc": "NRMSE fit, 100 (1 - |e| / |y - mean y|) [%]: 100 perfect, 0 no better "
                                            "than the mean (MATLAB compare's)"})

    def rounded(self) -> "ErrorFigures":
        """The figures as reports give them (to 1e-6 um / %, the fit to 1e-4 %)."""
        return ErrorFigures(round(self.rms_um, 6), round(self.peak_um, 6), round(self.peak_pct, 6),
                            round(self.fit_pct, 4))

    def as_dict(self) -> dict:
        return asdict(self.rounded())


def error_figures(actual_um: np.ndarray, predicted_um: np.ndarray, range_um: float) -> ErrorFigures:
    """:class:`ErrorFigures` of ``actual_um - predicted_um`` (same shape, [um]); ``range_um`` the range the
    peak is a share of (the measured or demanded span)."""
    actual = np.asarray(actual_um, float)
    err = actual - np.asarray(predicted_um, float)
    if not err.size:
        return ErrorFigures(0.0, 0.0, float("nan"), float("nan"))
    peak = float(np.max(np.abs(err)))
    spread = float(np.linalg.norm(actual - np.mean(actual)))
    fit = 100.0 * (1.0 - float(np.linalg.norm(err)) / spread) if spread > 0 else float("nan")
    return ErrorFigures(float(np.sqrt(np.mean(err * err))), peak, peak / range_um * 100.0 if range_um > 0 else float("nan"),
                        fit)
