"""G on a record: its discretisation for the way the record was sampled (raw samples or block means, a transport
delay after it), and filtering started at rest (at the record's first value, or at a value held before it).
What the identification runs its design through thousands of times; nothing here imports ROS."""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Optional

import numpy as np

from .dynamics import ContinuousTF, discretise, steady_state
from .iir import filter_columns, filter_rows

__all__ = ["discretised", "delay_taps", "filter_at_rest", "filter_rows_at_rest", "filter_state_columns_at_rest"]


@lru_cache(maxsize=4096)
def discretised(tf: ContinuousTF, dt: float, raw: bool, hold_delay_s: float = 0.0, delay_s: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of ``tf`` sampled every ``dt`` [s]: with a zero-order hold on ``raw`` samples (what a DAQ applies), or on
    block means with a first-order hold and ``hold_delay_s`` (the source's half sample); a transport delay
    ``delay_s`` [s] >= 0 after it as whole samples and a linear interpolation for the fraction (``delay_taps``).
    The arrays are shared (read-only): an analysis asks for the same few G thousands of times."""
    b, a = discretise(tf, dt, "zoh") if raw else discretise(tf, dt, "foh", hold_delay_s)
    if delay_s > 0.0:
        b = np.convolve(b, delay_taps(delay_s / dt))
    b.flags.writeable = a.flags.writeable = False
    return b, a


def delay_taps(samples: float) -> np.ndarray:
    """FIR taps of a delay of ``samples`` (>= 0, fractional): whole samples, then the fraction by linear
    interpolation between the two samples around it."""
    whole = int(math.floor(samples))
    fraction = samples - whole
    taps = np.zeros(whole + 2)
    taps[whole], taps[whole + 1] = 1.0 - fraction, fraction
    return taps


def filter_at_rest(b: np.ndarray, a: np.ndarray, x: np.ndarray, rest=None) -> np.ndarray:
    """lfilter of x (N,) or each column of x (N, k), started at rest at the first sample, or at rest at ``rest``
    (a value, or one per column) before it.  Columns are filtered as contiguous rows of the transpose."""
    x = np.asarray(x, float)
    if x.ndim == 1:
        start = x[:1] if rest is None else np.asarray(rest, float).reshape(-1)[:1]
        return filter_rows_at_rest(b, a, x[None, :], start)[0]
    if rest is not None:
        rest = np.broadcast_to(np.asarray(rest, float), (x.shape[1],))
    return filter_rows_at_rest(b, a, np.ascontiguousarray(x.T), rest).T


def filter_state_columns_at_rest(b: np.ndarray, a: np.ndarray, states: np.ndarray,
                                 rest: Optional[np.ndarray] = None) -> np.ndarray:
    """``filter_rows_at_rest(b, a, (states - states[0]).T, rest)``, bit for bit, from the operator states (N, n) as
    they are (``iir.filter_columns``: no transposed copy of them): the GPIM's columns through G, one row per
    operator (n, N), each at rest at its first sample (zero) or at ``rest`` (n,) before it."""
    first = states[0]
    start = (first - first) if rest is None else np.asarray(rest, float).reshape(-1)
    return filter_columns(b, a, states, first, start[:, None] * steady_state(b, a)[None, :])


def filter_rows_at_rest(b: np.ndarray, a: np.ndarray, rows: np.ndarray, rest: Optional[np.ndarray] = None,
                        out: Optional[np.ndarray] = None) -> np.ndarray:
    """lfilter of each row of ``rows`` (k, N), started at rest at its first sample, or at rest at ``rest`` (k,)
    before it (the same as adding ``(rest - first) x`` G's free response: G is linear); (k, N), in ``out`` where
    given.  The rows are advanced together (``iir.filter_rows``)."""
    zi = steady_state(b, a)
    start = rows[:, :1] if rest is None else np.asarray(rest, float).reshape(-1, 1)
    return filter_rows(b, a, rows, start * zi[None, :], out)
