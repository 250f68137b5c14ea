"""Banks of IIR filters run together: one filter on many rows, or first-order lags of one signal with many time
constants.

An identification filters the same records thousands of times (the design's rows through G, creep's lags of the
model output).  ``scipy.signal.lfilter`` runs one row at a time, and each output waits for the one before it.  The
kernels here advance several rows of a bank at each sample, so their recursions overlap: the same arithmetic as
lfilter's transposed direct form II, operation by operation (the same bits: ``test_iir``), several times faster
on a bank (bench/core_speed.py measures both), except that a subnormal output is flushed to zero, as a CPU's
flush-to-zero mode does (lfilter's recursion at rest decays into the subnormal range and can stay there, where
each operation, and each product of the filtered rows later, costs tens of times a normal one).  The rows and
columns kernels flush off the recursion's path (an output as it is stored, a state at the end of each block of
samples: a recursion decaying into subnormals runs on them for at most a block), so elsewhere their bits are
lfilter's and the flush costs nothing on a normal record; the first-order bank flushes in the recursion.  They are
compiled by numba on first use (cached on disk), so importing this module costs nothing until a bank is filtered.
Nothing here imports ROS.
"""
from __future__ import annotations

import functools
from typing import Optional

import numpy as np

from .compiled import load as load_kernels

__all__ = ["filter_rows", "filter_columns", "first_order_bank", "creep_lag_rows", "padded", "KERNEL_TAPS"]

KERNEL_TAPS = tuple(range(2, 9))   # filter lengths (taps of the longer of b and a) with a kernel; others: lfilter


@functools.cache
def _kernels():
    """The numba kernels, compiled (or loaded from numba's cache) on first use."""
    return load_kernels(__package__ + "._iir_kernels")


def padded(b, a) -> tuple[np.ndarray, np.ndarray]:
    """b and a (coefficients of z^-k) as float arrays of one length, zero padded (as lfilter pads them)."""
    b, a = np.atleast_1d(np.asarray(b, float)), np.atleast_1d(np.asarray(a, float))
    taps = max(b.size, a.size)
    return np.concatenate((b, np.zeros(taps - b.size))), np.concatenate((a, np.zeros(taps - a.size)))


def _into(out: Optional[np.ndarray], result: np.ndarray) -> np.ndarray:
    """``result``, or ``out`` (checked as ``_output`` checks it) holding a copy of it."""
    if out is None:
        return result
    out = _output(out, result.shape)
    out[...] = result
    return out


def _output(out: Optional[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """``out`` checked to be a C-contiguous float array of ``shape`` (the kernels write into it), or a new one."""
    if out is None:
        return np.empty(shape)
    if out.shape != shape or out.dtype != np.float64 or not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError(f"out must be a writeable C-contiguous float64 array of shape {shape}, got {out.dtype} "
                         f"{out.shape}")
    return out


def filter_rows(b, a, rows: np.ndarray, zi: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
    """``scipy.signal.lfilter(b, a, rows, axis=1, zi=zi)[0]``, bit for bit: the filter b(z)/a(z) on each row of
    ``rows`` (k, N), each from its own transposed-direct-form-II state ``zi`` (k, taps - 1); returns (k, N), in
    ``out`` where given (C-contiguous, e.g. rows of a larger design).  Each row's arithmetic is its own: a bank
    filtered in parts gives the same bits.  FIR filters (a of one tap: lfilter convolves them), a[0] != 1 and
    lengths the kernels do not run (``KERNEL_TAPS``) go to lfilter itself."""
    given = (b, a)
    b, a = padded(b, a)
    rows = np.asarray(rows, float)
    if rows.ndim != 2:
        raise ValueError(f"rows must be (k, N), got shape {rows.shape}")
    taps = b.size
    zi = np.asarray(zi, float).reshape(rows.shape[0], taps - 1) if taps > 1 else np.zeros((rows.shape[0], 0))
    if np.size(given[1]) == 1 or a[0] != 1.0 or taps not in KERNEL_TAPS:
        from scipy import signal
        return _into(out, signal.lfilter(*given, rows, axis=1, zi=zi)[0] if taps > 1
                     else signal.lfilter(*given, rows, axis=1))
    out = _output(out, rows.shape)
    state = np.array(zi.T, order="C")   # (taps - 1, k): each tap's states contiguous across the rows; a copy,
    # always C (one compiled specialisation, whether a bank has one row or several)
    _kernels().RUN_ROWS[taps](b, a, np.ascontiguousarray(rows), state, out)
    return out


def filter_columns(b, a, columns: np.ndarray, less: np.ndarray, zi: np.ndarray,
                   out: Optional[np.ndarray] = None) -> np.ndarray:
    """``filter_rows(b, a, (columns - less).T, zi)``, bit for bit, from a sample-major ``columns`` (N, k) without its
    transposed copy: each column less ``less`` (k,), filtered from its state ``zi`` (k, taps - 1); returns the
    filtered columns as rows (k, N), in ``out`` where given (C-contiguous).  The kernel advances every column at each sample in one loop (vector registers)
    and writes the rows out a block of samples at a time; on a long bank it is bound by memory, like the rows kernel,
    and saves the transposed copy (bench/core_speed.py).  Filters the kernels do not run go the way of
    ``filter_rows``."""
    given = (b, a)
    b, a = padded(b, a)
    columns = np.asarray(columns, float)
    if columns.ndim != 2:
        raise ValueError(f"columns must be (N, k), got shape {columns.shape}")
    n_samples, k = columns.shape
    less = np.asarray(less, float).reshape(k)
    taps = b.size
    zi = np.asarray(zi, float).reshape(k, taps - 1) if taps > 1 else np.zeros((k, 0))
    if np.size(given[1]) == 1 or a[0] != 1.0 or taps not in KERNEL_TAPS:
        return filter_rows(*given, (columns - less).T, zi, out)
    out = _output(out, (k, n_samples))
    state = np.array(zi.T, order="C")   # (taps - 1, k): a copy, always C (one compiled specialisation)
    _kernels().RUN_COLUMNS[taps](b, a, np.ascontiguousarray(columns), np.ascontiguousarray(less), state, out)
    return out


def first_order_bank(x: np.ndarray, poles: np.ndarray, gains: np.ndarray, start: float) -> np.ndarray:
    """The filters ``gain_i z^-1 / (1 - pole_i z^-1)`` on ``x`` (N,), each started from the state ``start``:
    ``lfilter([0, gain_i], [1, -pole_i], x, zi=[start])[0]`` for every i, bit for bit; returns (N, k), one column per
    filter, each column contiguous (a transposed view)."""
    x = np.ascontiguousarray(x, dtype=float)
    poles, gains = np.asarray(poles, float).reshape(-1), np.asarray(gains, float).reshape(-1)
    if poles.shape != gains.shape:
        raise ValueError(f"poles {poles.shape} and gains {gains.shape} differ in shape")
    out = np.empty((poles.size, x.size))
    _kernels().first_order_bank(x, np.zeros(poles.size), gains, -poles, np.full(poles.size, float(start)), out)
    return out.T


@functools.cache
def _lag_rows_kernel():
    return load_kernels(__package__ + "._lag_rows_kernel")


def creep_lag_rows(h: np.ndarray, before: float, poles: np.ndarray, shaped: int, centre: float, half: float
                   ) -> np.ndarray:
    """Creep's design rows (n + 2 shaped, N) in one pass: ``lag_j(h) - h`` for the first-order lags of ``poles`` (n,)
    started at rest at ``before``; then for the first ``shaped`` poles ``(lag(r) - r) - (lag(f) - f)`` with r and f
    the cumulative rising and falling changes of h through the first lag (each lag started at its input's first
    value); then the first ``shaped`` rows times ``(h - centre) / half``.  The same bits as those rows built from
    ``first_order_bank``, ``np.diff``, ``np.cumsum`` and numpy's products (``test_iir``)."""
    h = np.ascontiguousarray(h, dtype=float)
    poles = np.asarray(poles, float).reshape(-1)
    if not 0 <= shaped <= poles.size:
        raise ValueError(f"shaped must be 0..{poles.size}, got {shaped}")
    rows = np.empty((poles.size + 2 * shaped, h.size))
    _lag_rows_kernel().creep_rows(h, float(before), 1.0 - poles, -poles, int(shaped), float(centre), float(half), rows)
    return rows
