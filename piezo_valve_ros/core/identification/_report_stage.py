"""Stages 4 and 5 of the residual loop (``residual``): what the final model leaves, and the report assembled from
what every stage found.  Nothing here imports ROS."""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from .initial_state import WIPE_STATE_GAIN
from .report import (Analysed, Baseline, BaselineFits, Capacity, Decision, Final, FiguresFrom, IdentificationReport, NoiseEstimate,
                     LinearFit, NoiseFloorReport, PaperNLS, PaperParams, ResidualStructure, Session, ValveDynamics)
from .records import HELD_OUT_FRACTION, noise_peak_um
from .search import GAIN_THRESHOLD, MIN_EFFECT_NOISE_RATIO, PEAK_TOLERANCE, support, unsupported_because
from .split import WIPE_MARGIN
from ..metrics import ErrorFigures, error_figures
from ..model.dynamics import describe_dynamics
from ..model.hysteresis import GPIM_PARAMS_KEYS
from .valve_model import ValveModel
from .thresholds import (CAPACITY_TOLERANCE, INITIAL_STATE_TOLERANCE, WIPE_GAIN, UNEXPLAINED_NOISE_RATIO,
                         PEAK_NOISE_RATIO, SPREAD_SHARE, PEAK_BLOCK_S, PEAK_RANK, MIN_STRUCTURE_PCT, SEPARATION_SHARE)
from ._stages import (CapacityChoice, Remains, StartChoice, _ordinal, _peak_structure, _structure,
                      _summary_line, _unexplained_by_rms)
from ._effect_choice import Story, Verdict, _alternatives, _evidence


class ReportStage:
    """The loop's stages 4 and 5 (a part of ``residual._Loop``)."""

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
            if n == "drift" and self.trend is not None:   # a long record's: judged on its whole length (stage 3b)
                verdict = Verdict(self.trend.support, self.trend.without_um, self.trend.with_um)
                how = self.whole_record_evidence()
            elif exact:
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
        on_stretch = [a for a in story.added if not (a == "drift" and self.trend is not None)]   # (3b's: its own)
        alternatives = _alternatives(on_stretch, choice.names, story.verdicts, choice.search, choice.refit_many,
                                     choice.by_name)
        for a in alternatives:
            self.log(f"cannot tell apart: {a.effect} and {a.alternative}: {a.why}")
        held_out_text = (f"held-out last {100 * HELD_OUT_FRACTION:.0f} % of the training record" if split.held_out
                         else "separate validation record")
        sessions, final_start = self.sessions_report(start, final)
        report = IdentificationReport(
            range_um=round(self.range_um, 4),
            baseline=Baseline(model=baseline.name, fit=capacity.label, **figured[id(baseline)],
                              G_v=ValveDynamics.of(describe_dynamics(baseline.dynamics, baseline.dynamics_note)),
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
                linear=LinearFit(**figured[id(baseline)], operators=baseline.gpim.n, invertible=True),
                paper_nls=PaperNLS(**figured[id(paper.model)],
                                   params=PaperParams(**{k: getattr(paper.params, k) for k in GPIM_PARAMS_KEYS}),
                                   fixed="a0 = 1, a1 = 0: the 5-parameter form has two exact invariances (a0 with "
                                         "alpha, rho, tau; a1 with the offset)",
                                   condition_number=paper.condition_number, evaluations=paper.evaluations,
                                   failed=paper.failed),
            ),
            search=tuple(sorted(choice.table, key=lambda t: t.held_out_rms_um)),
            confirm=tuple(story.confirm_log),
            validation=held_out_text,
            held_out_fraction=HELD_OUT_FRACTION if split.held_out else None,
            held_out_samples=len(split.score_full) - split.start_full,
            analysed=Analysed(train=self.analysed["train"], validate=self.analysed.get("validate")),
            figures_from=self.figures_from(),
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
            whole_record=self.whole_record_report(),
        )
        report = replace(report, summary=_summary_line(report, self.floor))
        self.log(f"{report.summary} ({report.seconds:.1f} s)")
        return report

    def figures_from(self) -> FiguresFrom:
        """Which stretch of which record each of the report's figures comes from, in words."""
        split, a = self.split, self.analysed["train"]
        train = f"the training record's {split.fit_full.time_s[0]:.3f}..{a.to_s:.3f} s" + (
            f" (its rows before {split.wiped_at_s:.3f} s left out: the operators' state there unknown)"
            if split.wiped_at_s is not None else "")
        held = (f"its last {100 * HELD_OUT_FRACTION:.0f} % held out" if split.held_out
                else "held out: the validation record's "
                + f"{self.analysed['validate'].from_s:.3f}..{self.analysed['validate'].to_s:.3f} s")
        stretch = f"fitted on {train}, {held}"
        whole = None
        if self.whole is not None:
            whole = (f"the stretch's model run over the whole training record ({self.whole.time_s[0]:.3f}.."
                     f"{self.whole.time_s[-1]:.3f} s) at {self.whole.rate_hz:.0f} Hz, its residual searched for a "
                     f"trend")
        return FiguresFrom(
            baseline=stretch,
            final=stretch + ("; its drift fitted on the whole record" if self.trend is not None and self.trend.supported
                             else ""),
            diagnosis=stretch + ("; drift's on the whole record" if self.trend is not None else ""),
            residual_structure=(f"the final model's held-out error ({held} of {train})" if split.held_out
                                else f"the final model's held-out error ({held})"),
            whole_record=whole)

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
