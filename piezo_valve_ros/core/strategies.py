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

The output is clamped to the command range with conditional-integration anti-windup.
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


from .dynamics import PAPER_VALVE_MODEL, ContinuousTF
from .hysteresis import GPIM, InverseGPIM, NotInvertibleError, PAPER_GPIM, inverse_problems
from .drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V

__all__ = ["STRATEGIES", "PIDGains", "ControllerConfig", "ValveController", "TABLE1_GAINS", "gain_set",
           "nominal_static_gain", "CreepModel", "CreepCompensator"]

STRATEGIES = ("ol", "ol_hc", "pid", "pid_hc", "ff_pid", "ff_pid_g")
FALLBACK_LAW = {"pid": "ol", "pid_hc": "ol_hc", "ff_pid": "ol_hc", "ff_pid_g": "ol_hc"}  # feedback -> feedforward
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


@dataclass(frozen=True)
class CreepModel:
    """Creep as identified: ``y = H + sum_i g_i (lag_{tau_i}[H] - H)`` (H: hysteresis output [um])."""

    time_constants_s: tuple[float, ...] = ()
    gains: tuple[float, ...] = ()

    def problems(self) -> list[str]:
        taus, gains = self.time_constants_s, self.gains
        if len(taus) != len(gains):
            return [f"creep: {len(taus)} time constants but {len(gains)} gains"]
        if not all(math.isfinite(x) for x in tuple(taus) + tuple(gains)):
            return ["creep: non-finite value"]
        out = []
        if any(t <= 0 for t in taus):
            out.append("creep: time constants must be > 0")
        if sum(gains) >= 0.9:
            out.append(f"creep: gains sum to {sum(gains):.3g}; compensation needs a sum < 0.9")
        return out

    @property
    def active(self) -> bool:
        return any(g != 0.0 for g in self.gains)


class CreepCompensator:
    """Exact streaming inverse of :class:`CreepModel`: demanded position -> hysteresis demand [um].

    The ZOH lags depend only on past hysteresis outputs (l_k = a l_{k-1} + (1 - a) H_{k-1}), so
    ``H_k = (y_k - sum g_i l_i,k) / (1 - sum g_i)`` meets the demand exactly when the model holds.
    """

    def __init__(self, creep: CreepModel, dt: float, h0: float = 0.0):
        problems = creep.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self.creep = creep
        self._a = [math.exp(-dt / tau) for tau in creep.time_constants_s]
        self._g = [float(g) for g in creep.gains]
        self._den = 1.0 - sum(self._g)
        self.reset(h0)

    def reset(self, h0: float) -> None:
        self._lags = [float(h0)] * len(self._a)
        self._last_h = float(h0)

    def step(self, demand_um: float) -> float:
        lags, a, g = self._lags, self._a, self._g
        acc = 0.0
        for i in range(len(a)):
            lags[i] = a[i] * lags[i] + (1.0 - a[i]) * self._last_h
            acc += g[i] * lags[i]
        h = (demand_um - acc) / self._den
        self._last_h = h
        return h


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


def nominal_static_gain(model: GPIM, v_min: float = COMMAND_MIN_V, v_max: float = COMMAND_MAX_V) -> float:
    """Span of the major loop per volt [um/V] (about 13.5 um/V for the paper's model)."""
    _, up, down = model.major_loop(v_min, v_max, 401)
    return float((max(up.max(), down.max()) - min(up.min(), down.min())) / (v_max - v_min))


@dataclass(frozen=True)
class ControllerConfig:
    """Controller settings; times in s, voltages in V."""

    strategy: str = "pid_hc"
    gains: PIDGains = PIDGains(1.6879, 748.6437, 0.0)
    dt: float = 1e-4
    command_min_v: float = COMMAND_MIN_V
    command_max_v: float = COMMAND_MAX_V
    centre_voltage_v: float = CENTRE_VOLTAGE_V
    static_gain_um_per_v: Optional[float] = None  # None: derived from the GPIM's major loop
    derivative_filter_s: float = 5e-4
    bump_time_constant_s: float = 0.01

    def problems(self) -> list[str]:
        out = []
        if self.strategy not in STRATEGIES:
            out.append(f"unknown strategy {self.strategy!r}; choose one of {', '.join(STRATEGIES)}")
        out += self.gains.problems()
        for name in ("dt", "derivative_filter_s", "bump_time_constant_s"):
            x = getattr(self, name)
            if not (math.isfinite(x) and x > 0):
                out.append(f"{name} must be > 0, got {x}")
        if not (math.isfinite(self.command_min_v) and math.isfinite(self.command_max_v)
                and self.command_min_v < self.command_max_v):
            out.append("command range must be finite with command_min_v < command_max_v")
        elif not self.command_min_v <= self.centre_voltage_v <= self.command_max_v:
            out.append(f"centre_voltage_v {self.centre_voltage_v} V must lie within the command range")
        if self.static_gain_um_per_v is not None and not (math.isfinite(self.static_gain_um_per_v)
                                                          and self.static_gain_um_per_v > 0):
            out.append("static_gain_um_per_v must be > 0")
        return out


class ValveController:
    """Streaming controller: ``step(reference_m, measured_m) -> voltage [V]`` once per period."""

    def __init__(self, config: ControllerConfig = ControllerConfig(), model: GPIM = PAPER_GPIM.model(),
                 valve_model: ContinuousTF = PAPER_VALVE_MODEL, creep: CreepModel = CreepModel()):
        problems = config.problems() + inverse_problems(model) + valve_model.problems() + creep.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self.config = config
        self.model = model
        self.valve_model = valve_model
        self.creep = creep
        self._setup_model(model)
        self._gv = valve_model.discretise(config.dt)
        self.reset()

    # ------------------------------------------------------------------ configuration
    def _setup_model(self, model: GPIM) -> None:
        c = self.config
        self._k = c.static_gain_um_per_v or nominal_static_gain(model, c.command_min_v, c.command_max_v)
        _, up, down = model.major_loop(c.command_min_v, c.command_max_v, 401)
        self._demand_min_um = float(min(up.min(), down.min()))
        self._demand_max_um = float(max(up.max(), down.max()))

    def reset(self, voltage_v: Optional[float] = None, reference_m: Optional[float] = None) -> None:
        """Start afresh: inverses in the virgin state at ``voltage_v`` (default centre), integrator 0."""
        c = self.config
        v0 = c.centre_voltage_v if voltage_v is None else float(voltage_v)
        # feedforward inverse, driven by the demand every period whatever the strategy
        self.ff_inverse = InverseGPIM(self.model, v0=v0)
        # in-loop inverse of pid_hc, driven by the PID output
        self.loop_inverse = InverseGPIM(self.model, v0=v0)
        y0 = self.model.output_from_state(self.model.virgin_state(v0))
        # creep compensation of the feedforward path (None when no creep is modelled)
        self._creep = CreepCompensator(self.creep, c.dt, y0) if self.creep.active else None
        self._last_ref_um = y0 if reference_m is None else reference_m * 1e6
        self._gv.reset(self._last_ref_um)
        self._last_gv_out = self._last_ref_um
        self._last_ff_v, self._last_ff_demand_um = v0, None
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
        problems = new.problems()
        if problems:
            raise ValueError("; ".join(problems))
        self.config = new
        self._setup_model(self.model)
        self.last_command_v = min(max(self.last_command_v, command_min_v), command_max_v)
        self._transfer(self.config.strategy)

    def set_gains(self, gains: PIDGains) -> None:
        self.set_strategy(self.config.strategy, gains)

    def set_model(self, model: GPIM, valve_model: Optional[ContinuousTF] = None,
                  creep: Optional[CreepModel] = None) -> None:
        """Replace the GPIM (and G_v, creep): validated first, all or nothing; loop memory carried over."""
        problems = (inverse_problems(model) + (valve_model.problems() if valve_model else [])
                    + (creep.problems() if creep is not None else []))
        if problems:
            raise NotInvertibleError("; ".join(problems))
        ff = self.ff_inverse.with_model(model, self._last_ff_v)
        loop = self.loop_inverse.with_model(model, self.last_command_v)
        new_gv = valve_model.discretise(self.config.dt) if valve_model else None
        if creep is not None and creep != self.creep:
            self.creep = creep
            h_now = ff.peek_forward(self._last_ff_v)
            self._creep = CreepCompensator(creep, self.config.dt, h_now) if creep.active else None
        self.model, self.ff_inverse, self.loop_inverse = model, ff, loop
        self._setup_model(model)
        if self._last_ff_demand_um is not None:
            # the voltage the new model asks for the last demand: the transfer below makes the command
            # continuous from there (the integrator or the decaying bump takes the difference)
            self._last_ff_v = ff.peek(self._last_ff_demand_um)
        if new_gv is not None:
            new_gv.reset(self._last_gv_out)
            self._gv, self.valve_model = new_gv, valve_model
        self._transfer(self.config.strategy)

    # ------------------------------------------------------------------ bumpless transfer
    def _transfer(self, old_strategy: str) -> None:
        """Make the next command continuous with the last one after a law, gain or model change."""
        c = self.config
        s = c.strategy
        v_last = self.last_command_v
        # the error the new law would have seen in the last period
        e = (self._last_gv_out if s == "ff_pid_g" else self._last_ref_um) - self._last_measured_um
        self._last_error = e
        if s == "pid_hc" and old_strategy != "pid_hc":
            # the in-loop inverse takes over the valve's state as the demand history describes it
            self.loop_inverse.set_forward_state(self.ff_inverse.forward_state(), self.last_command_v)
        if s in ("pid", "ff_pid", "ff_pid_g"):
            base = c.centre_voltage_v if s == "pid" else self._last_ff_v
            self.integrator_um = (v_last - base) * self._k - c.gains.kp * e - self._d_state
            self._bump_v = 0.0
        elif s == "pid_hc":
            u_target = self.loop_inverse.peek_forward(v_last)
            self.integrator_um = u_target - c.gains.kp * e - self._d_state
            self._bump_v = 0.0
        else:  # ol, ol_hc have no state that could absorb the difference: let it decay
            self.integrator_um = 0.0
            predicted = c.centre_voltage_v + self._last_ref_um / self._k if s == "ol" else self._last_ff_v
            self._bump_v = v_last - predicted

    # ------------------------------------------------------------------ the loop
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
        h_ref = self._creep.step(y_ref) if self._creep is not None else y_ref
        ff_demand = min(max(h_ref, self._demand_min_um), self._demand_max_um)
        ff_v = self.ff_inverse.step(ff_demand)
        self._last_ff_v, self._last_ff_demand_um = ff_v, ff_demand
        gv_out = self._gv.step(y_ref)
        self._last_gv_out = gv_out
        y = measured_m * 1e6
        self._last_measured_um = y
        if s == "ol":
            return self._finish(c.centre_voltage_v + y_ref / self._k, 0.0, 0.0)
        if s == "ol_hc":
            return self._finish(ff_v, 0.0, 0.0)
        e = (gv_out if s == "ff_pid_g" else y_ref) - y
        g = c.gains
        if g.kd:
            self._d_state += self._d_alpha * (g.kd * (e - self._last_error) / c.dt - self._d_state)
        self._last_error = e
        di = g.ki * e * c.dt
        u = g.kp * e + self.integrator_um + di + self._d_state
        if s == "pid_hc":
            u_c = min(max(u, self._demand_min_um), self._demand_max_um)
            v = self._finish(self.loop_inverse.step(u_c), e, di, int(u > u_c) - int(u < u_c))
        else:
            base = c.centre_voltage_v if s == "pid" else ff_v
            v = self._finish(base + u / self._k, e, di)
        self._guard()
        return v

    def _finish(self, v_raw: float, e: float, di: float, demand_clip: int = 0) -> float:
        """Add the decaying bump, clamp, and integrate unless that pushes further into a limit.

        ``demand_clip`` is +1/-1 when pid_hc's position demand was clipped high/low.
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
        self.last_command_v = v
        return v
