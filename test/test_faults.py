"""A DAQ that fails, lies or goes silent: the hardware latches a fault, applies the safe voltage, says which fault
on /diagnostics and hardware_state, refuses commands, stays up, and leaves the fault only on ~/reset once its
cause is gone; the controller holds meanwhile.

The node runs in this process on the real-time clock with the kit's fault-injecting backend around the simulated
valve, on a clock the test moves:
each period is the node's own pacing tick (``claim_pacing``), so every fault lands at a known sample.
"""
import math
import os
import time
from itertools import count

import numpy as np
import pytest

import rclpy
from rclpy.parameter import Parameter
from std_msgs.msg import Float64, String

from piezo_valve_ros.backends import FaultInjectingBackend, check_backend
from piezo_valve_ros.backends import SimBackend
from piezo_valve_ros.core.sim import ValveSimConfig
from piezo_valve_ros.backends import FaultLimits, SampleCheck
from piezo_valve_ros.ros import COMMAND_QOS, SENSOR_QOS, STATE_QOS, make_executor
from piezo_valve_ros.nodes.controller import ValveControllerNode
from piezo_valve_ros.nodes.hardware import ValveHardwareNode

_ids = count()
PERIOD_S = 1e-3
SAFE_V = 5.0


# ---------------------------------------------------------------------------- the checks, without ROS
def rows_of(t, command, position):
    return np.column_stack((t, command, position))


def test_the_sample_checks_name_non_finite_implausible_and_frozen_samples():
    check = SampleCheck(FaultLimits())
    t = np.arange(10) * 1e-4
    assert check.check(rows_of(t, np.full(10, 5.0), 1e-6 * np.arange(10))) is None
    bad = rows_of(t + 1e-3, np.full(10, 5.0), np.r_[np.zeros(9), np.nan])
    assert check.check(bad)[0] == "non_finite_sample"
    assert SampleCheck(FaultLimits()).check(rows_of(t, np.full(10, 5.0), np.full(10, 2e-3)))[0] == "implausible_sample"
    # frozen: the same reading while the command sweeps 0.25 V every 10 ms: 0.5 s after the command has moved
    # over 1 V (40 ms in), not before; never while the command holds still (a valve at rest, a quantised sensor)
    frozen, still = SampleCheck(FaultLimits()), SampleCheck(FaultLimits())
    said = []
    for k in range(80):
        tk = k * 0.01 + np.arange(10) * 1e-3
        said.append(frozen.check(rows_of(tk, 4.0 + 0.25 * (k % 12) + 0 * tk, np.full(10, 3e-6))))
        assert still.check(rows_of(tk, np.full(10, 4.0), np.full(10, 3e-6))) is None
    first = next(i for i, s in enumerate(said) if s is not None)
    assert said[first][0] == "stuck_sensor" and 53 <= first <= 55, (first, said[first])
    # a noise-free valve settled for 2 s, then a 6 V step the sensor answers a sample later: no trip
    settled = SampleCheck(FaultLimits())
    for k in range(200):
        tk = k * 0.01 + np.arange(10) * 1e-3
        command = np.full(10, 2.0) if k < 199 else np.r_[2.0, np.full(9, 8.0)]
        position = np.full(10, -32e-6) if k < 199 else np.r_[-32e-6, -32e-6, np.linspace(-31e-6, -20e-6, 8)]
        assert settled.check(rows_of(tk, command, position)) is None, k
    with pytest.raises(ValueError, match="fault.stuck_time_s must lie in"):
        SampleCheck(FaultLimits(stuck_time_s=0.0))


def test_a_noise_free_valve_stepped_again_and_again_never_trips_the_frozen_check():
    """A noise-free valve (its reading still while it holds) stepped between 2 and 8 V every 0.6 s, each step on the
    last sample of a read of 10, its reading answering a sample later and moving for exactly two reads (each ending
    on a live reading), then still: the frozen-sensor timer starts again at every live reading, so no step ever
    trips it (a timer left running from the first step tripped the second)."""
    check = SampleCheck(FaultLimits())
    dt, move = 1e-3, 20
    k = np.arange(int(4.0 / dt))
    steps = np.arange(609, k.size, 600)                               # the last sample of a read
    command = np.where(np.searchsorted(steps, k, side="right") % 2 == 0, 2.0, 8.0)
    target = 14e-6 * command - 60e-6
    position = np.full(k.size, target[0])
    for s in steps:                                                   # a ramp over the next 20 samples, then still
        position[s + 1:] = target[s] if s + 1 + move >= k.size else position[s + 1:]
        ramp = np.linspace(position[s], target[s], move + 1)[1:]
        position[s + 1:s + 1 + move] = ramp[:max(0, min(move, k.size - s - 1))]
        position[s + 1 + move:] = target[s]
    rows = rows_of(k * dt, command, position)
    for start in range(0, k.size, 10):
        assert check.check(rows[start:start + 10]) is None, start


def test_a_healthy_valve_never_trips_the_checks_even_noise_free_or_at_a_rail():
    """The simulated valve (every effect, and again without noise) through a minute of the paper's training
    signal, steps to both rails and holds: no check trips."""
    from piezo_valve_ros.core.sim import rig_training_voltage
    from dataclasses import replace
    from piezo_valve_ros.core.sim import SensorParams, SimulatedValve
    for noise in (True, False):
        config = ValveSimConfig(dt=1e-4, seed=3)
        valve = SimulatedValve(config if noise else replace(config, sensor=SensorParams(noise_enabled=False)))
        v = np.concatenate((np.repeat(rig_training_voltage(1e-3, 30.0, 1.0), 10), np.full(20000, 0.0),
                            np.full(20000, 10.0), np.full(20000, 5.0)))
        y = valve.run(v)
        rows = np.column_stack((np.arange(v.size) * 1e-4, v, y))
        check = SampleCheck(FaultLimits())
        for start in range(0, v.size, 10):
            assert check.check(rows[start:start + 10]) is None, (noise, start)


# ---------------------------------------------------------------------------- the node
@pytest.fixture(scope="module")
def ros_context():
    rclpy.init()
    yield
    rclpy.try_shutdown()


class Rig:
    """The hardware node with a FaultyDaq, a helper node to command it and read what it says, and the ticks."""

    def __init__(self):
        ns = f"/faults{os.getpid()}_{next(_ids)}"
        self.now = 100.0   # the simulated DAQ's clock [s], moved by the test
        self.daq = FaultInjectingBackend(SimBackend(ValveSimConfig(dt=1e-4, seed=11), clock=lambda: self.now))
        self.hw = ValveHardwareNode(backend=self.daq, namespace=ns, parameter_overrides=[
            Parameter("command_timeout_s", value=0.5), Parameter("diagnostics_period_s", value=0.0)])
        self.tick = self.hw.claim_pacing().tick
        self.other = rclpy.create_node("fault_probe", namespace=ns)
        self.states = []
        self.other.create_subscription(String, "hardware_state", lambda m: self.states.append(m.data), STATE_QOS)
        self.commands = self.other.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        from std_srvs.srv import Trigger
        self.reset_client = self.other.create_client(Trigger, f"{ns}/valve_hardware/reset")
        self.executor = make_executor()
        self.executor.add_node(self.hw)
        self.executor.add_node(self.other)
        deadline = time.monotonic() + 5.0
        while self.commands.get_subscription_count() < 1 and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def run(self, periods: int, command=None) -> None:
        """``periods`` control periods; each sends ``command(k)`` [V] first (None: no command)."""
        for k in range(periods):
            if command is not None:
                self.commands.publish(Float64(data=float(command(k))))
                deadline = time.monotonic() + 1.0
                seen = (len(self.daq.writes), self.hw.refused_in_fault, self.hw.fault)
                while seen == (len(self.daq.writes), self.hw.refused_in_fault, self.hw.fault) \
                        and time.monotonic() < deadline:   # the command arrived: written, refused, or a fault
                    self.executor.spin_once(timeout_sec=0.005)
            self.now += PERIOD_S
            self.tick()

    def run_wall(self, seconds: float, command=None) -> None:
        """Periods for ``seconds`` of the wall clock (a check that waits on the wall clock: missing samples)."""
        deadline, k = time.monotonic() + seconds, 0
        while time.monotonic() < deadline:
            self.run(1, None if command is None else (lambda _, k=k: command(k)))
            time.sleep(PERIOD_S)
            k += 1

    def spin(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def health(self):
        status = self.hw.diagnostics.publish().status[0]
        return status.level, status.message

    def reset(self):
        from std_srvs.srv import Trigger
        assert self.reset_client.wait_for_service(timeout_sec=5.0)
        future = self.reset_client.call_async(Trigger.Request())
        deadline = time.monotonic() + 5.0
        while not future.done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)
        return future.result()

    def close(self):
        self.executor.remove_node(self.hw)
        self.executor.remove_node(self.other)
        self.hw.shutdown_safely()
        self.hw.destroy_node()
        self.other.destroy_node()
        self.executor.shutdown()


@pytest.fixture
def rig(ros_context):
    made = Rig()
    yield made
    made.close()


def sine(k):
    return 5.0 + 3.0 * math.sin(2 * math.pi * k / 200.0)


@pytest.mark.parametrize("fault, kind, periods", [
    ("read_raises", "read_failed", 1),
    ("nan", "non_finite_sample", 1),
    ("write_raises", "write_failed", 1),
    ("stuck", "stuck_sensor", 600),       # frozen while the sine moves the command: tripped after 0.5 s
    ("silent", "no_samples", None),       # no samples for 0.5 s of the wall clock
])
def test_a_fault_is_latched_safe_named_and_left_only_on_reset(rig, fault, kind, periods):
    rig.run(100, sine)
    assert rig.hw.fault is None and rig.health()[0] != b"\x02"   # (WARN: the test ticks faster than the wall clock)
    rig.daq.inject(fault)
    if fault == "silent":
        rig.run_wall(0.8, sine)
    else:
        rig.run(periods, sine)
    assert rig.hw.fault is not None and rig.hw.fault.kind == kind, rig.hw.fault
    writes = np.array(rig.daq.writes)
    assert np.all(np.isfinite(writes))                                      # no non-finite write, ever
    level, message = rig.health()
    assert level == b"\x02" and message.startswith(f"fault {kind}: ") and "~/reset" in message, message
    if fault == "write_raises":
        assert "could NOT be written" in message
    else:
        assert writes[-1] == SAFE_V and "safe voltage applied" in message
    rig.spin(0.3)
    assert rig.states and rig.states[-1].startswith(f"fault: {kind}: "), rig.states
    # latched: commands refused while it lasts, and after the cause is gone, until reset
    before = len(rig.daq.writes)
    rig.run(50, lambda k: 7.0)
    assert len(rig.daq.writes) == before and rig.hw.refused_in_fault >= 50
    if fault in ("read_raises", "write_raises"):   # the cause still there: reset refused, fault kept
        refused = rig.reset()
        assert not refused.success and refused.message.startswith(f"fault {kind} kept"), refused.message
        assert rig.hw.fault is not None
    if fault == "nan":   # a reset with no samples to check yet clears; the next period's samples latch it again
        again = rig.reset()
        assert again.success and "the next period's are checked" in again.message, again.message
        rig.run(1)
        assert rig.hw.fault is not None and rig.hw.fault.kind == kind
        rig.now += 3 * PERIOD_S   # samples waiting at the reset, still non-finite: checked by it, and refused
        kept = rig.reset()
        assert not kept.success and kept.message.startswith("fault non_finite_sample kept: non_finite_sample"), \
            kept.message
        assert rig.hw.fault is not None and rig.hw.fault.kind == kind
    rig.daq.inject(None)
    rig.run(20)
    assert rig.hw.fault is not None and rig.health()[0] == b"\x02"         # no silent clearing
    if fault == "write_raises":   # the safe voltage was retried every period until a write succeeded
        assert rig.daq.writes[-1] == SAFE_V and "safe voltage applied" in rig.health()[1]
    done = rig.reset()
    assert done.success and f"fault {kind} cleared" in done.message, done.message
    rig.spin(0.3)
    assert rig.states[-1] == "ok" and rig.health()[0] != b"\x02"
    rig.run(100, sine)
    assert rig.hw.fault is None and rig.daq.writes[-1] == pytest.approx(sine(99))


def test_a_daq_glitch_is_retried_within_the_period_said_and_counted_and_a_burst_latches(rig):
    """One read or write that raises is retried at once: no fault, but one WARN line naming the exception and a count
    on /diagnostics (the last minute's, WARN while there are any); a read that raises twice in a row latches."""
    said = []

    class Logger:   # what the node says from here on
        def __getattr__(self, level):
            return lambda text, **_: said.append((level, text))
    rig.run(50, sine)
    rig.hw.get_logger = lambda: Logger()
    rig.daq.inject("read_raises_once")
    rig.run(50, sine)
    assert rig.hw.fault is None and rig.hw.glitches == 1
    glitch = [text for level, text in said if level == "warning" and text.startswith("DAQ glitch: read_samples raised")]
    assert len(glitch) == 1 and "injected: DAQ glitch" in glitch[0] and "1 in the last minute" in glitch[0], said
    level, message = rig.health()
    assert level == b"\x01" and "1 DAQ glitch(es) in the last minute" in message, message
    values = {kv.key: kv.value for kv in rig.hw.diagnostics.publish().status[0].values}
    assert values["daq_glitches_last_minute"] == "1" and values["daq_glitches"] == "1", values
    rig.daq.inject("write_raises_once")
    rig.run(50, sine)
    assert rig.hw.fault is None and rig.hw.glitches == 2 and rig.daq.writes[-1] == pytest.approx(sine(49))
    rig.daq.inject("read_raises")   # a burst: twice in a row latches, as before
    rig.run(1, sine)
    assert rig.hw.fault is not None and rig.hw.fault.kind == "read_failed" and "twice in a row" in rig.hw.fault.detail


def test_the_controller_holds_while_the_hardware_is_in_fault_and_starts_afresh_after(ros_context):
    ns = f"/faults{os.getpid()}_{next(_ids)}"
    ctl = ValveControllerNode(namespace=ns, parameter_overrides=[Parameter("gain_set", value="pid_hc_2"),
                                                                  Parameter("diagnostics_period_s", value=0.0)])
    other = rclpy.create_node("fault_state", namespace=ns)
    state = other.create_publisher(String, "hardware_state", STATE_QOS)
    executor = make_executor()
    executor.add_node(ctl)
    executor.add_node(other)
    try:
        assert ctl.on_measurement(0.0) is not None
        state.publish(String(data="fault: stuck_sensor: position frozen"))
        deadline = time.monotonic() + 5.0
        while ctl.hardware_fault is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        assert ctl.on_measurement(1e-6) is None                    # no period runs: the integrator holds
        status = ctl.diagnostics.publish().status[0]
        assert status.level == b"\x01" and status.message.startswith("holding: the hardware is in fault (fault: "
                                                                     "stuck_sensor"), status.message
        state.publish(String(data="ok"))
        deadline = time.monotonic() + 5.0
        while ctl.hardware_fault is not None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        assert ctl.on_measurement(0.0) is not None
        assert "in control" in ctl.diagnostics.publish().status[0].message
    finally:
        executor.remove_node(ctl)
        executor.remove_node(other)
        ctl.destroy_node()
        other.destroy_node()
        executor.shutdown()


def test_valve_command_reset_leaves_the_fault_and_says_why_it_cannot(rig):
    """`valve_command reset` against the node: refused (exit 1, the backend's reason) while the DAQ still fails,
    then accepted (exit 0) once it reads again."""
    import subprocess
    import sys
    import threading
    from ros_helpers import ros_env
    rig.run(20, sine)
    rig.daq.inject("read_raises")
    rig.run(1)
    assert rig.hw.fault is not None
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            rig.executor.spin_once(timeout_sec=0.01)
    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    tool = [os.path.join(os.path.dirname(sys.executable), "valve_command"), "--namespace", rig.hw.get_namespace(),
            "reset"]
    try:
        refused = subprocess.run(tool, env=ros_env(), capture_output=True, text=True, timeout=60)
        assert refused.returncode == 1 and "reset refused: fault read_failed kept" in refused.stdout, refused
        rig.daq.inject(None)
        done = subprocess.run(tool, env=ros_env(), capture_output=True, text=True, timeout=60)
        assert done.returncode == 0 and "reset: fault read_failed cleared" in done.stdout, done
    finally:
        stop.set()
        spinner.join(5.0)
    assert rig.hw.fault is None


def test_the_backend_kit_passes_the_projects_backends_and_names_what_a_broken_one_breaks():
    """``check_backend`` on the simulated valve and the out-of-tree loopback DAQ: no problem; on backends that
    return NaN, lose samples, raise, or return rows of the wrong shape: each named."""
    import sys
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "data", "loopback_daq"))
    from loopback_daq import LoopbackBackend
    assert check_backend(lambda: SimBackend(ValveSimConfig(dt=1e-4, seed=1))) == []
    assert check_backend(lambda: LoopbackBackend(10e-6, 5.0, 2e-3, 1e-4, 5.0)) == []

    def faulty(kind):
        daq = FaultInjectingBackend(SimBackend(ValveSimConfig(dt=1e-4, seed=1)))
        daq.inject(kind)
        return daq
    assert any("non-finite" in p for p in check_backend(lambda: faulty("nan")))
    assert any("samples are lost" in p for p in check_backend(lambda: faulty("silent")))
    assert any("raised while running: OSError" in p for p in check_backend(lambda: faulty("read_raises")))

    class Transposed(SimBackend):
        def read_samples(self):
            return super().read_samples().T
    assert any("shape (k, 3)" in p for p in check_backend(lambda: Transposed(ValveSimConfig(dt=1e-4))))

    class Repeating(SimBackend):
        def read_samples(self):
            rows = super().read_samples()
            return np.vstack((rows, rows[-1:])) if rows.shape[0] else rows
    assert any("without gaps or repeats" in p for p in check_backend(lambda: Repeating(ValveSimConfig(dt=1e-4))))
    with pytest.raises(ValueError, match="fault must be one of"):
        faulty("smoke")


@pytest.mark.parametrize("fault, kind", [("read_raises", "read_failed"), ("nan", "non_finite_sample"),
                                         ("write_raises", "write_failed"), ("stuck", "stuck_sensor")])
def test_a_rig_tracking_through_a_fault_goes_safe_and_tracks_again_after_reset(ros_context, fault, kind):
    """The hardware and PID HC 2 linked in one process (valve_composed's wiring), 1 kHz on the DAQ's clock: a
    20 um reference tracked within 1 um; the fault: the safe voltage as it latches (at once; a frozen reading 0.5 s
    after the controller's command has moved 1 V), the controller holding; the cause gone and ~/reset: a step
    to -10 um tracked within 1 um within 3 s."""
    ns = f"/faults{os.getpid()}_{next(_ids)}"
    clock = [100.0]
    daq = FaultInjectingBackend(SimBackend(ValveSimConfig(dt=1e-4, seed=5), clock=lambda: clock[0]))
    hw = ValveHardwareNode(backend=daq, namespace=ns, parameter_overrides=[Parameter("diagnostics_period_s", value=0.0),
                                                                          Parameter("command_timeout_s", value=0.5)])
    ctl = ValveControllerNode(namespace=ns, parameter_overrides=[Parameter("gain_set", value="pid_hc_2"),
                                                                  Parameter("control_period_s", value=PERIOD_S),
                                                                  Parameter("diagnostics_period_s", value=0.0),
                                                                  Parameter("state_period_s", value=0.0)])
    hw.attach_controller(ctl.direct_link())
    tick = hw.claim_pacing().tick
    other = rclpy.create_node("fault_rig", namespace=ns)
    refs = other.create_publisher(Float64, "position_reference", 10)
    from std_srvs.srv import Trigger
    reset = other.create_client(Trigger, f"{ns}/valve_hardware/reset")
    executor = make_executor()
    for node in (hw, ctl, other):
        executor.add_node(node)

    def spin_until(done, timeout_s=5.0):
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        return done()

    def run(seconds):
        errors = []
        for _ in range(int(round(seconds / PERIOD_S))):
            clock[0] += PERIOD_S
            tick()
            errors.append(ctl.publish_state()[0, 3])
        return np.abs(np.array(errors)) * 1e6

    try:
        assert spin_until(lambda: refs.get_subscription_count() >= 1)
        refs.publish(Float64(data=20e-6))
        spin_until(lambda: False, 0.3)
        err = run(1.0)
        assert err[-300:].max() < 1.0, err[-300:].max()
        daq.inject(fault)
        onset = len(daq.writes)
        for _ in range(30):        # a frozen reading trips 0.5 s after the controller's command moved 1 V
            run(0.1)
            if hw.fault is not None:
                break
        assert hw.fault is not None and hw.fault.kind == kind
        assert np.all(np.isfinite(daq.writes))
        if fault != "write_raises":
            assert daq.writes[-1] == SAFE_V            # applied as the fault latched
        assert spin_until(lambda: ctl.hardware_fault is not None)
        assert ctl.diagnostics.publish().status[0].message.startswith("holding: the hardware is in fault")
        daq.inject(None)
        run(0.05)
        assert reset.wait_for_service(timeout_sec=5.0)
        future = reset.call_async(Trigger.Request())
        assert spin_until(future.done) and future.result().success, future.result()
        assert spin_until(lambda: ctl.hardware_fault is None)
        refs.publish(Float64(data=-10e-6))
        spin_until(lambda: False, 0.3)
        err = run(3.0)
        settled = np.flatnonzero(err > 1.0)
        assert settled.size == 0 or settled[-1] * PERIOD_S < 3.0 - 0.2, (settled[-5:], err[-10:])
        assert err[-200:].max() < 1.0 and len(daq.writes) > onset
    finally:
        for node in (hw, ctl, other):
            executor.remove_node(node)
        hw.shutdown_safely()
        for node in (hw, ctl, other):
            node.destroy_node()
        executor.shutdown()


@pytest.mark.parametrize("fault, kind", [("nan", "non_finite_sample"), ("write_raises", "write_failed")])
def test_a_lockstep_rig_in_fault_runs_no_period_and_says_nothing_as_a_position(ros_context, fault, kind):
    """In lockstep a command advances the simulated valve a period; NaN samples or a failing write latch the
    fault, and then neither commands, the watchdog, nor the repeat of an unanswered position publish a position,
    while the state says fault."""
    ns = f"/faults{os.getpid()}_{next(_ids)}"
    daq = FaultInjectingBackend(SimBackend(ValveSimConfig(dt=1e-4, seed=2)))
    hw = ValveHardwareNode(backend=daq, namespace=ns, parameter_overrides=[
        Parameter("clock", value="lockstep"), Parameter("command_timeout_s", value=0.2),
        Parameter("diagnostics_period_s", value=0.0)])
    other = rclpy.create_node("lockstep_probe", namespace=ns)
    positions, states = [], []
    other.create_subscription(Float64, "spool_position", lambda m: positions.append(m.data), SENSOR_QOS)
    other.create_subscription(String, "hardware_state", lambda m: states.append(m.data), STATE_QOS)
    commands = other.create_publisher(Float64, "voltage_command", COMMAND_QOS)
    executor = make_executor()
    executor.add_node(hw)
    executor.add_node(other)

    def spin(seconds, until=lambda: False):
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not until():
            executor.spin_once(timeout_sec=0.01)
        return until()
    try:
        assert spin(5.0, lambda: len(positions) >= 1)          # y_0 once the commander is matched
        for k in range(20):
            n = len(positions)
            commands.publish(Float64(data=5.0 + 0.05 * k))
            assert spin(2.0, lambda: len(positions) > n)
        daq.inject(fault)
        commands.publish(Float64(data=6.0))
        assert spin(2.0, lambda: hw.fault is not None) and hw.fault.kind == kind
        after = len(positions)
        for _ in range(5):
            commands.publish(Float64(data=6.5))
        spin(1.5)                                               # the watchdog's and the repeat's time
        assert len(positions) == after and all(math.isfinite(p) for p in positions)
        assert states[-1].startswith(f"fault: {kind}")
        assert daq.writes[-1] == SAFE_V if fault == "nan" else daq.writes[-1] == pytest.approx(5.95)
    finally:
        executor.remove_node(hw)
        executor.remove_node(other)
        hw.shutdown_safely()
        hw.destroy_node()
        other.destroy_node()
        executor.shutdown()


def test_the_watchdog_applies_the_safe_voltage_at_its_timeout_not_later(rig):
    """Commands stop (timeout 0.5 s): 0.3 s later the last command still holds, 0.8 s later the safe voltage is
    applied and /diagnostics says why (the wall clock: the watchdog's own)."""
    rig.run(50, lambda k: 7.0)
    last = time.monotonic()

    def ticks_until(seconds):
        while time.monotonic() - last < seconds:
            rig.run(1)
            time.sleep(PERIOD_S)
    ticks_until(0.3)
    assert rig.daq.writes[-1] == 7.0 and "watchdog" not in rig.health()[1]
    ticks_until(0.8)
    assert rig.daq.writes[-1] == SAFE_V
    level, message = rig.health()
    assert level == b"\x02" and message.startswith("watchdog: no valid command for 0.5 s"), message


@pytest.mark.parametrize("command, applied", [(10.5, 10.0), (10.001, 10.0), (-0.5, 0.0), (9.999, 9.999)])
def test_a_command_just_beyond_the_range_is_clamped_to_it(rig, command, applied):
    """The command range is 0..10 V: a command a little beyond it is applied at the limit and counted, one inside
    it as it is."""
    rig.run(5, lambda k: 5.0)
    rig.run(1, lambda k: command)
    assert rig.daq.writes[-1] == pytest.approx(applied, abs=1e-12)
    assert rig.hw.clamped == (0 if command == applied else 1)
