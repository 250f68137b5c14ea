"""The records of one analysis: the fit part and the held-out part, at the analysis rate and the record's own,
and where the input has wiped out an unknown state before the record.  Nothing here imports ROS."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from .records import (HELD_OUT_FRACTION, MIN_SAMPLES, IdentificationError, Record, analysis_record,
                      split_held_out)
from ..model.hysteresis import turning_points
from .valve_model import InitialState, ValveModel

__all__ = ["Split", "SessionStart", "split_records", "wipe_index", "first_rows", "WIPE_MARGIN", "WIPE_MAX_SHARE", "ESTIMATE_WINDOW_S"]

WIPE_MARGIN = 0.02                          # the input has wiped the unknown initial state once it has come this
                                            # close (share of its span) to both extremes of the fit part
WIPE_MAX_SHARE = 0.9                        # ... which must happen before the last tenth of the fit part (held-out
                                            # data then decide whether fitting after it pays, WIPE_GAIN)
ESTIMATE_WINDOW_S = 2.0  # ... on the rows before the wipe, at most this long (the start shows first)


def wipe_index(record: Record) -> int:
    """Row of ``record`` (analysis rate) from which its input has wiped out the operators' unknown state before
    it: it has come within ``WIPE_MARGIN`` of both its extremes."""
    v = record.voltage_v
    lo, hi = float(np.min(v)), float(np.max(v))
    margin = WIPE_MARGIN * (hi - lo)
    return max(int(np.argmax(v >= hi - margin)), int(np.argmax(v <= lo + margin)))


def first_rows(record: Record) -> Record:
    """The rows of ``record`` (analysis rate) a start is estimated on: before its input wiped the state out, at most
    ``ESTIMATE_WINDOW_S`` and at least ``MIN_SAMPLES``."""
    return record.slice(0, min(max(wipe_index(record), MIN_SAMPLES), max(int(ESTIMATE_WINDOW_S / record.dt),
                                                                          MIN_SAMPLES)))


@dataclass(frozen=True)
class SessionStart:
    """How a model is started on a separate session (a validation record): the operators' states and G's settled
    output before it (``history``), and the session's sensor offset [um] relative to the training record's (a
    re-zeroed sensor), with the rows the start was estimated on and the model's error RMS there about that offset
    (``initial_state.session_start``)."""

    history: InitialState
    offset_um: float
    rows: int
    first_rows_rms_um: float


@dataclass(frozen=True)
class Split:
    """The fit and held-out records, at the analysis rate and at the record's own rate.

    ``score`` is what the model runs over to be scored from row ``start`` on: the whole training record
    (the held-out tail continues the fit part, the operators keep their memory) or the validation record.
    """

    fit: Record
    score: Record
    start: int
    t0: float             # time origin of the fit (drift terms)
    score_t0: float
    fit_full: Record
    score_full: Record
    start_full: int
    held_out: bool
    wiped_at_s: Optional[float] = None   # record time [s] the fit starts at when cut after the wipe (after_wipe)

    def wipe_index(self, record: Optional[Record] = None) -> int:
        """Row of the fit record (or ``record``): ``wipe_index``."""
        return wipe_index(self.fit if record is None else record)

    def first_rows(self, record: Record) -> Record:
        """``first_rows`` of ``record``."""
        return first_rows(record)

    def after_wipe(self) -> Optional[tuple["Split", InitialState]]:
        """The split with the fit part cut where its input has wiped out the operators' unknown state before
        the record (it has been within ``WIPE_MARGIN`` of both its extremes: every operator below that much
        of half the span has forgotten it), with the initial state that the cut part's input path leaves
        (``InitialState`` "remanent": exact but for the operators the record never fully moves).  None for a
        validation record, or when the wipe comes later than ``WIPE_MAX_SHARE`` of the fit part."""
        if not self.held_out:
            return None
        w = self.wipe_index()
        if w == 0 or w > WIPE_MAX_SHARE * len(self.fit):
            return None
        w_full = w * (self.fit.block // max(self.fit_full.block, 1))
        try:
            self.fit_full.slice(w_full).check("training part after the wipe")
        except IdentificationError:
            return None
        history = InitialState("remanent", turning_points(self.fit_full.voltage_v[:w_full + 1]))
        t0 = float(self.fit.time_s[w])
        cut = Split(self.fit.slice(w), self.score.slice(w), self.start - w, t0, t0, self.fit_full.slice(w_full),
                    self.score_full.slice(w_full), self.start_full - w_full, True, float(self.fit_full.time_s[w_full]))
        return cut, history

    def held_out_error(self, model: ValveModel, full: bool = False, session: Optional[SessionStart] = None) -> np.ndarray:
        """The held-out error [um]; on a separate session ``session`` gives the model's start there and that
        session's offset (taken off)."""
        rec, start = (self.score_full, self.start_full) if full else (self.score, self.start)
        if session is None:
            return rec.position_um[start:] - model.predict(rec, self.score_t0)[start:]
        scored = replace(model, history=session.history)
        return rec.position_um[start:] - scored.predict(rec, self.score_t0)[start:] - session.offset_um

    def fit_error(self, model: ValveModel, full: bool = False) -> np.ndarray:
        rec = self.fit_full if full else self.fit
        return rec.position_um - model.predict(rec, self.t0)


def split_records(train: Record, validate: Optional[Record], max_rate_hz: float) -> Split:
    train = train.check("training record").check_rising("training record")
    block = analysis_record(train, max_rate_hz).block
    if validate is None:
        cut = split_held_out(train, HELD_OUT_FRACTION, block)
        pct = f"{100 * HELD_OUT_FRACTION:.0f} %"
        train.slice(0, cut).check(f"training part (first {100 - 100 * HELD_OUT_FRACTION:.0f} %)")
        train.slice(cut).check(f"held-out part (last {pct})", min_samples=50, min_reversals=1)
        whole = analysis_record(train, max_rate_hz)
        n_fit = cut // block
        t0 = float(whole.time_s[0])
        return Split(whole.slice(0, n_fit), whole, n_fit, t0, t0, train.slice(0, cut), train, cut, True)
    validate = validate.check("validation record", min_samples=50)
    fit = analysis_record(train, max_rate_hz)
    score = analysis_record(validate, max_rate_hz)
    return Split(fit, score, 0, float(fit.time_s[0]), float(score.time_s[0]), train, validate, 0, False)
