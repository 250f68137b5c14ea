"""Valve health from everyday operation: does the valve still match the model the controller runs?

The controller's model (:class:`~..control.compensation.CompensationModel`) runs forwards on the applied
voltage (:class:`~..control.forward.ModelValve`, one state from the first sample on); on each window its
residual against the measured position is judged against the sensor noise measured on the same window:

* the operators' state at the first sample is estimated from the first ``START_ROWS_S`` as the residual
  loop estimates a record's start (rest, cycled, rested at another voltage, back from an excursion), and
  the prediction settles for ``step_s`` before anything is judged; what remains of the unknown state
  before the monitor started (operators the input never moves) is a constant:
  their share of the prediction is a constant, measured as the residual's median on the first window judged
  (the *reference offset*) and taken off every later window, for later models too: the monitor watches for
  change since it started, not for an offset the model carried then;
* structured residual = sqrt(RMS^2 - noise^2) of the residual less the reference offset; above
  ``warn_ratio`` x the noise: WARN, above ``error_ratio`` x: ERROR;
* a window whose voltage spans less than ``min_span_v`` (a valve held still) cannot be judged: STALE;
* from WARN on, the window's held-out part (its last 30 %) names what the residual resembles: a gain change
  (a term in proportion to the prediction's swing, with an offset, takes ``REFIT_SHARE`` of its RMS and
  ``GAIN_SHARE`` of what an offset alone leaves: drift), an offset the model lacks (a constant takes
  ``REFIT_SHARE``: drift), the model's own parameters (the residual
  loop's subset search, ``identification.search.SubsetSearch``, refits the GPIM on the window's first 70 %
  and that takes ``REFIT_SHARE``), a catalogue effect that cuts the refit's held-out RMS by
  ``RESEMBLANCE_GAIN`` more, or none of them;
* where it names a gain change, the correction a push would make (:class:`GainCorrection`) is fitted on the
  window's first ``GAIN_FIT_SHARE`` and scored on the rest, where the prediction must span ``GAIN_SPAN_SHARE`` of
  the model's output range (else a gain cannot be told from an offset), the correction must cut the held-out
  RMS by ``PUSH_CUT``, do better there than an offset alone and agree with the held-out part's own gain;
* the first window after a model change is also predicted by the model before it, from the same state: the
  verdict carries that model's residual RMS on the same rows (``previous_model_rms_um``), which says whether the
  change made things worse.

Nothing here imports ROS: the ``valve_monitor`` node and ``valve_identify --monitor`` are thin faces over it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Optional

import numpy as np

from ..control.compensation import CompensationModel
from ..control.forward import ModelValve
from ..identification import effects as _effects
from ..identification.initial_state import estimate_state
from ..identification.records import ANALYSIS_RATE_HZ, IdentificationError, Record, analysis_record, noise_floor_um
from ..identification.search import SubsetSearch
from ..identification.split import split_records
from ..identification.valve_model import InitialState, ValveModel
from ..model.hysteresis import dominant_turning_points
from ..metrics import rms
from ..model.drive import COMMAND_MAX_V, COMMAND_MIN_V
from ..model.dynamics import sections
from ..validation import NON_NEGATIVE, POSITIVE, field_problems, ruled

__all__ = ["Level", "HealthLimits", "Health", "HealthMonitor", "WINDOW_S", "WARN_RATIO", "ERROR_RATIO",
           "MIN_SPAN_V", "RESEMBLANCE_GAIN", "REFIT_SHARE", "GAIN_SHARE", "SEARCH_RATE_HZ", "GainCorrection",
           "GAIN_FIT_SHARE", "GAIN_SPAN_SHARE", "GAIN_AGREEMENT", "PUSH_CUT", "OFFSET_PREFIX", "GAIN_PREFIX"]

WINDOW_S = 20.0           # judged windows are this long [s] ...
STEP_S = 5.0              # ... and one is judged this often [s]
WARN_RATIO = 2.0          # structured residual RMS above this many times the sensor noise: WARN ...
ERROR_RATIO = 5.0         # ... above this many: ERROR
MIN_SPAN_V = 0.5          # a window whose voltage spans less [V] does not excite the valve enough to judge
RESEMBLANCE_GAIN = 0.2    # a catalogue effect resembles the residual when it cuts the window's held-out RMS by this
REFIT_SHARE = 0.5         # "the model's own parameters" when a GPIM refit on the window takes this share of the RMS
GAIN_SHARE = 0.2          # a gain change (not an offset) when a gain term takes this share of what an offset leaves
GAIN_CHANGE_MAX = 0.5     # ... and changes the gain by at most this share: more is a residual regressed on a swing
                          # too small to carry it (a valve held still in the held-out part), not a drifting gain
SEARCH_RATE_HZ = 500.0    # the window's subset search runs on block means at most this rate [Hz]
START_ROWS_S = 2.0        # the operators' state at the first sample is estimated on this much of the first rows [s]
OFFSET_PREFIX = "drift: an offset"   # how a residual a constant explains is named (what refit_when can push)
GAIN_PREFIX = "drift: a gain change"   # ... and one a gain and an offset explain
GAIN_FIT_SHARE = 0.7      # a gain correction is fitted on a window's first this share and scored on the rest ...
GAIN_SPAN_SHARE = 0.25    # ... where the prediction spans this share of the model's output range in both parts ...
GAIN_AGREEMENT = 0.3      # ... and the held-out part's own gain must agree with it to this share of the larger
PUSH_CUT = 0.5            # ... and it must take this share of the held-out RMS to be pushed (a gain still changing
                          # within the window is fitted at its mean and leaves more: pushed on a later window)


class Level(IntEnum):
    """diagnostic_msgs/DiagnosticStatus levels."""
    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class HealthLimits:
    window_s: float = ruled(WINDOW_S, POSITIVE)
    step_s: float = ruled(STEP_S, POSITIVE)
    warn_ratio: float = ruled(WARN_RATIO, POSITIVE)
    error_ratio: float = ruled(ERROR_RATIO, POSITIVE)
    min_span_v: float = ruled(MIN_SPAN_V, NON_NEGATIVE)

    @property
    def first_verdict_s(self) -> float:
        """Samples [s] the first verdict needs: the prediction settles for a step, then rows are held a step at a
        time until a window is full."""
        return self.step_s * (1 + math.ceil(self.window_s / self.step_s - 1e-9))

    def problems(self) -> list[str]:
        out = field_problems(self)
        if not out and self.step_s > self.window_s:
            out.append(f"step_s ({self.step_s} s) must not exceed window_s ({self.window_s} s)")
        if not out and self.error_ratio <= self.warn_ratio:
            out.append(f"error_ratio ({self.error_ratio}) must exceed warn_ratio ({self.warn_ratio})")
        return out


def _gain_fit(residual_um: np.ndarray, predicted_um: np.ndarray) -> tuple[float, float, float]:
    """(level [um], gain, about [um]): the residual regressed on a constant and the prediction's swing about its mean
    ``about`` (a gain change, with an offset)."""
    about = float(np.mean(predicted_um))
    design = np.column_stack((np.ones(predicted_um.size), predicted_um - about))
    (level, gain), *_ = np.linalg.lstsq(design, residual_um, rcond=None)
    return float(level), float(gain), about


@dataclass(frozen=True)
class GainCorrection:
    """The gain change a window determines: the prediction's swing about ``about_um`` scaled by ``1 + gain`` and
    moved by ``level_um`` [um], fitted on the window's first ``GAIN_FIT_SHARE``; the residual RMS [um] of its
    held-out rest with the model in force and with the correction; ``span_share`` the prediction's span in the
    poorer part as a share of the model's output range; ``refused`` why the window does not support a push ("":
    it does)."""

    gain: float
    level_um: float
    about_um: float
    held_out_rms_in_force_um: float
    held_out_rms_corrected_um: float
    span_share: float
    refused: str

    @property
    def cut(self) -> float:
        """The share of the held-out RMS the correction takes."""
        return 1.0 - self.held_out_rms_corrected_um / max(self.held_out_rms_in_force_um, 1e-30)

    def applied_to(self, model: CompensationModel) -> CompensationModel:
        """``model`` with the correction in: its GPIM weights scaled by ``1 + gain`` (what the model's output swings
        scales with them: the GPIM, creep's lags of it, G_v), its offset set so the prediction moves as fitted
        (``(1 + g) p + level - g about`` for a prediction p; exact where the model is linear in the GPIM's output,
        to first order through an output map: the next window's check catches the rest)."""
        g = model.gpim
        gpim = replace(g, weights=g.weights * (1.0 + self.gain),
                       offset_um=(1.0 + self.gain) * g.offset_um + self.level_um - self.gain * self.about_um)
        return replace(model, gpim=gpim)

    def describe(self) -> str:
        return (f"gain {100.0 * self.gain:+.2f} % about {self.about_um:.2f} um and {self.level_um:+.3f} um, fitted on "
                f"the window's first {100 * GAIN_FIT_SHARE:.0f} %: held-out RMS {self.held_out_rms_in_force_um:.4f} "
                f"-> {self.held_out_rms_corrected_um:.4f} um ({100.0 * self.cut:.0f} % cut), the prediction spanning "
                f"{100.0 * self.span_share:.0f} % of the output range")


@dataclass(frozen=True)
class Health:
    """One window's verdict.  Positions [um], voltages [V], times [s] (the record's)."""

    level: Level
    start_s: float
    end_s: float
    residual_rms_um: float        # of the residual less the reference offset
    residual_mean_um: float       # ... its mean (a drift shows here)
    structured_rms_um: float
    noise_um: float
    ratio: float                  # structured RMS / noise
    voltage_span_v: float
    reference_offset_um: float
    resembles: str                # "" below WARN
    resembles_cut: float          # the held-out RMS cut that named it (0 when nothing did)
    message: str
    correction: Optional[GainCorrection] = None   # where a gain change is named: the push it would make
    previous_model_rms_um: Optional[float] = None  # the first window after a model change: the model before it

    def values(self) -> dict[str, str]:
        """Key-value pairs for a diagnostics status."""
        return {"window_s": f"{self.start_s:.3f}..{self.end_s:.3f}", "residual_rms_um": f"{self.residual_rms_um:.4f}",
                "residual_mean_um": f"{self.residual_mean_um:.4f}", "structured_rms_um": f"{self.structured_rms_um:.4f}",
                "noise_um": f"{self.noise_um:.4f}", "ratio_to_noise": f"{self.ratio:.2f}",
                "voltage_span_v": f"{self.voltage_span_v:.3f}", "reference_offset_um": f"{self.reference_offset_um:.4f}",
                "resembles": self.resembles, "resembles_cut": f"{self.resembles_cut:.3f}",
                **({"gain_correction": self.correction.describe() + (f"; not pushed: {self.correction.refused}"
                                                                     if self.correction.refused else "")}
                   if self.correction is not None else {}),
                **({"previous_model_rms_um": f"{self.previous_model_rms_um:.4f}"}
                   if self.previous_model_rms_um is not None else {})}

    def as_dict(self) -> dict:
        return {"level": self.level.name, "start_s": self.start_s, "end_s": self.end_s,
                "residual_rms_um": self.residual_rms_um, "residual_mean_um": self.residual_mean_um,
                "structured_rms_um": self.structured_rms_um, "noise_um": self.noise_um, "ratio": self.ratio,
                "voltage_span_v": self.voltage_span_v, "reference_offset_um": self.reference_offset_um,
                "resembles": self.resembles, "resembles_cut": self.resembles_cut, "message": self.message,
                "correction": None if self.correction is None else self.correction.__dict__.copy(),
                "previous_model_rms_um": self.previous_model_rms_um}


class HealthMonitor:
    """Feed it the rows of ``samples`` (time [s], voltage [V], position [m]) as they come (``add``); it
    returns a :class:`Health` for every ``limits.step_s`` of data once a window is full.  ``set_model``
    swaps the model in force (a refit pushed to the controller): the prediction restarts from the state
    the voltage history leaves.  Memory is bounded by the window and the voltage's nested extrema."""

    def __init__(self, model: CompensationModel, dt: float, limits: HealthLimits = HealthLimits(),
                 command_range_v: tuple[float, float] = (COMMAND_MIN_V, COMMAND_MAX_V)):
        problems = limits.problems() + ([] if math.isfinite(dt) and dt > 0 else [f"dt must be > 0, got {dt}"])
        if not (len(command_range_v) == 2 and command_range_v[0] < command_range_v[1]):
            problems.append(f"command_range_v must be (low, high) with low < high, got {command_range_v}")
        if problems:
            raise ValueError("; ".join(problems))
        self.limits, self.dt, self.command_range_v = limits, float(dt), tuple(float(x) for x in command_range_v)
        self._window = max(int(round(limits.window_s / dt)), 10)
        self._step = max(int(round(limits.step_s / dt)), 1)
        # time, voltage, measured [um], predicted [um], predicted by the model before the last change [um]
        self._rows = np.empty((self._window + self._step, 5))
        self._count = 0            # rows held
        self._since_judged = 0
        self._history: tuple[float, ...] = ()   # turning points [V] of the voltage before the rows held
        self._valve: Optional[ModelValve] = None
        self._previous: Optional[CompensationModel] = None   # the model before the last change, until a verdict
        self._previous_valve: Optional[ModelValve] = None    # ... run beside the model in force from the same state
        self._offset: Optional[float] = None
        self._warm_up = self._step   # rows after a (re)start that settle the prediction and are not judged
        self._pending: list[np.ndarray] = []   # the first rows, until the state before them is estimated
        self.start_state = None                # that estimate (an identification.valve_model.InitialState)
        self.model = model

    @property
    def held(self) -> tuple[int, int]:
        """(rows held, turning points of the voltage before them kept): bounded by the window and by the
        nesting of the voltage's extrema, however long the monitor runs."""
        return self._count + sum(len(p) for p in self._pending), len(self._history)

    def set_model(self, model: CompensationModel) -> None:
        """The model in force from the next row on: the rows held so far (predicted by the old one) are
        dropped, remembering where their voltage turned.  The reference offset stays: it is what the state
        before the monitor started left, not part of a model, and a refit that leaves an offset must show.  Until the
        next verdict the model before it runs beside it from the same state: that verdict carries its residual
        RMS on the same rows (``Health.previous_model_rms_um``)."""
        self._history = self._before(self._count)
        self._count = self._since_judged = 0
        self._previous = self.model
        self.model, self._valve, self._previous_valve, self._warm_up = model, None, None, self._step

    def _before(self, row: int) -> tuple[float, ...]:
        """Turning points [V] of the voltage before held row ``row``."""
        if not row:
            return self._history
        return dominant_turning_points(np.concatenate([self._history, self._rows[:row, 1]]))

    def _valve_for(self, v0: float, model: Optional[CompensationModel] = None) -> ModelValve:
        """``model``'s (default: the model in force) forward run, its operators in the state the voltage so far
        leaves."""
        model = self.model if model is None else model
        history = self._before(self._count)
        state = model.gpim.state_after(dominant_turning_points(np.asarray(history + (v0,))))
        return ModelValve(model, self.dt, v0, state)

    def _first_valve(self, rows: np.ndarray) -> ModelValve:
        """The forward run from the first rows: the state before them estimated as the residual loop does
        (``initial_state.estimate_state``: rest, cycled, rested at another voltage, back from an excursion,
        searched over the command range) with the model's GPIM and G_v; its turning points start the voltage
        history."""
        record = analysis_record(Record(rows[:, 0], rows[:, 1], rows[:, 2] * 1e6), ANALYSIS_RATE_HZ)
        model = ValveModel(self.model.gpim, tuple(sections(self.model.valve_model)), t0=float(rows[0, 0]))
        self.start_state, _ = estimate_state(model, record, record, range_v=self.command_range_v)
        v = rows[:, 1]
        state = self.start_state.states(self.model.gpim, v)
        if self.start_state.kind == "remanent":
            self._history = self.start_state.turning_points_v
        elif self.start_state.kind == "cycled":
            self._history = (float(np.min(v)), float(np.max(v))) if v[0] >= 0.5 * (np.min(v) + np.max(v)) \
                else (float(np.max(v)), float(np.min(v)))
        return ModelValve(self.model, self.dt, float(v[0]), state)

    def add(self, rows: np.ndarray) -> list[Health]:
        """Rows (N, 3) of time [s], voltage [V], position [m]; the verdicts of the windows they complete."""
        rows = np.asarray(rows, float)
        if rows.ndim != 2 or rows.shape[1] != 3:
            raise ValueError(f"rows must be (N, 3): time, voltage, position; got shape {rows.shape}")
        out = []
        if self._valve is None and not self._history and not self._count:   # the very first rows
            self._pending.append(rows)
            if sum(len(p) for p in self._pending) * self.dt < START_ROWS_S:
                return out
            rows, self._pending = np.concatenate(self._pending), []
            self._valve = self._first_valve(rows)
        while rows.size:
            room = self._step - self._since_judged
            part, rows = rows[:room], rows[room:]
            if self._valve is None:
                self._valve = self._valve_for(float(part[0, 1]))
                if self._previous is not None:
                    self._previous_valve = self._valve_for(float(part[0, 1]), self._previous)
            predicted = self._valve.run(part[:, 1]) * 1e6
            previous = self._previous_valve.run(part[:, 1]) * 1e6 if self._previous_valve is not None \
                else np.full(len(part), np.nan)
            if self._warm_up:   # the prediction settles from the assumed start: not judged
                self._warm_up = max(self._warm_up - len(part), 0)
                self._history = dominant_turning_points(np.concatenate([self._history, part[:, 1]]))
                continue
            self._append(np.column_stack([part[:, 0], part[:, 1], part[:, 2] * 1e6, predicted, previous]))
            self._since_judged += len(part)
            if self._since_judged >= self._step:
                self._since_judged = 0
                if self._count >= self._window:
                    out.append(self.judge())
        return out

    def _append(self, block: np.ndarray) -> None:
        n = len(block)
        if self._count + n > len(self._rows):   # drop the oldest rows, remembering where their voltage turned
            drop = self._count + n - len(self._rows)
            self._history = self._before(drop)
            self._rows[:self._count - drop] = self._rows[drop:self._count]
            self._count -= drop
        self._rows[self._count:self._count + n] = block
        self._count += n

    def judge(self) -> Health:
        """The verdict on the latest window."""
        first = max(self._count - self._window, 0)
        w = self._rows[first:self._count, :4]
        t, v, y, predicted = w[:, 0], w[:, 1], w[:, 2], w[:, 3]
        noise = noise_floor_um(y)
        span = float(np.ptp(v))
        e = y - predicted
        if self._offset is None and span >= self.limits.min_span_v:
            self._offset = float(np.median(e))
        offset = 0.0 if self._offset is None else self._offset
        e = e - offset
        total = rms(e)
        previous_rms = None
        if self._previous_valve is not None:   # the first verdict since the model changed: the one before, beside it
            previous_rms = rms(y - self._rows[first:self._count, 4] - offset)
            self._previous = self._previous_valve = None
        structured = math.sqrt(max(total * total - noise * noise, 0.0))
        ratio = structured / noise if noise > 0 else math.inf
        base = dict(start_s=float(t[0]), end_s=float(t[-1]), residual_rms_um=total, residual_mean_um=float(np.mean(e)),
                    structured_rms_um=structured, noise_um=noise, ratio=ratio, voltage_span_v=span,
                    reference_offset_um=offset, previous_model_rms_um=previous_rms)
        if span < self.limits.min_span_v:
            return Health(Level.STALE, resembles="", resembles_cut=0.0,
                          message=f"not enough excitation to judge: the voltage spans {span:.3g} V "
                                  f"(needs {self.limits.min_span_v:g} V)", **base)
        if ratio < self.limits.warn_ratio:
            return Health(Level.OK, resembles="", resembles_cut=0.0,
                          message=f"matches the model: structured residual {structured:.3f} um, {ratio:.1f}x the "
                                  f"noise (WARN at {self.limits.warn_ratio:g}x)", **base)
        level = Level.ERROR if ratio >= self.limits.error_ratio else Level.WARN
        resembles, cut = self.resemblance(w, self._before(first))
        correction = self.gain_correction(w) if resembles.startswith(GAIN_PREFIX) else None
        return Health(level, resembles=resembles, resembles_cut=cut, correction=correction,
                      message=f"the valve no longer matches its model: structured residual {structured:.3f} um, "
                              f"{ratio:.1f}x the noise (mean {np.mean(e):+.3f} um); resembles {resembles}", **base)

    def gain_correction(self, window: np.ndarray) -> GainCorrection:
        """The gain change ``window`` (rows of time [s], voltage [V], measured and predicted position [um])
        determines, fitted on its first GAIN_FIT_SHARE (the residual less the reference offset regressed on a
        constant and the prediction's swing) and scored on the rest.  Refused where the prediction spans less than
        GAIN_SPAN_SHARE of the model's output range in either part, the gain exceeds GAIN_CHANGE_MAX, the held-out
        RMS is cut by less than PUSH_CUT, the gain does not take GAIN_SHARE of what an offset alone (fitted on the
        same rows) leaves there, or the held-out part's own gain differs from it by more than GAIN_AGREEMENT of
        the larger (a drift still setting in within the window, which a swing-proportional term follows by
        chance)."""
        y, predicted = window[:, 2], window[:, 3]
        e = y - predicted - (self._offset or 0.0)
        cut_at = int(round(GAIN_FIT_SHARE * len(e)))

        level, gain, about = _gain_fit(e[:cut_at], predicted[:cut_at])
        _, held_gain, _ = _gain_fit(e[cut_at:], predicted[cut_at:])
        held = e[cut_at:]
        corrected = held - level - gain * (predicted[cut_at:] - about)
        offset_alone = rms(held - float(np.mean(e[:cut_at])))
        lo, hi = self.model.gpim.output_range(*self.command_range_v)
        share = min(float(np.ptp(predicted[:cut_at])), float(np.ptp(predicted[cut_at:]))) / max(hi - lo, 1e-12)
        correction = GainCorrection(gain, level, about, rms(held), rms(corrected), share, "")
        refused = (f"the prediction spans {100 * share:.0f} % of the output range (needs {100 * GAIN_SPAN_SHARE:.0f} %"
                   " in both parts of the window): a gain cannot be told from an offset" if share < GAIN_SPAN_SHARE
                   else f"a gain change of {100 * gain:+.0f} % is not a drift (at most {100 * GAIN_CHANGE_MAX:.0f} %)"
                   if abs(gain) > GAIN_CHANGE_MAX
                   else f"it cuts the held-out RMS by {100 * correction.cut:.0f} % (needs {100 * PUSH_CUT:.0f} %)"
                   if correction.cut < PUSH_CUT
                   else f"an offset alone does nearly as well there ({offset_alone:.4f} um against "
                        f"{correction.held_out_rms_corrected_um:.4f} um)"
                   if correction.held_out_rms_corrected_um > (1.0 - GAIN_SHARE) * offset_alone
                   else f"the held-out part's own gain {100 * held_gain:+.2f} % differs (the gain is still changing)"
                   if abs(held_gain - gain) > GAIN_AGREEMENT * max(abs(gain), abs(held_gain)) else "")
        return replace(correction, refused=refused)

    def resemblance(self, window: np.ndarray, before: tuple[float, ...] = ()) -> tuple[str, float]:
        """What the window's residual resembles, by the residual loop's subset search on the window (fit on
        its first part, scored on its held-out rest, block means at SEARCH_RATE_HZ): the model's own
        parameters when a GPIM refit on the window takes REFIT_SHARE of the held-out RMS of the model in
        force, else the catalogue effect that cuts the refit's by RESEMBLANCE_GAIN or more.  ``before``: the
        turning points [V] of the voltage before the window (the operators' state at its start).  (name, cut)."""
        t, v, y, predicted = window.T
        try:
            split = split_records(Record(t, v, y), None, SEARCH_RATE_HZ)
            residual = analysis_record(Record(t, v, y - predicted - (self._offset or 0.0)), SEARCH_RATE_HZ)
        except IdentificationError as exc:
            return f"nothing it can name ({exc})", 0.0
        held_out = residual.position_um[split.start:]
        in_force = rms(held_out)
        shift = float(np.median(held_out))
        offset_rms = rms(held_out - shift)
        # a gain change: the residual in proportion to the prediction's swing, about its mean (with an offset)
        swing = analysis_record(Record(t, v, predicted), SEARCH_RATE_HZ).position_um[split.start:]
        level_um, gain, about = _gain_fit(held_out, swing)
        gain_rms = rms(held_out - level_um - gain * (swing - about))
        if in_force > 0 and 1.0 - gain_rms / in_force >= REFIT_SHARE \
                and 1.0 - gain_rms / max(offset_rms, 1e-30) >= GAIN_SHARE \
                and abs(gain) <= GAIN_CHANGE_MAX:
            return (f"{GAIN_PREFIX} of {100.0 * gain:+.1f} % (the swing about {about:.1f} um "
                    f"scaled by {1.0 + gain:.4f}) and an offset of {level_um:+.3f} um the model lacks",
                    1.0 - gain_rms / in_force)
        if in_force > 0 and 1.0 - offset_rms / in_force >= REFIT_SHARE:
            return f"{OFFSET_PREFIX} of {shift:+.3f} um the model lacks", 1.0 - offset_rms / in_force
        history = tuple(before) + (float(v[0]),)
        start = InitialState("remanent", dominant_turning_points(np.asarray(history))) if len(history) > 1 else InitialState()
        baseline = ValveModel(self.model.gpim, tuple(sections(self.model.valve_model)), t0=split.t0, history=start)
        effects = [e for e in (cls.prepare(split.fit, baseline.context(split.fit).H) for cls in _effects.CATALOGUE)
                   if e is not None]
        search = SubsetSearch(baseline, split, effects)
        refit = search.score(frozenset())
        if in_force > 0 and 1.0 - refit.rms / in_force >= REFIT_SHARE:
            return "the model's own parameters (a refit of the GPIM on the window explains it)", 1.0 - refit.rms / in_force
        cuts = {e.name: 1.0 - search.score(frozenset({e.name})).rms / max(refit.rms, 1e-30) for e in effects}
        name, cut = max(cuts.items(), key=lambda kv: kv[1]) if cuts else ("", 0.0)
        if cut >= RESEMBLANCE_GAIN:
            return name, cut
        return "none of the catalogue's effects", max(cut, 0.0)
