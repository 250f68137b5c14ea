"""numba kernels of ``iir`` (imported on first use).  Written by scripts/iir_kernels.py: do not edit by
hand.

Each is lfilter's transposed direct form II, operation by operation,

    y[n] = z0 + b0 x[n];  z_j = z_(j+1) + x[n] b_(j+1) - y[n] a_(j+1);  z_last = x[n] b_last - y[n] a_last,

on several rows at each sample (each output waits for the one before it; the rows' independent recursions
overlap), their states and the coefficients locals, then the rows left over one at a time; or (``columns_*``) on
every column of a sample-major array at each sample, in one loop over the columns.  No fast-math: the operations
and their order are lfilter's, so are the bits, except that a subnormal output (below TINY in magnitude) is
flushed to zero, as a CPU's flush-to-zero mode does: lfilter's recursion, its input at rest, decays into the
subnormal range and can cycle there, and arithmetic on subnormals is tens of times slower (here and in every
product of the rows filtered).  The rows and columns kernels flush an output as it is stored and a subnormal state
at the end of each block of samples (off the recursion's path: it runs on the unflushed output until then); the
first-order bank flushes each output in the recursion."""
from __future__ import annotations

import numba
import numpy as np

TINY = np.finfo(np.float64).tiny   # the smallest normal float: outputs below it in magnitude are flushed to zero


@numba.njit(nogil=True, cache=True)
def rows_2(b, a, x, z, out):
    """Filters of 2 taps on each row of x (k, N); z (1, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1 = b[0], b[1]
    a1 = a[1]
    g = 0
    while g + 4 <= k:
        s0_0 = z[0, g + 0]
        s1_0 = z[0, g + 1]
        s2_0 = z[0, g + 2]
        s3_0 = z[0, g + 3]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        x2, o2 = x[g + 2], out[g + 2]
        x3, o3 = x[g + 3], out[g + 3]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = u * b1 - y * a1
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = u * b1 - y * a1
                o1[n] = 0.0 if -TINY < y < TINY else y
                u = x2[n]
                y = s2_0 + b0 * u
                s2_0 = u * b1 - y * a1
                o2[n] = 0.0 if -TINY < y < TINY else y
                u = x3[n]
                y = s3_0 + b0 * u
                s3_0 = u * b1 - y * a1
                o3[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s2_0 < TINY: s2_0 = 0.0
            if -TINY < s3_0 < TINY: s3_0 = 0.0
        z[0, g + 0] = s0_0
        z[0, g + 1] = s1_0
        z[0, g + 2] = s2_0
        z[0, g + 3] = s3_0
        g += 4
    while g < k:
        s0_0 = z[0, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = u * b1 - y * a1
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
        z[0, g + 0] = s0_0
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_3(b, a, x, z, out):
    """Filters of 3 taps on each row of x (k, N); z (2, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2 = b[0], b[1], b[2]
    a1, a2 = a[1], a[2]
    g = 0
    while g + 4 <= k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s1_0 = z[0, g + 1]
        s1_1 = z[1, g + 1]
        s2_0 = z[0, g + 2]
        s2_1 = z[1, g + 2]
        s3_0 = z[0, g + 3]
        s3_1 = z[1, g + 3]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        x2, o2 = x[g + 2], out[g + 2]
        x3, o3 = x[g + 3], out[g + 3]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = u * b2 - y * a2
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = s1_1 + u * b1 - y * a1
                s1_1 = u * b2 - y * a2
                o1[n] = 0.0 if -TINY < y < TINY else y
                u = x2[n]
                y = s2_0 + b0 * u
                s2_0 = s2_1 + u * b1 - y * a1
                s2_1 = u * b2 - y * a2
                o2[n] = 0.0 if -TINY < y < TINY else y
                u = x3[n]
                y = s3_0 + b0 * u
                s3_0 = s3_1 + u * b1 - y * a1
                s3_1 = u * b2 - y * a2
                o3[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s1_1 < TINY: s1_1 = 0.0
            if -TINY < s2_0 < TINY: s2_0 = 0.0
            if -TINY < s2_1 < TINY: s2_1 = 0.0
            if -TINY < s3_0 < TINY: s3_0 = 0.0
            if -TINY < s3_1 < TINY: s3_1 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[0, g + 1] = s1_0
        z[1, g + 1] = s1_1
        z[0, g + 2] = s2_0
        z[1, g + 2] = s2_1
        z[0, g + 3] = s3_0
        z[1, g + 3] = s3_1
        g += 4
    while g < k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = u * b2 - y * a2
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_4(b, a, x, z, out):
    """Filters of 4 taps on each row of x (k, N); z (3, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, b3 = b[0], b[1], b[2], b[3]
    a1, a2, a3 = a[1], a[2], a[3]
    g = 0
    while g + 4 <= k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s1_0 = z[0, g + 1]
        s1_1 = z[1, g + 1]
        s1_2 = z[2, g + 1]
        s2_0 = z[0, g + 2]
        s2_1 = z[1, g + 2]
        s2_2 = z[2, g + 2]
        s3_0 = z[0, g + 3]
        s3_1 = z[1, g + 3]
        s3_2 = z[2, g + 3]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        x2, o2 = x[g + 2], out[g + 2]
        x3, o3 = x[g + 3], out[g + 3]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = u * b3 - y * a3
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = s1_1 + u * b1 - y * a1
                s1_1 = s1_2 + u * b2 - y * a2
                s1_2 = u * b3 - y * a3
                o1[n] = 0.0 if -TINY < y < TINY else y
                u = x2[n]
                y = s2_0 + b0 * u
                s2_0 = s2_1 + u * b1 - y * a1
                s2_1 = s2_2 + u * b2 - y * a2
                s2_2 = u * b3 - y * a3
                o2[n] = 0.0 if -TINY < y < TINY else y
                u = x3[n]
                y = s3_0 + b0 * u
                s3_0 = s3_1 + u * b1 - y * a1
                s3_1 = s3_2 + u * b2 - y * a2
                s3_2 = u * b3 - y * a3
                o3[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s1_1 < TINY: s1_1 = 0.0
            if -TINY < s1_2 < TINY: s1_2 = 0.0
            if -TINY < s2_0 < TINY: s2_0 = 0.0
            if -TINY < s2_1 < TINY: s2_1 = 0.0
            if -TINY < s2_2 < TINY: s2_2 = 0.0
            if -TINY < s3_0 < TINY: s3_0 = 0.0
            if -TINY < s3_1 < TINY: s3_1 = 0.0
            if -TINY < s3_2 < TINY: s3_2 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[0, g + 1] = s1_0
        z[1, g + 1] = s1_1
        z[2, g + 1] = s1_2
        z[0, g + 2] = s2_0
        z[1, g + 2] = s2_1
        z[2, g + 2] = s2_2
        z[0, g + 3] = s3_0
        z[1, g + 3] = s3_1
        z[2, g + 3] = s3_2
        g += 4
    while g < k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = u * b3 - y * a3
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_5(b, a, x, z, out):
    """Filters of 5 taps on each row of x (k, N); z (4, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, b3, b4 = b[0], b[1], b[2], b[3], b[4]
    a1, a2, a3, a4 = a[1], a[2], a[3], a[4]
    g = 0
    while g + 2 <= k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s1_0 = z[0, g + 1]
        s1_1 = z[1, g + 1]
        s1_2 = z[2, g + 1]
        s1_3 = z[3, g + 1]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = u * b4 - y * a4
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = s1_1 + u * b1 - y * a1
                s1_1 = s1_2 + u * b2 - y * a2
                s1_2 = s1_3 + u * b3 - y * a3
                s1_3 = u * b4 - y * a4
                o1[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s1_1 < TINY: s1_1 = 0.0
            if -TINY < s1_2 < TINY: s1_2 = 0.0
            if -TINY < s1_3 < TINY: s1_3 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[0, g + 1] = s1_0
        z[1, g + 1] = s1_1
        z[2, g + 1] = s1_2
        z[3, g + 1] = s1_3
        g += 2
    while g < k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = u * b4 - y * a4
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_6(b, a, x, z, out):
    """Filters of 6 taps on each row of x (k, N); z (5, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, b3, b4, b5 = b[0], b[1], b[2], b[3], b[4], b[5]
    a1, a2, a3, a4, a5 = a[1], a[2], a[3], a[4], a[5]
    g = 0
    while g + 2 <= k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s0_4 = z[4, g + 0]
        s1_0 = z[0, g + 1]
        s1_1 = z[1, g + 1]
        s1_2 = z[2, g + 1]
        s1_3 = z[3, g + 1]
        s1_4 = z[4, g + 1]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = s0_4 + u * b4 - y * a4
                s0_4 = u * b5 - y * a5
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = s1_1 + u * b1 - y * a1
                s1_1 = s1_2 + u * b2 - y * a2
                s1_2 = s1_3 + u * b3 - y * a3
                s1_3 = s1_4 + u * b4 - y * a4
                s1_4 = u * b5 - y * a5
                o1[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s0_4 < TINY: s0_4 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s1_1 < TINY: s1_1 = 0.0
            if -TINY < s1_2 < TINY: s1_2 = 0.0
            if -TINY < s1_3 < TINY: s1_3 = 0.0
            if -TINY < s1_4 < TINY: s1_4 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[4, g + 0] = s0_4
        z[0, g + 1] = s1_0
        z[1, g + 1] = s1_1
        z[2, g + 1] = s1_2
        z[3, g + 1] = s1_3
        z[4, g + 1] = s1_4
        g += 2
    while g < k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s0_4 = z[4, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = s0_4 + u * b4 - y * a4
                s0_4 = u * b5 - y * a5
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s0_4 < TINY: s0_4 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[4, g + 0] = s0_4
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_7(b, a, x, z, out):
    """Filters of 7 taps on each row of x (k, N); z (6, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, b3, b4, b5, b6 = b[0], b[1], b[2], b[3], b[4], b[5], b[6]
    a1, a2, a3, a4, a5, a6 = a[1], a[2], a[3], a[4], a[5], a[6]
    g = 0
    while g + 2 <= k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s0_4 = z[4, g + 0]
        s0_5 = z[5, g + 0]
        s1_0 = z[0, g + 1]
        s1_1 = z[1, g + 1]
        s1_2 = z[2, g + 1]
        s1_3 = z[3, g + 1]
        s1_4 = z[4, g + 1]
        s1_5 = z[5, g + 1]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = s0_4 + u * b4 - y * a4
                s0_4 = s0_5 + u * b5 - y * a5
                s0_5 = u * b6 - y * a6
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = s1_1 + u * b1 - y * a1
                s1_1 = s1_2 + u * b2 - y * a2
                s1_2 = s1_3 + u * b3 - y * a3
                s1_3 = s1_4 + u * b4 - y * a4
                s1_4 = s1_5 + u * b5 - y * a5
                s1_5 = u * b6 - y * a6
                o1[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s0_4 < TINY: s0_4 = 0.0
            if -TINY < s0_5 < TINY: s0_5 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s1_1 < TINY: s1_1 = 0.0
            if -TINY < s1_2 < TINY: s1_2 = 0.0
            if -TINY < s1_3 < TINY: s1_3 = 0.0
            if -TINY < s1_4 < TINY: s1_4 = 0.0
            if -TINY < s1_5 < TINY: s1_5 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[4, g + 0] = s0_4
        z[5, g + 0] = s0_5
        z[0, g + 1] = s1_0
        z[1, g + 1] = s1_1
        z[2, g + 1] = s1_2
        z[3, g + 1] = s1_3
        z[4, g + 1] = s1_4
        z[5, g + 1] = s1_5
        g += 2
    while g < k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s0_4 = z[4, g + 0]
        s0_5 = z[5, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = s0_4 + u * b4 - y * a4
                s0_4 = s0_5 + u * b5 - y * a5
                s0_5 = u * b6 - y * a6
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s0_4 < TINY: s0_4 = 0.0
            if -TINY < s0_5 < TINY: s0_5 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[4, g + 0] = s0_4
        z[5, g + 0] = s0_5
        g += 1


@numba.njit(nogil=True, cache=True)
def rows_8(b, a, x, z, out):
    """Filters of 8 taps on each row of x (k, N); z (7, k) states in and out; out (k, N)."""
    k, n_samples = x.shape
    b0, b1, b2, b3, b4, b5, b6, b7 = b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]
    a1, a2, a3, a4, a5, a6, a7 = a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    g = 0
    while g + 2 <= k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s0_4 = z[4, g + 0]
        s0_5 = z[5, g + 0]
        s0_6 = z[6, g + 0]
        s1_0 = z[0, g + 1]
        s1_1 = z[1, g + 1]
        s1_2 = z[2, g + 1]
        s1_3 = z[3, g + 1]
        s1_4 = z[4, g + 1]
        s1_5 = z[5, g + 1]
        s1_6 = z[6, g + 1]
        x0, o0 = x[g + 0], out[g + 0]
        x1, o1 = x[g + 1], out[g + 1]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = s0_4 + u * b4 - y * a4
                s0_4 = s0_5 + u * b5 - y * a5
                s0_5 = s0_6 + u * b6 - y * a6
                s0_6 = u * b7 - y * a7
                o0[n] = 0.0 if -TINY < y < TINY else y
                u = x1[n]
                y = s1_0 + b0 * u
                s1_0 = s1_1 + u * b1 - y * a1
                s1_1 = s1_2 + u * b2 - y * a2
                s1_2 = s1_3 + u * b3 - y * a3
                s1_3 = s1_4 + u * b4 - y * a4
                s1_4 = s1_5 + u * b5 - y * a5
                s1_5 = s1_6 + u * b6 - y * a6
                s1_6 = u * b7 - y * a7
                o1[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s0_4 < TINY: s0_4 = 0.0
            if -TINY < s0_5 < TINY: s0_5 = 0.0
            if -TINY < s0_6 < TINY: s0_6 = 0.0
            if -TINY < s1_0 < TINY: s1_0 = 0.0
            if -TINY < s1_1 < TINY: s1_1 = 0.0
            if -TINY < s1_2 < TINY: s1_2 = 0.0
            if -TINY < s1_3 < TINY: s1_3 = 0.0
            if -TINY < s1_4 < TINY: s1_4 = 0.0
            if -TINY < s1_5 < TINY: s1_5 = 0.0
            if -TINY < s1_6 < TINY: s1_6 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[4, g + 0] = s0_4
        z[5, g + 0] = s0_5
        z[6, g + 0] = s0_6
        z[0, g + 1] = s1_0
        z[1, g + 1] = s1_1
        z[2, g + 1] = s1_2
        z[3, g + 1] = s1_3
        z[4, g + 1] = s1_4
        z[5, g + 1] = s1_5
        z[6, g + 1] = s1_6
        g += 2
    while g < k:
        s0_0 = z[0, g + 0]
        s0_1 = z[1, g + 0]
        s0_2 = z[2, g + 0]
        s0_3 = z[3, g + 0]
        s0_4 = z[4, g + 0]
        s0_5 = z[5, g + 0]
        s0_6 = z[6, g + 0]
        x0, o0 = x[g], out[g]
        for start in range(0, n_samples, 256):
            for n in range(start, min(start + 256, n_samples)):
                u = x0[n]
                y = s0_0 + b0 * u
                s0_0 = s0_1 + u * b1 - y * a1
                s0_1 = s0_2 + u * b2 - y * a2
                s0_2 = s0_3 + u * b3 - y * a3
                s0_3 = s0_4 + u * b4 - y * a4
                s0_4 = s0_5 + u * b5 - y * a5
                s0_5 = s0_6 + u * b6 - y * a6
                s0_6 = u * b7 - y * a7
                o0[n] = 0.0 if -TINY < y < TINY else y
            if -TINY < s0_0 < TINY: s0_0 = 0.0
            if -TINY < s0_1 < TINY: s0_1 = 0.0
            if -TINY < s0_2 < TINY: s0_2 = 0.0
            if -TINY < s0_3 < TINY: s0_3 = 0.0
            if -TINY < s0_4 < TINY: s0_4 = 0.0
            if -TINY < s0_5 < TINY: s0_5 = 0.0
            if -TINY < s0_6 < TINY: s0_6 = 0.0
        z[0, g + 0] = s0_0
        z[1, g + 0] = s0_1
        z[2, g + 0] = s0_2
        z[3, g + 0] = s0_3
        z[4, g + 0] = s0_4
        z[5, g + 0] = s0_5
        z[6, g + 0] = s0_6
        g += 1


RUN_ROWS = {2: rows_2, 3: rows_3, 4: rows_4, 5: rows_5, 6: rows_6, 7: rows_7, 8: rows_8}


@numba.njit(nogil=True, cache=True)
def columns_2(b, a, x, first, z, out):
    """Filters of 2 taps on each column of x (N, k) less first (k,); z (1, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1 = b[0], b[1]
    a1 = a[1]
    s0 = z[0].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = u * b1 - y * a1
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0


@numba.njit(nogil=True, cache=True)
def columns_3(b, a, x, first, z, out):
    """Filters of 3 taps on each column of x (N, k) less first (k,); z (2, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1, b2 = b[0], b[1], b[2]
    a1, a2 = a[1], a[2]
    s0 = z[0].copy()
    s1 = z[1].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = s1[j] + u * b1 - y * a1
                s1[j] = u * b2 - y * a2
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
            if -TINY < s1[j] < TINY: s1[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0
    z[1] = s1


@numba.njit(nogil=True, cache=True)
def columns_4(b, a, x, first, z, out):
    """Filters of 4 taps on each column of x (N, k) less first (k,); z (3, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1, b2, b3 = b[0], b[1], b[2], b[3]
    a1, a2, a3 = a[1], a[2], a[3]
    s0 = z[0].copy()
    s1 = z[1].copy()
    s2 = z[2].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = s1[j] + u * b1 - y * a1
                s1[j] = s2[j] + u * b2 - y * a2
                s2[j] = u * b3 - y * a3
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
            if -TINY < s1[j] < TINY: s1[j] = 0.0
            if -TINY < s2[j] < TINY: s2[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0
    z[1] = s1
    z[2] = s2


@numba.njit(nogil=True, cache=True)
def columns_5(b, a, x, first, z, out):
    """Filters of 5 taps on each column of x (N, k) less first (k,); z (4, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1, b2, b3, b4 = b[0], b[1], b[2], b[3], b[4]
    a1, a2, a3, a4 = a[1], a[2], a[3], a[4]
    s0 = z[0].copy()
    s1 = z[1].copy()
    s2 = z[2].copy()
    s3 = z[3].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = s1[j] + u * b1 - y * a1
                s1[j] = s2[j] + u * b2 - y * a2
                s2[j] = s3[j] + u * b3 - y * a3
                s3[j] = u * b4 - y * a4
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
            if -TINY < s1[j] < TINY: s1[j] = 0.0
            if -TINY < s2[j] < TINY: s2[j] = 0.0
            if -TINY < s3[j] < TINY: s3[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0
    z[1] = s1
    z[2] = s2
    z[3] = s3


@numba.njit(nogil=True, cache=True)
def columns_6(b, a, x, first, z, out):
    """Filters of 6 taps on each column of x (N, k) less first (k,); z (5, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1, b2, b3, b4, b5 = b[0], b[1], b[2], b[3], b[4], b[5]
    a1, a2, a3, a4, a5 = a[1], a[2], a[3], a[4], a[5]
    s0 = z[0].copy()
    s1 = z[1].copy()
    s2 = z[2].copy()
    s3 = z[3].copy()
    s4 = z[4].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = s1[j] + u * b1 - y * a1
                s1[j] = s2[j] + u * b2 - y * a2
                s2[j] = s3[j] + u * b3 - y * a3
                s3[j] = s4[j] + u * b4 - y * a4
                s4[j] = u * b5 - y * a5
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
            if -TINY < s1[j] < TINY: s1[j] = 0.0
            if -TINY < s2[j] < TINY: s2[j] = 0.0
            if -TINY < s3[j] < TINY: s3[j] = 0.0
            if -TINY < s4[j] < TINY: s4[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0
    z[1] = s1
    z[2] = s2
    z[3] = s3
    z[4] = s4


@numba.njit(nogil=True, cache=True)
def columns_7(b, a, x, first, z, out):
    """Filters of 7 taps on each column of x (N, k) less first (k,); z (6, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1, b2, b3, b4, b5, b6 = b[0], b[1], b[2], b[3], b[4], b[5], b[6]
    a1, a2, a3, a4, a5, a6 = a[1], a[2], a[3], a[4], a[5], a[6]
    s0 = z[0].copy()
    s1 = z[1].copy()
    s2 = z[2].copy()
    s3 = z[3].copy()
    s4 = z[4].copy()
    s5 = z[5].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = s1[j] + u * b1 - y * a1
                s1[j] = s2[j] + u * b2 - y * a2
                s2[j] = s3[j] + u * b3 - y * a3
                s3[j] = s4[j] + u * b4 - y * a4
                s4[j] = s5[j] + u * b5 - y * a5
                s5[j] = u * b6 - y * a6
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
            if -TINY < s1[j] < TINY: s1[j] = 0.0
            if -TINY < s2[j] < TINY: s2[j] = 0.0
            if -TINY < s3[j] < TINY: s3[j] = 0.0
            if -TINY < s4[j] < TINY: s4[j] = 0.0
            if -TINY < s5[j] < TINY: s5[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0
    z[1] = s1
    z[2] = s2
    z[3] = s3
    z[4] = s4
    z[5] = s5


@numba.njit(nogil=True, cache=True)
def columns_8(b, a, x, first, z, out):
    """Filters of 8 taps on each column of x (N, k) less first (k,); z (7, k) states in and out; out
    (k, N): the filtered columns as rows."""
    n_samples, k = x.shape
    b0, b1, b2, b3, b4, b5, b6, b7 = b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]
    a1, a2, a3, a4, a5, a6, a7 = a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    s0 = z[0].copy()
    s1 = z[1].copy()
    s2 = z[2].copy()
    s3 = z[3].copy()
    s4 = z[4].copy()
    s5 = z[5].copy()
    s6 = z[6].copy()
    block = np.empty((64, k))
    for start in range(0, n_samples, 64):
        m = min(64, n_samples - start)
        for i in range(m):
            xi, yi = x[start + i], block[i]
            for j in range(k):
                u = xi[j] - first[j]
                y = s0[j] + b0 * u
                s0[j] = s1[j] + u * b1 - y * a1
                s1[j] = s2[j] + u * b2 - y * a2
                s2[j] = s3[j] + u * b3 - y * a3
                s3[j] = s4[j] + u * b4 - y * a4
                s4[j] = s5[j] + u * b5 - y * a5
                s5[j] = s6[j] + u * b6 - y * a6
                s6[j] = u * b7 - y * a7
                yi[j] = 0.0 if -TINY < y < TINY else y
        for j in range(k):
            if -TINY < s0[j] < TINY: s0[j] = 0.0
            if -TINY < s1[j] < TINY: s1[j] = 0.0
            if -TINY < s2[j] < TINY: s2[j] = 0.0
            if -TINY < s3[j] < TINY: s3[j] = 0.0
            if -TINY < s4[j] < TINY: s4[j] = 0.0
            if -TINY < s5[j] < TINY: s5[j] = 0.0
            if -TINY < s6[j] < TINY: s6[j] = 0.0
        for j in range(k):
            oj = out[j]
            for i in range(m):
                oj[start + i] = block[i, j]
    z[0] = s0
    z[1] = s1
    z[2] = s2
    z[3] = s3
    z[4] = s4
    z[5] = s5
    z[6] = s6


RUN_COLUMNS = {2: columns_2, 3: columns_3, 4: columns_4, 5: columns_5, 6: columns_6, 7: columns_7, 8: columns_8}


@numba.njit(nogil=True, cache=True)
def first_order_bank(x, b0, b1, a1, z, out):
    """First-order filters (b0_i + b1_i z^-1) / (1 + a1_i z^-1), one per element of b0, b1, a1 (k), on one
    input x (N,); z (k,) states in and out; out (k, N)."""
    k = b0.size
    g = 0
    while g + 4 <= k:
        c0, d0, e0 = b0[g + 0], b1[g + 0], a1[g + 0]
        p0, o0 = z[g + 0], out[g + 0]
        c1, d1, e1 = b0[g + 1], b1[g + 1], a1[g + 1]
        p1, o1 = z[g + 1], out[g + 1]
        c2, d2, e2 = b0[g + 2], b1[g + 2], a1[g + 2]
        p2, o2 = z[g + 2], out[g + 2]
        c3, d3, e3 = b0[g + 3], b1[g + 3], a1[g + 3]
        p3, o3 = z[g + 3], out[g + 3]
        for n in range(x.size):
            u = x[n]
            y = p0 + c0 * u
            if -TINY < y < TINY: y = 0.0
            p0 = u * d0 - y * e0
            o0[n] = y
            y = p1 + c1 * u
            if -TINY < y < TINY: y = 0.0
            p1 = u * d1 - y * e1
            o1[n] = y
            y = p2 + c2 * u
            if -TINY < y < TINY: y = 0.0
            p2 = u * d2 - y * e2
            o2[n] = y
            y = p3 + c3 * u
            if -TINY < y < TINY: y = 0.0
            p3 = u * d3 - y * e3
            o3[n] = y
        z[g + 0] = p0
        z[g + 1] = p1
        z[g + 2] = p2
        z[g + 3] = p3
        g += 4
    while g < k:
        c0, d0, e0, p0, o0 = b0[g], b1[g], a1[g], z[g], out[g]
        for n in range(x.size):
            u = x[n]
            y = p0 + c0 * u
            if -TINY < y < TINY: y = 0.0
            p0 = u * d0 - y * e0
            o0[n] = y
        z[g] = p0
        g += 1
