"""Stages 2 and 3 of the residual loop (``residual``): every subset of the catalogue scored by one linear solve,
then exact refits, drop-one checks, exact checks of what the search underrated and swaps of look-alikes.
Nothing here imports ROS."""
from __future__ import annotations

import itertools
from dataclasses import dataclass, replace
from typing import Callable, Optional


from . import effects as _effects
from .effects import Effect
from .fitting import fit_model, refit_poles_with_effects, with_poles
from .report import ConfirmRound, Indistinguishable, SearchRow
from .search import (MAX_LOSS_RATIO, GAIN_THRESHOLD, MIN_EFFECT_NOISE_RATIO, NoiseLevels, Score, SubsetSearch,
                     Support, no_room_because, percent, room_for_an_effect, support, unsupported_because)
from ..metrics import rms
from .valve_model import ValveModel
from .thresholds import CONFIRM_ROUNDS, SEPARATION_SHARE, EXACT_CHECK_GAIN, EXACT_ALL_ROWS, DELAY_STEPS, SEARCH_TRUST
from ._stages import LoopState, _set_named, _structure, _unexplained_by_rms


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


class _EffectChoice:
    """Steps 2 and 3 of the module's docstring on one baseline: every subset of the catalogue scored by one linear
    solve (``search_subsets``, at construction unless ``search`` is False), then exact refits and drop-one checks
    (``story``).  The exact refits are cached per set (``refits``); the loop's records, noise, pools and caches
    are shared."""

    def __init__(self, loop: LoopState, baseline: ValveModel, label: str, search: bool = True):
        self.baseline, self.label = baseline, label
        self.fit, self.split, self.noise, self.cache = loop.fit, loop.split, loop.noise, loop.cache
        self.levels = loop.levels
        self.log, self.pool, self.each, self.each_form = loop.log, loop.pool, loop.each, loop.each_form
        self.each_beside = loop.each_beside
        self.held_out, self.session, self.polishes = loop.held_out, loop.session, loop.polishes
        self.error, self.range_val = loop.error, loop.range_val
        self.confirm_log: list[ConfirmRound] = []
        self._confirmed: Optional[tuple] = None   # the search's set as confirmed (story), once
        H_fit = baseline.context(self.fit).H
        self.effects: list[Effect] = [e for e in (cls.prepare(self.fit, H_fit) for cls in _effects.CATALOGUE)
                                      if e is not None]
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
                      cache=self.cache, warm=like, each=self.each_form, beside=self.each_beside)
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
                cache=self.cache, warm=best[0], beside=self.each_beside) for f in others])
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
            m = fit_model(self.fit, start, effects, try_forms=False, cache=self.cache, beside=self.each_beside)
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
        credited = [n for n in self.exact_options(current) if frozenset(current + [n]) not in tried]
        cheap = [n for n in credited if not self.by_name[n].costly_refit]
        refits = self.refit_many([(current + [n], final) for n in cheap])
        polished = polishing.result()
        polished_score = self.held_out(polished)
        base_score = min(final_score, polished_score, key=lambda s: s.rms)
        options, refits, best = self._costly_unless_settled(current, final, cheap, refits,
                                                            [n for n in credited if n not in cheap], base_score)
        if best is None and self.structure_remains(polished if polished_score.rms <= final_score.rms else final):
            # something is missing and none of the effects the search credited explains it: its first-order
            # ranking of the rest is what the exact refits are there to overrule (a slow pole beside an asymmetry,
            # which the search credits with nothing (-1 %), cuts a third of the held-out RMS refitted)
            rest = [n for n in self.names if n not in current and n not in credited
                    and frozenset(current + [n]) not in tried]
            cheap = [n for n in rest if not self.by_name[n].costly_refit]
            more, more_refits, best = self._costly_unless_settled(
                current, final, cheap, self.refit_many([(current + [n], final) for n in cheap]),
                [n for n in rest if n not in cheap], base_score)
            options, refits = options + more, refits + more_refits
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

    def _costly_unless_settled(self, current: list[str], final: ValveModel, options: list[str],
                               refits: list[tuple[ValveModel, Score]], costly: list[str], base: Score
                               ) -> tuple[list[str], list[tuple[ValveModel, Score]], Optional[tuple[str, Score]]]:
        """The exact checks ``options`` (refitted: ``refits``) joined by the ``costly`` ones (``Effect.costly_refit``,
        refitted here) unless the best supported of ``options`` leaves no room for an effect (``room_for_an_effect``):
        then a costly one could not be supported against it either (it would have to explain more than the structure
        it leaves), so the record could not tell which is better, and the cheaper is taken without the seconds of the
        costly refit.  Returns (options refitted, their refits, the best supported or None)."""
        best = self._best_supported(options, refits, base)
        if not costly:
            return options, refits, best
        if best is not None and not room_for_an_effect(best[1], self.levels):
            self.log(f"exact check on top of {_set_named(current)}: {', '.join(costly)} not refitted: with {best[0]} "
                     f"{no_room_because(best[1], self.levels)}, nor could it be told from {best[0]}")
            return options, refits, best
        options = options + costly
        refits = refits + self.refit_many([(current + [n], final) for n in costly])
        return options, refits, self._best_supported(options, refits, base)

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
