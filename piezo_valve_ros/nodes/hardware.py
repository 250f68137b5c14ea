"""``valve_hardware``: owns the valve through a backend; applies commands, publishes the position.

Clock modes
  realtime  a timer at ``control_period_s`` reads what the backend sampled on the wall clock
  lockstep  each received command advances the simulation one control period and publishes
            ``spool_position``, ``/clock`` and (batched) ``samples``; deterministic.
            ``lockstep.step_budget`` (-1 = unlimited) lets a test or demo pause the loop after a
            number of periods: commands that arrive while paused are held (the latest wins) and
            applied when budget is granted; ``samples`` is flushed on pausing.
            ``lockstep.max_speed`` (0 = as fast as commands come) keeps the valve's time from running
            more than that many times as fast as the wall clock: an idle rig then costs little CPU.

Faults (``faults``): a backend that raises, samples that are non-finite, implausible or frozen, or no samples at
all latch a fault: the safe voltage is applied (retried every period while writes fail, and said so), commands
are refused, nothing is published as a position, /diagnostics says ERROR naming the fault, and
``hardware_state`` says ``fault: <kind>: <what>``.  Only ``~/reset`` (std_srvs/Trigger; ``valve_command reset``)
leaves it, once the backend writes and reads sound samples again.

Lifecycle (a managed node: ``~/change_state``, ``~/get_state`` as every ROS 2 lifecycle node has them)
  unconfigured  the backend made but not opened (nothing written)
  configure     opens the backend at the safe voltage; nothing is driven, commands are refused
  activate      commands are applied and positions published (started on its own, the node comes up here:
                ``autostart``; ``autostart:=false`` leaves it unconfigured for a lifecycle manager)
  deactivate    the safe voltage; commands refused, nothing published as a position
  cleanup, shutdown  the safe voltage and the backend closed
A latched fault leaves ``active`` (to ``inactive``, at the safe voltage); ``~/reset`` returns to it.  An error in a
transition ends at the safe voltage with the backend closed (``unconfigured``).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
from builtin_interfaces.msg import Time
from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64, Float64MultiArray, String
from std_srvs.srv import Trigger

from ..backends.base import ValveBackend, available_backends, backend_class, backend_parameters
from ..backends.faults import Fault, FaultLimits
from ..runtime.hardware_loop import HardwareLoop, LoopSettings
from ..ros import (COMMAND_QOS, CONTROL_PERIOD, DIAGNOSTICS_PERIOD, MAX_CONTROL_PERIOD_S, SAMPLES_QOS, SENSOR_QOS,
                   STATE_QOS, declare_all, Diagnostics, given_parameter_names, named_with_nearest, Pacing,
                   parameter_values, period_parameter, realtime_settings, realtime_specs, refuse, run_node,
                   samples_message, SamplesBuffer, tighten_timer_slack)
from ..core.model.drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V
from ..core.validation import ParameterSpec, Settings, from_parameter, whole_periods


MAX_COMMAND_TIMEOUT_S = 10.0    # the watchdog may not be stretched beyond this
MIN_TIMEOUT_PERIODS = 2         # ... nor shortened below this many control periods (it would fire between commands)
FIRST_SAMPLE_SETTLE_S = 0.3   # lockstep: a commander matched this long before y_0 is sent (s)
UNANSWERED_REPEAT_S = 1.0     # lockstep: an unanswered position is sent again after this long (s)


HARDWARE_PARAMETERS: tuple[ParameterSpec, ...] = (
    ParameterSpec("autostart", True, "come up configured and active (false: stay unconfigured for a lifecycle "
                  "manager, which drives ~/change_state)", read_only=True),
    ParameterSpec("backend", "sim", "valve backend: sim (default) or one installed under the entry-point group "
                  "piezo_valve_ros.backends", read_only=True),
    ParameterSpec("clock", "realtime", "realtime (wall clock) or lockstep (one period per command)", read_only=True,
                  choices=("realtime", "lockstep")),
    CONTROL_PERIOD,
    ParameterSpec("samples_batch", 1000, "rows per samples message", read_only=True, low=1),
    ParameterSpec("command_timeout_s", 0.5, "no valid command for this long -> safe_voltage [s] "
                  f"(> 0, at least {MIN_TIMEOUT_PERIODS} control periods, at most {MAX_COMMAND_TIMEOUT_S} s)",
                  low=0.0, high=MAX_COMMAND_TIMEOUT_S),
    ParameterSpec("safe_voltage", CENTRE_VOLTAGE_V, "voltage applied on timeout and shutdown [V] (default: the "
                  "drive's centre)", read_only=True),
    ParameterSpec("command_min_v", COMMAND_MIN_V, "commands below are clamped [V]", read_only=True),
    ParameterSpec("command_max_v", COMMAND_MAX_V, "commands above are clamped [V]", read_only=True),
    ParameterSpec("lockstep.step_budget", -1, "lockstep only: periods to run before pausing (-1 = no pause); "
                  "refused on the real-time clock (a paused watchdog would hold the last command)", low=-1),
    ParameterSpec("lockstep.max_speed", 0.0, "lockstep only: the valve's time runs at most this many times as fast "
                  "as the wall clock (0 = as fast as commands come, which keeps two cores busy; 1 = never ahead of "
                  "the wall clock)", read_only=True, low=0.0),
    ParameterSpec("realtime.busy_poll_s", 0.0, "realtime clock: poll for messages instead of sleeping this long "
                  "before each tick [s] (costs a core; >= control_period_s polls all the time)", read_only=True,
                  low=0.0),
    *realtime_specs(),
    ParameterSpec("fault.position_limit_m", FaultLimits.position_limit_m, "a position beyond +- this is implausible: "
                  "fault [m]", read_only=True, low=1e-5, high=1.0),
    ParameterSpec("fault.stuck_time_s", FaultLimits.stuck_time_s, "a position that has not changed at all for this "
                  "long since the command moved over fault.stuck_command_span_v: stuck sensor, fault [s]",
                  read_only=True, low=0.05, high=10.0),
    ParameterSpec("fault.stuck_command_span_v", FaultLimits.stuck_command_span_v, "see fault.stuck_time_s [V]",
                  read_only=True, low=0.05, high=100.0),
    ParameterSpec("fault.missing_samples_s", FaultLimits.missing_samples_s, "realtime clock: no samples from the "
                  "backend for this long: fault [s]", read_only=True, low=0.05, high=10.0),
    ParameterSpec("loop_stats_period_s", 0.0, "log the loop timing (rate, commands in time, latency) this often [s]; "
                  "0: only at shutdown", read_only=True, low=0.0),
    DIAGNOSTICS_PERIOD,
)
SPECS = {s.name: s for s in HARDWARE_PARAMETERS}


@dataclass(frozen=True)
class HardwareSettings(Settings):
    """The hardware node's start-up settings that do not depend on the backend (``Settings.from_specs`` reads them
    from HARDWARE_PARAMETERS); the live ones (``command_timeout_s``, ``lockstep.step_budget``) stay the node's."""

    autostart: bool
    clock: str
    safe_voltage: float                  # [V]
    command_min_v: float                 # [V]
    command_max_v: float                 # [V]
    samples_batch: int
    max_speed: float = from_parameter("lockstep.max_speed")
    busy_poll_s: float = from_parameter("realtime.busy_poll_s")   # [s]
    loop_stats_period_s: float = from_parameter("loop_stats_period_s")   # [s]
    position_limit_m: float = from_parameter("fault.position_limit_m")
    stuck_time_s: float = from_parameter("fault.stuck_time_s")
    stuck_command_span_v: float = from_parameter("fault.stuck_command_span_v")
    missing_samples_s: float = from_parameter("fault.missing_samples_s")

    @property
    def fault_limits(self) -> FaultLimits:
        return FaultLimits(self.position_limit_m, self.stuck_time_s, self.stuck_command_span_v, self.missing_samples_s)

    def problems(self) -> list[str]:
        if not self.command_min_v < self.command_max_v:
            return [f"command_min_v ({self.command_min_v} V) must be below command_max_v ({self.command_max_v} V)"]
        out = []
        if not self.command_min_v <= self.safe_voltage <= self.command_max_v:
            out.append("safe_voltage must lie within [command_min_v, command_max_v]")
        if self.max_speed and self.clock != "lockstep":
            out.append("lockstep.max_speed applies only to clock lockstep (the real-time clock runs at the wall "
                       "clock's pace)")
        return out + self.fault_limits.problems()
IN_TIME_WARN_SHARE = 0.99   # /diagnostics: WARN when fewer commands than this share came within their period


def samples_per_period(control_period_s: float, sample_period_s: float) -> int:
    """Whole number of backend samples in one control period; ValueError with the reason otherwise."""
    if not (math.isfinite(control_period_s) and 0.0 < control_period_s <= MAX_CONTROL_PERIOD_S):
        raise ValueError(f"control_period_s must lie in (0, {MAX_CONTROL_PERIOD_S}] s, got {control_period_s}")
    k = whole_periods(control_period_s, sample_period_s)
    if k is None or k < 1:
        raise ValueError(f"control_period_s {control_period_s} s is not a whole number of the backend's sample "
                         f"periods ({sample_period_s} s)")
    return int(k)


ACTIVE, INACTIVE, UNCONFIGURED = "active", "inactive", "unconfigured"   # the lifecycle states commands care about


class ValveHardwareNode(LifecycleNode):
    """The ROS face of a :class:`~piezo_valve_ros.runtime.hardware_loop.HardwareLoop`: parameters, the lifecycle,
    the topics, ``~/reset`` and /diagnostics; the loop does read -> check -> write, the watchdog, the fault latch,
    the batch and the pacing."""

    STANDALONE = False   # the node has its process to itself (main): every name its command line gives is its own

    def __init__(self, backend: Optional[ValveBackend] = None, **kwargs):
        super().__init__("valve_hardware", **kwargs)
        declare_all(self, HARDWARE_PARAMETERS)
        backend_name = str(self.get_parameter("backend").value)
        backend_type = type(backend) if backend is not None else backend_class(backend_name)
        declare_all(self, backend_parameters(backend_name, backend_type))   # each backend's own, under its name
        self._refuse_unknown(backend_name, backend_type, kwargs.get("parameter_overrides") or ())
        p = parameter_values(self)
        stats_period = self._read_settings(p)
        if backend is None:
            values = {prm.name: p[f"{backend_name}.{prm.name}"] for prm in backend_type.PARAMETERS}
            backend = backend_type.from_parameters(values, self.settings.safe_voltage)
        timeout = self._bind_backend(backend, p)
        st = self.settings
        self.loop = HardwareLoop(
            backend, LoopSettings(st.clock, st.safe_voltage, st.command_min_v, st.command_max_v, st.samples_batch,
                                  st.max_speed, st.fault_limits),
            self.samples_per_period, timeout, logger=self.get_logger, on_position=self._position_out,
            on_batch=self._batch_out, on_advanced=self._clock_out if st.clock == "lockstep" else None,
            on_fault=self._on_fault)
        self.loop.logger = lambda: self.get_logger()   # looked up at each line (a test may replace get_logger)
        self.loop.step_budget = self._initial_budget
        self._create_interfaces()
        self._tick_timer = None
        self._linked_controller: Optional[Callable[[float], Optional[float]]] = None
        self._closed = False
        self._health_mark = (0, 0)
        self._p, self._stats_period = p, stats_period
        self._timers: list = []
        self._paced_by: Optional[str] = None   # who runs the real-time tick instead of the node's timer
        self._transition_error = ""
        self._deactivated_by_fault = False
        self._autostarting = False
        self._set_state(UNCONFIGURED)
        self.diagnostics = Diagnostics(self, period_parameter(DIAGNOSTICS_PERIOD, p["diagnostics_period_s"]),
                                       self._health)
        if self.settings.autostart:   # (hardware_state says ok once, not inactive first)
            self._autostarting = True
            for name, trigger in (("configure", self.trigger_configure), ("activate", self.trigger_activate)):
                if trigger() != TransitionCallbackReturn.SUCCESS:
                    raise RuntimeError(f"valve_hardware could not {name}: {self._transition_error}")
            self._autostarting = False
        else:
            self.get_logger().info("valve_hardware unconfigured (autostart false): waiting for ~/change_state")

    # the loop's figures, as the node's (tests, benches and /diagnostics read them here)
    backend = property(lambda self: self.loop.backend)
    fault = property(lambda self: self.loop.fault)
    periods = property(lambda self: self.loop.periods)
    glitches = property(lambda self: self.loop.glitches)
    clamped = property(lambda self: self.loop.clamped)
    rejected = property(lambda self: self.loop.rejected)
    late_commands = property(lambda self: self.loop.late_commands)
    refused_in_fault = property(lambda self: self.loop.refused_in_fault)
    refused_inactive = property(lambda self: self.loop.refused_inactive)
    loop_timing = property(lambda self: self.loop.loop_timing)
    step_budget = property(lambda self: self.loop.step_budget)
    command_timeout_s = property(lambda self: self.loop.command_timeout_s)

    def _refuse_unknown(self, backend_name: str, backend_type, overrides) -> None:
        """ValueError naming every parameter the command line (or ``overrides``) gives this node that it does not
        declare: rclpy would ignore it, so a misspelt backend parameter would leave its default in force.  Names
        the command line gives every node of the process count when this node has the process to itself
        (``valve_hardware``), else only backend parameters (``valve_composed``: the controller takes the rest)."""
        own, shared = given_parameter_names(self.get_name())
        if not self.STANDALONE:
            shared = {n for n in shared if "." in n and n.split(".", 1)[0] in (backend_name, *available_backends())}
        given = own | shared | {prm.name for prm in overrides}
        unknown = sorted(n for n in given if not self.has_parameter(n))
        if unknown:
            own = ", ".join(f"{backend_name}.{prm.name}" for prm in backend_type.PARAMETERS) or "none"
            unknown = [named_with_nearest(n, [self]) for n in unknown]
            raise ValueError(f"unknown parameter(s) {', '.join(unknown)} (the {backend_name} backend's own: {own}; "
                             "every parameter: valve_hardware --help)")

    def _read_settings(self, p: dict) -> float:
        """The start-up parameters that do not depend on the backend, checked (ValueError with every reason);
        returns loop_stats_period_s."""
        self.settings = HardwareSettings.from_specs(SPECS, p)
        self._initial_budget = self._step_budget(p["lockstep.step_budget"])
        return self.settings.loop_stats_period_s

    def _bind_backend(self, backend: ValveBackend, p: dict) -> float:
        """What follows from the backend's sample period: the control period in whole samples, the watchdog's
        timeout (returned); the real-time settings (applied at configure, on the real-time clock)."""
        if self.settings.clock == "lockstep" and not backend.supports_lockstep:
            raise ValueError(f"backend {p['backend']!r} cannot run in lockstep")
        self.samples_per_period = samples_per_period(SPECS["control_period_s"].checked(p["control_period_s"]),
                                                     backend.sample_period_s)
        self.control_period_s = self.samples_per_period * backend.sample_period_s
        timeout = self._command_timeout(p["command_timeout_s"])
        self.realtime = realtime_settings(p)
        if self.realtime.priority and self.settings.busy_poll_s > 0:
            raise ValueError("realtime.priority with realtime.busy_poll_s > 0: a polling thread at real-time "
                             "priority starves every other thread of its CPU, DDS's included; sleep "
                             "(realtime.busy_poll_s 0) or use priority 0")
        return timeout

    def _create_interfaces(self) -> None:
        self.position_pub = self.create_publisher(Float64, "spool_position", SENSOR_QOS)
        self.samples_pub = self.create_publisher(Float64MultiArray, "samples", SAMPLES_QOS)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10) if self.settings.clock == "lockstep" else None
        self._clock_msg = Clock(clock=Time())
        self._full_batch = SamplesBuffer(self.loop.full_batch_rows, 3)   # the usual batch's message, made once
        self._command_sub = self.create_subscription(Float64, "voltage_command", self._on_command, COMMAND_QOS)
        self.state_pub = self.create_publisher(String, "hardware_state", STATE_QOS)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.add_on_set_parameters_callback(self._on_parameters)

    # ------------------------------------------------------------------ the loop's outlets
    def _position_out(self, y: float) -> None:
        if self._linked_controller is not None:
            v = self._linked_controller(y)
            if v is not None:
                self.loop.accept_command(v)
        self.position_pub.publish(Float64(data=y))

    def _batch_out(self, rows: np.ndarray) -> None:
        if rows.shape[0] == self._full_batch.rows.shape[0]:   # the usual case: into the message made once
            self._full_batch.rows[:] = rows
            self.samples_pub.publish(self._full_batch.message)
        else:
            self.samples_pub.publish(samples_message(rows))

    def _clock_out(self, t_next_s: float) -> None:
        stamp = self._clock_msg.clock
        stamp.sec, stamp.nanosec = divmod(int(round(t_next_s * 1e9)), 1_000_000_000)
        self.clock_pub.publish(self._clock_msg)

    def _on_fault(self, fault: Fault) -> None:
        """A latched fault: said on hardware_state and /diagnostics; it leaves active (``~/reset`` returns to it)."""
        self.state_pub.publish(String(data=f"fault: {fault.kind}: {fault.detail}"))
        if self.lifecycle_state == ACTIVE:
            self._deactivated_by_fault = True
            self.trigger_deactivate()
        if hasattr(self, "diagnostics"):
            self.diagnostics.publish()

    # ------------------------------------------------------------------ lifecycle
    def _set_state(self, name: str) -> None:
        self.lifecycle_state = name
        self.loop.inactive_state = name

    def _transition(self, name: str, body: Callable[[], None]) -> TransitionCallbackReturn:
        """Run a transition's ``body``; an exception is said (rclpy would swallow it) and ends at the safe voltage
        (ERROR: on_error closes the backend)."""
        try:
            body()
        except Exception as exc:  # whatever the backend raises: said, and the valve left safe
            self._transition_error = f"{name} failed: {exc}"
            self.get_logger().error(f"lifecycle: {self._transition_error}")
            self.loop.try_safe_voltage()
            return TransitionCallbackReturn.ERROR
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Open the backend at the safe voltage and start the clock's timers; nothing is driven yet."""
        def body():
            if self.settings.clock == "realtime":
                from ..runtime.realtime import apply
                apply(self.realtime)
            self.loop.reset_counters()
            self._closed = False
            self._start(self._p, self._stats_period)
            self._set_state(INACTIVE)
            if not self._autostarting:
                self._publish_state()
        return self._transition("configure", body)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Commands are applied from now on (at the safe voltage until the first valid one)."""
        def body():
            self.loop.start()
            self._set_state(ACTIVE)
            self._publish_state()
            self.get_logger().info("lifecycle: active, commands applied")
        result = self._transition("activate", body)
        return super().on_activate(state) if result == TransitionCallbackReturn.SUCCESS else result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """The safe voltage; commands refused, nothing published as a position."""
        def body():
            self._set_state(INACTIVE)
            written = self.loop.stop()
            self._publish_state()
            self.get_logger().info(f"lifecycle: inactive, safe voltage {self.settings.safe_voltage} V "
                                   + ("applied" if written else "could NOT be written") + "; commands refused")
        result = self._transition("deactivate", body)
        return super().on_deactivate(state) if result == TransitionCallbackReturn.SUCCESS else result

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """The safe voltage and the backend closed (configure opens it again)."""
        return self._transition("cleanup", self._close)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._transition("shutdown", self.shutdown_safely)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """After a failed transition: the safe voltage and the backend closed (to unconfigured)."""
        try:
            self._close()
        except Exception as exc:   # nothing more to do than say it
            self.get_logger().error(f"lifecycle: closing after an error raised {exc!r}")
        return TransitionCallbackReturn.SUCCESS

    def _stop_timers(self) -> None:
        for timer in self._timers:
            timer.cancel()
            self.destroy_timer(timer)
        self._timers = []
        if self._tick_timer is not None:
            self._tick_timer.cancel()
            self.destroy_timer(self._tick_timer)
            self._tick_timer = None

    def _close(self) -> None:
        """Stop the timers, apply the safe voltage, flush the samples, close the backend (to unconfigured)."""
        self._stop_timers()
        self._set_state(UNCONFIGURED)
        self.loop.active = False
        self.loop.close()
        self._publish_state()
        self.get_logger().info("lifecycle: unconfigured, the backend closed")

    def _publish_state(self) -> None:
        """``hardware_state``: ok while active, the fault while one is latched, else the lifecycle state."""
        fault = self.loop.fault
        text = (f"fault: {fault.kind}: {fault.detail}" if fault is not None else
                "ok" if self.lifecycle_state == ACTIVE else self.lifecycle_state)
        self.state_pub.publish(String(data=text))

    def _start(self, p: dict, stats_period: float) -> None:
        """Open the backend at the safe voltage and start the clock's timers (configure)."""
        self.loop.open()
        if self.settings.clock == "lockstep":
            # y_0 (at the initial voltage) goes out once a commander is matched both ways and settled
            # (_lockstep_idle), or before the first command that arrives earlier
            self._matched_since: Optional[float] = None
            self._timers.append(self.create_timer(min(0.05, self.loop.command_timeout_s / 10), self._lockstep_idle))
        else:
            self.backend.prepare_realtime()
            if not tighten_timer_slack():
                self.get_logger().warning("could not reduce the timer slack: expect period jitter of ~50 us")
            # fallback when nobody claims the pacing (an executor spun elsewhere); spin_loop claims it
            if self._paced_by is None:
                self._tick_timer = self.create_timer(self.control_period_s, self.loop.tick)
        if stats_period > 0:
            self._timers.append(self.create_timer(stats_period, lambda: self.get_logger().info(self._loop_line())))
        self.get_logger().info(
            f"valve_hardware up: backend={p['backend']} clock={self.settings.clock} "
            f"period={self.control_period_s * 1e3:.3f} ms ({self.samples_per_period} samples)"
            + (f"; {self.realtime.describe()}" if self.settings.clock == "realtime" else ""))

    # ------------------------------------------------------------------ health
    def _health(self) -> tuple[str, str, dict]:
        """(level, message, values) for /diagnostics: the watchdog, commands in time since the last report
        (real-time clock), clamps and late commands; counters only, nothing that costs the loop."""
        loop = self.loop
        t = loop.loop_timing
        periods, in_time = t.periods - self._health_mark[0], t.in_time - self._health_mark[1]
        self._health_mark = (t.periods, t.in_time)
        share = in_time / periods if periods else float("nan")
        watchdog = ("fired: safe voltage applied" if loop.timed_out else
                    "armed" if loop.armed else "waiting for the first command (safe voltage applied)")
        values = {"clock": self.settings.clock, "control_period_s": self.control_period_s, "periods": t.periods,
                  "commands_in_time_share": round(share, 4) if periods else "no periods since the last report",
                  "commands_clamped": loop.clamped, "commands_rejected": loop.rejected,
                  "late_commands": loop.late_commands, "watchdog": watchdog,
                  "safe_voltage_v": self.settings.safe_voltage,
                  "daq_glitches_last_minute": loop.glitches_in_last_minute(time.monotonic()),
                  "daq_glitches": loop.glitches}
        values["lifecycle_state"] = self.lifecycle_state
        if loop.fault is not None:
            values.update({"fault": loop.fault.kind, "fault_detail": loop.fault.detail,
                           "commands_refused_in_fault": loop.refused_in_fault,
                           "safe_voltage_written": loop.safe_written})
            held = ("safe voltage applied" if loop.safe_written else
                    "the safe voltage could NOT be written (writes fail; retrying every period)")
            return "ERROR", (f"fault {loop.fault.text(time.monotonic())}; {held}; commands refused until "
                             f"~/reset (valve_command reset) once the cause is gone"), values
        if self.lifecycle_state != ACTIVE:
            return "WARN", (f"{self.lifecycle_state} (lifecycle): " + (
                "the backend is closed" if self.lifecycle_state == UNCONFIGURED else
                "safe voltage applied") + "; commands refused until ~/change_state activates it"), values
        if loop.timed_out:
            return "ERROR", f"watchdog: no valid command for {loop.command_timeout_s} s, safe voltage applied", values
        warnings = []
        if loop.armed and self.settings.clock == "realtime" and periods and share < IN_TIME_WARN_SHARE:
            warnings.append(f"{100 * share:.1f} % of the commands came within their period")
        if values["daq_glitches_last_minute"]:
            warnings.append(f"{values['daq_glitches_last_minute']} DAQ glitch(es) in the last minute (a backend call "
                            f"raised once and succeeded when retried; {loop.glitches} in all)")
        if warnings:
            return "WARN", "; ".join(warnings), values
        return "OK", f"watchdog {watchdog}", values

    # ------------------------------------------------------------------ commands
    def claim_pacing(self) -> Optional[Pacing]:
        """Real-time clock: the spin loop runs the period tick itself (ros.spin.spin_loop: more precise
        and cheaper than an rclpy timer at kHz rates); this node's own timer stops (or is never made, where the
        node is not configured yet: the tick does nothing until it is).  None in lockstep, or when claimed."""
        if self.settings.clock != "realtime" or self._paced_by is not None:
            return None
        self._paced_by = "the spin loop"
        if self._tick_timer is not None:
            self._tick_timer.cancel()
            self.destroy_timer(self._tick_timer)
            self._tick_timer = None
        return Pacing(self.control_period_s, self.loop.tick, self.settings.busy_poll_s)

    def attach_controller(self, on_measurement: Callable[[float], Optional[float]]) -> None:
        """Composed mode, real-time clock: hand each position [m] to ``on_measurement`` by function call
        and apply the command [V] it returns (None: no command) at once, as rclcpp's intra-process
        communication would; ``spool_position`` and ``samples`` are still published and
        ``voltage_command`` from other nodes is still applied.  In lockstep the loop stays on topics."""
        if self.settings.clock != "realtime":
            raise ValueError("a direct controller link needs clock realtime (lockstep runs on topics)")
        self._linked_controller = on_measurement

    def _on_command(self, msg: Float64) -> None:
        self.loop.accept_command(msg.data)

    def _on_reset(self, request, response):
        """~/reset: leave the fault once the backend writes the safe voltage and reads sound samples again; back to
        active where the fault left it."""
        had = self.loop.fault
        response.success, response.message = self.loop.reset()
        if had is None:
            return response
        if not response.success:
            self.get_logger().error(f"~/reset refused: {response.message}")
            return response
        if self._deactivated_by_fault and self.lifecycle_state == INACTIVE:   # back to where the fault left it
            self._deactivated_by_fault = False
            self.trigger_activate()
        else:
            self._publish_state()
        self.get_logger().info(f"~/reset: {response.message}")
        return response

    def _commander_matched(self) -> bool:
        return bool(self.position_pub.get_subscription_count() and self._command_sub.get_publisher_count())

    def _lockstep_idle(self) -> None:
        loop = self.loop
        if loop.fault is not None:   # no period runs and nothing is said again until ~/reset
            loop.retry_safe_voltage()
            return
        if self.lifecycle_state != ACTIVE:
            return
        if loop.periods == 0:
            self._publish_first_sample_when_settled()
        elif loop.step_budget != 0 and loop.check_watchdog():
            loop.advance_and_publish()  # the safe voltage is applied for one period
            loop.flush_samples()
        elif (not loop.command_since_publish and loop.held_command is None
              and time.monotonic() - loop.last_publish_wall > UNANSWERED_REPEAT_S
              and self._commander_matched()):
            # nobody answered the last position (e.g. the controller restarted): say it again, once a
            # commander's writer is matched on our side too (DDS matches each side on its own; an answer
            # sent before our reader knows its writer is dropped, and a repeat would be answered twice)
            loop.last_publish_wall = time.monotonic()
            self.position_pub.publish(Float64(data=loop.last_position_m))

    def _publish_first_sample_when_settled(self) -> None:
        """y_0 goes out once a commander is matched both ways and has stayed so for FIRST_SAMPLE_SETTLE_S:
        ``spool_position`` is best effort, so a sample sent while the commander's reader is still matching
        is lost, and one answered before our reader knows the commander's writer would be answered twice
        after a repeat (the controller's integrator would count the first period twice)."""
        if not self._commander_matched():
            self._matched_since = None
            return
        now = time.monotonic()
        if self._matched_since is None:
            self._matched_since = now
        elif now - self._matched_since >= FIRST_SAMPLE_SETTLE_S:
            self.loop.advance_and_publish()

    # ------------------------------------------------------------------ parameters
    def _step_budget(self, value) -> int:
        """The live ``lockstep.step_budget`` checked by its spec and against the clock; ValueError with the reason."""
        budget = SPECS["lockstep.step_budget"].checked(value)
        if budget != -1 and self.settings.clock != "lockstep":
            raise ValueError("lockstep.step_budget applies only to clock lockstep (on the real-time clock a "
                             "paused loop would stop the watchdog)")
        return budget

    def _command_timeout(self, value) -> float:
        """The live ``command_timeout_s`` checked by its spec and against the control period; ValueError with the
        reason."""
        timeout = SPECS["command_timeout_s"].checked(value)
        shortest = MIN_TIMEOUT_PERIODS * self.control_period_s
        if not shortest <= timeout <= MAX_COMMAND_TIMEOUT_S:
            raise ValueError(f"command_timeout_s must lie in [{shortest:g}, {MAX_COMMAND_TIMEOUT_S:g}] s "
                             f"({MIN_TIMEOUT_PERIODS} control periods .. {MAX_COMMAND_TIMEOUT_S:g} s), got {timeout}")
        return timeout

    def _on_parameters(self, params) -> SetParametersResult:
        """Validate the whole update first, then apply all of it (or nothing)."""
        budget, timeout = self.loop.step_budget, self.loop.command_timeout_s
        try:
            for prm in params:
                if prm.name == "lockstep.step_budget":
                    budget = self._step_budget(prm.value)
                elif prm.name == "command_timeout_s":
                    timeout = self._command_timeout(prm.value)
                else:  # read-only ones never get here (rclpy refuses them); anything else is not applied
                    raise ValueError(f"{prm.name} cannot be changed at run time (restart the node)")
        except ValueError as exc:
            return refuse(self, str(exc))
        self.loop.command_timeout_s = timeout
        self.loop.set_step_budget(budget)
        return SetParametersResult(successful=True)

    def _loop_line(self) -> str:
        summary = self.loop.loop_timing.summary()
        return summary.lockstep_line() if self.settings.clock == "lockstep" else f"loop: {summary.line()}"

    # ------------------------------------------------------------------ shutdown
    def shutdown_safely(self) -> None:
        """Apply safe_voltage, flush the samples, close the backend.  Idempotent."""
        if self._closed:
            return
        self._closed = True
        for timer in self._timers:
            timer.cancel()
        self._set_state(UNCONFIGURED)
        loop = self.loop
        loop.active = False
        if not loop.opened:   # never configured (or cleaned up): nothing to make safe
            return
        alive = self.context.ok()   # after Ctrl-C/SIGTERM the ROS context (publishers, /rosout) is already gone

        def say(level: str) -> Callable[[str], None]:
            return lambda line: print(f"[{level}] [valve_hardware]: {line}", file=sys.stderr, flush=True)
        written = loop.close(publish=alive, say=say("ERROR"))
        held = (f"safe_voltage {self.settings.safe_voltage} V applied" if written else
                f"the safe voltage {self.settings.safe_voltage} V could NOT be written: the DAQ holds its last value")
        line = f"valve_hardware stopped: {held}; {self._loop_line()}"
        if alive:
            self.get_logger().info(line)
        else:
            say("INFO")(line)


class _StandaloneHardwareNode(ValveHardwareNode):
    STANDALONE = True


def hardware_parameters_with_backends() -> tuple[ParameterSpec, ...]:
    """The node's own parameters and every backend's this process can make (``<backend>.<name>``), as ``--help``
    lists them; a backend that cannot be loaded is left out (``backend:=`` then says why)."""
    specs = list(HARDWARE_PARAMETERS)
    for name in available_backends():
        try:
            specs += backend_parameters(name)
        except ValueError:
            continue
    return tuple(specs)


def main(args=None) -> int:
    return run_node(_StandaloneHardwareNode, "valve_hardware", args, on_exit_of=lambda n: n.shutdown_safely,
                    specs=hardware_parameters_with_backends())


if __name__ == "__main__":
    sys.exit(main())
