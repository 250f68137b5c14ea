"""Measured records for identification: checks, block means, the held-out split, noise and error figures.

A record is time [s], applied voltage [V] and spool position [um] at one sampling rate.  Nothing here
imports ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Optional

import numpy as np

from ..errors import PiezoValveError
from ..model.dynamics import scipy_signal
from ..model.rate_dependence import rate_terms

__all__ = ["IdentificationError", "Record", "analysis_record", "split_held_out",
           "noise_floor_um", "noise_peak_um", "NOISE_PEAK_WINDOW_S", "FALLING_CORRELATION", "join", "HELD_OUT_FRACTION", "ANALYSIS_RATE_HZ", "SUPPORTED_RATE_HZ",
           "MIN_SAMPLES", "MAX_ANALYSED_S", "read_csv", "CSV_POSITION_COLUMNS"]

HELD_OUT_FRACTION = 0.3      # without a validation record, the last 30 % (in time) is held out (CONTRACT.md)
ANALYSIS_RATE_HZ = 2000.0    # fits run on block means at most this rate (error figures are at the record's rate)
SUPPORTED_RATE_HZ = 1000.0   # below this the paper's G_v (poles near 80 and 380 Hz) is not resolved: a warning says
                             # what the rate cannot show
MIN_SAMPLES = 200
MAX_ANALYSED_S = 100.0       # of a longer record the loop analyses its first this long (its memory and time grow
                             # with what it analyses: about 10 kB per analysed row); the report says what it used
NOISE_PEAK_WINDOW_S = 0.002  # noise_peak_um: the local cubic spans this long (at least 5 samples)
FALLING_CORRELATION = -0.5   # position and voltage correlated below this: the position falls as the drive rises


class IdentificationError(PiezoValveError, ValueError):
    """Data that cannot be identified from (the message says why, in one line)."""


@dataclass(frozen=True)
class Record:
    """A measured record: time [s], applied voltage [V], spool position [um].

    ``block`` is the number of source samples each row averages (1: raw samples); ``source_dt`` [s] is
    the source's sampling period (the models use it to reproduce the source's sample-and-hold).
    """

    time_s: np.ndarray
    voltage_v: np.ndarray
    position_um: np.ndarray
    block: int = 1
    source_dt: Optional[float] = None

    def __post_init__(self):
        t, v, y = (np.asarray(a, float).reshape(-1) for a in (self.time_s, self.voltage_v, self.position_um))
        if not (t.size == v.size == y.size):
            raise IdentificationError(f"record columns differ in length ({t.size}, {v.size}, {y.size})")
        object.__setattr__(self, "time_s", t)
        object.__setattr__(self, "voltage_v", v)
        object.__setattr__(self, "position_um", y)
        if self.source_dt is None and self.block == 1:
            object.__setattr__(self, "source_dt", self.dt)

    @classmethod
    def from_rows(cls, rows: np.ndarray) -> "Record":
        """From ``samples`` rows (time [s], voltage [V], position [m])."""
        rows = np.asarray(rows, float)
        if rows.ndim != 2 or rows.shape[1] < 3:
            raise IdentificationError(f"samples rows must be (N, 3) or wider, got shape {rows.shape}")
        return cls(rows[:, 0], rows[:, 1], rows[:, 2] * 1e6)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @cached_property
    def input_rate_terms(self) -> np.ndarray:
        """(N, k) the functions of the input rate a rate-dependent GPIM's thresholds grow with
        (``rate_dependence.rate_terms``, the valve at rest before the first sample): functions of the voltage alone,
        kept with the record (every prediction on it builds a context of its own: a session's start is estimated
        with a hundred of them)."""
        return rate_terms(self.voltage_v, self.dt)

    @cached_property
    def dt(self) -> float:
        """Sampling period [s] (median spacing)."""
        return float(np.median(np.diff(self.time_s))) if len(self) > 1 else float("nan")

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.dt

    @property
    def undersampled(self) -> bool:
        """Sampled below SUPPORTED_RATE_HZ (0.1 % below it, so a jittered 1 kHz time column counts as 1 kHz)."""
        return self.rate_hz < SUPPORTED_RATE_HZ * (1.0 - 1e-3)

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0] + self.dt) if len(self) > 1 else 0.0

    @property
    def range_um(self) -> float:
        return float(np.ptp(self.position_um)) if len(self) else 0.0

    def first(self, seconds: float) -> "Record":
        """The record's samples up to ``seconds`` [s] after its first (all of it when shorter)."""
        stop = int(np.searchsorted(self.time_s, self.time_s[0] + seconds, side="right"))
        return self if stop >= len(self) else self.slice(0, stop)

    def slice(self, start: int, stop: Optional[int] = None) -> "Record":
        return Record(self.time_s[start:stop], self.voltage_v[start:stop], self.position_um[start:stop],
                      self.block, self.source_dt)

    def check(self, what: str = "record", min_samples: int = MIN_SAMPLES, min_reversals: int = 2) -> "Record":
        """Raise IdentificationError unless the record can be fitted; returns it (time-ordered).

        ``min_reversals`` is how often the voltage must change direction: 2 (a full cycle) for a record a
        model is fitted on or started from, 1 for a held-out tail that continues the fitted record (the
        operators keep their memory, so one reversal already tests it).
        """
        if len(self) < min_samples:
            raise IdentificationError(f"{what} has {len(self)} samples; at least {min_samples} are needed")
        bad = ~(np.isfinite(self.time_s) & np.isfinite(self.voltage_v) & np.isfinite(self.position_um))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise IdentificationError(f"{what} has {int(bad.sum())} non-finite samples (first at row {k}, "
                                      f"t={float(self.time_s[k]):.6g} s)")
        if np.any(np.diff(self.time_s) <= 0):
            order = np.argsort(self.time_s, kind="stable")
            t = self.time_s[order]
            if np.any(np.diff(t) <= 0):
                raise IdentificationError(f"{what} has repeated sample times")
            return Record(t, self.voltage_v[order], self.position_um[order]).check(what, min_samples, min_reversals)
        gaps = np.diff(self.time_s)
        if float(np.max(gaps)) > 10.0 * self.dt:
            k = int(np.argmax(gaps))
            raise IdentificationError(f"{what} has a gap of {float(gaps[k]):.4g} s at t={float(self.time_s[k]):.6g} s "
                                      f"({float(gaps[k]) / self.dt:.0f} sample periods): record it again or cut it there")
        v_span = float(np.ptp(self.voltage_v))
        v_scale = max(float(np.max(np.abs(self.voltage_v))), 1e-12)
        if v_span <= 1e-6 * v_scale or v_span == 0.0:
            raise IdentificationError(f"{what}: the voltage is constant ({float(self.voltage_v[0]):.6g} V): "
                                      "no excitation to fit a hysteresis model")
        dv = np.diff(self.voltage_v)
        reversals = np.count_nonzero(np.diff(np.sign(dv[dv != 0])))
        if reversals < min_reversals:
            need = "at least one full cycle" if min_reversals >= 2 else "a reversal to test the model's memory"
            raise IdentificationError(f"{what}: the voltage reverses direction {reversals} time(s); it needs {need}")
        if self.range_um <= 0:
            raise IdentificationError(f"{what}: the position is constant: nothing to fit")
        return self

    def check_rising(self, what: str = "record") -> "Record":
        """Raise IdentificationError when the position falls as the voltage rises over the record (their
        correlation below ``FALLING_CORRELATION``): a GPIM with nonnegative weights cannot fit that valve.
        For a whole training record, where the excitation dominates (in a short stretch of closed-loop
        operation a controller countering a drift moves the two apart)."""
        correlation = float(np.corrcoef(self.voltage_v, self.position_um)[0, 1])
        if correlation < FALLING_CORRELATION:
            raise IdentificationError(
                f"{what}: the position falls as the voltage rises (correlation {correlation:+.2f}); the GPIM "
                "describes a valve whose position rises with its drive: flip the sign of the position (the "
                "sensor's mounting, or the backend's gain) or of the drive (an inverting amplifier) and record again")
        return self


CSV_POSITION_COLUMNS = {"position_m": 1e6, "position_um": 1.0}   # header name -> factor to um


def read_csv(path) -> Record:
    """A record from a CSV file with a header naming ``time_s``, ``voltage_v`` and ``position_m`` or
    ``position_um`` (any order, other columns ignored; ``#`` starts a comment line).  Raises
    IdentificationError with a one-line reason for a missing file, column or number."""
    import csv

    try:
        with open(path, newline="") as f:
            lines = [line for line in f if line.strip() and not line.lstrip().startswith("#")]
    except OSError as exc:
        raise IdentificationError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if not lines:
        raise IdentificationError(f"{path}: no header and no samples")
    reader = csv.reader(lines)
    header = [h.strip() for h in next(reader)]
    position = [h for h in header if h in CSV_POSITION_COLUMNS]
    missing = [h for h in ("time_s", "voltage_v") if h not in header] + ([] if position else ["position_m or position_um"])
    if missing:
        raise IdentificationError(f"{path}: the header ({', '.join(header)}) lacks {', '.join(missing)}")
    cols = [header.index(h) for h in ("time_s", "voltage_v", position[0])]
    rows = []
    for k, row in enumerate(reader, start=2):
        try:
            rows.append([float(row[c]) for c in cols])
        except (ValueError, IndexError):
            raise IdentificationError(f"{path}: data row {k} is not three numbers in those columns: "
                                      f"{','.join(row)[:80]!r}") from None
    if not rows:
        raise IdentificationError(f"{path}: a header but no samples")
    a = np.asarray(rows)
    return Record(a[:, 0], a[:, 1], a[:, 2] * CSV_POSITION_COLUMNS[position[0]])


def join(first: Record, second: Record) -> Record:
    """``second`` appended to ``first`` (same rate; used to run a model on through a held-out tail)."""
    return Record(np.concatenate((first.time_s, second.time_s)), np.concatenate((first.voltage_v, second.voltage_v)),
                  np.concatenate((first.position_um, second.position_um)), first.block, first.source_dt)


def analysis_record(record: Record, max_rate_hz: float = ANALYSIS_RATE_HZ) -> Record:
    """Block means down to at most ``max_rate_hz`` (a trailing partial block is dropped).

    Hysteresis is rate-independent and the linear dynamics carry over exactly (block means commute
    with a linear filter); the models reproduce the source's sample-and-hold from ``source_dt``.
    """
    dt = record.dt
    k = max(int(math.floor(1.0 / (max_rate_hz * dt) + 1e-9)), 1) if math.isfinite(max_rate_hz) else 1
    if k == 1:
        return record
    n = len(record) // k * k

    def blocks(a):
        return a[:n].reshape(-1, k).mean(axis=1)
    return Record(blocks(record.time_s), blocks(record.voltage_v), blocks(record.position_um), k * record.block,
                  record.source_dt)


def split_held_out(record: Record, fraction: float = HELD_OUT_FRACTION, multiple: int = 1) -> int:
    """Index where the held-out last ``fraction`` (in time) of ``record`` starts (a multiple of ``multiple``
    samples, so block means of both parts line up)."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"held-out fraction must lie in (0, 1), got {fraction}")
    cut = record.time_s[0] + (1.0 - fraction) * (record.time_s[-1] - record.time_s[0])
    k = int(np.searchsorted(record.time_s, cut))
    return k // multiple * multiple


def noise_floor_um(position_um: np.ndarray) -> float:
    """White-noise RMS [um] of a signal from its second differences (median absolute deviation: the smooth
    part and occasional fast moves do not count).  Applied to a model's residual it measures the noise at
    that signal's own rate."""
    y = np.asarray(position_um, float)
    if y.size < 5:
        return float("nan")
    d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return 1.4826 * mad / math.sqrt(6.0)


def noise_peak_um(position_um: np.ndarray, dt: float, window_s: float = NOISE_PEAK_WINDOW_S) -> float:
    """Largest deviation [um] of a measured signal from its own local cubic over ``window_s`` (Savitzky-Golay;
    at least 5 samples): the peak its sensor noise alone puts there.  A model's error cannot peak lower on
    that signal unless the model follows the noise within the window; on a smooth record (no steps faster
    than the window) it is the floor of the held-out peak."""
    y = np.asarray(position_um, float)
    window = max(5, int(round(window_s / dt)) | 1)
    if y.size < window:
        return float("nan")
    return float(np.max(np.abs(y - scipy_signal().savgol_filter(y, window, 3))))
