"""What the residual loop's stages hand each other (``residual``: the face), and the measures of a held-out
residual they decide with.  Nothing here imports ROS."""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

import numpy as np

from .fitting import PaperFit
from .noise import NoiseFloor
from .report import IdentificationReport
from .records import noise_floor_um
from ..metrics import rms
from .valve_model import ValveModel
from .fitting import FitCache
from .records import Record
from .search import NoiseLevels, Score
from .split import SessionStart, Split
from .thresholds import CAPACITY_TREND_DEGREE, UNEXPLAINED_NOISE_RATIO, PEAK_BLOCK_S, PEAK_RANK, MIN_STRUCTURE_PCT


def _ordinal(k: int) -> str:
    return {1: "1st", 2: "2nd", 3: "3rd"}.get(k, f"{k}th")


def _structure(error: np.ndarray, dt: float, noise_um: float, range_um: float) -> dict:
    """Size and shape of what remains in a held-out residual ``error`` [um] sampled every ``dt`` [s], against the
    sensor noise at that rate ``noise_um``: its RMS above the noise (structured), its lag-1 autocorrelation and its
    strongest spectral line (``noise_here_um``: the residual's own white-noise level from its second differences,
    for the reader: where the model misses fast structure it is not the sensor's)."""
    total = rms(error)
    structured = math.sqrt(max(total ** 2 - noise_um ** 2, 0.0))
    ec = error - error.mean()
    r1 = float(np.dot(ec[1:], ec[:-1]) / max(np.dot(ec, ec), 1e-30))
    spectrum = np.abs(np.fft.rfft(ec * np.hanning(ec.size)))
    freqs = np.fft.rfftfreq(ec.size, dt)
    k = int(np.argmax(spectrum[1:]) + 1) if spectrum.size > 1 else 0
    share = float(spectrum[k] ** 2 / max(np.sum(spectrum[1:] ** 2), 1e-30)) if k else 0.0
    return {"rms_um": total, "structured_rms_um": structured, "noise_here_um": noise_floor_um(error), "lag1": r1,
            "line_hz": float(freqs[k]) if k else 0.0, "line_share": share,
            "ratio_to_noise": structured / max(noise_um, 1e-12),
            "pct_of_range": 100.0 * structured / range_um if range_um > 0 else 0.0}


def _unexplained_by_rms(structure: dict) -> bool:
    """Whether a held-out residual's ``_structure`` holds structure no effect explains, by its RMS: above
    UNEXPLAINED_NOISE_RATIO times the sensor noise and above MIN_STRUCTURE_PCT of the range."""
    return structure["ratio_to_noise"] > UNEXPLAINED_NOISE_RATIO and structure["pct_of_range"] > MIN_STRUCTURE_PCT


def _peak_structure(e_full: np.ndarray, dt: float, noise_um: float, range_um: float) -> dict:
    """How far a held-out residual's peaks (record rate) stand above what the sensor noise alone gives.

    The residual is cut into ``PEAK_BLOCK_S`` blocks; the ``PEAK_RANK``-th largest block peak (so a lone
    outlier in the data cannot decide) is compared with the largest |noise| expected over the samples,
    noise * sqrt(2 ln N).  Backlash and dead zones leave little RMS but peaks at every reversal or
    crossing; a catalogue effect the model lacks raises them too."""
    n = e_full.size
    block = max(int(round(PEAK_BLOCK_S / dt)), 1)
    m = n // block
    if m < PEAK_RANK or not noise_um > 0:
        return {"peak_um": 0.0, "expected_noise_peak_um": 0.0, "peak_ratio": 0.0, "peak_pct_of_range": 0.0}
    peaks = np.abs(e_full[:m * block]).reshape(m, block).max(axis=1)
    ranked = float(np.partition(peaks, m - PEAK_RANK)[m - PEAK_RANK])
    expected = noise_um * math.sqrt(2.0 * math.log(n))
    return {"peak_um": ranked, "expected_noise_peak_um": expected, "peak_ratio": ranked / expected,
            "peak_pct_of_range": 100.0 * ranked / range_um if range_um > 0 else 0.0}


@dataclass(frozen=True)
class CapacityFit:
    """One GPIM size of the capacity choice: its label, operators, fitted model, and held-out RMS as it is and
    about its polynomial trend of degree CAPACITY_TREND_DEGREE [um]."""
    label: str
    operators: int
    model: ValveModel
    held_out_um: float
    about_trend_um: float

    def score(self, about_trend: bool) -> float:
        """What the sizes are compared on [um]."""
        return self.about_trend_um if about_trend else self.held_out_um


@dataclass(frozen=True)
class StartChoice:
    """Stage 1: the operators' state at the record's first sample."""
    first: ValveModel          # the model fitted from the chosen start (MID_CAPACITY operators, G_v's poles fitted)
    chosen: str                # rest, cycled, estimated or wiped
    held_out_rms_um: dict      # each start tried -> the held-out RMS fitted from it [um]
    assumed: dict              # what was assumed (in words), where the fit starts, what was estimated


@dataclass(frozen=True)
class CapacityChoice:
    """Stage 1b: the GPIM's number of thresholds, and the baseline fitted with it."""
    fits: tuple                # CapacityFit of every size tried
    label: str                 # the chosen one's
    about_trend: bool          # the sizes were compared about their held-out error's trend (TREND_DOMINANCE)
    chosen_on: str             # what they were compared on, in words
    baseline: ValveModel
    paper: PaperFit            # the paper's 5-parameter fit
    effects_grid: Optional[str] = None   # the size the effects are fitted on, where chosen again with them in

    def chosen(self) -> CapacityFit:
        return next(c for c in self.fits if c.label == self.label)


class LoopState(Protocol):
    """What every stage shares of one run of the loop (``residual._Loop`` holds it): the records and their split,
    the noise, the caches, the pools and the log."""
    split: Split
    noise: float                # the sensor noise [um] decisions compare with (at least RESOLUTION_SHARE of the range)
    levels: NoiseLevels         # ... at the record's rate and at the analysis rate
    range_val: float            # the held-out output's range [um]
    cache: FitCache
    polishes: dict
    log: Callable[[str], None]
    pool: ThreadPoolExecutor

    @property
    def fit(self) -> Record: ...
    def each(self, jobs: list[Callable[[], object]]) -> list: ...
    def each_form(self, jobs: list[Callable[[], object]]) -> list: ...
    def each_beside(self, jobs: list[Callable[[], object]]) -> list: ...
    def session(self, model: ValveModel, on: Optional[Split] = None) -> Optional[SessionStart]: ...
    def error(self, model: ValveModel, on: Optional[Split] = None, full: bool = False) -> np.ndarray: ...
    def held_out(self, model: ValveModel) -> Score: ...


@dataclass(frozen=True)
class Remains:
    """Stage 4: what the final model leaves in the held-out residual."""
    structure: dict
    unexplained: bool
    seen: str                  # in words


def _on_pool(pool: ThreadPoolExecutor, jobs: list[Callable[[], object]]) -> list:
    """Independent jobs on ``pool``, their results in order."""
    return [f.result() for f in [pool.submit(job) for job in jobs]]


def _beside(pool: ThreadPoolExecutor, jobs: list[Callable[[], object]]) -> list:
    """Independent jobs, their results in order: the first in this thread, the others handed to ``pool`` and each run
    here instead where no thread of the pool has taken it by the time this thread comes to it.  So a job running on
    any pool can hand work to any pool without waiting for a thread that waits for it: the work runs beside it
    where a thread is free, else after it, here (the jobs must not wait for this thread's caller)."""
    if len(jobs) <= 1:
        return [job() for job in jobs]
    futures = [pool.submit(job) for job in jobs[1:]]
    try:
        results = [jobs[0]()]
        for job, future in zip(jobs[1:], futures):
            results.append(job() if future.cancel() else future.result())
    except BaseException:
        for future in futures:
            future.cancel()
        raise
    return results


def _summary_line(report: IdentificationReport, floor: NoiseFloor) -> str:
    """The report's story in one line: what was added, whether structure remains, the held-out RMS, peak and fit
    before and after at the record's rate, and where the noise floor came from."""
    b, f = report.baseline.validate, report.final.validate
    noise = (f"noise floor {floor.rms_um:.4f} um from {floor.source}" if floor.known
             else "noise floor unknown (no holds, repeated periods or input-free band)")
    return (f"added: {', '.join(report.effects_added) or 'nothing'}; unexplained: {str(report.unexplained).lower()}; "
            f"held-out RMS {b.rms_um:.4f} -> {f.rms_um:.4f} um, peak {b.peak_pct:.2f} -> {f.peak_pct:.2f} % of the "
            f"range, fit {b.fit_pct:.1f} -> {f.fit_pct:.1f} % at {report.sample_rate_hz:.0f} Hz; {noise}")


def _set_named(effects: list[str]) -> str:
    """A set of effects in a log line: their names, or "the baseline" for none."""
    return ", ".join(effects) or "the baseline"


def _detrended(error: np.ndarray) -> np.ndarray:
    """``error`` minus its least-squares polynomial in time (sample index) of degree CAPACITY_TREND_DEGREE."""
    t = np.linspace(-1.0, 1.0, error.size)
    basis = np.vander(t, CAPACITY_TREND_DEGREE + 1)
    coefs, *_ = np.linalg.lstsq(basis, error, rcond=None)
    return error - basis @ coefs
