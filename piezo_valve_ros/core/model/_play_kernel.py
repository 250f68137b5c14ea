"""numba kernel of ``hysteresis.play_batch`` (imported on first use): the play operators' recursion itself,

    z_j = min(max(z_j, L - r_j s), U_j)   with   U_j = max(U + r_j s, L - r_j s)   (L - r_j s + 2 r_j s when symmetric),

sample by sample, with the bounds formed by the same operations as the composed-clamp path's (so the same bits: min
and max do not round)."""
from __future__ import annotations

import numba


@numba.njit(nogil=True, cache=True)
def play_rows(lower, upper, r, scale, symmetric, z, out):
    """Operators of thresholds r (n,) on drives lower, upper (rows,), thresholds times scale (rows,) where scale
    has rows (else unscaled); z (n,) states in and out; out (rows, n) the states."""
    n = r.size
    scaled = scale.size > 0
    for t in range(lower.size):
        low, up = lower[t], upper[t]
        for j in range(n):
            rs = r[j] * scale[t] if scaled else r[j]
            lo = low - rs
            hi = lo + 2.0 * rs if symmetric else up + rs
            if hi < lo:
                hi = lo
            v = z[j]
            if v < lo:
                v = lo
            if v > hi:
                v = hi
            z[j] = v
            out[t, j] = v
