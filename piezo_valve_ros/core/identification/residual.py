"""The residual loop: fit the paper's model, find what it lacks, add it, prove the gain on held-out data.

How it decides (every figure on data the fit has not seen: a validation record, or the last
``HELD_OUT_FRACTION`` of the training record, through which the model runs on with its memory):

1. **Baseline capacity first.**  The operators' state at the record's first sample is rest, cycled,
   estimated from the first rows (``initial_state.estimate_state``: the valve rested at another voltage, as in a
   closed-loop record, or came back from an excursion; a validation record's own start likewise), or,
   when none fits by ``WIPE_GAIN`` and a state before the record explains the rows before the wipe
   (``WIPE_STATE_GAIN``: a slow drift shows there too, and no state explains it), unknown: the fit then
   starts where the input has wiped it out (``split.Split.after_wipe``).  The
   baseline is the paper's model, GPIM followed by a second-order G_v with unity DC gain.  G_v's poles are fitted to the record (the paper's G_v as start, and as fallback
   when the record cannot determine them); the GPIM's number of thresholds is chosen on held-out data
   among ``CAPACITY_OPERATORS`` (and the grid of the paper's 5-parameter fit; then ``CAPACITY_EXTENSION`` while
   the largest keeps winning).  Only structure the best
   baseline cannot fit may be blamed on an effect.
2. **Effects, alone and in combination.**  Every subset of the catalogue is fitted from the baseline in
   one linear solve each (the effects' search columns, their nonlinear structures to first order) and
   scored on held-out data.  A subset is *supported* when each of its effects, removed last, raises the
   held-out RMS: adding it last cuts the held-out RMS by at least ``GAIN_THRESHOLD`` and explains an RMS
   of at least ``MIN_EFFECT_NOISE_RATIO`` times the sensor noise.  The supported subset with the lowest
   held-out error wins, so effects that mask each other (neither pays alone) are found together.
3. **Confirmation.**  The winning subset is refitted exactly (nonlinear structures, G's poles) and each
   effect's support is checked again by an exact drop-one refit; an effect that fails is dropped and the
   rest checked again.  Then every other effect the linear search credited with at least
   ``EXACT_CHECK_GAIN`` is refitted exactly on top (first-order proxies underrate a large nonlinear
   structure); the best supported one joins and all are confirmed again.  G_v's poles are then fitted
   again through the effects found (``fitting.refit_poles_with_effects``: a fast creep bends the
   baseline's) and kept when the held-out error does not rise.  The final model is never worse on
   held-out data than the baseline.  Where it names two effects or more and a smaller GPIM scored within
   ``CAPACITY_REVISIT`` of the chosen one (a knife edge), an effect may stand in for the grid (a grid that fits
   a symmetric baseline best leaves part of an asymmetric valve's envelopes to creep): on the smaller one the
   story less each effect is refitted, and where the best leaves a held-out RMS within ``CAPACITY_TOLERANCE`` of
   the story's, step 3 runs again from it (``revisit_capacity``).  A story that names a part of the first
   one's effects and explains as much replaces it.  Likewise where it names asymmetry: a descending envelope's
   shift alone is a symmetric loop on moved thresholds, so the story less asymmetry is refitted on the chosen
   grid moved so (``revisit_placement``).
4. **Unexplained.**  The final held-out residual's structured part (its RMS above the noise measured
   on the residual itself, at the analysis rate) is compared with the sensor noise at the record's rate:
   above ``UNEXPLAINED_NOISE_RATIO`` times it, structure remains that no catalogue effect explains.  So
   does a residual whose peaks stand ``PEAK_NOISE_RATIO`` times above what the noise gives (``_peak_structure``:
   backlash and dead zones leave little RMS but a peak at every reversal).  The report says its size, its
   peaks, its strongest spectral line and which effect comes closest.

Held-out error figures are at the record's own rate; fits and decisions use block means at up to
``ANALYSIS_RATE_HZ`` (extra keys give those figures too).  Nothing here imports ROS.
"""
from __future__ import annotations

import itertools
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from .effects import CATALOGUE, Effect
from .fitting import FitCache, PaperFit, fit_model, fit_paper_gpim, refit_poles_with_effects, with_poles, uniform_thresholds
from ..model.hysteresis import GPIM
from .noise import NoiseFloor, estimate_noise_floor
from .initial_state import ESTIMATE_ROUNDS, ESTIMATE_STATE_GAIN, WIPE_STATE_GAIN, estimate_state, session_start
from .report import (Baseline, BaselineFits, Capacity, ConfirmRound, Decision, Final, IdentificationReport,
                     Indistinguishable, NoiseEstimate, NoiseFloorReport, ResidualStructure, SearchRow, Session, to_json)
from .records import (ANALYSIS_RATE_HZ, HELD_OUT_FRACTION, MAX_ANALYSED_S, SUPPORTED_RATE_HZ, Record, noise_floor_um,
                      noise_peak_um)
from .search import (MAX_LOSS_RATIO, GAIN_THRESHOLD, MIN_EFFECT_NOISE_RATIO, PEAK_TOLERANCE, NoiseLevels, Score, SubsetSearch, Support,
                     no_room_because,
                     percent, room_for_an_effect, support, unsupported_because)
from .split import WIPE_MARGIN, SessionStart, Split, split_records
from ..blas import one_blas_thread
from ..defaults import analysis_threads
from ..metrics import ErrorFigures, error_figures, rms
from ..model.dynamics import describe_dynamics
from .valve_model import REST, InitialState, ValveModel

__all__ = ["analyse", "Analysis", "Split", "GAIN_THRESHOLD", "MIN_EFFECT_NOISE_RATIO", "UNEXPLAINED_NOISE_RATIO",
           "CAPACITY_OPERATORS", "CAPACITY_EXTENSION", "HELD_OUT_FRACTION", "MID_CAPACITY"]

CAPACITY_OPERATORS = (12, 18, 27, 40, 60)   # GPIM sizes tried for the baseline
CAPACITY_EXTENSION = (90, 135)              # ... then these, one at a time, while the largest so far is the best
                                            # by more than CAPACITY_TOLERANCE over the size below it
MID_CAPACITY = 27                           # the size G_v's poles are first fitted with
CAPACITY_TOLERANCE = 0.02                   # a smaller GPIM within 2 % of the best held-out RMS is preferred
CAPACITY_REVISIT = 0.05                     # a smaller size within this share of the chosen one's score is a
                                            # knife edge: the effects are chosen again on it (_Loop.revisit_capacity)
PLACEMENT_SHIFT_SHARE = 0.5                 # an asymmetry whose shift is at least this share of its envelope's
                                            # departure may be the thresholds' placement: it is tried
                                            # (_Loop.revisit_placement)
TREND_DOMINANCE = 0.5                       # when the best size's held-out error about its quadratic trend is
                                            # below this share of its RMS, a trend (a drift) swamps what the
                                            # sizes differ in, and they are compared about their trends
CAPACITY_TREND_DEGREE = 2                   # ... of this degree in time
INITIAL_STATE_TOLERANCE = 0.02              # "cycled" replaces "rest" only if it cuts the held-out RMS by more
WIPE_GAIN = 0.1                             # fitting only after the wipe must cut the held-out RMS by >= 10 %
HELD_OUT_RANGE_MARGIN = 0.05                # held-out data driven beyond the fit part's voltage range by more
                                            # than this share of it: warned (the fit cannot know that range)
KNOWN_MIN_SHARE = 0.1                       # ... and where they leave it after this share of their rows, an effect
                                            # must not do worse on the rows before (search.support)
RESOLUTION_SHARE = 1e-6                     # a record's noise is taken as at least this share of its range
UNEXPLAINED_NOISE_RATIO = 2.0               # structured residual RMS above this many noise RMS: unexplained
PEAK_NOISE_RATIO = 2.5                      # held-out peaks above this many times the noise's: unexplained
START_MOTION_MAX_S = 0.1                    # a validation session's start in motion: within its first this long ...
START_MOTION_MAX_SHARE = 0.01               # ... and this share of it ...
START_MOTION_FIRST_ROWS = 3                 # ... starting within its first rows ...
START_MOTION_RATIO = 5.0                    # ... the rows whose error stands this many spreads off are left out
MAD_TO_SIGMA = 1.4826                       # the median absolute deviation of a normal variable times this: its sigma
SPREAD_SHARE = 0.5                          # a held-out RMS of this share of the held-out output's own standard
                                            # deviation (a fit of 50 % or less) is unexplained, whatever else
PEAK_BLOCK_S = 0.005                        # ... judged on the PEAK_RANK-th largest peak of blocks this long
PEAK_RANK = 3
MIN_STRUCTURE_PCT = 0.01                    # ... and above this % of the range (noise-free records)
CONFIRM_ROUNDS = 4                          # exact drop-one rounds at most
SEPARATION_SHARE = 0.8                       # an effect that does this share of an added one's work in its
                                            # place: the record cannot tell the two apart (reported)
EXACT_CHECK_GAIN = 0.05                     # effects the linear search credits with >= 5 % are checked exactly ...
EXACT_ALL_ROWS = 20000                      # ... every effect, on a fit record of at most this many rows ...
DELAY_STEPS = (-2, -1, 1, 2, 3)             # a dead time chosen on held-out data: the fitted one and these many
                                            # analysis samples from it
SEARCH_TRUST = 0.2                          # ... or where the exact refit of its set does worse than its figure by more
                                            # than this share, or delivers less than 1 - this of the cut it promised


def _ordinal(k: int) -> str:
    return {1: "1st", 2: "2nd", 3: "3rd"}.get(k, f"{k}th")


# --------------------------------------------------------------------------- result
@dataclass
class Analysis:
    report: IdentificationReport   # report.json's content: ``report.to_json()``
    baseline: ValveModel
    final: ValveModel
    split: Split
    drop_one: dict = field(default_factory=dict)   # effect name -> the final model refitted without it
    sessions: dict = field(default_factory=dict)   # id(model) -> (model, its start and offset on a validation record)

    def session(self, model: ValveModel) -> Optional[SessionStart]:
        """``model``'s start and offset on a separate validation record (None on a held-out tail): as the loop
        estimated it, or estimated the same way (``initial_state.session_start``)."""
        if self.split.held_out:
            return None
        if id(model) not in self.sessions:
            self.sessions[id(model)] = (model, session_start(model, self.split.score, self.split.score_t0))
        return self.sessions[id(model)][1]

    def held_out_error(self, model: Optional[ValveModel] = None, full: bool = False) -> np.ndarray:
        """The final model's (or ``model``'s) held-out error [um] as every decision and the report take it (analysis
        rate, or the record's own with ``full``): on a validation record from the model's own start, less the
        session's offset."""
        model = self.final if model is None else model
        return self.split.held_out_error(model, full, self.session(model))


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


def analyse(train_full: Record, validate_full: Optional[Record] = None, *, max_rate_hz: float = ANALYSIS_RATE_HZ,
            log: Callable[[str], None] = lambda s: None, threads: Optional[int] = None) -> Analysis:
    """Fit, diagnose and extend; ``validate_full`` None holds out the last ``HELD_OUT_FRACTION`` of the record.

    Independent refits run on ``threads`` threads (the result does not depend on how many; None:
    ``defaults.analysis_threads()``, which PIEZO_ANALYSIS_THREADS sets).  BLAS runs on
    one thread meanwhile (``core.blas``): its threads gain nothing on these tall, narrow least-squares problems
    and, beside other busy processes, oversubscribe the cores (measured 3-4x slower on a loaded 2-core machine).
    """
    if threads is None:
        threads = analysis_threads()
    elif threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    # the forms of one refit run on a pool of their own: a refit on the first pool waits for them there
    with one_blas_thread(), \
            ThreadPoolExecutor(threads, thread_name_prefix="refit") as pool, \
            ThreadPoolExecutor(threads, thread_name_prefix="form") as forms_pool:
        return _Loop(train_full, validate_full, max_rate_hz, log, pool, forms_pool).run()


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


@dataclass(frozen=True)
class Story:
    """Stages 2 and 3 on one baseline: the effects added and the models that show them."""
    baseline: ValveModel
    final: ValveModel
    added: list                # effect names, in catalogue order
    drop_one: dict             # effect name -> the final model refitted without it
    verdicts: dict             # effect name -> its exact drop-one support figures
    confirm_log: list[ConfirmRound]   # the exact refits and drop-one checks, round by round
    choice: "_EffectChoice"    # its search and refits (the report's diagnosis and alternatives use them)


@dataclass(frozen=True)
class Remains:
    """Stage 4: what the final model leaves in the held-out residual."""
    structure: dict
    unexplained: bool
    seen: str                  # in words


def _on_pool(pool: ThreadPoolExecutor, jobs: list[Callable[[], object]]) -> list:
    """Independent jobs on ``pool``, their results in order."""
    return [f.result() for f in [pool.submit(job) for job in jobs]]


class _Loop:
    """One run of the residual loop on one pair of records; ``run`` takes the stages of the module's
    docstring in order and returns the :class:`Analysis`.  Each stage returns what it found (``StartChoice``,
    ``CapacityChoice``, ``Story``, ``Remains``) to the stages after it; the instance holds what they all share:
    the records and their split (``split`` is replaced once, as the initial state is settled: the cut after
    the wipe), the noise, the caches and the warnings."""

    def __init__(self, train_full: Record, validate_full: Optional[Record], max_rate_hz: float,
                 log: Callable[[str], None], pool: ThreadPoolExecutor, forms_pool: ThreadPoolExecutor):
        self.started = time.monotonic()
        self.log, self.pool, self.forms_pool = log, pool, forms_pool
        self.warnings: list[str] = []
        self.known_rows: Optional[int] = None   # held-out rows before the input first leaves the fit part's range
        self.start_left_out: Optional[dict] = None   # a validation session's first rows left out (in motion)
        self.analysed: dict = {}   # what of each record the loop analysed (the report's "analysed")
        train_full = self.representative_part(train_full, "train", "training record")
        if validate_full is not None:
            validate_full = self.representative_part(validate_full, "validate", "validation record")
        self.split = split_records(train_full, validate_full, max_rate_hz)
        split = self.split
        self.full = full = split.fit_full
        if full.undersampled:
            self.warnings.append(f"the record is sampled at {full.rate_hz:.0f} Hz, below {SUPPORTED_RATE_HZ:.0f} Hz: what "
                                 f"happens faster than its Nyquist rate ({0.5 * full.rate_hz:.0f} Hz) goes unseen (a "
                                 f"G_v with poles above it keeps the paper's); delays and lags of a sample or more, "
                                 f"rate dependence and the slow effects are identified as at any rate")
            log("warning: " + self.warnings[-1])
        self.range_um = float(np.ptp(split.score_full.position_um if split.held_out else full.position_um))
        # the sensor's noise from what the input cannot explain, on every record the loop analyses (record rate)
        self.noise_records = [train_full, validate_full]
        self.floor = estimate_noise_floor(self.noise_records)
        resolution = RESOLUTION_SHARE * self.range_um
        if not self.floor.known:
            self.noise = resolution
            self.warnings.append(f"the records offer no evidence for the sensor noise ({self.floor.detail}): no "
                                 f"residual is called noise (unexplained unless the model leaves nothing), and effects "
                                 f"are judged on their held-out cuts alone")
            log("warning: " + self.warnings[-1])
        elif not self.floor.rms_um >= resolution:   # a simulated or a smoothed record
            self.noise = resolution
            self.warnings.append(f"the record shows no sensor noise (below {RESOLUTION_SHARE:g} of its range, from "
                                 f"{self.floor.source}): the noise is taken as {self.noise:.3g} um, and figures "
                                 f"relative to it are relative to that")
            log("warning: " + self.warnings[-1])
        else:
            self.noise = self.floor.rms_um
        block = split.score.block / max(split.score_full.block, 1)   # block means: the noise's share at that rate
        self.levels = NoiseLevels(self.noise, self.noise / math.sqrt(block))
        self.range_val = (float(np.ptp(split.score_full.position_um[split.start_full:])) if not split.held_out
                          else self.range_um)
        held_out_text = ('last ' + format(100 * HELD_OUT_FRACTION, '.0f') + ' %' if split.held_out
                         else 'validation record')
        log(f"records: fit {len(full)} samples ({full.duration_s:.1f} s at {full.rate_hz:.0f} Hz), held-out "
            f"{len(split.score_full) - split.start_full} samples ({held_out_text}); "
            f"analysis at {split.fit.rate_hz:.0f} Hz; sensor noise: {self.floor.describe()}")
        self.cache = FitCache()  # operator states etc. shared by every fit on the fit record
        self.polishes: dict[int, tuple[ValveModel, ValveModel]] = {}   # id(model) -> (model, its poles refitted)
        self.sessions: dict[int, tuple[ValveModel, SessionStart]] = {}   # each model's start on a validation session
        self.session_bounds: dict = {}   # the operators' clamp bounds there, per hysteresis structure

    # ------------------------------------------------------------------ helpers
    def representative_part(self, record: Record, key: str, what: str) -> Record:
        """The part of ``record`` the loop analyses: its first MAX_ANALYSED_S (a record of repeated experiments
        shows its valve in its first minutes as well as in hours; the loop's memory grows with what it analyses);
        kept in ``analysed[key]`` and said in a warning where that is not all of it."""
        part = record.first(MAX_ANALYSED_S)
        self.analysed[key] = {"from_s": float(part.time_s[0]), "to_s": float(part.time_s[-1]),
                              "samples": len(part), "of_samples": len(record),
                              "record_duration_s": record.duration_s}
        if part is not record:
            self.warnings.append(f"the {what} is {record.duration_s:.0f} s long: its first {part.duration_s:.0f} s "
                                 f"({len(part)} of {len(record)} samples) were analysed (MAX_ANALYSED_S; the "
                                 f"loop's memory and time grow with what it analyses)")
            self.log("warning: " + self.warnings[-1])
        return part

    @property
    def fit(self) -> Record:
        return self.split.fit

    def each(self, jobs: list[Callable[[], object]]) -> list:
        """Independent jobs on the pool, results in order (a job never waits for another)."""
        return _on_pool(self.pool, jobs)

    def each_form(self, jobs: list[Callable[[], object]]) -> list:
        """The forms of one refit (``fit_model``'s ``each``) on their own pool: a refit running on ``pool``
        waits for them, so they cannot queue behind it there.  A combined form waits only for forms handed to
        the pool before it (first come, first served: they run or have run)."""
        return _on_pool(self.forms_pool, jobs)

    def session(self, model: ValveModel, on: Optional[Split] = None) -> Optional[SessionStart]:
        """``model``'s start and offset on a separate validation session (estimated once per model, the same way for
        every model: each is scored from its own, so every comparison of two models is one of the same kind); None
        for a held-out tail, which continues the fit part."""
        on = self.split if on is None else on
        if on.held_out:
            return None
        key = id(model)
        if key not in self.sessions:
            self.sessions[key] = (model, session_start(model, on.score, on.score_t0, self.session_bounds))
        return self.sessions[key][1]

    def error(self, model: ValveModel, on: Optional[Split] = None, full: bool = False) -> np.ndarray:
        """``model``'s held-out error [um] (analysis rate, or the record's own with ``full``): on a separate session
        from the model's own start there and less the session's offset."""
        on = self.split if on is None else on
        return on.held_out_error(model, full, self.session(model, on))

    def held_out(self, model: ValveModel) -> Score:
        """``model``'s held-out score (``error``): the one figure every decision compares (with the RMS before the
        held-out input first leaves the fit part's range, where it does: ``check_held_out_range``)."""
        return Score.of(self.error(model), self.known_rows)

    def start_model(self, thresholds: np.ndarray, like: Optional[ValveModel] = None,
                    history: InitialState = REST) -> ValveModel:
        m = ValveModel(GPIM(thresholds, np.ones(thresholds.size)), t0=self.split.t0, history=history)
        if like is not None:
            m = replace(m, sections=like.sections, dynamics_note=like.dynamics_note, dynamics_free=like.dynamics_free,
                        history=like.history)
        return m

    def fitted_and_scored(self, start: ValveModel, poles: str, on: Optional[Split] = None) -> tuple[ValveModel, float]:
        on = self.split if on is None else on
        m = fit_model(on.fit, start, poles=poles, cache=self.cache)
        return m, rms(self.error(m, on))

    def mid_capacity_start(self, like: ValveModel, history: InitialState, on: Optional[Split] = None) -> ValveModel:
        on = self.split if on is None else on
        return replace(self.start_model(uniform_thresholds(on.fit.voltage_v, MID_CAPACITY), like), history=history)

    # ------------------------------------------------------------------ 1. the initial state
    def choose_initial_state(self) -> StartChoice:
        """The operators' state at the first sample: a valve started from rest, a record cut from running
        operation, estimated from the first rows, or unknown (a valve left off its loop by an unrecorded
        excitation): then the fit starts where the record's own input has wiped it out (``split`` is replaced by
        the cut).  ``starts`` and ``start_rms`` (each start tried -> its model, its held-out RMS) grow as the
        starts are tried."""
        starts, start_rms, chosen = self._rest_or_cycled()
        chosen, estimate = self._estimated_start(starts, start_rms, chosen)
        chosen, before_wipe = self._wiped_start(starts, start_rms, chosen)
        return self._describe_start(starts, start_rms, chosen, estimate, before_wipe)

    def _rest_or_cycled(self) -> tuple[dict, dict, str]:
        candidates = {"rest": REST, "cycled": InitialState("cycled")}
        fits = self.each([lambda h=h: self.fitted_and_scored(
            self.start_model(uniform_thresholds(self.fit.voltage_v, MID_CAPACITY), history=h), "baseline")
            for h in candidates.values()])
        starts = {h: m for h, (m, _) in zip(candidates, fits)}
        start_rms = {h: r for h, (_, r) in zip(candidates, fits)}
        return starts, start_rms, ("cycled" if start_rms["cycled"] < (1 - INITIAL_STATE_TOLERANCE) * start_rms["rest"]
                                   else "rest")

    def _estimated_start(self, starts: dict, start_rms: dict, chosen: str) -> tuple[str, dict]:
        """A state estimated from the rows before the input wiped it (rested elsewhere, or left off the loop):
        (the start chosen, what the estimate found)."""
        first_rows = self.split.first_rows(self.fit)
        estimated, estimate = estimate_state(starts["rest"], first_rows, self.fit)
        if estimate["rms_before_wipe_um"] > (1 - ESTIMATE_STATE_GAIN) * estimate["rms_before_wipe_from_rest_um"]:
            estimated = REST   # it cannot be taken (below): not fitted
        for round_ in range(ESTIMATE_ROUNDS):   # weights fitted from rest are bent by the wrong start: alternate
            if estimated.kind != "remanent":
                break
            starts["estimated"], start_rms["estimated"] = self.fitted_and_scored(
                self.mid_capacity_start(starts[chosen], estimated), "fixed")
            if round_ == ESTIMATE_ROUNDS - 1:
                break
            again, estimate_again = estimate_state(starts["estimated"], first_rows, self.fit)
            if again == estimated or again.kind != "remanent":
                estimate = estimate_again if again == estimated else estimate
                break
            estimated, estimate = again, estimate_again
        if "estimated" in start_rms:
            # as for the wipe below: a clear gain, and the state must explain the start (a slow effect cannot);
            # a valve that rested at one voltage until the record's first command moved it (a closed-loop record)
            # is one parameter beyond rest and shows in the first rows alone: there it must halve their misfit,
            # whatever the baseline's held-out RMS says (a baseline that lacks an effect, creep say, bends its
            # weights to the wrong start and scores better from it; the effect fitted later needs the right one)
            explains = estimate["rms_before_wipe_um"] / max(estimate["rms_before_wipe_from_rest_um"], 1e-12)
            clear_gain = (start_rms["estimated"] < (1 - WIPE_GAIN) * start_rms[chosen]
                          and explains <= 1 - ESTIMATE_STATE_GAIN)
            rested_elsewhere = estimated.rested_at_v is not None and explains <= 1 - WIPE_STATE_GAIN
            # held-out data that cannot tell the starts apart (a separate session has its own start): the
            # training record's first rows can, and a start they refute would bend every later fit to it
            indistinct = (explains <= 1 - ESTIMATE_STATE_GAIN and start_rms["estimated"]
                          <= (1 + INITIAL_STATE_TOLERANCE) * min(start_rms["rest"], start_rms["cycled"]))
            self.log(f"initial state: estimated {estimate['estimate']}; first rows' RMS "
                     f"{estimate['rms_before_wipe_um']:.4f} um against {estimate['rms_before_wipe_from_rest_um']:.4f} from rest")
            if clear_gain or rested_elsewhere or indistinct:
                chosen = "estimated"
                if indistinct and not (clear_gain or rested_elsewhere):
                    self.log(f"initial state: held-out data cannot tell the starts apart (within "
                             f"{100 * INITIAL_STATE_TOLERANCE:g} %); the estimate leaves {100 * explains:.0f} % of "
                             f"the training record's first rows' misfit from rest: estimated")
        return chosen, estimate

    def _wiped_start(self, starts: dict, start_rms: dict, chosen: str) -> tuple[str, Optional[dict]]:
        """Fitting only after the input has wiped out an unknown start, on the poles just fitted on the whole
        record (only the initial state differs): (the start chosen, the state before the record where that is
        the wipe)."""
        wiped = self.split.after_wipe()
        if wiped is None:
            return chosen, None
        cut, state = wiped
        starts["wiped"], start_rms["wiped"] = self.fitted_and_scored(
            replace(self.mid_capacity_start(starts[chosen], state, cut), t0=cut.t0), "fixed", cut)
        if start_rms["wiped"] < (1 - WIPE_GAIN) * start_rms[chosen]:
            # a start off the loop, or a slow effect (drift, creep) that the earlier rows show most: only an
            # initial state that explains the rows before the wipe makes it the former
            _, before_wipe = estimate_state(starts["wiped"], self.fit.slice(0, len(self.fit) - len(cut.fit)), self.fit)
            if before_wipe["rms_before_wipe_um"] <= (1 - WIPE_STATE_GAIN) * before_wipe["rms_before_wipe_from_rest_um"]:
                self.split = cut
                return "wiped", before_wipe
            else:
                self.log(f"initial state: fitting from the wipe on cuts the held-out RMS {start_rms[chosen]:.4f} "
                         f"-> {start_rms['wiped']:.4f} um, but no state before the record explains the rows before it "
                         f"({before_wipe['rms_before_wipe_um']:.4f} um RMS against "
                         f"{before_wipe['rms_before_wipe_from_rest_um']:.4f} from rest): a slow effect, not the start; "
                         f"the whole record is fitted")
        return chosen, None

    def _describe_start(self, starts: dict, start_rms: dict, chosen_state: str, estimate: dict,
                        before_wipe: Optional[dict]) -> StartChoice:
        split = self.split
        first = starts[chosen_state]
        assumed = {"assumed": first.history.describe(), "fit_starts_at_s": split.wiped_at_s}
        if chosen_state == "estimated":
            assumed["assumed"] += ": estimated from the record's rows before its input wiped the state out"
            assumed["before_the_record"] = estimate
        if chosen_state == "wiped":
            assumed = {"assumed": f"unknown before the record: the fit and every decision use the record from "
                                  f"t = {split.wiped_at_s:.6g} s, where its input has come within "
                                  f"{100 * WIPE_MARGIN:g} % of both its extremes and so wiped the state out; the "
                                  f"operators start there as the record's input since its first sample left them",
                       "fit_starts_at_s": split.wiped_at_s,
                       "before_the_record": before_wipe}
        if not split.held_out:
            assumed["validation_record_start"] = (
                "a separate session: each model's operator states at its first sample and the output G had settled "
                "to before it (estimated on the rows until the input has wiped them out) and the session's sensor "
                "offset (the whole record) estimated for it; its held-out error taken from that start, less that offset")
        self.log("initial state: " + ", ".join(f"{h} {r:.4f}" for h, r in start_rms.items())
                 + " um held-out RMS; chosen "
                 + (f"{chosen_state}: the state before the record is unknown, the fit starts at t = "
                    f"{split.wiped_at_s:.4g} s, where the input has wiped it out" if chosen_state == "wiped"
                    else chosen_state))
        self.log(f"G_v: {first.dynamics_note}")
        return StartChoice(first, chosen_state, start_rms, assumed)

    # ------------------------------------------------------------------ 1b. the GPIM's capacity
    def choose_capacity(self, start: StartChoice) -> CapacityChoice:
        """The GPIM's number of thresholds, chosen on held-out data among CAPACITY_OPERATORS and the paper's
        5-parameter fit's grid, from ``start``'s model.  The sizes are compared on their held-out RMS, or, where a slow trend dominates it
        (TREND_DOMINANCE: a drift the baseline cannot follow, which would make every size look alike and the
        smallest win), on their held-out error about its trend."""
        fit, first, pool = self.fit, start.first, self.pool
        paper_job = pool.submit(fit_paper_gpim, fit, first.sections, history=first.history)
        grids = {f"{n} operators": uniform_thresholds(fit.voltage_v, n) for n in CAPACITY_OPERATORS}
        jobs = {label: pool.submit(self.capacity_fit, grid, first) for label, grid in grids.items()}
        paper = paper_job.result()
        if paper.failed is None:
            label = f"paper grid ({paper.params.n} operators, alpha {paper.params.alpha:.4g} V)"
            grids[label] = paper.model.gpim.thresholds
            jobs[label] = pool.submit(self.capacity_fit, grids[label], first)
        fits = {label: job.result() for label, job in jobs.items()}
        about_trend = (min(f.about_trend_um for f in fits.values())
                       < TREND_DOMINANCE * min(f.held_out_um for f in fits.values()))
        capacity = [replace(f, label=label) for label, f in fits.items()]

        def score(c: CapacityFit) -> float:
            return c.score(about_trend)
        ladder = [c for c in capacity if c.label.endswith(" operators")]
        for n in CAPACITY_EXTENSION:   # a record with fine loop structure (a measured one) may want more
            largest, below = ladder[-1], ladder[-2]
            if not (score(largest) < (1 - CAPACITY_TOLERANCE) * score(below)
                    and score(largest) <= min(score(c) for c in capacity)):
                break
            ladder.append(replace(self.capacity_fit(uniform_thresholds(fit.voltage_v, n), first), label=f"{n} operators"))
            capacity.append(ladder[-1])
        best = min(score(c) for c in capacity)
        chosen = min((c for c in capacity if score(c) <= (1 + CAPACITY_TOLERANCE) * best), key=lambda c: c.operators)
        label = chosen.label
        baseline = fit_model(fit, chosen.model, poles="baseline", cache=self.cache)
        chosen_on = "held-out RMS about its trend" if about_trend else "held-out RMS"
        self.log("capacity: " + ", ".join(f"{c.label} {score(c):.4f}" for c in capacity) + f" um {chosen_on}"
                 + (" (a trend dominates the held-out error; as it is: " + ", ".join(f"{c.held_out_um:.4f}" for c in capacity)
                    + " um)" if about_trend else "") + f"; chosen {label}")
        return CapacityChoice(tuple(capacity), label, about_trend, chosen_on, baseline, paper)

    def revisit_capacity(self, capacity: CapacityChoice, story: Story) -> tuple[CapacityChoice, Story]:
        """Where ``story`` names two effects or more and the best smaller size scored within CAPACITY_REVISIT of the
        chosen one (a knife edge), one of the effects may stand in for the grid: on the smaller size's baseline the
        story less each of its effects is refitted exactly; where the best of them leaves a held-out RMS within
        CAPACITY_TOLERANCE of the story's, the effects are confirmed, checked and swapped from it (``story``), and
        that second story replaces the first when it names a part of the first's effects and still explains as
        much (fewer names that explain as much)."""
        if len(story.added) < 2:
            return capacity, story
        chosen = capacity.chosen()
        limit = (1 + CAPACITY_REVISIT) * chosen.score(capacity.about_trend)
        smaller = [c for c in capacity.fits if c.operators < chosen.operators and c.score(capacity.about_trend) <= limit]
        if not smaller:
            return capacity, story
        other = min(smaller, key=lambda c: c.score(capacity.about_trend))
        before, effects = self.held_out(story.final).rms, ", ".join(story.added)
        baseline = fit_model(self.fit, other.model, poles="baseline", cache=self.cache)
        choice = _EffectChoice(self, baseline, other.label, search=False)   # the search only if it is taken further
        fewer = [[n for n in story.added if n != e] for e in story.added]
        refits = choice.refit_many([(f, None) for f in fewer])
        tried = ", ".join(f"{', '.join(f)} {score.rms:.4f}" for f, (_, score) in zip(fewer, refits))
        best, (_, best_score) = min(zip(fewer, refits), key=lambda t: t[1][1].rms)
        looked = (f"capacity: {effects} found on {capacity.label}, where {other.label} scored within "
                  f"{100 * CAPACITY_REVISIT:.0f} %; on {other.label} with one effect fewer: {tried} um held-out RMS "
                  f"against {before:.4f} um: ")
        if best_score.rms > (1 + CAPACITY_TOLERANCE) * before:
            self.log(looked + f"{capacity.label} kept")
            return capacity, story
        self.log(looked + f"the effects chosen again on {other.label} from {', '.join(best)}")
        choice.search_subsets()
        second = choice.story(best)
        after, names = self.held_out(second.final).rms, ", ".join(second.added) or "nothing"
        if set(second.added) < set(story.added) and after <= (1 + CAPACITY_TOLERANCE) * before:
            self.log(f"capacity: {names} on {other.label} explains as much as {effects} on {capacity.label} (held-out "
                     f"RMS {after:.4f} against {before:.4f} um): {other.label} kept")
            chosen_on = (f"{capacity.chosen_on}; with the effects found, {other.label} ({names}, {after:.4f} um) "
                         f"explains as much as {capacity.label} ({effects}, {before:.4f} um) with fewer effects")
            return replace(capacity, label=other.label, chosen_on=chosen_on, baseline=baseline), second
        self.log(f"capacity: {names} on {other.label}, held-out RMS {after:.4f} um against {before:.4f} um with "
                 f"{effects}: {capacity.label} kept")
        return capacity, story

    def revisit_placement(self, start: StartChoice, capacity: CapacityChoice, story: Story
                          ) -> tuple[CapacityChoice, Story]:
        """Where ``story`` names asymmetry whose descending envelope departs from the ascending one by a shift more
        than by a slope or a curvature (``Asymmetry.shift_share`` at least PLACEMENT_SHIFT_SHARE), the shift may stand
        in for the thresholds' placement: the shift alone is the same loop as a symmetric GPIM on thresholds moved by
        half of it (``Asymmetry.symmetric_thresholds``), which no grid of the capacity choice has (a coarse grid chosen
        on a baseline whose error a slow effect dominates can sit half a spacing off the valve's).  On the grid so
        placed the story less asymmetry is refitted exactly; where it leaves a held-out RMS within
        CAPACITY_TOLERANCE of the story's, the effects are confirmed, checked and swapped from it (``story``), and
        that second story replaces the first when it names a part of the first's effects and explains as much
        (the record then shows no branch difference beyond a placement: asymmetry is not named)."""
        term = story.final.term("asymmetry")
        if term is None or term[0].shift_share(story.final.gpim) < PLACEMENT_SHIFT_SHARE:
            return capacity, story   # (a slope or a curvature that departs further than the shift: the branches differ)
        asymmetry = term[0]
        moved_v = asymmetry.threshold_move(story.final.gpim)
        placed = asymmetry.symmetric_thresholds(story.final.gpim)   # (the chosen grid's: effects keep the thresholds)
        label = f"{capacity.label}, thresholds moved {moved_v:+.3g} V"
        # the check on the chosen baseline's G_v (one linear solve moves it to the new thresholds); the baseline
        # proper, its poles fitted again, only where the effects are chosen again there
        moved = fit_model(self.fit, self.start_model(placed, capacity.baseline), poles="fixed", cache=self.cache)
        without = [n for n in story.added if n != "asymmetry"]
        (_, without_score), = _EffectChoice(self, moved, label, search=False).refit_many([(without, None)])
        before, effects = self.held_out(story.final).rms, ", ".join(story.added)
        looked = (f"placement: asymmetry's descending shift {2 * moved_v:+.4g} V is the same loop as the thresholds of "
                  f"{capacity.label} moved {moved_v:+.4g} V; there, {', '.join(without) or 'the baseline'} leaves "
                  f"{without_score.rms:.4f} um held-out RMS against {before:.4f} um with {effects}: ")
        if without_score.rms > (1 + CAPACITY_TOLERANCE) * before:
            self.log(looked + "the branches differ (asymmetry kept)")
            return capacity, story
        self.log(looked + f"the effects chosen again on the moved thresholds from {', '.join(without) or 'none'}")
        fit = replace(self.capacity_fit(placed, start.first), label=label)
        baseline = fit_model(self.fit, fit.model, poles="baseline", cache=self.cache)
        second = _EffectChoice(self, baseline, label).story(without)
        after, names = self.held_out(second.final).rms, ", ".join(second.added) or "nothing"
        if set(second.added) < set(story.added) and after <= (1 + CAPACITY_TOLERANCE) * before:
            self.log(f"placement: {names} on {label} explains as much as {effects} on {capacity.label} (held-out RMS "
                     f"{after:.4f} against {before:.4f} um): the thresholds moved, asymmetry not named")
            chosen_on = (f"{capacity.chosen_on}; with the effects found, asymmetry's descending shift alone "
                         f"({2 * moved_v:+.4g} V) was the thresholds' placement: {label} ({names}, {after:.4f} um) "
                         f"explains as much as {capacity.label} ({effects}, {before:.4f} um)")
            return replace(capacity, fits=capacity.fits + (fit,), label=label, chosen_on=chosen_on,
                           baseline=baseline), second
        self.log(f"placement: {names} on {label}, held-out RMS {after:.4f} um against {before:.4f} um with {effects}: "
                 f"{capacity.label} kept")
        return capacity, story

    def rechoose_capacity(self, start: StartChoice, capacity: CapacityChoice, story: Story, extend: bool = True
                          ) -> tuple[CapacityChoice, Story]:
        """The GPIM's size chosen again with ``story``'s effects in the model (capacity and effects are chosen
        together: an effect must not stand in for operators the baseline's choice left out, nor a size win only
        because an effect it lacks swamped what the sizes differ in).  Each larger size of the capacity choice gets
        the story's effects refitted on it (from the story's structures); where one leaves a held-out RMS lower by
        more than CAPACITY_TOLERANCE, the effects are confirmed again on it (each must earn its place there), and
        that story replaces the first where it explains at least as much (``extend``: and the other effects checked
        exactly on top there, where ``story``'s were not).  Skipped for a story of one effect that leaves no room
        for another (``search.room_for_an_effect``): near the noise no size shows more."""
        if not story.added:
            return capacity, story
        final_score = self.held_out(story.final)
        if len(story.added) < 2 and not room_for_an_effect(final_score, self.levels):
            # one effect that leaves the noise's order: no effect stands in for another, and no size could show more
            return capacity, story
        before = final_score.rms
        chosen = capacity.chosen()
        # the larger sizes: an effect that stands in for operators makes up for too few (the smaller sizes within
        # reach of the chosen one are revisit_capacity's)
        others = [c for c in capacity.fits if c.operators > chosen.operators]
        if not others:
            return capacity, story

        def refit(c: CapacityFit) -> tuple[CapacityFit, float]:   # a job on the pool: refit, not refit_many
            choice = _EffectChoice(self, c.model, c.label, search=False)
            result = choice.refit(story.added, story.final)
            choice.refits[frozenset(story.added)] = result   # the story goes on from it where this size is taken
            choices[c.label] = choice
            return c, result[1].rms
        choices: dict[str, _EffectChoice] = {}
        tried = self.each([lambda c=c: refit(c) for c in others])
        effects = ", ".join(story.added)
        text = ", ".join(f"{c.label} {r:.4f}" for c, r in tried)
        better = [(r, c.operators, c) for c, r in tried if r < (1 - CAPACITY_TOLERANCE) * before]
        if not better:
            self.log(f"capacity with {effects}: {capacity.label} {before:.4f} um held-out RMS, the other sizes "
                     f"{text}: {capacity.label} kept")
            return capacity, story
        best = min(better)[2]
        self.log(f"capacity with {effects}: {capacity.label} {before:.4f} um held-out RMS, the other sizes {text}: "
                 f"the effects chosen again on {best.label}")
        # the story's effects confirmed on it (each must still earn its place: one that stood in for operators does
        # not), then the others checked exactly on top there; on the size's own fit (G_v as the chosen start fitted
        # it), from the refit that chose it; the report's first-order figures (the subset search) stay the first
        # size's, the baseline's
        choice = choices[best.label]
        choice.search, choice.table, choice.chosen_set = story.choice.search, story.choice.table, frozenset(story.added)
        choice.exact_checks = dict(story.choice.exact_checks)   # the checks that refused the others, as they decided
        second = choice.story(story.added, extend=extend)
        after, names = self.held_out(second.final).rms, ", ".join(second.added) or "nothing"
        if after <= (1 + CAPACITY_TOLERANCE) * before:
            self.log(f"capacity: {names} on {best.label} (held-out RMS {after:.4f} um) against {effects} on "
                     f"{capacity.label} ({before:.4f} um): {best.label} taken")
            chosen_on = (f"{capacity.chosen_on}; chosen again with the effects in the model: {best.label} ({names}, "
                         f"{after:.4f} um) against {capacity.label} ({effects}, {before:.4f} um): the effects are "
                         f"fitted on {best.label}, the baseline's figures stay those of {capacity.label}")
            return replace(capacity, chosen_on=chosen_on, effects_grid=best.label), second
        self.log(f"capacity: {names} on {best.label} leaves {after:.4f} um against {before:.4f} um with {effects} on "
                 f"{capacity.label}: {capacity.label} kept")
        return capacity, story

    def capacity_fit(self, thresholds: np.ndarray, first: ValveModel) -> CapacityFit:
        """A GPIM on ``thresholds`` fitted from the chosen start's model ``first`` (G_v fixed), with its held-out
        figures."""
        m = fit_model(self.fit, self.start_model(thresholds, first), poles="fixed", cache=self.cache)
        error = self.error(m)
        return CapacityFit("", thresholds.size, m, rms(error), rms(_detrended(error)))

    # ------------------------------------------------------------------ 4. what remains
    def what_remains(self, story: Story) -> Remains:
        """Size, peaks and shape of ``story``'s final held-out residual at the record's rate, against the noise floor
        the records give evidence for.  Unexplained where its RMS above the floor is more than
        UNEXPLAINED_NOISE_RATIO times the floor, where its peaks stand PEAK_NOISE_RATIO above the noise's, where the
        records give no evidence for the floor (no residual is then called noise), and wherever the model leaves
        SPREAD_SHARE of the held-out output's own spread (whatever a floor says)."""
        split, final, noise, search = self.split, story.final, self.noise, story.choice.search
        e_full = self.error(final, full=True)
        structure = _structure(e_full, split.score_full.dt, noise, self.range_val)
        final_set = frozenset(story.added)
        closest = {n: 1.0 - search.score(final_set | {n}).rms / max(search.score(final_set).rms, 1e-30)
                   for n in story.choice.names if n not in final_set}
        near = max(closest.items(), key=lambda kv: kv[1]) if closest else ("none", 0.0)
        peaks = _peak_structure(e_full, split.score_full.dt, noise, self.range_val)
        structure.update(peaks)
        measured = split.score_full.position_um[split.start_full:]
        structure["held_out_noise_peak_um"] = noise_peak_um(measured, split.score_full.dt)
        structure["held_out_noise_peak_pct"] = (100.0 * structure["held_out_noise_peak_um"] / self.range_val
                                                if self.range_val > 0 else 0.0)
        spread = float(np.std(measured))
        structure["share_of_spread"] = structure["rms_um"] / spread if spread > 0 else 0.0
        by_rms = _unexplained_by_rms(structure)
        by_peak = peaks["peak_ratio"] > PEAK_NOISE_RATIO and peaks["peak_pct_of_range"] > MIN_STRUCTURE_PCT
        by_spread = structure["share_of_spread"] >= SPREAD_SHARE
        no_floor = not self.floor.known and structure["pct_of_range"] > MIN_STRUCTURE_PCT
        floor = (f"the sensor noise {noise:.4f} um from {self.floor.source}" if self.floor.known
                 else f"no evidence for the sensor noise, so none of it is called noise")
        seen = (
            f"held-out residual RMS {structure['rms_um']:.4f} um at {split.score_full.rate_hz:.0f} Hz "
            f"({100 * structure['share_of_spread']:.1f} % of the held-out output's own spread, threshold "
            f"{100 * SPREAD_SHARE:.0f} %), of which {structure['structured_rms_um']:.4f} um stands above "
            + (f"{floor} ({structure['ratio_to_noise']:.1f}x it, threshold {UNEXPLAINED_NOISE_RATIO:g}x)"
               if self.floor.known else floor)
            + f"; peaks: the {_ordinal(PEAK_RANK)} largest {1e3 * PEAK_BLOCK_S:g} ms peak {peaks['peak_um']:.3f} um"
            + (f" is {peaks['peak_ratio']:.1f}x what the noise gives ({peaks['expected_noise_peak_um']:.3f} um, "
               f"threshold {PEAK_NOISE_RATIO:g}x;" if self.floor.known else " (no noise to compare it with;")
            + f" the held-out measurement's own noise peaks at "
            f"{structure['held_out_noise_peak_um']:.3f} um about its local cubic); lag-1 autocorrelation "
            f"{structure['lag1']:.2f}; strongest spectral line {structure['line_hz']:.3g} Hz "
            f"({100 * structure['line_share']:.0f} % of residual power); closest catalogue effect: {near[0]} "
            f"(would cut the held-out RMS by {100 * max(near[1], 0):.1f} %)")
        unexplained = by_rms or by_peak or by_spread or no_floor
        self.log(("structure remains: " if unexplained else "residual: ") + seen)
        return Remains(structure, unexplained, seen)

    # ------------------------------------------------------------------ 5. figures at the record's own rate, report
    def figures(self, model: ValveModel) -> dict[str, ErrorFigures]:
        """``model``'s error figures as the report gives them (``Figures``' fields): on the training part, and
        on the held-out data at the record's and the analysis rate."""
        split = self.split
        return {"train": error_figures(split.fit_full.position_um,
                                       split.fit_full.position_um - split.fit_error(model, True), self.range_um).rounded(),
                "validate": error_figures(split.score_full.position_um[split.start_full:],
                                          split.score_full.position_um[split.start_full:] - self.error(model, full=True),
                                          self.range_val).rounded(),
                "validate_analysis_rate": error_figures(split.score.position_um[split.start:],
                                                        split.score.position_um[split.start:] - self.error(model),
                                                        self.range_val).rounded()}

    def diagnosis(self, story: Story) -> list[Decision]:
        """Each effect's decision with its statistic (the share of the structured residual it removes), threshold,
        margin and consistency: the added ones by their exact drop-one refits, the others by their exact refit on
        top of the final set where one was made (an exact check, or forward selection's), else added last to the
        final set in the linear search."""
        added, names, final_set, search = story.added, story.choice.names, frozenset(story.added), story.choice.search
        diagnosis = []
        checked, refits = story.choice.exact_checks.get(final_set, {}), story.choice.refits
        for n in names:
            exact = n in story.verdicts and n in added
            if exact:
                verdict = story.verdicts[n]
                how = "exact refit without it"
            else:   # the exact refit on top of the final set where there was one: the figure the decision used
                refitted = checked.get(n) or (
                    (refits[final_set | {n}][1], refits[final_set][1]) if final_set | {n} in refits
                    and final_set in refits else None)
                with_s, without_s = refitted or (search.score(final_set | {n}), search.score(final_set))
                verdict = Verdict(support(with_s, without_s, self.levels), without_s.rms, with_s.rms)
                how = ("refitted exactly on top of the final model" if refitted
                       else "added last to the final model (one linear solve from the baseline)")
                if refitted and not verdict.support.supported and verdict.support.share >= GAIN_THRESHOLD:
                    how += f"; not supported: {unsupported_because(with_s, without_s, self.levels)}"
            sup = verdict.support
            diagnosis.append(Decision(effect=n, added=exact, statistic=round(sup.share, 4), threshold=GAIN_THRESHOLD,
                                      margin=round(sup.share - GAIN_THRESHOLD, 4), held_out_gain=round(sup.cut, 4),
                                      explained_rms_um=round(sup.explained_um, 5),
                                      better_share=round(sup.consistency.better_share, 4),
                                      loss_ratio=round(min(sup.consistency.loss_ratio, 1e9), 4),
                                      t=round(sup.consistency.t, 3) if math.isfinite(sup.consistency.t) else 1e9,
                                      decided_by=sup.by,
                                      evidence=_evidence(story.choice.by_name[n], verdict, self.levels, how)))
        diagnosis.sort(key=lambda d: (not d.added, added.index(d.effect) if d.added else names.index(d.effect)))
        return diagnosis

    def report(self, start: StartChoice, capacity: CapacityChoice, story: Story, remains: Remains
               ) -> IdentificationReport:
        split, baseline, final, paper = self.split, capacity.baseline, story.final, capacity.paper
        unique = list({id(m): m for m in (baseline, final, paper.model)}.values())
        figured = {id(m): f for m, f in zip(unique, self.each([lambda m=m: self.figures(m) for m in unique]))}  # once each
        diagnosis = self.diagnosis(story)
        choice = story.choice
        alternatives = _alternatives(story.added, choice.names, story.verdicts, choice.search, choice.refit_many,
                                     choice.by_name)
        for a in alternatives:
            self.log(f"cannot tell apart: {a.effect} and {a.alternative}: {a.why}")
        held_out_text = (f"held-out last {100 * HELD_OUT_FRACTION:.0f} % of the training record" if split.held_out
                         else "separate validation record")
        sessions, final_start = self.sessions_report(start, final)
        report = IdentificationReport(
            range_um=round(self.range_um, 4),
            baseline=Baseline(model=baseline.name, fit=capacity.label, **figured[id(baseline)],
                              G_v=describe_dynamics(baseline.dynamics, baseline.dynamics_note),
                              operators=baseline.gpim.n),
            effects_added=tuple(story.added),
            diagnosis=tuple(diagnosis),
            indistinguishable=tuple(alternatives),
            final=Final(model=final.name, **figured[id(final)]),
            unexplained=bool(remains.unexplained),
            residual=remains.seen,
            residual_structure=ResidualStructure(**{k: round(v, 6) for k, v in remains.structure.items()}),
            baseline_fits=BaselineFits(
                capacity=tuple(Capacity(grid=c.label, operators=c.operators, held_out_rms_um=round(c.held_out_um, 6),
                                        held_out_rms_about_trend_um=round(c.about_trend_um, 6)) for c in capacity.fits),
                chosen=capacity.label,
                chosen_on=capacity.chosen_on,
                initial_state={"held_out_rms_um": {h: round(r, 6) for h, r in start.held_out_rms_um.items()},
                               "chosen": start.chosen, **start.assumed, **final_start},
                linear={**to_json(figured[id(baseline)]), "operators": baseline.gpim.n, "invertible": True},
                paper_nls={**to_json(figured[id(paper.model)]),
                           "params": {k: getattr(paper.params, k) for k in ("a0", "a1", "alpha", "rho", "tau", "n",
                                                                            "offset_um")},
                           "fixed": "a0 = 1, a1 = 0: the 5-parameter form has two exact invariances (a0 with "
                                    "alpha, rho, tau; a1 with the offset)",
                           "condition_number": paper.condition_number, "evaluations": paper.evaluations,
                           "failed": paper.failed},
            ),
            search=tuple(sorted(choice.table, key=lambda t: t.held_out_rms_um)),
            confirm=tuple(story.confirm_log),
            validation=held_out_text,
            held_out_fraction=HELD_OUT_FRACTION if split.held_out else None,
            held_out_samples=len(split.score_full) - split.start_full,
            analysed=self.analysed,
            validate_range_um=round(self.range_val, 4),
            sample_rate_hz=round(self.full.rate_hz, 3),
            analysis_rate_hz=round(self.fit.rate_hz, 3),
            noise_floor_um=round(self.noise, 6) if self.floor.known else None,
            noise_floor=NoiseFloorReport(
                rms_um=None if self.floor.rms_um is None else round(self.floor.rms_um, 6), source=self.floor.source,
                detail=self.floor.detail,
                evidence=tuple(NoiseEstimate(source=e.source, rms_um=None if e.rms_um is None else round(e.rms_um, 6),
                                             detail=e.detail, samples=e.samples) for e in self.floor.evidence)),
            summary="",
            thresholds={"held_out_gain": GAIN_THRESHOLD, "signature": GAIN_THRESHOLD,
                        "min_effect_noise_ratio": MIN_EFFECT_NOISE_RATIO, "peak_tolerance": PEAK_TOLERANCE,
                        "unexplained_noise_ratio": UNEXPLAINED_NOISE_RATIO, "unexplained_pct": MIN_STRUCTURE_PCT,
                        "unexplained_peak_ratio": PEAK_NOISE_RATIO, "peak_block_s": PEAK_BLOCK_S,
                        "peak_rank": PEAK_RANK, "capacity_tolerance": CAPACITY_TOLERANCE,
                        "initial_state_tolerance": INITIAL_STATE_TOLERANCE, "wipe_gain": WIPE_GAIN,
                        "wipe_state_gain": WIPE_STATE_GAIN, "wipe_margin": WIPE_MARGIN,
                        "separation_share": SEPARATION_SHARE, "unexplained_spread_share": SPREAD_SHARE},   # signature: earlier reports' name of held_out_gain
            sessions=tuple(sessions),
            transport_delay_s=round(final.delay_s, 7),
            warnings=tuple(self.warnings),
            final_model=final.describe(),
            seconds=round(time.monotonic() - self.started, 3),
        )
        report = replace(report, summary=_summary_line(report, self.floor))
        self.log(f"{report.summary} ({report.seconds:.1f} s)")
        return report

    def sessions_report(self, start: StartChoice, final: ValveModel) -> tuple[list[Session], dict]:
        """Each record as a session of its own, for the final model (``Session`` in the report's schema), and how
        the final model started on a validation record (for the initial state's description)."""
        first = start.first.history.describe() if self.split.wiped_at_s is None else start.assumed["assumed"]
        out = [Session(record="training", offset_um=0.0, start=first, start_rows=0, start_rows_rms_um=0.0)]
        final_start = {}
        session = self.session(final)
        if session is not None:
            final_start["validation_record_start_final_model"] = session.history.describe()
            out.append(Session(record="validation", offset_um=round(session.offset_um, 6),
                               start="its own, estimated for the model: " + session.history.describe(),
                               start_rows=session.rows, start_rows_rms_um=round(session.first_rows_rms_um, 6),
                               left_out=self.start_left_out))
            self.log(f"validation session: sensor offset {session.offset_um:+.4f} um against the training record's; "
                     f"start estimated on its first {session.rows} rows ({session.first_rows_rms_um:.4f} um RMS there)")
        return out, final_start

    def check_held_out_range(self) -> None:
        """Warn when the held-out data drive the valve beyond the fit part's voltage range: the operators that
        only the held-out part moves (and whatever the valve does there) are not identified by the fit, and the
        held-out error there is extrapolation, which no effect explains.  Where they leave it after their first
        KNOWN_MIN_SHARE, the rows before are where every decision also asks an effect to do no worse
        (``known_rows``, ``search.support``)."""
        fit_v, held_v = self.split.fit.voltage_v, self.split.score.voltage_v[self.split.start:]
        lo, hi = float(np.min(fit_v)), float(np.max(fit_v))
        margin = HELD_OUT_RANGE_MARGIN * (hi - lo)
        below, above = float(np.min(held_v)), float(np.max(held_v))
        beyond = max(lo - below, above - hi)
        if beyond > margin:
            first_out = int(np.argmax((held_v < lo - margin) | (held_v > hi + margin)))
            if first_out >= KNOWN_MIN_SHARE * held_v.size:
                self.known_rows = first_out
            where = "the validation record" if not self.split.held_out else "the held-out part"
            self.warnings.append(f"{where} drives the valve to {below:.4g} .. {above:.4g} V, {beyond:.3g} V beyond the fit "
                                 f"part's {lo:.4g} .. {hi:.4g} V ({100 * beyond / (hi - lo):.0f} % of its range): the fit "
                                 f"cannot know the valve there, and the held-out error from there is extrapolation, "
                                 f"which no effect explains (a training record should span every voltage the valve "
                                 f"will see)" + (f"; an effect must also do no worse on its first "
                                                 f"{self.known_rows * self.split.score.dt:.3g} s, before it first "
                                                 f"leaves that range"
                                                 if self.known_rows is not None else ""))
            self.log("warning: " + self.warnings[-1])

    def leave_out_start_in_motion(self, start: StartChoice) -> None:
        """A separate validation session that starts in motion, still settling from a voltage nobody recorded (a
        jump just before it), shows an error at its first rows that no start estimated for the valve's memory takes
        away: the rows from the first to the last one, within START_MOTION_MAX_S, whose error (``start``'s model, at
        the record's rate) stands START_MOTION_RATIO times above the rest of the session's robust spread are left out
        of every held-out figure and decision (``split``'s start moves past them; the models still run from the
        session's first sample), and the report says so (``start_left_out``)."""
        split = self.split
        if split.held_out:
            return
        e = self.error(start.first, full=True)
        dt = split.score_full.dt
        reach = min(int(START_MOTION_MAX_S / dt), int(START_MOTION_MAX_SHARE * e.size))
        if reach < 1 or e.size <= 4 * reach:
            return
        rest = e[reach:]
        spread = max(MAD_TO_SIGMA * float(np.median(np.abs(rest - np.median(rest)))), self.noise)
        outside = np.flatnonzero(np.abs(e[:reach] - np.median(rest)) > START_MOTION_RATIO * spread)
        if outside.size == 0 or outside[0] > START_MOTION_FIRST_ROWS:
            return
        rows_full = int(outside[-1]) + 1
        ratio = split.score.block // max(split.score_full.block, 1)
        rows = -(-rows_full // ratio)   # whole analysis rows, so both rates leave out the same stretch
        rows_full = rows * ratio
        self.start_left_out = {"rows": rows_full, "seconds": round(rows_full * dt, 6),
                               "peak_error_um": round(float(np.max(np.abs(e[:rows_full]))), 4),
                               "spread_um": round(spread, 5)}
        self.split = replace(split, start=rows, start_full=rows_full)
        self.warnings.append(f"the validation session starts in motion (still settling from a voltage before it): its "
                             f"first {rows_full} rows ({1e3 * rows_full * dt:.0f} ms, error up to "
                             f"{self.start_left_out['peak_error_um']:.3g} um against a spread of {spread:.3g} um after "
                             f"them) are left out of the held-out figures")
        self.log("warning: " + self.warnings[-1])

    def noise_beyond_response(self, start: StartChoice) -> None:
        """Where the records gave no direct evidence for the noise (a closed loop's drive is never still and feeds
        the sensor's noise back at every frequency), the band beyond the response of ``start``'s fitted G."""
        if self.floor.known:
            return
        tf = start.first.dynamics

        def response(f: np.ndarray) -> np.ndarray:
            return np.abs(tf.frequency_response(f)) ** 2
        floor = estimate_noise_floor(self.noise_records, response)
        if not floor.known:
            self.floor = floor
            return
        self.floor = floor
        self.warnings[:] = [w for w in self.warnings if not w.startswith("the records offer no evidence")]
        self.noise = max(floor.rms_um, RESOLUTION_SHARE * self.range_um)
        self.levels = NoiseLevels(self.noise, self.noise * self.levels.analysis_um / self.levels.record_um)
        self.log(f"sensor noise: {floor.describe()}")

    def run(self) -> Analysis:
        start = self.choose_initial_state()
        self.noise_beyond_response(start)
        self.leave_out_start_in_motion(start)
        self.check_held_out_range()
        capacity = self.choose_capacity(start)
        choice = _EffectChoice(self, capacity.baseline, capacity.label)
        # the search's effects confirmed, the size chosen again with them in, and only then the effects the search
        # underrated checked exactly on top (on the size they will be fitted on: checks on too small a size let an
        # effect stand in for operators, and cost most of an analysis)
        confirmed = choice.story(extend=False)
        capacity, story = self.rechoose_capacity(start, capacity, confirmed)
        if story is confirmed:
            story = choice.story()   # (its confirmation's refits are cached)
            if story.added != confirmed.added:   # effects the exact checks found: the size again with them in (the
                capacity, story = self.rechoose_capacity(start, capacity, story, extend=False)   # others checked)
        if capacity.effects_grid is None:   # (a size chosen again with the effects in has settled the grid)
            capacity, story = self.revisit_placement(start, capacity, story)
            capacity, story = self.revisit_capacity(capacity, story)
        remains = self.what_remains(story)
        report = self.report(start, capacity, story, remains)
        return Analysis(report, capacity.baseline, story.final, self.split, story.drop_one, self.sessions)


class _EffectChoice:
    """Steps 2 and 3 of the module's docstring on one baseline: every subset of the catalogue scored by one linear
    solve (``search_subsets``, at construction unless ``search`` is False), then exact refits and drop-one checks
    (``story``).  The exact refits are cached per set (``refits``); the loop's records, noise, pools and caches
    are shared."""

    def __init__(self, loop: "_Loop", baseline: ValveModel, label: str, search: bool = True):
        self.baseline, self.label = baseline, label
        self.fit, self.split, self.noise, self.cache = loop.fit, loop.split, loop.noise, loop.cache
        self.levels = loop.levels
        self.log, self.pool, self.each, self.each_form = loop.log, loop.pool, loop.each, loop.each_form
        self.held_out, self.session, self.polishes = loop.held_out, loop.session, loop.polishes
        self.error, self.range_val = loop.error, loop.range_val
        self.confirm_log: list[ConfirmRound] = []
        self._confirmed: Optional[tuple] = None   # the search's set as confirmed (story), once
        H_fit = baseline.context(self.fit).H
        self.effects: list[Effect] = [e for e in (cls.prepare(self.fit, H_fit) for cls in CATALOGUE) if e is not None]
        self.by_name: dict[str, Effect] = {e.name: e for e in self.effects}
        self.names: list[str] = [e.name for e in self.effects]
        self.search: Optional[SubsetSearch] = None
        self.table: list[SearchRow] = []
        self.chosen_set: frozenset = frozenset()
        if search:
            self.search_subsets()
        self.refits: dict[frozenset, tuple[ValveModel, Score]] = {frozenset(): (baseline, self.held_out(baseline))}
        # effect -> (held-out score with it, without it) of the exact checks on top of a confirmed set, per set
        self.exact_checks: dict[frozenset, dict[str, tuple[Score, Score]]] = {}

    # ------------------------------------------------------------------ 2. every subset, one linear solve each
    def search_subsets(self) -> None:
        """Every subset of the catalogue scored by one linear solve from the baseline (at construction, unless
        told not to): sets ``search``, ``table`` and ``chosen_set`` (the best supported subset)."""
        baseline, names = self.baseline, self.names
        self.search = search = SubsetSearch(baseline, self.split, self.effects, self.each, self.session(baseline))
        subsets = [frozenset(c) for r in range(len(names) + 1) for c in itertools.combinations(names, r)]
        table = []
        for s in subsets:
            sc = search.score(s)
            checks = {e: support(sc, search.score(s - {e}), self.levels) for e in s}
            table.append(SearchRow(effects=tuple(n for n in names if n in s), held_out_rms_um=round(sc.rms, 6),
                                   held_out_peak_um=round(sc.peak, 5),
                                   supported=all(c.supported for c in checks.values())))
        supported = [(t.held_out_rms_um, len(t.effects), frozenset(t.effects)) for t in table if t.supported]
        self.table, self.chosen_set = table, min(supported)[2]
        self.log(f"search on {self.label}: {len(subsets)} subsets of {', '.join(names)}; best supported: "
                 f"{', '.join(n for n in names if n in self.chosen_set) or 'none'}")

    # ------------------------------------------------------------------ 3. exact refits and drop-one checks
    def refit_many(self, requests: list[tuple[list[str], Optional[ValveModel]]]) -> list[tuple[ValveModel, Score]]:
        """Exact refits of subsets with their held-out scores (cached; the missing ones on the pool).  In a
        request ``(subset, like)``, effects that ``like`` has keep the form it chose (their nested held-out forms
        chosen again: ``held_out_form``) and start from the nonlinear structure it fitted (a warm start: drop-one
        refits and additions stay near it); the others are fitted in each of their forms from their neutral
        structure."""
        missing = {}
        for subset, like in requests:
            if frozenset(subset) not in self.refits:
                missing.setdefault(frozenset(subset), (subset, like))
        for key, result in zip(missing, self.each([lambda r=r: self.refit(*r) for r in missing.values()])):
            self.refits[key] = result
        return [self.refits[frozenset(subset)] for subset, _ in requests]

    def refit(self, subset: list[str], like: Optional[ValveModel]) -> tuple[ValveModel, Score]:
        """One exact refit of ``subset`` (``refit_many``'s job; uncached): a job for the loop's pool, whose forms
        run on the forms' pool."""
        chosen = {e.name: e for e in like.effects} if like is not None else {}
        effects = [chosen.get(n, self.by_name[n]) for n in subset]
        m = fit_model(self.fit, self.baseline, effects, try_forms={n for n in subset if n not in chosen},
                      cache=self.cache, warm=like, each=self.each_form)
        # nested forms are chosen on held-out data for the effects new to the set, and again for all of them where
        # the set is one the model it starts from had less an effect (a drop-one refit: a form chosen beside one
        # effect, a drift's slow form beside creep, need not be the best without it)
        dropped = like is not None and set(subset) < set(chosen)
        return self.held_out_form(m, subset if dropped else [n for n in subset if n not in chosen])

    def held_out_form(self, model: ValveModel, free: list[str]) -> tuple[ValveModel, Score]:
        """``model`` with each effect of ``free`` that has nested forms (``Effect.held_out_forms``) in the one
        that leaves the lowest held-out RMS, the other effects as ``model`` fitted them (training error cannot
        choose among nested forms: the richest always fits best); with its held-out score."""
        best = (model, self.held_out(model))
        for name in free:
            effect = best[0].term(name)[0]
            others = [f for f in effect.held_out_forms() if f != effect]
            if not others:
                continue
            fits = self.each_form([lambda f=f: fit_model(
                self.fit, self.baseline, [f if e.name == name else e for e in best[0].effects], try_forms=False,
                cache=self.cache, warm=best[0]) for f in others])
            for fit in fits:
                score = self.held_out(fit)
                if score.rms < best[1].rms:
                    best = (fit, score)
        return best

    def search_untrusted(self, current: list[str]) -> bool:
        """Whether the first-order search cannot be trusted to choose or rank effects here: a short record (exact
        refits cost little) or one where the exact refit of ``current`` does worse than the search's figure for it
        by more than SEARCH_TRUST, or delivers less than 1 - SEARCH_TRUST of the cut the search promised for it (the
        search saw a set that is not there: at low sample rates a delay of a sample or two is far from its
        first-order proxy; on a separate session each model has its own start).  A search that
        underrates a set (a large nonlinear structure) chose it rightly: the exact checks that follow add to it."""
        if len(self.fit) <= EXACT_ALL_ROWS:
            return True
        (_, exact), = self.refit_many([(current, None)])
        searched = self.search.score(frozenset(current)).rms
        # ... by its figure, or by the cut it promised from the baseline (the search's own baseline figure may
        # differ from the exact one: a set it credits with half the error gone that the exact refit does not cut):
        # the exact refit delivers less than 1 - SEARCH_TRUST of the share of the error the search said it takes
        # (a share, not what is left: 25 % left where the search said 18 % is 92 % of the cut it promised)
        promised = 1.0 - searched / max(self.search.score(frozenset()).rms, 1e-30)
        delivered = 1.0 - exact.rms / max(self.refits[frozenset()][1].rms, 1e-30)   # the baseline's score, scored once
        return exact.rms > (1 + SEARCH_TRUST) * searched or delivered < (1 - SEARCH_TRUST) * promised

    def forward_selection(self) -> list[str]:
        """Effects chosen by exact refits alone: from the baseline, the effect whose exact refit on top of the set
        is supported and leaves the lowest held-out RMS joins it, until none does (where the search cannot be
        trusted, ``search_untrusted``)."""
        current: list[str] = []
        score = self.held_out(self.baseline)
        while len(current) < len(self.names):
            if not room_for_an_effect(score, self.levels):
                self.log(f"exact selection: nothing more on top of {_set_named(current)}: "
                         f"{no_room_because(score, self.levels)}")
                break
            options = [n for n in self.names if n not in current]
            so_far = self.refit_many([(current, None)])[0][0] if current else None
            fits = self.refit_many([([m for m in self.names if m in current or m == n], so_far) for n in options])
            supported = [(s.rms, n) for n, (_, s) in zip(options, fits) if support(s, score, self.levels).supported]
            supported_fits = [(n, s) for n, (_, s) in zip(options, fits)]
            if not supported:
                self.log(f"exact selection: nothing more on top of {_set_named(current)}: "
                         + "; ".join(f"{n} ({unsupported_because(s, score, self.levels)})"
                                     for n, (_, s) in zip(options, fits)))
                break
            best_rms, best = min(supported)
            self.log(f"exact selection: {best} cuts the held-out RMS {score.rms:.4f} -> {best_rms:.4f} um on top of "
                     f"{_set_named(current)}, {_decided(support(dict(supported_fits)[best], score, self.levels))} "
                     f"(the first-order search is not trusted here)")
            current = [m for m in self.names if m in current or m == best]
            score = self.delay_on_held_out(current)
        return current

    def delay_on_held_out(self, subset: list[str]) -> Score:
        """Where ``subset``'s exact refit has a transport delay, the delay chosen as the capacity is, on held-out
        data: refits with the delay held at the fitted one and DELAY_STEPS analysis samples from it; the best
        replaces the subset's refit (later refits from it hold that delay).  A record of one frequency cannot tell a
        lag from the loop's width, so its training error does not place the delay; a separate session can (as
        system identification chooses a model's dead time on validation data).  Returns the subset's score."""
        (model, score), = self.refit_many([(subset, None)])
        dynamics = next((e for e in model.effects if e.name == "dynamics"), None)
        if dynamics is None or dynamics.delay_held:
            return score
        # a form without a delay (a lag in its place) is tried with one besides its own structures: its whole delay
        # from the samples up
        held = replace(dynamics.with_delay(), delay_held=True)
        effects = [held if e.name == "dynamics" else e for e in model.effects]
        dt = self.fit.dt
        delays = sorted({round(max(model.delay_s + k * dt, 0.0), 12) for k in DELAY_STEPS}
                        | ({round(k * dt, 12) for k in range(1, max(DELAY_STEPS) + 1)} if not dynamics.has("delay")
                           else set()))
        delays = [d for d in delays if d != model.delay_s or not dynamics.has("delay")]

        def job(delay_s: float) -> tuple[ValveModel, Score]:
            # a delay moved from the fitted one: from the fitted structure (its poles, its rate terms), a few
            # Gauss-Newton rounds; a delay in a lag's place: the poles placed afresh (the lag's are a local minimum)
            start = held.carry(model, self.baseline) if dynamics.has("delay") else self.baseline
            start = replace(start, delay_s=delay_s)
            m = fit_model(self.fit, start, effects, try_forms=False, cache=self.cache)
            return m, self.held_out(m)

        tried = self.each([lambda d=d: job(d) for d in delays])
        best_model, best = min(tried, key=lambda t: t[1].rms)
        if best.rms >= score.rms:
            return score
        fitted = f"the {1e3 * model.delay_s:.2f} ms" if dynamics.has("delay") else f"the {dynamics.form} form (no delay)"
        self.log(f"dynamics: transport delay {1e3 * best_model.delay_s:.2f} ms chosen on held-out data over {fitted} "
                 f"the training record fitted ({', '.join(f'{1e3 * m.delay_s:.2f}' for m, _ in tried)} ms tried); "
                 f"held-out RMS {score.rms:.4f} -> {best.rms:.4f} um")
        self.refits[frozenset(subset)] = (best_model, best)
        return best

    def untrusted_or_confirmed(self, searched: list[str]) -> tuple[ValveModel, dict, dict, list[str]]:
        """The search's set confirmed by exact refits (``confirm``); where the search cannot be trusted
        (``search_untrusted``), also the forward selection's, and of the two the one with the lower held-out
        RMS: effects chosen one at a time miss those that are supported only together (a rate-dependent gain
        that a slow lag and a rate term share), the search's set may hold one the exact refits do not want."""
        if not self.search_untrusted(searched):
            return self.confirm(searched)
        forward = self.confirm(self.forward_selection())
        if not searched or set(searched) == set(forward[3]):
            return forward
        confirmed = self.confirm(searched)
        if set(confirmed[3]) == set(forward[3]):
            return forward
        search_score, forward_score = self.held_out(confirmed[0]), self.held_out(forward[0])
        with_search, with_forward = search_score.rms, forward_score.rms
        # effects supported only together must, together, pass the rule an effect added last passes
        together = support(search_score, forward_score, self.levels).supported
        if with_search < with_forward and not together:
            self.log(f"exact selection: the search's {', '.join(searched)}, confirmed as {', '.join(confirmed[3])}, "
                     f"leaves a held-out RMS of {with_search:.4f} um against {with_forward:.4f} um with "
                     f"{', '.join(forward[3]) or 'nothing'} chosen one at a time; together they are not supported "
                     f"({unsupported_because(search_score, forward_score, self.levels)}); "
                     f"{', '.join(forward[3]) or 'nothing'} kept")
            return forward
        if with_search < with_forward:
            self.log(f"exact selection: the search's {', '.join(searched)}, confirmed as "
                     f"{', '.join(confirmed[3]) or 'nothing'}, leaves a held-out RMS of {with_search:.4f} um against "
                     f"{with_forward:.4f} um with {', '.join(forward[3]) or 'nothing'} chosen one at a time "
                     f"(effects supported only together); kept")
            return confirmed
        self.log(f"exact selection: {', '.join(forward[3]) or 'nothing'} chosen one at a time leaves a held-out RMS "
                 f"of {with_forward:.4f} um against {with_search:.4f} um with the search's {', '.join(searched)} "
                 f"confirmed as {', '.join(confirmed[3]) or 'nothing'}; kept")
        return forward

    def exact_options(self, current: list[str]) -> list[str]:
        """Effects outside ``current`` to refit exactly on top of it: those the linear search credits with at least
        EXACT_CHECK_GAIN, or every one where the search cannot be trusted to rank them: on a separate validation
        session where it found nothing (it scores every set from the baseline's start there, which may have taken
        a slow effect's share: each model's own start may not), on a short record (a few refits cost little) or
        where its first-order figure for ``current`` misses the exact refit's by more than
        SEARCH_TRUST (at low sample rates a delay of a sample or two is far from its first-order proxy; a separate
        session's start moves with each model)."""
        linear_base = self.search.score(frozenset(current))
        outside = [n for n in self.names if n not in current]
        if (not self.split.held_out and not current) or self.search_untrusted(current):
            return outside
        return [n for n in outside
                if 1.0 - self.search.score(frozenset(current) | {n}).rms / max(linear_base.rms, 1e-30) >= EXACT_CHECK_GAIN]

    def structure_remains(self, model: ValveModel) -> bool:
        """Whether ``model``'s held-out residual holds structure above UNEXPLAINED_NOISE_RATIO times the sensor noise
        (and above MIN_STRUCTURE_PCT of the range): what the story's end reports as unexplained (``what_remains``,
        which also counts peaks)."""
        return _unexplained_by_rms(_structure(self.error(model), self.split.score.dt, self.levels.analysis_um,
                                              self.range_val))

    def confirm(self, current: list[str]) -> tuple[ValveModel, dict, dict, list[str]]:
        """Backward elimination with exact refits: (final model, drop-one models, verdicts, effects kept)."""
        for _ in range(CONFIRM_ROUNDS):
            if not current:
                return self.baseline, {}, {}, []
            (model, score_model), = self.refit_many([(current, None)])
            # the drop-one refits alone: the exact checks that follow a set are refitted only once it is confirmed
            # (refitted beside them, they were lost whenever an effect was dropped: a dynamics check is six forms)
            dropped = self.refit_many([([m for m in current if m != n], model) for n in current])
            drops, verdicts, withouts = {}, {}, {}
            for n, (without_model, without) in zip(current, dropped):
                drops[n], withouts[n] = without_model, without
                verdicts[n] = Verdict(support(score_model, without, self.levels), without.rms, score_model.rms)
            self.confirm_log.append(ConfirmRound(effects=tuple(current), held_out_rms_um=round(score_model.rms, 6),
                                                 drop_one={n: round(v.support.share, 4) for n, v in verdicts.items()}))
            failing = [n for n in current if not verdicts[n].support.supported]
            if not failing:
                for n in current:
                    self.log(f"confirm: {n} kept, {_decided(verdicts[n].support)}")
                return model, drops, verdicts, current
            weakest = min(failing, key=lambda n: verdicts[n].support.share)
            self.log(f"confirm: {weakest} not supported by the exact refit "
                     f"({unsupported_because(score_model, withouts[weakest], self.levels)}); dropped")
            current = [n for n in current if n != weakest]
        return self.baseline, {}, {}, []

    def polished(self, model: ValveModel) -> ValveModel:
        """``model`` with G_v's poles fitted again through its effects (``refit_poles_with_effects``), once per
        model: the exact checks score against it and the end of ``extend`` takes it."""
        if id(model) not in self.polishes:
            self.polishes[id(model)] = (model, refit_poles_with_effects(self.fit, model, self.cache))
        return self.polishes[id(model)][1]

    def exact_addition(self, current: list[str], final: ValveModel, tried: set[frozenset]) -> Optional[list[str]]:
        """The search judged nonlinear structures to first order, which can underrate a large one: effects whose
        linear estimate shows some gain (``exact_options``) are refitted exactly on top of the confirmed set, and,
        where none of them is supported but the set's model as it would end (its poles refitted where that helps)
        leaves structure that would be reported unexplained (``structure_remains``), every other effect too; the
        set with the best one that is supported (None: none is)."""
        if len(current) == len(self.names):
            return None
        final_score = self.held_out(final)
        if not room_for_an_effect(final_score, self.levels):   # (the polished model's is lower still)
            self.log(f"exact check on top of {_set_named(current)}: none, {no_room_because(final_score, self.levels)}")
            return None
        # against the set as it ends if nothing is added: with G_v's poles fitted again through it (an effect
        # added here must do more than the poles' refit at the end would do anyway)
        polishing = self.pool.submit(self.polished, final)   # beside the refits (it waits for nothing)
        options = [n for n in self.exact_options(current) if frozenset(current + [n]) not in tried]
        refits = self.refit_many([(current + [n], final) for n in options])
        polished = polishing.result()
        polished_score = self.held_out(polished)
        base_score = min(final_score, polished_score, key=lambda s: s.rms)
        best = self._best_supported(options, refits, base_score)
        if best is None and self.structure_remains(polished if polished_score.rms <= final_score.rms else final):
            # something is missing and none of the effects the search credited explains it: its first-order
            # ranking of the rest is what the exact refits are there to overrule (a slow pole beside an asymmetry,
            # which the search credits with nothing (-1 %), cuts a third of the held-out RMS refitted)
            rest = [n for n in self.names if n not in current and n not in options
                    and frozenset(current + [n]) not in tried]
            options, refits = options + rest, refits + self.refit_many([(current + [n], final) for n in rest])
            best = self._best_supported(options, refits, base_score)
        self.exact_checks.setdefault(frozenset(current), {}).update(
            {n: (score, base_score) for n, (_, score) in zip(options, refits)})
        if best is None:
            if options:   # one line for what the exact checks found, not silence after seconds of refits
                self.log(f"exact check on top of {_set_named(current)}: " + "; ".join(
                    f"{n} {base_score.rms:.4f} -> {score.rms:.4f} um, not supported "
                    f"({unsupported_because(score, base_score, self.levels)})"
                    for n, (_, score) in zip(options, refits)) + "; nothing added")
            return None
        self.log(f"exact check: {best[0]} cuts the held-out RMS {base_score.rms:.4f} -> {best[1].rms:.4f} um, "
                 f"{_decided(support(best[1], base_score, self.levels))} (the first-order search underrated it); added")
        return current + [best[0]]

    def _best_supported(self, options: list[str], refits: list[tuple[ValveModel, Score]], base: Score
                        ) -> Optional[tuple[str, Score]]:
        """(effect, held-out score) of the option whose refit on top is supported against ``base`` and leaves the
        lowest held-out RMS; None where none is."""
        best = None
        for n, (_, score) in zip(options, refits):
            if support(score, base, self.levels).supported and (best is None or score.rms < best[1].rms):
                best = (n, score)
        return best

    def better_swap(self, current: list[str], verdicts: dict, tried: set[frozenset]) -> Optional[list[str]]:
        """An effect the record cannot tell apart from an added one (see :func:`_alternatives`) that, put in its
        place, leaves the lower held-out RMS by the exact refits: the set with the two swapped, to be confirmed
        (None: every added effect is the better of its pair).  The search's first-order ranking chose the
        added one; the exact refits decide."""
        best = None
        for alt in _alternatives(current, self.names, verdicts, self.search, self.refit_many, self.by_name):
            a, b, held = alt.effect, alt.alternative, alt.held_out_rms_um
            swapped = [n for n in self.names if n in (set(current) - {a}) | {b}]
            if held["with_" + b] < held["with_" + a] and frozenset(swapped) not in tried \
                    and (best is None or held["with_" + b] < best[3]):
                best = (a, b, swapped, held["with_" + b], held["with_" + a])
        if best is None:
            return None
        a, b, swapped, with_b, with_a = best
        self.log(f"swap: {b} in {a}'s place leaves a held-out RMS of {with_b:.4f} um against {with_a:.4f} um with "
                 f"{a} (the first-order search ranked {a} first); {a} replaced by {b}")
        return swapped

    def story(self, start: Optional[list[str]] = None, extend: bool = True) -> Story:
        """The winning subset (or ``start``) confirmed; then (``extend``) effects the linear search underrated,
        checked exactly, and effects that do better in an added one's place, swapped in (each change confirmed
        again); then G_v's poles again through the effects found.  The final model is never worse on held-out data
        than the baseline (by the one score every decision used: ``held_out``)."""
        if start is None:
            if self._confirmed is None:   # once per choice: a story told again goes on from the same set
                self._confirmed = self.untrusted_or_confirmed([n for n in self.names if n in self.chosen_set])
            final, drop_one, verdicts, current = self._confirmed
        else:
            final, drop_one, verdicts, current = self.confirm([n for n in self.names if n in start])
        tried: set[frozenset] = set()   # sets already put to confirm: each once (an effect added here and dropped
        while extend:                   # by confirm would be added again, and dropped again, forever)
            changed = self.exact_addition(current, final, tried) or self.better_swap(current, verdicts, tried)
            if changed is None:
                break
            tried.add(frozenset(changed))
            confirmed = self.confirm(changed)
            before, after = self.held_out(final).rms, self.held_out(confirmed[0]).rms
            if current and after >= before:   # confirm dropped its way to a set that does worse: keep the last one
                self.log(f"confirm: {', '.join(confirmed[3]) or 'nothing'} left of {', '.join(changed)}, held-out RMS "
                         f"{after:.4f} um against {before:.4f} um with {', '.join(current)}; kept {', '.join(current)}")
                continue
            final, drop_one, verdicts, current = confirmed
        # G_v's poles again through the effects found (creep's fast share bends the baseline's poles)
        polished = self.polished(final)
        if polished is not final:
            before, after = self.held_out(final).rms, self.held_out(polished).rms
            if after <= before:
                self.log(f"G_v: {polished.dynamics_note} with {', '.join(current)} in the model; held-out RMS "
                         f"{before:.4f} -> {after:.4f} um")
                final = polished
                # the drop-one models on the same poles: final minus one of them is that effect's share alone
                drop_one = {n: with_poles(self.fit, m, final.sections, final.dynamics_note, self.cache)
                            for n, m in drop_one.items()}
            else:
                self.log(f"G_v: refitted with {', '.join(current)} ({polished.dynamics_note}) but the held-out RMS "
                         f"rose {before:.4f} -> {after:.4f} um; poles kept")
        if self.held_out(final).rms > self.held_out(self.baseline).rms:
            self.log("the extended model is worse on held-out data than the baseline: baseline kept")
            final, drop_one, current = self.baseline, {}, []
        elif current and self.split.score.block > self.split.score_full.block:
            # decided on block means: the record's own rate must not disagree (what happens faster than the
            # analysis rate resolves, an effect may fit worse)
            before, after = (rms(self.error(m, full=True)) for m in (self.baseline, final))
            if after > before:
                self.log(f"{', '.join(current)} cut the held-out RMS at the analysis rate ({self.split.score.rate_hz:.0f} "
                         f"Hz) but raise it at the record's ({self.split.score_full.rate_hz:.0f} Hz), {before:.4f} -> "
                         f"{after:.4f} um: baseline kept")
                final, drop_one, current = self.baseline, {}, []
        return Story(self.baseline, final, [n for n in self.names if n in current], drop_one, verdicts,
                     self.confirm_log, self)


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


def _alternatives(added: list[str], names: list[str], verdicts: dict, search: "SubsetSearch",
                  refit_many: Callable, by_name: dict[str, Effect]) -> list[Indistinguishable]:
    """Effects the record cannot tell apart: for each added effect a, each effect b outside the final set that,
    put in a's place, explains at least SEPARATION_SHARE of what a explains (its held-out RMS cut from the
    final model without a), by the linear search and then by an exact refit.  The loop names the better of
    the two; the report says that the other would do nearly as well (a closed-loop record whose voltage
    follows the output, or an excitation too narrow to separate their signatures).  Where the linear search gives a
    no cut of its own (it underrated a: the exact checks found it), it cannot screen the others either: every
    effect outside the set is refitted in a's place."""
    found = []
    for a in added:
        rest = frozenset(added) - {a}
        cut_a_linear = 1.0 - search.score(rest | {a}).rms / max(search.score(rest).rms, 1e-30)
        options = [b for b in names if b not in added
                   and (cut_a_linear <= 0.0
                        or 1.0 - search.score(rest | {b}).rms / max(search.score(rest).rms, 1e-30)
                        >= SEPARATION_SHARE * cut_a_linear)]
        if not options:
            continue
        without, with_ = verdicts[a].without_um, verdicts[a].with_um
        cut_a = 1.0 - with_ / max(without, 1e-30)
        for b, (_, swapped) in zip(options, refit_many([([n for n in names if n in rest | {b}], None)
                                                         for b in options])):
            cut_b = 1.0 - swapped.rms / max(without, 1e-30)
            if cut_b >= SEPARATION_SHARE * cut_a:
                found.append(Indistinguishable(
                    effect=a, alternative=b,
                    held_out_rms_um={"without_either": round(without, 6), "with_" + a: round(with_, 6),
                                     "with_" + b: round(swapped.rms, 6)},
                    share=round(cut_b / cut_a, 4) if cut_a > 0 else None,
                    why=f"in {a}'s place {b} cuts the held-out RMS {without:.4f} -> {swapped.rms:.4f} um against "
                        f"{with_:.4f} um with {a} ({100 * cut_b / max(cut_a, 1e-30):.0f} % of its cut, "
                        f"threshold {100 * SEPARATION_SHARE:.0f} %): both signatures fit what this record shows; "
                        f"{a} is named as the better",
                    experiment=f"to tell {a} from {b}, record {by_name[a].telling_experiment} (for {a}), and "
                               f"{by_name[b].telling_experiment} (for {b})"))
    return found


def _evidence(effect: Effect, verdict: "Verdict", noise: NoiseLevels, how: str) -> str:
    sup, c = verdict.support, verdict.support.consistency
    return (f"{effect.signature}; held-out RMS {verdict.without_um:.4f} -> {verdict.with_um:.4f} um with it ({how}): "
            f"{percent(sup.cut, sign=True)} % cut, removing {percent(sup.share)} % of the structured residual "
            f"(threshold {100 * GAIN_THRESHOLD:.0f} %), better in {100 * c.better_share:.0f} % of the held-out "
            f"stretches, losing {percent(min(c.loss_ratio, 9.99))} % of its gain in the others (threshold "
            f"{100 * MAX_LOSS_RATIO:.0f} %, t {c.t:.1f}), explaining {sup.explained_um:.4f} um "
            f"RMS (threshold {MIN_EFFECT_NOISE_RATIO:g}x the sensor noise {noise.record_um:.4f} um)"
            + (f"; decided by: {sup.by}" if sup.by else "; not supported"))


def _decided(sup: Support) -> str:
    """Which evidence supported an effect, in words (for the log)."""
    return f"supported by {sup.by}: {sup.describe()}"


@dataclass(frozen=True)
class Verdict:
    """An effect's exact drop-one check: its :class:`Support` and the held-out RMS without and with it [um]."""
    support: Support
    without_um: float
    with_um: float
