"""Stage 3b of the residual loop (``residual``): a long record's whole length judges the slow trend (drift) that its
analysed stretch cannot show (``whole_record``).  Nothing here imports ROS."""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Optional

import numpy as np

from .effects.drift import Drift
from .report import Stretch, TrendRMS, WholeRecordReport
from .search import NoiseLevels
from .whole_record import (TREND_BLOCK_S, TREND_RESOLUTION_S, TREND_SEGMENT_S, Trend, slow_creep_rows, trend_search,
                           whole_residual)
from ._effect_choice import Story, Verdict, _decided

DRIFT = "drift"


class WholeRecordStage:
    """The loop's stage 3b (a part of ``residual._Loop``): ``self.whole`` is the whole training record (or its window)
    at the analysis rate where the loop analysed only its first MAX_ANALYSED_S, else None (from the fit's start on, once
    searched); ``self.trend`` what the search found there."""

    whole: Optional["object"] = None
    trend: Optional[Trend] = None

    def whole_record_story(self, story: Story) -> Story:
        """``story`` with the drift the whole record supports (the stretch's own drift replaced by the whole record's
        trend), or without drift where the whole record supports none: a long record's trend is judged on all of it."""
        if self.whole is None:
            return story
        final = story.final
        had = DRIFT in story.added
        base = final.without(DRIFT) if had else final
        like = Drift.prepare(self.fit, base.context(self.fit, self.split.t0).H)
        t0 = base.t0   # where the fit starts (after a wipe, where the loop found the start unknown): so does this
        whole = self.whole = self.whole.slice(int(np.searchsorted(self.whole.time_s, t0 - 0.5 * self.whole.dt)))
        duration = float(whole.time_s[-1] - t0 + whole.dt)
        residual = whole_residual(base, whole, like, self.log, slow_creep_rows(base))
        source_rows = residual.rows_per_block * whole.block
        levels = NoiseLevels(self.noise, self.noise / math.sqrt(source_rows), known=self.floor.known)
        stretch_end = (float(self.split.score_full.time_s[-1]) if self.split.held_out
                       else float(self.split.fit_full.time_s[-1]))
        # a story that showed no drift on its stretch keeps it there: the trend starts where the stretch ends (so
        # the stretch's figures stand, and a drift is found where it happens); the stretch's own drift is replaced
        # by one over the whole record
        from_s = 0.0 if had else max(stretch_end - t0, 0.0)
        trend = self.trend = trend_search(residual, t0, duration, like, levels, self.log, stretch_end_s=stretch_end,
                                          from_s=from_s)
        span = f"{self.whole.time_s[0]:.0f}..{self.whole.time_s[-1]:.0f} s"
        added, verdicts, drop_one = list(story.added), dict(story.verdicts), dict(story.drop_one)
        self.log(f"whole record ({span}): the stretch's model leaves {trend.rms_um[0]:.4f} um RMS at the analysis "
                 f"rate over all of it" + ("" if math.isnan(trend.beyond_rms_um[0]) else
                                           f", {trend.beyond_rms_um[0]:.4f} um beyond the analysed stretch")
                 + f"; {trend.rms_um[1]:.4f} um with the best trend")
        if trend.supported:
            final = replace(base, effects=base.effects + (trend.effect,), coefs=base.coefs + (trend.coefs,))
            if not had:
                added = [n for n in story.choice.names if n in set(added) | {DRIFT}]
            verdicts[DRIFT] = Verdict(trend.support, trend.without_um, trend.with_um)
            drop_one[DRIFT] = base
            self.log(f"whole record ({span}): drift over the whole record {_decided(trend.support)}"
                     + ("; it replaces the stretch's own drift" if had else ""))
        else:
            self.log(f"whole record ({span}): no trend supported (cross-validated block RMS {trend.without_um:.4f} -> "
                     f"{trend.with_um:.4f} um with the best)" + ("; the stretch's own drift is dropped: the whole "
                                                                   "record does not bear it out" if had else ""))
            if had:
                final = base
                added.remove(DRIFT)
                verdicts.pop(DRIFT, None)
                drop_one.pop(DRIFT, None)
        return replace(story, final=final, added=added, verdicts=verdicts, drop_one=drop_one)

    def whole_record_report(self) -> Optional[WholeRecordReport]:
        """What the whole record showed, for the report (None where the loop analysed all of it)."""
        if self.whole is None or self.trend is None:
            return None
        t, w = self.trend, self.whole
        return WholeRecordReport(
            from_s=float(w.time_s[0]), to_s=float(w.time_s[-1]), rows=len(w), rate_hz=round(w.rate_hz, 3),
            block_s=TREND_BLOCK_S, segment_s=TREND_SEGMENT_S, resolution_s=TREND_RESOLUTION_S,
            trend_terms=t.effect.trend_terms, trend_gain=bool(np.any(t.coefs[t.coefs.size // 2:])),
            tried={k: round(v, 6) for k, v in t.tried.items()},
            held_out_rms_um=TrendRMS(round(t.without_um, 6), round(t.with_um, 6)),
            judged_beside=t.judged_beside,
            drift_added=t.supported, decided_by=t.support.by, evidence=t.support.describe(),
            peak_to_peak_um=round(t.peak_to_peak_um, 6), onset_s=round(t.onset_s, 3),
            rms_um=TrendRMS(round(t.rms_um[0], 6), round(t.rms_um[1], 6)),
            beyond_stretch_rms_um=(None if math.isnan(t.beyond_rms_um[0]) else
                                   TrendRMS(round(t.beyond_rms_um[0], 6), round(t.beyond_rms_um[1], 6))),
            stretches=tuple(Stretch(round(a, 3), round(b, 3), round(r0, 6), round(r1, 6))
                            for a, b, r0, r1 in t.stretch_rms_um))

    def whole_record_evidence(self) -> str:
        """How the whole-record verdict was reached, in words (the diagnosis' ``how``)."""
        beside = self.trend.judged_beside if self.trend is not None else ""
        return (f"a trend in time of offset and gain over the whole record ({self.whole.time_s[0]:.0f}..."
                f"{self.whole.time_s[-1]:.0f} s, {TREND_BLOCK_S:g} s block means), cross-validated over alternate "
                f"{TREND_SEGMENT_S:g} s stretches" + (f", judged beside {beside}" if beside else ""))
