"""numba kernels of ``hysteresis`` (imported on first use): ``play_batch``'s recursion itself,

    z_j = min(max(z_j, L - r_j s), U_j)   with   U_j = max(U + r_j s, L - r_j s)   (L - r_j s + 2 r_j s when symmetric),

sample by sample, with the bounds formed by the same operations as the composed-clamp path's (so the same bits: min
and max do not round); and ``last_contact``'s scan."""
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
            if hi < lo:
                hi = lo
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
