"""The whole of a long record: streamed to the analysis rate, and searched for a slow trend the loop's stretch
cannot show.

A record longer than ``MAX_ANALYSED_S`` is analysed in two parts.  The residual loop fits the fast parts (the GPIM's
shape, G_v, delay, creep, the effects it finds) on its first ``MAX_ANALYSED_S`` at the analysis rate.  The whole
record counts for what only shows over time: it is reduced to block means at the analysis rate as it is read
(``BlockMeans``: memory of one message, not of the record), the stretch's model runs over all of it in chunks
(``whole_residual``: each chunk after a warm-up long enough for creep's slowest lag to settle, so memory is that
of one chunk and cost is linear in length; per block of TREND_BLOCK_S the sums a least-squares fit needs), and the
residual is searched for a smooth trend in time of offset and gain (``trend_search``): the drift effect's "whole"
form, cubic B-splines over the whole record on intervals no finer than ``TREND_RESOLUTION_S`` (each zero outside
four of them, so a trend that sets in late leaves the rest untouched), fitted at the analysis rate from the blocks'
sums.  The trend is scored by two-fold cross-validation over alternate ``TREND_SEGMENT_S`` stretches and judged by
the loop's own rule (``search.support``); a trend that shows only late in the record (a warm-up at minute 20) is
found where it happens.  Where the model has creep, its slow terms (time constants from ``NUISANCE_MIN_TAU_S``:
what a stretch of ``MAX_ANALYSED_S`` determines least) are refitted over the whole record on both sides of that
judgement, so a trend must explain what creep, refitted there, does not (a creeping valve's slow tail beyond the
stretch is not a drift).  Nothing here imports ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from ..metrics import rms
from .effects.base import normalised
from .effects.drift import Drift
from .records import ANALYSIS_RATE_HZ, Record
from .search import NoiseLevels, Score, Support, support
from .valve_model import REST, ValveModel

__all__ = ["BlockMeans", "whole_residual", "WholeResidual", "trend_search", "Trend", "slow_creep_rows", "TREND_BLOCK_S",
           "TREND_SEGMENT_S", "TREND_RESOLUTION_S", "TREND_TERMS", "CHUNK_S", "WARM_UP_S", "NUISANCE_MIN_TAU_S"]

TREND_BLOCK_S = 0.25          # the residual's block means the trend is fitted to [s]
TREND_SEGMENT_S = 20.0        # cross-validation: alternate stretches this long fit and score each other [s]
TREND_RESOLUTION_S = 60.0    # the trend's spline intervals span at least this long [s] (coarser than a
                              # repeated experiment's period: a trend is not the hysteresis' periodic misfit)
TREND_TERMS = (1, 2, 4, 8, 16, 32, 64)   # spline intervals tried, up to the record's resolution
CHUNK_S = 200.0               # the model runs over the record this long at a time [s] ...
WARM_UP_S = 150.0             # ... after this long before it (3x creep's slowest lag: its transient < 5 %) [s]
MIN_STREAM_ROWS = 64          # the sampling period is taken from at least this many first rows
NUISANCE_MIN_TAU_S = 1.5      # creep's terms of this time constant and slower are refitted beside a trend [s]


class BlockMeans:
    """Rows (time [s], voltage [V], position [m]) streamed in, the record at most ``max_rate_hz`` out: block means as
    ``records.analysis_record`` takes them (the same block length and source period), with a memory of one message.
    Rows at or before the last one taken are dropped and counted in ``dropped`` (a batch delivered twice counts
    once).  ``record()`` gives the reduced record so far; ``rows`` counts the source rows taken."""

    def __init__(self, max_rate_hz: float = ANALYSIS_RATE_HZ):
        self.max_rate_hz = max_rate_hz
        self.k: Optional[int] = None           # source rows per block, once the period is known
        self.source_dt: Optional[float] = None
        self.pending: list[np.ndarray] = []    # rows not yet in a block
        self.blocks: list[np.ndarray] = []     # (m, 3) block means: time, voltage, position [um]
        self.rows = 0
        self.dropped = 0   # rows at or before one taken already (delivered twice, or out of order)
        self.last_s = -math.inf

    def add(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, float)
        if rows.shape[0] == 0:
            return
        if not rows[0, 0] > self.last_s or np.any(np.diff(rows[:, 0]) <= 0):
            later = np.maximum.accumulate(np.concatenate(([self.last_s], rows[:, 0])))[:-1]
            keep = rows[:, 0] > later
            self.dropped += int(rows.shape[0] - np.count_nonzero(keep))
            rows = rows[keep]
            if rows.shape[0] == 0:
                return
        self.last_s = float(rows[-1, 0])
        self.rows += rows.shape[0]
        self.pending.append(rows[:, :3])
        if self.k is None:
            if sum(p.shape[0] for p in self.pending) < MIN_STREAM_ROWS:
                return
            first = np.concatenate(self.pending)
            self.source_dt = float(np.median(np.diff(first[:, 0])))
            self.k = (max(int(math.floor(1.0 / (self.max_rate_hz * self.source_dt) + 1e-9)), 1)
                      if math.isfinite(self.max_rate_hz) else 1)
        self._reduce()

    def _reduce(self) -> None:
        rows = np.concatenate(self.pending) if len(self.pending) > 1 else self.pending[0]
        n = rows.shape[0] // self.k * self.k
        if n:
            means = rows[:n].reshape(-1, self.k, 3).mean(axis=1)
            means[:, 2] *= 1e6
            self.blocks.append(means)
        self.pending = [rows[n:]] if n < rows.shape[0] else []

    def record(self) -> Record:
        """The reduced record so far (a trailing partial block left out, as ``analysis_record`` does)."""
        if self.k is None and self.pending:   # fewer rows than MIN_STREAM_ROWS: the period from what there is
            first = np.concatenate(self.pending)
            self.source_dt = float(np.median(np.diff(first[:, 0]))) if first.shape[0] > 1 else math.nan
            self.k = 1
            self._reduce()
        rows = np.concatenate(self.blocks) if self.blocks else np.zeros((0, 3))
        self.blocks = [rows]
        return Record(rows[:, 0], rows[:, 1], rows[:, 2], self.k or 1, self.source_dt)


@dataclass(frozen=True)
class WholeResidual:
    """A model's residual over a whole record, in TREND_BLOCK_S block means: block times [s], the residual
    (measured - predicted) [um], the hysteresis output normalised as the drift effect's gain terms take it, and the
    rows each block averages (at the record's analysis rate); ``sums``: per block, the sums over its rows of e^2,
    e h and h^2 (e the residual, h that output), from which ``rms_with`` gives the RMS at the analysis rate with a
    trend taken out.  ``nuisance``: per block, the sums over its rows of c c', c e, c h and c for the k columns c
    refitted beside a trend (creep's slow terms, ``slow_creep_rows``; k = 0: none), shapes (blocks, k, k) and
    (blocks, k) x 3."""

    time_s: np.ndarray
    error_um: np.ndarray
    gain_input: np.ndarray
    rows_per_block: int
    sums: np.ndarray   # (blocks, 3)
    nuisance: tuple = ()   # (cc, ce, ch, c) or () for none
    nuisance_names: str = ""   # what the nuisance columns are, in words

    @property
    def k(self) -> int:
        """Columns refitted beside a trend."""
        return self.nuisance[1].shape[1] if self.nuisance else 0

    def rms_with(self, offset_um: np.ndarray, gain_um: np.ndarray, rows: slice = slice(None)) -> float:
        """The residual's RMS [um] at the analysis rate over the blocks ``rows``, less a trend of ``offset_um`` +
        ``gain_um`` x h per block (constant within a block: TREND_BLOCK_S is far shorter than any trend's scale)."""
        e = _block_errors(self, offset_um, gain_um)[rows]
        return math.sqrt(float(np.mean(e * e))) if e.size else 0.0


def slow_creep_rows(model: ValveModel) -> Optional[tuple[Callable[[object], np.ndarray], str]]:
    """(rows, words): ``rows(ctx)`` the (k, N) terms of ``model``'s creep with time constants of NUISANCE_MIN_TAU_S
    and slower (plain, by direction, by level), through G, on a context of the model; None where the model has no
    creep, or none that slow."""
    from ..model.at_rest import filter_rows_at_rest
    term = model.term("creep")
    if term is None:
        return None
    creep = term[0]
    n, k = len(creep.time_constants_s), len(creep.shaped)
    slow = [i for i, t in enumerate(creep.time_constants_s) if t >= NUISANCE_MIN_TAU_S]
    shaped = [i for i, t in enumerate(creep.shaped) if t >= NUISANCE_MIN_TAU_S]
    index = slow + [n + i for i in shaped] + [n + k + i for i in shaped]
    if not index:
        return None
    taus = [creep.time_constants_s[i] for i in slow]
    words = (f"creep's {len(index)} terms of {min(taus):g} s and slower ({', '.join(f'{t:g}' for t in taus)} s) "
             f"refitted over the whole record")
    return (lambda ctx: filter_rows_at_rest(*ctx.filter, creep.design_rows(ctx)[index])), words


def whole_residual(model: ValveModel, record: Record, drift: Drift,
                   progress: Callable[[str], None] = lambda s: None, nuisance: Optional[tuple] = None
                   ) -> WholeResidual:
    """``model``'s residual over ``record`` (the whole record at the analysis rate) in TREND_BLOCK_S block means,
    run CHUNK_S at a time, each chunk after WARM_UP_S of the record before it (from rest there; the first from the
    model's own start): memory of one chunk, cost linear in length.  ``drift`` gives the gain terms' normalisation;
    ``nuisance``: (rows, words) of columns to refit beside a trend (``slow_creep_rows``), their sums kept per block."""
    dt = record.dt
    per_block = max(int(round(TREND_BLOCK_S / dt)), 1)
    chunk = max(int(round(CHUNK_S / dt)) // per_block, 1) * per_block
    warm = int(round(WARM_UP_S / dt))
    n = len(record) // per_block * per_block
    times, errors, gains, sums, extra = [], [], [], [], []
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        first = max(start - warm, 0)
        part = record.slice(first, stop)
        m = model if first == 0 else _from_rest(model)
        ctx = m.context(part)
        static, rest = m.static_output_and_rest(ctx)
        predicted = m.after_dynamics(ctx.through_dynamics(static, rest))
        skip = start - first

        def blocks(a: np.ndarray) -> np.ndarray:
            return a[skip:].reshape(-1, per_block).mean(axis=1)
        e = (part.position_um - predicted)[skip:].reshape(-1, per_block)
        h = normalised(ctx.H, drift.centre_um, drift.half_range_um)[skip:].reshape(-1, per_block)
        times.append(blocks(part.time_s))
        errors.append(e.mean(axis=1))
        gains.append(h.mean(axis=1))
        sums.append(np.column_stack((np.einsum("ij,ij->i", e, e), np.einsum("ij,ij->i", e, h),
                                     np.einsum("ij,ij->i", h, h))))
        if nuisance is not None:
            c = nuisance[0](ctx)[:, skip:]
            c = c.reshape(c.shape[0], -1, per_block)   # (k, blocks, rows)
            extra.append((np.einsum("ibr,jbr->bij", c, c, optimize=True), np.einsum("ibr,br->bi", c, e, optimize=True),
                          np.einsum("ibr,br->bi", c, h, optimize=True), c.sum(axis=2).T))
        progress(f"whole record: the stretch's model run to {part.time_s[-1]:.0f} s of "
                 f"{record.time_s[-1]:.0f} s")
    return WholeResidual(np.concatenate(times), np.concatenate(errors), np.concatenate(gains), per_block,
                         np.concatenate(sums), tuple(np.concatenate(x) for x in zip(*extra)) if extra else (),
                         nuisance[1] if nuisance is not None else "")


def _from_rest(model: ValveModel) -> ValveModel:
    return replace(model, history=REST)


@dataclass(frozen=True)
class Trend:
    """The trend search's finding: the drift effect over the whole record (``effect``, ``coefs``: its offset then gain
    coefficients [um]) where ``support`` supports it; the residual's cross-validated block RMS without and with it
    [um], the trend's size (peak to peak [um]) and the first time it departs from its start by a tenth of that,
    what every form tried scored (by its intervals and terms), and the residual's RMS at the analysis rate without and with
    the trend: by tenth of the record, over all of it, and over what lies beyond the analysed stretch."""

    effect: Drift
    coefs: np.ndarray
    support: Support
    without_um: float
    with_um: float
    peak_to_peak_um: float
    onset_s: float
    tried: dict
    stretch_rms_um: tuple[tuple[float, float, float, float], ...]   # (from_s, to_s, rms without, rms with) by tenth
    rms_um: tuple[float, float]          # the residual's RMS at the analysis rate over the record, without and with
    beyond_rms_um: tuple[float, float]   # ... over what lies beyond the analysed stretch (never fitted)
    judged_beside: str = ""              # what was refitted beside it on both sides of the judgement ("": nothing)

    @property
    def supported(self) -> bool:
        return self.support.supported


def _normal_equations(residual: WholeResidual, F: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares normal equations of the nuisance columns (a, constant over the record) and the trend (offset
    F c and gain F d times h, each block's F constant over its rows) over the blocks ``rows``, at the analysis rate:
    exact from the blocks' sums.  Unknowns in the order (a, c, d)."""
    n, Fr = residual.rows_per_block, F[rows]
    sum_e, sum_h = residual.error_um[rows] * n, residual.gain_input[rows] * n
    sums = residual.sums[rows]
    gram = np.block([[Fr.T @ Fr * n, Fr.T @ (Fr * sum_h[:, None])],
                     [Fr.T @ (Fr * sum_h[:, None]), Fr.T @ (Fr * sums[:, 2:3])]])
    rhs = np.concatenate((Fr.T @ sum_e, Fr.T @ sums[:, 1]))
    if not residual.k:
        return gram, rhs
    cc, ce, ch, c = (x[rows] for x in residual.nuisance)
    cross = np.hstack((c.T @ Fr, ch.T @ Fr))   # (k, 2m)
    return np.block([[cc.sum(axis=0), cross], [cross.T, gram]]), np.concatenate((ce.sum(axis=0), rhs))


def _solve_form(gram: np.ndarray, rhs: np.ndarray, k: int, with_gain: bool, trend: bool = True) -> np.ndarray:
    """(a, c, d) of ``_normal_equations`` (k nuisance columns, then m offset and m gain terms): the gain terms zero
    where ``with_gain`` is False, the trend's where ``trend`` is False (the nuisance alone)."""
    m = (rhs.size - k) // 2
    keep = np.zeros(rhs.size, bool)
    keep[:k] = True
    keep[k:k + m] = trend
    keep[k + m:] = trend and with_gain
    out = np.zeros(rhs.size)
    if keep.any():
        out[keep] = _solve(gram[np.ix_(keep, keep)], rhs[keep])
    return out


def _solve(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    g = gram / np.outer(scale, scale)
    g[np.diag_indices_from(g)] += 1e-10
    return np.linalg.lstsq(g, rhs / scale, rcond=None)[0] / scale


def _block_errors(residual: WholeResidual, offset_um: np.ndarray, gain_um: np.ndarray,
                  nuisance: Optional[np.ndarray] = None) -> np.ndarray:
    """Each block's RMS error at the analysis rate less the trend and (``nuisance``: their coefficients a) the
    nuisance columns (what ``search.Score`` takes as the held-out error: its RMS, stretches' mean squares and peak
    are those of the rows, a block's peak its RMS)."""
    n = residual.rows_per_block
    e, h, s = residual.error_um * n, residual.gain_input * n, residual.sums
    sse = (s[:, 0] - 2 * offset_um * e - 2 * gain_um * s[:, 1] + n * offset_um ** 2 + 2 * offset_um * gain_um * h
           + gain_um ** 2 * s[:, 2])
    if nuisance is not None and residual.k:
        cc, ce, ch, c = residual.nuisance
        sse = (sse - 2 * ce @ nuisance + np.einsum("i,bij,j->b", nuisance, cc, nuisance)
               + 2 * offset_um * (c @ nuisance) + 2 * gain_um * (ch @ nuisance))
    return np.sqrt(np.maximum(sse, 0.0) / n)


def trend_search(residual: WholeResidual, t0: float, duration_s: float, like: Drift, noise: NoiseLevels,
                 log: Callable[[str], None] = lambda s: None, stretch_end_s: float = -math.inf,
                 from_s: float = 0.0) -> Trend:
    """Search ``residual`` for a smooth trend in time of offset and gain (the drift effect's "whole" form over
    ``duration_s`` [s] from ``t0``), with every number of spline intervals in TREND_TERMS the record resolves
    (TREND_RESOLUTION_S), of offset alone and of offset and gain; each fitted at the analysis rate (the normal equations from the blocks' sums) and scored by
    two-fold cross-validation over alternate TREND_SEGMENT_S stretches, the best judged by ``search.support`` against
    no trend (``noise``: the floor at the record's and the analysis rate).  The trend starts ``from_s`` [s] after
    ``t0`` (zero before: the stretch the model was fitted and judged on, where it showed none).  Where ``residual``
    carries nuisance columns (creep's slow terms), they are refitted on both sides: the trend is judged against
    them alone, cross-validated the same way (a trend must explain what they, refitted over the whole record, do
    not); the trend the model takes is fitted without them."""
    segment = np.floor((residual.time_s - residual.time_s[0]) / TREND_SEGMENT_S).astype(int)
    folds = (segment % 2 == 0, segment % 2 == 1)
    most = max(int((duration_s - from_s) // TREND_RESOLUTION_S), 1)
    zero = np.zeros(residual.time_s.size)
    q = residual.k

    def cross_validated(F: np.ndarray, with_gain: bool, trend: bool = True) -> np.ndarray:
        """Each block's error scored by the fit on the other fold (the nuisance columns and, with ``trend``, the
        trend of ``F``)."""
        cv, m = np.empty_like(zero), F.shape[1]
        for rows, score_rows in zip(folds, folds[::-1]):
            x = _solve_form(*_normal_equations(residual, F, rows), q, with_gain, trend)
            cv[score_rows] = _block_errors(residual, F @ x[q:q + m], F @ x[q + m:], x[:q])[score_rows]
        return cv

    tried, best = {}, None
    for k in [k for k in TREND_TERMS if k <= most]:
        effect = like.whole(duration_s, k, from_s)
        F = effect.time_rows(residual.time_s - t0).T
        for with_gain in (False, True):   # an offset alone, or offset and gain (nested: the simpler first)
            cv = cross_validated(F, with_gain)
            label = f"{k}{' offset and gain' if with_gain else ' offset'}"
            tried[label] = rms(cv)
            if best is None or tried[label] < tried[best[0]]:
                best = (label, effect, F, cv, with_gain)
    label, effect, F, cv, with_gain = best
    k = effect.trend_terms
    alone = cross_validated(F, False, trend=False) if q else _block_errors(residual, zero, zero)
    without, with_ = Score.of(alone), Score.of(cv)
    sup = support(with_, without, noise)
    bare = replace(residual, nuisance=())   # the trend the model takes: fitted without the nuisance columns (the
    # model keeps the stretch's creep; fitted beside them, the trend trades against terms that smooth and slow)
    coefs = _solve_form(*_normal_equations(bare, F, np.ones(zero.size, bool)), 0, with_gain)
    offset, gain = F @ coefs[:F.shape[1]], F @ coefs[F.shape[1]:]
    full = offset + gain * residual.gain_input   # the trend's block means
    pp = float(np.ptp(full)) if full.size else 0.0
    departs = np.flatnonzero(np.abs(full - full[0]) > 0.1 * pp) if pp > 0 else np.array([], int)
    onset = float(residual.time_s[departs[0]]) if departs.size else float(residual.time_s[0])
    tenths = [i for i in np.array_split(np.arange(zero.size), 10) if i.size]
    stretches = tuple((float(residual.time_s[i[0]]), float(residual.time_s[i[-1]]),
                       residual.rms_with(zero, zero, slice(i[0], i[-1] + 1)),
                       residual.rms_with(offset, gain, slice(i[0], i[-1] + 1))) for i in tenths)
    beyond = slice(int(np.searchsorted(residual.time_s, stretch_end_s, side="right")), None)
    whole = (residual.rms_with(zero, zero), residual.rms_with(offset, gain))
    past = ((residual.rms_with(zero, zero, beyond), residual.rms_with(offset, gain, beyond))
            if residual.time_s[beyond].size else (math.nan, math.nan))
    beside = f" beside {residual.nuisance_names}" if q else ""
    log(f"whole record: a trend of {'offset and gain' if with_gain else 'offset'} on {k} spline interval(s) scores best "
        f"({', '.join(f'{n}: {r:.4f}' for n, r in tried.items())} um RMS, cross-validated{beside}; without a trend "
        f"{without.rms:.4f} um); offset {float(np.ptp(offset)):.3f} um and gain {float(np.ptp(gain)):.3f} um peak "
        f"to peak, in all {pp:.3f} um, from {onset:.0f} s")
    return Trend(effect, coefs, sup, without.rms, with_.rms, pp, onset, tried, stretches, whole, past,
                 residual.nuisance_names)
