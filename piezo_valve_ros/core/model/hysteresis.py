"""Play operator, Generalized Prandtl-Ishlinskii model (GPIM) and its exact inverse.

Units follow the paper: model input is the amplifier input voltage [V], model
output is spool position [um].  Nothing here imports ROS.

The play operator with threshold ``r`` is a clamp of its own state::

    z_k = min(max(z_{k-1}, L_k), U_k),   L_k = gamma_asc(v_k) - r,  U_k = gamma_desc(v_k) + r

(for the paper's symmetric envelope ``gamma_asc = gamma_desc = a0*v + a1``).  Where the bounds cross (a descending
envelope below the ascending one, thresholds the rate narrows below zero) the formula's last clamp, the upper
bound, wins: the state is ``U_k``, as the paper's operator (``paper.md``) and other implementations of it give.
Clamps compose into clamps, and within a monotone stretch of input the state is
the closed form ``clip(z_at_last_reversal, L_k, U_k)``.  The batch evaluation
uses both facts: a log-depth scan over the reversal points only, then one vectorised
clip over all samples; asked to (the identification's long records), it runs the plain
recursion compiled instead (numba, ``_play_kernel``: the same bits, min and max do not
round).  The streaming ``step`` is the plain recursion.
"""
from __future__ import annotations

import functools
import math
import operator
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..errors import PiezoValveError
from .compiled import load as load_kernels
from .drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V

__all__ = ["GPIM_PARAMS_KEYS", "play_bounds", "contact_sensitivity", "CONTACT_BOUNDS", 
    "PlayOperatorBank",
    "play_batch",
    "last_contact",
    "GPIM",
    "GPIMParams",
    "InverseGPIM",
    "MonotoneInverseGPIM",
    "inverse_gpim",
    "inverse_problems",
    "dead_band_problems",
    "NotInvertibleError",
    "PAPER_GPIM",
    "turning_points",
    "dominant_turning_points",
]


OUTPUT_RANGE_POINTS = 401     # major-loop points behind GPIM.output_range
ORDER_TOLERANCE_V = 1e-12     # breakpoints out of the operators' order by no more than rounding count as in order
HOLD_TOLERANCE_UM = 1e-12   # a demand this close to the present output [um] holds the input (the output summed
                            # operator by operator differs from the model's dot product in the last bits)


class NotInvertibleError(PiezoValveError, ValueError):
    """A parameter set that has no analytic inverse (the reason is the message)."""


# --------------------------------------------------------------------------- play operator
def _hillis_steele(A: np.ndarray, B: np.ndarray, axis: int) -> None:
    """In-place inclusive clamp-composition scan along ``axis`` (log2 passes)."""
    count = A.shape[axis]
    step = 1
    while step < count:
        later = [slice(None)] * A.ndim
        earlier = [slice(None)] * A.ndim
        later[axis] = slice(step, None)
        earlier[axis] = slice(None, -step)
        later, earlier = tuple(later), tuple(earlier)
        later_lo, later_hi = A[later], B[later]
        new_lo = np.minimum(np.maximum(A[earlier], later_lo), later_hi)
        new_hi = np.minimum(np.maximum(B[earlier], later_lo), later_hi)
        A[later] = new_lo
        B[later] = new_hi
        step *= 2


SCAN_BLOCK = 32           # rows composed one after another in each block of the clamp scan ...
SCAN_BLOCK_LONG = 64      # ... and in records of at least SCAN_LONG_ROWS rows (fewer levels of block totals)
SCAN_LONG_ROWS = 16384
ROW_BLOCK = 4096   # rows per block of the batch paths over (N, n) arrays (play_batch's clip, last_contact, the fits'
                   # contact gathers): a block's (rows, n) arrays stay in the cache, none of (N, n) is a temporary


def _compose_clamps_scan(lo: np.ndarray, hi: np.ndarray, block: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive prefix composition of clamps along axis 0.

    Element k is the clamp ``z -> min(max(z, lo[k]), hi[k])`` (lo <= hi).  Returns
    (A, B) with ``f_k o ... o f_0 (z) = min(max(z, A[k]), B[k])``.  Two-level scheme: the rows of each block
    composed one after another (a step is one operation on a row of every block at once), the block totals
    scanned recursively, then one combining pass: a few passes over the data.  Clamps compose exactly (min
    and max do not round), so any grouping gives the same bits.
    """
    count = lo.shape[0]
    block = block or (SCAN_BLOCK_LONG if count >= SCAN_LONG_ROWS else SCAN_BLOCK)
    if count <= 4 * block:
        A, B = lo.copy(), hi.copy()
        _hillis_steele(A, B, 0)
        return A, B
    n_blocks = -(-count // block)
    pad = n_blocks * block - count
    rest = lo.shape[1:]
    # laid out (block, n_blocks, ...): each step of the in-block composition is one contiguous slab;
    # the padding is the identity clamp (-inf, +inf)
    A = np.concatenate((lo, np.full((pad,) + rest, -np.inf))).reshape((n_blocks, block) + rest).swapaxes(0, 1).copy()
    B = np.concatenate((hi, np.full((pad,) + rest, np.inf))).reshape((n_blocks, block) + rest).swapaxes(0, 1).copy()
    for k in range(1, block):
        lo_k, hi_k = A[k], B[k]
        after_lo = np.maximum(A[k - 1], lo_k)
        after_hi = np.maximum(B[k - 1], lo_k)
        np.minimum(after_lo, hi_k, out=A[k])
        np.minimum(after_hi, hi_k, out=B[k])
    tot_A, tot_B = _compose_clamps_scan(A[-1], B[-1], block)
    prev_A, prev_B = tot_A[None, :-1], tot_B[None, :-1]
    inner_A, inner_B = A[:, 1:], B[:, 1:]
    new_A = np.minimum(np.maximum(prev_A, inner_A), inner_B)
    B[:, 1:] = np.minimum(np.maximum(prev_B, inner_A), inner_B)
    A[:, 1:] = new_A
    shape = (n_blocks * block,) + rest
    return A.swapaxes(0, 1).reshape(shape)[:count], B.swapaxes(0, 1).reshape(shape)[:count]


def _union(*indices: np.ndarray) -> np.ndarray:
    """Sorted distinct values of integer index arrays (``np.union1d`` by sort and compare: numpy's hashed unique
    costs several times as much on the long turn lists of a closed-loop record)."""
    merged = np.sort(np.concatenate(indices), kind="stable")
    if merged.size < 2:
        return merged
    keep = np.empty(merged.size, bool)
    keep[0] = True
    np.not_equal(merged[1:], merged[:-1], out=keep[1:])
    return merged[keep]


def _reversal_indices(drive: np.ndarray) -> np.ndarray:
    """Indices that end a monotone stretch of ``drive`` (always includes 0 and N-1)."""
    n = drive.shape[0]
    if n <= 2:
        return np.arange(n)
    direction = np.sign(np.diff(drive))
    nonzero = np.flatnonzero(direction)
    if nonzero.size == 0:
        return np.array([0, n - 1])
    # carry the last non-zero direction over flat stretches
    carried = direction[nonzero][np.maximum(np.searchsorted(nonzero, np.arange(n - 1), side="right") - 1, 0)]
    change = np.flatnonzero(carried[1:] != carried[:-1]) + 1  # sample index where direction flips
    return np.concatenate(([0], change, [n - 1]))


def _clamp_bounds(lower_drive: np.ndarray, upper_drive: np.ndarray, r: np.ndarray, symmetric: bool,
                  scale: Optional[np.ndarray] = None):
    """The clamp bounds (lower, upper), shape (N, n), as every batch path computes them (bit for bit: the
    sensitivities test states for equality with them).  The upper bound may lie below the lower one.
    ``scale`` (N,) multiplies the thresholds sample by sample."""
    rs = r if scale is None else r * scale[:, None]
    lo = lower_drive[:, None] - rs
    return lo, (lo + 2.0 * rs if symmetric else upper_drive[:, None] + rs)


def _turns_per_operator(drive: np.ndarray, r: np.ndarray, scale: np.ndarray, sign: float,
                        chunk: int = 1 << 15) -> np.ndarray:
    """Indices where ``drive + sign * r_j * scale`` reverses for any operator j (with 0 and N-1)."""
    n = drive.shape[0]
    d_drive, d_scale = np.diff(drive), np.diff(scale)
    carried = np.zeros(r.size)
    turns = [np.array([0])]
    for start in range(0, n - 1, chunk):
        stop = min(start + chunk, n - 1)
        direction = np.sign(d_drive[start:stop, None] + sign * r * d_scale[start:stop, None])
        rows = np.arange(stop - start)[:, None]
        last = np.maximum.accumulate(np.where(direction != 0, rows, -1), axis=0)
        filled = np.where(last >= 0, np.take_along_axis(direction, np.maximum(last, 0), axis=0), carried)
        previous = np.vstack((carried[None, :], filled[:-1]))
        change = np.any((filled != previous) & (previous != 0), axis=1)
        turns.append(np.flatnonzero(change) + start)
        carried = filled[-1]
    turns.append(np.array([n - 1]))
    return _union(*turns)


def _last_crossed_indices(lower_drive: np.ndarray, upper_drive: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Samples after which some operator's bounds stop crossing (lower - r > upper + r, where the upper bound
    wins and the state is ``upper + r`` whatever came before), and the first sample after: while crossed, the
    effective lower bound ``min(lower - r, upper + r)`` follows the upper drive, so it need not move with the
    lower drive, and the state after is not a clip of one from before (thresholds that narrow with the
    rate, crossing envelopes)."""
    crossed = np.searchsorted(2.0 * r, lower_drive - upper_drive, side="left")   # operators with 2 r_j < L - U
    last = np.flatnonzero(crossed[1:] < crossed[:-1])
    return _union(last, last + 1)   # the last crossed sample and the first after it


def play_batch(
    lower_drive: np.ndarray,
    upper_drive: np.ndarray,
    thresholds: np.ndarray,
    initial_state: np.ndarray,
    weights: Optional[np.ndarray] = None,
    chunk: int = ROW_BLOCK,
    threshold_scale: Optional[np.ndarray] = None,
    compiled: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate a bank of (generalized) play operators over a whole record.

    ``lower_drive`` = gamma_asc(v) and ``upper_drive`` = gamma_desc(v), shape (N,); where an operator's bounds
    cross (``upper_drive + r < lower_drive - r``) the upper one wins.  Within any stretch where
    each drive is monotone (whichever way each goes) an operator's state is the clip of its state at the
    stretch's start to the present bounds, so only the reversal points of either drive are scanned:
    this covers asymmetric envelopes and thresholds that widen with time (rate dependence: pass
    ``lower - w`` and ``upper + w``, and ``threshold_scale`` (N,) to scale the thresholds sample by sample,
    which adds each operator's own reversal points).  ``thresholds`` shape (n,).  ``chunk`` rows are clipped
    at a time (their (chunk, n) bounds stay in the cache; the result does not depend on it).  With ``compiled``,
    records of ``KERNEL_MIN_WORK`` operator-samples and more run the recursion itself compiled (numba), to the
    same bits: the identification asks for it; the control and simulator paths the nodes run do not (loading
    numba takes a fraction of a second, a stall inside a control period).
    Returns ``(out, final_state)``: with ``weights`` given, ``out`` is the weighted sum
    (N,); otherwise the operator states (N, n).
    """
    lower_drive = np.asarray(lower_drive, dtype=float)
    upper_drive = np.asarray(upper_drive, dtype=float)
    r = np.asarray(thresholds, dtype=float)
    z0 = np.asarray(initial_state, dtype=float)
    n_samples = lower_drive.shape[0]
    if n_samples == 0:
        empty = np.zeros(0) if weights is not None else np.zeros((0, r.size))
        return empty, z0.copy()
    same = lower_drive is upper_drive or np.array_equal(lower_drive, upper_drive)
    scale = None if threshold_scale is None else np.asarray(threshold_scale, dtype=float)
    if compiled and n_samples * r.size >= KERNEL_MIN_WORK:
        return _play_by_kernel(lower_drive, upper_drive, r, z0, weights, chunk, scale, same)
    if scale is not None:
        turns = _union(_turns_per_operator(lower_drive, r, scale, -1.0),
                           _turns_per_operator(upper_drive, r, scale, 1.0))
    elif same:
        turns = _reversal_indices(lower_drive)
    else:
        turns = _union(_reversal_indices(lower_drive), _reversal_indices(upper_drive))
    if not same:
        turns = _union(turns, _last_crossed_indices(lower_drive, upper_drive, r))
    lo_t, hi_t = _clamp_bounds(lower_drive[turns], upper_drive[turns], r, same, None if scale is None else scale[turns])
    lo_t = np.minimum(lo_t, hi_t)   # crossed bounds: the upper wins (min(max(z, lo), hi) = hi)
    A, B = _compose_clamps_scan(lo_t, hi_t)
    state_at_turns = np.minimum(np.maximum(z0, A), B)  # (R, n)
    # base state for sample t in (T_k, T_{k+1}] is the state at T_k; for t = 0 it is z0
    bases = np.vstack((z0[None, :], state_at_turns))
    symmetric = same
    if weights is not None:
        out = np.empty(n_samples)
    else:
        out = np.empty((n_samples, r.size))
    for start in range(0, n_samples, chunk):
        stop = min(start + chunk, n_samples)
        idx = np.searchsorted(turns, np.arange(start, stop), side="left")
        lo, hi = _clamp_bounds(lower_drive[start:stop], upper_drive[start:stop], r, symmetric,
                               None if scale is None else scale[start:stop])
        z = np.maximum(bases[idx], lo, out=lo)
        z = np.minimum(z, hi, out=z)
        if weights is not None:
            out[start:stop] = z @ weights
        else:
            out[start:stop] = z
    return out, state_at_turns[-1].copy()


KERNEL_MIN_WORK = 20000   # operator-samples from which play_batch and last_contact, asked to, run compiled
                          # (_play_kernel): below, numpy's vectorised forms cost less than the kernels' first load


@functools.cache
def _kernels():
    """The compiled recursions (``_play_kernel``), loaded on first use."""
    return load_kernels(__package__ + "._play_kernel")


def _play_by_kernel(lower_drive, upper_drive, r, z0, weights, chunk, scale, symmetric):
    """``play_batch`` by the compiled recursion, ``chunk`` rows at a time (the weighted sum of each block as the
    composed-clamp path forms it)."""
    n_samples = lower_drive.shape[0]
    run = _kernels().play_rows
    z = np.array(z0, dtype=float)
    r = np.array(r, dtype=float)   # a writable copy: the kernel compiles once, not again for read-only thresholds
    no_scale = np.zeros(0)
    lower_drive, upper_drive = np.ascontiguousarray(lower_drive), np.ascontiguousarray(upper_drive)
    if weights is None:
        out = np.empty((n_samples, r.size))
        run(lower_drive, upper_drive, r, no_scale if scale is None else np.ascontiguousarray(scale), symmetric, z, out)
        return out, z
    out = np.empty(n_samples)
    block = np.empty((min(chunk, n_samples), r.size))
    for start in range(0, n_samples, chunk):
        stop = min(start + chunk, n_samples)
        rows = block[:stop - start]
        run(lower_drive[start:stop], upper_drive[start:stop], r,
            no_scale if scale is None else np.ascontiguousarray(scale[start:stop]), symmetric, z, rows)
        out[start:stop] = rows @ weights
    return out, z


def play_bounds(lower_drive: np.ndarray, upper_drive: np.ndarray, thresholds: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """How a bank of play operators depends on its initial state: (L, U), each (N, n), such that the states
    :func:`play_batch` gives from any initial state z0 are ``min(max(z0, L), U)`` (clamps compose into one).  Where
    ``L == U`` the input has wiped the start out of that operator; before, its state is its start clipped.  The
    drives and thresholds as :func:`play_batch` takes them (no per-sample threshold scale)."""
    lower_drive = np.asarray(lower_drive, dtype=float)
    upper_drive = np.asarray(upper_drive, dtype=float)
    r = np.asarray(thresholds, dtype=float)
    same = lower_drive is upper_drive or np.array_equal(lower_drive, upper_drive)
    turns = _reversal_indices(lower_drive) if same else _union(
        _reversal_indices(lower_drive), _reversal_indices(upper_drive),
        _last_crossed_indices(lower_drive, upper_drive, r))
    lo_t, hi_t = _clamp_bounds(lower_drive[turns], upper_drive[turns], r, same)
    A, B = _compose_clamps_scan(np.minimum(lo_t, hi_t), hi_t)
    # each sample: the composition up to the turn before it, then its own clamp
    A = np.vstack((np.full((1, r.size), -np.inf), A))
    B = np.vstack((np.full((1, r.size), np.inf), B))
    idx = np.searchsorted(turns, np.arange(lower_drive.shape[0]), side="left")
    lo, hi = _clamp_bounds(lower_drive, upper_drive, r, same)
    return np.minimum(np.maximum(A[idx], lo), hi), np.minimum(np.maximum(B[idx], lo), hi)


def last_contact(states: np.ndarray, lower_drive: np.ndarray, upper_drive: np.ndarray,
                 thresholds: np.ndarray, threshold_scale: Optional[np.ndarray] = None,
                 compiled: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Which clamp each operator touched last, and when: the exact first-order sensitivity of a play bank.

    ``states`` (N, n) as :func:`play_batch` returned them for the same drives, thresholds and scale.  An
    operator's state is a copy of one of its clamp bounds taken at its last contact, so a small change
    of the bounds moves the state by the change of that bound *at that time*.  Returns ``(side,
    index)``, both (N, n): side +1 = upper (descending) bound, -1 = lower (ascending) bound, 0 = no
    contact yet; index = sample of the last contact (-1: none).  Where both bounds coincide (threshold
    0, equal drives) the side follows the direction of the input; where the upper bound lies below the
    lower one the upper wins.
    """
    lower_drive = np.asarray(lower_drive, float)
    upper_drive = np.asarray(upper_drive, float)
    r = np.asarray(thresholds, float)
    scale = None if threshold_scale is None else np.asarray(threshold_scale, float)
    same = lower_drive is upper_drive or np.array_equal(lower_drive, upper_drive)
    n = states.shape[0]
    if compiled and states.size >= KERNEL_MIN_WORK:   # the scan compiled (the same sides and indices; see play_batch)
        side_last, index = np.empty(states.shape, np.int8), np.empty(states.shape, np.int32)
        # the thresholds as a writable copy: the kernel compiles once, not again for read-only ones
        _kernels().last_contacts(np.ascontiguousarray(states), np.ascontiguousarray(lower_drive),
                                 np.ascontiguousarray(upper_drive), np.array(r, dtype=float),
                                 np.zeros(0) if scale is None else np.ascontiguousarray(scale), same,
                                 lower_drive + upper_drive, side_last, index)
        return side_last, index
    descending = None   # where both bounds coincide: +1 if the input last moved down, else -1 (per sample)
    side_last = np.empty(states.shape, np.int8)
    index = np.empty(states.shape, np.int32)
    carried_index = np.full(states.shape[1], -1, np.int32)   # the last contact before the block, and its side
    carried_side = np.zeros(states.shape[1], np.int8)
    for start in range(0, n, ROW_BLOCK):
        rows = slice(start, min(start + ROW_BLOCK, n))
        lo, hi = _clamp_bounds(lower_drive[rows], upper_drive[rows], r, same, None if scale is None else scale[rows])
        z = states[rows]
        on_lo = z == lo
        on_hi = z == hi
        side = on_hi.astype(np.int8) - on_lo.astype(np.int8)
        both = on_lo & on_hi
        if both.any():
            if descending is None:
                drive = lower_drive + upper_drive
                d = np.sign(np.diff(drive, prepend=drive[0]))
                last = np.maximum.accumulate(np.where(d != 0, np.arange(d.size), 0))
                descending = np.where(d[last] < 0, 1, -1).astype(np.int8)
            side = np.where(both, descending[rows][:, None], side)
        local = np.where(on_lo | on_hi, np.arange(rows.stop - rows.start, dtype=np.int32)[:, None], np.int32(-1))
        np.maximum.accumulate(local, axis=0, out=local)
        block_side = np.take_along_axis(side, np.maximum(local, 0), axis=0)
        before = local < 0   # no contact yet in this block: the one carried in
        np.copyto(block_side, np.broadcast_to(carried_side, block_side.shape), where=before)
        block_index = local + np.int32(rows.start)
        np.copyto(block_index, np.broadcast_to(carried_index, block_index.shape), where=before)
        side_last[rows], index[rows] = block_side, block_index
        carried_side, carried_index = block_side[-1].copy(), block_index[-1].copy()
    return side_last, index


CONTACT_BOUNDS = {"lower": -1, "upper": 1, "both": 0}   # contact_sensitivity's ``bounds``, as the kernel codes them


def contact_sensitivity(side: np.ndarray, index: np.ndarray, weights: np.ndarray, change: np.ndarray, bounds: str,
                        compiled: bool = False) -> np.ndarray:
    """dH [um] of a play bank for a small change of its operators' clamp bounds, exactly to first order: each
    operator moves by the change of the bound it touched last (``side``, ``index`` (N, n) from :func:`last_contact`),
    at that time, times its weight (``weights`` (n,) [um/V]).  ``change`` (N,) or (N, k) [V]; ``bounds`` "lower"
    (the lower bounds move by it), "upper", or "both" (thresholds widened: lower bounds down, upper bounds up).
    Returns (N,) or (N, k).  Block by block of ROW_BLOCK rows (the (N, n) products are never formed), each row
    summed as one contiguous row; ``compiled`` (records of KERNEL_MIN_WORK operator-samples and more, up to
    ``_play_kernel.PAIRWISE_BLOCK`` operators) runs it row by row in numba, to the same bits."""
    if bounds not in CONTACT_BOUNDS:
        raise ValueError(f"bounds must be one of {', '.join(CONTACT_BOUNDS)}, got {bounds!r}")
    c = np.asarray(change, float)
    columns = np.ascontiguousarray((c[:, None] if c.ndim == 1 else c).T)   # (k, N): each column contiguous
    n_rows, n = index.shape
    out = np.empty((n_rows, columns.shape[0]))
    w = np.asarray(weights, float)
    if compiled and index.size >= KERNEL_MIN_WORK and n <= _kernels().PAIRWISE_BLOCK:
        # the weights as a writable copy: a GPIM's are read-only, a caller's may not be, and the kernel would compile
        # once for each layout (a test worker that ran both saw two specialisations)
        _kernels().contact_sums(np.ascontiguousarray(side), np.ascontiguousarray(index), np.array(w, dtype=float),
                                CONTACT_BOUNDS[bounds], columns, out)
        return out[:, 0] if c.ndim == 1 else out
    which = {"lower": lambda s: (s < 0) * w, "upper": lambda s: (s > 0) * w, "both": lambda s: s * w}[bounds]
    gathered = np.empty((min(ROW_BLOCK, n_rows), n))
    for start in range(0, n_rows, ROW_BLOCK):
        rows = slice(start, min(start + ROW_BLOCK, n_rows))
        g = gathered[:rows.stop - rows.start]
        at_rows, weighted = np.maximum(index[rows], 0), which(side[rows])   # before any contact: sample 0, side 0
        for k in range(columns.shape[0]):
            np.take(columns[k], at_rows, out=g, mode="clip")   # indices lie in 0..N-1
            np.multiply(g, weighted, out=g)
            out[rows, k] = g.sum(axis=1)
    return out[:, 0] if c.ndim == 1 else out


def output_play(x: np.ndarray, width: float, compiled: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One play operator of half-width ``width`` >= 0 on a signal ``x`` (N,) (backlash: the output follows ``x``
    only where ``x`` is ``width`` away from it, and holds between), starting at ``x[0]``.
    Returns ``(y, index, side)``, each (N,): the output, the sample of the last contact (0 before any) and its
    side (+1 = the upper bound ``x + width``, -1 = the lower ``x - width``, 0 = none yet), so that
    ``y = x[index] + side * width`` exactly: linear in ``x`` and ``width`` for given contacts.  Units: those of
    ``x``.  ``compiled``: as :func:`play_batch`'s."""
    x = np.asarray(x, dtype=float)
    width = max(float(width), 0.0)
    states = play_batch(x, x, np.array([width]), x[:1].copy(), compiled=compiled)[0]
    side, index = last_contact(states, x, x, np.array([width]), compiled=compiled)
    index, side = index[:, 0], side[:, 0]
    return states[:, 0], np.maximum(index, 0), side.astype(float)


class PlayOperatorBank:
    """Streaming bank of play operators with preallocated buffers (no allocation per step)."""

    def __init__(self, thresholds: Sequence[float], initial_state: Sequence[float]):
        self.thresholds = np.array(thresholds, dtype=float)
        self.state = np.array(initial_state, dtype=float)
        if self.state.shape != self.thresholds.shape:
            raise ValueError("initial state and thresholds differ in length")
        self._buf = np.empty_like(self.thresholds)

    def step(self, lower_drive: float, upper_drive: float) -> np.ndarray:
        """Advance one sample; returns the state array (a view, do not keep)."""
        buf = self._buf
        np.subtract(lower_drive, self.thresholds, out=buf)
        np.maximum(self.state, buf, out=self.state)
        np.add(upper_drive, self.thresholds, out=buf)
        np.minimum(self.state, buf, out=self.state)   # last: where the bounds cross, the upper wins
        return self.state

    def run(self, lower_drive: np.ndarray, upper_drive: np.ndarray, weights: Optional[np.ndarray] = None):
        """Batch form over a record; advances the bank's state like repeated ``step``."""
        out, final = play_batch(lower_drive, upper_drive, self.thresholds, self.state, weights)
        self.state[:] = final
        return out


# --------------------------------------------------------------------------- GPIM
@dataclass(frozen=True)
class GPIM:
    """Free-form generalized PI model: ``y = sum_j p_j * F_{r_j}[gamma(v)] + offset_um``.

    thresholds: r_j (input-envelope units, i.e. V after gamma), strictly increasing, r_0 = 0.
    weights: p_j [um per envelope unit].
    a0, a1: ascending envelope gamma_asc(v) = a0*v + a1 (v in V).
    b0, b1, b2: descending envelope gamma_desc(v) = b0*v + b1 + b2*v**2 (b2 optional); None means the same
        as ascending (the paper's choice).
    offset_um: constant output offset [um].
    """

    thresholds: np.ndarray
    weights: np.ndarray
    a0: float = 1.0
    a1: float = 0.0
    offset_um: float = 0.0
    b0: Optional[float] = None
    b1: Optional[float] = None
    b2: float = 0.0

    def __post_init__(self):
        r = np.array(self.thresholds, dtype=float).reshape(-1)
        p = np.array(self.weights, dtype=float).reshape(-1)
        r.setflags(write=False)
        p.setflags(write=False)
        object.__setattr__(self, "thresholds", r)
        object.__setattr__(self, "weights", p)
        problems = self.problems()
        if problems:
            raise ValueError("invalid GPIM: " + "; ".join(problems))

    # -- validation
    def problems(self) -> list[str]:
        """Reasons this model cannot be evaluated (empty when fine)."""
        out = []
        r, p = self.thresholds, self.weights
        if r.size == 0:
            out.append("no operators")
        if r.shape != p.shape:
            out.append(f"{r.size} thresholds but {p.size} weights")
        scalars = [self.a0, self.a1, self.offset_um, self.b2] + [x for x in (self.b0, self.b1) if x is not None]
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(p)) and np.all(np.isfinite(scalars))):
            out.append("non-finite value")
        elif r.size:
            if r[0] < 0 or np.any(np.diff(r) <= 0):
                out.append("thresholds must be >= 0 and strictly increasing")
            if self.a0 <= 0 or (self.b0 is not None and self.b0 <= 0):
                out.append("envelope slope a0 (and b0) must be > 0")
        if (self.b0 is None) != (self.b1 is None):
            out.append("give both b0 and b1 or neither")
        if self.b2 and self.b0 is None:
            out.append("b2 needs b0 and b1")
        return out

    @property
    def symmetric(self) -> bool:
        return self.b0 is None or (self.b0 == self.a0 and self.b1 == self.a1 and not self.b2)

    @property
    def n(self) -> int:
        return int(self.thresholds.size)

    # -- envelopes
    def ascending_envelope(self, v):
        return self.a0 * v + self.a1

    def descending_envelope(self, v):
        if self.b0 is None:
            return self.a0 * v + self.a1
        if self.b2:
            return self.b0 * v + self.b1 + self.b2 * v * v
        return self.b0 * v + self.b1

    def virgin_state(self, v0: float = CENTRE_VOLTAGE_V) -> np.ndarray:
        """Operator states consistent with input ``v0`` and no history (initial-loading state)."""
        x0 = 0.5 * (self.ascending_envelope(v0) + self.descending_envelope(v0))
        return np.clip(np.full(self.n, x0), self.ascending_envelope(v0) - self.thresholds,
                       self.descending_envelope(v0) + self.thresholds)

    def cycled_state(self, v: np.ndarray) -> np.ndarray:
        """Operator states at ``v[0]`` after the input swept the whole range of ``v`` before it: down to its
        minimum if ``v`` starts rising, having come from its maximum (and the mirror image if it starts
        falling).  The state of a record cut from running operation, where :meth:`virgin_state` is that
        of a valve started from rest."""
        v = np.asarray(v, dtype=float).reshape(-1)
        lo, hi = float(np.min(v)), float(np.max(v))
        moves = np.diff(v)
        rising = bool(moves[np.flatnonzero(moves)[0]] > 0) if np.any(moves) else True
        return self.state_after([hi, lo, v[0]] if rising else [lo, hi, v[0]])

    def state_after(self, path_v) -> np.ndarray:
        """Operator states after the input went through the voltages ``path_v`` [V] in order, from rest at the
        first (straight lines between them: only the turning points matter)."""
        path = np.asarray(path_v, dtype=float).reshape(-1)
        lower = self.ascending_envelope(path)
        upper = lower if self.symmetric else self.descending_envelope(path)
        states, _ = play_batch(lower, upper, self.thresholds, self.virgin_state(float(path[0])))
        return states[-1].copy()

    def output_from_state(self, state: np.ndarray) -> float:
        return float(self.weights @ state + self.offset_um)

    # -- evaluation
    def run(self, v: np.ndarray, state: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
        """Batch evaluation over input voltages ``v`` [V]; returns (y_um, final_state)."""
        v = np.asarray(v, dtype=float)
        z0 = self.virgin_state(float(v[0]) if v.size else CENTRE_VOLTAGE_V) if state is None else np.asarray(state, float)
        lower = self.ascending_envelope(v)
        upper = lower if self.symmetric else self.descending_envelope(v)
        y, final = play_batch(lower, upper, self.thresholds, z0, self.weights)
        return y + self.offset_um, final

    def stream(self, state: Optional[np.ndarray] = None, v0: float = CENTRE_VOLTAGE_V) -> "GPIMStream":
        return GPIMStream(self, self.virgin_state(v0) if state is None else state)

    def retarget_state(self, state: np.ndarray, other: "GPIM", v_now: float, widening_v: float = 0.0) -> np.ndarray:
        """Map operator states of this model onto ``other``'s thresholds, keeping the loop memory.

        The state of a play bank is a curve z(r) (1-Lipschitz in r); it is interpolated at the new
        thresholds and clamped to be consistent with the present input ``v_now`` (and the thresholds'
        present rate widening ``widening_v`` [V], see ``rate_dependence``).
        """
        z_new = np.interp(other.thresholds, self.thresholds, np.asarray(state, float))
        r = other.thresholds + widening_v
        lo = other.ascending_envelope(v_now) - r
        hi = other.descending_envelope(v_now) + r
        return np.minimum(np.maximum(z_new, lo), hi)

    def major_loop(self, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V, points: int = 2001):
        """Ascending then descending branch after a full cycle; returns (v, y_up, y_down)."""
        v_up = np.linspace(v_min, v_max, points)
        cycle = np.concatenate((v_up[::-1], v_up[1:], v_up[::-1][1:]))  # max->min->max->min
        y, _ = self.run(cycle, self.virgin_state(v_max))
        y_up = y[points - 1: 2 * points - 1]
        y_down = y[2 * points - 2:][::-1]
        return v_up, y_up, y_down

    def output_range(self, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V,
                     points: int = OUTPUT_RANGE_POINTS) -> tuple[float, float]:
        """(lowest, highest) output [um] of the major loop over inputs ``v_min..v_max`` [V]."""
        _, up, down = self.major_loop(v_min, v_max, points)
        return float(min(up.min(), down.min())), float(max(up.max(), down.max()))

    def descending_inverse(self, x):
        """The input [V] at which the descending envelope b0 v + b1 + b2 v^2 (a symmetric model's: the ascending
        one) reaches ``x`` (its rising branch; scalar or array)."""
        b0, b1 = (self.a0, self.a1) if self.b0 is None else (self.b0, self.b1)
        d = (x if isinstance(x, float) else np.asarray(x, float)) - b1   # a float stays one (per-step use)
        if not self.b2:
            return d / b0
        root = np.sqrt(np.maximum(b0 * b0 + 4.0 * self.b2 * d, 0.0))
        return 2.0 * d / (b0 + root)


class GPIMStream:
    """Per-sample GPIM evaluation with state (allocation-free ``step``)."""

    def __init__(self, model: GPIM, state: np.ndarray):
        self.model = model
        self.bank = PlayOperatorBank(model.thresholds, state)
        self._weights = model.weights
        self._offset = model.offset_um

    def step(self, v: float) -> float:
        m = self.model
        z = self.bank.step(m.a0 * v + m.a1, m.descending_envelope(v))
        return float(self._weights @ z) + self._offset

    def run(self, v: np.ndarray) -> np.ndarray:
        m = self.model
        lower = m.ascending_envelope(np.asarray(v, float))
        upper = lower if m.symmetric else m.descending_envelope(np.asarray(v, float))
        return self.bank.run(lower, upper, self._weights) + self._offset

    @property
    def state(self) -> np.ndarray:
        return self.bank.state


@dataclass(frozen=True)
class GPIMParams:
    """The paper's 5-parameter GPIM: r_j = alpha*j, p_j = rho*exp(-tau*r_j), gamma = a0*v + a1.

    Input V, output um.  The default ``offset_um`` centres the 0..10 V major loop on 0 um for the
    paper's values (the test suite recomputes it).
    Optional ``b0, b1`` give a separate descending envelope (asymmetric loops).
    """

    a0: float = 0.9647
    a1: float = 0.1014
    alpha: float = 0.4193
    rho: float = 5.8387
    tau: float = 1.0302
    n: int = 15
    offset_um: float = -81.8864  # centres the 0..10 V major loop on 0 um (see README)
    b0: Optional[float] = None
    b1: Optional[float] = None

    def model(self) -> GPIM:
        if not (isinstance(self.n, (int, np.integer)) and self.n >= 1):
            raise ValueError(f"n must be a positive integer, got {self.n!r}")
        if not (np.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"alpha must be > 0, got {self.alpha}")
        r = self.alpha * np.arange(self.n)
        return GPIM(r, self.rho * np.exp(-self.tau * r), self.a0, self.a1, self.offset_um, self.b0, self.b1)


GPIM_PARAMS_KEYS = ("a0", "a1", "alpha", "rho", "tau", "n", "offset_um")
"""``GPIMParams``' fields of the paper's symmetric form (without the descending envelope's b0, b1)."""


PAPER_GPIM = GPIMParams()


# --------------------------------------------------------------------------- inverse
ENVELOPE_CHECK_POINTS = 401   # where an asymmetric model's envelopes are compared over the drive range


def inverse_problems(model: GPIM, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V) -> list[str]:
    """Reasons no exact inverse exists for ``model`` on inputs ``v_min..v_max`` [V] (empty when invertible,
    see :func:`inverse_gpim`).  An asymmetric model needs a rising descending envelope and nonnegative
    weights (its output then rises with the input from any state)."""
    out = list(model.problems())
    if out:
        return out
    r, p = model.thresholds, model.weights
    if not model.symmetric:
        v = np.linspace(v_min, v_max, ENVELOPE_CHECK_POINTS)
        slope = model.b0 + 2.0 * model.b2 * v
        if np.any(slope <= 0):
            out.append(f"descending envelope not rising at {v[np.argmax(slope <= 0)]:.3g} V")
        if dead_band_problems(model, v_min, v_max) and np.any(p < 0):
            out.append(f"envelopes that cross need nonnegative weights (weight {int(np.argmin(p))} is "
                       f"{p.min():.6g})")
    if r[0] != 0:
        out.append(f"first threshold must be 0 (got {r[0]})")
    if p[0] <= 0:
        out.append(f"first weight must be > 0 (got {p[0]:.6g})")
    partial = np.cumsum(p)
    bad = np.flatnonzero(partial <= 0)
    if bad.size:
        out.append(f"partial sum of weights p_0..p_{bad[0]} = {partial[bad[0]]:.6g} is not > 0")
    return out


def dead_band_problems(model: GPIM, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V) -> list[str]:
    """Where an asymmetric model's descending envelope falls below the ascending one on ``v_min..v_max``
    (empty: a dead band throughout, the case :class:`InverseGPIM` inverts in closed form)."""
    if model.symmetric:
        return []
    v = np.linspace(v_min, v_max, ENVELOPE_CHECK_POINTS)
    gap = model.descending_envelope(v) - model.ascending_envelope(v)
    if not np.any(gap < 0):
        return []
    where = v[gap < 0]
    return [f"descending envelope below the ascending one from {where[0]:.3g} to {where[-1]:.3g} V "
            f"(by up to {-gap.min():.3g}): no closed-form inverse (it needs the loop's dead band, "
            "descending >= ascending; inverse_gpim solves each step instead)"]


def inverse_gpim(model: GPIM, forward_state: Optional[np.ndarray] = None, v0: float = CENTRE_VOLTAGE_V,
                 v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V):
    """The exact inverse of ``model``: :class:`InverseGPIM` (closed form) for a symmetric model or one with a
    dead band, :class:`MonotoneInverseGPIM` (each step solved) for envelopes that cross on ``v_min..v_max``."""
    problems = inverse_problems(model, v_min, v_max)
    if problems:
        raise NotInvertibleError("; ".join(problems))
    if dead_band_problems(model, v_min, v_max):
        return MonotoneInverseGPIM(model, forward_state, v0, v_min, v_max)
    return InverseGPIM(model, forward_state, v0)


class InverseGPIM:
    """Exact inverse of a GPIM (Krejci-Kuhnen form), streaming and batch.

    ``x = sum_j ph_j * F_{rh_j}[y - offset]`` with ``rh_j = sum_{i<=j} p_i (r_j - r_i)``, ``ph_0 = 1/p_0``,
    ``ph_j = -p_j / (P_j P_{j-1})``, ``P_j = p_0 + ... + p_j``; symmetric: ``v = gamma^{-1}(x)``.

    Asymmetric envelopes (ascending L, descending U >= L on the drive range): the bank of two-drive play
    operators with r_0 = 0 is the symmetric PI driven by ``x = z_0``, which follows the dead-band operator
    ``x <- min(max(x, L(v)), U(v))``.  So ``x`` comes from the same inverse PI, and ``v = L^{-1}(x)`` while
    ``x`` rises, ``U^{-1}(x)`` while it falls, the last ``v`` while it holds (Al Janaideh, Rakheja and Su's
    inverse of the generalized PI model with invertible envelopes).

    The operator states are kept consistent with the forward model's states
    (``zh_j = P_j z_j + sum_{i>j} p_i z_i``), so forward(inverse(y)) == y.
    """

    def __init__(self, model: GPIM, forward_state: Optional[np.ndarray] = None, v0: float = CENTRE_VOLTAGE_V):
        problems = inverse_problems(model) + dead_band_problems(model)
        if problems:
            raise NotInvertibleError("; ".join(problems))
        self.model = model
        r, p = model.thresholds, model.weights
        partial = np.cumsum(p)
        self._partial = partial
        self.thresholds = np.array([np.sum(p[: j + 1] * (r[j] - r[: j + 1])) for j in range(r.size)])
        ph = np.empty_like(p)
        ph[0] = 1.0 / p[0]
        ph[1:] = -p[1:] / (partial[1:] * partial[:-1])
        self.weights = ph
        z = model.virgin_state(v0) if forward_state is None else np.asarray(forward_state, float)
        self.bank = PlayOperatorBank(self.thresholds, self.state_from_forward(z))
        self._a0, self._a1 = model.a0, model.a1
        self._offset = model.offset_um
        self._asymmetric = not model.symmetric
        self._x_last, self._v_last = float(z[0]), float(v0)  # the dead band's memory (asymmetric models)
        self._settle_in_band()

    # -- the dead band of an asymmetric model
    def _settle_in_band(self) -> None:
        """Keep the remembered input inside the band of inputs that hold ``x`` (after a state change)."""
        if self._asymmetric:
            lo = float(self.model.descending_inverse(self._x_last))
            hi = (self._x_last - self._a1) / self._a0
            self._v_last = min(max(self._v_last, lo), hi)

    def _input_for(self, x: float) -> float:
        if not self._asymmetric:
            return (x - self._a1) / self._a0
        if x > self._x_last:
            v = (x - self._a1) / self._a0
        elif x < self._x_last:
            v = float(self.model.descending_inverse(x))
        else:
            v = self._v_last
        self._x_last, self._v_last = x, v
        return v

    # -- state mapping
    def state_from_forward(self, z: np.ndarray) -> np.ndarray:
        p = self.model.weights
        tail = np.concatenate((np.cumsum(p[::-1] * z[::-1])[::-1][1:], [0.0]))  # sum_{i>j} p_i z_i
        return self._partial * z + tail

    def forward_state(self) -> np.ndarray:
        """Forward-model operator states equivalent to the present inverse state."""
        zh = self.bank.state
        p = self.model.weights
        n = zh.size
        z = np.empty(n)
        tail = 0.0
        for j in range(n - 1, -1, -1):
            z[j] = (zh[j] - tail) / self._partial[j]
            tail += p[j] * z[j]
        return z

    def set_forward_state(self, z: np.ndarray, v_now: Optional[float] = None) -> None:
        """Take over forward-model operator states ``z`` (and the input ``v_now`` [V] they were reached at)."""
        z = np.asarray(z, float)
        self.bank.state[:] = self.state_from_forward(z)
        self._x_last = float(z[0])
        if v_now is not None:
            self._v_last = float(v_now)
        self._settle_in_band()

    def reset(self, v0: float = CENTRE_VOLTAGE_V) -> None:
        """Virgin state at input ``v0`` (the paper's synchronised start)."""
        self.set_forward_state(self.model.virgin_state(v0), v0)

    def with_model(self, model: GPIM, v_now: float) -> "InverseGPIM":
        """A new inverse for ``model``, with the loop memory carried over (raises if not invertible)."""
        z = self.model.retarget_state(self.forward_state(), model, v_now)
        return inverse_gpim(model, z, v_now)

    # -- evaluation
    def step(self, y_um: float) -> float:
        """Voltage [V] that makes the forward model output ``y_um``; advances the state."""
        zh = self.bank.step(y_um - self._offset, y_um - self._offset)
        return self._input_for(float(self.weights @ zh))

    def peek(self, y_um: float) -> float:
        """What :meth:`step` would return for ``y_um`` [um], without advancing the state (allocates: for
        occasional use such as a model swap, not per sample)."""
        saved = self.bank.state.copy()
        try:
            return self.step(y_um)
        finally:
            self.bank.state[:] = saved

    def run(self, y_um: np.ndarray) -> np.ndarray:
        """Batch form of :meth:`step` over outputs ``y_um`` [um]; voltages [V]."""
        y = np.asarray(y_um, float) - self._offset
        x = self.bank.run(y, y, self.weights)
        if not self._asymmetric:
            return (x - self._a1) / self._a0
        if x.size == 0:
            return x
        dx = np.diff(np.concatenate(([self._x_last], x)))
        v = np.where(dx > 0, (x - self._a1) / self._a0, self.model.descending_inverse(x))
        held = dx == 0
        if held.any():  # a held x keeps the last input: carry it forward from the last change
            last = np.maximum.accumulate(np.where(held, -1, np.arange(x.size)))
            v = np.where(last >= 0, v[np.maximum(last, 0)], self._v_last)
        self._x_last, self._v_last = float(x[-1]), float(v[-1])
        return v

    def peek_forward(self, v: float) -> float:
        """Forward-model output [um] for input ``v`` from the present state, without advancing it."""
        z = self.forward_state()
        m = self.model
        lower, upper = m.ascending_envelope(v), m.descending_envelope(v)
        z = np.minimum(np.maximum(z, lower - m.thresholds), upper + m.thresholds)
        return m.output_from_state(z)


class MonotoneInverseGPIM:
    """Exact inverse of a GPIM whose envelopes rise but may cross, one step at a time.

    From a given state every operator's next output ``min(max(z_j, L(v) - r_j), U(v) + r_j)`` (the upper
    bound wins where the bounds cross, as in :class:`PlayOperatorBank`) rises with
    the input v, and so does the model's output (nonnegative weights; or, where the bounds do not cross,
    positive partial sums of the weights, since the operators that move are then a prefix of the bank).  Between the inputs where an operator
    starts to follow its lower bound (L(v) = z_j + r_j), its upper bound (U(v) = z_j - r_j) or where its
    bounds cross (L(v) - U(v) = 2 r_j), each operator is held or follows one envelope, so the output is
    ``C + A L(v) + B U(v)``: linear (or quadratic, for a curved U) in v.  Each step finds the piece from
    the last input towards the demand where the output reaches it, and solves there: forward(inverse(y)) = y
    to rounding, inputs limited to ``v_min..v_max`` [V] (the demand is clamped to the reachable output).

    Same interface as :class:`InverseGPIM`; the state is the forward model's (``forward_state``).  The usual
    step (on one envelope, no operator's bounds crossing on the way) is solved in closed form in a few
    microseconds; the general solve walks the breakpoints in floats, a few times that (``bench/core_speed.py``).
    """

    def __init__(self, model: GPIM, forward_state: Optional[np.ndarray] = None, v0: float = CENTRE_VOLTAGE_V,
                 v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V):
        problems = inverse_problems(model, v_min, v_max)
        if problems:
            raise NotInvertibleError("; ".join(problems))
        self.model = model
        self.v_min, self.v_max = float(v_min), float(v_max)
        symmetric = model.b0 is None
        self._b0 = float(model.a0 if symmetric else model.b0)
        self._b1 = float(model.a1 if symmetric else model.b1)
        self._b2 = float(model.b2)
        self._dead_band = not dead_band_problems(model, v_min, v_max)   # the bounds never cross (r_j >= 0)
        self._one_envelope = model.symmetric
        self._p_list, self._base_list = model.weights.tolist(), model.thresholds.tolist()
        self._shift = 0.0              # every threshold widened by this [V] (rate_dependence sets it)
        self._consistent = False       # the state is what the last step left at _v_last (output _y_now)
        self._y_now = 0.0
        self._moving: Optional[tuple[int, list]] = None   # the closed form's last solve: (operators moving, states)
        self.set_forward_state(model.virgin_state(v0) if forward_state is None else forward_state, v0)

    # -- state: the operators as floats (a bank is a few dozen; numpy's per-call cost would be most of a step)
    @property
    def _z(self) -> np.ndarray:
        """The operators' states [V] (n,), a new array."""
        return np.array(self._state)

    def forward_state(self) -> np.ndarray:
        return self._z

    def set_forward_state(self, z: np.ndarray, v_now: Optional[float] = None) -> None:
        z = np.array(z, dtype=float)
        self._state = z.tolist()
        if v_now is not None:
            self._v_last = float(v_now)
        # the operators in order (steps keep it): z_j + r_j rises and z_j - r_j falls with j
        r = self.model.thresholds
        up, down = z + r, z - r
        self._ordered = bool(np.all(up[1:] >= up[:-1] - ORDER_TOLERANCE_V)
                             and np.all(down[1:] <= down[:-1] + ORDER_TOLERANCE_V))
        self._consistent = False

    def reset(self, v0: float = CENTRE_VOLTAGE_V) -> None:
        self.set_forward_state(self.model.virgin_state(v0), v0)

    def with_model(self, model: GPIM, v_now: float):
        z = self.model.retarget_state(self._z, model, v_now)
        return inverse_gpim(model, z, v_now, self.v_min, self.v_max)

    # -- the forward model from the present state
    def peek_forward(self, v: float) -> float:
        return self._output_at(float(v))

    def _solve_on_one_envelope(self, y: float, rising: bool, z: list, now: float) -> Optional[float]:
        """The usual step, in closed form, from a state within its bounds at the last input with the operators
        in order (``z_j + r_j`` rising and ``z_j - r_j`` falling with j, as every step keeps them): falling, each
        operator's next state is ``min(z_j, U(v) + r_j)`` (a crossed one sits on its upper bound and follows it);
        rising with bounds that cannot cross, ``max(z_j, L(v) - r_j)``.  The output is then piecewise linear
        in L(v) (U(v)) with breakpoints ``z_j + r_j`` (``z_j - r_j``) in the operators' order; a demand a
        step away passes a few of them, so a plain loop from the first finds the piece and solves it.  None
        when the step is not of this kind (the general solve then takes it).  ``state``: the operators at the
        last input under the present thresholds (a list, which the step updates), ``now``: the output there [um];
        sets ``_moving`` (how many operators follow, that list)."""
        # one envelope (L = U): an operator whose threshold the rate narrowed below 0 has crossed bounds for good
        # and follows U(v) + r_j = L(v) + r_j; with two, any crossing on the way up is the general solve's
        crossed_for_good = rising and self._one_envelope
        p, base, w = self._p_list, self._base_list, self._shift
        off = self.model.offset_um
        sign = 1.0 if rising else -1.0    # the breakpoints are z_j + sign r_j
        held = now - off                  # sum_j p_j z_j over the operators held
        following = before = 0.0          # sum p_j and sum p_j r_j over the operators that follow
        moving = len(z)                   # the operators that follow: a prefix (the thresholds rise with j)
        for i in range(len(z)):
            r_i = base[i] + w
            if crossed_for_good and r_i < 0.0:    # follows from the start, on its upper bound L(v) + r_i
                p_i = p[i]
                following += p_i
                before -= p_i * r_i
                held -= p_i * z[i]
                continue
            if sign * (off + held + following * (z[i] + sign * r_i) - sign * before - y) >= 0.0:
                moving = i
                break                     # the demand is reached before this operator starts to follow
            p_i = p[i]
            following += p_i
            before += p_i * r_i
            held -= p_i * z[i]
        if following <= 0.0:
            return None
        drive = (y - off - held + sign * before) / following     # L(v) rising, U(v) falling
        if rising:
            v = min((drive - self.model.a1) / self.model.a0, self.v_max)
            if not crossed_for_good and self._gap_range(self._v_last, max(v, self._v_last))[1] > \
                    2.0 * (base[0] + w):
                return None   # some operator's bounds cross on the way up to v: the general solve's
        else:
            v = max(float(self.model.descending_inverse(drive)), self.v_min)
        self._moving = (moving, z)
        return v

    def _gap_range(self, a: float, b: float) -> tuple[float, float]:
        """(min, max) of L(u) - U(u) over u in a..b [V] (linear or quadratic in u: the ends and the vertex)."""
        m = self.model
        q2, q1, q0 = -self._b2, m.a0 - self._b0, m.a1 - self._b1
        points = [a, b]
        if q2 and a < -q1 / (2.0 * q2) < b:
            points.append(-q1 / (2.0 * q2))
        gaps = [q2 * u * u + q1 * u + q0 for u in points]
        return min(gaps), max(gaps)

    def _state_at_last_input(self) -> tuple[list, float, bool, float]:
        """The operators at the last input under the present thresholds, after the thresholds changed (rate
        dependence) or the state was set: (states, output there [um], whether one lies above its upper bound, the
        largest 2 r_j of an operator below its lower bound (-inf: none)).  Each state clamped to its bounds there,
        the upper bound last (it wins where they cross).  One pass over the operators in floats: a bank is a few
        dozen operators, where numpy's per-call cost is most of a step."""
        m, v_last, w = self.model, self._v_last, self._shift
        low, high = float(m.ascending_envelope(v_last)), float(m.descending_envelope(v_last))
        state, f_now = [], m.offset_um
        above, below_r2 = False, -math.inf
        for z_j, base_j, p_j in zip(self._state, self._base_list, self._p_list):
            r_j = base_j + w
            lo, hi = low - r_j, high + r_j
            s_j = lo if z_j < lo else z_j
            if s_j > hi:
                s_j = hi
            state.append(s_j)
            f_now += p_j * s_j
            if z_j > hi:
                above = True
            elif z_j < lo and 2.0 * r_j > below_r2:
                below_r2 = 2.0 * r_j
        return state, f_now, above, below_r2

    def _solve(self, y: float) -> float:
        self._moving = None
        v_last = self._v_last
        if self._consistent:
            state, f_now, usual = self._state, self._y_now, self._ordered
        else:  # the thresholds changed since the last step (rate dependence) or the state was set
            state, f_now, above, below_r2 = self._state_at_last_input()
        if abs(y - f_now) <= HOLD_TOLERANCE_UM:
            return v_last
        rising = y > f_now
        # an operator pushed against the motion by the new thresholds follows its other bound for a while: not
        # the usual step.  Rising, one above its upper bound follows U + r up (the upper bound is the last clamp);
        # falling, one below its lower bound follows L - r down, unless its bounds cross all the way down (then
        # the upper wins, as it does for one pushed along the motion)
        if not self._consistent:
            usual = self._ordered and not (
                above if rising else below_r2 >= self._gap_range(min(self.v_min, v_last), v_last)[0])
        if usual:
            v = self._solve_on_one_envelope(y, rising, state, f_now)
            if v is not None:
                return v
        return self._solve_piecewise(y, rising)

    def _solve_piecewise(self, y: float, rising: bool) -> float:
        """The general solve, from any state: the inputs where an operator starts to follow an envelope or its
        bounds cross between the last input and the end of the range in the motion's
        direction, walked from the last input until the output reaches ``y`` [um]; then solved on that piece,
        where each operator is held or follows one bound (linear, or quadratic for a curved U).  In floats: a bank
        is a few dozen operators and the demand is usually a breakpoint or two away."""
        m, w, v_last = self.model, self._shift, self._v_last
        a0, a1, b0, b1, b2 = m.a0, m.a1, self._b0, self._b1, self._b2
        z, base, p = self._state, self._base_list, self._p_list
        start, end = (v_last, self.v_max) if rising else (v_last, self.v_min)
        low, high = min(start, end), max(start, end)
        q1 = a0 - b0
        points = {start, end}
        for z_j, base_j in zip(z, base):
            r = base_j + w
            q0 = a1 - b1 - 2.0 * r                       # L(v) - U(v) = 2 r: -b2 v^2 + q1 v + q0 = 0
            if b2:
                disc = math.sqrt(max(q1 * q1 + 4.0 * b2 * q0, 0.0))
                crossings = ((q1 + disc) / (2.0 * b2), (q1 - disc) / (2.0 * b2))
            else:
                crossings = (-q0 / q1,) if q1 else ()
            for u in ((z_j + r - a1) / a0, float(m.descending_inverse(z_j - r)), *crossings):
                if low < u < high:                       # L(v) = z + r, U(v) = z - r, or the crossing
                    points.add(u)
        previous = None
        for u in sorted(points, reverse=not rising):
            f = self._output_at(u)
            if (f >= y) if rising else (f <= y):
                break
            previous = u
        else:
            return u                     # beyond the reachable output: the end of the input range
        if f == y or previous is None:
            return u
        a, b_ = previous, u
        mid = 0.5 * (a + b_)
        lower_env, upper_env = a0 * mid + a1, float(m.descending_envelope(mid))
        A = B = 0.0
        C = m.offset_um
        for z_j, base_j, p_j in zip(z, base, p):
            r = base_j + w
            lo, hi = lower_env - r, upper_env + r
            if hi <= (lo if lo > z_j else z_j):          # follows U + r (the upper bound wins where they cross)
                B += p_j
                C += p_j * r
            elif lo >= z_j:                              # follows L - r
                A += p_j
                C -= p_j * r
            else:
                C += p_j * z_j
        q2, q1, q0 = B * b2, A * a0 + B * b0, C + A * a1 + B * b1 - y
        if q2:
            disc = math.sqrt(max(q1 * q1 - 4.0 * q2 * q0, 0.0))
            roots = ((-q1 + disc) / (2.0 * q2), (-q1 - disc) / (2.0 * q2))
            v = min(roots, key=lambda x: abs(x - mid))
        else:
            v = -q0 / q1 if q1 else b_
        return min(max(v, min(a, b_)), max(a, b_))

    def _output_at(self, v: float) -> float:
        """The model's output [um] at input ``v`` [V] from the state at the last input (floats)."""
        lower_env, upper_env = self.model.a0 * v + self.model.a1, float(self.model.descending_envelope(v))
        w, f = self._shift, self.model.offset_um
        for z_j, base_j, p_j in zip(self._state, self._base_list, self._p_list):
            r = base_j + w
            s_j = lower_env - r if lower_env - r > z_j else z_j
            if s_j > upper_env + r:
                s_j = upper_env + r
            f += p_j * s_j
        return f

    # -- evaluation
    def step(self, y_um: float) -> float:
        """Voltage [V] that makes the forward model output ``y_um``; advances the state."""
        v = self._solve(float(y_um))
        m, w, base = self.model, self._shift, self._base_list
        high, low = float(m.descending_envelope(v)), float(m.ascending_envelope(v))
        # the closed form's step moves only its prefix of operators; after the general solve or a hold, any may
        moving, state = self._moving if self._moving is not None else (len(self._state), self._state[:])
        for j in range(moving):
            r_j = base[j] + w
            z_j = state[j]
            if z_j < low - r_j:
                z_j = low - r_j
            if z_j > high + r_j:   # after the lower clamp: the upper bound wins where they cross
                z_j = high + r_j
            state[j] = z_j
        self._state = state
        self._v_last = v
        self._y_now = sum(map(operator.mul, self._p_list, state)) + m.offset_um
        self._consistent = True
        return v

    def peek(self, y_um: float) -> float:
        return self._solve(float(y_um))

    def run(self, y_um: np.ndarray) -> np.ndarray:
        return np.array([self.step(y) for y in np.asarray(y_um, float)])


def turning_points(v: np.ndarray) -> tuple[float, ...]:
    """The first value and the turning points [V] of an input path, ending with its last value: what
    ``GPIM.state_after`` needs to give the same states as for the whole path (the operators remember
    only where the input turned)."""
    v = np.asarray(v, float).reshape(-1)
    keep = [float(v[0])]
    moves = np.diff(v)
    idx = np.flatnonzero(moves)
    if idx.size:
        sign = np.sign(moves[idx])
        ends = np.concatenate((idx[np.flatnonzero(sign[1:] != sign[:-1])], [idx[-1]])) + 1  # each run's end
        keep += [float(v[k]) for k in ends]
    return tuple(keep)


def dominant_turning_points(path_v) -> tuple[float, ...]:
    """The first value and the turning points [V] of a path that still set the operators' state, ending with
    its last value: a pair of turning points nested in the swing before it is wiped out once the path goes
    beyond the first of them (the wiping-out property of play operators, whatever their envelopes: the
    operators the pair moved are all moved again), so ``GPIM.state_after`` gives the same
    states for this as for the whole path while the list stays as short as the nested extrema are few
    (bounded for a valve in operation, where every sample would otherwise turn)."""
    out: list[float] = []
    for x in turning_points(np.asarray(path_v, float)) if len(path_v) else ():
        if out and x == out[-1]:
            continue
        out.append(float(x))
        if len(out) >= 3 and (out[-3] - out[-2]) * (out[-2] - out[-1]) >= 0:
            del out[-2]                      # not a turning point: the path went on the same way
        # a move beyond the extremum two back wipes it and the one between out, where that pair lies within
        # the swing before it (nested: always but right after the start, which stays)
        while len(out) >= 4 and abs(out[-1] - out[-2]) >= abs(out[-3] - out[-2]) \
                and abs(out[-2] - out[-3]) <= abs(out[-4] - out[-3]):
            del out[-3:-1]
    return tuple(out)
