"""What the controller compensates, as one model with one parameter schema.

The identified valve model (``valve_model.ValveModel``) is ``y = G(s)[S]`` with the static part
``S = M(H) + sum_i g_i (lag_i[H] - H)`` (H: the GPIM's output, M: the saturation map, the sum: creep).
The controller inverts it along the feedforward path::

    y_ref --backlash inverse--> --W(s) = F(s)/G(s)--> S_ref --creep and M inverse--> H_ref --inverse GPIM--> v

* the backlash inverse (``terms.backlash.PlayInverse``): the clearance added in the direction the reference
  moves (the model's play after G, ``y = P_r(G[S])``);
* ``W`` (``feedforward.dynamics``): G's poles cancelled and replaced by the critically damped F
  (:class:`DynamicFeedforward`); off, W = 1 (the paper's OL HC).  FF PID G then shapes the
  feedback's reference with F instead of G (the response the feedforward aims at);
* the creep and saturation inverse (:class:`StaticInverse`) is exact: the creep lags depend on past H
  only, so each period solves the monotone scalar equation ``M(H) - sum g_i H = S_ref - sum g_i l_i``;
* the inverse GPIM (``hysteresis.inverse_gpim``): symmetric or asymmetric, with thresholds that widen with
  the input rate when ``rate_widening_v`` is set (``rate_dependence.hysteresis_inverse``).

``CompensationModel`` holds all of it; ``to_parameters``/``from_parameters`` are the one place its
``valve_controller`` parameters are written and read, ``problems`` validates it as a whole.  What it
cannot represent (drift) the identification refuses with a reason
(``identify.compensation``).  No ROS import.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from ..defaults import CONTROL_PERIOD_S
from ..model.drive import COMMAND_MAX_V, COMMAND_MIN_V
from ..model.dynamics import PAPER_VALVE_MODEL, ContinuousTF, DiscreteFilter, sections
from ..model.hysteresis import GPIM, PAPER_GPIM, GPIMParams, inverse_problems
from ..model.output_map import OutputMap
from ..model.rate_dependence import widening_problems
from ..validation import as_float, as_float_list, as_int
from . import terms as _terms
from .terms.creep import MAX_CREEP_GAIN_SUM, CreepModel

__all__ = ["CreepModel", "OutputMap", "DynamicFeedforward", "CompensationModel", "StaticInverse", "reference_filters",
           "MODEL_PARAMETERS", "GPIM_FORM_KEYS", "FF_BANDWIDTH_RATIO", "FF_NYQUIST_SHARE", "MAX_CREEP_GAIN_SUM"]

FF_BANDWIDTH_RATIO = 3.0     # F's poles this factor above each of G's sections ...
FF_NYQUIST_SHARE = 0.5       # ... and at most this share of the Nyquist frequency pi/dt
GPIM_FORM_KEYS = ("alpha", "rho", "tau", "n")   # the paper's 5-parameter form (with a0, a1, offset_um)
FITTED_RANGE_MARGIN = 0.25   # commands may go this share of the fitted span beyond the voltages a model was fitted on
MIN_FITTED_SPAN_SHARE = 0.25  # ... and must span at least this share of them (else: another amplifier's model)


class StaticInverse:
    """Exact streaming inverse of creep and the saturation map: demand S [um] -> hysteresis demand H [um].

    The ZOH lags depend only on past outputs (``l_k = a l_{k-1} + (1 - a) H_{k-1}``), so ``H_k`` solves
    ``M(H) - g H = S_k - sum_i g_i l_i,k`` (g = sum g_i), which rises in H wherever ``CompensationModel``
    checked it (``OutputMap.solve`` from the last H).  H stays within ``bounds`` [um] (the GPIM's output
    range: what the valve can deliver, and what the creep lags then follow).
    """

    def __init__(self, creep: CreepModel, output_map: OutputMap, dt: float, h0: float = 0.0,
                 bounds: tuple[float, float] = (-math.inf, math.inf)):
        problems = creep.problems() + output_map.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self._a = [math.exp(-dt / tau) for tau in creep.time_constants_s]
        self._g = [float(g) for g in creep.gains]
        self._gsum = float(sum(self._g))
        self._map = output_map
        self._plain = not output_map.active
        self.bounds = bounds
        self.reset(h0)

    def reset(self, h0: float) -> None:
        self._lags = [float(h0)] * len(self._a)
        self._last_h = float(h0)

    @property
    def last_h(self) -> float:
        return self._last_h

    def forward(self, h: float) -> float:
        """S for hysteresis output ``h`` now, without advancing (the lags as they are)."""
        acc = 0.0
        for a, g, lag in zip(self._a, self._g, self._lags):
            acc += g * (a * lag + (1.0 - a) * self._last_h)
        return self._map.value(h) - self._gsum * h + acc

    def step(self, demand_um: float) -> float:
        lags, a, g = self._lags, self._a, self._g
        acc = 0.0
        for i in range(len(a)):
            lags[i] = a[i] * lags[i] + (1.0 - a[i]) * self._last_h
            acc += g[i] * lags[i]
        lo, hi = self.bounds
        if self._plain:
            h = min(max((demand_um - acc) / (1.0 - self._gsum), lo), hi)
        else:
            h = self._map.solve(demand_um - acc, self._last_h, self._gsum, lo, hi)
        self._last_h = h
        return h


@dataclass(frozen=True)
class DynamicFeedforward:
    """``W(s) = F(s) / G(s)``: G's poles cancelled and replaced by critically damped pairs, one per second-order
    section (omega_i, zeta_i) of G, at ``omega_f = min(FF_BANDWIDTH_RATIO * omega_i, FF_NYQUIST_SHARE * pi/dt)``.

    Why this F: critically damped poles give a response without overshoot to steps in the demand; the
    ratio 3 cuts G's lag (2 zeta / omega per section) to 2 / (3 omega), with the high-frequency gain of W at
    most 9 per section (a demand's fast changes reach the command at most 9-fold, then the command range
    clamps); the Nyquist share keeps F's poles where the sampled W still behaves like the continuous one.
    Needs an all-pole G (unity DC gain, no zeros), as identification fits it.
    """

    valve_model: ContinuousTF
    dt: float

    def problems(self) -> list[str]:
        out = self.valve_model.problems()
        if out:
            return out
        if len(np.trim_zeros(np.asarray(self.valve_model.num, float), "f")) != 1:
            out.append("feedforward.dynamics needs a G_v without zeros (numerator a constant)")
        elif not math.isclose(self.valve_model.num[-1], self.valve_model.den[-1], rel_tol=1e-6):
            out.append("feedforward.dynamics needs a G_v of unity DC gain")
        return out

    def filter_poles(self) -> list[float]:
        """F's double poles omega_f [rad/s], one per section of G."""
        cap = FF_NYQUIST_SHARE * math.pi / self.dt
        return [min(FF_BANDWIDTH_RATIO * w, cap) for w, _ in sections(self.valve_model)]

    def target(self) -> ContinuousTF:
        """F(s): the response the feedforward aims at (unity DC gain)."""
        num, den = np.array([1.0]), np.array([1.0])
        for wf in self.filter_poles():
            num, den = np.polymul(num, [wf * wf]), np.polymul(den, [1.0, 2.0 * wf, wf * wf])
        return ContinuousTF(tuple(float(x) for x in num), tuple(float(x) for x in den))

    def inverse(self) -> ContinuousTF:
        """W(s) = F(s) / G(s), biproper."""
        f, g = self.target(), self.valve_model
        num = np.polymul(f.num, g.den) / g.num[-1]
        return ContinuousTF(tuple(float(x) for x in num), tuple(float(x) for x in f.den))

    def filters(self) -> tuple[DiscreteFilter, DiscreteFilter]:
        """(W, F) as the controller runs them every ``dt``, designed on the *sampled* plant.

        Sampling W and F separately (W_d G_d != F_d) overshoots: W's fast transient held over each period
        carries more than the continuous one, 8.6 % on the paper's 2 ms step at 10 kHz.  Instead, with the
        zero-order-hold valve ``G_d = z^-1 B(z) / A(z)`` and F's sampled step ``F_d = z^-1 F'(z)``:
        ``W = F' A / B(1)``, so that ``W G_d = F_d B(z) / B(1)``: G_d's poles are cancelled, its sampling
        zeros (B's, near z = -1 for a second order, not invertible without ringing at Nyquist) are kept as
        a unity-gain FIR with positive taps, which adds no overshoot to F's.  Returned F is that product,
        what the valve's output follows."""
        g = self.valve_model.discretise(self.dt)
        f = self.target().discretise(self.dt)
        # both strictly proper, so their ZOH samples start with a zero tap: z^-1 taken out of G_d and F_d
        b_g, a_g, b_f = g.b[1:], g.a, f.b[1:]
        w = DiscreteFilter(np.convolve(b_f, a_g) / np.sum(b_g), f.a)
        return w, DiscreteFilter(np.convolve(f.b, b_g) / np.sum(b_g), f.a)   # (np.polymul drops the leading 0)


def reference_filters(model: "CompensationModel", dt: float) -> tuple[DiscreteFilter, Optional[DiscreteFilter]]:
    """The controller's filters on the demand, sampled every ``dt`` [s]: (ff_pid_g's shaping filter, the
    dynamic inverse W or None).  Shaping is G_v, or with the dynamic feedforward on F (what the valve follows
    through W), either one period late: the measurement the error compares with answers the previous
    command."""
    if model.dynamic_feedforward:
        w, f = DynamicFeedforward(model.valve_model, dt).filters()
    else:
        w, f = None, model.valve_model.discretise(dt)
    return DiscreteFilter(np.concatenate(([0.0], f.b)), f.a), w


def _asymmetric(descending: Optional[list[float]], a0: float, a1: float) -> bool:
    """A descending envelope that differs from the ascending one ([] and [a0, a1(, 0)] do not)."""
    if not descending:
        return False
    return descending[:2] != [a0, a1] or (len(descending) == 3 and descending[2] != 0.0)


def _floats(values) -> list[float]:
    return [float(x) for x in values]


def fitted_range_problems(fitted_range_v: tuple[float, ...], v_min: float, v_max: float) -> list[str]:
    """Why commands ``v_min..v_max`` [V] do not suit a model fitted on ``fitted_range_v`` = (lo, hi) [V] (empty:
    unknown, nothing checked): they go beyond it by more than FITTED_RANGE_MARGIN of its span, or span less
    than MIN_FITTED_SPAN_SHARE of it (a model of a +-150 V drive under a 0-10 V controller)."""
    if not fitted_range_v:
        return []
    if len(fitted_range_v) != 2 or not all(math.isfinite(x) for x in fitted_range_v) \
            or not fitted_range_v[0] < fitted_range_v[1]:
        return [f"model.fitted_range_v must be [lo, hi] with lo < hi (or [0, 0]: unknown), got {list(fitted_range_v)}"]
    lo, hi = fitted_range_v
    margin = FITTED_RANGE_MARGIN * (hi - lo)
    if v_min < lo - margin or v_max > hi + margin:
        return [f"the model was fitted on {lo:.4g}..{hi:.4g} V; commands {v_min:g}..{v_max:g} V go beyond it (more than "
                f"{FITTED_RANGE_MARGIN:g} of its span): limit command_min_v/command_max_v to "
                f"{lo - margin:.4g}..{hi + margin:.4g} V in the parameters file, or identify the valve on a record that "
                f"drives it across the range it will be commanded over"]
    if v_max - v_min < MIN_FITTED_SPAN_SHARE * (hi - lo):
        return [f"the model was fitted on {lo:.4g}..{hi:.4g} V, {(hi - lo) / (v_max - v_min):.3g}x the command range "
                f"{v_min:g}..{v_max:g} V: a model of another drive"]
    return []


def command_range_for(fitted_range_v: tuple[float, ...], v_min: float, v_max: float,
                      centre_v: float) -> Optional[tuple[float, float]]:
    """The part of the command range ``v_min..v_max`` [V] a model fitted on ``fitted_range_v`` = (lo, hi) may
    command (``fitted_range_problems``: at most FITTED_RANGE_MARGIN of its span beyond it): the range itself when
    it suits the model, a narrower one when the model knows only part of it, None when that part leaves out the
    centre voltage ``centre_v`` (too narrow a record to control the valve with)."""
    if not fitted_range_problems(fitted_range_v, v_min, v_max):
        return v_min, v_max
    lo, hi = fitted_range_v
    margin = FITTED_RANGE_MARGIN * (hi - lo)
    narrowed = max(v_min, lo - margin), min(v_max, hi + margin)
    if not narrowed[0] <= centre_v <= narrowed[1] or fitted_range_problems(fitted_range_v, *narrowed):
        return None
    return narrowed


_CORE = ("gpim", "valve_model")   # CompensationModel's own fields; every other term's value is in its ``terms``


@dataclass(frozen=True, init=False)
class CompensationModel:
    """Everything ``valve_controller`` inverts: the GPIM, G_v and the value of every other term of ``TERMS`` by its
    field name (``terms``): thresholds widening with the input rate (``rate_widening_v`` [V], see
    ``rate_dependence``), creep, the saturation map (``output_map``), backlash on the spool's path, whether the
    feedforward inverts G_v too (``dynamic_feedforward``) and the voltages the model was fitted on
    (``fitted_range_v``).  Made as ``CompensationModel(gpim, valve_model, creep=..., backlash=...)``: a term not given
    takes its ``Term.default``; a name no term has is a TypeError.  Each term's value reads as an attribute
    (``model.creep``) or ``model.terms[name]``.  Units: V, um, s."""

    gpim: GPIM
    valve_model: ContinuousTF
    terms: dict

    def __init__(self, gpim: Optional[GPIM] = None, valve_model: ContinuousTF = PAPER_VALVE_MODEL,
                 terms: Optional[dict] = None, **values: Any):
        known = {t.field: t for t in _terms.TERMS if t.field not in _CORE}
        given = {**(terms or {}), **values}
        unknown = sorted(set(given) - set(known))
        if unknown:
            raise TypeError(f"CompensationModel has no term {', '.join(unknown)} (terms: {', '.join(known)})")
        object.__setattr__(self, "gpim", PAPER_GPIM.model() if gpim is None else gpim)
        object.__setattr__(self, "valve_model", valve_model)
        object.__setattr__(self, "terms", {name: given.get(name, t.default) for name, t in known.items()})

    def __getattr__(self, name: str) -> Any:   # a term's value by its field name (only called where no attribute is)
        terms = self.__dict__.get("terms")
        if terms is not None and name in terms:
            return terms[name]
        raise AttributeError(f"{type(self).__name__!s} has no attribute or term {name!r}")

    def value(self, field_name: str) -> Any:
        """A term's value (or the GPIM's, G_v's) by its field name."""
        return getattr(self, field_name) if field_name in _CORE else self.terms[field_name]

    @property
    def rate_dependent(self) -> bool:
        return any(c != 0.0 for c in self.rate_widening_v)

    def problems(self, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V, dt: Optional[float] = None
                 ) -> list[str]:
        """Every reason the controller cannot invert this model on commands ``v_min..v_max`` [V] (empty: fine);
        with ``dt`` also the dynamic feedforward's."""
        out = (inverse_problems(self.gpim, v_min, v_max) + self.valve_model.problems() + self.creep.problems()
               + widening_problems(self.rate_widening_v) + fitted_range_problems(self.fitted_range_v, v_min, v_max))
        map_problems = self.output_map.problems()
        span = math.inf
        if not out and not map_problems:
            lo, hi = self.gpim.output_range(v_min, v_max)
            map_problems = self.output_map.problems(lo, hi, floor=self.creep.gain_sum if self.creep.active else 0.0)
            span = hi - lo
        out += map_problems
        for term in _terms.TERMS:   # the terms that check themselves (those on the spool's path)
            if term.problems is not None:
                out += term.problems(self.terms[term.field], span)
        if self.dynamic_feedforward and not self.valve_model.problems():
            out += DynamicFeedforward(self.valve_model, CONTROL_PERIOD_S if dt is None else dt).problems()
        return out

    # ------------------------------------------------------------------ the parameter schema
    def to_parameters(self) -> dict[str, Any]:
        """``valve_controller`` parameters (name -> value); every model parameter is written, so applying them
        replaces a whole older model.  The GPIM's here, each other term's by its own module (``terms``)."""
        g = self.gpim
        b = [float(g.a0), float(g.a1), 0.0] if g.symmetric else [float(g.b0), float(g.b1), float(g.b2)]
        out: dict[str, Any] = {"gpim.thresholds": _floats(g.thresholds), "gpim.weights": _floats(g.weights),
                               "gpim.a0": float(g.a0), "gpim.a1": float(g.a1), "gpim.offset_um": float(g.offset_um),
                               "gpim.descending_envelope": b}
        for term in _terms.TERMS:
            out.update(term.write(self.value(term.field)))
        return out

    @classmethod
    def from_parameters(cls, p: dict[str, Any], v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V,
                        dt: Optional[float] = None) -> "CompensationModel":
        """The model from ``valve_controller`` parameters (names as in MODEL_PARAMETERS; the GPIM in free form
        when ``gpim.thresholds``/``gpim.weights`` are set, else the paper's 5-parameter form); raises
        ValueError with every problem found, the whole model checked (see ``problems``)."""
        problems: list[str] = []

        def get(name, conv):
            try:
                return conv(name, p[name] if name in p else MODEL_DEFAULTS[name])
            except ValueError as exc:
                problems.append(str(exc))
                return None

        thresholds, weights = get("gpim.thresholds", as_float_list), get("gpim.weights", as_float_list)
        a0, a1, offset = get("gpim.a0", as_float), get("gpim.a1", as_float), get("gpim.offset_um", as_float)
        descending = get("gpim.descending_envelope", as_float_list)
        gpim = None
        if not problems:
            try:
                if descending is not None and len(descending) not in (0, 2, 3):
                    raise ValueError(f"gpim.descending_envelope must be [] or [b0, b1] or [b0, b1, b2], "
                                     f"got {descending}")
                if thresholds or weights:  # free form (e.g. from the identification's linear fit)
                    gpim = GPIM(thresholds, weights, a0, a1, offset)
                else:
                    form = {k: get(f"gpim.{k}", as_int if k == "n" else as_float) for k in GPIM_FORM_KEYS}
                    if not problems:
                        gpim = GPIMParams(a0=a0, a1=a1, offset_um=offset, **form).model()
                if gpim is not None and _asymmetric(descending, a0, a1):
                    gpim = GPIM(gpim.thresholds, gpim.weights, a0, a1, offset, *descending)
            except ValueError as exc:
                problems.append(str(exc))
        values = {term.field: term.read(get) for term in _terms.TERMS}   # each term reads its own parameters
        if problems:
            raise ValueError("; ".join(problems))
        model = cls(gpim, **values)
        problems = model.problems(v_min, v_max, dt)
        if problems:
            raise ValueError("; ".join(problems))
        return model


_PAPER = PAPER_GPIM
# name -> (default, description): the controller declares these; from_parameters reads them.  The GPIM's here, then
# each other term's from its own module (``terms``)
MODEL_PARAMETERS: dict[str, tuple[Any, str]] = {
    "gpim.a0": (_PAPER.a0, "envelope slope [1]"),
    "gpim.a1": (_PAPER.a1, "envelope offset [V]"),
    "gpim.alpha": (_PAPER.alpha, "threshold spacing [V]"),
    "gpim.rho": (_PAPER.rho, "weight scale [um/V]"),
    "gpim.tau": (_PAPER.tau, "weight decay [1/V]"),
    "gpim.n": (_PAPER.n, "number of operators"),
    "gpim.offset_um": (_PAPER.offset_um, "output offset [um]"),
    "gpim.thresholds": ([], "free-form thresholds [V] (empty: 5-parameter form)"),
    "gpim.weights": ([], "free-form weights [um/V] (empty: 5-parameter form)"),
    "gpim.descending_envelope": ([], "asymmetric GPIM: descending envelope [b0, b1] or [b0, b1, b2] (b0 v + b1 + "
                                     "b2 v^2, at or above the ascending one on the command range; empty or equal "
                                     "to [a0, a1]: the ascending one)"),
    **{name: entry for term in _terms.TERMS for name, entry in term.parameters.items()},
}
MODEL_DEFAULTS = {name: default for name, (default, _) in MODEL_PARAMETERS.items()}
