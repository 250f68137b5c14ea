"""The residual loop: find what the model lacks, add it, prove the gain on held-out data.

Round by round, for every effect of the catalogue not yet in the model:

1. **signature statistic** (computed on the residual): the effect's signature columns are built from
   the present model, regressed on the *training* residual, and the share of the *held-out* residual
   variance they explain is the statistic (threshold ``SIGNATURE_THRESHOLD``).  For ``asymmetry`` the
   signature is the linearised descending-envelope term (operators on their descending clamp, times
   1 and v) plus an even term of the output;
2. **pay-off**: the model with the effect is refitted on the training data and its held-out RMS error
   compared with the present one (threshold ``GAIN_THRESHOLD``, relative).

The effect that pays most among those that pass both is added; rounds go on while one pays.  After
the last round the held-out residual is tested for remaining structure: when it is well above the
sensor noise floor, correlated in time and larger than ``UNEXPLAINED_PCT`` of the range, the report
says ``unexplained`` and what it saw (size, dominant period, best catalogue match).  Nothing here
imports ROS.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from .hysteresis import play_batch
from .identification import (EFFECTS, Effect, FitQuality, Record, ValveModel, _Context,
                             _design, analysis_record, fit_linear_gpim, fit_model, fit_paper_gpim, quality)

__all__ = ["SIGNATURE_THRESHOLD", "GAIN_THRESHOLD", "UNEXPLAINED_PCT", "Analysis", "analyse", "noise_floor_um",
           "split_held_out"]

SIGNATURE_THRESHOLD = 0.2   # share of held-out residual variance the effect's signature must explain
GAIN_THRESHOLD = 0.2        # relative cut of the held-out RMS error the refitted model must bring
UNEXPLAINED_PCT = 0.4       # held-out RMS (% of range) above which remaining structure is reported
HELD_OUT_FRACTION = 0.3


def split_held_out(record: Record, fraction: float = HELD_OUT_FRACTION) -> tuple[Record, Record]:
    """(first 1 - fraction, last fraction) of the record in time."""
    cut = record.time_s[0] + (1.0 - fraction) * (record.time_s[-1] - record.time_s[0])
    k = int(np.searchsorted(record.time_s, cut))
    return record.slice(0, k), record.slice(k)


def noise_floor_um(record: Record) -> float:
    """Sensor noise RMS [um] from first differences (robust: median absolute deviation)."""
    d = np.diff(record.position_um)
    mad = float(np.median(np.abs(d - np.median(d))))
    return 1.4826 * mad / math.sqrt(2.0)


def _signature_columns(eff: Effect, ctx: _Context) -> np.ndarray:
    if eff.name != "asymmetry":
        return eff.columns(ctx)
    g = ctx.gpim
    x = g.ascending_envelope(ctx.v)
    states, _ = play_batch(x, g.descending_envelope(ctx.v), g.thresholds, g.virgin_state(float(ctx.v[0])))
    on_upper = np.abs(states - (g.descending_envelope(ctx.v)[:, None] + g.thresholds)) <= 1e-9 * (1 + np.abs(x))[:, None]
    on_upper[:, 0] = False
    u = on_upper @ g.weights / max(float(np.sum(np.abs(g.weights))), 1e-12)
    v_mid, v_half = float(np.mean(ctx.v)), max(float(np.ptp(ctx.v)) / 2, 1e-12)
    return np.column_stack((u, u * (ctx.v - v_mid) / v_half, eff.columns(ctx)))


@dataclass(frozen=True)
class Scored:
    """A record the model runs over from its start, scored from ``start`` on (held-out tail or a whole record)."""

    record: Record
    start: int
    t0: float

    @property
    def measured(self) -> np.ndarray:
        return self.record.position_um[self.start:]

    def predict(self, model: ValveModel) -> np.ndarray:
        return model.predict(self.record, self.t0)[self.start:]

    def error(self, model: ValveModel) -> np.ndarray:
        return self.measured - self.predict(model)

    def quality(self, model: ValveModel, range_um: float) -> FitQuality:
        return quality(self.measured, self.predict(model), range_um)


class _RoundBasis:
    """What one round's signature statistics share: contexts of the present model and the QR of its design."""

    def __init__(self, model: ValveModel, train: Record, validate: Scored):
        self.ctx_t = _Context(train, model.gpim, model.t0)
        self.ctx_v = _Context(validate.record, model.gpim, validate.t0)
        self.start = validate.start
        descending = None if model.gpim.symmetric else (model.gpim.b0, model.gpim.b1)

        def design(rec, ctx):
            return np.column_stack([_design(rec, model.gpim.thresholds, descending), np.ones(len(rec))]
                                   + [e.columns(ctx) for e, _ in model.terms])
        At = design(train, self.ctx_t)
        self.Av = design(validate.record, self.ctx_v)[validate.start:]
        self.scale = np.sqrt(np.mean(At * At, axis=0))
        self.scale[self.scale == 0] = 1.0
        self.Q, self.R = np.linalg.qr(At / self.scale)

    def statistic(self, eff: Effect, e_train: np.ndarray, e_val: np.ndarray) -> float:
        """Share of held-out residual variance explained by the effect's signature fitted on the training
        residual, after projecting out what the present model could absorb by refitting (Frisch-Waugh)."""
        ct = _signature_columns(eff, self.ctx_t)
        cv = _signature_columns(eff, self.ctx_v)[self.start:]
        QtC = self.Q.T @ ct
        B = np.linalg.lstsq(self.R, QtC, rcond=None)[0] / self.scale[:, None]
        ct = ct - self.Q @ QtC
        cv = cv - self.Av @ B
        c = np.linalg.lstsq(ct, e_train, rcond=None)[0]
        rest = e_val - cv @ c
        return float(1.0 - np.mean(rest ** 2) / max(np.mean(e_val ** 2), 1e-30))


@dataclass
class Candidate:
    effect: str
    statistic: float
    rms_before_um: float
    rms_after_um: float
    peak_before_um: float
    peak_after_um: float
    model: Optional[ValveModel] = None

    @property
    def gain(self) -> float:
        return 1.0 - self.rms_after_um / self.rms_before_um if self.rms_before_um > 0 else 0.0

    @property
    def passes(self) -> bool:
        return (self.statistic >= SIGNATURE_THRESHOLD and self.gain >= GAIN_THRESHOLD
                and self.peak_after_um <= 1.1 * self.peak_before_um)

    def evidence(self) -> str:
        sig = EFFECTS[self.effect].signature
        return (f"{sig}; held-out residual variance explained by this signature {self.statistic:.3f} "
                f"(threshold {SIGNATURE_THRESHOLD}); refitted with it, held-out RMS {self.rms_before_um:.3f} -> "
                f"{self.rms_after_um:.3f} um ({100 * self.gain:+.1f} % cut, threshold {100 * GAIN_THRESHOLD:.0f} %), "
                f"peak {self.peak_before_um:.3f} -> {self.peak_after_um:.3f} um")


@dataclass
class Analysis:
    report: dict
    baseline: ValveModel
    final: ValveModel
    train: Record          # analysis-rate records the figures refer to
    validate: Scored
    rounds: list = field(default_factory=list)
    history: list = field(default_factory=list)  # the model before each effect was added, then the final one


def _refit(train: Record, model: ValveModel, new: str, H_range) -> ValveModel:
    """The present model's effects (with their chosen settings) plus ``new`` (best of its options)."""
    fixed = [eff for eff, _ in model.terms]
    best, best_rms = None, math.inf
    for option in EFFECTS[new].prepare(train, H_range):
        m = fit_model(train, fixed + [option], t0=model.t0)
        rms = float(np.sqrt(np.mean((train.position_um - m.predict(train)) ** 2)))
        if rms < best_rms:
            best, best_rms = m, rms
    return best


def _unexplained(e_val: np.ndarray, dt: float, range_um: float, noise_um: float, stats: dict) -> tuple[bool, str]:
    rms = float(np.sqrt(np.mean(e_val ** 2)))
    ec = e_val - e_val.mean()
    r1 = float(np.dot(ec[1:], ec[:-1]) / max(np.dot(ec, ec), 1e-30))
    spectrum = np.abs(np.fft.rfft(ec * np.hanning(ec.size)))
    freqs = np.fft.rfftfreq(ec.size, dt)
    k = int(np.argmax(spectrum[1:]) + 1) if spectrum.size > 1 else 0
    share = float(spectrum[k] ** 2 / max(np.sum(spectrum[1:] ** 2), 1e-30)) if k else 0.0
    best = max(stats.items(), key=lambda kv: kv[1]) if stats else ("none", 0.0)
    structured = rms > 4.0 * noise_um and r1 > 0.5 and 100.0 * rms / range_um > UNEXPLAINED_PCT
    text = (f"held-out residual RMS {rms:.3f} um ({100 * rms / range_um:.2f} % of range, threshold "
            f"{UNEXPLAINED_PCT} %), {rms / max(noise_um, 1e-12):.1f}x the sensor noise {noise_um:.3f} um, "
            f"lag-1 autocorrelation {r1:.2f}; strongest spectral line {freqs[k]:.3g} Hz "
            f"({100 * share:.0f} % of residual power); best catalogue signature: {best[0]} explains "
            f"{max(best[1], 0.0):.2f} of it")
    return structured, text


def analyse(train_full: Record, validate_full: Optional[Record] = None, *, max_rate_hz: float = 2000.0,
            max_effects: int = 5, log: Callable[[str], None] = lambda s: None) -> Analysis:
    """Fit, diagnose and extend; ``validate_full`` None holds out the last 30 % of ``train_full``."""
    train_full = train_full.check("training record")
    held_out = validate_full is None
    if held_out:
        train_full, validate_full = split_held_out(train_full)
        train_full.check("training part (first 70 %)")
        validate_full.check("held-out part (last 30 %)", min_samples=50)
    else:
        validate_full = validate_full.check("validation record", min_samples=50)
    noise = noise_floor_um(train_full)
    train = analysis_record(train_full, max_rate_hz)
    t0 = float(train.time_s[0])
    if held_out:  # the model runs on through the held-out tail: its operators keep their memory
        whole = analysis_record(Record(np.concatenate((train_full.time_s, validate_full.time_s)),
                                       np.concatenate((train_full.voltage_v, validate_full.voltage_v)),
                                       np.concatenate((train_full.position_um, validate_full.position_um))),
                                max_rate_hz)
        validate = Scored(whole, len(train), t0)
        train = whole.slice(0, len(train))
    else:
        va = analysis_record(validate_full, max_rate_hz)
        validate = Scored(va, 0, float(va.time_s[0]))
    noise_a = noise / math.sqrt(max(len(train_full) / max(len(train), 1), 1.0))
    range_um = float(np.ptp(np.concatenate((train_full.position_um, validate_full.position_um))) if held_out
                     else np.ptp(train_full.position_um))
    range_val = range_um if held_out else float(np.ptp(validate_full.position_um))
    started = time.monotonic()
    log(f"records: training {len(train_full)} samples ({train_full.duration_s:.1f} s at "
        f"{1 / train_full.dt:.0f} Hz), validation {len(validate_full)} samples; analysis at "
        f"{1 / train.dt:.0f} Hz; sensor noise {noise:.3f} um")

    # -- baseline: both fits, the better on held-out data is used
    linear = fit_linear_gpim(train)
    paper = fit_paper_gpim(train)
    paper_model = ValveModel(paper.params.model(), (), t0)
    fits = {}
    for name, m in (("linear", linear), ("paper_nls", paper_model)):
        fits[name] = {"train": quality(train.position_um, m.predict(train), range_um).as_dict(),
                      "validate": validate.quality(m, range_val).as_dict()}
    fits["paper_nls"].update({"condition_number": paper.condition_number, "evaluations": paper.evaluations,
                              "params": {k: getattr(paper.params, k) for k in ("a0", "a1", "alpha", "rho", "tau", "n",
                                                                               "offset_um")}})
    fits["linear"].update({"operators": linear.gpim.n, "invertible": True})
    chosen = "linear" if fits["linear"]["validate"]["rms_um"] <= fits["paper_nls"]["validate"]["rms_um"] else "paper_nls"
    baseline = linear if chosen == "linear" else paper_model
    log(f"baseline fits: linear (fixed thresholds, bounded LS) held-out RMS {fits['linear']['validate']['rms_um']:.3f} um; "
        f"paper 5-parameter NLS {fits['paper_nls']['validate']['rms_um']:.3f} um (Jacobian condition "
        f"{paper.condition_number:.2g}); using {chosen}")

    # -- rounds: extensions are built on the invertible linear form; where the paper's fit generalises better,
    # its thresholds (in V) are the better grid for the linear form too
    model = linear
    if chosen == "paper_nls":
        on_paper_grid = fit_model(train, thresholds=paper_model.gpim.thresholds / paper.params.a0)
        if validate.quality(on_paper_grid, range_val).rms_um < validate.quality(linear, range_val).rms_um:
            model = on_paper_grid
            log("linear form refitted on the thresholds of the paper's fit")
    rounds = []
    verdicts: dict[str, Candidate] = {}
    added: list[str] = []
    H_train = model.predict(train)
    H_range = (float(H_train.min()), float(H_train.max()))
    last_stats: dict[str, float] = {}
    history = [model]
    while len(added) < max_effects:
        e_train = train.position_um - model.predict(train)
        e_val = validate.error(model)
        rms0 = float(np.sqrt(np.mean(e_val ** 2)))
        peak0 = float(np.max(np.abs(e_val)))
        candidates = []
        last_stats = {}
        basis = _RoundBasis(model, train, validate)
        for name in EFFECTS:
            if name in added:
                continue
            options = EFFECTS[name].prepare(train, H_range)
            if not options:
                continue
            stat = max(basis.statistic(o, e_train, e_val) for o in options)
            last_stats[name] = stat
            cand = Candidate(name, stat, rms0, rms0, peak0, peak0)
            if stat >= SIGNATURE_THRESHOLD:
                m = _refit(train, model, name, H_range)
                ev = validate.error(m)
                cand.rms_after_um = float(np.sqrt(np.mean(ev ** 2)))
                cand.peak_after_um = float(np.max(np.abs(ev)))
                cand.model = m
            candidates.append(cand)
            verdicts[name] = cand
            log(f"round {len(rounds) + 1}: {name:10s} signature {stat:6.3f}  held-out RMS {rms0:.3f} -> "
                f"{cand.rms_after_um:.3f} um{'  passes' if cand.passes else ''}")
        rounds.append([{"effect": c.effect, "statistic": c.statistic, "rms_after_um": c.rms_after_um,
                        "gain": c.gain, "passes": c.passes} for c in candidates])
        passing = [c for c in candidates if c.passes]
        if not passing:
            break
        best = max(passing, key=lambda c: c.gain)
        model = best.model
        history.append(model)
        added.append(best.effect)
        verdicts[best.effect] = best
        log(f"added {best.effect}: held-out RMS {best.rms_before_um:.3f} -> {best.rms_after_um:.3f} um")

    e_val = validate.error(model)
    unexplained, seen = _unexplained(e_val, validate.record.dt, range_val, noise_a, last_stats)
    diagnosis = []
    for name in EFFECTS:
        c = verdicts.get(name)
        if c is None:
            continue
        diagnosis.append({"effect": name, "added": name in added, "statistic": round(c.statistic, 4),
                          "threshold": SIGNATURE_THRESHOLD, "held_out_gain": round(c.gain, 4),
                          "evidence": c.evidence()})
    diagnosis.sort(key=lambda d: (not d["added"], added.index(d["effect"]) if d["added"] else 0))
    report = {
        "range_um": round(range_um, 4),
        "baseline": {"model": "gpim", "fit": chosen, "train": fits[chosen]["train"],
                     "validate": fits[chosen]["validate"]},
        "effects_added": added,
        "diagnosis": diagnosis,
        "final": {"model": model.name, "train": quality(train.position_um, model.predict(train), range_um).as_dict(),
                  "validate": validate.quality(model, range_val).as_dict()},
        "unexplained": bool(unexplained),
        "residual": seen,
        "baseline_fits": fits,
        "validation": "held-out last 30 % of the training record" if held_out else "separate validation record",
        "validate_range_um": round(range_val, 4),
        "analysis_rate_hz": round(1.0 / train.dt, 3),
        "noise_floor_um": round(noise, 5),
        "thresholds": {"signature": SIGNATURE_THRESHOLD, "held_out_gain": GAIN_THRESHOLD,
                       "unexplained_pct": UNEXPLAINED_PCT},
        "rounds": rounds,
        "final_model": model.describe(),
        "seconds": round(time.monotonic() - started, 3),
    }
    log(("structure remains: " if unexplained else "residual: ") + seen)
    return Analysis(report, baseline, model, train, validate, rounds, history)
