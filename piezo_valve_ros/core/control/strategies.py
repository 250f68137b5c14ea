"""The paper's six control strategies as one streaming controller.

Convention (paper.md): gains act on normalised units.  The PID's output is a
position-equivalent demand [um]; it becomes a voltage either through the inverse GPIM
(``pid_hc``) or through the nominal static gain k [um/V] about the centre voltage
(``pid``, ``ff_pid``, ``ff_pid_g``).

==========  ==========================================================
ol          v = v_c + y_ref / k
ol_hc       v = inverse(y_ref)
pid         v = v_c + PID(y_ref - y) / k
pid_hc      v = inverse(PID(y_ref - y))
ff_pid      v = inverse(y_ref) + PID(y_ref - y) / k
ff_pid_g    v = inverse(y_ref) + PID(G_v(y_ref) - y) / k
==========  ==========================================================

``inverse`` is the whole compensation model (``compensation.CompensationModel``): on the feedforward
path the dynamic inverse W = F/G_v when ``dynamic_feedforward`` is on (ff_pid_g then shapes with F
instead of G_v), the creep and saturation inverse, the inverse GPIM; in pid_hc's loop the saturation
inverse and the inverse GPIM (creep and dynamics are the feedback's there).  With rate-dependent thresholds
the inverses widen them as the model does (``rate_dependence``); pid_hc's in-loop inverse takes the
feedforward's widening (the demand's cycling rate), not one from its own noisy command.

The output is clamped to the command range with conditional-integration anti-windup: the integrator stops
while the command is on a limit and the error pushes further into it.  pid_hc's integrator holds the position
demand the inverse turns into volts (in steady state it is the demand plus what the model misses), so there
it may still move toward the demand on a limit, never past it nor past the loop's admissible range
(``_finish``): frozen where a large step first met the rail it would be tens of um short of the new demand
and the step would settle on a slow integrator tail; bounded by the demand it cannot wind up.
Switching strategy (or gains) is bumpless: the integrator absorbs the difference where the
new law has one, and any rest decays with ``bump_time_constant_s``.

Oscillation guard (cannot be switched off): a feedback loop whose commands hit both rails within
``GUARD_WINDOW_S``, or come onto a rail ``GUARD_ENTRIES`` times within ``GUARD_ENTRY_WINDOW_S`` (coming
away by ``GUARD_AWAY_SHARE`` of the range in between), is oscillating (a loop delay of two periods makes PID HC 5 at 1 kHz swing rail to
rail: a busy computer does that to a loop across processes).  The controller then runs on its
feedforward path alone (the inverse, OL HC, or OL for ``pid``), which needs no timing, with the
integrator frozen, for ``GUARD_HOLD_S`` (doubled while it recurs, up to ``GUARD_MAX_HOLD_S``), and
returns to feedback bumplessly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional


from ..defaults import CONTROL_PERIOD_S, PAPER_CONTROL_PERIOD_S
from .compensation import CompensationModel, StaticInverse, reference_filters
from . import terms as _terms
from ..model.hysteresis import GPIM, NotInvertibleError
from ..model.rate_dependence import hysteresis_inverse, swap_inverse, take_over_state
from ..model.drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V
from ..validation import POSITIVE, field_problems, ruled

__all__ = ["STRATEGIES", "REGISTRY", "Strategy", "NO_INVERSE", "FEEDFORWARD_INVERSE", "IN_LOOP_INVERSE", "PIDGains", "ControllerConfig", "ValveController", "TABLE1_GAINS", "gain_set",
           "SAFE_PERIOD_S", "default_gain_set", "NO_SAFE_SET_STRATEGY",
           "LOOP_SETTINGS", "loop_settings",
           "nominal_static_gain", "FEEDBACK_STRATEGIES", "has_feedback"]

NO_INVERSE, FEEDFORWARD_INVERSE, IN_LOOP_INVERSE = "none", "feedforward", "in_loop"   # where a law puts the inverse


@dataclass(frozen=True)
class Strategy:
    """One of the paper's control laws, as the controller, the tuner, the nodes and the benches ask for it."""

    name: str
    label: str                  # the paper's name
    inverse: str                # NO_INVERSE, FEEDFORWARD_INVERSE (the demand through it) or IN_LOOP_INVERSE (the
                                # PID's output through it)
    fallback: Optional[str]     # a feedback law: the feedforward law the oscillation guard holds it on; else None
    shaped_reference: bool = False   # the error is taken against the G_v-shaped reference (FF PID G)

    @property
    def feedback(self) -> bool:
        """Whether it closes a feedback loop (its PID gains are used, and tuned)."""
        return self.fallback is not None


REGISTRY: dict[str, Strategy] = {s.name: s for s in (
    Strategy("ol", "OL", NO_INVERSE, None),
    Strategy("ol_hc", "OL HC", FEEDFORWARD_INVERSE, None),
    Strategy("pid", "PID", NO_INVERSE, "ol"),
    Strategy("pid_hc", "PID HC", IN_LOOP_INVERSE, "ol_hc"),
    Strategy("ff_pid", "FF PID", FEEDFORWARD_INVERSE, "ol_hc"),
    Strategy("ff_pid_g", "FF PID G", FEEDFORWARD_INVERSE, "ol_hc", shaped_reference=True),
)}
STRATEGIES = tuple(REGISTRY)
FALLBACK_LAW = {s.name: s.fallback for s in REGISTRY.values() if s.feedback}   # feedback -> feedforward
FEEDBACK_STRATEGIES = tuple(FALLBACK_LAW)   # the strategies with a feedback loop: their gains are used (and tuned)
REFERENCE_CLAMP_SHARE = 0.05  # a reference this share of the reachable span outside it is clamped; further: refused
GUARD_WINDOW_S = 0.02     # commands on both rails within this long: the loop oscillates
GUARD_ENTRIES = 3         # ... and so does a command that comes onto a rail this often ...
GUARD_ENTRY_WINDOW_S = 0.05  # ... within this long (a lopsided limit cycle that reaches only one rail),
GUARD_AWAY_SHARE = 0.2    # ... having come away from the rails by this share of the range in between (not chatter)
GUARD_HOLD_S = 0.25       # ... and runs on feedforward alone this long
GUARD_MAX_HOLD_S = 4.0    # ... doubled each time it recurs within two holds of the last, up to this


@dataclass(frozen=True)
class PIDGains:
    """Normalised gains: kp [-], ki [1/s], kd [s]."""

    kp: float = 1.1987
    ki: float = 474.5090
    kd: float = 0.0

    def problems(self) -> list[str]:
        vals = (self.kp, self.ki, self.kd)
        if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in vals):
            return [f"gains must be finite numbers, got kp={self.kp!r} ki={self.ki!r} kd={self.kd!r}"]
        if min(vals) < 0:
            return ["gains must be >= 0"]
        return []


# Table 1 of the paper: (kp, ki); kd = 0 throughout.
_TABLE1 = {
    "pid": [(1.1987, 474.5090), (2.3968, 949.0180), (0.5992, 474.5090), (1.1987, 949.0180),
            (1.1987, 237.2552), (0.5992, 237.2552)],
    "pid_hc": [(0.4823, 190.9162), (0.4823, 213.8982), (0.9645, 427.7964), (1.4468, 641.6946),
               (1.6879, 748.6437), (1.4468, 748.6437)],
    "ff_pid": [(1.1987, 474.5090), (0.5992, 474.5090), (1.1987, 949.0180), (1.1987, 237.2552),
               (0.5992, 237.2552), (0.2996, 118.6276)],
    "ff_pid_g": [(1.1987, 474.5090), (2.3968, 949.0180), (0.5992, 474.5090), (1.1987, 949.0180),
                 (0.5992, 237.2552), (0.2996, 118.6276)],
}
TABLE1_GAINS: dict[str, tuple[str, PIDGains]] = {
    f"{strategy}_{i + 1}": (strategy, PIDGains(kp, ki, 0.0))
    for strategy, rows in _TABLE1.items() for i, (kp, ki) in enumerate(rows)
}


def gain_set(name: str) -> tuple[str, PIDGains]:
    """Table 1 gain set by name, e.g. ``"pid_hc_5"`` or ``"PID HC 5"`` -> (strategy, gains)."""
    key = name.strip().lower().replace(" ", "_")
    if key not in TABLE1_GAINS:
        raise KeyError(f"unknown gain set {name!r}; known: {', '.join(TABLE1_GAINS)}")
    return TABLE1_GAINS[key]


# The longest control period [s] at which each PID HC set of Table 1 keeps the tuner's default margins (gain margin
# >= 6 dB, phase margin >= 45 deg, worst case over the plant-gain range, one period of loop delay) on the paper's
# model (test_tuning checks every entry there and that 1.5x the period breaks it).  Table 1 was tuned at 10 kHz;
# at longer periods the faster sets lose their margins (pid_hc_5 at 1 ms: 0.3 dB).
SAFE_PERIOD_S = {"pid_hc_5": 4e-4, "pid_hc_6": 4e-4, "pid_hc_4": 5e-4, "pid_hc_3": 7e-4, "pid_hc_2": 1.5e-3,
                 "pid_hc_1": 2e-3}
FASTEST_FIRST = ("pid_hc_5", "pid_hc_6", "pid_hc_4", "pid_hc_3", "pid_hc_2", "pid_hc_1")  # Table 1's settling
NO_SAFE_SET_STRATEGY = "ol_hc"   # beyond every set's safe period: open loop with the inverse (no loop to destabilise)


def has_feedback(strategy: str) -> bool:
    """Whether ``strategy`` closes a feedback loop (its PID gains are used)."""
    return strategy in REGISTRY and REGISTRY[strategy].feedback


def default_gain_set(period_s: float) -> Optional[str]:
    """The fastest Table 1 PID HC set (by the paper's average settling time) that is safe at ``period_s`` [s]
    (``SAFE_PERIOD_S``); None when none is (a rig then runs ``NO_SAFE_SET_STRATEGY`` until gains are tuned
    for its period)."""
    for name in FASTEST_FIRST:
        if period_s <= SAFE_PERIOD_S[name] * (1 + 1e-9):
            return name
    return None


def nominal_static_gain(model: GPIM, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V) -> float:
    """Span of the major loop per volt [um/V] (about 13.5 um/V for the paper's model)."""
    lo, hi = model.output_range(v_min, v_max)
    return (hi - lo) / (v_max - v_min)


@dataclass(frozen=True)
class ControllerConfig:
    """Controller settings; times in s, voltages in V."""

    strategy: str = "pid_hc"
    gains: PIDGains = PIDGains(1.6879, 748.6437, 0.0)
    dt: float = ruled(PAPER_CONTROL_PERIOD_S, POSITIVE)   # the paper's loop; a rig's: defaults.CONTROL_PERIOD_S
    command_min_v: float = COMMAND_MIN_V
    command_max_v: float = COMMAND_MAX_V
    centre_voltage_v: float = CENTRE_VOLTAGE_V
    static_gain_um_per_v: Optional[float] = None  # None: derived from the GPIM's major loop
    derivative_filter_s: float = ruled(5e-4, POSITIVE)
    bump_time_constant_s: float = ruled(0.01, POSITIVE)

    def problems(self) -> list[str]:
        out = []
        if self.strategy not in REGISTRY:
            out.append(f"unknown strategy {self.strategy!r}; choose one of {', '.join(REGISTRY)}")
        out += self.gains.problems()
        out += field_problems(self)
        if not (math.isfinite(self.command_min_v) and math.isfinite(self.command_max_v)
                and self.command_min_v < self.command_max_v):
            out.append("command range must be finite with command_min_v < command_max_v")
        elif not self.command_min_v <= self.centre_voltage_v <= self.command_max_v:
            out.append(f"centre_voltage_v {self.centre_voltage_v} V must lie within the command range")
        if self.static_gain_um_per_v is not None and not (math.isfinite(self.static_gain_um_per_v)
                                                          and self.static_gain_um_per_v > 0):
            out.append("static_gain_um_per_v must be > 0")
        return out


LOOP_SETTINGS = ("control_period_s", "command_min_v", "command_max_v", "centre_voltage_v", "derivative_filter_s")


def loop_settings(values: dict, strategy: str, gains: PIDGains = PIDGains(), dt: Optional[float] = None,
                  default_dt: float = CONTROL_PERIOD_S) -> ControllerConfig:
    """A ControllerConfig from ``valve_controller`` parameter values (``LOOP_SETTINGS``; a missing one takes
    ControllerConfig's default, the period ``default_dt`` [s]); ``dt`` overrides the period.  Unchecked (see
    ``ControllerConfig.problems``); ValueError for a value that is not a finite number."""
    from ..validation import as_float
    d = ControllerConfig()
    defaults = {"control_period_s": default_dt, "command_min_v": d.command_min_v, "command_max_v": d.command_max_v,
                "centre_voltage_v": d.centre_voltage_v, "derivative_filter_s": d.derivative_filter_s}
    v = {k: as_float(k, values.get(k, defaults[k])) for k in LOOP_SETTINGS}
    return ControllerConfig(strategy=strategy, gains=gains, dt=v["control_period_s"] if dt is None else float(dt),
                            command_min_v=v["command_min_v"], command_max_v=v["command_max_v"],
                            centre_voltage_v=v["centre_voltage_v"], derivative_filter_s=v["derivative_filter_s"])


class ValveController:
    """Streaming controller: ``step(reference_m, measured_m) -> voltage [V]`` once per period."""

    def __init__(self, config: ControllerConfig = ControllerConfig(),
                 compensation: CompensationModel = CompensationModel()):
        problems = config.problems() + compensation.problems(config.command_min_v, config.command_max_v, config.dt)
        if problems:
            raise ValueError("; ".join(problems))
        self.config = config
        self.compensation = compensation
        self._setup_model()
        self._gv, self._dyn = reference_filters(compensation, self.config.dt)
        self._inverse_by_term: dict = {}   # the output place's inverses by term (``_fold_output_inverses``)
        self.reset()

    @property
    def model(self) -> GPIM:
        """The GPIM the controller inverts."""
        return self.compensation.gpim

    # ------------------------------------------------------------------ configuration
    def _setup_model(self) -> None:
        c, comp = self.config, self.compensation
        lo, hi = comp.gpim.output_range(c.command_min_v, c.command_max_v)
        self._demand_min_um, self._demand_max_um = lo, hi
        # nominal_static_gain, from the same major loop
        self._k = c.static_gain_um_per_v or (hi - lo) / (c.command_max_v - c.command_min_v)
        out_map = comp.output_map
        self._map = out_map if out_map.active else None
        # pid_hc's demand range: the GPIM's output range through the saturation map
        self._loop_min_um = out_map.value(self._demand_min_um)
        self._loop_max_um = out_map.value(self._demand_max_um)
        if getattr(self, "_static", None) is not None:
            self._static.bounds = (lo, hi)

    def _inverse(self, v0: float, follow=None):
        """A fresh inverse of the model's hysteresis (rate-dependent when the model says so), virgin at v0 [V];
        ``follow``: the inverse whose rate widening it uses (``rate_dependence.RateDependentInverseGPIM``)."""
        c, comp = self.config, self.compensation
        return hysteresis_inverse(comp.gpim, comp.rate_widening_v, c.dt, v0=v0, v_min=c.command_min_v,
                                  v_max=c.command_max_v, follow=follow)

    def _swap_inverse(self, old, compensation: CompensationModel, v_now: float, follow=None):
        """``old``'s loop memory (operator states, rate history) carried into an inverse of ``compensation``."""
        c = self.config
        return swap_inverse(old, compensation.gpim, compensation.rate_widening_v, c.dt, v_now, c.command_min_v,
                            c.command_max_v, follow)

    def _static_inverse(self, h0: float) -> Optional[StaticInverse]:
        comp = self.compensation
        if not (comp.creep.active or comp.output_map.active):
            return None
        return StaticInverse(comp.creep, comp.output_map, self.config.dt, h0,
                             (self._demand_min_um, self._demand_max_um))

    def _fold_output_inverses(self, y0_um: float, old: Optional[CompensationModel] = None) -> list:
        """The reference path's inverses of the terms at the ``output`` place (``terms.TERMS``), last term first, at rest
        at the reference ``y0_um`` [um]; with ``old`` (the model before a swap) a term whose value is unchanged keeps
        its inverse and a changed one carries on from it (``Term.inverse``)."""
        before = self._inverse_by_term
        steps = {}
        for term in _terms.TERMS:
            if term.place != "output":
                continue
            value = self.compensation.terms[term.field]
            if old is not None and term.field in before and old.terms.get(term.field) == value:
                step = before[term.field]
            else:
                step = term.inverse(value, y0_um, before.get(term.field) if old is not None else None)
            if step is not None:
                steps[term.field] = step
        self._inverse_by_term = steps
        return list(steps.values())[::-1]

    def reset(self, voltage_v: Optional[float] = None, reference_m: Optional[float] = None,
              forward_state=None) -> None:
        """Start afresh: inverses in the virgin state at ``voltage_v`` (default centre), or in the forward model's
        operator states ``forward_state`` reached at that voltage (the valve's memory, where it is known: see
        ``handover.AppliedPath``), integrator 0."""
        c = self.config
        v0 = c.centre_voltage_v if voltage_v is None else float(voltage_v)
        # feedforward inverse, driven by the demand every period whatever the strategy
        self.ff_inverse = self._inverse(v0)
        # in-loop inverse of pid_hc, driven by the PID output (with the feedforward's rate widening)
        self.loop_inverse = self._inverse(v0, follow=self.ff_inverse)
        state = self.model.virgin_state(v0)
        if forward_state is not None and len(forward_state) == len(state):
            state = forward_state
            self.ff_inverse.set_forward_state(state, v0)
            self.loop_inverse.set_forward_state(state, v0)
        y0 = self.model.output_from_state(state)
        # creep and saturation inverse of the feedforward path (None when neither is modelled)
        self._static = self._static_inverse(y0)
        s0 = self._static.forward(y0) if self._static is not None else y0
        self._loop_h = y0                   # pid_hc's last hysteresis demand (where the map's inverse starts)
        self._last_ref_um = s0 if reference_m is None else reference_m * 1e6
        # the inverses of the terms on the spool's path (backlash), in the order the reference passes them
        self._output_inverses = self._fold_output_inverses(self._last_ref_um)
        self._gv.reset(self._last_ref_um)
        if self._dyn is not None:
            self._dyn.reset(self._last_ref_um)
        self._last_gv_out = self._last_ref_um
        self._last_ff_v, self._last_ff_demand_um = v0, None
        self._swap_from = None              # the feedforward inverse before a model swap, for one period
        self._last_measured_um = self._last_ref_um
        self.integrator_um = 0.0
        self._d_state = 0.0
        self._last_error = 0.0
        self._bump_v = 0.0
        self.last_command_v = v0
        self.saturated = False
        self._rail = 0                      # +1/-1: the last command was held at the upper/lower limit
        self._bump_decay = math.exp(-c.dt / c.bump_time_constant_s)
        self._d_alpha = c.dt / (c.derivative_filter_s + c.dt)
        self._tick = 0                      # periods since reset
        self._rail_high_at = self._rail_low_at = -(1 << 30)
        self._rail_entries = [-(1 << 30)] * (GUARD_ENTRIES - 1)  # ticks of the last rail entries (a ring)
        self._rail_entry_pos = 0
        self._away_from_rails = True        # the command came away from the rails since the last entry
        self._fallback_left = 0             # periods still to run on feedforward alone
        self._fallback_ended_at = -(1 << 30)
        self._hold_periods = max(int(round(GUARD_HOLD_S / c.dt)), 1)
        self.guard_trips = 0

    @property
    def guard_hold_s(self) -> float:
        """How long the guard's last (or current) hold on feedforward lasts [s]."""
        return self._hold_periods * self.config.dt

    @property
    def in_fallback(self) -> bool:
        """True while the oscillation guard holds the loop on its feedforward path."""
        return self._fallback_left > 0

    def _guard(self) -> None:
        """After each feedback command: both rails within GUARD_WINDOW_S, or GUARD_ENTRIES entries onto a rail
        within GUARD_ENTRY_WINDOW_S -> feedforward alone for a hold."""
        c = self.config
        if self._rail == 0:
            margin = GUARD_AWAY_SHARE * (c.command_max_v - c.command_min_v)
            if c.command_min_v + margin < self.last_command_v < c.command_max_v - margin:
                self._away_from_rails = True
            return
        entered, self._away_from_rails = self._away_from_rails, False
        if self._rail > 0:
            self._rail_high_at = self._tick
        else:
            self._rail_low_at = self._tick
        oscillating = abs(self._rail_high_at - self._rail_low_at) <= max(int(round(GUARD_WINDOW_S / c.dt)), 1)
        if entered:
            k = self._rail_entry_pos
            oldest = self._rail_entries[k]  # the entry GUARD_ENTRIES - 1 entries before this one
            self._rail_entries[k] = self._tick
            self._rail_entry_pos = (k + 1) % len(self._rail_entries)
            oscillating = oscillating or self._tick - oldest <= max(int(round(GUARD_ENTRY_WINDOW_S / c.dt)), 1)
        if not oscillating:
            return
        base = max(int(round(GUARD_HOLD_S / c.dt)), 1)
        recurs = self._tick - self._fallback_ended_at <= 2 * self._hold_periods
        self._hold_periods = min(2 * self._hold_periods, int(round(GUARD_MAX_HOLD_S / c.dt))) if recurs else base
        self._fallback_left = self._hold_periods
        self._rail_high_at = self._rail_low_at = -(1 << 30)
        self._rail_entries = [-(1 << 30)] * (GUARD_ENTRIES - 1)
        self.guard_trips += 1
        self._bump_v = 0.0      # no continuity with a rail-to-rail swing: straight to the feedforward command
        self.integrator_um = 0.0
        if REGISTRY[c.strategy].inverse == IN_LOOP_INVERSE:
            # the swing has moved the valve's operators far from where the demand history puts the feedforward
            # inverse's; pid_hc's in-loop inverse has followed every command applied: the feedforward takes
            # over its states (otherwise the fallback is off by up to the hysteresis width until the demand's
            # next reversal)
            self.ff_inverse.set_forward_state(self.loop_inverse.forward_state(), self.last_command_v)

    def set_strategy(self, strategy: str, gains: Optional[PIDGains] = None) -> None:
        """Switch law (and optionally gains) at run time without a jump in the command."""
        new = replace(self.config, strategy=strategy, gains=gains or self.config.gains)
        problems = new.problems()
        if problems:
            raise ValueError("; ".join(problems))
        old_strategy = self.config.strategy
        self.config = new
        self._transfer(old_strategy)

    def set_command_range(self, command_min_v: float, command_max_v: float, centre_voltage_v: float) -> None:
        """New command range [V]: the static gain and the demand limits follow it; bumpless."""
        new = replace(self.config, command_min_v=command_min_v, command_max_v=command_max_v,
                      centre_voltage_v=centre_voltage_v)
        problems = new.problems() or self.compensation.problems(command_min_v, command_max_v, new.dt)
        if problems:
            raise ValueError("; ".join(problems))
        self.config = new
        self._setup_model()
        # the inverses limit their inputs to the command range: rebuilt on it, loop memory kept
        self.ff_inverse = self._swap_inverse(self.ff_inverse, self.compensation, self._last_ff_v)
        self.loop_inverse = self._swap_inverse(self.loop_inverse, self.compensation, self.last_command_v,
                                               self.ff_inverse)
        self.last_command_v = min(max(self.last_command_v, command_min_v), command_max_v)
        self._transfer(self.config.strategy)

    def set_model_and_command_range(self, compensation: CompensationModel, command_min_v: float,
                                    command_max_v: float, centre_voltage_v: float) -> None:
        """A new model and a new command range [V] together (a fitted model and the range it knows, from one
        parameters file): validated together, all or nothing; either alone may not suit the other one in force."""
        new = replace(self.config, command_min_v=command_min_v, command_max_v=command_max_v,
                      centre_voltage_v=centre_voltage_v)
        problems = new.problems() or compensation.problems(command_min_v, command_max_v, new.dt)
        if problems:
            raise ValueError("; ".join(problems))
        old = self.config
        self.config = new
        try:
            self.set_model(compensation)
        except Exception:
            self.config = old
            self._setup_model()
            raise
        self.last_command_v = min(max(self.last_command_v, command_min_v), command_max_v)
        self._transfer(self.config.strategy)

    def set_derivative_filter(self, time_constant_s: float) -> None:
        """New time constant [s] of the D term's filter; the filter's present output carries on (bumpless)."""
        new = replace(self.config, derivative_filter_s=time_constant_s)
        problems = new.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self.config = new
        self._d_alpha = new.dt / (new.derivative_filter_s + new.dt)

    def set_gains(self, gains: PIDGains) -> None:
        self.set_strategy(self.config.strategy, gains)

    def set_model(self, compensation: CompensationModel) -> None:
        """Replace the whole compensation model: validated first, all or nothing; loop memory carried over
        (operator states, the creep lags' present output, the filters' present outputs)."""
        c = self.config
        problems = compensation.problems(c.command_min_v, c.command_max_v, c.dt)
        if problems:
            raise NotInvertibleError("; ".join(problems))
        old, old_ff = self.compensation, self.ff_inverse
        ff = self._swap_inverse(self.ff_inverse, compensation, self._last_ff_v)
        loop = self._swap_inverse(self.loop_inverse, compensation, self.last_command_v, ff)
        dynamics_changed = (compensation.valve_model, compensation.dynamic_feedforward) != \
            (old.valve_model, old.dynamic_feedforward)
        filters = reference_filters(compensation, self.config.dt) if dynamics_changed else None
        self.compensation, self.ff_inverse, self.loop_inverse = compensation, ff, loop
        if (compensation.creep, compensation.output_map) != (old.creep, old.output_map):
            self._static = self._static_inverse(ff.peek_forward(self._last_ff_v))
        # each changed term on the spool's path carries on from its old inverse (backlash: the reference's direction)
        self._output_inverses = self._fold_output_inverses(self._last_ref_um, old)
        self._setup_model()
        # the next period's feedforward voltage is taken over from the old model (its inverse, as it stands,
        # asked for that period's demand) and the difference handed to the integrator or the decaying bump:
        # the command moves as the old model would have moved it, then settles onto the new one.  (The new
        # model's voltage for the last demand is no reference: with thresholds widened by the rate it may
        # lie across a dead band from the voltage the next demand needs.)  Two swaps before a period: the
        # command still follows the first one's old model.
        if self._swap_from is None and self._last_ff_demand_um is not None:
            self._swap_from = old_ff
        if filters is not None:
            self._gv, self._dyn = filters
            self._gv.reset(self._last_gv_out)
            if self._dyn is not None:
                self._dyn.reset(self._last_ref_um)
        self._transfer(self.config.strategy)

    # ------------------------------------------------------------------ bumpless transfer
    def _transfer(self, old_strategy: str) -> None:
        """Make the next command continuous with the last one after a law, gain or model change."""
        c = self.config
        law = REGISTRY[c.strategy]
        v_last = self.last_command_v
        if law.shaped_reference and not REGISTRY[old_strategy].shaped_reference:
            # G_v ran only under a law that follows it: it starts settled at the reference (what was followed)
            self._gv.reset(self._last_ref_um)
            self._last_gv_out = self._last_ref_um
        # the error the new law would have seen in the last period
        e = (self._last_gv_out if law.shaped_reference else self._last_ref_um) - self._last_measured_um
        self._last_error = e
        if law.inverse == IN_LOOP_INVERSE and REGISTRY[old_strategy].inverse != IN_LOOP_INVERSE:
            # the in-loop inverse takes over the valve's state as the demand history describes it
            take_over_state(self.loop_inverse, self.ff_inverse, self.last_command_v)
        if law.feedback and law.inverse != IN_LOOP_INVERSE:
            base = c.centre_voltage_v if law.inverse == NO_INVERSE else self._last_ff_v
            self.integrator_um = (v_last - base) * self._k - c.gains.kp * e - self._d_state
            self._bump_v = 0.0
        elif law.feedback:
            h_target = self.loop_inverse.peek_forward(v_last)
            self._loop_h = h_target
            u_target = self._map.value(h_target) if self._map is not None else h_target
            self.integrator_um = u_target - c.gains.kp * e - self._d_state
            self._bump_v = 0.0
        else:  # the open-loop laws have no state that could absorb the difference: let it decay
            self.integrator_um = 0.0
            predicted = (c.centre_voltage_v + self._last_ref_um / self._k if law.inverse == NO_INVERSE
                         else self._last_ff_v)
            self._bump_v = v_last - predicted

    def _take_over_swap(self, law: str, difference_v: float) -> None:
        """First period after a model swap: the old model's feedforward voltage minus the new one's, handed to
        the law's state (decaying bump, integrator) so the command continues as the old model would."""
        self._swap_from = None
        strategy = REGISTRY[law]
        if strategy.inverse != FEEDFORWARD_INVERSE:
            return
        if strategy.feedback:
            self.integrator_um += difference_v * self._k
        else:
            self._bump_v += difference_v

    # ------------------------------------------------------------------ the loop
    @property
    def reachable_m(self) -> tuple[float, float]:
        """(lowest, highest) position [m] the model says the valve reaches on the command range: the GPIM's
        major loop through the saturation map."""
        return self._loop_min_um * 1e-6, self._loop_max_um * 1e-6

    def admit_reference(self, reference_m: float) -> tuple[Optional[float], str]:
        """A position reference [m] checked against what the valve can reach: (the reference to follow,
        "") when inside; (the nearest reachable position, why) when at most REFERENCE_CLAMP_SHARE of the
        span outside; (None, why) when not finite or further out (a unit mistake: 20 meant as um, 1e-3 as
        mm), which would hold the command on a rail."""
        lo, hi = self.reachable_m
        if not math.isfinite(reference_m):
            return None, f"position_reference {reference_m!r} is not a finite number"
        if lo <= reference_m <= hi:
            return reference_m, ""
        margin = REFERENCE_CLAMP_SHARE * (hi - lo)
        where = f"outside the reachable range [{lo:.4g}, {hi:.4g}] m of the model in force"
        if lo - margin <= reference_m <= hi + margin:
            near = min(max(reference_m, lo), hi)
            return near, f"position_reference {reference_m:.6g} m {where}: clamped to {near:.6g} m"
        return None, (f"position_reference {reference_m:.6g} m {where} (references are in metres: "
                      f"20 um is 2e-05): refused, the last reference stays")

    def step(self, reference_m: float, measured_m: float) -> float:
        """One control period: demand and measured position [m] -> command [V]."""
        c = self.config
        s = c.strategy
        self._tick += 1
        if self._fallback_left:
            self._fallback_left -= 1
            if self._fallback_left:
                s = FALLBACK_LAW[s]
            else:  # back to feedback, continuous with the last feedforward command
                self._fallback_ended_at = self._tick
                self._transfer(FALLBACK_LAW[s])
        y_ref = reference_m * 1e6
        self._last_ref_um = y_ref
        x_ref = y_ref
        for inverse in self._output_inverses:
            x_ref = inverse.step(x_ref)
        s_ref = self._dyn.step(x_ref) if self._dyn is not None else x_ref
        h_ref = self._static.step(s_ref) if self._static is not None else s_ref
        ff_demand = min(max(h_ref, self._demand_min_um), self._demand_max_um)
        ff_v = self.ff_inverse.step(ff_demand)
        self._last_ff_v, self._last_ff_demand_um = ff_v, ff_demand
        if self._swap_from is not None:
            self._take_over_swap(s, self._swap_from.peek(ff_demand) - ff_v)
        # G_v shapes the reference only for a law that follows it (the fallback of one keeps it running)
        gv_out = self._last_gv_out = self._gv.step(y_ref) if REGISTRY[c.strategy].shaped_reference else y_ref
        y = measured_m * 1e6
        self._last_measured_um = y
        law = REGISTRY[s]
        if not law.feedback:
            return self._finish(ff_v if law.inverse == FEEDFORWARD_INVERSE else c.centre_voltage_v + y_ref / self._k,
                                0.0, 0.0)
        e = (gv_out if law.shaped_reference else y_ref) - y
        g = c.gains
        if g.kd:
            self._d_state += self._d_alpha * (g.kd * (e - self._last_error) / c.dt - self._d_state)
        self._last_error = e
        di = g.ki * e * c.dt
        u = g.kp * e + self.integrator_um + di + self._d_state
        if law.inverse == IN_LOOP_INVERSE:
            u_c = min(max(u, self._loop_min_um), self._loop_max_um)
            if self._map is not None:
                h_c = self._loop_h = self._map.solve(u_c, self._loop_h, 0.0, self._demand_min_um,
                                                     self._demand_max_um)
            else:
                h_c = u_c
            v = self._finish(self.loop_inverse.step(h_c), e, di, int(u > u_c) - int(u < u_c),
                             min(max(y_ref, self._loop_min_um), self._loop_max_um))
        else:
            base = c.centre_voltage_v if law.inverse == NO_INVERSE else ff_v
            v = self._finish(base + u / self._k, e, di)
        if self._rail or not self._away_from_rails:   # off the rails and already away from them: nothing to watch
            self._guard()
        return v

    def _finish(self, v_raw: float, e: float, di: float, demand_clip: int = 0,
                integrator_goal_um: Optional[float] = None) -> float:
        """Add the decaying bump, clamp, and integrate unless that pushes further into a limit.

        ``demand_clip`` is +1/-1 when pid_hc's position demand was clipped high/low; ``integrator_goal_um``
        (pid_hc: the demand within the loop's range [um]): on a limit the integrator may still move toward it,
        never past it.
        """
        c = self.config
        if self._bump_v:
            v_raw += self._bump_v
            self._bump_v *= self._bump_decay
            if abs(self._bump_v) < 1e-9:
                self._bump_v = 0.0
        v = min(max(v_raw, c.command_min_v), c.command_max_v)
        high = v_raw > c.command_max_v or demand_clip > 0
        low = v_raw < c.command_min_v or demand_clip < 0
        self.saturated = high or low
        self._rail = 1 if high else (-1 if low else 0)
        if not ((high and e > 0) or (low and e < 0)):
            self.integrator_um += di
        elif integrator_goal_um is not None:
            i = self.integrator_um
            self.integrator_um = min(i + di, max(i, integrator_goal_um)) if high else max(i + di, min(i, integrator_goal_um))
        self.last_command_v = v
        return v
