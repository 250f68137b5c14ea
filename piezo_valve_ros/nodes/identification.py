"""``valve_identification``: runs experiments on the rig, records them, refits, pushes the new model.

The ``plan`` (comma-separated, run in order once the rig answers) is made of:

``train``     the controller is disabled and this node drives ``voltage_command`` one value per
              ``spool_position`` (so it works in lockstep and in real time): the experiment of
              ``core.sim.signals.rig_training_voltage`` (synchronising sine, step-and-hold and multisine
              segments before and after the paper's training signal, and a closing synchronising sine
              that leaves the valve in a known state at the centre); then the controller is re-enabled
              and resumes from there.
``refit``     ``valve_identify``'s analysis of the last training bag (last 30 % held out), the model
              pushed to the controller with one atomic parameter request (all or nothing), then the
              parameters file written atomically.  A failed refit or a rejected push leaves the last
              good parameters (file and controller) untouched.
``tune``      PID gains for ``tune_strategy`` chosen on the last refit's model (``core.tuning``: margins of the
              linearised loop with one period of delay, the paper's steps on the model with at most
              ``tune_max_overshoot_pct`` overshoot, the controller's period, range and D filter), pushed to
              the controller with one atomic request (strategy, kp, ki, kd, derivative_filter_s; a Table 1
              gain set cleared) and added to the parameters file.  Gains that
              cannot meet the limits are reported and nothing is pushed.
``validate``  the controller (switched to ``validation_strategy``, default ``ol_hc``) tracks the paper's
              validation demand (eq. 12) sent on ``position_reference``; the tracking error is logged.

On a free-running lockstep rig (the hardware's ``clock`` lockstep, ``lockstep.step_budget`` -1) the rig is
paused (budget 0) while no experiment runs: refit and tune take no simulated time and get the CPU the
lockstep loop would spin on.  It is resumed for each experiment and when the plan ends or the node stops.
A rig on the wall clock, one paced by someone else (budget >= 0) or a hardware node that does not answer is
left alone.

Every experiment is recorded to its own crash-safe rosbag2 bag under ``bag_dir`` (``samples``,
``voltage_command``, ``spool_position``, ``position_reference``).  ``bag_dir/summary.json`` lists what
each step did and measured.
"""
from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path
from typing import Optional

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.exceptions import InvalidServiceNameException
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float64

from ..core.defaults import BAG_STORAGE, analysis_threads
from ..io.bags import STORAGES, BagError
from ..core.identification.records import IdentificationError
from ..core.identification.report import to_json
from ..core.metrics import error_figures
from ..core.sim.signals import rig_training_voltage, validation_reference_m
from ..core.control.strategies import LOOP_SETTINGS, STRATEGIES, loop_settings
from ..core.tuning.tuner import OVERSHOOT_LIMIT_PCT, TUNABLE_STRATEGIES, TuningError, TuningLimits, tune
from ..identify import (summary_json, compensation, controller_parameters, controller_parameters_yaml, identify_bags, report_json,
                        write_atomically)
from ..rig.client import get_parameter_values, wait_future, wait_until_answering
from ..rig.recording import RigRecorder
from ..runtime.memory import keep_freed_memory
from ..ros import (COMMAND_QOS, CONTROL_PERIOD, REFERENCE_QOS, SENSOR_QOS, declare_all, parameter_values,
                   refuse_undeclared, run_node)
from ..core.validation import ParameterSpec, Settings, from_parameter
from ..core.model.drive import CENTRE_VOLTAGE_V

STEPS = ("train", "refit", "tune", "validate")
PROGRESS_PERIOD_S = 5.0   # default: a running experiment logs its progress this often [s]
HARDWARE_ANSWER_S = 10.0  # the hardware node's parameter services answer within this or are taken to be absent [s]
RELEASE_ANSWER_S = 2.0    # on the way out, a paused rig's release is waited for this long [s]
LOCKSTEP_BUDGET = "lockstep.step_budget"


class _Player:
    """Values sent one per ``spool_position`` message; ``done`` is set after the last one."""

    def __init__(self, values: np.ndarray, publisher, record=None):
        self.values = np.asarray(values, float)
        self.publisher = publisher
        self.record = record
        self.index = 0
        self.positions: list[float] = []
        self.done = threading.Event()

    def next(self) -> None:
        if self.index >= self.values.size:
            self.done.set()
            return
        value = float(self.values[self.index])
        self.index += 1
        self.publisher.publish(Float64(data=value))
        if self.record is not None:
            self.record(value)


VALIDATION_LEAD_S = 0.5    # the validation demand is eased in from 0 over this long [s]
VALIDATION_RESTORES = ("strategy", "kp", "ki", "kd", "gain_set")   # the controller's, put back after a validation
RIG_WAIT_SAY_S = 10.0      # with no rig in the domain, say what the plan waits for this often [s]
RIG_ANSWER_S = 60.0        # ... and give up after this long

# the plan's settings: start-up only
IDENTIFICATION_PARAMETERS: tuple[ParameterSpec, ...] = (CONTROL_PERIOD,) + tuple(
    ParameterSpec(name, default, text, read_only=True) for name, default, text in [
        ("plan", "train,refit", f"steps run in order: {', '.join(STEPS)}"),
        ("training_s", 30.0, "length of the paper's training signal (eq. 11) in the experiment [s]"),
        ("validation_s", 30.0, "length of the validation demand (eq. 12) [s]"),
        ("validation_amplitude_m", 50e-6, "peak of the validation demand [m]"),
        ("validation_strategy", "ol_hc", "controller strategy during validate"),
        ("tune_strategy", "pid_hc", "strategy the tune step chooses gains for"),
        ("tune_max_overshoot_pct", OVERSHOOT_LIMIT_PCT, "tune: largest overshoot of any paper step [%]"),
        ("time_scale", 1.0, "< 1 compresses the experiments in time (quick runs); 1 = the paper's signals"),
        ("bag_dir", "identification_runs", "one bag per experiment is written below this directory"),
        ("storage", BAG_STORAGE, "bag storage"),
        ("params_out", "", "parameters file written by refit (default: <bag_dir>/fitted.yaml)"),
        ("push", True, "push refitted parameters to the controller"),
        ("keep_worse_refit", "", "a refit whose validation tracks worse than the one before it is taken back, unless "
                                 "this gives the reason to keep it (said in the log)"),
        ("controller", "valve_controller", "name of the controller node (relative to this namespace)"),
        ("hardware", "valve_hardware", "name of the hardware node (relative to this namespace): a free-running "
                                       "lockstep rig is paused while no experiment runs"),
        ("exit_when_done", False, "shut down after the plan (a failed plan always shuts the node down, exit 1)"),
        ("progress_period_s", PROGRESS_PERIOD_S, "a running experiment logs its progress this often [s]"),
    ])
_CHOICES = {"storage": tuple(STORAGES), "tune_strategy": TUNABLE_STRATEGIES, "validation_strategy": STRATEGIES}
IDENTIFICATION_PARAMETERS = tuple(replace(s, choices=_CHOICES.get(s.name, ())) for s in IDENTIFICATION_PARAMETERS)
SPECS = {s.name: s for s in IDENTIFICATION_PARAMETERS}


@dataclass(frozen=True)
class IdentificationSettings(Settings):
    """``valve_identification``'s settings (all start-up only), read from IDENTIFICATION_PARAMETERS by
    ``Settings.from_specs``; the plan's order and the lengths checked together in ``problems``."""

    plan: str
    control_period_s: float            # [s]
    training_s: float                  # [s]
    validation_s: float                # [s]
    validation_amplitude_m: float      # [m]
    validation_strategy: str
    tune_strategy: str
    tune_max_overshoot_pct: float      # [%]
    time_scale: float
    bag_dir: str
    storage: str
    params_out: str
    push: bool
    keep_worse_refit: str
    controller: str
    hardware: str
    exit_when_done: bool
    progress_period_s: float = from_parameter("progress_period_s")   # [s]

    @property
    def steps(self) -> list[str]:
        """The plan's steps in order."""
        return [s.strip() for s in self.plan.split(",") if s.strip()]

    @property
    def bag_path(self) -> Path:
        return Path(self.bag_dir)

    @property
    def params_path(self) -> Path:
        """Where refit and tune write the controller's parameters (default: <bag_dir>/fitted.yaml)."""
        return Path(self.params_out) if self.params_out else self.bag_path / "fitted.yaml"

    @property
    def tune_limits(self) -> TuningLimits:
        return TuningLimits(max_overshoot_pct=self.tune_max_overshoot_pct)

    @property
    def reason_to_keep_worse(self) -> str:
        return self.keep_worse_refit.strip()

    def problems(self) -> list[str]:
        steps, out = self.steps, []
        unknown = [s for s in steps if s not in STEPS]
        if unknown:
            out.append(f"plan: unknown step(s) {', '.join(unknown)}; steps are {', '.join(STEPS)}")
        if "refit" in steps and ("train" not in steps or steps.index("train") > steps.index("refit")):
            out.append("plan: refit needs a train step before it (it refits on that run's bag)")
        if "tune" in steps and ("refit" not in steps or steps.index("refit") > steps.index("tune")):
            out.append("plan: tune needs a refit step before it (it tunes on that model)")
        positive = ("control_period_s", "time_scale", "training_s", "validation_s", "validation_amplitude_m",
                    "progress_period_s")
        out += [f"{name} must be > 0, got {getattr(self, name)!r}" for name in positive if not getattr(self, name) > 0]
        return out + self.tune_limits.problems()


class ValveIdentificationNode(Node):
    def __init__(self, **kwargs):
        super().__init__("valve_identification", **kwargs)
        declare_all(self, IDENTIFICATION_PARAMETERS)
        # before the plan's thread starts: a misspelt ``plan`` would run the default plan (it drives the valve and
        # pushes a model); this node has its process to itself, so every name its command line gives is its own
        refuse_undeclared([self], "valve_identification")
        p = parameter_values(self)
        self.settings = settings = IdentificationSettings.from_specs(SPECS, p)
        if "refit" in settings.steps:
            analysis_threads()   # a bad PIEZO_ANALYSIS_THREADS refuses the plan now, not after its experiments
        self.step_now: Optional[str] = None          # the step running (what Ctrl-C cuts short)
        self.interrupted = False
        self._last_validation: Optional[float] = None   # the last validation's tracking RMS [um]
        self._before_refit: Optional[tuple[dict, Optional[bytes]]] = None   # what a pushed refit replaced

        self.command_pub = self.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        self.reference_pub = self.create_publisher(Float64, "position_reference", REFERENCE_QOS)
        self.recorder = RigRecorder(self, self.settings.storage)
        self._player: Optional[_Player] = None
        self.create_subscription(Float64, "spool_position", self._on_position, SENSOR_QOS)
        self.controller_name, self.controller = self._parameter_client("controller", settings.controller)
        self.hardware_name, self.hardware = self._parameter_client("hardware", settings.hardware)
        self._paces_lockstep = False   # this node pauses the lockstep rig between experiments
        self._rig_paused = False
        self.summary: list[dict] = []
        self.finished = threading.Event()
        self.failed = False
        self._worker = threading.Thread(target=self._run_plan, daemon=True)
        self._worker.start()
        self.get_logger().info(f"valve_identification up: plan {', '.join(settings.steps) or '(none)'}; "
                               f"bags in {settings.bag_path}")

    def _parameter_client(self, parameter: str, value) -> tuple[str, AsyncParameterClient]:
        """(name, client) of the node the ``parameter`` names (ValueError naming the parameter if it names none)."""
        name = str(value)
        if not name:
            raise ValueError(f"{parameter} must name a node (relative to this namespace, or absolute), got ''")
        try:
            return name, AsyncParameterClient(self, name)
        except InvalidServiceNameException as exc:
            raise ValueError(f"{parameter} {name!r} is not a node name: {exc}") from None

    # ------------------------------------------------------------------ recording
    def _start_recording(self, label: str) -> Path:
        stamp = datetime.now().strftime("%Y%m%d_%H%M%S_%f")
        return self.recorder.start(self.settings.bag_path / f"{label}_{stamp}")

    def _stop_recording(self) -> dict:
        return self.recorder.stop()

    def stop(self) -> None:
        """When the node stops (Ctrl-C, SIGTERM, the plan's end): what was cut short said, the open bag closed, a
        paused rig released."""
        if not self.finished.is_set():
            self.interrupted = True
            done = ", ".join(s["step"] for s in self.summary) or "nothing"
            self.get_logger().warning(
                f"interrupted: step {self.step_now or '(waiting for the rig)'} cut short (done: {done}); its bag is "
                f"closed as it stands" + ("; the controller, disabled for training, takes control back after its "
                                          "handback_timeout_s" if (self.step_now or "").startswith("train") else "")
                + ("; the controller still runs the validation strategy until it is set back"
                   if (self.step_now or "").startswith("validate") else ""))
        self._stop_recording()
        self.release_rig()

    # ------------------------------------------------------------------ experiment playback
    def _on_position(self, msg: Float64) -> None:
        player = self._player
        if player is None:
            return
        if player.record is not None and player.index > 0:
            player.positions.append(msg.data)
        player.next()

    def _play(self, player: _Player, what: str) -> None:
        """Run an experiment: the rig resumed for it (when this node paces a lockstep rig) and paused after."""
        self._pause_rig(False)
        try:
            self._play_on_running_rig(player, what)
        finally:
            self._pause_rig(True)

    def _play_on_running_rig(self, player: _Player, what: str) -> None:
        expected_s = player.values.size * self.settings.control_period_s
        self._player = player
        player.next()  # the first value goes out at once (in lockstep it also advances the rig)
        started = last_log = time.monotonic()
        deadline = started + 60.0 + 20.0 * expected_s
        while not player.done.wait(0.5):
            if not rclpy.ok():
                raise RuntimeError("shut down during an experiment")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{what}: rig stopped answering ({player.index}/{player.values.size} periods)")
            now = time.monotonic()
            if now - last_log > self.settings.progress_period_s:
                last_log = now
                done = player.index / player.values.size
                elapsed = now - started
                left = f", about {elapsed * (1 - done) / done:.0f} s left" if done > 0 else ""
                self.get_logger().info(f"{what}: {100 * done:.0f} % ({player.index}/{player.values.size} periods), "
                                       f"{elapsed:.0f} s elapsed{left}")
        self._player = None

    def _set_controller(self, values: dict, atomically: bool = False, timeout_s: float = 10.0) -> tuple[bool, str]:
        if not wait_until_answering(self.controller, timeout_s):  # not just discovered: answering
            return False, "the controller's parameter services do not answer"
        params = [Parameter(k, value=v) for k, v in values.items()]
        future = (self.controller.set_parameters_atomically(params) if atomically
                  else self.controller.set_parameters(params))
        try:
            answer = wait_future(future, timeout_s, "the controller")
        except TimeoutError as exc:
            return False, str(exc)
        results = answer.result if atomically else answer.results
        results = [results] if atomically else results
        bad = [r.reason for r in results if not r.successful]
        return (not bad), "; ".join(bad)

    # ------------------------------------------------------------------ lockstep pacing
    def _take_lockstep_pacing(self) -> None:
        """Pause the rig between experiments when it is a free-running lockstep rig (see the module docstring)."""
        if not wait_until_answering(self.hardware, HARDWARE_ANSWER_S):
            self.get_logger().info(f"the hardware node {self.hardware_name!r} does not answer parameter requests: "
                                   "the rig is not paused between experiments")
            return
        try:
            values = get_parameter_values(self.hardware, ["clock", LOCKSTEP_BUDGET], HARDWARE_ANSWER_S)
        except TimeoutError as exc:
            self.get_logger().info(f"the rig is not paused between experiments ({exc})")
            return
        if values["clock"] != "lockstep" or values[LOCKSTEP_BUDGET] != -1:
            return
        self._paces_lockstep = True
        self._pause_rig(True)
        self.get_logger().info("lockstep rig: paused while no experiment runs (refit and tune take no simulated "
                               "time); resumed for each experiment and at the end")

    def _step_budget_request(self, budget: int):
        """The hardware's ``lockstep.step_budget`` set to ``budget``: the future of the request."""
        return self.hardware.set_parameters([Parameter(LOCKSTEP_BUDGET, value=budget)])

    def _set_step_budget(self, budget: int, timeout_s: float = 10.0) -> None:
        answer = wait_future(self._step_budget_request(budget), timeout_s, f"{self.hardware_name} {LOCKSTEP_BUDGET}")
        result = answer.results[0]
        if not result.successful:
            raise RuntimeError(f"{self.hardware_name} refused {LOCKSTEP_BUDGET} := {budget}: {result.reason}")

    def _pause_rig(self, paused: bool) -> None:
        if self._paces_lockstep and paused != self._rig_paused:
            self._set_step_budget(0 if paused else -1)
            self._rig_paused = paused

    def release_rig(self) -> None:
        """Leave a paused lockstep rig running, also after the spin loop ended (Ctrl-C): the request is answered
        through this node's executor, spun here for at most RELEASE_ANSWER_S."""
        if not self._rig_paused:
            return
        self._rig_paused = False
        future = self._step_budget_request(-1)
        if self.executor is not None and self.context.ok():
            self.executor.spin_until_future_complete(future, timeout_sec=RELEASE_ANSWER_S)
        if not future.done() or not future.result().results[0].successful:
            self.get_logger().warning(f"the lockstep rig may still be paused: set {self.hardware_name} "
                                      f"{LOCKSTEP_BUDGET}:=-1")

    def _plan_length(self) -> str:
        """One line: how long the plan's experiments run in the rig's time, and what that means on a lockstep rig."""
        st = self.settings
        train_s = rig_training_voltage(st.control_period_s, st.training_s, st.time_scale).size * st.control_period_s
        validate_s = st.validation_s * st.time_scale + VALIDATION_LEAD_S
        seconds = sum(train_s if step == "train" else validate_s if step == "validate" else 0.0 for step in st.steps)
        return (f"plan: {seconds:.0f} s of experiments in the rig's time (train {train_s:.0f} s, validate "
                f"{validate_s:.0f} s each); on the wall clock as long, on a lockstep rig at its own pace (the "
                "progress lines say how far); refit and tune take seconds to a minute each")

    # ------------------------------------------------------------------ steps
    def _step_train(self) -> dict:
        st = self.settings
        values = rig_training_voltage(st.control_period_s, st.training_s, st.time_scale)
        ok, reason = self._set_controller({"enabled": False})
        if not ok:
            raise RuntimeError(f"cannot disable the controller: {reason}")
        bag = self._start_recording("train")
        self.get_logger().info(f"train: {values.size} periods ({values.size * st.control_period_s:.1f} s), recording {bag}")
        try:
            self._play(_Player(values, self.command_pub), "train")
        finally:
            time.sleep(0.3)  # the last samples batch
            counts = self._stop_recording()
            ok, reason = self._set_controller({"enabled": True})
            if not ok:
                self.get_logger().error(f"could not re-enable the controller: {reason}")
            self.command_pub.publish(Float64(data=CENTRE_VOLTAGE_V))  # hand over: the controller answers the next position
        self.last_train_bag = bag
        self.get_logger().info(f"train: done, {counts} messages recorded")
        return {"step": "train", "bag": str(bag), "periods": int(values.size), "messages": counts}

    def _step_refit(self) -> dict:
        """Analyse the last training bag, push the compensation model to the controller (one atomic request),
        and only then write the parameters file: a refused push or failed refit leaves the last good file
        and the controller as they were.  The report goes into the training bag either way."""
        bag = getattr(self, "last_train_bag", None)
        if bag is None:
            raise RuntimeError("refit needs a train step before it")
        self.get_logger().info(f"refit: analysing {bag}")
        try:
            analysis, _ = identify_bags(bag, log=lambda s: self.get_logger().info(f"refit: {s}"))
            comp = compensation(analysis)
        except (BagError, IdentificationError) as exc:
            self.get_logger().error(f"refit failed, last good parameters kept: {exc}")
            return {"step": "refit", "ok": False, "reason": str(exc)}
        report = analysis.report
        write_atomically(Path(str(bag)) / "report.json", report_json(analysis))
        for name, why in comp.refused.items():
            self.get_logger().warning(f"refit: {why}")
        values = controller_parameters(comp)
        before = None
        if self.settings.push:   # what the push replaces: a validation that tracks worse after it takes it back
            try:
                before = (self._controller_values(list(values)),
                          self.settings.params_path.read_bytes() if self.settings.params_path.exists() else None)
            except (RuntimeError, TimeoutError) as exc:
                self.get_logger().warning(f"refit: the controller's model before the push could not be read ({exc}): "
                                          f"a worse validation after it cannot take it back")
        pushed, reason = self._set_controller(values, atomically=True) if self.settings.push else (False, "push disabled")
        if pushed:
            self._before_refit = before
        if pushed or not self.settings.push:
            write_atomically(self.settings.params_path, controller_parameters_yaml(comp, str(bag), report))
            self.last_refit = (comp, str(bag), report)  # what a tune step tunes on
        if pushed:
            self.get_logger().info(f"refit: model {comp.model.name} pushed to the controller; parameters in "
                                   f"{self.settings.params_path}")
        elif self.settings.push:
            self.get_logger().warning(f"refit: model not pushed ({reason}); last good parameters file kept")
        return {"step": "refit", "ok": True, "model": comp.model.name, "effects_added": list(report.effects_added),
                "baseline_validate": to_json(report.baseline.validate), "final_validate": to_json(report.final.validate),
                "params_out": str(self.settings.params_path), "pushed": pushed, "reason": reason}

    def _controller_values(self, names: list[str], timeout_s: float = 10.0) -> dict:
        """The running controller's values of ``names`` (RuntimeError when it does not answer)."""
        if not wait_until_answering(self.controller, timeout_s):
            raise RuntimeError("the controller's parameter services do not answer")
        return get_parameter_values(self.controller, names, timeout_s)

    def _step_tune(self) -> dict:
        """Gains for ``tune_strategy`` on the last refit's model, at the controller's period and command range;
        pushed atomically, then the parameters file rewritten with them.  No gains meeting the limits, or a
        refused push: reported, the controller and the file left as they were."""
        last = getattr(self, "last_refit", None)
        if last is None:
            self.get_logger().error("tune: no refitted model to tune on (the refit failed or was not pushed)")
            return {"step": "tune", "ok": False, "reason": "no refitted model"}
        comp, bag, report = last
        config = loop_settings(self._controller_values(list(LOOP_SETTINGS)), self.settings.tune_strategy)
        try:
            result = tune(self.settings.tune_strategy, comp.controller_model, config.dt, self.settings.tune_limits, config,
                          log=lambda s: self.get_logger().info(s))
        except TuningError as exc:
            self.get_logger().error(f"tune: {exc}; the controller's gains are unchanged")
            return {"step": "tune", "ok": False, "reason": str(exc)}
        gains = result.parameters()
        pushed, reason = self._set_controller(gains, atomically=True) if self.settings.push else (False, "push disabled")
        if pushed or not self.settings.push:
            write_atomically(self.settings.params_path, controller_parameters_yaml(
                comp, bag, report, extra=gains, extra_comments=[f"tuned: {result.summary()}"]))
        if pushed:
            self.get_logger().info(f"tune: gains pushed to the controller; parameters in {self.settings.params_path}")
        elif self.settings.push:
            self.get_logger().warning(f"tune: gains not pushed ({reason}); parameters file unchanged")
        m, s = result.margins, result.score
        finite = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731  (JSON has no infinity)
        return {"step": "tune", "ok": True, "strategy": result.strategy, "kp": result.gains.kp, "ki": result.gains.ki,
                "kd": result.gains.kd, "gain_margin_db": finite(m.gain_margin_db),
                "phase_margin_deg": finite(m.phase_margin_deg),
                "noise_gain": m.noise_gain, "model_settling_ms": 1e3 * s.settling_time_s,
                "model_overshoot_pct": s.worst_overshoot_pct, "pushed": pushed, "reason": reason}

    def _step_validate(self) -> dict:
        # the controller's settings, put back after the validation: the rig is left as the plan found it
        settings = self._controller_values(list(VALIDATION_RESTORES))
        # one atomic request: an active gain_set refuses a strategy unless the same update clears it
        ok, reason = self._set_controller({"enabled": True, "strategy": self.settings.validation_strategy, "gain_set": ""},
                                          atomically=True)
        if not ok:
            raise RuntimeError(f"cannot set the controller up for validation: {reason}")
        try:
            result = self._validate()
        finally:
            self._restore_controller(settings)
        return self._judge_refit(result)

    def _restore_controller(self, settings: dict) -> None:
        """The strategy and gains the controller had before a validation (a gain set as a gain set), in one request."""
        back = ({"gain_set": settings["gain_set"]} if settings["gain_set"] else
                {"gain_set": "", **{k: settings[k] for k in ("strategy", "kp", "ki", "kd")}})
        ok, reason = self._set_controller(back, atomically=True)
        said = (f"gain set {settings['gain_set']}" if settings["gain_set"] else
                f"strategy {settings['strategy']}, kp {settings['kp']:g}, ki {settings['ki']:g}, kd {settings['kd']:g}")
        if ok:
            self.get_logger().info(f"validate: the controller back on {said}, as before the validation")
        else:
            self.get_logger().error(f"validate: the controller could not be put back on {said} ({reason}): it runs "
                                    f"{self.settings.validation_strategy}")

    def _judge_refit(self, result: dict) -> dict:
        """A validation after a pushed refit that tracks worse than the one before it: the model the refit replaced
        pushed back (and its parameters file), unless ``keep_worse_refit`` gives the reason to keep it."""
        before, now = self._last_validation, result["rms_um"]
        self._last_validation = now
        replaced, self._before_refit = self._before_refit, None
        if replaced is None or before is None:
            return result
        if now <= before:
            self.get_logger().info(f"validate: the refit cut the tracking error RMS {before:.3f} -> {now:.3f} um")
            return {**result, "refit_judged": "better"}
        if self.settings.reason_to_keep_worse:
            self.get_logger().warning(f"validate: the refit made tracking worse ({before:.3f} -> {now:.3f} um RMS); "
                                      f"kept as told: {self.settings.reason_to_keep_worse}")
            return {**result, "refit_judged": "worse, kept: " + self.settings.reason_to_keep_worse}
        values, file_bytes = replaced
        ok, reason = self._set_controller(values, atomically=True)
        if ok and file_bytes is not None:
            write_atomically(self.settings.params_path, file_bytes.decode())
        self.get_logger().warning(
            f"validate: the refit made tracking worse ({before:.3f} -> {now:.3f} um RMS): " +
            ("the model before it pushed back" + (" and its parameters file restored" if file_bytes is not None else "")
             if ok else f"the model before it could NOT be pushed back ({reason})")
            + " (keep_worse_refit:=<reason> keeps such a refit)")
        self._last_validation = before if ok else now
        return {**result, "refit_judged": "worse, taken back" if ok else "worse, could not be taken back"}

    def _validate(self) -> dict:
        st = self.settings
        ref = validation_reference_m(st.control_period_s / st.time_scale, st.validation_s, st.validation_amplitude_m * 1e6)
        lead = max(int(VALIDATION_LEAD_S / st.control_period_s), 1)  # ease in from 0 (the validation demand starts off 0)
        ref = np.concatenate((ref[0] * np.linspace(0.0, 1.0, lead), ref))
        bag = self._start_recording("validate")
        sent: list[float] = []
        player = _Player(ref, self.reference_pub, record=sent.append)
        try:
            self._play(player, "validate")
        finally:
            time.sleep(0.3)
            self._stop_recording()
        # the position answering reference k arrives with the position after it
        n = min(len(player.positions), len(sent) - 1)
        err_um = (np.asarray(player.positions[:n]) - np.asarray(sent[:n])) * 1e6
        err_um = err_um[lead:]  # scored on the demand itself
        span = float(np.ptp(ref) * 1e6)
        demand_um = np.asarray(sent[:n])[lead:] * 1e6
        figures = error_figures(demand_um + err_um, demand_um, span)
        self.get_logger().info(f"validate ({self.settings.validation_strategy}): tracking error RMS {figures.rms_um:.3f} um, "
                               f"peak {figures.peak_um:.3f} um ({figures.peak_pct:.2f} % of the {span:.1f} um demand "
                               f"range), fit {figures.fit_pct:.1f} % (NRMSE)")
        return {"step": "validate", "strategy": self.settings.validation_strategy, "bag": str(bag),
                **{k: float(v) for k, v in vars(figures).items()}}

    def _wait_for_the_rig(self) -> None:
        """Until the controller answers and a hardware node listens to voltage_command, saying every
        RIG_WAIT_SAY_S what the plan waits for (a rig in another ROS_DOMAIN_ID is not there)."""
        import os
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        started = said = time.monotonic()
        while rclpy.ok() and not self.controller.wait_for_services(timeout_sec=1.0):
            if time.monotonic() - said >= RIG_WAIT_SAY_S:
                said = time.monotonic()
                self.get_logger().warning(f"waiting {said - started:.0f} s for the controller {self.controller_name!r} "
                                          f"to answer in ROS_DOMAIN_ID {domain} (is the rig up, in this domain?)")
            if time.monotonic() - started > RIG_ANSWER_S:
                raise RuntimeError(f"no controller answers (parameter services of {self.controller_name!r} not found "
                                   f"in ROS_DOMAIN_ID {domain} within {RIG_ANSWER_S:.0f} s)")
        while self.count_subscribers("voltage_command") == 0 and rclpy.ok():
            time.sleep(0.05)  # the hardware is not up yet
            if time.monotonic() - said >= RIG_WAIT_SAY_S:
                said = time.monotonic()
                self.get_logger().warning(f"waiting {said - started:.0f} s for a hardware node to listen to "
                                          f"voltage_command in ROS_DOMAIN_ID {domain}")

    def _run_plan(self) -> None:
        if not self.settings.steps:
            self.get_logger().info("empty plan: nothing to do")
            self.finished.set()
            if self.settings.exit_when_done:
                self.context.try_shutdown()
            return
        try:
            self._wait_for_the_rig()
            self._take_lockstep_pacing()
            self.get_logger().info(self._plan_length())
            for k, step in enumerate(self.settings.steps):
                self.step_now = f"{step} ({k + 1} of {len(self.settings.steps)})"
                result = getattr(self, f"_step_{step}")()
                self.summary.append(result)
                write_atomically(self.settings.bag_path / "summary.json", summary_json(self.summary))
            self.step_now = None
            self.get_logger().info("plan done")
        except Exception as exc:
            self.failed = True
            self.get_logger().error(f"plan stopped: {exc}")
        finally:
            self._player = None
            self._stop_recording()
            try:
                self._pause_rig(False)
            except (RuntimeError, TimeoutError) as exc:
                self.get_logger().warning(f"the lockstep rig may still be paused ({exc}): set {self.hardware_name} "
                                          f"{LOCKSTEP_BUDGET}:=-1")
            self.finished.set()
            if self.settings.exit_when_done or self.failed:   # a failed plan has nothing left to do: exit 1
                self.context.try_shutdown()


def main(args=None) -> int:
    """Exit code 1 when the plan stopped on an error, 130 when a signal cut it short."""
    keep_freed_memory()   # its refits' arrays (runtime.memory); before ROS starts its threads
    made = []

    def factory():
        made.append(ValveIdentificationNode())
        return made[0]
    code = run_node(factory, "valve_identification", args, on_exit_of=lambda n: n.stop,
                    specs=IDENTIFICATION_PARAMETERS)
    if code:
        return code
    if made and made[0].interrupted:
        return 130
    return 1 if made and made[0].failed else 0


if __name__ == "__main__":
    sys.exit(main())
