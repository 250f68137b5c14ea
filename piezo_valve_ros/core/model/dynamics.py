"""Discrete-time linear filters (exact ZOH discretisation) with identical streaming and batch paths.

The valve model of the paper, ``G_v(s) = 1.2e6 / (s^2 + 2900 s + 1.2e6)`` (amplifier input
to spool position, unity DC gain), lives here as ``PAPER_VALVE_MODEL``.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .iir import first_order_bank, padded

__all__ = ["scipy_signal", "steady_state", "ContinuousTF", "DiscreteFilter", "PAPER_VALVE_MODEL", "PAPER_SECTION", "first_order_lag", "lag_bank", "lag_poles", "discretise",
           "second_order", "unity_dc_poles", "sections", "describe_dynamics"]


def scipy_signal():
    """scipy.signal, imported on first use: the import takes most of a node's start-up (0.6 s of CPU), and
    the nodes' per-sample paths never need it."""
    from scipy import signal
    return signal


def steady_state(b, a) -> np.ndarray:
    """Transposed-direct-form-II state of the filter b(z)/a(z) that has seen a unit input forever
    (scipy.signal.lfilter_zi written out: b and a normalised by a[0] and padded to one length, then
    (I - A') z = b[1:] - a[1:] b[0], A the companion matrix of a).  Read-only: kept for the next call with the
    same coefficients (an analysis starts the same few filters at rest tens of thousands of times)."""
    b, a = padded(b, a)
    return _steady_state(b.tobytes(), a.tobytes())


@functools.lru_cache(maxsize=1024)
def _steady_state(b_bytes: bytes, a_bytes: bytes) -> np.ndarray:
    b, a = np.frombuffer(b_bytes), np.frombuffer(a_bytes)
    b, a = b / a[0], a / a[0]
    n = b.size - 1
    companion = np.zeros((n, n))
    companion[0, :] = -a[1:]
    companion[1:, :-1] += np.eye(n - 1)
    zi = np.linalg.solve(np.eye(n) - companion.T, b[1:] - a[1:] * b[0])
    zi.flags.writeable = False
    return zi


@dataclass(frozen=True)
class ContinuousTF:
    """Continuous transfer function num(s)/den(s), coefficients in descending powers of s."""

    num: tuple[float, ...]
    den: tuple[float, ...]

    def problems(self) -> list[str]:
        out = []
        if not self.num or not self.den:
            out.append("empty numerator or denominator")
            return out
        if not (np.all(np.isfinite(self.num)) and np.all(np.isfinite(self.den))):
            out.append("non-finite coefficient")
            return out
        if self.den[0] == 0:
            out.append("leading denominator coefficient is 0")
        elif len(self.num) > len(self.den):
            out.append("improper transfer function (numerator order > denominator order)")
        else:
            poles = np.roots(self.den)
            if np.any(poles.real >= 0):
                out.append(f"unstable or marginal poles {poles}")
        return out

    def discretise(self, dt: float) -> "DiscreteFilter":
        """Exact zero-order-hold discretisation for sample time ``dt`` [s]."""
        problems = self.problems()
        if problems:
            raise ValueError("invalid transfer function: " + "; ".join(problems))
        return DiscreteFilter(*discretise(self, dt))

    def frequency_response(self, freqs_hz: np.ndarray) -> np.ndarray:
        _, h = scipy_signal().freqs(self.num, self.den, worN=2 * np.pi * np.asarray(freqs_hz, float))
        return h


DISTINCT_POLE_GAP = 1e-2   # two poles closer than this share of the larger go through scipy's matrix exponential

PAPER_VALVE_MODEL = ContinuousTF((1.2e6,), (1.0, 2900.0, 1.2e6))


def discretise(tf: ContinuousTF, dt: float, method: str = "zoh", delay_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of ``tf`` sampled every ``dt`` [s] behind a zero-order hold (``"zoh"``, exact for a DAC's
    held samples) or a first-order hold (``"foh"``, inputs joined by straight lines), optionally with a
    ``delay_s`` as a Pade 1/1 factor.

    Strictly proper transfer functions with distinct poles (every fitted G) go through partial fractions
    in closed form, microseconds instead of the milliseconds of a matrix exponential of a badly scaled
    companion form; anything else through ``scipy.signal.cont2discrete``.
    """
    num = np.asarray(tf.num, float)
    num = num[np.argmax(num != 0):] if np.any(num != 0) else num[-1:]
    den = np.asarray(tf.den, float)
    if delay_s:
        num = np.convolve(num, [-0.5 * delay_s, 1.0])   # (np.polymul's product, without its poly1d objects:
        den = np.convolve(den, [0.5 * delay_s, 1.0])    # a fit discretises hundreds of trial poles)
    num, den = num / den[0], den / den[0]
    poles = np.roots(den)
    size = np.abs(poles)
    # a root of multiplicity m comes out of np.roots split by ~eps^(1/m) (1e-4 relative for a 4-fold one, as
    # in a feedforward target with two equal double poles), and partial fractions over such near-equal poles
    # cancel catastrophically: only poles apart by DISTINCT_POLE_GAP of the larger of each pair take the
    # closed form (each pair on its own scale: a fast delay factor beside two slow poles 10 % apart does not
    # send them through the matrix exponential)
    distinct = poles.size > 0 and bool(np.all(size > 0))   # (a pole at 0: no closed form, and no scale)
    if distinct:
        gaps = np.where(np.eye(poles.size, dtype=bool), np.inf,
                        np.abs(np.subtract.outer(poles, poles)) / np.maximum.outer(size, size))
        distinct = bool(np.min(gaps) > DISTINCT_POLE_GAP)
    if num.size >= den.size or not distinct:
        b, a, _ = scipy_signal().cont2discrete((num, den), dt, method=method)
        return np.atleast_1d(np.squeeze(b)), np.asarray(a, float)
    residues = np.polyval(num, poles) / np.polyval(np.polyder(den), poles)
    E = np.exp(poles * dt)
    if method == "zoh":
        direct = 0.0
        c = residues / poles * (E - 1.0)
    elif method == "foh":
        direct = complex(np.sum(residues * ((E - 1.0) / (poles * poles * dt) - 1.0 / poles)))
        c = residues * (E - 1.0) ** 2 / (poles * poles * dt)
    else:
        raise ValueError(f"method must be zoh or foh, got {method!r}")
    # a(z) = prod (z - E_i);  b(z) = direct a(z) + sum_i c_i prod_{j != i} (z - E_j)  (plain complex
    # arithmetic: these polynomials have a handful of coefficients, numpy's per-call cost would dominate)
    E_list, c_list = [complex(e) for e in E], [complex(x) for x in c]
    a = [1.0 + 0j]
    for e in E_list:
        a = [x - e * y for x, y in zip(a + [0j], [0j] + a)]
    b = [direct * x for x in a]
    for i, e in enumerate(E_list):
        q = [a[0]]  # a(z) / (z - E_i) by synthetic division (exact: E_i is a root)
        for coef in a[1:-1]:
            q.append(coef + e * q[-1])
        for k, coef in enumerate(q):
            b[k + 1] += c_list[i] * coef
    b, a = np.array(b), np.array(a)
    return np.real(b), np.real(a)


def first_order_lag(time_constant_s: float, dt: float) -> "DiscreteFilter":
    """ZOH-exact first-order lag 1/(tau s + 1)."""
    return ContinuousTF((1.0,), (float(time_constant_s), 1.0)).discretise(dt)


def lag_bank(x: np.ndarray, time_constants_s: Sequence[float], dt: float,
             initial: Optional[float] = None) -> np.ndarray:
    """First-order lags 1/(tau s + 1) of ``x`` (ZOH-exact, started at rest at ``initial``, default x[0]);
    shape (N, k), one column per time constant (``iir.first_order_bank``: several lags advanced together)."""
    x = np.asarray(x, float)
    start = float(x[0]) if initial is None else float(initial)
    # first_order_lag's ZOH filter written out (b = [0, 1 - a], a = [1, -a], a = exp(-dt/tau); at rest at
    # ``start`` its one state is ``start``): this runs thousands of times per analysis
    poles = lag_poles(time_constants_s, dt)
    return first_order_bank(x, poles, 1.0 - poles, start)


def lag_poles(time_constants_s: Sequence[float], dt: float) -> np.ndarray:
    """The sampled poles exp(-dt / tau) of first-order lags [1] (libm's exp, as the ZOH lag's)."""
    return np.array([math.exp(-dt / float(tau)) for tau in time_constants_s])


def second_order(omega_rad_s: float, zeta: float) -> ContinuousTF:
    """Unity-DC-gain second order w^2 / (s^2 + 2 zeta w s + w^2)."""
    w = float(omega_rad_s)
    return ContinuousTF((w * w,), (1.0, 2.0 * float(zeta) * w, w * w))


def unity_dc_poles(sections: Sequence[tuple[float, float]]) -> ContinuousTF:
    """Product of unity-DC-gain second-order sections given as (omega [rad/s], zeta)."""
    return _unity_dc_poles(tuple((float(w), float(z)) for w, z in sections))


@functools.lru_cache(maxsize=4096)   # fits ask for the same few G thousands of times (every model's context)
def _unity_dc_poles(sections: tuple[tuple[float, float], ...]) -> ContinuousTF:
    num, den = np.array([1.0]), np.array([1.0])
    for w, z in sections:
        tf = second_order(w, z)
        num, den = np.convolve(num, tf.num), np.convolve(den, tf.den)
    return ContinuousTF(tuple(float(x) for x in num), tuple(float(x) for x in den))


PAPER_SECTION = (float(np.sqrt(1.2e6)), float(2900.0 / (2.0 * np.sqrt(1.2e6))))  # the paper's G_v as (omega, zeta)


def sections(tf: ContinuousTF) -> list[tuple[float, float]]:
    """(omega [rad/s], zeta) of the second-order sections of a unity-DC-gain G with stable poles (real
    poles are paired in order of magnitude; an odd one out becomes a section with a very fast partner)."""
    poles = np.roots(tf.den)
    complex_ = sorted([p for p in poles if p.imag > 1e-9 * abs(p)], key=abs)
    real = sorted([-p.real for p in poles if abs(p.imag) <= 1e-9 * abs(p)])
    out = [(float(abs(p)), float(-p.real / abs(p))) for p in complex_]
    if len(real) % 2:
        real.append(1e3 * max(real))
    for p1, p2 in zip(real[0::2], real[1::2]):
        w = float(np.sqrt(p1 * p2))
        out.append((w, float((p1 + p2) / (2.0 * w))))
    return sorted(out)


def describe_dynamics(tf: ContinuousTF, note: str) -> dict:
    poles = np.roots(tf.den)
    return {"num": [float(x) for x in tf.num], "den": [float(x) for x in tf.den],
            "poles_rad_s": [[round(float(p.real), 3), round(float(p.imag), 3)] for p in sorted(poles, key=abs)],
            "source": note}


class DiscreteFilter:
    """IIR filter b(z)/a(z) in transposed direct form II.

    ``step`` (per sample, scalar state, no allocation) and ``run`` (batch, scipy.signal.lfilter)
    share the state, so a record may be processed in any mix of the two.
    """

    def __init__(self, b: Sequence[float], a: Sequence[float]):
        b, a = padded(b, a)
        b, a = b / a[0], a / a[0]
        order = b.size
        self.b = b
        self.a = a
        self._b = [float(x) for x in b]
        self._a = [float(x) for x in a]
        self.order = order - 1
        self.state = [0.0] * self.order

    def reset(self, steady_input: float = 0.0) -> None:
        """State of a filter that has seen ``steady_input`` forever."""
        if self.order == 0:
            return
        zi = steady_state(self.b, self.a) * steady_input
        self.state = [float(x) for x in zi]

    def step(self, u: float) -> float:
        b, a, s = self._b, self._a, self.state
        y = b[0] * u + (s[0] if self.order else 0.0)
        for i in range(self.order - 1):
            s[i] = s[i + 1] + b[i + 1] * u - a[i + 1] * y
        if self.order:
            s[self.order - 1] = b[self.order] * u - a[self.order] * y
        return y

    def run(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, float)
        if self.order == 0:
            return self.b[0] * u
        y, zf = scipy_signal().lfilter(self.b, self.a, u, zi=np.asarray(self.state))
        self.state = [float(x) for x in zf]
        return y
