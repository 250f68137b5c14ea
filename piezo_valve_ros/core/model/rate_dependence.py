"""Rate-dependent hysteresis: the play operators' thresholds widen with the input rate, and the exact inverse.

The rate-dependent Prandtl-Ishlinskii model of Al Janaideh and Krejci has thresholds that are functions
of the input rate.  Ours widens every threshold by the same amount::

    r_j(t) = r_j + w(t),    w(t) = sum_{f,k} c_{f,k} rho_f(t) / (rho_f(t) + s_k)     [V]

with ``rho_f`` the input rate |dv/dt| (backward difference, V/s) through the zero-order-hold lag of time
constant ``f`` (``RATE_FILTERS_S``: cycling rates over three memories, not the slope inside a 2 ms ramp)
and the scales ``s_k`` of ``RATE_SCALES_V_S`` (linear at low rates, levelling off).  The ZOH lag makes
``rho`` at sample k depend on the inputs up to k - 1 only, so ``w`` is known before the sample's input
is chosen: at every sample the model is the GPIM with thresholds ``r + w``.  Its inverse is of the same
family: at every sample the inverse of that GPIM (:class:`RateDependentInverseGPIM`, each step solved on
the piece of the output's piecewise polynomial that reaches the demand), exact to rounding.

:func:`rate_terms` (batch, for fitting) and :class:`RateWidening` (streaming, for the controller and the
model valve) compute the same ``w``.  No ROS import.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from .drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V
from .dynamics import scipy_signal
from .hysteresis import GPIM, MonotoneInverseGPIM, PlayOperatorBank, inverse_gpim

__all__ = ["RATE_FILTERS_S", "RATE_SCALES_V_S", "TERM_COUNT", "EARLIER_TERM_COUNT", "MAX_WIDENING_V", "rate_terms", "RateWidening",
           "RateDependentInverseGPIM", "RateDependentGPIMStream", "hysteresis_stream", "hysteresis_inverse",
           "solved_each_step", "describe_inverse", "swap_inverse", "take_over_state", "widening_problems"]

RATE_FILTERS_S = (0.02, 0.1, 0.005)      # the input rate |dv/dt| through first-order lags of these [s] (the 5 ms
                                         # one last: it came last, and earlier files' coefficients keep their place)
RATE_SCALES_V_S = (10.0, 100.0, 1000.0)  # ... widens the thresholds by sum c rho / (rho + s_k), for each lag
TERM_COUNT = len(RATE_FILTERS_S) * len(RATE_SCALES_V_S)   # coefficients c, filter-major: (f0 s0, f0 s1, ...)
EARLIER_TERM_COUNT = 2 * len(RATE_SCALES_V_S)             # parameters files before the 5 ms filter: its terms are 0
MAX_WIDENING_V = 20.0  # |c| at most [V] (rho / (rho + 1000 V/s) is still linear at 350 V/s)


def _lag_pole(tau_s: float, dt: float) -> float:
    return math.exp(-dt / tau_s)


def rate_terms(v: np.ndarray, dt: float, v_before: Optional[float] = None) -> np.ndarray:
    """(N, TERM_COUNT) functions of the input rate the thresholds grow with, ``rho_f / (rho_f + s_k)``.

    v: inputs [V] (N,), one per ``dt`` [s]; v_before: the input before ``v[0]`` (default ``v[0]``: at rest).
    Column order filter-major, as the coefficients.  Row k depends on ``v[:k]`` only.
    """
    v = np.asarray(v, float)
    if v_before is None:
        v_before = float(v[0]) if v.size else 0.0
    rate = np.abs(np.diff(v, prepend=v_before)) / dt
    cols = []
    for tau in RATE_FILTERS_S:
        a = _lag_pole(tau, dt)
        rho = scipy_signal().lfilter([0.0, 1.0 - a], [1.0, -a], rate)   # rho_k = a rho_{k-1} + (1 - a) rate_{k-1}
        cols += [rho / (rho + s) for s in RATE_SCALES_V_S]
    return np.column_stack(cols)


def widening_problems(widening_v: Sequence[float]) -> list[str]:
    """Reasons ``widening_v`` is not a usable set of rate coefficients (empty: fine; () or all 0: none)."""
    c = tuple(widening_v)
    if not c:
        return []
    if len(c) != TERM_COUNT:
        return [f"rate widening needs {TERM_COUNT} coefficients ({len(RATE_FILTERS_S)} filters x "
                f"{len(RATE_SCALES_V_S)} scales; a parameters file may give the {EARLIER_TERM_COUNT} of the first two "
                f"filters) or none, got {len(c)}"]
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in c):
        return ["rate widening: non-finite coefficient"]
    if max(abs(x) for x in c) > MAX_WIDENING_V:
        return [f"rate widening: coefficients must lie within +-{MAX_WIDENING_V:g} V"]
    return []


class RateWidening:
    """Streaming ``w`` [V]: ``value`` is the widening for the next sample; ``advance(v)`` after each input.
    No array per sample (a few floats); the same numbers as :func:`rate_terms` on the same inputs."""

    def __init__(self, widening_v: Sequence[float], dt: float, v0: float = CENTRE_VOLTAGE_V):
        problems = widening_problems(widening_v)
        if problems:
            raise ValueError("; ".join(problems))
        self.coefficients = tuple(float(x) for x in widening_v) or (0.0,) * TERM_COUNT
        self.dt = float(dt)
        self._a = [_lag_pole(tau, self.dt) for tau in RATE_FILTERS_S]
        self._b = [1.0 - a for a in self._a]
        # (filter index, scale [V/s], coefficient [V]) of each non-zero term, filter-major
        self._terms = [(i, s, self.coefficients[i * len(RATE_SCALES_V_S) + k])
                       for i in range(len(RATE_FILTERS_S)) for k, s in enumerate(RATE_SCALES_V_S)
                       if self.coefficients[i * len(RATE_SCALES_V_S) + k]]
        self.reset(v0)

    def reset(self, v0: float) -> None:
        """At rest at input ``v0`` [V]."""
        self.rho = [0.0] * len(self._a)
        self._last_v = float(v0)
        self.value = self._widening()

    def _widening(self) -> float:
        rho = self.rho
        return sum([c * (rho[i] / (rho[i] + s)) for i, s, c in self._terms])

    def advance(self, v: float) -> float:
        """Take the input [V] applied this sample; returns the widening [V] for the next one."""
        rate = abs(v - self._last_v) / self.dt
        self.rho = [b * rate + a * rho for a, b, rho in zip(self._a, self._b, self.rho)]
        self._last_v = float(v)
        self.value = self._widening()
        return self.value

    def state(self) -> tuple:
        """(filtered rates [V/s], last input [V]): the rate history."""
        return (tuple(self.rho), self._last_v)

    def set_state(self, state: tuple) -> None:
        rho, self._last_v = state
        self.rho = list(rho)
        self.value = self._widening()



class RateDependentGPIMStream:
    """The rate-dependent GPIM forwards, one input [V] per ``dt`` -> output [um] (allocation-free ``step``)."""

    def __init__(self, model: GPIM, widening_v: Sequence[float], dt: float, v0: float = CENTRE_VOLTAGE_V):
        self.model = model
        self.rate = RateWidening(widening_v, dt, v0)
        self.bank = PlayOperatorBank(model.thresholds, model.virgin_state(v0))

    def step(self, v: float) -> float:
        m, w = self.model, self.rate.value
        z = self.bank.step(m.ascending_envelope(v) - w, m.descending_envelope(v) + w)
        self.rate.advance(v)
        return float(m.weights @ z) + m.offset_um

    @property
    def state(self) -> np.ndarray:
        return self.bank.state


def hysteresis_stream(model: GPIM, widening_v: Sequence[float], dt: float, v0: float = CENTRE_VOLTAGE_V):
    """The model forwards per sample, virgin at ``v0`` [V]: ``GPIM.stream`` or :class:`RateDependentGPIMStream`."""
    if not any(widening_v):
        return model.stream(v0=v0)
    return RateDependentGPIMStream(model, widening_v, dt, v0)


class RateDependentInverseGPIM(MonotoneInverseGPIM):
    """Exact inverse of the rate-dependent GPIM (``model`` with every threshold widened by ``w``, the
    :class:`RateWidening` of ``widening_v`` on this inverse's own outputs).

    ``w`` for the next sample is known from the inputs so far, so each step is the inverse of the GPIM with
    thresholds ``r + w``: the per-step solve of :class:`hysteresis.MonotoneInverseGPIM` (whose output rises
    with the input from any state for any uniform shift of the thresholds: the operators that follow are
    still a prefix of the bank).  forward(inverse(y)) = y to rounding; inputs within ``v_min..v_max`` [V].
    Same interface as the other inverses; ``rate`` holds the rate history.

    ``follow``: another rate-dependent inverse whose widening this one uses (the one it applied in its last
    step) instead of computing it from its own outputs.  The controller's in-loop inverse follows the
    feedforward's: the widening was identified on the cycling rate of smooth drives, and a feedback
    command's sample-to-sample rate is mostly sensor noise (rectified by |dv/dt|, it would widen the
    thresholds for nothing: PID HC's error doubled on the rate-dependent valve).
    """

    def __init__(self, model: GPIM, widening_v: Sequence[float], dt: float,
                 forward_state: Optional[np.ndarray] = None, v0: float = CENTRE_VOLTAGE_V,
                 v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V,
                 follow: Optional["RateDependentInverseGPIM"] = None):
        self.rate = RateWidening(widening_v, dt, v0)
        self.follow = follow
        super().__init__(model, forward_state, v0, v_min, v_max)
        self.applied_widening_v = self.rate.value   # the widening the present state was reached with
        self._use_widening()

    def _use_widening(self, w: Optional[float] = None) -> None:
        """Thresholds for the next step: r + w (default: this inverse's own widening)."""
        w = self.rate.value if w is None else w
        # the state stays what the last step left only in a band at least as wide, where no bounds cross (a
        # crossed operator sits on its upper bound, which moves with w)
        self._consistent = (self._consistent and w >= self.applied_widening_v and self._dead_band
                            and self._base_list[0] + self.applied_widening_v >= 0.0)
        self._shift = w

    def step(self, y_um: float) -> float:
        follow = self.follow
        if follow is not None:
            self._use_widening(follow.applied_widening_v)
        v = super().step(y_um)
        if follow is not None:   # a follower's own rate history is never used: it keeps the widening it was just
            self.applied_widening_v = follow.applied_widening_v   # given until the next step (what peeks see)
            self._use_widening(self.applied_widening_v)
        else:
            self.applied_widening_v = self.rate.value
            self.rate.advance(v)
            self._use_widening()
        return v

    def reset(self, v0: float = CENTRE_VOLTAGE_V) -> None:
        """Virgin state at ``v0`` [V], at rest (no rate history)."""
        self.rate.reset(v0)
        self.applied_widening_v = self.rate.value
        self._use_widening()
        super().reset(v0)

    def set_rate_state(self, state: tuple, applied_widening_v: Optional[float] = None) -> None:
        """Take over a rate history (``RateWidening.state``)."""
        self.rate.set_state(state)
        self.applied_widening_v = self.rate.value if applied_widening_v is None else float(applied_widening_v)
        self._use_widening(self.applied_widening_v if self.follow is not None else None)

    def with_model(self, model: GPIM, v_now: float):
        return swap_inverse(self, model, self.rate.coefficients, self.rate.dt, v_now, self.v_min, self.v_max,
                            self.follow)


def hysteresis_inverse(model: GPIM, widening_v: Sequence[float], dt: float,
                       forward_state: Optional[np.ndarray] = None, v0: float = CENTRE_VOLTAGE_V,
                       v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V, follow=None):
    """The exact inverse of ``model`` with rate widening ``widening_v`` [V] (none: ``()`` or all 0) sampled
    every ``dt`` [s]: :func:`hysteresis.inverse_gpim` without widening, else :class:`RateDependentInverseGPIM`
    (``follow``: see there)."""
    if not any(widening_v):
        return inverse_gpim(model, forward_state, v0, v_min, v_max)
    return RateDependentInverseGPIM(model, widening_v, dt, forward_state, v0, v_min, v_max,
                                    follow if isinstance(follow, RateDependentInverseGPIM) else None)


def _applied_widening(inverse) -> float:
    return float(getattr(inverse, "applied_widening_v", 0.0))


def swap_inverse(old, model: GPIM, widening_v: Sequence[float], dt: float, v_now: float,
                 v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V, follow=None):
    """A new inverse of ``model`` (widening ``widening_v``) that keeps ``old``'s loop memory: its operator
    states mapped onto the new thresholds at the input ``v_now`` [V] (``GPIM.retarget_state``, at the
    widening they were reached with) and its rate history, if it has one (a model without one starts its
    rates at rest).  The states are made consistent with the new thresholds at the widening the old states
    were reached with (so the same model swapped in changes nothing), or with none for a model without."""
    z = old.model.retarget_state(old.forward_state(), model, v_now, _applied_widening(old) if any(widening_v) else 0.0)
    new = hysteresis_inverse(model, widening_v, dt, z, v_now, v_min, v_max, follow)
    if isinstance(new, RateDependentInverseGPIM) and isinstance(old, RateDependentInverseGPIM):
        new.set_rate_state(old.rate.state(), old.applied_widening_v)
    return new


def take_over_state(target, source, v_now: float) -> None:
    """``target`` (an inverse of the same model) takes over ``source``'s operator states and rate history."""
    target.set_forward_state(source.forward_state(), v_now)
    if isinstance(target, RateDependentInverseGPIM) and isinstance(source, RateDependentInverseGPIM):
        target.set_rate_state(source.rate.state(), source.applied_widening_v)


def solved_each_step(inverse) -> bool:
    """True for an inverse that solves every step (crossing envelopes, rate dependence): tens of microseconds
    per step where the closed form takes a few (``bench/core_speed.py``)."""
    return isinstance(inverse, MonotoneInverseGPIM)


def describe_inverse(inverse) -> str:
    """One line for logs: which inverse runs."""
    if isinstance(inverse, RateDependentInverseGPIM):
        return "rate-dependent GPIM inverse, solved each step"
    if isinstance(inverse, MonotoneInverseGPIM):
        return "GPIM inverse with crossing envelopes, solved each step"
    return "GPIM inverse in closed form"
