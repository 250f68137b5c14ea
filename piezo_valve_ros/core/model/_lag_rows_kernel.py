"""numba kernel of ``iir.creep_lag_rows`` (imported on first use): creep's design rows, each lag the recursion of
``_iir_kernels.first_order_bank`` (``y = z + 0 u``, a subnormal y flushed to zero, ``z = u b1 - y a1``), each
difference, sum and product the operation numpy's would do, in the same order, so the same bits as the rows built
from ``first_order_bank``, ``np.diff``, ``np.cumsum`` and numpy's products; without their temporary arrays.  Lags
run four, or a rising and a falling one, at a time along the record (independent recursions overlap)."""
from __future__ import annotations

import numba
import numpy as np

TINY = np.finfo(np.float64).tiny


@numba.njit(inline="always", cache=True)
def _lag(z, u, b1, a1):
    """One step of a first-order lag: (output, next state)."""
    y = z + 0.0 * u
    if -TINY < y < TINY:
        y = 0.0
    return y, u * b1 - y * a1


@numba.njit(nogil=True, cache=True)
def creep_rows(h, before, b1, a1, k, centre, half, rows):
    """h (N,) the model output, before its value at rest before the record; b1, a1 (n,) the lags' coefficients
    (1 - pole, -pole), the first k also the shaped ones'; rows (n + 2k, N) out: lag_j(h) - h, then for j < k the lag of
    the rising minus the lag of the falling cumulative change of the fastest lag (each minus its input), then
    row j times (h - centre) / half."""
    n, N = b1.size, h.size
    j = 0
    while j + 4 <= n:                      # the plain lags, four at a time
        c0, e0, c1, e1 = b1[j], a1[j], b1[j + 1], a1[j + 1]
        c2, e2, c3, e3 = b1[j + 2], a1[j + 2], b1[j + 3], a1[j + 3]
        z0 = z1 = z2 = z3 = before
        r0, r1, r2, r3 = rows[j], rows[j + 1], rows[j + 2], rows[j + 3]
        for i in range(N):
            u = h[i]
            y0, z0 = _lag(z0, u, c0, e0)
            y1, z1 = _lag(z1, u, c1, e1)
            y2, z2 = _lag(z2, u, c2, e2)
            y3, z3 = _lag(z3, u, c3, e3)
            r0[i] = y0 - u
            r1[i] = y1 - u
            r2[i] = y2 - u
            r3[i] = y3 - u
        j += 4
    while j < n:                           # the rest one at a time
        c0, e0 = b1[j], a1[j]
        z0 = before
        r0 = rows[j]
        for i in range(N):
            u = h[i]
            y0, z0 = _lag(z0, u, c0, e0)
            r0[i] = y0 - u
        j += 1
    if k == 0:
        return
    rising = np.empty(N)                   # the cumulative rising and falling changes of the fastest lag
    falling = np.empty(N)
    z = before
    previous = before
    for i in range(N):
        slow, z = _lag(z, h[i], b1[0], a1[0])
        d = slow - previous
        previous = slow
        up = np.maximum(d, 0.0)
        down = np.minimum(d, 0.0)
        if i == 0:
            rising[0], falling[0] = up, down
        else:
            rising[i] = rising[i - 1] + up
            falling[i] = falling[i - 1] + down
    for j in range(k):                     # each shaped lag: its rising and falling recursions side by side
        c0, e0 = b1[j], a1[j]
        zr, zf = rising[0], falling[0]
        shaped, level_row, plain = rows[n + j], rows[n + k + j], rows[j]
        for i in range(N):
            r, f = rising[i], falling[i]
            yr, zr = _lag(zr, r, c0, e0)
            yf, zf = _lag(zf, f, c0, e0)
            shaped[i] = (yr - r) - (yf - f)
            level_row[i] = plain[i] * ((h[i] - centre) / half)
