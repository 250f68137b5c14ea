"""The real-time loop: loop timing, the simulated DAQ's sample clock, the paced spin loop, composed
mode with the direct link, and a real-time hardware process (watchdog, SIGTERM)."""
import contextlib
import os
import re
import signal
import time

import numpy as np
import pytest

from ros_helpers import ros_env, start, wait_for_text

import rclpy
from rclpy.parameter import Parameter
from std_msgs.msg import Float64, Float64MultiArray

from piezo_valve_ros.backends import SimBackend
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.runtime import LoopTiming
from piezo_valve_ros.ros import (COMMAND_QOS, SAMPLES_QOS, SENSOR_QOS, claim_pacing, make_executor, Pacing,
                                 samples_from_message, spin_loop)
from piezo_valve_ros.runtime import ProcessGroup, node_command


# ---------------------------------------------------------------------------- ROS-free pieces
def test_loop_timing_counts_in_time_unanswered_and_late_commands():
    lt = LoopTiming(control_period_s=1e-3, capacity=4)
    lt.measured(0.0000)
    lt.commanded(0.0003)       # in time, 0.3 ms
    lt.commanded(0.0004)       # a second command for the same measurement: late
    lt.measured(0.0010)        # never answered
    lt.measured(0.0020)
    lt.commanded(0.0032)       # 1.2 ms: answered, not in time
    lt.measured(0.0030)
    lt.commanded(0.0035)       # in time
    s = lt.summary()
    assert (s.periods, s.answered, s.in_time, s.unanswered, s.late) == (4, 3, 2, 1, 1)
    assert s.in_time_share == pytest.approx(2 / 4)
    assert s.latency_p50_s == pytest.approx(0.5e-3) and s.latency_max_s == pytest.approx(1.2e-3)
    assert s.achieved_rate_hz == pytest.approx(1000.0)
    # a tick that came 3 periods late: the periods that should have elapsed count, not the ticks
    lt.measured(0.0070)
    lt.commanded(0.0071)
    assert lt.summary().in_time_share == pytest.approx(3 / 8)
    assert "commands in time 37.50 %" in lt.summary().line()
    lt.reset()
    assert lt.summary().periods == 0
    with pytest.raises(ValueError):
        LoopTiming(0.0)


def test_latency_ring_keeps_the_most_recent_periods():
    lt = LoopTiming(1e-3, capacity=3)
    for k, lat in enumerate([9e-4, 1e-4, 2e-4, 3e-4]):
        lt.measured(k * 1e-3)
        lt.commanded(k * 1e-3 + lat)
    assert lt.summary().latency_max_s == pytest.approx(3e-4)  # 9e-4 fell out of the ring
    assert lt.summary().answered == 4


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def test_simulated_daq_locks_its_phase_to_a_jittery_reader():
    clock = FakeClock()
    b = SimBackend(ValveSimConfig(seed=1), clock=clock)
    b.open()
    rng = np.random.default_rng(0)
    period = 2 * b.sample_period_s          # a 5 kHz reader of a 10 kHz DAQ
    clock.t += 0.37 * b.sample_period_s     # the reader starts at an arbitrary phase
    counts = []
    for k in range(2000):
        jitter = rng.uniform(-0.3, 0.3) * b.sample_period_s
        clock.t = 100.0 + 0.37e-4 + k * period + jitter
        counts.append(b.read_samples().shape[0])
    assert sum(counts[100:]) == 2 * len(counts[100:])   # every read after the lock-in: exactly one period
    assert set(counts[100:]) == {2}
    # a reader three periods late gets what it missed, nothing is dropped or repeated
    done = b._done
    clock.t += 3 * period
    rows = b.read_samples()
    assert rows.shape[0] == 6
    np.testing.assert_allclose(np.diff(rows[:, 0]), b.sample_period_s)
    assert rows[0, 0] == pytest.approx(done * b.sample_period_s)


def test_short_advances_step_sample_by_sample_with_the_batch_result():
    a, b = SimBackend(ValveSimConfig(seed=4)), SimBackend(ValveSimConfig(seed=4))
    a.open(), b.open()
    b.per_sample_below = 0  # always the batch path
    for n, v in [(1, 6.0), (5, 7.5), (13, 3.0), (2, 5.0)]:
        a.write_voltage(v), b.write_voltage(v)
        np.testing.assert_allclose(a.advance(n), b.advance(n), rtol=0, atol=1e-15)


def test_the_batch_path_is_ready_before_a_realtime_loop_and_its_warm_up_leaves_the_valve_untouched():
    """A real-time reader that falls behind gets the samples it missed by the batch path; its first run imported
    scipy.signal inside that very tick (0.5-0.9 s: the longest stall of the composed 10 kHz loop).
    ``prepare_realtime`` (the hardware node calls it on the real-time clock) runs it once on a copy of the valve:
    afterwards the import is done, and the valve gives what a valve that never warmed up gives."""
    import subprocess
    import sys
    code = ("import sys; from piezo_valve_ros.backends import SimBackend; b = SimBackend(); "
            "b.open(); before = 'scipy.signal' in sys.modules; b.prepare_realtime(); "
            "print(before, 'scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["False", "True"], out.stderr
    opened = SimBackend(ValveSimConfig(seed=7))
    opened.open()
    opened.prepare_realtime()
    opened.write_voltage(6.5)
    fresh = SimulatedValve(ValveSimConfig(seed=7))
    np.testing.assert_array_equal(opened.advance(40)[:, 2], fresh.run(np.full(40, 6.5)))


def test_a_throttled_warning_is_decided_before_the_logger_is_called():
    """The first time due, then at most once per period (rclpy's own throttle costs a source-file lookup per call)."""
    from piezo_valve_ros.ros import Throttle
    now = [100.0]
    say = Throttle(5.0, clock=lambda: now[0])
    seen = []
    for t in (100.0, 101.0, 104.9, 105.0, 105.1, 110.2):
        now[0] = t
        seen.append(say.due())
    assert seen == [True, False, False, True, False, True]


class FakeExecutor:
    """spin_once advances the fake clock by its timeout (nothing arrives) and counts the calls."""

    def __init__(self, clock):
        self.clock = clock
        self.calls = []

    def spin_once(self, timeout_sec):
        self.calls.append((self.clock.t, timeout_sec))
        self.clock.t += max(timeout_sec, 2e-5)  # a poll costs time too


def test_spin_loop_ticks_on_a_grid_skips_missed_periods_and_never_starves_callbacks():
    clock = FakeClock()
    ex = FakeExecutor(clock)
    ticks = []

    def tick():
        ticks.append(clock.t)
        if len(ticks) == 3:
            clock.t += 3.5e-3   # preempted for 3.5 periods
    spin_loop(ex, lambda: len(ticks) < 6, Pacing(1e-3, tick), clock=clock)
    t = np.array(ticks) - 100.0
    np.testing.assert_allclose(t, [1e-3, 2e-3, 3e-3, 7e-3, 8e-3, 9e-3], atol=1e-9)  # 4, 5, 6 ms skipped
    assert any(timeout == 0.0 for _, timeout in ex.calls)  # callbacks ran right after the late tick
    # busy polling: sleeps until busy_poll_s before the tick, then polls (spin_once(0)) up to it
    clock3 = FakeClock()
    ex3 = FakeExecutor(clock3)
    ticks3 = []
    spin_loop(ex3, lambda: len(ticks3) < 3, Pacing(1e-3, lambda: ticks3.append(clock3.t), busy_poll_s=1e-4),
              clock=clock3)
    sleeps = [timeout for _, timeout in ex3.calls if timeout > 0]
    polls = [t for t, timeout in ex3.calls if timeout == 0]
    assert sleeps and max(sleeps) <= 0.9e-3 + 1e-12 and len(polls) >= 3 * 4
    assert all(0 <= (t - 100.0) % 1e-3 < 2e-5 + 1e-9 or (t - 100.0) % 1e-3 > 1e-3 - 1e-4 - 1e-9
               for t in polls)  # polls only in the last 0.1 ms before a tick
    np.testing.assert_allclose(np.array(ticks3) - 100.0, [1e-3, 2e-3, 3e-3], atol=2.1e-5)  # late by < one poll
    ex2 = FakeExecutor(FakeClock())
    n = iter(range(5))
    spin_loop(ex2, lambda: next(n, None) is not None)  # unpaced: plain spin_once(0.1) calls
    assert [timeout for _, timeout in ex2.calls] == [0.1] * 5


def test_every_spin_loop_starts_with_what_start_up_allocated_out_of_the_collectors_sight():
    """gc.freeze before the loop, paced or not: a lockstep node's collections cost ~10 % of its CPU, and a full
    one over the libraries' objects would stall a paced loop."""
    import gc
    for pacing in (None, Pacing(1e-3, lambda: None)):
        gc.unfreeze()
        try:
            made_before = [[] for _ in range(10)]   # container objects the collector tracks
            clock = FakeClock()
            calls = iter(range(3))
            spin_loop(FakeExecutor(clock), lambda: next(calls, None) is not None, pacing, clock=clock)
            assert gc.get_freeze_count() >= len(made_before), pacing
        finally:
            gc.unfreeze()


# ---------------------------------------------------------------------------- ROS
def spin_until(executor, done, timeout_s: float) -> None:
    """Spin until ``done()``; fails after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < end, "timed out"
        executor.spin_once(timeout_sec=0.005)


def spin_for(executor, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.005)


@contextlib.contextmanager
def client(name: str, namespace: str):
    """A node of this test process, spun on demand; removed however the test ends."""
    node = rclpy.create_node(name, namespace=namespace)
    executor = make_executor()
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown()


@pytest.fixture(scope="module")
def ros_context():
    rclpy.init()
    yield
    rclpy.try_shutdown()


def test_composed_realtime_loop_tracks_a_reference_by_direct_link(ros_context):
    """Both nodes in one process on the wall clock at the paper's 10 kHz: every measurement gets
    its command within the tick; topics still carry positions and samples for observers."""
    from piezo_valve_ros.nodes.composed import build
    ns = f"/rt{os.getpid()}"
    with pytest.raises(ValueError, match="control_period_s differs"):
        build([Parameter("control_period_s", value=1e-4)], [Parameter("control_period_s", value=1e-3)], namespace=ns)
    hw, ctl = build([Parameter("clock", value="realtime"), Parameter("control_period_s", value=1e-4),
                     Parameter("sim.seed", value=2)],
                    [Parameter("gain_set", value="pid_hc_5"), Parameter("reference_ramp_s", value=0.002),
                     Parameter("control_period_s", value=1e-4)], namespace=ns)
    assert hw._linked_controller is not None
    observer = rclpy.create_node("observer", namespace=ns)
    seen = {"positions": 0, "rows": []}
    observer.create_subscription(Float64, "spool_position", lambda m: seen.__setitem__(
        "positions", seen["positions"] + 1), SENSOR_QOS)
    observer.create_subscription(Float64MultiArray, "samples",
                                 lambda m: seen["rows"].append(samples_from_message(m)), SAMPLES_QOS)
    ref_pub = observer.create_publisher(Float64, "position_reference", 10)
    nodes = [hw, ctl, observer]
    executor = make_executor()
    for n in nodes:
        executor.add_node(n)
    pacing = claim_pacing(nodes)
    assert pacing is not None and pacing.period_s == pytest.approx(1e-4)
    assert claim_pacing(nodes) is None  # claimed once
    timing = hw.loop_timing

    def run_periods(n: int, limit_s: float = 60.0) -> None:
        """``n`` more ticks (a loaded machine runs fewer ticks a second, not fewer ticks)."""
        target, t0 = timing.periods + n, time.monotonic()
        spin_loop(executor, lambda: timing.periods < target and time.monotonic() - t0 < limit_s, pacing)
    try:
        run_periods(3000)
        ref_pub.publish(Float64(data=30e-6))
        # the step counts from the period the controller has it (on a loaded machine the message may take many ticks)
        t0 = time.monotonic()
        while abs(ctl.publish_state()[0, 1] - 30e-6) > 1e-12 and time.monotonic() - t0 < 30.0:
            run_periods(10)
        assert abs(ctl.publish_state()[0, 1] - 30e-6) <= 1e-12   # the controller has the step
        run_periods(10000)
        # a loaded machine may stall the process (the valve runs on the last command meanwhile): then more
        # periods until the spool sits on the reference, which load can delay but not prevent
        t0 = time.monotonic()
        while abs(seen["rows"][-1][-1, 2] * 1e6 - 30.0) >= 1.0 and time.monotonic() - t0 < 30.0:
            run_periods(100)
        hw.shutdown_safely()
        t0 = time.monotonic()
        spin_loop(executor, lambda: time.monotonic() - t0 < 0.3)
        s = hw.loop_timing.summary()
        assert s.periods >= 13000
        assert s.unanswered <= 1 and s.late == 0 and s.answered >= s.periods - 1  # answered within the tick
        assert seen["positions"] > 100
        rows = np.concatenate(seen["rows"])
        assert abs(rows[-2, 2] * 1e6 - 30.0) < 1.0   # tracking (the last row is the safe voltage's)
        np.testing.assert_allclose(np.diff(rows[:, 0]), 1e-4, atol=1e-12)  # nothing lost in samples
        assert hw.backend.voltage_v == 5.0 and not hw.backend.is_open  # safe voltage, then closed
    finally:
        for n in nodes:
            executor.remove_node(n)
            n.destroy_node()
        executor.shutdown()


def test_direct_link_needs_the_realtime_clock(ros_context):
    from piezo_valve_ros.nodes.hardware import ValveHardwareNode
    hw = ValveHardwareNode(namespace=f"/ls{os.getpid()}", parameter_overrides=[Parameter("clock", value="lockstep")])
    try:
        with pytest.raises(ValueError, match="realtime"):
            hw.attach_controller(lambda y: 5.0)
        with pytest.raises(ValueError, match="samples_batch must be >= 1"):
            ValveHardwareNode(namespace=f"/ls{os.getpid()}", parameter_overrides=[Parameter("samples_batch", value=0)])
        with pytest.raises(ValueError, match="busy_poll_s must be >= 0"):
            ValveHardwareNode(namespace=f"/ls{os.getpid()}", parameter_overrides=[
                Parameter("clock", value="realtime"), Parameter("realtime.busy_poll_s", value=-1.0)])
        with pytest.raises(ValueError, match="loop_stats_period_s must be >= 0"):
            ValveHardwareNode(namespace=f"/ls{os.getpid()}",
                              parameter_overrides=[Parameter("loop_stats_period_s", value=-0.5)])
        with pytest.raises(ValueError, match="loop_stats_period_s must be finite"):
            ValveHardwareNode(namespace=f"/ls{os.getpid()}",
                              parameter_overrides=[Parameter("loop_stats_period_s", value=float("nan"))])
        # several bad values at start-up: every reason in the one refusal (HardwareSettings.from_specs)
        with pytest.raises(ValueError, match=r"samples_batch must be >= 1.*; loop_stats_period_s must be >= 0"):
            ValveHardwareNode(namespace=f"/ls{os.getpid()}", parameter_overrides=[
                Parameter("samples_batch", value=0), Parameter("loop_stats_period_s", value=-1.0)])
        assert hw.claim_pacing() is None
    finally:
        hw.destroy_node()


@pytest.mark.slow
def test_realtime_hardware_process_watchdog_and_sigterm(ros_context, tmp_path):
    """valve_hardware on the wall clock at 10 kHz in its own process: commands apply, the watchdog
    puts it on safe_voltage within command_timeout_s plus a period, SIGTERM ends it cleanly."""
    ns, timeout, period = f"/rtp{os.getpid()}", 0.2, 1e-4
    rows = []
    with client("commander", ns) as (node, executor), ProcessGroup() as procs:
        node.create_subscription(Float64MultiArray, "samples", lambda m: rows.append(samples_from_message(m)),
                                 SAMPLES_QOS)
        pub = node.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        hw = start(procs, "hardware", node_command("valve_hardware", {
            "clock": "realtime", "control_period_s": period, "command_timeout_s": timeout,
            "samples_batch": 200}, ns), str(tmp_path))
        deadline = time.monotonic() + 30
        while pub.get_subscription_count() == 0 or not rows:
            assert time.monotonic() < deadline, open(tmp_path / "hardware.log").read()
            executor.spin_once(timeout_sec=0.05)
        commands = [6.0 + 0.05 * k for k in range(20)]  # distinct values, each once applied, then silence
        for v in commands:   # (a loaded machine may not run the hardware for tens of ms: a fixed pace would
            pub.publish(Float64(data=v))   # let a later command overtake one still queued)
            spin_until(executor, lambda: any(np.any(r[:, 1] == v) for r in rows[-50:]), 5.0)
        wait_for_text(tmp_path / "hardware.log", "applying safe_voltage", timeout_s=5)
        spin_for(executor, 0.3)
        hw.send_signal(signal.SIGTERM)
        assert hw.wait(10) == 0
    data = np.concatenate(rows)
    np.testing.assert_allclose(np.diff(data[:, 0]), period, atol=1e-12)  # every sample, none lost
    cmd = data[:, 1]
    applied = [v for v in commands if np.any(cmd == v)]
    assert applied == commands                            # each applied, in order
    first_last = np.flatnonzero(cmd == commands[-1])[0]   # the tick after the last command arrived
    safe = first_last + np.flatnonzero(cmd[first_last:] == 5.0)[0]
    held_s = (safe - first_last) * period   # from applying the last command to the watchdog's tick
    log = open(tmp_path / "hardware.log").read()
    # never early: the watchdog's own silence, from the last command's arrival (a busy box may apply a
    # command a few ticks after it arrived, so the samples alone cannot show this bound)
    silent_s = float(re.search(r"no valid command for ([0-9.]+) s", log).group(1))
    # ... nor late by more than a tick that came late: the loop's longest stall (a loaded machine may not run
    # the process for a second; no watchdog in it can fire meanwhile), as its shutdown line reports it
    stall_s = 1e-3 * float(re.search(r"stalls > 2 periods \(longest ([0-9.]+) ms\)", log).group(1))
    assert timeout - 1e-3 <= silent_s <= timeout + period + max(0.05, stall_s + 0.01), (silent_s, stall_s)
    # ... and the valve held the last command until then: at most a period (+ scheduling) after it
    assert 0.5 * timeout <= held_s <= silent_s + period + 0.05, (held_s, silent_s)
    assert "safe_voltage 5.0 V applied; loop:" in log and "commands in time" in log


def test_valve_composed_process_runs_10khz_on_the_wall_clock_and_stops_on_sigterm(ros_context, tmp_path):
    ns = f"/cp{os.getpid()}"
    rows = []
    with client("client", ns) as (node, executor), ProcessGroup() as procs:
        node.create_subscription(Float64MultiArray, "samples", lambda m: rows.append(samples_from_message(m)),
                                 SAMPLES_QOS)
        ref = node.create_publisher(Float64, "position_reference", 10)
        proc = start(procs, "composed", node_command("valve_composed", {
            "clock": "realtime", "control_period_s": 1e-4, "gain_set": "ff_pid_g_2", "reference_ramp_s": 0.002},
            ns), str(tmp_path))
        deadline = time.monotonic() + 30
        while ref.get_subscription_count() == 0 or not rows:
            assert time.monotonic() < deadline, open(tmp_path / "composed.log").read()
            executor.spin_once(timeout_sec=0.05)
        # the node's side of the match may lag ours on a loaded machine (a message before it is dropped):
        # the reference is repeated until the spool moves (a repeated reference changes nothing)
        deadline = time.monotonic() + 20
        while rows[-1][-1, 2] > -5e-6:
            assert time.monotonic() < deadline, open(tmp_path / "composed.log").read()
            ref.publish(Float64(data=-25e-6))
            spin_for(executor, 0.2)
        # then at least 0.3 s of the valve's time (the samples' stamps: 3000 ticks at 10 kHz), until the spool
        # sits on the reference: a loaded machine may stall the process for seconds (the valve runs on, the
        # watchdog may apply the safe voltage meanwhile), which delays settling but cannot prevent it
        moved_at = rows[-1][-1, 0]
        deadline = time.monotonic() + 60
        while rows[-1][-1, 0] < moved_at + 0.3 or abs(rows[-1][-1, 2] * 1e6 + 25.0) >= 1.0:
            assert time.monotonic() < deadline, (rows[-1][-1], open(tmp_path / "composed.log").read())
            executor.spin_once(timeout_sec=0.05)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    data = np.concatenate(rows)
    log = open(tmp_path / "composed.log").read()
    np.testing.assert_allclose(np.diff(data[:, 0]), 1e-4, atol=1e-12)
    assert "position and command pass by function call" in log
    assert "safe_voltage 5.0 V applied; loop:" in log and "unanswered 0, late 0" in log


def test_controller_steps_only_when_its_command_can_arrive(ros_context):
    """A measurement that arrives before anyone subscribes to voltage_command is not used: stepping
    then would integrate against a valve that never gets the command (and the hardware repeats its
    position until answered, so the lockstep rig would see two steps for one period)."""
    from piezo_valve_ros.nodes.controller import ValveControllerNode
    ns = f"/cl{os.getpid()}"
    ctl = ValveControllerNode(namespace=ns, parameter_overrides=[Parameter("gain_set", value="pid_1"),
                                                                 Parameter("initial_reference_m", value=20e-6)])
    try:
        before = ctl.controller.integrator_um
        ctl._on_position(Float64(data=0.0))
        assert ctl.controller.integrator_um == before and ctl._said_no_listener
        with client("listener", ns) as (node, executor):
            seen = []
            node.create_subscription(Float64, "voltage_command", lambda m: seen.append(m.data), COMMAND_QOS)
            deadline = time.monotonic() + 10
            while not ctl.command_has_listener:
                assert time.monotonic() < deadline
                spin_for(executor, 0.05)
            ctl._on_position(Float64(data=0.0))
            assert ctl.controller.integrator_um != before  # stepped once the command has a listener
            deadline = time.monotonic() + 5
            while not seen and time.monotonic() < deadline:
                spin_for(executor, 0.05)
            assert len(seen) == 1
    finally:
        ctl.destroy_node()


SIGNAL_BURST_SCRIPT = """
import sys, time
import rclpy
from piezo_valve_ros.ros import init_ros, spin
init_ros([])
node = rclpy.create_node('signal_burst')
node.create_timer(0.001, lambda: None)
print('spinning', flush=True)
sys.exit(spin([node], on_exit=lambda: print('cleaned up', flush=True)))
"""


@pytest.mark.parametrize("burst", [False, True])
def test_a_burst_of_signals_stops_a_node_cleanly(tmp_path, burst):
    """A node's stop request must survive signals arriving inside its own handler (a parent's death brings
    two SIGTERMs at once: the kernel's and the parent watcher's).  A handler taking a lock deadlocked there."""
    import subprocess
    import sys
    log = tmp_path / "burst.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-c", SIGNAL_BURST_SCRIPT], env=ros_env(), stdout=out,
                                stderr=subprocess.STDOUT)
    try:
        wait_for_text(log, "spinning", timeout_s=30)
        deadline = time.monotonic() + (2.0 if burst else 0.0)
        while True:  # one SIGTERM, or SIGTERMs without a pause until the process has ended (or 2 s)
            try:
                os.kill(proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                break
            if time.monotonic() > deadline or proc.poll() is not None:
                break
        assert proc.wait(10) == 0, log.read_text()
        assert "cleaned up" in log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_traced_loops_late_ticks_are_given_to_what_filled_them():
    """bench/loop_trace.attribute_misses on a made-up trace of a 100 us loop: a gap after a collection, one after a
    tick that ran past the next one's due time, one with a callback in it, one after a wait that woke late and one
    with nothing in it; each gap's missed periods (whole periods less one) go to its cause, the callback's by name."""
    from loop_trace import CAUSES, LoopTrace, attribute_misses
    period = 1e-4
    trace = LoopTrace()
    t = 0.0
    starts = []
    for gap in [1] * 5 + [3] + [1] * 5 + [2] + [1] * 5 + [4] + [1] * 5 + [2] + [1] * 5 + [3] + [1] * 3:
        starts.append(t)
        t += gap * period
    for s in starts:
        trace.ticks.append((s, 3e-5))
    late = [k for k in range(1, len(starts)) if starts[k] - starts[k - 1] > 1.5 * period]
    gc_gap, tick_gap, callback_gap, wake_gap, silent_gap = (starts[k - 1] for k in late)
    trace.collections.append((gc_gap + 1.2 * period, 1.5 * period))
    trace.ticks[starts.index(tick_gap)] = (tick_gap, 1.6 * period)
    trace.callbacks.append((callback_gap + 0.5 * period, 2.8 * period, "controller: publish_state"))
    trace.waits.append((wake_gap + 3e-5, 1.6 * period, 5e-5))   # asked for 50 us, back after 160 us
    trace.waits.append((silent_gap + 3e-5, 5e-5, 5e-5))          # on time: the gap is nothing the process saw
    misses = attribute_misses(trace, period)
    assert misses.late_ticks == 5
    assert misses.periods == dict(zip(CAUSES, (2, 1, 3, 1, 2))), misses.periods
    assert misses.by_callback == {"controller: publish_state": 3}
    assert misses.excess_s["callbacks"] == pytest.approx(3 * period)
    assert misses.line().startswith("9 periods missed in 5 late ticks: garbage collection 2, the tick itself 1, "
                                    "callbacks 3 (controller: publish_state 3), woke late 1, unaccounted 2")


def test_a_samples_buffer_refilled_in_place_is_the_message_made_anew():
    """ros.messages.SamplesBuffer (what the hardware's full batches and the controller's state go out in): after
    each refill its message equals ``samples_message`` of the same rows, layout and label included, and reads back
    as those rows."""
    from piezo_valve_ros.ros import samples_from_message, samples_message, SamplesBuffer
    rng = np.random.default_rng(3)
    buffer = SamplesBuffer(4, 3)
    for _ in range(2):
        rows = rng.normal(size=(4, 3))
        buffer.rows[:] = rows
        assert buffer.message == samples_message(rows)
        np.testing.assert_array_equal(samples_from_message(buffer.message), rows)
    state = SamplesBuffer(1, 2, "a,b")
    state.rows[0] = (1.5, 2.5)
    assert state.message == samples_message(np.array([[1.5, 2.5]]), "a,b")
