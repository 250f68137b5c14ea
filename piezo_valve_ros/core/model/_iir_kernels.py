"""numba kernels of ``iir`` (imported on first use): lfilter's transposed direct form II, operation by operation,

    y[n] = z0 + b0 x[n];  z_j = z_(j+1) + x[n] b_(j+1) - y[n] a_(j+1);  z_last = x[n] b_last - y[n] a_last,

four filters advanced together at each sample, their states and coefficients in registers (each output waits for
the one before it; four independent recursions overlap), then the rows left over one at a time.  One kernel per
filter length.  No fast-math: the operations and their order are lfilter's, so are the bits."""
from __future__ import annotations

import numba

# Rows advanced together: four recursions hide each one's latency, and their states and the coefficients still
# fit the registers (eight filters spill and are no faster).
UNROLL = 4


@numba.njit(nogil=True, cache=True)
def rows_2(b, a, x, z, out):
    """First order on each row of x (k, N); z (1, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, a1 = b[0], b[1], a[1]
    g = 0
    while g + UNROLL <= k:
        p0, p1, p2, p3 = z[0, g], z[0, g + 1], z[0, g + 2], z[0, g + 3]
        x0, x1, x2, x3 = x[g], x[g + 1], x[g + 2], x[g + 3]
        o0, o1, o2, o3 = out[g], out[g + 1], out[g + 2], out[g + 3]
        for n in range(n_samples):
            u = x0[n]; y = p0 + b0 * u; p0 = u * b1 - y * a1; o0[n] = y   # noqa: E702
            u = x1[n]; y = p1 + b0 * u; p1 = u * b1 - y * a1; o1[n] = y   # noqa: E702
            u = x2[n]; y = p2 + b0 * u; p2 = u * b1 - y * a1; o2[n] = y   # noqa: E702
            u = x3[n]; y = p3 + b0 * u; p3 = u * b1 - y * a1; o3[n] = y   # noqa: E702
        z[0, g], z[0, g + 1], z[0, g + 2], z[0, g + 3] = p0, p1, p2, p3
        g += UNROLL
    while g < k:
        p0 = z[0, g]
        x0, o0 = x[g], out[g]
        for n in range(n_samples):
            u = x0[n]; y = p0 + b0 * u; p0 = u * b1 - y * a1; o0[n] = y   # noqa: E702
        z[0, g] = p0
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_3(b, a, x, z, out):
    """Second order on each row of x (k, N); z (2, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, a1, a2 = b[0], b[1], b[2], a[1], a[2]
    g = 0
    while g + UNROLL <= k:
        p0, p1, p2, p3 = z[0, g], z[0, g + 1], z[0, g + 2], z[0, g + 3]
        q0, q1, q2, q3 = z[1, g], z[1, g + 1], z[1, g + 2], z[1, g + 3]
        x0, x1, x2, x3 = x[g], x[g + 1], x[g + 2], x[g + 3]
        o0, o1, o2, o3 = out[g], out[g + 1], out[g + 2], out[g + 3]
        for n in range(n_samples):
            u = x0[n]; y = p0 + b0 * u; p0 = q0 + u * b1 - y * a1; q0 = u * b2 - y * a2; o0[n] = y   # noqa: E702
            u = x1[n]; y = p1 + b0 * u; p1 = q1 + u * b1 - y * a1; q1 = u * b2 - y * a2; o1[n] = y   # noqa: E702
            u = x2[n]; y = p2 + b0 * u; p2 = q2 + u * b1 - y * a1; q2 = u * b2 - y * a2; o2[n] = y   # noqa: E702
            u = x3[n]; y = p3 + b0 * u; p3 = q3 + u * b1 - y * a1; q3 = u * b2 - y * a2; o3[n] = y   # noqa: E702
        z[0, g], z[0, g + 1], z[0, g + 2], z[0, g + 3] = p0, p1, p2, p3
        z[1, g], z[1, g + 1], z[1, g + 2], z[1, g + 3] = q0, q1, q2, q3
        g += UNROLL
    while g < k:
        p0, q0 = z[0, g], z[1, g]
        x0, o0 = x[g], out[g]
        for n in range(n_samples):
            u = x0[n]; y = p0 + b0 * u; p0 = q0 + u * b1 - y * a1; q0 = u * b2 - y * a2; o0[n] = y   # noqa: E702
        z[0, g], z[1, g] = p0, q0
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_4(b, a, x, z, out):
    """Third order on each row of x (k, N); z (3, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, b3, a1, a2, a3 = b[0], b[1], b[2], b[3], a[1], a[2], a[3]
    g = 0
    while g + UNROLL <= k:
        p0, p1, p2, p3 = z[0, g], z[0, g + 1], z[0, g + 2], z[0, g + 3]
        q0, q1, q2, q3 = z[1, g], z[1, g + 1], z[1, g + 2], z[1, g + 3]
        r0, r1, r2, r3 = z[2, g], z[2, g + 1], z[2, g + 2], z[2, g + 3]
        x0, x1, x2, x3 = x[g], x[g + 1], x[g + 2], x[g + 3]
        o0, o1, o2, o3 = out[g], out[g + 1], out[g + 2], out[g + 3]
        for n in range(n_samples):
            u = x0[n]; y = p0 + b0 * u; p0 = q0 + u * b1 - y * a1; q0 = r0 + u * b2 - y * a2   # noqa: E702
            r0 = u * b3 - y * a3; o0[n] = y   # noqa: E702
            u = x1[n]; y = p1 + b0 * u; p1 = q1 + u * b1 - y * a1; q1 = r1 + u * b2 - y * a2   # noqa: E702
            r1 = u * b3 - y * a3; o1[n] = y   # noqa: E702
            u = x2[n]; y = p2 + b0 * u; p2 = q2 + u * b1 - y * a1; q2 = r2 + u * b2 - y * a2   # noqa: E702
            r2 = u * b3 - y * a3; o2[n] = y   # noqa: E702
            u = x3[n]; y = p3 + b0 * u; p3 = q3 + u * b1 - y * a1; q3 = r3 + u * b2 - y * a2   # noqa: E702
            r3 = u * b3 - y * a3; o3[n] = y   # noqa: E702
        z[0, g], z[0, g + 1], z[0, g + 2], z[0, g + 3] = p0, p1, p2, p3
        z[1, g], z[1, g + 1], z[1, g + 2], z[1, g + 3] = q0, q1, q2, q3
        z[2, g], z[2, g + 1], z[2, g + 2], z[2, g + 3] = r0, r1, r2, r3
        g += UNROLL
    while g < k:
        p0, q0, r0 = z[0, g], z[1, g], z[2, g]
        x0, o0 = x[g], out[g]
        for n in range(n_samples):
            u = x0[n]; y = p0 + b0 * u; p0 = q0 + u * b1 - y * a1; q0 = r0 + u * b2 - y * a2   # noqa: E702
            r0 = u * b3 - y * a3; o0[n] = y   # noqa: E702
        z[0, g], z[1, g], z[2, g] = p0, q0, r0
        g += 1


RUN_ROWS = {2: rows_2, 3: rows_3, 4: rows_4}


@numba.njit(nogil=True, cache=True)
def first_order_bank(x, b0, b1, a1, z, out):
    """First-order filters (b0_i + b1_i z^-1) / (1 + a1_i z^-1), one per element of b0, b1, a1 (k,), on one input
    x (N,); z (k,) states in and out; out (k, N)."""
    k = b0.size
    g = 0
    while g + UNROLL <= k:
        c0, c1, c2, c3 = b0[g], b0[g + 1], b0[g + 2], b0[g + 3]
        d0, d1, d2, d3 = b1[g], b1[g + 1], b1[g + 2], b1[g + 3]
        e0, e1, e2, e3 = a1[g], a1[g + 1], a1[g + 2], a1[g + 3]
        p0, p1, p2, p3 = z[g], z[g + 1], z[g + 2], z[g + 3]
        o0, o1, o2, o3 = out[g], out[g + 1], out[g + 2], out[g + 3]
        for n in range(x.size):
            u = x[n]
            y = p0 + c0 * u; p0 = u * d0 - y * e0; o0[n] = y   # noqa: E702
            y = p1 + c1 * u; p1 = u * d1 - y * e1; o1[n] = y   # noqa: E702
            y = p2 + c2 * u; p2 = u * d2 - y * e2; o2[n] = y   # noqa: E702
            y = p3 + c3 * u; p3 = u * d3 - y * e3; o3[n] = y   # noqa: E702
        z[g], z[g + 1], z[g + 2], z[g + 3] = p0, p1, p2, p3
        g += UNROLL
    while g < k:
        c0, d0, e0, p0 = b0[g], b1[g], a1[g], z[g]
        o0 = out[g]
        for n in range(x.size):
            u = x[n]
            y = p0 + c0 * u; p0 = u * d0 - y * e0; o0[n] = y   # noqa: E702
        z[g] = p0
        g += 1
