"""numba kernels of ``hysteresis`` (imported on first use): ``play_batch``'s recursion itself,

    z_j = min(max(z_j, L - r_j s), U + r_j s)   (U + r_j s: L - r_j s + 2 r_j s when symmetric; the upper bound wins
                                                 where the bounds cross),

sample by sample, with the bounds formed by the same operations as the composed-clamp path's (so the same bits: min
and max do not round); ``last_contact``'s scan; and ``contact_sensitivity``'s sums."""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(inline="always", cache=True)
def _bounds(low, up, rj, st, symmetric):
    """One operator's (lower, upper) clamp bounds at one sample as ``hysteresis._clamp_bounds`` forms them: drives
    low, up; threshold rj times the sample's scale st (1.0 where unscaled: the same product)."""
    rs = rj * st
    lo = low - rs
    return lo, (lo + 2.0 * rs if symmetric else up + rs)


@numba.njit(nogil=True, cache=True)
def play_rows(lower, upper, r, scale, symmetric, z, out):
    """Operators of thresholds r (n,) on drives lower, upper (rows,), thresholds times scale (rows,) where scale
    has rows (else unscaled); z (n,) states in and out; out (rows, n) the states."""
    n = r.size
    scaled = scale.size > 0
    for t in range(lower.size):
        low, up, st = lower[t], upper[t], scale[t] if scaled else 1.0
        for j in range(n):
            lo, hi = _bounds(low, up, r[j], st, symmetric)
            v = z[j]
            if v < lo:
                v = lo
            if v > hi:
                v = hi
            z[j] = v
            out[t, j] = v


@numba.njit(nogil=True, cache=True)
def last_contacts(states, lower, upper, r, scale, symmetric, drive, side_out, index_out):
    """``hysteresis.last_contact`` sample by sample: states (N, n); the bounds formed as ``_clamp_bounds`` forms them
    (no max of the two: a state on either counts); drive (N,) = lower + upper, whose last move sets the side where
    both bounds coincide; side_out (N, n) int8 and index_out (N, n) int32 written."""
    n_samples, n = states.shape
    scaled = scale.size > 0
    side = np.zeros(n, np.int8)
    index = np.full(n, -1, np.int32)
    last_move = 0.0
    for t in range(n_samples):
        if t > 0:
            move = drive[t] - drive[t - 1]
            if move != 0:
                last_move = move
        both_side = 1 if last_move < 0 else -1
        low, up, st = lower[t], upper[t], scale[t] if scaled else 1.0
        for j in range(n):
            lo, hi = _bounds(low, up, r[j], st, symmetric)
            z = states[t, j]
            on_lo = z == lo
            on_hi = z == hi
            if on_lo or on_hi:
                index[j] = t
                side[j] = both_side if (on_lo and on_hi) else (1 if on_hi else -1)
            side_out[t, j] = side[j]
            index_out[t, j] = index[j]


PAIRWISE_BLOCK = 128   # numpy's PW_BLOCKSIZE: its sums of up to this many contiguous numbers are one unrolled block


@numba.njit(inline="always", cache=True)
def _numpy_sum(a, n):
    """``a[:n].sum()`` as numpy adds up a contiguous row of n <= PAIRWISE_BLOCK numbers (its pairwise sum: below 8
    one by one from -0.0; else eight running sums, combined in pairs, then the rest one by one): the same bits."""
    if n < 8:
        res = -0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    m = n - n % 8
    i = 8
    while i < m:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res


@numba.njit(nogil=True, cache=True)
def contact_sums(side, index, weights, which, columns, out):
    """``hysteresis.contact_sensitivity`` row by row: side (N, n) int8 and index (N, n) int32 of the last contacts,
    weights (n,), which -1 (lower bounds), +1 (upper) or 0 (both, upper minus lower), columns (k, N); out (N, k)
    written.  Each term formed and each row summed as the numpy path forms and sums them (n <= PAIRWISE_BLOCK)."""
    n_samples, n = index.shape
    terms, weighted, at = np.empty(n), np.empty(n), np.empty(n, np.int64)
    for t in range(n_samples):
        for j in range(n):
            s = side[t, j]
            if which == 0:
                on = float(s)
            elif which < 0:
                on = 1.0 if s < 0 else 0.0
            else:
                on = 1.0 if s > 0 else 0.0
            weighted[j] = on * weights[j]
            at[j] = max(index[t, j], 0)   # before any contact: sample 0 (its side is 0)
        for k in range(columns.shape[0]):
            column = columns[k]
            for j in range(n):
                terms[j] = column[at[j]] * weighted[j]
            out[t, k] = _numpy_sum(terms, n)
