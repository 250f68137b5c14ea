"""``valve_monitor``: valve health from everyday operation, without an experiment or an interruption.

It listens to ``samples`` and to the controller's model parameters, runs that model on the applied voltage
and judges its residual on sliding windows against the sensor noise (``core/monitoring/health.py``: OK,
WARN, ERROR, or STALE when a window does not excite the valve enough to judge).  Each verdict goes to
``/diagnostics`` (diagnostic_msgs, with the figures and what the residual resembles) and to ``~/health`` (one
labelled row: HEALTH_COLUMNS); a change of level is logged in one line.  When the controller's model changes
(a refit pushed), the monitor follows it.  A separate process: it costs the control loop nothing.

``refit_when`` (never, warn, error; default never): at that level it asks for a refit.  What the operating
data determine it pushes itself (``core/monitoring/refits.py``): an offset the model lacks (a drift), and a gain
change where the window's excitation tells it from an offset and its held-out part confirms it; only while the
controller is enabled with its oscillation guard off, under a strategy that runs the model (read on
``~/controller_state``), and at most once a window.  Each push sets the controller's whole model in one atomic
parameter change, is logged with its evidence, announced on ``/diagnostics`` and on ``~/pushes`` (one labelled
row: PUSH_COLUMNS, for the day's bag), and checked on the next window: one that leaves it worse than the model
it replaced is undone.  Anything else needs a designed experiment: it logs the identification plan to run.

    valve_monitor [--ros-args -p window_s:=20.0 -p controller:=valve_controller -r __ns:=/valve1]
"""
from __future__ import annotations

import math
import queue
import threading
from dataclasses import dataclass
from typing import Optional

import numpy as np
from rcl_interfaces.msg import ParameterEvent
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float64MultiArray

from ..core.control.compensation import MODEL_PARAMETERS, CompensationModel
from ..core.monitoring.health import (ERROR_RATIO, MIN_SPAN_V, STEP_S, WARN_RATIO, WINDOW_S, Health, HealthLimits,
                                      HealthMonitor)
from ..core.monitoring.refits import GAIN, PUSH_COLUMNS, REFIT_LEVELS, UNDO, RefitDecision, RefitPolicy, push_row
from ..io.samples import SamplesLayoutError
from ..runtime.memory import keep_freed_memory
from ..core.validation import ParameterSpec, Settings
from ..ros import (DIAGNOSTICS_PERIOD, SAMPLES_QOS, declare_all, Diagnostics, parameter_values, refuse_undeclared,
                   run_node, samples_from_message, samples_message)

HEALTH_COLUMNS = ("end_s", "level", "ratio_to_noise", "structured_rms_um", "residual_mean_um", "noise_um",
                  "voltage_span_v")
MODEL_FETCH_PERIOD_S = 1.0   # the controller's model is asked for this often until it answers (and after changes)

MONITOR_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("controller", "valve_controller", "the controller whose model is watched (a node name, relative "
                  "to this node's namespace, or absolute)", read_only=True),
    ParameterSpec("window_s", WINDOW_S, "each verdict judges the last this long of operation [s]", read_only=True,
                  low=1.0, high=3600.0),
    ParameterSpec("step_s", STEP_S, "a verdict this often [s] (at most window_s)", read_only=True, low=0.1, high=600.0),
    ParameterSpec("warn_ratio", WARN_RATIO, "WARN when the structured residual exceeds this many times the sensor "
                  "noise", read_only=True, low=0.1, high=1000.0),
    ParameterSpec("error_ratio", ERROR_RATIO, "ERROR when it exceeds this many times (> warn_ratio)", read_only=True,
                  low=0.1, high=1000.0),
    ParameterSpec("min_span_v", MIN_SPAN_V, "a window whose voltage spans less [V] is not judged (STALE)",
                  read_only=True, low=0.0, high=1000.0),
    ParameterSpec("refit_when", "never", "never, warn or error: at that level push what the operating data "
                  "determine (an offset the model lacks, a gain change its held-out part confirms) to the controller, "
                  "and what an offset push leaves at WARN until OK, each push checked on the next window and undone "
                  "where that is worse; else log the identification plan to run", read_only=True,
                  choices=tuple(REFIT_LEVELS)),
)


SPECS = {s.name: s for s in MONITOR_PARAMETERS}


@dataclass(frozen=True)
class MonitorSettings(Settings):
    """``valve_monitor``'s settings (all read-only), read from MONITOR_PARAMETERS by ``Settings.from_specs``."""

    controller: str
    window_s: float
    step_s: float
    warn_ratio: float
    error_ratio: float
    min_span_v: float
    refit_when: str

    @property
    def limits(self) -> HealthLimits:
        return HealthLimits(self.window_s, self.step_s, self.warn_ratio, self.error_ratio, self.min_span_v)

    def problems(self) -> list[str]:
        return self.limits.problems()


class ValveMonitorNode(Node):
    def __init__(self, **kwargs):
        super().__init__("valve_monitor", **kwargs)
        declare_all(self, MONITOR_PARAMETERS)
        refuse_undeclared([self], "valve_monitor")   # before anything runs (a misspelt name would leave its default)
        settings = MonitorSettings.from_specs(SPECS, parameter_values(self))
        self.limits, self.refit_at = settings.limits, REFIT_LEVELS[settings.refit_when]
        name = settings.controller
        ns = self.get_namespace().rstrip("/")
        self.controller_name = name if name.startswith("/") else f"{ns}/{name}"
        self.client = AsyncParameterClient(self, self.controller_name)
        self.model: Optional[CompensationModel] = None
        self.command_range_v: Optional[tuple[float, float]] = None
        self.monitor: Optional[HealthMonitor] = None
        self.latest: Optional[Health] = None
        self.verdicts = 0
        self._model_wanted, self._request, self._model_values = True, None, None
        self._waiting_said = False
        self._first_sample_s: Optional[float] = None   # the rig's time [s] of the first and the latest sample judged
        self._latest_sample_s: Optional[float] = None
        self.controller_state: dict[str, float] = {}
        self.refits = RefitPolicy(self.refit_at, self.limits.window_s)
        # the windows are judged on a thread of their own: a judgement (its resemblance search) takes a second or two,
        # which would hold up the 1 Hz diagnostics and every other callback of the executor (valve_command status
        # then missed the monitor); samples and model changes reach it in order through one queue
        self._work: queue.SimpleQueue = queue.SimpleQueue()
        self._stopping = threading.Event()
        self._judge = threading.Thread(target=self._judge_loop, name="valve_monitor_judge", daemon=True)
        self._judge.start()
        self.create_subscription(Float64MultiArray, "samples", self._on_samples, SAMPLES_QOS)
        self.create_subscription(Float64MultiArray, f"{self.controller_name}/controller_state", self._on_state, 10)
        self.create_subscription(ParameterEvent, "/parameter_events", self._on_parameter_event, 10)
        self.health_pub = self.create_publisher(Float64MultiArray, "~/health", 10)
        self.pushes_pub = self.create_publisher(Float64MultiArray, "~/pushes", 10)
        self.last_push = ""   # the latest push, as /diagnostics says it
        # with every verdict, and the latest every second as the other nodes report (valve_command status waits
        # for every node of the rig: a monitor heard only at its verdicts, every step_s, could miss its listening)
        self.diagnostics = Diagnostics(self, DIAGNOSTICS_PERIOD.default, self._status)
        self.create_timer(MODEL_FETCH_PERIOD_S, self._fetch_model)
        self.get_logger().info(f"valve_monitor up: watching {self.controller_name}'s model; windows of "
                               f"{self.limits.window_s:g} s every {self.limits.step_s:g} s; WARN at "
                               f"{self.limits.warn_ratio:g}x, ERROR at {self.limits.error_ratio:g}x the noise")

    # ------------------------------------------------------------------ the model in force
    def _on_parameter_event(self, msg: ParameterEvent) -> None:
        if msg.node == self.controller_name and any(
                prm.name in MODEL_PARAMETERS or prm.name in ("command_min_v", "command_max_v")
                for prm in list(msg.new_parameters) + list(msg.changed_parameters)):
            self._model_wanted = True

    def _fetch_model(self) -> None:
        if not self._model_wanted or self._request is not None or not self.client.services_are_ready():
            return
        names = sorted(MODEL_PARAMETERS) + ["command_min_v", "command_max_v"]
        self._model_wanted = False
        self._request = self.client.get_parameters(names)
        self._request.add_done_callback(lambda future: self._on_model(names, future))

    def _on_model(self, names: list[str], future) -> None:
        self._request = None
        try:
            values = {n: parameter_value_to_python(v) for n, v in zip(names, future.result().values)}
            command_range = (float(values.pop("command_min_v")), float(values.pop("command_max_v")))
            model = CompensationModel.from_parameters(values, *command_range)
        except Exception as exc:   # a controller that does not answer or a model that cannot run: say so, ask again
            self.get_logger().warning(f"cannot take {self.controller_name}'s model: {exc}")
            self._model_wanted = True
            return
        if self.model is not None and (values, command_range) == self._model_values:
            return
        first = self.model is None
        self.model, self.command_range_v, self._model_values = model, command_range, (values, command_range)
        self._work.put(("model", model))
        self.get_logger().info(("model in force taken from " if first else "the model in force changed; judged "
                                "afresh from now on: ") + f"{self.controller_name} ({model.gpim.n} operators, "
                               f"commands {command_range[0]:g}..{command_range[1]:g} V)")

    # ------------------------------------------------------------------ samples and verdicts
    def _on_samples(self, msg: Float64MultiArray) -> None:
        try:
            rows = samples_from_message(msg)
        except SamplesLayoutError as exc:
            self.get_logger().warning(f"rejected samples message: {exc}")
            return
        if self.model is None or not len(rows):
            return
        if self._first_sample_s is None:
            dt = float(np.median(np.diff(rows[:, 0]))) if len(rows) > 1 else math.nan
            if not (math.isfinite(dt) and dt > 0):
                self.get_logger().warning("rejected samples message: its times do not give a sample period")
                return
            self._first_sample_s = float(rows[0, 0])
            self._work.put(("start", (self.model, dt, self.command_range_v)))
        self._latest_sample_s = float(rows[-1, 0])
        self._work.put(("rows", rows))

    def _judge_loop(self) -> None:
        """The judging thread: the monitor started, its model changed and its windows judged, in the order the
        executor's callbacks handed them over."""
        while not self._stopping.is_set():
            try:
                kind, item = self._work.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                if kind == "start":
                    model, dt, command_range = item
                    self.monitor = HealthMonitor(model, dt, self.limits, command_range)
                elif kind == "model":
                    if self.monitor is not None:
                        self.monitor.set_model(item)
                elif self.monitor is not None:
                    self._judge_rows(item)
            except Exception as exc:   # a window that cannot be judged: said, and the next one judged
                self.get_logger().error(f"a window could not be judged: {exc!r}")

    def stop(self) -> None:
        """The judging thread ended (the node stops)."""
        self._stopping.set()
        self._judge.join(timeout=5.0)

    def _judge_rows(self, rows: np.ndarray) -> None:
        for health in self.monitor.add(rows):
            self.latest, self.verdicts = health, self.verdicts + 1
            self.health_pub.publish(samples_message(np.array([[
                health.end_s, float(health.level), health.ratio, health.structured_rms_um, health.residual_mean_um,
                health.noise_um, health.voltage_span_v]]), ",".join(HEALTH_COLUMNS)))
            self.diagnostics.publish()
            model = self.model   # the model in force (the executor's thread may replace it meanwhile)
            self._act_on(health, self.refits.decide(health, self.controller_state, model, self.monitor.model), model)

    # ------------------------------------------------------------------ refits
    def _on_state(self, msg: Float64MultiArray) -> None:
        if len(msg.layout.dim) == 2:
            self.controller_state = dict(zip(msg.layout.dim[1].label.split(","), msg.data))

    def _act_on(self, health: Health, decision: Optional[RefitDecision], model: CompensationModel) -> None:
        """Push what the verdict determines (what it changes of the model, in one atomic change), or say why not
        now, that a push was kept, or which experiment would refit."""
        if decision is None:
            return
        if decision.advice:
            self.get_logger().warning(decision.advice)
        elif decision.not_now:
            self.get_logger().info(f"refit not pushed: {decision.not_now}")
        elif decision.kept:
            self.get_logger().info(decision.kept)
        elif decision.pushes:
            row = push_row(health, decision, model)
            before, after = model.to_parameters(), decision.model.to_parameters()
            changed = [Parameter(k, value=v) for k, v in after.items() if v != before.get(k)]
            if not changed:   # the model in force already: no change will come to judge it on
                self.refits.pushed(False)
                self.get_logger().info(f"refit not pushed: the {decision.kind} push changes no parameter of the "
                                       f"model in force")
                return
            future = self.client.set_parameters_atomically(changed)   # what the push changes, in one atomic change
            future.add_done_callback(lambda f: self._pushed(f, decision, row))

    def _pushed(self, future, decision: RefitDecision, row: list[float]) -> None:
        """The controller's answer to a push (a future's done callback: nothing may raise out of it)."""
        try:
            result = future.result().result
        except Exception as exc:
            self.get_logger().warning(f"refit not pushed: {exc}")
            self.refits.pushed(False)
            return
        self.refits.pushed(result.successful)
        if not result.successful:
            self.get_logger().warning(f"refit refused by {self.controller_name}: {result.reason}")
            return
        what = ("undid the last push" if decision.kind == UNDO else
                f"pushed a gain change of {100 * decision.gain_change:+.2f} %" if decision.kind == GAIN else
                f"pushed an offset change of {decision.offset_change_um:+.4f} um")
        self.last_push = (f"{what} at {row[0]:.1f} s: gpim.offset_um {row[3]:.4f} -> {row[4]:.4f} um; "
                          f"{decision.evidence}")
        self.get_logger().info(f"{self.controller_name}: {self.last_push}")
        self.pushes_pub.publish(samples_message(np.array([row]), ",".join(PUSH_COLUMNS)))
        self.diagnostics.publish()

    def _status(self) -> tuple[str, str, dict]:
        if self.latest is None:
            if self.model is None:
                return "STALE", "waiting for the controller's model", {}
            have = 0.0 if self._first_sample_s is None else self._latest_sample_s - self._first_sample_s
            lim = self.limits
            return "STALE", (f"waiting for its first window: {have:.1f} of {lim.first_verdict_s:g} s of the rig's "
                             f"time so far (its prediction settles for step_s {lim.step_s:g} s, then a window of "
                             f"window_s {lim.window_s:g} s; a lockstep rig's time runs at its own pace)"), {}
        return self.latest.level.name, self.latest.message, {**self.latest.values(),
                                                             **({"last_push": self.last_push} if self.last_push else {})}


def main(args=None) -> int:
    keep_freed_memory()   # its windows' analyses (runtime.memory); before ROS starts its threads
    return run_node(ValveMonitorNode, "valve_monitor", args, on_exit_of=lambda n: n.stop, specs=MONITOR_PARAMETERS)


if __name__ == "__main__":
    import sys
    sys.exit(main())
