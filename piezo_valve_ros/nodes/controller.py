"""``valve_controller``: the selected strategy with the inverse GPIM, one command per measurement.

Every parameter change is validated as a whole before anything is applied (a rejected update
leaves the controller as it was and returns the reason); what is accepted is applied, and strategy,
gain, range and model changes are bumpless.

``gain_set`` (e.g. ``pid_hc_5``), when non-empty, selects strategy and gains from Table 1 and writes them
into ``strategy``/``kp``/``ki``/``kd``, which then read back what runs.  While a set is active those four
are refused unless the same request clears it (``gain_set: ''``); clearing it alone keeps the set's values.

Hand-over: with ``enabled: false`` another node drives ``voltage_command`` (e.g. identification).  The
controller tracks the voltage actually applied (those commands, and the hardware's ``samples``); when the
other node's commands stop for ``handback_timeout_s`` (it died, say), the controller enables itself.
Either way it resumes bumplessly from the applied voltage.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
import sys
import time
from typing import Any, Callable, Optional, Sequence

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64, Float64MultiArray, String

from ..core.control.compensation import MODEL_PARAMETERS, CompensationModel
from ..core.control.handover import AppliedPath
from ..core.model.rate_dependence import describe_inverse, solved_each_step
from ..core.sim.signals import ReferenceRamp
from ..core.control.strategies import (GUARD_WINDOW_S, has_feedback, SAFE_PERIOD_S, STRATEGIES, TABLE1_GAINS, ControllerConfig,
                                       PIDGains, ValveController, default_gain_set, gain_set, loop_settings)
from ..ros import (COMMAND_QOS, CONTROL_PERIOD, DIAGNOSTICS_PERIOD, LATEST_SENSOR_QOS, SAMPLES_QOS, STATE_QOS,
                   declare_all, Diagnostics, parameter_values, realtime_settings, realtime_specs,
                   refuse, refuse_undeclared, run_node, samples_from_message, SamplesBuffer, Throttle)
from ..core.validation import ParameterSpec, Settings
from ..core.model.drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V

GAIN_SET_KEYS = ("strategy", "kp", "ki", "kd")   # what an active gain_set decides
HANDBACK_TIMEOUT_RANGE_S = (0.05, 10.0)          # handback_timeout_s may not be shorter or longer than this
HANDBACK_CHECK_S = 0.02                          # how often the hand-back condition is checked [s]
DERIVATIVE_FILTER_RANGE_S = (1e-5, 0.1)          # the D term's filter time constant may lie within this [s]


def gain_set_values(name: str) -> dict[str, Any]:
    """strategy/kp/ki/kd of a Table 1 set; ValueError for an unknown name."""
    try:
        strategy, gains = gain_set(name)
    except KeyError as exc:
        raise ValueError(str(exc.args[0])) from None
    return {"strategy": strategy, "kp": gains.kp, "ki": gains.ki, "kd": gains.kd}


def settings_from_parameters(p: dict[str, Any]) -> tuple[ControllerConfig, CompensationModel]:
    """Controller settings and the compensation model from a flat parameter dict (the control law's parameters
    checked by their ``ParameterSpec`` first, then together by ``ControllerConfig`` and the model's own checks);
    raises ValueError with every problem found."""
    problems = []
    for name in CONTROL_LAW_PARAMETERS:
        try:
            SPECS[name].checked(p[name])
        except ValueError as exc:
            problems.append(str(exc))
    if problems:
        raise ValueError("; ".join(problems))
    strategy = str(p["strategy"])
    gains = PIDGains(float(p["kp"]), float(p["ki"]), float(p["kd"]))
    name = str(p.get("gain_set", "") or "")
    if name:
        wanted = gain_set_values(name)
        differ = [k for k in GAIN_SET_KEYS if p[k] != wanted[k]]
        if differ:
            raise ValueError(f"gain_set {name!r} is active and decides {', '.join(GAIN_SET_KEYS)}: to set "
                             f"{', '.join(differ)}, clear it in the same request (gain_set:= with nothing after it, or gain_set: '' in a file)")
    config = loop_settings(p, strategy, gains)
    problems = config.problems()
    model = None
    try:
        model = CompensationModel.from_parameters(p, config.command_min_v, config.command_max_v, config.dt)
    except ValueError as exc:
        problems.append(str(exc))
    if problems:
        raise ValueError("; ".join(problems))
    return config, model


SOLVED_INVERSE_MIN_PERIOD_S = 5e-4   # below this period an inverse solved each step is said to risk overruns


STATE_PERIOD = ParameterSpec(
    "state_period_s", 0.1, "publish ~/controller_state (the latest period's reference, measurement, error, command, "
    "strategy, guard) this often [s]; 0: never", read_only=True, low=0.0, high=10.0)
DEFAULT_GAIN_SET = default_gain_set(CONTROL_PERIOD.default)   # the node's default gains are safe at its default period
_GAINS = TABLE1_GAINS[DEFAULT_GAIN_SET][1]
CONTROLLER_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("strategy", "pid_hc", "the control law (the paper's six)", choices=STRATEGIES),
    ParameterSpec("gain_set", "", "Table 1 gain set name: sets strategy/kp/ki/kd (which read back its values); '' = none"),
    ParameterSpec("kp", _GAINS.kp, f"proportional gain (normalised, um/um; default: {DEFAULT_GAIN_SET}'s, safe at the "
                  "default control period)", low=0.0),
    ParameterSpec("ki", _GAINS.ki, "integral gain [1/s]", low=0.0),
    ParameterSpec("kd", _GAINS.kd, "derivative gain [s] (the paper uses 0)", low=0.0),
    ParameterSpec("derivative_filter_s", ControllerConfig.derivative_filter_s,
                  "time constant of the D term's first-order filter [s] (valve_tune and the tune step use it)",
                  low=DERIVATIVE_FILTER_RANGE_S[0], high=DERIVATIVE_FILTER_RANGE_S[1]),
    ParameterSpec("command_min_v", COMMAND_MIN_V, "[V]"),
    ParameterSpec("command_max_v", COMMAND_MAX_V, "[V]"),
    ParameterSpec("centre_voltage_v", CENTRE_VOLTAGE_V, "[V]"),
    ParameterSpec("reference_ramp_s", 0.0, "reference changes become ramps of this duration [s] (paper: 0.002; "
                  "0: steps)", low=0.0),
    ParameterSpec("initial_reference_m", 0.0, "reference until the first position_reference [m]"),
    ParameterSpec("enabled", True, "false: publish no commands (another node drives voltage_command, e.g. "
                  "identification); true again resumes from the applied voltage"),
    *(ParameterSpec(name, default, text) for name, (default, text) in MODEL_PARAMETERS.items()),
    CONTROL_PERIOD,
    ParameterSpec("handback_timeout_s", 1.0, "disabled: when the commands of the node that took over stop for this "
                  "long, take control back [s]", low=HANDBACK_TIMEOUT_RANGE_S[0], high=HANDBACK_TIMEOUT_RANGE_S[1]),
    *realtime_specs(),
    STATE_PERIOD,
    DIAGNOSTICS_PERIOD,
)
SPECS = {s.name: s for s in CONTROLLER_PARAMETERS}
CONTROL_LAW_PARAMETERS = ("strategy", "kp", "ki", "kd", "derivative_filter_s", "command_min_v", "command_max_v",
                          "centre_voltage_v", "control_period_s")   # what ControllerConfig is made of (loop_settings)


@dataclass(frozen=True)
class ControllerNodeSettings(Settings):
    """``valve_controller``'s own settings beside the control law's (``settings_from_parameters``), read by
    ``Settings.from_specs`` from CONTROLLER_PARAMETERS at start-up and again for every update (the live ones:
    ``enabled``, ``reference_ramp_s``, ``handback_timeout_s``)."""

    enabled: bool
    reference_ramp_s: float       # [s]; 0: steps
    initial_reference_m: float    # [m]
    handback_timeout_s: float     # [s]
    state_period_s: float         # [s]; 0: never
    diagnostics_period_s: float   # [s]; 0: never
CONTROLLER_STATE_COLUMNS = ("time_s", "reference_m", "measured_m", "error_m", "command_v", "strategy_index",
                            "guard_active", "enabled")   # ~/controller_state: one row; strategy_index into STRATEGIES


class ValveControllerNode(Node):
    def __init__(self, siblings: Sequence[Node] = (), **kwargs):
        """``siblings``: the other nodes of its process (a name the command line gives that none of them declares
        is refused here, before anything runs: rclpy would ignore it, leaving its default in force)."""
        super().__init__("valve_controller", **kwargs)
        self._say_non_finite = Throttle(1.0)   # a per-measurement warning, at most this often
        declare_all(self, CONTROLLER_PARAMETERS)
        refuse_undeclared([*siblings, self], "valve_controller" if not siblings else "valve_composed")
        name = str(self.get_parameter("gain_set").value or "")
        if name:  # the set's values are what runs: the parameters say so
            self.set_parameters([Parameter(k, value=v) for k, v in gain_set_values(name).items()])
        p = parameter_values(self)
        config, model = settings_from_parameters(p)
        settings = ControllerNodeSettings.from_specs(SPECS, p)
        self.handback_timeout_s = settings.handback_timeout_s
        from ..runtime.realtime import apply
        self.realtime = realtime_settings(p)
        apply(self.realtime)
        self.controller = ValveController(config, model)
        self._check_inverse_cost(self.controller)
        self.ramp = ReferenceRamp(settings.initial_reference_m, settings.reference_ramp_s, config.dt)
        self.enabled = settings.enabled
        self._last_position_m = None
        self._guarding = False
        self._said_no_listener = False
        self._applied_v: Optional[float] = None       # while disabled: the voltage last applied, as far as we know
        self._applied_path: Optional[AppliedPath] = None   # while disabled: every voltage applied (the samples)
        self._foreign_command_at: Optional[float] = None  # while disabled: monotonic time of the last foreign command
        self._samples_sub = self._command_watch = None   # while disabled: what others command, the hardware applies
        self.command_pub = self.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        # depth 1: after a stall the controller answers the newest position, never a queue of stale ones
        self._position_sub = self.create_subscription(Float64, "spool_position", self._on_position, LATEST_SENSOR_QOS)
        self.create_subscription(Float64, "position_reference", self._on_reference, 10)
        self.hardware_fault: Optional[str] = None   # what hardware_state says while the hardware is in fault
        self.create_subscription(String, "hardware_state", self._on_hardware_state, STATE_QOS)
        self.add_pre_set_parameters_callback(self._expand_gain_set)
        self.add_on_set_parameters_callback(self._on_parameters)
        self.create_timer(HANDBACK_CHECK_S, self._check_handback)
        if not self.enabled:
            self._watch_applied_voltage(True)
        self.rejected_references = 0
        self.clamped_references = 0
        self._last_reference_m = float("nan")
        self._last_command_v = float("nan")
        self.state_pub = self.create_publisher(Float64MultiArray, "~/controller_state", 10)
        self._state = SamplesBuffer(1, len(CONTROLLER_STATE_COLUMNS), ",".join(CONTROLLER_STATE_COLUMNS))
        if settings.state_period_s > 0:
            self.create_timer(settings.state_period_s, self.publish_state)
        self.diagnostics = Diagnostics(self, settings.diagnostics_period_s, self._health)
        self.get_logger().info(f"valve_controller up: strategy={config.strategy}{self._gains_text(config)} "
                               f"period={config.dt * 1e3:.3f} ms" + (f" (gain_set {p['gain_set']})" if p["gain_set"] else "")
                               + f"; {self.realtime.describe()}")
        self._check_gain_set_period(str(p["gain_set"] or ""), config.dt)

    def _check_gain_set_period(self, name: str, dt: float) -> None:
        """Say so when a Table 1 set runs at a period longer than the one its margins hold at (SAFE_PERIOD_S)."""
        safe = SAFE_PERIOD_S.get(name.strip().lower().replace(" ", "_"))
        if safe is not None and dt > safe * (1 + 1e-9):
            better = default_gain_set(dt)
            self.get_logger().warning(
                f"gain_set {name} at {dt * 1e3:g} ms: its margins hold only up to {safe * 1e3:g} ms (Table 1 was tuned at "
                f"0.1 ms); at this period it may swing rail to rail. Use {better or 'ol_hc (no Table 1 set is safe)'}, "
                "or gains from valve_tune for this period")

    def _check_inverse_cost(self, ctl: ValveController) -> None:
        """Say so when the model's inverse is solved each step at a period too short for it to be sure."""
        if solved_each_step(ctl.ff_inverse) and ctl.config.dt < SOLVED_INVERSE_MIN_PERIOD_S:
            self.get_logger().warning(
                f"the model's inverse is solved each step ({describe_inverse(ctl.ff_inverse)}): tens of us per "
                f"pass, two passes per period; at {ctl.config.dt * 1e3:g} ms the loop may overrun "
                f"(bench/core_speed.py; periods >= {SOLVED_INVERSE_MIN_PERIOD_S * 1e3:g} ms are safe)")

    @staticmethod
    def _gains_text(config: ControllerConfig) -> str:
        if not has_feedback(config.strategy):
            return ""  # the gains are not used
        g = config.gains
        return f" kp={g.kp} ki={g.ki}" + (f" kd={g.kd}" if g.kd else "")

    # ------------------------------------------------------------------ loop
    def on_measurement(self, y: float) -> Optional[float]:
        """One control period: the command [V] for the measured position ``y`` [m] (None: none)."""
        if not math.isfinite(y):
            if self._say_non_finite.due():
                self.get_logger().warning(f"ignored non-finite spool_position {y!r}")
            return None
        self._last_position_m = y
        if not self.enabled or self.hardware_fault is not None:
            return None
        ctl = self.controller
        trips = ctl.guard_trips
        r = self.ramp.step()
        v = ctl.step(r, y)
        self._last_reference_m, self._last_command_v = r, v
        if ctl.guard_trips != trips:
            self.get_logger().warning(
                f"oscillation guard: commands on both rails within {GUARD_WINDOW_S * 1e3:.0f} ms (the loop "
                f"oscillates, e.g. measurements delayed by a busy computer): feedforward only, integrator frozen, "
                f"for {ctl.guard_hold_s:.2f} s (trip {ctl.guard_trips})")
            self._guarding = True
        elif self._guarding and not ctl.in_fallback:
            self._guarding = False
            self.get_logger().info("oscillation guard: feedback back in charge (bumpless)")
        return v

    # ------------------------------------------------------------------ what it is doing
    def publish_state(self) -> np.ndarray:
        """One row of CONTROLLER_STATE_COLUMNS on ~/controller_state (the latest period)."""
        y = self._last_position_m if self._last_position_m is not None else float("nan")
        ctl = self.controller
        row = self._state.rows[0]   # the message's own data, refilled in place (ros.messages.SamplesBuffer)
        clock = self.get_clock()   # ROS time: simulated where /clock drives it, else the system clock, read directly
        row[0] = clock.now().nanoseconds * 1e-9 if clock.ros_time_is_active else time.time()
        row[1], row[2], row[3], row[4] = self._last_reference_m, y, self._last_reference_m - y, self._last_command_v
        row[5], row[6], row[7] = STRATEGIES.index(ctl.config.strategy), ctl.in_fallback, self.enabled
        self.state_pub.publish(self._state.message)
        return self._state.rows.copy()

    def _health(self) -> tuple[str, str, dict]:
        """(level, message, values) for /diagnostics: the oscillation guard, the model in force, refused and
        clamped references."""
        ctl = self.controller
        comp = ctl.compensation
        parts = [f"GPIM {comp.gpim.n} operators"] + [name for name, on in (
            ("asymmetric", comp.gpim.b0 is not None), ("rate-dependent", comp.rate_dependent),
            ("creep", comp.creep.active), ("saturation map", comp.output_map.active),
            ("dynamic feedforward", comp.dynamic_feedforward)) if on]
        lo, hi = ctl.reachable_m
        g = ctl.config.gains
        values = {"strategy": ctl.config.strategy, "kp": g.kp, "ki": g.ki, "kd": g.kd, "enabled": self.enabled,
                  "model": ", ".join(parts), "reachable_m": f"{lo:.6g} .. {hi:.6g}", "guard_trips": ctl.guard_trips,
                  "references_rejected": self.rejected_references, "references_clamped": self.clamped_references,
                  "period_s": ctl.config.dt}
        if self.hardware_fault is not None:
            values["hardware"] = self.hardware_fault
            return "WARN", f"holding: the hardware is in fault ({self.hardware_fault}): no commands, integrator held", values
        if self.enabled and ctl.in_fallback:
            return "WARN", f"oscillation guard: feedforward only (trip {ctl.guard_trips})", values
        if not self.enabled:
            return "OK", "disabled: another node commands the valve", values
        if self._last_position_m is None:
            return "OK", f"{ctl.config.strategy}: waiting for spool_position", values
        return "OK", f"{ctl.config.strategy}: in control", values

    def _on_hardware_state(self, msg: String) -> None:
        """The hardware's state: while it is in fault no period runs (the integrator holds); when it leaves it,
        control starts afresh from the controller's centre voltage (the hardware's default safe voltage)."""
        fault = None if msg.data == "ok" else msg.data
        if fault == self.hardware_fault:
            return
        if fault is not None:
            self.get_logger().warning(f"hardware {fault}: holding (no commands, integrator held)")
        else:
            self.controller.reset(None, self._last_position_m)
            self.get_logger().info("hardware fault cleared: control starts afresh from the centre voltage")
        self.hardware_fault = fault

    @property
    def command_has_listener(self) -> bool:
        """Whether another node subscribes to voltage_command (this node's own watch while disabled aside)."""
        return self.command_pub.get_subscription_count() > (self._command_watch is not None)

    def _on_position(self, msg: Float64) -> None:
        if not self.command_has_listener:
            # the command would go nowhere (e.g. the hardware's subscription is not matched yet): stepping
            # would wind the controller up against a valve that never got the command
            if not self._said_no_listener:
                self._said_no_listener = True
                self.get_logger().info("nobody subscribes to voltage_command yet: measurements wait for a listener")
            return
        v = self.on_measurement(msg.data)
        if v is not None:
            self.command_pub.publish(Float64(data=v))

    def direct_link(self) -> Callable[[float], Optional[float]]:
        """Composed mode: stop listening to ``spool_position`` and publishing ``voltage_command``; the
        hardware node in this process calls the returned function instead (see
        ``ValveHardwareNode.attach_controller``)."""
        if self._position_sub is not None:
            self.destroy_subscription(self._position_sub)
            self._position_sub = None
        self.get_logger().info("composed: position and command pass by function call (no DDS in the loop)")
        return self.on_measurement

    def _on_command_seen(self, msg: Float64) -> None:
        """While disabled: what others command is what the valve gets (to resume from it, and to notice when
        it stops)."""
        if not self.enabled and math.isfinite(msg.data):
            self._applied_v = msg.data
            self._foreign_command_at = time.monotonic()

    def _on_samples(self, msg: Float64MultiArray) -> None:
        """While disabled: the hardware's own account of the applied voltage (e.g. its safe voltage after its
        watchdog fired)."""
        try:
            rows = samples_from_message(msg)
        except ValueError:
            return
        if rows.shape[0]:
            if self._applied_path is None and not self.enabled and math.isfinite(rows[0, 1]):
                self._applied_path = AppliedPath(float(rows[0, 1]))   # started disabled: from where the samples begin
            if self._applied_path is not None:
                self._applied_path.extend(rows[:, 1])
            v = float(rows[-1, 1])
            if math.isfinite(v):
                self._applied_v = v

    def _watch_applied_voltage(self, on: bool) -> None:
        """While disabled, follow ``voltage_command`` (another node's) and ``samples``; while enabled, neither (the
        commands would be our own, one more message to take every period)."""
        if on and self._samples_sub is None:
            self._samples_sub = self.create_subscription(Float64MultiArray, "samples", self._on_samples, SAMPLES_QOS)
            self._command_watch = self.create_subscription(Float64, "voltage_command", self._on_command_seen,
                                                           COMMAND_QOS)
        elif not on and self._samples_sub is not None:
            self.destroy_subscription(self._samples_sub)
            self.destroy_subscription(self._command_watch)
            self._samples_sub = self._command_watch = None

    def _check_handback(self) -> None:
        """Disabled, and the node that took over stopped commanding: take control back."""
        if self.enabled or self._foreign_command_at is None:
            return
        silent = time.monotonic() - self._foreign_command_at
        if silent < self.handback_timeout_s:
            return
        self.get_logger().warning(f"no voltage_command from the node that took over for {silent:.2f} s "
                                  f"(handback_timeout_s {self.handback_timeout_s} s): taking control back")
        result = self.set_parameters([Parameter("enabled", value=True)])[0]
        if not result.successful:
            self.get_logger().error(f"could not take control back: {result.reason}")
            self._foreign_command_at = time.monotonic()  # try again after another timeout

    def _set_enabled(self, enabled: bool) -> None:
        if enabled == self.enabled:
            return
        self.enabled = enabled
        if enabled:
            ctl = self.controller
            v = ctl.last_command_v if self._applied_v is None else self._applied_v
            v = min(max(v, ctl.config.command_min_v), ctl.config.command_max_v)
            path = self._applied_path
            # the operators where the voltages applied meanwhile left them (the hardware's samples), from the state
            # the controller left them in: an identification's wide swings leave the valve up to the loop's width
            # from a synchronised state at the last voltage, which OL HC would keep as its error
            state = path.state(ctl.model) if path is not None and len(path.points()) > 1 else None
            ctl.reset(v, self._last_position_m, state)
            if self._last_position_m is not None:
                self.ramp.hold(self._last_position_m)
            self._watch_applied_voltage(False)
            self._foreign_command_at = None
            self._applied_path = None
            self.get_logger().info(f"enabled: resuming from the applied {v:.4g} V" + (
                f" (operators where the {len(path.points()) - 1} turning point(s) applied since left them)"
                if state is not None else " (operators in the state of a synchronised valve at that voltage)"))
        else:
            ctl = self.controller
            self._applied_v = ctl.last_command_v
            self._applied_path = AppliedPath(ctl.last_command_v, ctl.ff_inverse.forward_state())
            self._foreign_command_at = None
            self._watch_applied_voltage(True)
            self.get_logger().info("disabled: publishing no commands")

    def _on_reference(self, msg: Float64) -> None:
        r, why = self.controller.admit_reference(msg.data)
        if r is None:
            self.rejected_references += 1
            self.get_logger().warning(f"rejected {why}")
            return
        if why:
            self.clamped_references += 1
            self.get_logger().warning(why)
        self.ramp.set_target(r)

    # ------------------------------------------------------------------ parameters
    def _expand_gain_set(self, params: list[Parameter]) -> list[Parameter]:
        """A new gain_set brings its strategy and gains into the same update (so they read back what runs)."""
        named = {prm.name for prm in params}
        for prm in params:
            if prm.name == "gain_set" and isinstance(prm.value, str) and prm.value:
                try:
                    values = gain_set_values(prm.value)
                except ValueError:
                    return params  # refused with its reason by _on_parameters
                params = params + [Parameter(k, value=v) for k, v in values.items() if k not in named]
        return params

    def _on_parameters(self, params) -> SetParametersResult:
        p = parameter_values(self)
        for prm in params:
            p[prm.name] = prm.value
        try:
            config, model = settings_from_parameters(p)
            settings = ControllerNodeSettings.from_specs(SPECS, p)
        except ValueError as exc:
            return refuse(self, f"({', '.join(x.name for x in params)}): {exc}")
        ctl = self.controller
        changed = {x.name for x in params}
        if "initial_reference_m" in changed:
            return refuse(self, "initial_reference_m applies at start-up only (send position_reference instead)")
        old = ctl.config
        new_range = (config.command_min_v, config.command_max_v, config.centre_voltage_v)
        range_changed = new_range != (old.command_min_v, old.command_max_v, old.centre_voltage_v)
        if changed & MODEL_PARAMETERS.keys():
            if range_changed:   # together: the new model may know only the new range
                ctl.set_model_and_command_range(model, *new_range)
            else:
                ctl.set_model(model)
            self.get_logger().info(f"new model parameters in use ({describe_inverse(ctl.ff_inverse)})")
            self._check_inverse_cost(ctl)
        elif range_changed:
            ctl.set_command_range(*new_range)
        if range_changed:
            self.get_logger().info(f"command range {config.command_min_v:g}..{config.command_max_v:g} V "
                                   f"(centre {config.centre_voltage_v:g} V) in use (bumpless)")
        if config.derivative_filter_s != old.derivative_filter_s:
            ctl.set_derivative_filter(config.derivative_filter_s)
            self.get_logger().info(f"derivative filter {config.derivative_filter_s:g} s in use")
        if (config.strategy, config.gains) != (old.strategy, old.gains):
            ctl.set_strategy(config.strategy, config.gains)
            self.get_logger().info(f"strategy={config.strategy}{self._gains_text(config)} (bumpless)")
        self.ramp.set_ramp(settings.reference_ramp_s, config.dt)
        self.handback_timeout_s = settings.handback_timeout_s
        if "enabled" in changed:
            self._set_enabled(settings.enabled)
        return SetParametersResult(successful=True)


def main(args=None) -> int:
    return run_node(ValveControllerNode, "valve_controller", args, specs=CONTROLLER_PARAMETERS)


if __name__ == "__main__":
    sys.exit(main())
