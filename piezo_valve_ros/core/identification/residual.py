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

This module is the loop's face (``analyse``, ``Analysis``, the thresholds of ``thresholds``) and its conductor
(``_Loop.run``); the stages live behind it: ``_start_stage`` (1), ``_capacity_stage`` (1b), ``_effect_choice``
(2 and 3), ``_report_stage`` (4 and the report), and ``_stages`` what they hand each other.
"""
from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Optional

import numpy as np

from .fitting import FitCache, fit_model, uniform_thresholds
from ..model.hysteresis import GPIM
from .noise import estimate_noise_floor
from .initial_state import session_start
from .report import AnalysedRecord, AnalysedWhole, IdentificationReport, LeftOut
from .records import ANALYSIS_RATE_HZ, HELD_OUT_FRACTION, MAX_ANALYSED_S, SUPPORTED_RATE_HZ, Record, analysis_record
from .search import GAIN_THRESHOLD, MIN_EFFECT_NOISE_RATIO, PEAK_TOLERANCE, NoiseLevels, Score  # noqa: F401
from .split import SessionStart, Split, split_records
from ..blas import one_blas_thread
from ..defaults import analysis_threads
from ..metrics import rms
from .valve_model import REST, InitialState, ValveModel
from .thresholds import *  # noqa: F401,F403  (the loop's thresholds, read here by tests and benches)
from .thresholds import MID_CAPACITY, RESOLUTION_SHARE, UNEXPLAINED_NOISE_RATIO
from ._stages import _beside, _on_pool
from ._capacity_stage import CapacityStage
from ._effect_choice import _EffectChoice
from ._report_stage import ReportStage
from ._start_stage import StartStage
from ._whole_record_stage import WholeRecordStage

__all__ = ["analyse", "Analysis", "Split", "GAIN_THRESHOLD", "MIN_EFFECT_NOISE_RATIO", "UNEXPLAINED_NOISE_RATIO",
           "CAPACITY_OPERATORS", "CAPACITY_EXTENSION", "HELD_OUT_FRACTION", "MID_CAPACITY"]


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


def analyse(train_full: Record, validate_full: Optional[Record] = None, *, max_rate_hz: float = ANALYSIS_RATE_HZ,
            log: Callable[[str], None] = lambda s: None, threads: Optional[int] = None,
            whole: Optional[Record] = None, analysed_s: float = MAX_ANALYSED_S) -> Analysis:
    """Fit, diagnose and extend; ``validate_full`` None holds out the last ``HELD_OUT_FRACTION`` of the record.

    A training record longer than ``analysed_s`` [s] is analysed on its first ``analysed_s``, and its whole length at
    the analysis rate judges a slow trend (``whole_record``): ``whole`` is that whole record already reduced to the
    analysis rate (``whole_record.BlockMeans``, as ``identify_bags`` streams a bag), where ``train_full`` holds only
    its first stretch; None reduces ``train_full`` itself.

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
        return _Loop(train_full, validate_full, max_rate_hz, log, pool, forms_pool, whole, analysed_s).run()


class _Loop(StartStage, CapacityStage, WholeRecordStage, ReportStage):
    """One run of the residual loop on one pair of records; ``run`` takes the stages of the module's
    docstring in order and returns the :class:`Analysis`.  Each stage returns what it found (``StartChoice``,
    ``CapacityChoice``, ``Story``, ``Remains``) to the stages after it; the instance holds what they all share:
    the records and their split (``split`` is replaced once, as the initial state is settled: the cut after
    the wipe), the noise, the caches and the warnings."""

    def __init__(self, train_full: Record, validate_full: Optional[Record], max_rate_hz: float,
                 log: Callable[[str], None], pool: ThreadPoolExecutor, forms_pool: ThreadPoolExecutor,
                 whole: Optional[Record] = None, analysed_s: float = MAX_ANALYSED_S):
        self.started = time.monotonic()
        self.analysed_s = analysed_s
        self.log, self.pool, self.forms_pool = log, pool, forms_pool
        self.warnings: list[str] = []
        self.known_rows: Optional[int] = None   # held-out rows before the input first leaves the fit part's range
        self.start_left_out: Optional[LeftOut] = None   # a validation session's first rows left out (in motion)
        self.analysed: dict[str, AnalysedRecord] = {}   # what of each record the loop analysed (the report's)
        whole_rows = len(train_full) if whole is None else None
        part = self.representative_part(train_full, "train", "training record", whole)
        if part is not train_full or (whole is not None and whole.time_s[-1] > part.time_s[-1]):
            self.whole = analysis_record(train_full, max_rate_hz) if whole is None else whole
            self.analysed["train"] = replace(self.analysed["train"], whole_record=AnalysedWhole(
                from_s=float(self.whole.time_s[0]), to_s=float(self.whole.time_s[-1]), rows=len(self.whole),
                rate_hz=round(self.whole.rate_hz, 3), samples=whole_rows))
        train_full = part
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
        self.levels = NoiseLevels(self.noise, self.noise / math.sqrt(block), known=self.floor.known)
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
    def representative_part(self, record: Record, key: str, what: str, whole: Optional[Record] = None) -> Record:
        """The part of ``record`` the loop analyses: its first ``analysed_s`` (MAX_ANALYSED_S: a record of repeated
        experiments shows its valve's fast parts in its first minutes as well as in hours; the loop's memory grows
        with what it analyses); kept in ``analysed[key]`` and said in a warning where that is not all of it.  The
        training record's whole length (``whole``: already reduced, where ``record`` is only its start) is searched
        for a slow trend (stage 3b)."""
        part = record.first(self.analysed_s)
        duration = record.duration_s if whole is None else float(whole.time_s[-1] - record.time_s[0] + record.dt)
        of = len(record) if whole is None else len(whole) * whole.block   # (source rows, less a partial block)
        self.analysed[key] = AnalysedRecord(from_s=float(part.time_s[0]), to_s=float(part.time_s[-1]),
                                            samples=len(part), of_samples=of, record_duration_s=duration)
        if part is not record or (whole is not None and duration > part.duration_s + 2 * record.dt):
            if key == "train":
                self.warnings.append(f"the {what} is {duration:.0f} s long: its first {part.duration_s:.0f} s were "
                                     f"analysed for the model's fast parts (MAX_ANALYSED_S; the loop's memory and time "
                                     f"grow with what it analyses), and all of it, at the analysis rate, for a slow "
                                     f"trend (drift): the report's whole_record and figures_from say which figure "
                                     f"comes from where")
            else:
                self.warnings.append(f"the {what} is {duration:.0f} s long: its first {part.duration_s:.0f} s "
                                     f"({len(part)} samples) were analysed (MAX_ANALYSED_S; the loop's memory and "
                                     f"time grow with what it analyses)")
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

    def each_beside(self, jobs: list[Callable[[], object]]) -> list:
        """Independent parts of one fit (a new pole pair's placements and their refinements: ``fit_model``'s
        ``beside``), from whatever thread runs it: the first in that thread, the others on a refit thread that is
        free (a refit that waits for its forms leaves its own idle), else after it in that thread (``_beside``)."""
        return _beside(self.pool, jobs)

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
        story = self.whole_record_story(story)   # a long record: its whole length judges a slow trend
        remains = self.what_remains(story)
        report = self.report(start, capacity, story, remains)
        return Analysis(report, capacity.baseline, story.final, self.split, story.drop_one, self.sessions)
