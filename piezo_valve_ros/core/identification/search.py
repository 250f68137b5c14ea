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

__all__ = ["SubsetSearch", "Score", "support", "GAIN_THRESHOLD", "MIN_EFFECT_NOISE_RATIO", "PEAK_TOLERANCE"]

GAIN_THRESHOLD = 0.2                        # an effect added last must cut the held-out RMS by >= 20 %
MIN_EFFECT_NOISE_RATIO = 1.0                # ... and explain an RMS >= the sensor noise RMS
PEAK_TOLERANCE = 1.1                        # ... and not raise the held-out peak by > 10 %


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
            self.y_score = self.y_score - settling
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
    leaves the fit part's voltage range (None where it never leaves it, or leaves it too soon to tell)."""

    rms: float
    peak: float
    known_rms: Optional[float] = None

    @classmethod
    def of(cls, error: np.ndarray, known_rows: Optional[int] = None) -> "Score":
        return cls(rms(error), float(np.max(np.abs(error))) if error.size else 0.0,
                   None if known_rows is None else rms(error[:known_rows]))


def unsupported_because(with_: Score, without: Score, noise_um: float) -> str:
    """Why :func:`support` refuses an effect added last (empty when it does not)."""
    cut, explained, _ = support(with_, without, noise_um)
    why = []
    if cut < GAIN_THRESHOLD:
        why.append(f"held-out RMS cut {percent(cut)} % < {100 * GAIN_THRESHOLD:.0f} %")
    if explained < MIN_EFFECT_NOISE_RATIO * noise_um:
        why.append(f"explains {explained:.4f} um < {MIN_EFFECT_NOISE_RATIO:g}x the sensor noise {noise_um:.4f} um")
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


def room_for_an_effect(without: Score, noise_um: float) -> bool:
    """Whether an effect added to a model that leaves ``without`` could be supported at all: it must explain
    MIN_EFFECT_NOISE_RATIO times the sensor noise (:func:`support`), and it explains at most ``without``'s RMS.
    False: every exact refit on top would be refused, whatever it gives."""
    return without.rms >= MIN_EFFECT_NOISE_RATIO * noise_um


def no_room_because(without: Score, noise_um: float) -> str:
    """Why :func:`room_for_an_effect` is False (one phrase)."""
    return (f"its held-out RMS {without.rms:.4f} um is below {MIN_EFFECT_NOISE_RATIO:g}x the sensor noise "
            f"{noise_um:.4f} um: no effect added to it could explain that much")


def support(with_: Score, without: Score, noise_um: float) -> tuple[float, float, bool]:
    """(held-out RMS cut, explained RMS [um], supported?) of an effect added last: it must cut the held-out
    RMS by GAIN_THRESHOLD, explain MIN_EFFECT_NOISE_RATIO times the sensor noise and not raise the peak by
    more than PEAK_TOLERANCE; where the held-out data leave the fit part's voltage range (``Score.known_rms``),
    it must not raise the RMS before they first do: a cut made only where the model extrapolates is the
    extrapolation's, not the effect's."""
    cut = 1.0 - with_.rms / without.rms if without.rms > 0 else 0.0
    explained = math.sqrt(max(without.rms ** 2 - with_.rms ** 2, 0.0))
    return cut, explained, (cut >= GAIN_THRESHOLD and explained >= MIN_EFFECT_NOISE_RATIO * noise_um
                            and with_.peak <= PEAK_TOLERANCE * without.peak and not _worse_where_known(with_, without))
