"""``valve_controller``: the selected strategy with the inverse GPIM, one command per measurement.

Every parameter change is validated as a whole before anything is applied (a rejected update
leaves the controller as it was and returns the reason); strategy and gain changes are bumpless.
``gain_set`` (e.g. ``pid_hc_5``), when non-empty, selects strategy and gains from Table 1 and
overrides ``strategy``/``kp``/``ki``/``kd``.
"""
from __future__ import annotations

import math
import sys
from dataclasses import replace
from typing import Any, Callable, Optional

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from std_msgs.msg import Float64

from ..core.dynamics import PAPER_VALVE_MODEL, ContinuousTF
from ..core.hysteresis import GPIM, PAPER_GPIM, GPIMParams, inverse_problems
from ..core.signals import ReferenceRamp
from ..core.strategies import STRATEGIES, ControllerConfig, CreepModel, PIDGains, ValveController, gain_set
from .common import COMMAND_QOS, SENSOR_QOS, as_float, as_float_list, as_int, declare, run_node

GPIM_KEYS = ("a0", "a1", "alpha", "rho", "tau", "n", "offset_um")


def settings_from_parameters(p: dict[str, Any]) -> tuple[ControllerConfig, GPIM, ContinuousTF, CreepModel]:
    """Controller settings from a flat parameter dict; raises ValueError with every problem found."""
    name = str(p.get("gain_set", "") or "")
    if name:
        try:
            strategy, gains = gain_set(name)
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None
    else:
        strategy = str(p["strategy"])
        gains = PIDGains(as_float("kp", p["kp"]), as_float("ki", p["ki"]), as_float("kd", p["kd"]))
    config = ControllerConfig(
        strategy=strategy, gains=gains, dt=as_float("control_period_s", p["control_period_s"]),
        command_min_v=as_float("command_min_v", p["command_min_v"]),
        command_max_v=as_float("command_max_v", p["command_max_v"]),
        centre_voltage_v=as_float("centre_voltage_v", p["centre_voltage_v"]))
    problems = config.problems()
    thresholds = as_float_list("gpim.thresholds", p.get("gpim.thresholds", []))
    weights = as_float_list("gpim.weights", p.get("gpim.weights", []))
    a0, a1 = as_float("gpim.a0", p["gpim.a0"]), as_float("gpim.a1", p["gpim.a1"])
    offset = as_float("gpim.offset_um", p["gpim.offset_um"])
    model = None
    try:
        if thresholds or weights:  # free form (e.g. from the identification's linear fit)
            model = GPIM(thresholds, weights, a0, a1, offset)
        else:
            model = GPIMParams(a0=a0, a1=a1, alpha=as_float("gpim.alpha", p["gpim.alpha"]),
                               rho=as_float("gpim.rho", p["gpim.rho"]), tau=as_float("gpim.tau", p["gpim.tau"]),
                               n=as_int("gpim.n", p["gpim.n"]), offset_um=offset).model()
        problems += inverse_problems(model)
    except ValueError as exc:
        problems.append(str(exc))
    valve_model = ContinuousTF(tuple(as_float_list("valve_model.num", p["valve_model.num"])),
                               tuple(as_float_list("valve_model.den", p["valve_model.den"])))
    problems += valve_model.problems()
    creep = CreepModel(tuple(as_float_list("creep.time_constants_s", p.get("creep.time_constants_s", []))),
                       tuple(as_float_list("creep.gains", p.get("creep.gains", []))))
    problems += creep.problems()
    if problems:
        raise ValueError("; ".join(problems))
    return config, model, valve_model, creep


class ValveControllerNode(Node):
    def __init__(self, **kwargs):
        super().__init__("valve_controller", **kwargs)
        g = ControllerConfig().gains
        pg = PAPER_GPIM
        for name, default, text in [
            ("strategy", "pid_hc", f"one of {', '.join(STRATEGIES)}"),
            ("gain_set", "", "Table 1 gain set name, overrides strategy/kp/ki/kd when set"),
            ("kp", g.kp, "proportional gain (normalised, um/um)"), ("ki", g.ki, "integral gain [1/s]"),
            ("kd", g.kd, "derivative gain [s] (the paper uses 0)"),
            ("control_period_s", 1e-3, "control period [s]; must match the hardware's (same default)"),
            ("command_min_v", 0.0, "[V]"), ("command_max_v", 10.0, "[V]"), ("centre_voltage_v", 5.0, "[V]"),
            ("reference_ramp_s", 0.0, "reference changes become ramps of this duration [s] (paper: 0.002)"),
            ("initial_reference_m", 0.0, "reference until the first position_reference [m]"),
            ("gpim.a0", pg.a0, "envelope slope [1]"), ("gpim.a1", pg.a1, "envelope offset [V]"),
            ("gpim.alpha", pg.alpha, "threshold spacing [V]"), ("gpim.rho", pg.rho, "weight scale [um/V]"),
            ("gpim.tau", pg.tau, "weight decay [1/V]"), ("gpim.n", pg.n, "number of operators"),
            ("gpim.offset_um", pg.offset_um, "output offset [um]"),
            ("gpim.thresholds", [], "free-form thresholds [V] (empty: 5-parameter form)"),
            ("gpim.weights", [], "free-form weights [um/V] (empty: 5-parameter form)"),
            ("valve_model.num", list(PAPER_VALVE_MODEL.num), "G_v(s) numerator"),
            ("valve_model.den", list(PAPER_VALVE_MODEL.den), "G_v(s) denominator"),
            ("creep.time_constants_s", [], "creep compensation (feedforward path): lag time constants [s]"),
            ("creep.gains", [], "creep compensation: gains [-] (empty or all 0: none)"),
            ("enabled", True, "false: publish no commands (another node drives voltage_command, e.g. identification); "
                              "true again resumes from the last command seen"),
        ]:
            declare(self, name, default, text)
        p = self._values()
        config, model, valve_model, creep = settings_from_parameters(p)
        self.controller = ValveController(config, model, valve_model, creep)
        self.ramp = ReferenceRamp(as_float("initial_reference_m", p["initial_reference_m"]),
                                  as_float("reference_ramp_s", p["reference_ramp_s"]), config.dt)
        self.enabled = bool(p["enabled"])
        self._last_position_m = None
        self._said_no_listener = False
        self._last_foreign_command_v = None
        self.command_pub = self.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        self.create_subscription(Float64, "voltage_command", self._on_command_seen, COMMAND_QOS)
        self._position_sub = self.create_subscription(Float64, "spool_position", self._on_position, SENSOR_QOS)
        self.create_subscription(Float64, "position_reference", self._on_reference, 10)
        self.add_on_set_parameters_callback(self._on_parameters)
        self.rejected_references = 0
        self.get_logger().info(f"valve_controller up: strategy={config.strategy} kp={config.gains.kp} "
                               f"ki={config.gains.ki} period={config.dt * 1e3:.3f} ms")

    def _values(self) -> dict[str, Any]:
        return {name: param.value for name, param in self._parameters.items()}

    # ------------------------------------------------------------------ loop
    def on_measurement(self, y: float) -> Optional[float]:
        """One control period: the command [V] for the measured position ``y`` [m] (None: none)."""
        if not math.isfinite(y):
            self.get_logger().warning(f"ignored non-finite spool_position {y!r}", throttle_duration_sec=1.0)
            return None
        self._last_position_m = y
        if not self.enabled:
            return None
        return self.controller.step(self.ramp.step(), y)

    def _on_position(self, msg: Float64) -> None:
        if self.command_pub.get_subscription_count() <= 1:  # our own _on_command_seen is one of them
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
        """While disabled, remember what others command (to resume from it)."""
        if not self.enabled and math.isfinite(msg.data):
            self._last_foreign_command_v = msg.data

    def _set_enabled(self, enabled: bool) -> None:
        if enabled == self.enabled:
            return
        self.enabled = enabled
        if enabled:
            ctl = self.controller
            v = ctl.last_command_v if self._last_foreign_command_v is None else self._last_foreign_command_v
            v = min(max(v, ctl.config.command_min_v), ctl.config.command_max_v)
            ctl.reset(v, self._last_position_m)
            if self._last_position_m is not None:
                self.ramp.hold(self._last_position_m)
            self.get_logger().info(f"enabled: resuming from {v:.4g} V (operators in the state of a synchronised "
                                   f"valve at that voltage)")
        else:
            self._last_foreign_command_v = None
            self.get_logger().info("disabled: publishing no commands")

    def _on_reference(self, msg: Float64) -> None:
        r = msg.data
        if not math.isfinite(r):
            self.rejected_references += 1
            self.get_logger().warning(f"rejected non-finite position_reference {r!r}")
            return
        self.ramp.set_target(r)

    # ------------------------------------------------------------------ parameters
    def _on_parameters(self, params) -> SetParametersResult:
        p = self._values()
        for prm in params:
            p[prm.name] = prm.value
        try:
            config, model, valve_model, creep = settings_from_parameters(p)
            ramp_s = as_float("reference_ramp_s", p["reference_ramp_s"])
        except ValueError as exc:
            reason = str(exc)
            self.get_logger().warning(f"rejected parameter update ({', '.join(x.name for x in params)}): {reason}")
            return SetParametersResult(successful=False, reason=reason)
        ctl = self.controller
        if config.dt != ctl.config.dt:
            reason = "control_period_s cannot be changed at run time (restart the node)"
            self.get_logger().warning(f"rejected parameter update: {reason}")
            return SetParametersResult(successful=False, reason=reason)
        changed = {x.name for x in params}
        if changed & {f"gpim.{k}" for k in GPIM_KEYS + ("thresholds", "weights")} \
                or changed & {"valve_model.num", "valve_model.den", "creep.time_constants_s", "creep.gains"}:
            ctl.set_model(model, valve_model, creep)
            self.get_logger().info("new model parameters in use")
        if (config.strategy, config.gains) != (ctl.config.strategy, ctl.config.gains) or \
                (config.command_min_v, config.command_max_v, config.centre_voltage_v) != \
                (ctl.config.command_min_v, ctl.config.command_max_v, ctl.config.centre_voltage_v):
            ctl.config = replace(ctl.config, command_min_v=config.command_min_v,
                                 command_max_v=config.command_max_v, centre_voltage_v=config.centre_voltage_v)
            ctl.set_strategy(config.strategy, config.gains)
            self.get_logger().info(f"strategy={config.strategy} kp={config.gains.kp} ki={config.gains.ki} "
                                   f"kd={config.gains.kd} (bumpless)")
        self.ramp.set_ramp(ramp_s, config.dt)
        if "enabled" in changed:
            self._set_enabled(bool(p["enabled"]))
        return SetParametersResult(successful=True)


def main(args=None) -> int:
    return run_node(ValveControllerNode, "valve_controller", args)


if __name__ == "__main__":
    sys.exit(main())
