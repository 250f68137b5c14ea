"""Safety that no parameter can switch off, and parameter updates that are applied or refused with a reason.

The nodes run in this process; ``node.set_parameters`` goes through the same pre-set/on-set callbacks and
descriptor checks as a remote ``ros2 param set`` (rclpy's parameter service calls it), so what is refused
here is refused over ROS too.
"""
import contextlib
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ros_helpers import ros_env

import rclpy
from rclpy.parameter import Parameter
from std_msgs.msg import Float64, Float64MultiArray

from piezo_valve_ros.core.control import ControllerConfig, ValveController, gain_set
from piezo_valve_ros.ros import COMMAND_QOS, SAMPLES_QOS, make_executor, samples_message
from piezo_valve_ros.nodes.controller import ValveControllerNode
from piezo_valve_ros.nodes.hardware import ValveHardwareNode
from piezo_valve_ros.nodes.identification import ValveIdentificationNode

_ids = iter(range(1000))


@pytest.fixture(scope="module")
def ros_context():
    rclpy.init()
    yield
    rclpy.try_shutdown()


def namespace() -> str:
    return f"/safety{os.getpid()}_{next(_ids)}"


def params(**values) -> list[Parameter]:
    return [Parameter(k.replace("__", "."), value=v) for k, v in values.items()]


def set_one(node, name, value):
    return node.set_parameters([Parameter(name, value=value)])[0]


def _nodes(cls, close):
    """A factory of ``cls`` nodes (each in a namespace of its own) and the cleanup of all it made."""
    made = []

    def make(**overrides):
        node = cls(namespace=namespace(), parameter_overrides=params(**overrides))
        made.append(node)
        return node

    def cleanup():
        for node in made:
            close(node)
            node.destroy_node()
    return make, cleanup


@pytest.fixture
def hardware(ros_context):
    make, cleanup = _nodes(ValveHardwareNode, lambda node: node.shutdown_safely())
    yield make
    cleanup()


@pytest.fixture
def controller(ros_context):
    make, cleanup = _nodes(ValveControllerNode, lambda node: None)
    yield make
    cleanup()


# ---------------------------------------------------------------------------- hardware
@pytest.mark.parametrize("overrides, says", [
    ({"command_timeout_s": 0.0}, "command_timeout_s must lie in"),
    ({"command_timeout_s": -1}, "command_timeout_s must lie in"),
    ({"command_timeout_s": 0.001}, "command_timeout_s must lie in"),   # shorter than two periods
    ({"command_timeout_s": 60.0}, "out of range"),
    ({"control_period_s": 0.0}, "control_period_s must lie in"),
    ({"control_period_s": -0.001}, "out of range"),
    ({"control_period_s": 0.00015}, "not a whole number"),
    ({"lockstep__step_budget": 5}, "applies only to clock lockstep"),
    ({"clock": "wallclock"}, "clock must be one of realtime, lockstep, got 'wallclock'"),
    ({"samples_batch": 0}, "samples_batch must be >= 1, got 0"),
    ({"samples_batch": 2.5}, "samples_batch must be an integer"),
    ({"lockstep__step_budget": -2, "clock": "lockstep"}, "lockstep.step_budget must be >= -1"),
    ({"lockstep__max_speed": 2.0}, "lockstep.max_speed applies only to clock lockstep"),
    ({"lockstep__max_speed": -1.0, "clock": "lockstep"}, "lockstep.max_speed must be >= 0, got -1.0"),
    ({"lockstep__max_speed": float("nan"), "clock": "lockstep"}, "lockstep.max_speed must be finite"),
    ({"lockstep__max_speed": "fast", "clock": "lockstep"}, "lockstep.max_speed"),
    ({"safe_voltage": 11.0}, "safe_voltage must lie within"),
    ({"command_min_v": 5.0, "command_max_v": 5.0, "safe_voltage": 5.0}, "must be below"),
    ({"sim__sensor_delay_s": 0.00015}, "whole number of sample periods"),
    ({"sim__sensor_delay_s": -0.001}, "sim.sensor_delay_s out of range"),   # a double: rclpy's range check
    ({"realtime__switch_interval_s": 0.1}, "out of range"),
    ({"realtime__switch_interval_s": 1}, "switch_interval_s must lie in"),
    ({"realtime__priority": 99}, "realtime.priority must lie in 0..98"),
    ({"realtime__priority": 1.5}, "realtime.priority must be an integer"),
    ({"realtime__priority": float("nan")}, "realtime.priority must be an integer"),
    ({"realtime__priority": float("inf")}, "realtime.priority must be an integer"),
    ({"realtime__priority": -1}, "realtime.priority must lie in 0..98"),
    ({"realtime__priority": "high"}, "realtime.priority must be an integer"),
    ({"realtime__cpus": ["a"]}, "realtime.cpus must be an integer"),
    ({"realtime__cpus": [4096]}, "no CPU 4096 on this machine"),
    ({"realtime__cpu_wakeup_latency_us": -2}, "realtime.cpu_wakeup_latency_us must lie in 0.."),
    ({"realtime__cpu_wakeup_latency_us": 2.5}, "realtime.cpu_wakeup_latency_us must be an integer"),
    ({"realtime__cpu_wakeup_latency_us": "low"}, "realtime.cpu_wakeup_latency_us must be an integer"),
    ({"realtime__priority": 10, "realtime__busy_poll_s": 0.001}, "starves every other thread"),
    ({"diagnostics_period_s": -1}, "diagnostics_period_s must lie in"),
    ({"diagnostics_period_s": float("nan")}, "diagnostics_period_s out of range"),   # rclpy's range check
    ({"diagnostics_period_s": "often"}, "diagnostics_period_s must be a number"),
    # the fault checks cannot be switched off: no zero, negative, endless or non-number limit
    ({"fault__position_limit_m": 0.0}, "fault.position_limit_m"),
    ({"fault__position_limit_m": 5.0}, "fault.position_limit_m"),
    ({"fault__stuck_time_s": -1.0}, "fault.stuck_time_s"),
    ({"fault__stuck_time_s": float("inf")}, "fault.stuck_time_s"),
    ({"fault__stuck_command_span_v": float("nan")}, "fault.stuck_command_span_v"),
    ({"fault__missing_samples_s": 0.0}, "fault.missing_samples_s"),
    ({"fault__missing_samples_s": "never"}, "fault.missing_samples_s"),
    ({"autostart": "yes"}, "expecting type 'BOOL': autostart"),   # rclpy's typed declaration
    ({"autostart": 0}, "expecting type 'BOOL': autostart"),
    ({"autostart": float("nan")}, "expecting type 'BOOL': autostart"),
])
def test_hardware_refuses_unsafe_start_up_parameters(hardware, overrides, says):
    with pytest.raises(Exception, match=says):
        hardware(**overrides)


def test_hardware_start_up_refusal_is_one_line_and_a_nonzero_exit():
    exe = os.path.join(os.path.dirname(sys.executable), "valve_hardware")  # the console script
    proc = subprocess.run([exe, "--ros-args", "-p", "control_period_s:=0.0"], env=ros_env(),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == ["valve_hardware: control_period_s must lie in (0, 0.1] s, got 0.0"]


@pytest.mark.parametrize("value", [0.0, -1, -1.0, float("nan"), float("inf"), "abc", 0.0005, 11.0])
def test_hardware_watchdog_cannot_be_switched_off_at_run_time(hardware, value):
    hw = hardware(clock="realtime", command_timeout_s=0.5)
    result = set_one(hw, "command_timeout_s", value)
    assert not result.successful and result.reason
    assert hw.command_timeout_s == 0.5 and hw.get_parameter("command_timeout_s").value == 0.5


def test_hardware_applies_a_valid_timeout_and_refuses_step_budget_on_the_real_time_clock(hardware):
    hw = hardware(clock="realtime")
    assert set_one(hw, "command_timeout_s", 0.2).successful and hw.command_timeout_s == 0.2
    result = set_one(hw, "lockstep.step_budget", 0)
    assert not result.successful and "lockstep" in result.reason
    assert hw.step_budget == -1 and hw.get_parameter("lockstep.step_budget").value == -1


@pytest.mark.parametrize("name, value", [("safe_voltage", 8.0), ("command_max_v", 20.0), ("control_period_s", 2e-3),
                                         ("clock", "lockstep"), ("backend", "other"), ("sim.noise", False),
                                         ("realtime.cpu_wakeup_latency_us", 0), ("autostart", False)])
def test_hardware_start_up_settings_are_read_only(hardware, name, value):
    hw = hardware(clock="realtime")
    before = hw.get_parameter(name).value
    result = set_one(hw, name, value)
    assert not result.successful and "read-only" in result.reason
    assert hw.get_parameter(name).value == before


def test_lockstep_step_budget_still_pauses_a_lockstep_rig(hardware):
    hw = hardware(clock="lockstep", lockstep__step_budget=0)
    assert set_one(hw, "lockstep.step_budget", 10).successful and hw.step_budget == 10


def test_a_lockstep_pace_slower_than_the_watchdog_never_trips_it(hardware):
    """lockstep.max_speed 0.004 at 1 ms: a period every 0.25 s, longer than command_timeout_s 0.1: the wait is the
    hardware's own, so a commander that answers every position at once never trips the watchdog; the pace holds."""
    hw = hardware(clock="lockstep", control_period_s=0.001, command_timeout_s=0.1, lockstep__max_speed=0.004)
    t0 = time.monotonic()
    for _ in range(4):
        hw._on_command(Float64(data=6.0))   # as the subscription delivers it, answered at once
        hw._lockstep_idle()                 # the watchdog's timer, right after the position went out
    assert not hw.loop.timed_out and hw.periods == 5   # y_0 and one period per command
    assert time.monotonic() - t0 >= 3 * 0.25 - 0.02   # periods 2..4 each waited for the pace


# ---------------------------------------------------------------------------- controller
def test_an_active_gain_set_decides_strategy_and_gains_and_says_so(controller):
    ctl = controller(gain_set="pid_hc_5")
    strategy, gains = gain_set("pid_hc_5")
    # the parameters read back what runs
    assert ctl.get_parameter("strategy").value == strategy == ctl.controller.config.strategy
    assert ctl.get_parameter("kp").value == gains.kp == ctl.controller.config.gains.kp
    assert ctl.get_parameter("ki").value == gains.ki
    # strategy/gains alone are refused while the set is active, valid or not, and change nothing
    for name, value in [("kp", 2.0), ("strategy", "pid"), ("strategy", "bogus"), ("kp", float("nan")),
                        ("ki", float("inf")), ("kp", "abc"), ("kd", -1.0)]:
        result = set_one(ctl, name, value)
        assert not result.successful and result.reason, (name, value)
        assert ctl.controller.config.gains == gains and ctl.controller.config.strategy == strategy
        assert ctl.get_parameter("kp").value == gains.kp and ctl.get_parameter("strategy").value == strategy
    # clearing the set in the same request lets them through, and they are applied
    assert ctl.set_parameters_atomically(params(gain_set="", strategy="pid", kp=1.5, ki=400.0)).successful
    assert ctl.controller.config.strategy == "pid" and ctl.controller.config.gains.kp == 1.5
    # a new set brings its values; clearing it alone keeps them (nothing stored that is not applied)
    assert set_one(ctl, "gain_set", "ff_pid_1").successful
    strategy, gains = gain_set("ff_pid_1")
    assert ctl.get_parameter("strategy").value == strategy == ctl.controller.config.strategy
    assert ctl.get_parameter("ki").value == gains.ki == ctl.controller.config.gains.ki
    assert set_one(ctl, "gain_set", "").successful
    assert ctl.controller.config.strategy == strategy and ctl.controller.config.gains == gains
    # a bad set name is refused
    result = set_one(ctl, "gain_set", "bogus")
    assert not result.successful and "unknown gain set" in result.reason
    assert ctl.get_parameter("gain_set").value == ""


@pytest.mark.parametrize("name, value", [("strategy", "bogus"), ("kp", float("nan")), ("kp", float("inf")),
                                         ("kp", "abc"), ("ki", -1.0), ("enabled", "false"), ("enabled", 0),
                                         ("reference_ramp_s", -1.0), ("handback_timeout_s", 0.0),
                                         ("control_period_s", 2e-3), ("initial_reference_m", 1e-5),
                                         ("command_min_v", 11.0),
                                         ("saturation.half_range_um", 0.0), ("saturation.half_range_um", -5.0),
                                         ("saturation.half_range_um", float("nan")), ("saturation.half_range_um", "abc"),
                                         ("saturation.coefficients_um", [float("nan")] * 8),
                                         ("saturation.coefficients_um", [0.0] * 7), ("feedforward.dynamics", "true"),
                                         ("feedforward.dynamics", 0), ("derivative_filter_s", 0.0),
                                         ("derivative_filter_s", -1e-3), ("derivative_filter_s", 1.0),
                                         ("derivative_filter_s", float("nan")), ("derivative_filter_s", "abc"),
                                         ("gpim.rate_widening_v", [30.0] * 9), ("gpim.rate_widening_v", "abc"),
                                         ("gpim.rate_widening_v", [float("nan")] * 9),
                                         ("gpim.rate_widening_v", [1.0, 2.0])])
def test_controller_refuses_what_it_would_not_apply(controller, name, value):
    ctl = controller(gain_set="")
    before = (ctl.controller.config, ctl.controller.compensation, ctl.enabled, ctl.get_parameter(name).value)
    result = set_one(ctl, name, value)
    assert not result.successful and result.reason
    assert (ctl.controller.config, ctl.controller.compensation, ctl.enabled, ctl.get_parameter(name).value) == before


@pytest.mark.parametrize("overrides, says", [
    ({"derivative_filter_s": 0.0}, "derivative_filter_s out of range"),   # a double: rclpy's range check
    ({"derivative_filter_s": -1e-3}, "derivative_filter_s out of range"),
    ({"derivative_filter_s": float("nan")}, "derivative_filter_s"),
    ({"derivative_filter_s": "abc"}, "derivative_filter_s must be a number"),
    ({"derivative_filter_s": 1.0}, "derivative_filter_s out of range"),
    ({"derivative_filter_s": 1}, r"derivative_filter_s must lie in \[1e-05, 0.1\]"),   # an integer: the node's own
    ({"reference_ramp_s": -1}, "reference_ramp_s must be >= 0"),
    ({"handback_timeout_s": 20}, r"handback_timeout_s must lie in \[0.05, 10\]"),
    ({"kp": -1}, "kp must be >= 0"),
    ({"gpim__rate_widening_v": [1.0, 2.0]}, "needs 9 coefficients"),
    ({"gpim__rate_widening_v": [float("nan")] * 9}, "must be finite"),
    ({"gpim__rate_widening_v": "abc"}, "list of numbers"),
    ({"state_period_s": -0.1}, "state_period_s out of range"),     # a double: rclpy's range check
    ({"state_period_s": -1}, "state_period_s must lie in"),        # an integer: the node's own
    ({"state_period_s": 11}, "state_period_s must lie in"),
    ({"state_period_s": "fast"}, "state_period_s must be a number"),
    ({"diagnostics_period_s": float("inf")}, "diagnostics_period_s out of range"),
])
def test_controller_refuses_bad_filter_and_rate_widening_at_start_up(controller, overrides, says):
    with pytest.raises(Exception, match=says):
        controller(gain_set="", **overrides)


def test_rate_widening_zeros_mean_none_and_negative_coefficients_are_a_model(controller):
    from piezo_valve_ros.core.model import RateDependentInverseGPIM
    assert not isinstance(controller(gain_set="", gpim__rate_widening_v=[0.0] * 9).controller.ff_inverse,
                          RateDependentInverseGPIM)
    narrowing = controller(gain_set="", gpim__rate_widening_v=[-1.0] * 9)   # thresholds that narrow with the rate
    assert isinstance(narrowing.controller.ff_inverse, RateDependentInverseGPIM)


def test_derivative_filter_is_applied_at_run_time(controller):
    ctl = controller(gain_set="", strategy="pid_hc", kd=1e-4)
    assert ctl.controller.config.derivative_filter_s == pytest.approx(5e-4)
    assert set_one(ctl, "derivative_filter_s", 2e-3).successful
    assert ctl.controller.config.derivative_filter_s == pytest.approx(2e-3)
    dt = ctl.controller.config.dt
    assert ctl.controller._d_alpha == pytest.approx(dt / (2e-3 + dt))   # the filter the D term now runs


def test_enabled_is_a_boolean_and_false_disables(controller):
    ctl = controller(gain_set="")
    assert set_one(ctl, "enabled", False).successful and not ctl.enabled


def test_command_range_update_moves_static_gain_and_demand_limits(controller):
    ctl = controller(gain_set="")
    k_before = ctl.controller._k
    assert ctl.set_parameters_atomically(params(command_min_v=2.0, command_max_v=8.0)).successful
    fresh = ValveController(ControllerConfig(dt=1e-3, command_min_v=2.0, command_max_v=8.0))
    assert ctl.controller._k == pytest.approx(fresh._k, rel=1e-12)
    assert ctl.controller._k != pytest.approx(k_before, rel=1e-3)
    assert (ctl.controller._demand_min_um, ctl.controller._demand_max_um) == \
        pytest.approx((fresh._demand_min_um, fresh._demand_max_um))
    assert ctl.controller.config.command_max_v == 8.0
    # the centre outside the range is refused as a whole
    result = ctl.set_parameters_atomically(params(command_min_v=6.0))
    assert not result.successful and "centre_voltage_v" in result.reason
    assert ctl.controller.config.command_min_v == 2.0


def test_a_model_that_knows_part_of_the_drive_loads_with_its_command_range_in_one_update(controller):
    """A fitted model of a record over 2.94..7.01 V and the command range it knows (1.93..8.02 V), in one update,
    as valve_command load sends a valve_identify/valve_tune file: applied together (the model alone does not suit
    0..10 V, the range alone not the old model's checks); the model alone is refused with the range to set."""
    from piezo_valve_ros.core.control import CompensationModel, command_range_for
    ctl = controller(gain_set="pid_hc_2")
    fitted = (2.9396, 7.009)
    lo, hi = command_range_for(fitted, 0.0, 10.0, 5.0)
    model = CompensationModel(fitted_range_v=fitted).to_parameters()
    alone = ctl.set_parameters_atomically([Parameter(k, value=v) for k, v in model.items()])
    assert not alone.successful and "limit command_min_v/command_max_v" in alone.reason, alone.reason
    together = ctl.set_parameters_atomically([Parameter(k, value=v) for k, v in model.items()]
                                             + params(command_min_v=round(lo + 1e-4, 4), command_max_v=round(hi - 1e-4, 4)))
    assert together.successful, together.reason
    assert ctl.controller.config.command_min_v == round(lo + 1e-4, 4)
    assert ctl.controller.compensation.fitted_range_v == fitted
    v = ctl.on_measurement(0.0)
    assert ctl.controller.config.command_min_v <= v <= ctl.controller.config.command_max_v


# ---------------------------------------------------------------------------- hand-back
@contextlib.contextmanager
def beside(node, name: str):
    """An executor spinning ``node`` and a helper node ``name`` in its namespace (to publish to it and read
    what it says); both taken down afterwards, whatever the test did."""
    other = rclpy.create_node(name, namespace=node.get_namespace())
    executor = make_executor()
    executor.add_node(node)
    executor.add_node(other)
    try:
        yield other, executor
    finally:
        executor.remove_node(node)
        executor.remove_node(other)
        other.destroy_node()
        executor.shutdown()


def spin_until(executor, condition, timeout_s=5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
        if condition():
            return True
    return False


@pytest.mark.parametrize("hardware_timed_out", [False, True])
def test_control_comes_back_when_the_node_that_took_over_falls_silent(controller, hardware_timed_out):
    """The identification node disables the controller and commands the valve itself, then dies (no
    re-enable).  When its commands stop for handback_timeout_s the controller enables itself and resumes
    from the voltage actually applied: the dead node's last command, or the hardware's safe voltage when its
    watchdog fired first (reported in samples)."""
    ctl = controller(gain_set="pid_hc_5", handback_timeout_s=0.3)
    with beside(ctl, "other_commander") as (other, executor):
        commands = other.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        samples = other.create_publisher(Float64MultiArray, "samples", SAMPLES_QOS)
        assert set_one(ctl, "enabled", False).successful
        assert spin_until(executor, lambda: commands.get_subscription_count() >= 1
                          and samples.get_subscription_count() >= 1)
        for v in (6.0, 7.0, 7.6):
            commands.publish(Float64(data=v))
            spin_until(executor, lambda: False, 0.05)
        assert not ctl.enabled  # still within the timeout: the other node has control
        if hardware_timed_out:
            samples.publish(samples_message(np.array([[1.0, 7.6, 30e-6], [1.0001, 5.0, 29e-6]])))
        assert spin_until(executor, lambda: ctl.enabled, 3.0)
        assert ctl.get_parameter("enabled").value is True  # the parameter says what runs
        assert ctl.controller.last_command_v == pytest.approx(5.0 if hardware_timed_out else 7.6)


def test_control_comes_back_with_the_valves_memory_of_what_was_applied_meanwhile(controller):
    """An identification drives the valve through wide swings and dies; the controller takes over under OL HC (no
    feedback to take an error away).  It resumes with its inverses' operators where the voltages applied meanwhile
    (the hardware's samples) left them, from the state it left them in: its open-loop commands then put the valve,
    which went through the same swings, on the reference.  Resumed from a synchronised state at the last voltage, as
    it once did, it stayed off by most of the loop's width (22 um from outside, in 2 runs of 3)."""
    ctl = controller(gain_set="", strategy="ol_hc")
    ctl.controller.reset(5.0)
    gpim = ctl.controller.model
    valve = gpim.stream(ctl.controller.ff_inverse.forward_state(), 5.0)      # the valve, as the model has it
    assert set_one(ctl, "enabled", False).successful
    t = np.arange(4000) * 1e-3
    swings = 5.0 + 4.5 * np.sin(2 * np.pi * 2.0 * t) * np.exp(-t / 3.0) + 0.3 * np.sin(2 * np.pi * 7.0 * t)
    swings = np.concatenate([swings, np.full(50, 3.2)])                    # the identification stops at 3.2 V
    for k in range(0, swings.size, 100):                                     # the hardware's samples, in batches
        rows = np.column_stack([t[:1].repeat(min(100, swings.size - k)), swings[k:k + 100], np.zeros(min(100, swings.size - k))])
        ctl._on_samples(samples_message(rows))
        for v in swings[k:k + 100]:
            valve.step(float(v))
    assert set_one(ctl, "enabled", True).successful
    assert np.allclose(ctl.controller.ff_inverse.forward_state(), valve.state)
    synchronised = gpim.virgin_state(3.2)
    assert np.max(np.abs(gpim.output_from_state(synchronised) - gpim.output_from_state(valve.state))) > 5.0
    reference_um = gpim.output_from_state(valve.state) + 10.0
    for _ in range(200):
        v = ctl.controller.step(reference_um * 1e-6, gpim.output_from_state(valve.state) * 1e-6)
        y = valve.step(v)
    assert y == pytest.approx(reference_um, abs=0.5)


def test_a_controller_follows_voltage_command_only_while_disabled(controller):
    """Enabled, the commands on voltage_command are the controller's own: it takes none back (one message less
    every period); disabled, it follows another node's (to resume from the applied voltage and to notice when
    they stop), and enabled again it stops."""
    ctl = controller(gain_set="")
    ns = ctl.get_namespace()
    assert ctl.count_subscribers(f"{ns}/voltage_command") == 0
    assert set_one(ctl, "enabled", False).successful
    assert ctl.count_subscribers(f"{ns}/voltage_command") == 1 and ctl.count_subscribers(f"{ns}/samples") == 1
    assert set_one(ctl, "enabled", True).successful
    assert ctl.count_subscribers(f"{ns}/voltage_command") == 0 and ctl.count_subscribers(f"{ns}/samples") == 0


def test_a_controller_disabled_by_hand_stays_disabled_without_a_commander(controller):
    ctl = controller(gain_set="", handback_timeout_s=0.05)
    executor = make_executor()
    executor.add_node(ctl)
    try:
        assert set_one(ctl, "enabled", False).successful
        assert not spin_until(executor, lambda: ctl.enabled, 0.5)
    finally:
        executor.remove_node(ctl)
        executor.shutdown()


@pytest.mark.parametrize("executable", ["valve_hardware", "valve_controller", "valve_identification", "valve_composed",
                                        "valve_rig", "valve_identify"])
def test_every_executable_answers_help_without_starting_anything(executable):
    exe = os.path.join(os.path.dirname(sys.executable), executable)
    proc = subprocess.run([exe, "--help"], env=ros_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.startswith(f"usage: {executable}"), proc.stdout + proc.stderr
    assert "[INFO]" not in proc.stdout + proc.stderr and "rig up" not in proc.stdout  # no node was started


@pytest.mark.parametrize("executable", ["valve_hardware", "valve_composed", "valve_identify", "valve_command"])
def test_help_into_a_reader_that_stops_early_ends_without_a_traceback(executable):
    """``valve_hardware --help | head -1``: the reader closes the pipe before the help is written; the executable
    ends quietly (exit 0), as a shell user expects."""
    exe = os.path.join(os.path.dirname(sys.executable), executable)
    proc = subprocess.Popen([exe, "--help"], env=ros_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()   # the reader is gone before the first byte
    err = proc.stderr.read().decode()
    assert proc.wait(60) == 0 and "Traceback" not in err and "BrokenPipe" not in err, err


def _stop_or_kill(proc: subprocess.Popen, log, grace_s: float = 20.0) -> None:
    """SIGTERM must end a node within ``grace_s``; if it does not, it dumps its threads' stacks (SIGUSR1) and is
    killed (a real-time process left spinning on a CPU would starve the rest of the suite), and the test fails
    with its log and those stacks."""
    proc.terminate()
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        threads = _thread_table(proc.pid)   # a starved process handles no signal: which thread holds the CPU
        proc.send_signal(signal.SIGUSR1)
        time.sleep(2.0)
        proc.kill()
        proc.wait(5)
        raise AssertionError(f"{proc.args[0]} still ran {grace_s:g} s after SIGTERM (stacks, then killed); its "
                             f"threads (tid, name, state, CPU ticks, FIFO priority):\n{threads}\n"
                             + log.read_text()[-8000:]) from None


def _thread_table(pid: int) -> str:
    rows = []
    for tid in sorted(os.listdir(f"/proc/{pid}/task")):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                head, _, tail = f.read().rpartition(")")
            fields = tail.split()   # from field 3 (state) on: utime, stime are fields 14, 15; rt_priority 40
            rows.append(f"{tid} {head.partition('(')[2]} {fields[0]} {int(fields[11]) + int(fields[12])} {fields[37]}")
        except (OSError, IndexError, ValueError):
            pass
    return "\n".join(rows)


def test_a_node_dumps_its_threads_stacks_on_sigusr1_and_runs_on(tmp_path):
    """SIGUSR1 to any node: every thread's Python stack to its stderr (faulthandler), and it runs on; a node that
    hangs can say where before it is killed."""
    exe = os.path.join(os.path.dirname(sys.executable), "valve_controller")
    log = tmp_path / "ctl.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([exe, "--ros-args", "-r", f"__ns:={namespace()}"], env=ros_env(), stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        # its first health line comes from a timer: the node is in its spin loop ("up" is logged before it gets
        # there, and a dump then shows the constructor)
        deadline = time.monotonic() + 30
        while "health " not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        proc.send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + 10
        while "spin_loop" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.05)
        text = log.read_text()
        assert "Current thread" in text and "spin_loop" in text, text   # the main thread, in the spin loop
        assert proc.poll() is None
    finally:
        _stop_or_kill(proc, log)
    assert proc.returncode == 0


def test_a_node_leaves_its_real_time_priority_before_it_tears_down():
    """The shutdown runs on the normal scheduler: ``leave_realtime`` puts every SCHED_FIFO thread of the process
    back on SCHED_OTHER (threads at one FIFO priority on one CPU run until they block, so a teardown that waits
    by spinning would starve itself there).  In a child process; skipped where SCHED_FIFO is not allowed."""
    out = _in_a_realtime_child(10, "tids = [int(x) for x in os.listdir('/proc/self/task')]\n"
                                   "before = {os.sched_getscheduler(tid) for tid in tids}\n"
                                   "realtime.leave_realtime()\n"
                                   "after = {os.sched_getscheduler(tid) for tid in tids}\n"
                                   "print(len(tids), before == {os.SCHED_FIFO}, after == {os.SCHED_OTHER})\n")
    assert out.split() == ["2", "True", "True"], out


def _in_a_realtime_child(priority: int, body: str) -> str:
    """What ``body`` prints, run in a child process (``os``, ``threading`` and ``realtime`` imported) after
    ``realtime.apply`` at ``priority``, with a second thread ``t`` waiting beside the main one; the test is skipped
    where SCHED_FIFO is not allowed."""
    script = ("import os, threading\n"
              "from piezo_valve_ros.runtime import realtime\n"
              "stop = threading.Event(); t = threading.Thread(target=stop.wait); t.start()\n"
              "try:\n"
              f"    realtime.apply(realtime.RealtimeSettings(priority={priority}))\n"
              "except realtime.RealtimeError:\n"
              "    print('refused'); stop.set(); raise SystemExit(0)\n"
              "try:\n"
              + "".join(f"    {line}\n" for line in body.splitlines()) +
              "finally:\n"
              "    realtime.leave_realtime(); stop.set(); t.join()\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    if out.stdout.strip() == "refused":
        pytest.skip("SCHED_FIFO is not allowed here")
    return out.stdout.strip()


@pytest.mark.parametrize("priority, others", [(10, "FIFO 9"), (1, "OTHER 0")])
def test_the_threads_beside_the_loop_run_below_its_priority(priority, others):
    """``realtime.apply`` gives the calling (loop) thread the priority and every other thread of the process one
    below it, so that one that spins cannot starve the loop: at priority 1 that is the normal scheduler (at the
    loop's own FIFO priority a thread runs until it blocks).  In a child process; skipped where SCHED_FIFO is not
    allowed."""
    out = _in_a_realtime_child(priority, "name = {os.SCHED_FIFO: 'FIFO', os.SCHED_OTHER: 'OTHER'}\n"
                                         "rank = lambda tid: f'{name[os.sched_getscheduler(tid)]} "
                                         "{os.sched_getparam(tid).sched_priority}'\n"
                                         "print(rank(threading.get_native_id()), '|', rank(t.native_id))\n")
    assert out == f"FIFO {priority} | {others}", out


def test_hardware_applies_its_real_time_priority_and_cpus(tmp_path):
    """realtime.priority / realtime.cpus reach every thread of the process: the loop's thread at the priority,
    every other (DDS's included) one below, so a middleware thread that spins cannot starve the loop on its CPU;
    or the node refuses to start with the OS's reason and what to do."""
    cpu = max(os.sched_getaffinity(0))
    exe = os.path.join(os.path.dirname(sys.executable), "valve_hardware")
    log = tmp_path / "hw.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([exe, "--ros-args", "-p", "realtime.priority:=10", "-p", f"realtime.cpus:=[{cpu}]"],
                                env=ros_env(), stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "valve_hardware up" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if proc.poll() is not None:  # no permission for SCHED_FIFO on this machine: refused with the reason
            assert proc.returncode == 2 and "the OS refused SCHED_FIFO" in log.read_text(), log.read_text()
            return
        assert f"SCHED_FIFO 10, CPUs {cpu}" in log.read_text()

        def ranks():
            tids = [int(t) for t in os.listdir(f"/proc/{proc.pid}/task")]
            return {tid: (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority, os.sched_getaffinity(tid))
                    for tid in tids}
        # as its loop starts, the node ranks the threads started since (the executor's) with DDS's
        want = {tid: (os.SCHED_FIFO, 10 if tid == proc.pid else 9, {cpu}) for tid in ranks()}   # the loop: main
        deadline = time.monotonic() + 10
        while ranks() != want and time.monotonic() < deadline:
            time.sleep(0.05)
            want = {tid: (os.SCHED_FIFO, 10 if tid == proc.pid else 9, {cpu}) for tid in ranks()}
        assert len(want) > 3 and ranks() == want, _thread_table(proc.pid)  # DDS's threads as well as the loop
    finally:
        _stop_or_kill(proc, log)


def test_a_cpu_wakeup_latency_request_is_held_while_the_process_runs(tmp_path):
    """realtime.cpu_wakeup_latency_us: the request is written to the kernel's PM QoS file as a 32-bit number and
    its file is held open (the request lasts as long); a file that cannot be opened refuses with what to do."""
    import struct
    from piezo_valve_ros.runtime import realtime
    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    realtime.release_cpu_wakeup_latency()
    try:
        realtime.hold_cpu_wakeup_latency(0, str(device))
        (fd,) = realtime._held_requests
        assert os.readlink(f"/proc/self/fd/{fd}") == str(device)
        assert struct.unpack("=i", device.read_bytes()) == (0,)
    finally:
        realtime.release_cpu_wakeup_latency()
    assert realtime._held_requests == [] and not any(
        os.readlink(f"/proc/self/fd/{f}") == str(device) for f in os.listdir("/proc/self/fd")
        if os.path.islink(f"/proc/self/fd/{f}"))
    with pytest.raises(realtime.RealtimeError, match="cannot open .*missing.*udev rule.*or use -1"):
        realtime.hold_cpu_wakeup_latency(0, str(tmp_path / "missing"))
    settings = realtime.RealtimeSettings.from_values(5e-5, 0, [], 0)
    assert settings.cpu_wakeup_latency_us == 0 and "idle CPUs polling" in settings.describe()
    assert "idle" not in realtime.RealtimeSettings.from_values(5e-5, 0, []).describe()


def test_hardware_holds_the_cpus_awake_when_asked(tmp_path):
    """realtime.cpu_wakeup_latency_us 0 on the real-time clock: the running process holds the kernel's request
    open (/proc/<pid>/fd), and says so in its start-up line; or, where the OS does not allow it, the node
    refuses to start with the reason."""
    exe = os.path.join(os.path.dirname(sys.executable), "valve_hardware")
    log = tmp_path / "hw.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([exe, "--ros-args", "-p", "realtime.cpu_wakeup_latency_us:=0"],
                                env=ros_env(), stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "valve_hardware up" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if proc.poll() is not None:   # no write access to the PM QoS file here: refused with the reason
            assert proc.returncode == 2 and "cannot open /dev/cpu_dma_latency" in log.read_text(), log.read_text()
            return
        assert "idle CPUs polling" in log.read_text(), log.read_text()
        held = [os.readlink(f"/proc/{proc.pid}/fd/{fd}") for fd in os.listdir(f"/proc/{proc.pid}/fd")]
        assert "/dev/cpu_dma_latency" in held, held
    finally:
        _stop_or_kill(proc, log)


def test_controller_takes_an_asymmetric_model_only_when_it_can_invert_it(controller):
    """Issue 11.2/3: gpim.descending_envelope makes the controller's GPIM asymmetric (inverted exactly);
    one that is not rising on the command range, or a malformed list, is refused with the reason."""
    from piezo_valve_ros.core.model import PAPER_GPIM
    g = PAPER_GPIM
    good = [g.a0 * 1.03, g.a1 + 0.08, 0.0]
    ctl = controller(gain_set="", strategy="ol_hc", gpim__descending_envelope=good)
    assert not ctl.controller.model.symmetric and ctl.controller.model.b0 == pytest.approx(good[0])
    falling = [1.0, 0.5, -0.06]  # the descending envelope turns down above 8.3 V
    with pytest.raises(Exception, match="descending envelope not rising at 8.3"):
        controller(gain_set="", gpim__descending_envelope=falling)
    result = set_one(ctl, "gpim.descending_envelope", falling)
    assert not result.successful and "not rising" in result.reason
    assert ctl.controller.model.b0 == pytest.approx(good[0])  # untouched
    crossing = [0.95, 0.2]  # below the ascending envelope above 6.7 V: inverted step by step
    assert set_one(ctl, "gpim.descending_envelope", crossing).successful
    assert ctl.controller.model.b0 == pytest.approx(0.95)
    result = set_one(ctl, "gpim.descending_envelope", [1.0])
    assert not result.successful and "[b0, b1] or [b0, b1, b2]" in result.reason
    assert set_one(ctl, "gpim.descending_envelope", [g.a0, g.a1, 0.0]).successful  # back to symmetric
    assert ctl.controller.model.symmetric


def test_controller_takes_a_whole_extended_model_in_one_update_or_refuses_it_whole(controller):
    """Issue 11.3: the model the identification pushes (creep, saturation map, dynamic feedforward) is applied
    in one atomic update; a malformed part refuses all of it, with the reason, and changes nothing."""
    from piezo_valve_ros.core.control import CompensationModel, CreepModel
    from piezo_valve_ros.core.model import OutputMap
    ctl = controller(gain_set="", strategy="ol_hc")
    extended = CompensationModel(creep=CreepModel((0.5, 5.0), (0.02, 0.02)),
                                 output_map=OutputMap(0.0, 70.0, (0.0, -3.0, 0.0, 0.0, -1.0, 0.0, 0.0, 1.0)),
                                 dynamic_feedforward=True)
    update = [Parameter(k, value=v) for k, v in extended.to_parameters().items()]
    assert ctl.set_parameters_atomically(update).successful
    assert ctl.controller.compensation.to_parameters() == extended.to_parameters()
    bad = [Parameter("feedforward.dynamics", value=False), Parameter("saturation.coefficients_um", value=[1.0, 2.0])]
    result = ctl.set_parameters_atomically(bad)
    assert not result.successful and "needs 8 values" in result.reason
    assert ctl.controller.compensation.dynamic_feedforward  # untouched


def test_controller_takes_a_rate_dependent_model_and_says_what_its_inverse_costs(controller, capfd):
    """Issue 11.2/3: gpim.rate_widening_v makes the controller's inverse rate-dependent (pushed with the rest
    of the model, atomically); a malformed widening is refused whole; at a 0.1 ms period the node warns that
    an inverse solved each step may overrun, at 1 ms it does not."""
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.model import RateDependentInverseGPIM
    model = CompensationModel(rate_widening_v=(-0.006, -0.37, 1.79, -0.028, 0.44, -1.25, 0.0, 0.0, 0.0))
    ctl = controller(gain_set="", strategy="ol_hc")
    assert ctl.set_parameters_atomically([Parameter(k, value=v) for k, v in model.to_parameters().items()]).successful
    assert isinstance(ctl.controller.ff_inverse, RateDependentInverseGPIM)
    assert ctl.controller.compensation.rate_widening_v == model.rate_widening_v
    result = set_one(ctl, "gpim.rate_widening_v", [1.0, 2.0])
    assert not result.successful and "needs 9 coefficients" in result.reason
    assert ctl.controller.compensation.rate_widening_v == model.rate_widening_v  # untouched
    assert "may overrun" not in capfd.readouterr().err
    fast = controller(gain_set="", strategy="ol_hc", control_period_s=1e-4,
                      gpim__rate_widening_v=list(model.rate_widening_v))
    assert isinstance(fast.controller.ff_inverse, RateDependentInverseGPIM)
    err = capfd.readouterr().err
    assert "solved each step" in err and "may overrun" in err


# ---------------------------------------------------------------------------- identification
@pytest.fixture
def identification(ros_context, tmp_path):
    make, cleanup = _nodes(ValveIdentificationNode, lambda node: node._stop_recording())
    yield lambda **kw: make(**{"plan": "", "bag_dir": str(tmp_path), **kw})
    cleanup()


@pytest.mark.parametrize("overrides, says", [
    ({"tune_strategy": "ol_hc"}, "tune_strategy must be one of pid, pid_hc, ff_pid, ff_pid_g"),
    ({"tune_strategy": "dance"}, "tune_strategy must be one of"),
    ({"validation_strategy": "pid_h"}, "validation_strategy must be one of ol, ol_hc, pid, pid_hc"),
    ({"storage": "zip"}, "storage must be one of mcap, sqlite3, got 'zip'"),
    ({"tune_max_overshoot_pct": -1.0}, "max_overshoot_pct must be a finite number >= 0"),
    ({"tune_max_overshoot_pct": float("nan")}, "tune_max_overshoot_pct must be finite"),
    ({"tune_max_overshoot_pct": "abc"}, "tune_max_overshoot_pct must be a number"),
    ({"plan": "train,tune"}, "tune needs a refit step before it"),
    ({"hardware": ""}, "hardware must name a node"),
    ({"hardware": "the rig!"}, "hardware 'the rig!' is not a node name"),
    ({"controller": ""}, "controller must name a node"),
    ({"plan": "train,bogus"}, "unknown step"),
    ({"training_s": 0.0}, "training_s must be > 0"),
    ({"validation_amplitude_m": -1e-6}, "validation_amplitude_m must be > 0"),
    ({"training_s": 0.0, "time_scale": 0.0, "plan": "refit"},   # every reason in one refusal
     "refit needs a train step.*time_scale must be > 0.*training_s must be > 0"),
])
def test_identification_refuses_bad_settings_at_start_up(identification, overrides, says):
    with pytest.raises(ValueError, match=says):
        identification(**overrides)


@pytest.mark.parametrize("name, value", [("tune_strategy", "pid"), ("tune_max_overshoot_pct", 0.0),
                                         ("tune_max_overshoot_pct", float("nan")), ("plan", "train"),
                                         ("control_period_s", 1e-4), ("hardware", "other_hardware")])
def test_identification_settings_are_start_up_only(identification, name, value):
    """Read at start-up by the plan: a run-time change is refused with the reason, never stored and ignored."""
    node = identification(tune_max_overshoot_pct=0.0)   # 0 %: a valid (strict) limit
    before = node.get_parameter(name).value
    result = set_one(node, name, value)
    assert not result.successful and "read-only" in result.reason.lower()
    assert node.get_parameter(name).value == before or (before != before and value != value)
    assert node.settings.tune_limits.max_overshoot_pct == 0.0 and node.settings.tune_strategy == "pid_hc"


@pytest.mark.parametrize("executable, module", [("valve_hardware", "hardware"), ("valve_controller", "controller"),
                                                ("valve_identification", "identification"),
                                                ("valve_monitor", "monitor")])
def test_help_lists_every_parameter_of_the_one_declaration_the_node_uses(executable, module, hardware, controller):
    """Each node declares its parameters from one tuple of ParameterSpec; --help prints each with its type,
    default and range; the handbook's tables are written from the same tuples and are up to date."""
    import importlib
    specs = getattr(importlib.import_module(f"piezo_valve_ros.nodes.{module}"), f"{module.upper()}_PARAMETERS")
    if module == "hardware":   # and the simulated backend's own, declared from the same spec type
        from piezo_valve_ros.backends import backend_parameters
        specs = specs + backend_parameters("sim")
        assert all(s.name.startswith("sim.") and s.read_only for s in backend_parameters("sim"))
    exe = os.path.join(os.path.dirname(sys.executable), executable)
    text = subprocess.run([exe, "--help"], env=ros_env(), capture_output=True, text=True, timeout=60).stdout
    for s in specs:
        assert f"  {s.name} ({s.type_name}, default {s.default!r}" in text, s.name
        if s.read_only:
            assert s.help_line().splitlines()[0] in text
    if module in ("hardware", "controller"):   # in-process: what the node declared is that tuple, read-only flags too
        node = {"hardware": hardware, "controller": controller}[module]()
        for s in specs:
            descriptor = node.describe_parameter(s.name)
            assert descriptor.read_only == s.read_only and descriptor.description == s.description, s.name
    script = os.path.join(os.path.dirname(__file__), "..", "scripts", "parameter_tables.py")
    check = subprocess.run([sys.executable, script, "--check"], capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr


def test_the_composed_process_lists_both_nodes_parameters_under_their_names():
    """valve_composed --help lists every parameter of both nodes (and the simulated backend's), each under the node
    name a command line addresses it with (valve_hardware:clock:=realtime)."""
    from piezo_valve_ros.backends import backend_parameters
    from piezo_valve_ros.nodes.controller import CONTROLLER_PARAMETERS
    from piezo_valve_ros.nodes.hardware import HARDWARE_PARAMETERS
    exe = os.path.join(os.path.dirname(sys.executable), "valve_composed")
    text = subprocess.run([exe, "--help"], env=ros_env(), capture_output=True, text=True, timeout=60).stdout
    for node, specs in (("valve_hardware", HARDWARE_PARAMETERS + backend_parameters("sim")),
                        ("valve_controller", CONTROLLER_PARAMETERS)):
        for s in specs:
            assert f"  {node}:{s.name} ({s.type_name}, default {s.default!r}" in text, (node, s.name)


def test_every_node_shares_the_one_control_period_declaration():
    from piezo_valve_ros.ros import CONTROL_PERIOD
    from piezo_valve_ros.nodes.controller import CONTROLLER_PARAMETERS
    from piezo_valve_ros.nodes.hardware import HARDWARE_PARAMETERS
    from piezo_valve_ros.nodes.identification import IDENTIFICATION_PARAMETERS
    for specs in (HARDWARE_PARAMETERS, CONTROLLER_PARAMETERS, IDENTIFICATION_PARAMETERS):
        assert [s for s in specs if s.name == "control_period_s"] == [CONTROL_PERIOD]
        assert len({s.name for s in specs}) == len(specs)   # declared once each


def test_a_reference_the_valve_cannot_reach_is_refused_and_never_drives_the_command_to_a_rail(controller):
    """position_reference 20 (um meant), -1, 1e-3 (mm meant) and NaN, through ROS to a running PID HC
    controller: each refused (counted, one log line), the last good reference kept, the command never on a
    rail; a reference just beyond the reachable range is clamped to it instead."""
    from piezo_valve_ros.ros import REFERENCE_QOS, SENSOR_QOS
    ctl = controller(gain_set="pid_hc_5")
    lo, hi = ctl.controller.reachable_m
    commands = []
    with beside(ctl, "reference_sender") as (other, executor):
        refs = other.create_publisher(Float64, "position_reference", REFERENCE_QOS)
        positions = other.create_publisher(Float64, "spool_position", SENSOR_QOS)
        other.create_subscription(Float64, "voltage_command", lambda m: commands.append(m.data), COMMAND_QOS)
        assert spin_until(executor, lambda: refs.get_subscription_count() and positions.get_subscription_count())

        def run(reference, periods=150):
            refs.publish(Float64(data=reference))
            spin_until(executor, lambda: False, 0.05)
            for _ in range(periods):   # the valve sits at the good reference
                positions.publish(Float64(data=20e-6))
                spin_until(executor, lambda: False, 0.002)

        run(20e-6)
        good = len(commands)
        assert good > 50
        for bad in (20.0, -1.0, 1e-3, float("nan")):
            run(bad)
        assert ctl.rejected_references == 4 and ctl.clamped_references == 0
        held = commands[good:]
        assert len(held) > 300 and 0.5 < min(held) and max(held) < 9.5   # never near a rail (0 / 10 V)
        run(hi + 0.01 * (hi - lo))
        assert ctl.clamped_references == 1 and ctl.rejected_references == 4


def test_admit_reference_clamps_a_little_beyond_the_reach_and_refuses_more():
    ctl = ValveController(ControllerConfig(strategy="pid_hc", dt=1e-3))
    lo, hi = ctl.reachable_m
    assert lo < -50e-6 and hi > 50e-6            # the paper's valve: about +-65 um
    assert ctl.admit_reference(10e-6) == (10e-6, "")
    near, why = ctl.admit_reference(hi + 0.02 * (hi - lo))
    assert near == hi and "clamped" in why
    for bad in (20.0, -1.0, 1e-3, hi + 0.2 * (hi - lo), float("nan"), float("inf")):
        r, why = ctl.admit_reference(bad)
        assert r is None and why


def test_valve_command_loads_a_fitted_model_atomically_where_set_refuses_it(controller, tmp_path):
    """A new GPIM with a different number of operators: thresholds and weights set one at a time are each
    refused (their counts differ in between); `valve_command load` applies the whole file in one update,
    and a file whose model is not invertible, or was fitted on another drive, is refused whole, nothing
    changed."""
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.model import GPIMParams
    from piezo_valve_ros.identify import parameters_yaml
    from piezo_valve_ros.rig import run_in_background
    ctl = controller()
    thread, stop, executor = run_in_background([ctl])
    exe = os.path.join(os.path.dirname(sys.executable), "valve_command")

    def command(*args):
        return subprocess.run([exe, "--namespace", ctl.get_namespace(), "--timeout", "20", *args], env=ros_env(),
                              capture_output=True, text=True, timeout=90)
    try:
        new = CompensationModel(GPIMParams(a0=0.9647, a1=0.1014, alpha=0.40, rho=4.0, tau=0.9, n=9,
                                           offset_um=-80.0).model()).to_parameters()
        fitted = tmp_path / "fitted.yaml"
        fitted.write_text(parameters_yaml(new, ["a model with 9 operators"]))
        one_by_one = command("set", "controller", "gpim.thresholds:=" + str(new["gpim.thresholds"]))
        assert one_by_one.returncode == 1 and "refused" in one_by_one.stdout
        loaded = command("load", "controller", str(fitted))
        assert loaded.returncode == 0 and "applied together" in loaded.stdout, loaded.stdout + loaded.stderr
        assert list(ctl.get_parameter("gpim.weights").value) == pytest.approx(new["gpim.weights"])
        assert ctl.controller.model.n == 9
        broken = tmp_path / "broken.yaml"
        broken.write_text(parameters_yaml({**new, "gpim.weights": [-1.0] * 9}, ["not invertible"]))
        refused = command("load", "controller", str(broken))
        assert refused.returncode == 1 and "refused, nothing changed" in refused.stdout, refused.stdout
        assert list(ctl.get_parameter("gpim.weights").value) == pytest.approx(new["gpim.weights"])
        # a model fitted on a +-150 V drive, under this 0-10 V controller: refused with the reason
        wide = tmp_path / "wide.yaml"
        wide.write_text(parameters_yaml({**new, "model.fitted_range_v": [-150.0, 150.0]}, ["fitted at +-150 V"]))
        refused = command("load", "controller", str(wide))
        assert refused.returncode == 1 and "a model of another drive" in refused.stdout, refused.stdout
        assert list(ctl.get_parameter("model.fitted_range_v").value) == [0.0, 0.0]
    finally:
        stop.set()
        thread.join(2.0)
        executor.remove_node(ctl)
        executor.shutdown()


def test_controller_state_and_diagnostics_say_what_the_controller_is_doing(controller):
    """~/controller_state: the latest period's reference, measurement, error, command, strategy, guard,
    enabled (a labelled row); /diagnostics: the node's health (OK in control, the model in force, refused
    references), both at a low rate on their own timers."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from piezo_valve_ros.ros import REFERENCE_QOS, SENSOR_QOS
    from piezo_valve_ros.nodes.controller import CONTROLLER_STATE_COLUMNS
    ctl = controller(gain_set="pid_hc_5", state_period_s=0.05, diagnostics_period_s=0.2)
    states, health = [], []
    with beside(ctl, "state_reader") as (other, executor):
        other.create_subscription(Float64MultiArray, f"{ctl.get_fully_qualified_name()}/controller_state",
                                  states.append, 10)
        other.create_subscription(DiagnosticArray, "/diagnostics",
                                  lambda m: health.extend(s for s in m.status if s.name == ctl.get_fully_qualified_name()), 10)
        refs = other.create_publisher(Float64, "position_reference", REFERENCE_QOS)
        positions = other.create_publisher(Float64, "spool_position", SENSOR_QOS)
        other.create_subscription(Float64, "voltage_command", lambda m: None, COMMAND_QOS)
        assert spin_until(executor, lambda: refs.get_subscription_count() and positions.get_subscription_count())
        refs.publish(Float64(data=20e-6))
        refs.publish(Float64(data=1.0))            # refused: counted in the health values
        spin_until(executor, lambda: False, 0.05)
        for _ in range(100):
            positions.publish(Float64(data=18e-6))
            spin_until(executor, lambda: False, 0.003)
        assert spin_until(executor, lambda: len(health) >= 1 and len(states) >= 2, 3.0)
        msg = states[-1]
        assert msg.layout.dim[1].label == ",".join(CONTROLLER_STATE_COLUMNS)
        row = dict(zip(CONTROLLER_STATE_COLUMNS, np.asarray(msg.data)))
        assert row["reference_m"] == pytest.approx(20e-6) and row["measured_m"] == pytest.approx(18e-6)
        assert row["error_m"] == pytest.approx(2e-6) and 0.0 <= row["command_v"] <= 10.0
        assert row["strategy_index"] == 3 and row["guard_active"] == 0.0 and row["enabled"] == 1.0
        status = health[-1]
        values = {kv.key: kv.value for kv in status.values}
        assert status.level == DiagnosticStatus.OK and "in control" in status.message
        assert values["strategy"] == "pid_hc" and values["references_rejected"] == "1"
        assert "GPIM 15 operators" in values["model"]


def test_hardware_diagnostics_report_the_watchdog(hardware):
    """/diagnostics from the hardware: waiting for the first command (OK), then, after its commands stop,
    the watchdog fired (ERROR, with the timeout), on the real-time clock."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    hw = hardware(command_timeout_s=0.1, diagnostics_period_s=0.1)
    health = []
    with beside(hw, "health_reader") as (other, executor):
        other.create_subscription(DiagnosticArray, "/diagnostics",
                                  lambda m: health.extend(s for s in m.status if s.name == hw.get_fully_qualified_name()), 10)
        commands = other.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        assert spin_until(executor, lambda: len(health) >= 1, 3.0)
        assert health[-1].level == DiagnosticStatus.OK and "waiting for the first command" in health[-1].message
        assert spin_until(executor, lambda: commands.get_subscription_count() >= 1)
        commands.publish(Float64(data=6.0))
        assert spin_until(executor, lambda: health[-1].level == DiagnosticStatus.ERROR, 3.0)
        assert "watchdog" in health[-1].message and "safe voltage" in health[-1].message
        values = {kv.key: kv.value for kv in health[-1].values}
        assert values["watchdog"].startswith("fired") and values["clock"] == "realtime"


def test_one_rule_says_whether_a_time_is_a_whole_number_of_periods():
    """The hardware's control period, the simulator's sensor delay and the composed node's two periods are
    judged by one rule (``core.validation``): equal to rounding, never to a choice."""
    from piezo_valve_ros.core import same_period, whole_periods
    assert whole_periods(1e-3, 1e-4) == 10 and whole_periods(0.3e-3, 1e-4) == 3 and whole_periods(0.0, 1e-4) == 0
    assert whole_periods(1.5e-4, 1e-4) is None and whole_periods(1.0005e-3, 1e-4) is None
    assert whole_periods(float("nan"), 1e-4) is None and whole_periods(float("inf"), 1e-4) is None
    assert same_period(1e-4, 1e-4 * (1 + 1e-9)) and not same_period(1e-4, 1.0001e-4)


def test_a_node_whose_shutdown_hangs_dumps_its_stacks_and_exits_by_its_deadline():
    """After the first Ctrl-C/SIGTERM a node process has SHUTDOWN_DEADLINE_S to end; one whose shutdown hangs (here a
    loop that never looks at the stop request, as a thread spinning on a lock would) writes every thread's stack to
    stderr, naming where it hung, and exits 1 instead of holding the valve and a CPU for ever."""
    from piezo_valve_ros.ros import SHUTDOWN_DEADLINE_S
    script = ("import os, signal, time\n"
              "from piezo_valve_ros.ros import init_ros\n"
              "init_ros(['hung_node'])\n"
              "def stuck_in_shutdown():\n"
              "    while True:\n"
              "        time.sleep(0.01)\n"
              "print('up', flush=True)\n"
              "stuck_in_shutdown()\n")
    proc = subprocess.Popen([sys.executable, "-c", script], env=ros_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "up"
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=SHUTDOWN_DEADLINE_S + 30)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, (proc.returncode, err)
    assert took >= SHUTDOWN_DEADLINE_S - 0.1, took
    assert "Timeout" in err and "stuck_in_shutdown" in err and "most recent call first" in err, err


def test_settings_checks_are_declared_on_their_fields_and_checked_by_one_function():
    """HealthLimits, TuningLimits and ControllerConfig declare each field's rule beside its default (``ruled``);
    ``field_problems`` checks them all (no hand loop over names that can miss a field): every ruled field of each
    refuses nan and a negative value, and a positive one refuses zero, one line naming it."""
    import dataclasses
    import math
    from piezo_valve_ros.core.control import ControllerConfig
    from piezo_valve_ros.core.monitoring import HealthLimits
    from piezo_valve_ros.core.tuning import TuningLimits
    from piezo_valve_ros.core import POSITIVE, field_problems, ruled
    checked = 0
    for settings in (HealthLimits(), TuningLimits(), ControllerConfig()):
        assert settings.problems() == []
        for f in dataclasses.fields(settings):
            rule = f.metadata.get("rule")
            if rule is None:
                continue
            checked += 1
            bad = [math.nan, -1.0] + ([0.0] if rule == POSITIVE else [])
            for value in bad:
                problems = field_problems(dataclasses.replace(settings, **{f.name: value}))
                assert len(problems) == 1 and problems[0].startswith(f.name + " must be"), (f.name, value, problems)
                assert problems[0] in dataclasses.replace(settings, **{f.name: value}).problems()
    assert checked == 5 + 5 + 3
    with pytest.raises(ValueError, match="unknown rule"):
        ruled(1.0, "odd")
