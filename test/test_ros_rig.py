"""End-to-end tests through the ROS graph: separate processes, lockstep, private DDS domain."""
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ros_helpers import ros_env, start, wait_for_text

import rclpy
from std_msgs.msg import Float64

from piezo_valve_ros.core.sim import run_closed_loop
from piezo_valve_ros.core import step_metrics
from piezo_valve_ros.core.sim import step_reference_m
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import STRATEGIES, ControllerConfig, PIDGains, ValveController, gain_set
from piezo_valve_ros.ros import COMMAND_QOS
from piezo_valve_ros.nodes.hardware import MAX_COMMAND_TIMEOUT_S
from piezo_valve_ros.rig import RigClient, run_in_background
from piezo_valve_ros.runtime import ProcessGroup, node_command

DT = 1e-4
GAINS = {"pid": "pid_1", "pid_hc": "pid_hc_5", "ff_pid": "ff_pid_1", "ff_pid_g": "ff_pid_g_2"}


@pytest.fixture(scope="module")
def ros_context():
    rclpy.init()
    yield
    rclpy.try_shutdown()


_counter = iter(range(1000))


@pytest.fixture
def ros(ros_context):
    """A rig client in a namespace of its own, so no test sees another's rig."""
    client = RigClient(namespace=f"/t{os.getpid()}_{next(_counter)}")
    thread, stop, executor = run_in_background([client])
    yield client
    stop.set()
    thread.join(2)
    executor.remove_node(client)
    client.destroy_node()


@pytest.fixture
def procs():
    group = ProcessGroup()
    yield group
    group.stop()


def start_rig(procs, tmp_path, ns, hw=None, ctl=None, controller=True):
    # the watchdog runs on the wall clock even in lockstep: at its longest, a controller stalled by a busy
    # machine does not get the safe voltage mid-run (the watchdog test sets its own timeout)
    hw_params = {"clock": "lockstep", "control_period_s": DT, "lockstep.step_budget": 0, "sim.seed": 3,
                 "command_timeout_s": MAX_COMMAND_TIMEOUT_S}
    hw_params.update(hw or {})
    start(procs, "hardware", node_command("valve_hardware", hw_params, ns), str(tmp_path))
    if controller:
        ctl_params = {"control_period_s": DT, "reference_ramp_s": 0.002}
        ctl_params.update(ctl or {})
        start(procs, "controller", node_command("valve_controller", ctl_params, ns), str(tmp_path))


def this_rig_rows(client):
    """Rows of the newest hardware process (its sample times restart at 0)."""
    rows = client.all_rows()
    return rows[np.flatnonzero(rows[:, 0] == 0.0)[-1]:]


@pytest.mark.slow
@pytest.mark.parametrize("strategy", STRATEGIES)
def test_step_through_ros_equals_in_process(ros, procs, tmp_path, strategy):
    a, b = -17.5, 35.0
    gains = gain_set(GAINS[strategy])[1] if strategy in GAINS else PIDGains(0.0, 0.0)
    start_rig(procs, tmp_path, ros.get_namespace(), ctl={"strategy": strategy, "kp": gains.kp, "ki": gains.ki,
                                    "initial_reference_m": a * 1e-6})
    ros.wait_ready()
    n_hold, n_after = 300, 700
    ros.run_periods(n_hold)
    ros.set_reference(b * 1e-6)
    ros.run_periods(n_after)
    time.sleep(0.2)
    rows = this_rig_rows(ros)[1:]  # row 0 is the hardware's first sample at its initial voltage
    assert rows.shape[0] >= n_hold + n_after
    # in process: the same valve, controller and reference sequence
    ref, ramp_index = step_reference_m(DT, a, b, hold_before_s=(n_hold + 1) * DT, hold_after_s=1.0)
    ref = ref[: n_hold + n_after]
    valve = SimulatedValve(ValveSimConfig(seed=3))
    rec = run_closed_loop(valve, ValveController(ControllerConfig(strategy=strategy, gains=gains)), ref)
    y_ros = rows[: n_hold + n_after, 2]          # position after each applied command
    y_core = np.append(rec.position_m[1:], np.nan)[: n_hold + n_after]
    np.testing.assert_allclose(rows[: n_hold + n_after - 1, 1], rec.command_v[: n_hold + n_after - 1], atol=1e-9)
    m_ros = step_metrics(y_ros[:-1], ramp_index, a, b, DT)
    m_core = step_metrics(y_core[:-1], ramp_index, a, b, DT)
    assert abs(m_ros.settling_time_s - m_core.settling_time_s) <= DT + 1e-12
    assert abs(m_ros.overshoot_pct - m_core.overshoot_pct) < 0.05


@pytest.mark.slow
def test_strategy_switch_over_parameters_is_bumpless_and_bad_updates_rejected(ros, procs, tmp_path):
    start_rig(procs, tmp_path, ros.get_namespace(), ctl={"gain_set": "", "strategy": "pid", "kp": 1, "ki": 474})  # ints accepted
    ros.wait_ready()
    ros.set_reference(30e-6)
    before = ros.run_periods(400)
    # bad updates are rejected with a reason and change nothing
    for bad in ({"strategy": "bang_bang"}, {"gpim.rho": -5.0}, {"kp": float("nan")}, {"gpim.n": 2.5},
                {"valve_model.den": [1.0, -1.0]}):
        res = ros.set_params(ros.controller, bad)
        assert not res[0].successful and res[0].reason, bad
    res = ros.set_params(ros.controller, {"strategy": "pid_hc", "kp": 1.6879, "ki": 748.6437})
    assert all(r.successful for r in res)
    after = ros.run_periods(400)
    jump = abs(after[1, 1] - before[-1, 1])  # after[0] applies the command held across the switch
    assert jump < 0.05
    assert abs(after[-1, 2] * 1e6 - 30.0) < 1.0
    log = open(tmp_path / "controller.log").read()
    assert "rejected parameter update" in log and "bang_bang" in log


@pytest.mark.slow
def test_watchdog_applies_safe_voltage_when_controller_dies(ros, procs, tmp_path):
    timeout = 0.3
    start_rig(procs, tmp_path, ros.get_namespace(), hw={"command_timeout_s": timeout, "safe_voltage": 5.0})
    ros.wait_ready()
    ros.set_reference(50e-6)
    ros.run_periods(500)
    controller = [p for n, p in procs.procs if n == "controller"][0]
    assert ros.all_rows()[-1, 1] > 6.0  # driving well away from the safe voltage
    ros.set_params(ros.hardware, {"lockstep.step_budget": -1})
    time.sleep(0.2)
    controller.kill()
    killed = time.monotonic()
    fired = wait_for_text(tmp_path / "hardware.log", "applying safe_voltage", timeout_s=5)
    assert fired - killed <= timeout + 0.1  # timeout plus the watchdog's check period (lockstep: wall clock)
    deadline = time.monotonic() + 5
    while abs(ros.all_rows()[-1, 1] - 5.0) > 1e-12 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert ros.all_rows()[-1, 1] == 5.0


def test_bad_commands_are_rejected_or_clamped_and_logged(ros, procs, tmp_path):
    start_rig(procs, tmp_path, ros.get_namespace(), hw={"lockstep.step_budget": -1, "command_timeout_s": 10.0}, controller=False)
    pub = ros.create_publisher(Float64, "voltage_command", COMMAND_QOS)
    try:
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # the hardware's side of the match may lag ours; a message sent before it is dropped
        for v in (7.0, float("nan"), 12.0, float("inf"), -3.0, float("-inf"), 6.0):
            pub.publish(Float64(data=v))
            time.sleep(0.15)
        ros.set_params(ros.hardware, {"lockstep.step_budget": 0})  # pause -> samples flushed
        time.sleep(0.3)
        applied = this_rig_rows(ros)[1:, 1]
        assert list(applied) == [7.0, 10.0, 0.0, 6.0]  # NaN/inf never reach the valve
        log = open(tmp_path / "hardware.log").read()
        assert "rejected non-finite voltage command" in log and "clamped voltage command 12" in log
    finally:
        ros.destroy_publisher(pub)


def run_rig_until_signal(tmp_path, args, sig, run_s=0.5, until=None) -> str:
    """Start ``valve_rig --demo none ARGS`` in its own process group, send ``sig`` ``run_s`` after it runs (or,
    given ``until``, once ``until(log text)`` holds): SIGINT to the whole group, as a terminal's Ctrl-C goes to
    its foreground process group, SIGTERM to the rig alone.  It must exit 0, print no KeyboardInterrupt and
    leave no process behind.  Returns its output."""
    log = open(tmp_path / "rig.log", "w")
    rig = subprocess.Popen([sys.executable, "-m", "piezo_valve_ros.cli.rig", "--demo", "none", *args],
                           env=ros_env(), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for_text(tmp_path / "rig.log", "running; Ctrl-C", timeout_s=30)
        deadline = time.monotonic() + 60
        while until is not None and not until(open(tmp_path / "rig.log").read()):
            assert time.monotonic() < deadline, open(tmp_path / "rig.log").read()
            time.sleep(0.1)
        time.sleep(run_s)
        if sig == signal.SIGINT:
            os.killpg(rig.pid, sig)
        else:
            rig.send_signal(sig)
        assert rig.wait(15) == 0, open(tmp_path / "rig.log").read()
        time.sleep(0.5)
        with pytest.raises(ProcessLookupError):
            os.killpg(rig.pid, 0)  # nobody left in the rig's process group
        text = open(tmp_path / "rig.log").read()
        assert "KeyboardInterrupt" not in text, text   # the nodes' parent watchers do not get the Ctrl-C
        return text
    finally:
        try:
            os.killpg(rig.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_a_node_that_ends_on_the_rigs_own_ctrl_c_before_the_rig_sees_it_is_a_stop_not_a_failure(monkeypatch, capsys):
    """A Ctrl-C reaches the rig and its nodes at once; on a loaded machine a node can exit before the rig has
    handled it (the README tour's rig once ended with exit 1, "a node exited").  A node's exit followed by the
    rig's context closing within STOP_RACE_S is the stop; one that no stop follows is a failure."""
    from piezo_valve_ros.cli import rig

    class Ended:
        def poll(self):
            return 0

    class Procs:
        procs = [("valve_hardware", Ended())]

    args = rig.parse_args(["--demo", "none"])
    ok = iter([True, True, True, False])    # the loop's check, then the signal closes the context
    monkeypatch.setattr(rig.rclpy, "ok", lambda: next(ok, False))
    monkeypatch.setattr(rig.time, "sleep", lambda s: None)
    assert rig._run_until_stopped(args, Procs(), None) == 0
    assert "a node exited" not in capsys.readouterr().err
    monkeypatch.setattr(rig.rclpy, "ok", lambda: True)   # no stop follows: the node failed
    monkeypatch.setattr(rig, "STOP_RACE_S", 0.05)
    assert rig._run_until_stopped(args, Procs(), None) == 1
    assert "valve_rig: a node exited; stopping the rig" in capsys.readouterr().err


@pytest.mark.slow
def test_sigterm_to_rig_leaves_no_process(tmp_path):
    text = run_rig_until_signal(tmp_path, ["--clock", "realtime", "--control-period-s", "0.001"], signal.SIGTERM)
    assert "safe_voltage 5.0 V applied" in text
    assert "FATAL" not in text and "Traceback" not in text and "Error occurred" not in text, text


@pytest.mark.slow
def test_sigterm_to_a_lockstep_rig_stops_every_node_without_a_stack_trace(tmp_path):
    """Lockstep runs flat out: a signal lands inside a callback nearly every time (it used to print
    "[FATAL] Exception in 'subscriptions' callback" with a trace).  The shutdown line says what lockstep
    measures, not real-time deadlines."""
    text = run_rig_until_signal(tmp_path, [], signal.SIGTERM, run_s=2.0)
    assert "FATAL" not in text and "Traceback" not in text and "Error occurred" not in text, text
    line = [x for x in text.splitlines() if "safe_voltage 5.0 V applied; lockstep:" in x]
    assert line and "periods/s" in line[0] and "commands in time" not in line[0]


@pytest.mark.slow
def test_a_lockstep_rig_runs_no_faster_than_its_max_speed(tmp_path):
    """--lockstep-speed 2: the valve's time runs at most twice the wall clock's (load can slow it, never speed it
    up), every period still answered; the option is refused off lockstep.  The loop's own stats lines say when it
    has run long enough (a busy machine can take seconds to match the controller)."""
    params = tmp_path / "stats.yaml"
    params.write_text("valve_hardware:\n  ros__parameters:\n    loop_stats_period_s: 0.25\n")

    def ran_long_enough(text):
        return any(int(n) >= 1200 for n in re.findall(r"lockstep: (\d+) periods", text))

    text = run_rig_until_signal(tmp_path, ["--control-period-s", "0.001", "--lockstep-speed", "2",
                                           "--params-file", str(params)], signal.SIGINT, run_s=0.0,
                                until=ran_long_enough)
    line = next(x for x in text.splitlines() if "safe_voltage 5.0 V applied; lockstep:" in x)
    periods, rate = re.search(r"lockstep: (\d+) periods .* = (\d+) periods/s", line).groups()
    assert int(periods) >= 1200 and int(rate) <= 2000 * 1.02, line
    refused = subprocess.run([sys.executable, "-m", "piezo_valve_ros.cli.rig", "--demo", "none", "--clock", "realtime",
                              "--lockstep-speed", "1"], env=ros_env(), capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "--lockstep-speed" in refused.stderr and "lockstep" in refused.stderr, refused
    from piezo_valve_ros.cli.rig import main as valve_rig
    for speed in ("nan", "inf", "-1"):   # refused before anything starts
        assert valve_rig(["--demo", "none", "--lockstep-speed", speed]) == 2, speed


@pytest.mark.slow
def test_nodes_die_with_a_rig_killed_by_sigkill(tmp_path):
    """SIGKILL gives the rig no chance to stop its children: they get SIGTERM from the kernel
    (PR_SET_PDEATHSIG), apply the safe voltage and exit."""
    log = open(tmp_path / "rig.log", "w")
    rig = subprocess.Popen([sys.executable, "-m", "piezo_valve_ros.cli.rig", "--demo", "none", "--clock", "realtime",
                            "--control-period-s", "0.001"], env=ros_env(), stdout=log, stderr=subprocess.STDOUT,
                           start_new_session=True)
    try:
        wait_for_text(tmp_path / "rig.log", "running; Ctrl-C", timeout_s=30)
        rig.kill()
        rig.wait(5)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                os.killpg(rig.pid, 0)  # the children are still in the rig's process group
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            ps = subprocess.run(["ps", "-o", "pid,ppid,stat,etime,args", "-g", str(rig.pid)], capture_output=True,
                                text=True).stdout
            raise AssertionError(f"the rig's children outlived it:\n{ps}\n{open(tmp_path / 'rig.log').read()}")
        assert "safe_voltage 5.0 V applied" in open(tmp_path / "rig.log").read()
    finally:
        try:
            os.killpg(rig.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


_STUCK_CHILD = """
import ctypes, signal
from piezo_valve_ros.runtime.processes import die_with_parent
signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})   # a stop request it will not act on ...
assert die_with_parent()
print("child ready", flush=True)
libc = ctypes.PyDLL(None)
while True:
    libc.sleep(60)   # ... and in C, holding the GIL: no thread of its own can run
"""

_PARENT = """
import subprocess, sys, time
from piezo_valve_ros.runtime.processes import ProcessGroup
group = ProcessGroup()
group.start("stuck", [sys.executable, "-c", sys.argv[1]], stdout=sys.stdout, stderr=sys.stderr)
time.sleep(600)
"""


def test_a_child_stuck_in_c_holding_the_gil_is_ended_after_its_parents_sigkill(tmp_path):
    """The backstop of the death signal works where the child's own Python cannot run: its SIGTERM handler and
    any thread of its own wait for the GIL, so a separate watcher process dumps its stacks and kills it
    PARENT_DEATH_GRACE_S after it was asked to stop."""
    from piezo_valve_ros.runtime import PARENT_DEATH_GRACE_S
    log_path = tmp_path / "parent.log"
    with open(log_path, "w") as log:
        parent = subprocess.Popen([sys.executable, "-c", _PARENT, _STUCK_CHILD], stdout=log,
                                  stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for_text(log_path, "child ready", timeout_s=30)
        time.sleep(0.5)   # the watcher has started (it is spawned before "child ready")
        parent.kill()
        parent.wait(5)
        killed_at = time.monotonic()
        deadline = killed_at + PARENT_DEATH_GRACE_S + 10
        while time.monotonic() < deadline:
            try:
                os.killpg(parent.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            raise AssertionError(f"the stuck child outlived its parent:\n{log_path.read_text()}")
        gone_after = time.monotonic() - killed_at
        assert gone_after >= PARENT_DEATH_GRACE_S - 0.5   # first asked to stop, which it could not do
        text = log_path.read_text()
        assert "its shutdown hung; ending it (stacks follow)" in text
        assert "most recent call first" in text   # faulthandler's dump of the stuck thread
    finally:
        try:
            os.killpg(parent.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_parameter_files_load_into_the_nodes(procs, tmp_path):
    root = os.path.join(os.path.dirname(__file__), "..")
    cmd = node_command("valve_controller", {}, "/pf") + [
        "--params-file", os.path.join(root, "config", "paper_model.yaml"),
        "--params-file", os.path.join(root, "config", "rig.yaml")]
    start(procs, "controller", cmd, str(tmp_path))
    wait_for_text(tmp_path / "controller.log", "valve_controller up: strategy=pid_hc kp=1.6879", timeout_s=20)
    cmd = node_command("valve_hardware", {}, "/pf") + ["--params-file", os.path.join(root, "config", "rig.yaml")]
    start(procs, "hardware", cmd, str(tmp_path))
    wait_for_text(tmp_path / "hardware.log", "clock=lockstep period=0.100 ms", timeout_s=20)


def _demo_table(text: str) -> list[tuple[float, ...]]:
    rows = []
    for line in text.splitlines():
        parts = line.replace("->", " ").split()
        if len(parts) == 4 and all(p.lstrip("-").replace(".", "", 1).isdigit() for p in parts):
            rows.append(tuple(float(p) for p in parts))
    return rows


@pytest.mark.slow
def test_step_demo_prints_the_same_table_in_separate_processes_and_composed(tmp_path):
    """The main job (`valve_rig`): the paper's three steps, settling time and overshoot, identical
    whether the nodes run in separate processes or composed in one."""
    tables = []
    for extra in ([], ["--composed"]):
        out = subprocess.run([sys.executable, "-m", "piezo_valve_ros.cli.rig", *extra], env=ros_env(),
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        assert "Paper step tests under pid_hc_5" in out.stdout
        table = _demo_table(out.stdout)
        assert [(a, b) for a, b, _, _ in table] == [(0.0, 17.5), (-17.5, 35.0), (-52.5, 35.0)]
        assert all(0 < ts < 20 and 0 <= os_ < 5 for _, _, ts, os_ in table), table
        tables.append(table)
    assert tables[0] == tables[1]


@pytest.mark.slow
def test_step_demo_counts_control_periods_not_sample_rows():
    """At 2 ms a control period holds 20 samples: settling times and the period count are in periods; the rig
    runs in the namespace it is given."""
    ns = f"demo{os.getpid()}"
    out = subprocess.run([sys.executable, "-m", "piezo_valve_ros.cli.rig", "--control-period-s", "0.002",
                          "--hold-s", "0.2", "--namespace", f"/{ns}"], env=ros_env(), capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert f"[{ns}.valve_hardware]" in out.stderr and f"[{ns}.valve_controller]" in out.stderr  # --namespace
    table = _demo_table(out.stdout)
    assert len(table) == 3 and all(ts >= 2.0 for _, _, ts, _ in table), out.stdout  # at least one period
    periods = int(out.stdout.split(" control periods in ")[0].split()[-1])
    assert periods == 2 + 3 * 2 * 100, out.stdout  # the start-up period, the first command, hold + after x 3
    # six references, each acknowledged by the controller before the next period (what orders them in
    # lockstep): within ms with the fast-acknowledgement profile, up to Fast DDS's 3 s heartbeat without it
    wall_s = float(out.stdout.split(" s wall time")[0].split()[-1])
    assert wall_s < 6 * 1.5, out.stdout


def test_fast_acknowledgements_are_chosen_for_tools_and_not_passed_to_nodes():
    """The profile is chosen where nothing else is (Fast DDS, no profiles file of the user's), and dropped
    from the environment of the nodes a launcher starts; its writers' heartbeat is 20 ms."""
    import xml.etree.ElementTree as ET
    from piezo_valve_ros.runtime import (FAST_ACK_PROFILE, HEARTBEAT_PERIOD_S, use_fast_acknowledgements,
                                         without_fast_acknowledgements)
    from piezo_valve_ros.runtime import ProcessGroup
    env = {}
    assert use_fast_acknowledgements(env) and env == {"FASTRTPS_DEFAULT_PROFILES_FILE": str(FAST_ACK_PROFILE)}
    assert use_fast_acknowledgements(env)                                   # chosen twice: still ours
    assert without_fast_acknowledgements(env) == {}
    mine = {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/my_profiles.xml"}
    assert not use_fast_acknowledgements(mine) and mine == {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/my_profiles.xml"}
    assert without_fast_acknowledgements(dict(mine)) == mine                # the user's file stays
    assert not use_fast_acknowledgements(cyclone := {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"})
    assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in cyclone
    ns = {"p": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    writer = ET.parse(FAST_ACK_PROFILE).getroot().find("p:data_writer", ns)
    assert writer.get("is_default_profile") == "true"
    period = writer.find("p:times/p:heartbeatPeriod", ns)
    assert int(period.find("p:sec", ns).text) + 1e-9 * int(period.find("p:nanosec", ns).text) == HEARTBEAT_PERIOD_S
    # a node started by a launcher runs on the middleware's defaults
    with ProcessGroup() as procs:
        child = procs.start("env", [sys.executable, "-c", "import os; print(os.environ.get("
                                    "'FASTRTPS_DEFAULT_PROFILES_FILE', 'none'))"],
                            env={**os.environ, "FASTRTPS_DEFAULT_PROFILES_FILE": str(FAST_ACK_PROFILE)},
                            stdout=subprocess.PIPE, text=True)
        assert child.communicate(timeout=30)[0].strip() == "none"


def test_composed_realtime_rig_runs_and_stops_on_sigint(tmp_path):
    text = run_rig_until_signal(tmp_path, ["--composed", "--clock", "realtime"], signal.SIGINT, run_s=1.0)
    assert "rig up (composed, realtime)" in text and "position and command pass by function call" in text
    line = [x for x in text.splitlines() if "safe_voltage 5.0 V applied; loop:" in x]
    assert line and "(nominal 10000 Hz)" in line[0] and "unanswered 0, late 0" in line[0]


@pytest.mark.slow
def test_a_loop_with_two_periods_of_delay_is_caught_by_the_guard_through_ros(ros, procs, tmp_path):
    """A sensor (or transport) delay of two control periods makes PID HC 5 at 1 kHz oscillate rail to rail
    (the +-60 um swings a busy computer produced).  Through the ROS graph, in lockstep (deterministic): the
    controller's oscillation guard catches it, says so, and the command spends almost no time on the rails;
    the same run in process gives the same commands."""
    period, delay_s = 1e-3, 2e-3
    start_rig(procs, tmp_path, ros.get_namespace(), hw={"control_period_s": period, "sim.sensor_delay_s": delay_s},
              ctl={"control_period_s": period, "gain_set": "pid_hc_5", "reference_ramp_s": 0.0})
    ros.samples_per_period = 10
    ros.wait_ready()
    ros.run_periods(50)
    ros.set_reference(30e-6)
    rows = ros.run_periods(1500)
    commands = rows[:, 1]
    on_rail = (commands <= 0.0) | (commands >= 10.0)
    log = open(tmp_path / "controller.log").read()
    assert "oscillation guard: commands on both rails" in log
    assert on_rail.mean() < 0.05, on_rail.mean()
    # in process, the same valve (delay included) and controller: the guard is part of the controller
    from piezo_valve_ros.core.sim import SensorParams
    config = ValveSimConfig(seed=3, sensor=SensorParams(delay_samples=20))
    valve = SimulatedValve(config)
    strategy, gains = gain_set("pid_hc_5")
    ctl = ValveController(ControllerConfig(strategy=strategy, gains=gains, dt=period))
    y = valve.run(np.full(10, config.initial_voltage_v))[-1]
    v_core = []
    for k in range(50 + 1500):  # the command applied first in the second budget was computed before the new reference
        v = ctl.step(0.0 if k <= 50 else 30e-6, y)
        v_core.append(v)
        y = valve.run(np.full(10, v))[-1]
    assert ctl.guard_trips >= 1
    np.testing.assert_allclose(commands, v_core[50:], atol=1e-9)


@pytest.mark.parametrize("demo, keeps", [("steps", True), ("none", False)])
def test_valve_rig_keeps_the_samples_only_for_its_step_demo(ros_context, demo, keeps):
    """valve_rig's own client subscribes to ``samples`` for the step demo, which reads them; with --demo none the
    rig runs until stopped, and a client keeping every sample would grow without end."""
    from piezo_valve_ros.cli.rig import parse_args, rig_client
    client = rig_client(parse_args(["--demo", demo, "--namespace", f"/k{os.getpid()}_{demo}"]), 1)
    try:
        topics = [sub.topic_name for sub in client.subscriptions]
        assert any(t.endswith("/samples") for t in topics) == keeps, topics
    finally:
        client.destroy_node()
