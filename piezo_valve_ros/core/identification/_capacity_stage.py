"""Stage 1b of the residual loop (``residual``): the GPIM's number of thresholds, chosen on held-out data, and
chosen again with the effects in.  Nothing here imports ROS."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .fitting import fit_model, fit_paper_gpim, uniform_thresholds
from .search import room_for_an_effect
from ..metrics import rms
from .valve_model import ValveModel
from .thresholds import (CAPACITY_OPERATORS, CAPACITY_EXTENSION, CAPACITY_TOLERANCE, CAPACITY_REVISIT,
                         PLACEMENT_SHIFT_SHARE, TREND_DOMINANCE)
from ._stages import CapacityChoice, CapacityFit, StartChoice, _detrended
from ._effect_choice import Story, _EffectChoice


class CapacityStage:
    """The loop's stage 1b (a part of ``residual._Loop``)."""

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
