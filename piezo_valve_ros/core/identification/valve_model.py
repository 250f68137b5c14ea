"""The identified valve model: the paper's structure, hysteresis followed by linear dynamics.

    S = H(v) + sum_effects terms(H, v, t) @ coefs        static part [um]
    y = G(s)[S]                                          G unity DC gain (the paper's G_v: second order)

``H`` is a GPIM in the linear form (input V, a0 = 1, a1 = 0, free weights on fixed thresholds, an
output offset); effects may switch on a separate descending envelope (asymmetry), thresholds that
widen with the input rate (rate-dependent hysteresis) or a higher-order G (extra poles).  The model
runs on a raw record (G discretised with a zero-order hold, exactly as a DAQ applies its samples) or on
block means (first-order hold plus the source's half-sample delay).  Nothing here imports ROS.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Optional, Protocol, Sequence

import numpy as np

from ..model.dynamics import (PAPER_SECTION, ContinuousTF, describe_dynamics, scipy_signal,
                              steady_state, unity_dc_poles)
from ..model.at_rest import discretised, filter_at_rest, filter_rows_at_rest
from ..model.iir import filter_columns
from ..model.hysteresis import GPIM, contact_sensitivity, last_contact, play_batch
from .records import Record

__all__ = ["ValveModel", "Context", "ModelTerm", "discretise_for", "INITIAL_STATES",
           "InitialState", "REST"]

class ModelTerm(Protocol):
    """What a model asks of an effect term (``effects.base.Effect`` is one): its name, its columns on a record
    (N, k), the columns' values at rest before it (k,), and a description of its coefficients."""

    name: str
    after_dynamics: int

    def columns(self, ctx: "Context") -> np.ndarray: ...

    def output(self, x: np.ndarray, coefs: np.ndarray) -> np.ndarray: ...

    def rest_columns(self, ctx: "Context", columns: np.ndarray) -> np.ndarray: ...

    def describe(self, model: "ValveModel", coefs: np.ndarray) -> dict: ...


INITIAL_STATES = ("rest", "cycled", "remanent", "given")   # kinds of the operators' state before a record


@dataclass(frozen=True)
class InitialState:
    """The operators' state at a record's first sample, as the input path that left it there.

    kind:  "rest" (no history at the first voltage: a valve started from rest), "cycled" (the record's own
           range swept before it: a record cut from running operation), "remanent" (the input went from
           rest at ``turning_points_v[0]`` through the others to the record's first voltage: a valve left
           off its loop by an earlier excitation, e.g. the part of a record before its input wiped the
           unknown state out, see ``residual``) or "given" (the operators' states themselves, estimated for one
           model from the record's first rows: a session recorded after an excitation nobody recorded, see
           ``initial_state.session_start``)
    turning_points_v: [V], remanent only
    states_v: [V], given only: each operator's state at the first sample (the model's thresholds, in order)
    rest_output_um: given only: the static output [um] G had settled to before the first sample (None: the first
           sample's, G at rest there)
    """

    kind: str = "rest"
    turning_points_v: tuple[float, ...] = ()
    states_v: tuple[float, ...] = ()
    rest_output_um: Optional[float] = None

    def __post_init__(self):
        if self.kind not in INITIAL_STATES:
            raise ValueError(f"initial state must be one of {INITIAL_STATES}, got {self.kind!r}")
        if (self.kind == "remanent") != bool(self.turning_points_v):
            raise ValueError("turning points are given for a remanent initial state, and only for it")
        if (self.kind == "given") != bool(self.states_v) or (self.rest_output_um is not None and self.kind != "given"):
            raise ValueError("operator states (and a rest output) are given for a given initial state, and only for it")
        object.__setattr__(self, "turning_points_v", tuple(float(x) for x in self.turning_points_v))
        object.__setattr__(self, "states_v", tuple(float(x) for x in self.states_v))

    @property
    def rested_at_v(self) -> Optional[float]:
        """The voltage [V] the valve rested at until the record's first sample moved it (a remanent state
        with one turning point: e.g. a closed-loop record whose controller's first command left the rest
        voltage); None when it rested at the first voltage.  G then starts at rest at that voltage's output."""
        return self.turning_points_v[0] if self.kind == "remanent" and len(self.turning_points_v) == 1 else None

    def states(self, gpim: GPIM, v: np.ndarray) -> np.ndarray:
        """Operator states (n,) at ``v[0]`` for the record whose input is ``v`` [V]."""
        if self.kind == "cycled":
            return gpim.cycled_state(v)
        if self.kind == "remanent":
            return gpim.state_after(self.turning_points_v + (float(v[0]),))
        if self.kind == "given":
            if len(self.states_v) != gpim.n:
                raise ValueError(f"{len(self.states_v)} operator states given for a GPIM of {gpim.n} operators")
            return np.asarray(self.states_v, float)
        return gpim.virgin_state(float(v[0]))

    def describe(self) -> str:
        if self.kind == "given":
            return (f"estimated ({len(self.states_v)} operator states at the first sample" +
                    (f", G settled at {self.rest_output_um:.4g} um before it)" if self.rest_output_um is not None
                     else ")"))
        if self.kind == "remanent":
            tp = self.turning_points_v
            shown = " V to ".join(f"{x:.4g}" for x in tp) if len(tp) <= 6 else (
                f"{tp[0]:.4g} V through {len(tp) - 3} turning points to " + " V to ".join(f"{x:.4g}" for x in tp[-2:]))
            return f"remanent (before the record the input went from rest at {shown} V, then to the first voltage)"
        return {"rest": "rest (no history at the first voltage)",
                "cycled": "cycled (the record's own range swept before it)"}[self.kind]


REST = InitialState()


@dataclass(frozen=True)
class ValveModel:
    """GPIM (linear form) -> effect terms -> G(s).  Units: V in, um out, s.

    gpim:      thresholds [V], weights [um/V], offset [um]; b0/b1 set when the envelopes differ
    sections:  G(s) as unity-DC-gain second-order sections (omega [rad/s], zeta); the first is G_v's own
               (the paper's, or fitted: ``dynamics_note`` says which), more come with extra poles
    rate_widening_v: thresholds grow with the input rate by ``sum c rho_f / (rho_f + RATE_SCALES_V_S[k])``
               [V], rho_f = |dv/dt| through each lag of RATE_FILTERS_S (linear at low rates, levelling off)
    effects:   the effects added, each with its coefficients (possibly none: its structure is nonlinear)
    t0:        record time [s] from which drift terms count
    dynamics_note, dynamics_free: where G's poles came from, and whether refits may move them
    delay_s:   a transport delay [s] after G, in whole and fractional samples (``discretise_for``)
    history:   the operators' state at a record's first sample (``InitialState``; a kind's name is accepted)
    """

    gpim: GPIM
    sections: tuple[tuple[float, float], ...] = (PAPER_SECTION,)
    rate_widening_v: tuple[float, ...] = ()
    effects: tuple[ModelTerm, ...] = ()
    coefs: tuple[np.ndarray, ...] = ()
    t0: float = 0.0
    dynamics_note: str = "paper"
    dynamics_free: bool = True   # the record determines G_v's poles (refits may move them)
    history: InitialState = REST
    delay_s: float = 0.0         # transport delay between drive and sensor after G [s] (the dynamics effect's)

    def __post_init__(self):
        if isinstance(self.history, str):
            object.__setattr__(self, "history", InitialState(self.history))

    @property
    def dynamics(self) -> ContinuousTF:
        """G(s): the product of the unity-DC-gain sections."""
        return unity_dc_poles(list(self.sections))

    @property
    def name(self) -> str:
        return "+".join(["gpim", "G_v"] + [e.name for e in self.effects])

    @property
    def effect_names(self) -> list[str]:
        return [e.name for e in self.effects]

    def term(self, name: str) -> Optional[tuple[ModelTerm, np.ndarray]]:
        for e, c in zip(self.effects, self.coefs):
            if e.name == name:
                return e, c
        return None

    def context(self, record: Record, t0: Optional[float] = None, shared: Optional[dict] = None) -> "Context":
        """The evaluation context on ``record``; ``shared`` holds structural values of an earlier context of the
        same record and hysteresis structure (``structure_key``)."""
        return Context(record, self, self.t0 if t0 is None else t0, {} if shared is None else shared)

    @property
    def structure_key(self) -> tuple:
        """What operator states depend on besides the input: thresholds, envelopes, rate widening, history."""
        g = self.gpim
        return (g.thresholds.tobytes(), g.a0, g.a1, g.b0, g.b1, g.b2, tuple(self.rate_widening_v), self.history)

    def static_output(self, ctx: "Context") -> np.ndarray:
        """S = H + effect terms [um] (before G)."""
        return self.static_output_and_rest(ctx)[0]

    def static_output_and_rest(self, ctx: "Context") -> tuple[np.ndarray, Optional[float]]:
        """(S (N,), S while the valve rested before the record [um], or None where it rested at the first
        voltage): G's input and the value it had settled to (``Context.through_dynamics``)."""
        static = ctx.H.copy()
        rest = ctx.H_before if ctx.rest_states is not None else None
        for e, c in zip(self.effects, self.coefs):
            if c.size and not e.after_dynamics:
                columns = e.columns(ctx)
                static += columns @ c
                if rest is not None:
                    rest += float(e.rest_columns(ctx, columns) @ c)
        if self.history.rest_output_um is not None:   # estimated as the whole static output before the record
            rest = self.history.rest_output_um
        return static, rest

    def predict(self, record: Record, t0: Optional[float] = None) -> np.ndarray:
        """Position [um] for the record's voltages (operators in the ``history`` state; G at rest at the first
        sample, or before it where the valve rested at another voltage)."""
        ctx = self.context(record, t0)
        return self.after_dynamics(ctx.through_dynamics(*self.static_output_and_rest(ctx)))

    def after_dynamics(self, x: np.ndarray) -> np.ndarray:
        """The position [um] for G's output ``x`` [um]: the output maps of effects on the spool's path after G."""
        for e, c in zip(self.effects, self.coefs):
            if e.after_dynamics:
                x = e.output(x, c)
        return x

    @property
    def output_maps(self) -> list[tuple[ModelTerm, np.ndarray]]:
        """The effects that act after G, with their coefficients."""
        return [(e, c) for e, c in zip(self.effects, self.coefs) if e.after_dynamics]

    def without(self, name: str) -> "ValveModel":
        keep = [(e, c) for e, c in zip(self.effects, self.coefs) if e.name != name]
        return replace(self, effects=tuple(e for e, _ in keep), coefs=tuple(c for _, c in keep))

    def describe(self) -> dict:
        g = self.gpim
        out = {"model": self.name,
               "gpim": {"thresholds": [float(x) for x in g.thresholds], "weights": [float(x) for x in g.weights],
                        "a0": g.a0, "a1": g.a1, "offset_um": g.offset_um},
               "G_v": describe_dynamics(self.dynamics, self.dynamics_note),
               "delay_s": self.delay_s,
               "initial_state": {"kind": self.history.kind, "turning_points_v": list(self.history.turning_points_v),
                                 "description": self.history.describe()}}
        if not g.symmetric:
            out["gpim"].update({"b0": g.b0, "b1": g.b1})
        if any(self.rate_widening_v):
            out["gpim"]["rate_widening_v"] = list(self.rate_widening_v)
        for e, c in zip(self.effects, self.coefs):
            out[e.name] = e.describe(self, c)
        return out


@dataclass
class Context:
    """One evaluation of a model on one record: drives, operator states, hysteresis output, filters.

    Built lazily: a prediction needs only ``H``; a fit needs the operator ``states`` and, for the
    nonlinear structures, the ``contacts`` (which bound each operator touched last, and when).
    """

    record: Record
    model: ValveModel
    t0: float
    _cache: dict = field(default_factory=dict, repr=False)  # structural values (see _structural)

    @property
    def v(self) -> np.ndarray:
        return self.record.voltage_v

    @cached_property
    def t(self) -> np.ndarray:
        """Time since the model's t0 [s]."""
        return self.record.time_s - self.t0

    @property
    def dt(self) -> float:
        return self.record.dt

    def _structural(self, name: str, compute):
        """A value that depends on the input and the hysteresis structure only (not on the weights), kept in
        ``_cache``, which contexts of the same record and structure may share (``fitting.FitCache``)."""
        if name not in self._cache:
            self._cache[name] = compute()
        return self._cache[name]

    @property
    def rate_terms(self) -> np.ndarray:
        """(N, k) functions of the input rate the thresholds grow with (``rate_dependence.rate_terms``: causal,
        the valve at rest before the first sample)."""
        return self._structural("rate_terms", lambda: self.record.input_rate_terms)

    @property
    def drives(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) drives of the operators: the envelopes, widened by the rate terms."""
        def compute():
            g, m = self.model.gpim, self.model
            lower = g.ascending_envelope(self.v)
            upper = lower if g.symmetric else g.descending_envelope(self.v)
            if any(m.rate_widening_v):
                w = self.rate_terms @ np.asarray(m.rate_widening_v)
                lower, upper = lower - w, upper + w
            return lower, upper
        return self._structural("drives", compute)

    @property
    def initial_state(self) -> np.ndarray:
        return self._structural("initial_state", lambda: self.model.history.states(self.model.gpim, self.v))

    @property
    def states(self) -> np.ndarray:
        """Operator states (N, n)."""
        def compute():
            lower, upper = self.drives
            return play_batch(lower, upper, self.model.gpim.thresholds, self.initial_state, compiled=True)[0]
        return self._structural("states", compute)

    @cached_property
    def H(self) -> np.ndarray:
        """Hysteresis output [um] (N,)."""
        g = self.model.gpim
        if "states" in self._cache:
            return self.states @ g.weights + g.offset_um
        lower, upper = self.drives
        h, _ = play_batch(lower, upper, g.thresholds, self.initial_state, g.weights, compiled=True)
        return h + g.offset_um

    @property
    def H_before(self) -> float:
        """Hysteresis output [um] while the valve rested before the record: at the rest voltage where it
        rested at another voltage than the first (``rest_states``), the settled output of an estimated start
        (``InitialState.rest_output_um``: slow effects, creep's lags, start at rest there too), else the first
        sample's."""
        if self.model.history.rest_output_um is not None:
            return float(self.model.history.rest_output_um)
        z = self.rest_states
        if z is None:
            return float(self.H[0])
        g = self.model.gpim
        return float(g.weights @ z + g.offset_um)

    @property
    def contacts(self) -> tuple[np.ndarray, np.ndarray]:
        """(side, index) of every operator's last contact, see :func:`hysteresis.last_contact`."""
        def compute():
            lower, upper = self.drives
            return last_contact(self.states, lower, upper, self.model.gpim.thresholds, compiled=True)
        return self._structural("contacts", compute)

    def bound_sensitivity(self, lower_change: Optional[np.ndarray], upper_change: Optional[np.ndarray]) -> np.ndarray:
        """dH [um] for a small change of the operators' lower / upper bounds (each (N,) or (N, k) in V, or None),
        exactly to first order: each operator moves by the change of the bound it touched last, at that time
        (:func:`hysteresis.contact_sensitivity`).  Returns (N,) or (N, k), a column per column of the changes."""
        side, index = self.contacts
        w = self.model.gpim.weights
        moved = [contact_sensitivity(side, index, w, change, bounds, compiled=True)
                 for change, bounds in ((lower_change, "lower"), (upper_change, "upper")) if change is not None]
        return sum(moved[1:], moved[0]) if moved else np.zeros(len(self.record))

    def widening_sensitivity(self, change: np.ndarray) -> np.ndarray:
        """dH [um] for the thresholds widened by ``change`` (N,) or (N, k) [V] (lower bounds down, upper bounds
        up by it): ``bound_sensitivity(-change, change)`` in one gather per column."""
        side, index = self.contacts
        return contact_sensitivity(side, index, self.model.gpim.weights, change, "both", compiled=True)

    # ------------------------------------------------------------------ the linear dynamics
    @cached_property
    def filter(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) of G on this record (``discretise_for``)."""
        return discretise_for(self.model.dynamics, self.record, self.model.delay_s)

    def through_dynamics(self, x: np.ndarray, rest=None) -> np.ndarray:
        """G(s) applied to x (N,) or to each column of x (N, k), at rest at the first sample, or at rest at
        ``rest`` (a value, or one per column) before it: G started from its steady state there (the same as
        adding (rest - x[0]) times G's free response, G being linear)."""
        return filter_at_rest(*self.filter, x, rest)

    def states_and_columns_through_dynamics(self, less: np.ndarray, blocks: Sequence[np.ndarray],
                                            rest: Optional[np.ndarray] = None) -> np.ndarray:
        """``through_dynamics(np.column_stack([states - less, *blocks]), rest)``, bit for bit, without the stacked
        copy nor its transpose: the operator states (N, n) less ``less`` (n,) and the columns of ``blocks`` (each
        (N, w); a block that is a transposed view of rows is copied as rows) through G, each at rest at its first
        sample or at ``rest`` (n + k,) before it; (N, n + k), a transposed view of one C-contiguous (n + k, N)
        array, as ``filter_at_rest`` returns."""
        b, a = self.filter
        states = self.states
        n, samples = states.shape[1], len(self.record)
        blocks = [np.asarray(block, float).reshape(samples, -1) for block in blocks]
        rows = np.empty((sum(block.shape[1] for block in blocks), samples))
        at = 0
        for block in blocks:
            rows[at:at + block.shape[1]] = block.T
            at += block.shape[1]
        rest = None if rest is None else np.asarray(rest, float).reshape(-1)
        start = (states[0] - less) if rest is None else rest[:n]
        out = np.empty((n + rows.shape[0], samples))
        filter_columns(b, a, states, less, start[:, None] * steady_state(b, a)[None, :], out[:n])
        filter_rows_at_rest(b, a, rows, None if rest is None else rest[n:], out[n:])
        return out.T

    @cached_property
    def free_response(self) -> np.ndarray:
        """(N,) G's output from rest at 1 with its input at 0 from the first sample on (1 - step response)."""
        b, a = self.filter
        return 1.0 - scipy_signal().lfilter(b, a, np.ones(len(self.record)))

    @property
    def rest_states(self) -> Optional[np.ndarray]:
        """Operator states (n,) while the valve rested before the record, where it rested at another voltage
        than the first (``InitialState.rested_at_v``); else None."""
        e = self.model.history.rested_at_v
        if e is None:
            return None
        return self._structural("rest_states", lambda: self.model.gpim.state_after((e,)))


def discretise_for(tf: ContinuousTF, record: Record, delay_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of G for this record: zero-order hold on raw samples (what a DAQ applies); on block means a
    first-order hold plus the source's half-sample delay, which reproduces the source's zero-order hold
    to 0.004 um RMS at 2 kHz block means of a 10 kHz record.  A transport delay ``delay_s`` [s] >= 0 follows
    as whole samples and a linear interpolation between two for the fraction (``delay_taps``).  The arrays are
    shared (read-only): an analysis asks for the same few G on a record thousands of times."""
    return discretised(tf, float(record.dt), record.block == 1, 0.5 * float(record.source_dt or 0.0),
                       float(delay_s))
