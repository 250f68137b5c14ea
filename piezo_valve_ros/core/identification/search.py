"""Effects judged on held-out data: every subset of the catalogue fitted from the baseline in one linear solve,
the held-out score of a model, and the rule an effect added last must pass.  Nothing here imports ROS."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from ..metrics import rms
from .effects import Effect
from .fitting import BASIS_RIDGE, gpim_lower_bounds, position_slope, run_in_order, solve_standardised
from .split import SessionStart, Split
from .valve_model import ValveModel

__all__ = ["SubsetSearch", "Score", "Consistency", "consistency", "NoiseLevels", "Support", "structured_rms", "support", "GAIN_THRESHOLD", "MIN_EFFECT_NOISE_RATIO", "PEAK_TOLERANCE"]

GAIN_THRESHOLD = 0.2                        # an effect added last must remove >= 20 % of the structured residual
MAX_LOSS_RATIO = 0.1                        # ... losing in the held-out stretches it does worse in at most 10 % of what
                                            # it gains in those it does better in
SMALL_SHARE = 0.05                          # ... or >= 5 % of a structured residual
LARGE_RESIDUAL_RATIO = 2.0                  # ... of this many times the noise or more
STRONG_SHARE = 0.9                          # ... doing better in >= 90 % of the stretches
STRONG_LOSS_RATIO = 0.02                    # ... losing at most 2 % of what it gains
STRONG_T = 5.0                              # ... with a paired t of at least this
MIN_EFFECT_NOISE_RATIO = 1.0                # ... and explain an RMS >= the sensor noise RMS (near the floor the
                                            # structured residual's share is a ratio of small differences)
PEAK_TOLERANCE = 1.1                        # ... and not raise the held-out peak by > 10 %
SEGMENTS = 10                               # the held-out data in this many stretches, for how consistent a cut is


class SubsetSearch:
    """Every subset of the effects fitted from the baseline in one ridge least-squares solve each, the GPIM's weights
    held to the bounds an exact refit holds them to (``fitting.gpim_lower_bounds``: without them, weights of either
    sign fit the training part as well and extrapolate wildly where the held-out part drives the valve beyond it).

    The columns (GPIM basis, offset, every effect's search columns, all through the baseline's G) are
    built once for the fit rows and the held-out rows; one Gram matrix serves all subsets.
    """

    def __init__(self, baseline: ValveModel, split: Split, effects: list[Effect],
                 each: Callable[[list[Callable[[], object]]], list] = run_in_order,
                 session: Optional[SessionStart] = None):
        """``session``: on a separate session, the baseline's start and the session's offset there (every subset is
        scored from them)."""
        self.effects = effects
        ctx_f = baseline.context(split.fit, split.t0)
        scored = baseline if session is None else replace(baseline, history=session.history)
        ctx_s = scored.context(split.score, split.score_t0)
        z_first = ctx_f.states[0]

        def design(ctx) -> tuple[np.ndarray, list[int]]:
            """The columns through the baseline's G, and each effect's width (``each`` runs fit and score
            records side by side)."""
            before = [e for e in effects if not e.after_dynamics]
            blocks = [np.ones((len(ctx.record), 1))] + [e.search_columns(ctx) for e in before]
            rest = None
            if ctx.rest_states is not None:   # G at rest before the first move: each column's rest value
                rest = np.concatenate([ctx.rest_states - z_first, [1.0]]
                                      + [e.rest_columns(ctx, b) for e, b in zip(before, blocks[1:])])
            # the GPIM's columns (the states less the fit record's first) and the others, through G
            through = ctx.states_and_columns_through_dynamics(z_first, blocks, rest)
            if len(before) == len(effects):
                return through, [b.shape[1] for b in blocks[1:]]
            # an output map after G: its search columns on the baseline's output, after G, in the catalogue's order
            x = ctx.through_dynamics(*ctx.model.static_output_and_rest(ctx))
            n_basis = z_first.size + 1
            filtered = iter(np.split(through[:, n_basis:], np.cumsum([b.shape[1] for b in blocks[1:]])[:-1], axis=1))
            own = [e.output_search_columns(x) if e.after_dynamics else next(filtered) for e in effects]
            return np.column_stack([through[:, :n_basis]] + own), [b.shape[1] for b in own]

        (A, widths), (B, _) = each([lambda: design(ctx_f), lambda: design(ctx_s)])
        n_basis = z_first.size + 1
        self.groups = [np.arange(n_basis)]
        ridge = [np.full(n_basis, BASIS_RIDGE)]
        col = n_basis
        for e, width in zip(effects, widths):
            self.groups.append(np.arange(col, col + width))
            ridge.append(np.full(width, e.ridge))
            col += width
        # the held-out columns one contiguous block per group: a subset's error sums the blocks it has (no copy
        # of the columns it picks, which cost more than the products)
        self.B_groups = [np.ascontiguousarray(B[split.start:, g]) for g in self.groups]
        y = split.fit.position_um
        self.y_score = split.score.position_um[split.start:]
        self.own_offset = session is not None   # a separate session: each subset is scored about its own zero there
        if session is not None:   # G's settling from before the session, as the baseline has it
            static, rest = scored.static_output_and_rest(ctx_s)
            settling = 0.0 if rest is None else (rest - static[0]) * ctx_s.free_response
            self.y_score = self.y_score - (settling[split.start:] if np.ndim(settling) else settling)
        n = A.shape[0]
        self.scale = np.sqrt(np.einsum("ij,ij->j", A, A) / n)
        self.scale[self.scale == 0] = 1.0
        self.gram = (A.T @ A) / np.outer(self.scale, self.scale)
        self.gram[np.diag_indices_from(self.gram)] += np.concatenate(ridge) * n
        self.rhs = (A.T @ y) / self.scale
        lower = np.full(self.scale.size, -np.inf)
        lower[:z_first.size] = gpim_lower_bounds(z_first.size, position_slope(split.fit))
        self.lower = lower * self.scale   # in the standardised columns' units, as the Gram
        self._cache: dict[frozenset, float] = {}

    def score(self, subset: frozenset) -> "Score":
        if subset not in self._cache:
            chosen = [0] + [1 + i for i, e in enumerate(self.effects) if e.name in subset]
            idx = np.concatenate([self.groups[g] for g in chosen])
            x = solve_standardised(self.gram[np.ix_(idx, idx)], self.rhs[idx], self.lower[idx]) / self.scale[idx]
            error = self.y_score.copy()
            start = 0
            for g in chosen:
                width = self.groups[g].size
                error -= self.B_groups[g] @ x[start:start + width]
                start += width
            self._cache[subset] = Score.of(error - np.mean(error) if self.own_offset else error)
        return self._cache[subset]


@dataclass(frozen=True)
class Score:
    """Held-out error [um] at the analysis rate; ``known_rms``: its RMS over the held-out rows before the input first
    leaves the fit part's voltage range (None where it never leaves it, or leaves it too soon to tell);
    ``segments``: its mean square [um^2] over each of SEGMENTS stretches of the held-out data in turn (what
    :func:`consistency` compares)."""

    rms: float
    peak: float
    known_rms: Optional[float] = None
    segments: tuple[float, ...] = ()

    @classmethod
    def of(cls, error: np.ndarray, known_rows: Optional[int] = None) -> "Score":
        parts = np.array_split(error, SEGMENTS) if error.size >= SEGMENTS else []
        return cls(rms(error), float(np.max(np.abs(error))) if error.size else 0.0,
                   None if known_rows is None else rms(error[:known_rows]),
                   tuple(float(np.mean(p * p)) for p in parts))


@dataclass(frozen=True)
class Consistency:
    """How consistently a model ``with_`` beats one ``without`` over the held-out data's SEGMENTS stretches: the
    share of stretches where its mean square error is lower, what it loses where it does worse as a share of what
    it gains where it does better (an effect that shows only in part of the record, a lag in the fast stretches,
    loses next to nothing elsewhere; one that fits the training record's quirks pays for its cut elsewhere), and
    the paired t statistic of the differences (their mean over its standard error)."""

    better_share: float
    loss_ratio: float
    t: float


def consistency(with_: Score, without: Score) -> Consistency:
    """:class:`Consistency` of ``with_`` against ``without`` (no segments: none shown, t 0)."""
    if not with_.segments or len(with_.segments) != len(without.segments):
        return Consistency(0.0, math.inf, 0.0)
    d = np.asarray(without.segments) - np.asarray(with_.segments)
    spread = float(np.std(d, ddof=1)) if d.size > 1 else 0.0
    mean = float(np.mean(d))
    t = mean / (spread / math.sqrt(d.size)) if spread > 0 else (math.inf if mean > 0 else 0.0)
    gained, lost = float(np.sum(np.maximum(d, 0.0))), float(np.sum(np.maximum(-d, 0.0)))
    return Consistency(float(np.mean(d > 0)), lost / gained if gained > 0 else math.inf, t)


@dataclass(frozen=True)
class NoiseLevels:
    """The sensor noise floor [um RMS] at the record's rate (what an effect must explain a share of) and at the
    analysis rate the held-out scores are taken at (block means: the noise's share there; what the structured
    residual is measured above); ``known``: whether the records gave evidence for it (False: a stand-in of the
    record's resolution, and every residual counts as structure)."""

    record_um: float
    analysis_um: float
    known: bool = True

    @classmethod
    def same(cls, noise_um: float) -> "NoiseLevels":
        return cls(noise_um, noise_um)


@dataclass(frozen=True)
class Support:
    """The evidence for an effect added last (its model ``with_`` against the one ``without`` it), on held-out data:
    the held-out RMS cut (a share), the share of the structured residual (the RMS above the noise floor) it
    removes, the RMS it explains [um], how consistently it does so over the held-out stretches, whether that
    supports it and by which rule (``by``: "share", "small but consistent", or "" when it does not)."""

    cut: float
    share: float
    explained_um: float
    consistency: Consistency
    supported: bool
    by: str

    def describe(self) -> str:
        """The evidence in words (one phrase)."""
        c = self.consistency
        return (f"held-out RMS cut {percent(self.cut, sign=True)} %, {percent(self.share)} % of the structured "
                f"residual, better in {100 * c.better_share:.0f} % of the held-out stretches, losing "
                f"{percent(min(c.loss_ratio, 9.99))} % of its gain elsewhere (t {c.t:.1f})")


def structured_rms(score: Score, noise: NoiseLevels) -> float:
    """The RMS [um] of ``score``'s held-out error above the noise at the analysis rate."""
    return math.sqrt(max(score.rms ** 2 - noise.analysis_um ** 2, 0.0))


def support(with_: Score, without: Score, noise: NoiseLevels) -> Support:
    """The evidence for an effect added last (:class:`Support`).  It is supported where it does not raise the
    held-out peak by more than PEAK_TOLERANCE, explains MIN_EFFECT_NOISE_RATIO times the sensor noise, does no worse
    before the held-out data leave the fit part's voltage range (``Score.known_rms``: a cut made only where the
    model extrapolates is the extrapolation's, not the effect's), and either

    * removes GAIN_THRESHOLD of the structured residual (its RMS above the noise floor) and loses, in the held-out
      stretches it does worse in, at most MAX_LOSS_RATIO of what it gains in the others ("share"); where the noise
      is not known (``NoiseLevels.known``: every residual counts as structure, a closed-loop record's wandering
      too), it must also do better in STRONG_SHARE of the stretches, or
    * removes at least SMALL_SHARE of a large structured residual (LARGE_RESIDUAL_RATIO times the noise or more),
      doing better in STRONG_SHARE of the stretches, losing at most STRONG_LOSS_RATIO, with a paired t of STRONG_T
      ("small but consistent": a small but real effect on a residual much of which stays unexplained)."""
    cut = 1.0 - with_.rms / without.rms if without.rms > 0 else 0.0
    before, after = structured_rms(without, noise), structured_rms(with_, noise)
    explained = math.sqrt(max(before ** 2 - after ** 2, 0.0))   # of the structure (below the floor: the noise's)
    share = 1.0 - after / before if before > 0 else 0.0
    c = consistency(with_, without)
    admissible = (explained >= MIN_EFFECT_NOISE_RATIO * noise.record_um and with_.peak <= PEAK_TOLERANCE * without.peak
                  and not _worse_where_known(with_, without))
    by = ""
    if admissible and _share_holds(share, c) and _consistent_enough(c, noise):
        by = "share"
    elif (admissible and share >= SMALL_SHARE and before >= LARGE_RESIDUAL_RATIO * noise.analysis_um
          and c.better_share >= STRONG_SHARE and c.loss_ratio <= STRONG_LOSS_RATIO and c.t >= STRONG_T):
        by = "small but consistent"
    return Support(cut, share, explained, c, bool(by), by)


def _share_holds(share: float, c: Consistency) -> bool:
    """The "share" rule's own figures: GAIN_THRESHOLD of the structured residual, at most MAX_LOSS_RATIO paid back."""
    return share >= GAIN_THRESHOLD and c.loss_ratio <= MAX_LOSS_RATIO


def _consistent_enough(c: Consistency, noise: NoiseLevels) -> bool:
    """Whether the "share" rule's consistency holds: any where the noise is known; better in STRONG_SHARE of the
    held-out stretches where it is not (a share of a residual that is all called structure is no evidence alone)."""
    return noise.known or c.better_share >= STRONG_SHARE


def unsupported_because(with_: Score, without: Score, noise: NoiseLevels) -> str:
    """Why :func:`support` refuses an effect added last (empty when it does not)."""
    s = support(with_, without, noise)
    if s.supported:
        return ""
    why = []
    c = s.consistency
    if _share_holds(s.share, c) and not _consistent_enough(c, noise):
        why.append(f"removes {percent(s.share)} % of the structured residual, but the records give no evidence for "
                   f"the noise (all of the residual counts as structure) and it does better in only "
                   f"{100 * c.better_share:.0f} % of the held-out stretches (needs {100 * STRONG_SHARE:.0f} % there)")
    elif not _share_holds(s.share, c):
        why.append(f"removes {percent(s.share)} % of the structured residual (threshold {100 * GAIN_THRESHOLD:.0f} %), "
                   f"losing {percent(min(c.loss_ratio, 9.99))} % of that gain in the held-out stretches it does worse "
                   f"in (threshold {100 * MAX_LOSS_RATIO:.0f} %; better in {100 * c.better_share:.0f} % of them, "
                   f"held-out RMS cut {percent(s.cut, sign=True)} %); not small but consistent either (needs "
                   f"{100 * SMALL_SHARE:.0f} % of a structured residual of {LARGE_RESIDUAL_RATIO:g}x the noise, better "
                   f"in {100 * STRONG_SHARE:.0f} % of the stretches losing at most {100 * STRONG_LOSS_RATIO:.0f} %, t "
                   f">= {STRONG_T:g}; t {c.t:.1f})")
    if s.explained_um < MIN_EFFECT_NOISE_RATIO * noise.record_um:
        why.append(f"explains {s.explained_um:.4f} um < {MIN_EFFECT_NOISE_RATIO:g}x the sensor noise "
                   f"{noise.record_um:.4f} um")
    if with_.peak > PEAK_TOLERANCE * without.peak:
        why.append(f"raises the held-out peak {without.peak:.3f} -> {with_.peak:.3f} um (> {PEAK_TOLERANCE:g}x)")
    if _worse_where_known(with_, without):
        why.append(f"raises the held-out RMS {without.known_rms:.4f} -> {with_.known_rms:.4f} um where the input stays "
                   f"within the fit part's range (its cut comes from the extrapolation beyond it)")
    return "; ".join(why)


def _worse_where_known(with_: Score, without: Score) -> bool:
    """Where the held-out data leave the fit part's voltage range, whether ``with_`` does worse than ``without``
    on the held-out rows before they first leave it (where the fit knows the valve)."""
    return with_.known_rms is not None and without.known_rms is not None and with_.known_rms > without.known_rms


def percent(share: float, sign: bool = False) -> str:
    """``share`` in per cent to one decimal, a cut that rounds to zero as 0.0 (never -0.0); ``sign``: always
    with its sign."""
    value = round(100.0 * share, 1) + 0.0   # + 0.0 turns -0.0 into 0.0
    return f"{value:+.1f}" if sign else f"{value:.1f}"


def room_for_an_effect(without: Score, noise: NoiseLevels) -> bool:
    """Whether an effect added to a model that leaves ``without`` could be supported at all: it must explain
    MIN_EFFECT_NOISE_RATIO times the sensor noise of the structured residual (:func:`support`), and it explains at
    most all of it.  False: every exact refit on top would be refused, whatever it gives."""
    return structured_rms(without, noise) >= MIN_EFFECT_NOISE_RATIO * noise.record_um


def no_room_because(without: Score, noise: NoiseLevels) -> str:
    """Why :func:`room_for_an_effect` is False (one phrase)."""
    return (f"its held-out RMS {without.rms:.4f} um stands {structured_rms(without, noise):.4f} um above the noise "
            f"(structured), below {MIN_EFFECT_NOISE_RATIO:g}x the sensor noise {noise.record_um:.4f} um: no effect "
            f"added to it could explain that much")
