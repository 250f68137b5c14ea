"""The everyday tools around a running rig: valve_record, valve_command, valve_plot (issue 12)."""
import contextlib
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from ros_helpers import ros_env, wait_for_text

from piezo_valve_ros.io import FLOAT64_TYPE, TYPESTORE, read_samples
from piezo_valve_ros.core.sim import load_profile, ramp_profile, sine_profile
from piezo_valve_ros.cli.command import parse_assignment
from piezo_valve_ros.cli.record import dropped_sample_rows
from piezo_valve_ros.runtime import ProcessGroup

BIN = os.path.dirname(sys.executable)  # the console scripts of the installed package


def tool(name: str, *args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([os.path.join(BIN, name), *args], env=ros_env(), capture_output=True, text=True,
                          timeout=timeout_s)


# ---------------------------------------------------------------------------- no ROS
def test_valve_plot_puts_its_figures_beside_the_bag_named_as_the_user_named_it():
    from pathlib import Path
    from piezo_valve_ros.cli.plot import default_figures_dir
    assert default_figures_dir("run1") == Path("run1_plots") == default_figures_dir("run1/")
    assert default_figures_dir("/data/day2/run1") == Path("/data/day2/run1_plots")
    assert default_figures_dir(".") == Path(os.getcwd() + "_plots")
    assert default_figures_dir("x/..") == Path(os.getcwd() + "_plots")   # resolved: x/.. is this directory


def test_reference_profiles_and_their_refusals(tmp_path):
    t, y = ramp_profile(0.0, 30e-6, 2.0, rate_hz=10.0)
    assert t[0] == 0 and t[-1] == 2.0 and y[-1] == pytest.approx(30e-6) and t.size == 21
    t, y = sine_profile(40e-6, 1.0, 1.0, offset_m=5e-6, rate_hz=100.0)
    assert y.max() == pytest.approx(45e-6, rel=1e-3) and y[-1] == pytest.approx(5e-6)
    for call, says in [(lambda: ramp_profile(0, 1e-5, 0.0), "duration must be > 0"),
                       (lambda: sine_profile(1e-5, 150.0, 1.0, rate_hz=200.0), "frequency must lie in"),
                       (lambda: sine_profile(1e-5, 1.0, 1.0, rate_hz=1e6), "rate must lie in")]:
        with pytest.raises(ValueError, match=says):
            call()
    good = tmp_path / "demand.csv"
    good.write_text("time_s,position_m  # header\n0, 0\n0.5, 1e-5\n# a comment\n1.0 2e-5\n")
    t, y = load_profile(good)
    assert list(t) == [0, 0.5, 1.0] and list(y) == [0, 1e-5, 2e-5]
    for text, says in [("0,0\n0.5,abc\n", "demand.csv:2: not two numbers"), ("0,0\n1,1,1\n", "expected"),
                       ("1,0\n0.5,0\n", "never decrease"), ("# nothing\n", "no 'time_s, position_m' rows")]:
        good.write_text(text)
        with pytest.raises(ValueError, match=says):
            load_profile(good)
    # the header says the unit: a file in micrometres is read as micrometres, never as metres
    good.write_text("time_s, position_um\n0, 0\n0.5, 20\n")
    assert load_profile(good)[1] == pytest.approx([0.0, 20e-6], rel=1e-12)
    good.write_text("time_s, position\n0, 0\n0.5, 20\n")
    with pytest.raises(ValueError, match="expected 'time_s, position_m'"):
        load_profile(good)


@pytest.mark.parametrize("args, says", [(["step", "20"], "a position of 20 m"), (["step", "--", "-1"], "a position of 1 m"),
                                        (["step", "1e-3"], "a position of 0.001 m"), (["step", "nan"], "finite")])
def test_valve_command_refuses_a_reference_no_valve_reaches_before_sending(args, says):
    """A unit mistake (20 meant as um, 1e-3 as mm) is refused with one line and exit 2, before ROS starts."""
    exe = os.path.join(os.path.dirname(sys.executable), "valve_command")
    proc = subprocess.run([exe] + args, env=ros_env(), capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert says in proc.stderr and "[INFO]" not in proc.stdout + proc.stderr


def test_steps_are_found_in_a_recorded_reference_and_measured():
    from piezo_valve_ros.core import find_steps, reference_on_samples
    t = np.arange(10000) * 1e-4                                  # 1 s at 10 kHz
    ref_t = np.r_[0.1, 0.3, 0.6 + np.arange(40) * 5e-3]           # 0, a step to 20 um, then a sine in small moves
    ref_m = np.r_[0.0, 20e-6, 20e-6 + 2e-6 * np.sin(np.arange(1, 41) * 0.5)]
    ref = reference_on_samples(t, ref_t, ref_m)
    assert np.isnan(ref[t < 0.1]).all() and ref[(t >= 0.1) & (t < 0.3)].max() == 0.0
    tau = 0.01                                                   # a first-order valve: 5 % band after 3 tau
    y = np.where(t < 0.3, 0.0, 20e-6 * (1 - np.exp(-(t - 0.3) / tau)))
    steps = find_steps(t, y, ref)
    assert len(steps) == 1
    s = steps[0]
    assert (s.start_um, s.end_um) == (0.0, 20.0) and s.time_s == pytest.approx(0.3, abs=2e-4)
    assert s.settling_time_s == pytest.approx(3 * tau, abs=2e-4) and s.overshoot_pct == 0.0


def test_references_are_put_on_the_samples_time_axis_where_simulated_time_runs_at_its_own_pace(tmp_path):
    """A lockstep rig's time runs at a varying share of the wall clock (here 0.25x, then 2x): a reference is placed by
    the messages around it that pair a receive time with a sample time, not by one constant offset (which put a
    tour's step seconds away from where it happened and reported a tracking error of 5-11 um)."""
    from piezo_valve_ros.io import (BagRecorder, SAMPLES_TYPE, qos_profile, serialize_float64, serialize_samples,
                                    read_run)
    from piezo_valve_ros.core import find_steps, reference_on_samples, receive_to_sample_time
    dt = 1e-3
    t = np.arange(4000) * dt
    wall = np.where(t < 2.0, 4.0 * t, 8.0 + 0.5 * (t - 2.0)) + 1000.0   # receive time [s] of each sample
    ref = np.where(t < 1.5, 0.0, np.where(t < 3.0, 20e-6, -20e-6))
    y = np.where(t < 1.5, 0.0, ref)                                    # the valve follows at once
    rows = np.column_stack((t, 5.0 + y * 1e5, y + 1e-9 * np.arange(t.size)))   # distinct positions
    bag = tmp_path / "run"
    topics = {"/samples": (SAMPLES_TYPE, qos_profile(True, 10)), "/spool_position": (FLOAT64_TYPE, qos_profile(False, 1)),
              "/position_reference": (FLOAT64_TYPE, qos_profile(True, 10))}
    recorder = BagRecorder(bag, topics, "mcap")
    for k in range(0, t.size, 100):                                    # batches of 100 rows, as the hardware sends
        for j in range(k, k + 100):
            recorder.write("/spool_position", int(wall[j] * 1e9), serialize_float64(rows[j, 2]))
        recorder.write("/samples", int((wall[k + 99] + 1e-4) * 1e9), serialize_samples(rows[k:k + 100]))
    for at in (0.5, 1.5, 3.0):                                         # 0, then a step up and a step down
        j = int(round(at / dt))
        recorder.write("/position_reference", int((wall[j] - 1e-4) * 1e9), serialize_float64(float(ref[j])))
    recorder.close()
    got_rows, ref_t, ref_m, _ = read_run(bag)
    assert np.allclose(ref_t, [0.5 - dt, 1.5 - dt, 3.0 - dt], atol=1.5 * dt), ref_t
    steps = find_steps(got_rows[:, 0], got_rows[:, 2], reference_on_samples(got_rows[:, 0], ref_t, ref_m))
    assert [(s.start_um, s.end_um) for s in steps] == [(0.0, 20.0), (20.0, -20.0)]
    # without positions the samples messages alone place it within their batch
    to_t = receive_to_sample_time(wall[99::100] + 1e-4, t[99::100])
    assert abs(float(to_t(np.array([wall[1500]]))[0]) - 1.5) < 0.1


def test_two_steps_sent_close_together_are_each_moved_to_their_own_reaction():
    """A tour's two steps, 20 um then -20 um, sent a few tenths of a second apart on a loaded machine: the command's
    reaction to the second (a 40 um swing down the loop's other branch) is more than twice the first's, and within
    a second of both.  Each jump is moved to the command's change in its own direction, after the jump before it
    (the first was moved onto the second's reaction, held for no time, and the step table had no 20 -> -20)."""
    from piezo_valve_ros.core import align_jumps, find_steps, reference_on_samples
    dt = 1e-3
    t = np.arange(3000) * dt
    up_at, down_at = 1.0, 1.35                                            # where the controller applied them
    ref = np.where(t < up_at, 0.0, np.where(t < down_at, 20e-6, -20e-6))
    command = 5.0 + np.where(t < up_at, 0.0, np.where(t < down_at, 1.0, -1.5))   # 1 V up, then 2.5 V down
    command = command + 1e-4 * np.sin(40.0 * t)                           # a controller's small corrections
    received = np.array([0.2, up_at - 0.15, down_at - 0.25])              # delivered early (the rig's time lags)
    values = np.array([0.0, 20e-6, -20e-6])
    aligned = align_jumps(t, command, received, values)
    assert aligned[1] == pytest.approx(up_at, abs=dt) and aligned[2] == pytest.approx(down_at, abs=dt), aligned
    steps = find_steps(t, ref, reference_on_samples(t, aligned, values))
    assert [(round(s.start_um), round(s.end_um)) for s in steps] == [(0, 20), (20, -20)]
    # a jump with no reaction in its direction keeps its receive time
    flat = align_jumps(t, np.where(t < up_at, 5.0, 4.0), received[:2], values[:2])
    assert flat[1] == pytest.approx(received[1])


def test_a_sine_sent_as_many_small_changes_keeps_its_times_and_its_tracking_figures():
    """The bring-up's 40 um, 1 Hz sine, sent every 20 ms (2.5 um changes, each above the 1 um a step needs, none
    held): no change is a step, none is moved (each was moved to a "reaction" up to a second away, and valve_plot
    said RMS 22.5 um and fit 19 % on a valve that tracked within 2 um); the figures valve_plot gives are those of the
    position against the reference in force at each sample."""
    from piezo_valve_ros.cli.plot import summary_lines
    from piezo_valve_ros.core import align_jumps, reference_on_samples
    dt = 1e-3
    t = np.arange(8000) * dt
    received = np.arange(0.5, 7.5, 0.02)
    values = 40e-6 * np.sin(2 * np.pi * 1.0 * (received - 0.5))
    in_force = reference_on_samples(t, received, values)
    position = np.where(np.isfinite(in_force), np.roll(np.nan_to_num(in_force), 3), 0.0)  # tracks 3 ms late
    command = 5.0 + position / 14.8e-6
    aligned = align_jumps(t, command, received, values)
    assert np.array_equal(aligned, received)
    rows = np.column_stack((t, command, position))
    line = next(x for x in summary_lines(rows, reference_on_samples(t, aligned, values), "/samples")
                if "tracking" in x and "RMS" in x)
    known = np.isfinite(in_force)
    direct = float(np.sqrt(np.mean((position[known] - in_force[known]) ** 2))) * 1e6
    assert f"RMS {direct:.3f} um" in line or f"RMS {direct:.2f} um" in line, (line, direct)
    assert direct < 2.0      # (the staircase the 20 ms messages make, 3 ms late)


def test_valve_plots_summary_of_a_stretch_says_it_is_a_stretch_and_why_it_has_no_reference():
    """--from/--to: the extent is the stretch's, said as such; no reference sent by its end is not 'none in the bag'."""
    from piezo_valve_ros.cli.plot import summary_lines
    from piezo_valve_ros.core import TimeWindow
    t = 600.0 + np.arange(6001) * 1e-2
    rows = np.column_stack((t, 5.0 + np.sin(t), 13e-6 * (5.0 + np.sin(t))))
    none = np.full(t.size, np.nan)
    stretch = summary_lines(rows, none, "/samples", TimeWindow(600.0, 660.0))
    assert "over 60.00 s, the stretch 600 to 660 s from the record's first sample (not the whole record)" in stretch[0]
    assert stretch[1] == "no position_reference sent by the stretch's end: no tracking error, no steps"
    assert summary_lines(rows, none, "/samples")[1] == "no position_reference in the bag: no tracking error, no steps"
    assert "over 60.00 s;" in summary_lines(rows, none, "/samples")[0]


def test_parameter_assignments_read_as_yaml():
    assert parse_assignment("kp:=1.5") == ("kp", 1.5)
    assert parse_assignment("samples_batch:=10") == ("samples_batch", 10)
    assert parse_assignment("enabled:=false") == ("enabled", False)
    assert parse_assignment("strategy=ol_hc") == ("strategy", "ol_hc")
    assert parse_assignment("creep.gains:=[0.1, 0.2]") == ("creep.gains", [0.1, 0.2])
    assert parse_assignment("gain_set:=''") == ("gain_set", "")
    assert parse_assignment("gain_set:=") == ("gain_set", "")   # what a shell leaves of gain_set:=''
    for bad in ("kp", ":=1", "kp:=~"):
        with pytest.raises(ValueError):
            parse_assignment(bad)


def test_dropped_sample_rows_are_counted_from_the_time_column():
    t = np.arange(1000) * 1e-4
    assert dropped_sample_rows(t) == 0
    assert dropped_sample_rows(np.delete(t, np.r_[100:150, 700])) == 51


@pytest.mark.slow
def test_tools_refuse_bad_arguments_before_touching_ros(tmp_path):
    for args, says in [(("sine", "--amplitude", "1e-5", "--frequency", "500", "--duration", "1"), "frequency"),
                       (("set", "controller", "kp"), "expected NAME:=VALUE"),
                       (("file", str(tmp_path / "missing.csv")), "No such file"),
                       (("ramp", "nan", "1e-5", "--duration", "1"), "positions must be finite"),
                       (("sine", "--amplitude", "1e-5", "--frequency", "1", "--duration", "1", "--offset", "nan"),
                        "positions must be finite"),
                       (("--timeout", "nan", "step", "1e-6"), "--timeout must be > 0"),
                       (("--timeout", "-1", "get", "controller"), "--timeout must be > 0"),
                       (("--wait-readers", "0", "step", "1e-6"), "--wait-readers must be >= 1")]:
        proc = tool("valve_command", *args)
        assert proc.returncode == 2 and says in proc.stderr, proc.stderr
    (tmp_path / "exists").mkdir()
    proc = tool("valve_record", str(tmp_path / "exists"))
    assert proc.returncode == 2 and "exists already" in proc.stderr
    for duration in ("0", "-1", "nan"):
        proc = tool("valve_record", "--duration", duration, str(tmp_path / "never"))
        assert proc.returncode == 2 and "--duration must be > 0" in proc.stderr, proc.stderr
    assert not (tmp_path / "never").exists()
    proc = tool("valve_record", "--duration", "1", "--namespace", "/nobody_here", str(tmp_path / "empty"))
    assert proc.returncode == 0 and "0 messages (" in proc.stdout and "samples rows 0" in proc.stdout, proc
    proc = tool("valve_plot", str(tmp_path / "no_such_bag"))
    assert proc.returncode == 2 and "no bag at" in proc.stderr
    for name in ("valve_record", "valve_command", "valve_plot"):
        proc = tool(name, "--help")
        assert proc.returncode == 0 and "usage:" in proc.stdout


# ---------------------------------------------------------------------------- through a running rig
@pytest.mark.slow
@pytest.mark.wall_clock(seconds=40)
def test_record_command_and_identify_a_running_rig(tmp_path):
    """A real-time rig in its own namespace; valve_record records while valve_command sends a step and a
    sine and changes parameters; the bag holds what was sent and what the valve did, and valve_identify
    reads it."""
    ns = f"/tools{os.getpid()}"
    bag = tmp_path / "run1"
    with ProcessGroup() as procs:
        rig_log = open(tmp_path / "rig.log", "w")
        procs.start("rig", [os.path.join(BIN, "valve_rig"), "--demo", "none", "--clock", "realtime",
                            "--control-period-s", "0.001", "--busy-poll-s", "0", "--namespace", ns],   # a core free
                    env=ros_env(), stdout=rig_log, stderr=subprocess.STDOUT)
        wait_for_text(tmp_path / "rig.log", "running; Ctrl-C", timeout_s=60)
        rec_log = open(tmp_path / "record.log", "w")
        recorder = procs.start("record", [os.path.join(BIN, "valve_record"), "--namespace", ns, str(bag)],
                               env=ros_env(), stdout=rec_log, stderr=subprocess.STDOUT)
        wait_for_text(tmp_path / "record.log", "recording", timeout_s=60)
        time.sleep(1.0)
        step = tool("valve_command", "--namespace", ns, "--wait-readers", "2", "step", "20e-6")
        assert step.returncode == 0 and "1 reference(s)" in step.stdout and "acknowledged by 2 reader" in step.stdout, step
        time.sleep(1.5)
        refused = tool("valve_command", "--namespace", ns, "set", "controller", "kp:=-1.0", "reference_ramp_s:=0.01")
        assert refused.returncode == 1   # two values: one update, refused whole with the node's reason
        assert "kp := -1.0, reference_ramp_s := 0.01 refused, nothing changed: " in refused.stdout, refused.stdout
        assert "gain_set" in refused.stdout or "kp" in refused.stdout.split("nothing changed:")[1], refused.stdout
        got = tool("valve_command", "--namespace", ns, "get", "controller", "strategy", "gain_set")
        assert got.returncode == 0 and "strategy: 'pid_hc'" in got.stdout, got
        accepted = tool("valve_command", "--namespace", ns, "set", "hardware", "command_timeout_s:=0.3")
        assert accepted.returncode == 0 and "command_timeout_s := 0.3 accepted" in accepted.stdout, accepted
        absent = tool("valve_command", "--namespace", ns + "_nobody", "--timeout", "2", "step", "1e-6")
        assert absent.returncode == 1 and "nobody subscribes" in absent.stderr, absent
        # the sine close to the end: the record's held-out last 30 % needs its reversals, however long the
        # tools above took on a loaded machine
        sine = tool("valve_command", "--namespace", ns, "--wait-readers", "2", "sine", "--amplitude", "30e-6",
                    "--frequency", "2", "--duration", "3", "--offset", "-10e-6")
        assert sine.returncode == 0 and "601 reference(s)" in sine.stdout, sine
        step2 = tool("valve_command", "--namespace", ns, "--wait-readers", "2", "step", "5e-6")
        assert step2.returncode == 0, step2
        time.sleep(0.5)
        recorder.send_signal(signal.SIGINT)  # Ctrl-C: a clean stop with its summary line
        assert recorder.wait(60) == 0
    summary = open(tmp_path / "record.log").read().strip().splitlines()[-1]
    assert summary.startswith(f"valve_record: {bag}: ") and "dropped 0" in summary, summary

    rows, topic = read_samples(bag)
    assert topic == f"{ns}/samples" and rows.shape[0] > 50_000  # 10 kHz for more than 5 s
    from rosbags.rosbag2 import Reader
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == f"{ns}/position_reference"]
        refs = np.array([TYPESTORE.deserialize_cdr(raw, FLOAT64_TYPE).data
                         for _, _, raw in reader.messages(connections=conns)])
        topics = {c.topic for c in reader.connections}
    assert {f"{ns}/voltage_command", f"{ns}/spool_position", f"{ns}/samples"} <= topics
    assert refs[0] == pytest.approx(20e-6) and refs[-1] == pytest.approx(5e-6) and refs.size == 603
    assert refs[1:-1].max() == pytest.approx(20e-6, abs=0.1e-6) and refs[1:-1].min() == pytest.approx(-40e-6, abs=0.1e-6)
    # the valve followed: held near 20 um after the step, then swept the sine's range
    pos_um = rows[:, 2] * 1e6
    assert np.any(np.abs(pos_um - 20.0) < 1.0) and pos_um.min() < -35.0

    plot = tool("valve_plot", str(bag), "--out", str(tmp_path / "plots"), timeout_s=300)
    assert plot.returncode == 0, plot.stdout + plot.stderr
    assert f"{ns}/samples: " in plot.stdout and "tracking error over" in plot.stdout
    step_rows = [line for line in plot.stdout.splitlines() if "-10.00 ->    5.00" in line]
    assert len(step_rows) == 1, plot.stdout  # the last step, found in the recorded reference
    assert sorted(os.listdir(tmp_path / "plots")) == ["hysteresis_loop.png", "run_time.png"]
    as_json = tool("valve_plot", str(bag), "--out", str(tmp_path / "plots_json"), "--json", timeout_s=300)
    figures = json.loads(as_json.stdout)
    assert figures["topic"] == f"{ns}/samples" and figures["samples"] == rows.shape[0]
    assert [(round(s["start_um"], 2), round(s["end_um"], 2)) for s in figures["steps"]][-1] == (-10.0, 5.0)
    assert figures["tracking"]["rms_um"] > 0 and len(figures["figures"]) == 2
    no_mpl = subprocess.run([sys.executable, "-c", "import sys; sys.modules['matplotlib'] = None; "
                             "from piezo_valve_ros.cli.plot import main; sys.exit(main(sys.argv[1:]))",
                             str(bag), "--out", str(tmp_path / "none")], capture_output=True, text=True, timeout=300)
    assert no_mpl.returncode == 1 and "no figures: plots need matplotlib" in no_mpl.stderr
    assert "tracking error over" in no_mpl.stdout and not (tmp_path / "none").exists()

    report = tmp_path / "report.json"
    proc = tool("valve_identify", str(bag), "--report", str(report), timeout_s=600)
    assert proc.returncode == 0 and report.exists(), proc.stdout + proc.stderr


def test_valve_rig_asks_for_priority_and_cpus_only_on_the_real_time_clock():
    from piezo_valve_ros.cli.rig import parse_args, rig_parameters
    from piezo_valve_ros.runtime import available_cpus
    cpus = sorted(available_cpus())
    hw, ctl = rig_parameters(parse_args(["--demo", "none", "--clock", "realtime", "--control-period-s", "0.0005"]))
    assert hw["realtime.busy_poll_s"] == 0.0005 and hw["realtime.priority"] == 0 and "realtime.cpus" not in hw
    # at 1 ms and longer the hardware sleeps between ticks: as many commands in time, no core spent polling
    for period in ("0.001", "0.002"):
        hw, _ = rig_parameters(parse_args(["--demo", "none", "--clock", "realtime", "--control-period-s", period]))
        assert hw["realtime.busy_poll_s"] == 0.0
    hw, _ = rig_parameters(parse_args(["--demo", "none", "--clock", "realtime", "--control-period-s", "0.001",
                                       "--busy-poll-s", "0.001"]))
    assert hw["realtime.busy_poll_s"] == 0.001
    hw, ctl = rig_parameters(parse_args(["--demo", "none", "--clock", "realtime", "--priority", "50", "--pin"]))
    assert hw["realtime.busy_poll_s"] == 0.0 and hw["realtime.priority"] == ctl["realtime.priority"] == 50
    assert hw["realtime.cpus"] == [cpus[0]] and ctl["realtime.cpus"] == [cpus[-1]]
    hw, ctl = rig_parameters(parse_args(["--demo", "none", "--clock", "realtime", "--composed", "--pin"]))
    assert hw["realtime.cpus"] == ctl["realtime.cpus"] == [cpus[-1]]
    assert "realtime.cpu_wakeup_latency_us" not in hw and "realtime.cpu_wakeup_latency_us" not in ctl
    hw, ctl = rig_parameters(parse_args(["--demo", "none", "--clock", "realtime", "--cpu-wakeup-latency-us", "0"]))
    assert hw["realtime.cpu_wakeup_latency_us"] == ctl["realtime.cpu_wakeup_latency_us"] == 0
    for option in (["--priority", "50"], ["--cpu-wakeup-latency-us", "0"]):
        proc = tool("valve_rig", *option)  # lockstep
        assert proc.returncode == 2 and "apply to --clock realtime" in proc.stderr


# ---------------------------------------------------------------------------- an out-of-tree backend
PLUGIN_DIR = os.path.join(os.path.dirname(__file__), "data", "loopback_daq")  # a "vendor" package, dist-info and all


def plugin_env() -> dict:
    env = ros_env()
    env["PYTHONPATH"] = PLUGIN_DIR + os.pathsep + env["PYTHONPATH"]
    return env


@pytest.mark.slow
@pytest.mark.wall_clock(seconds=10)
def test_an_out_of_tree_backend_runs_the_rig(tmp_path):
    """A backend installed by another package (found through the entry-point group piezo_valve_ros.backends)
    runs the rig with no change to this package: its parameters are declared under its name and checked by
    it; the controller closes the loop through it."""
    hw_exe = os.path.join(BIN, "valve_hardware")
    bad = subprocess.run([hw_exe, "--ros-args", "-p", "backend:=loopback", "-p", "loopback.gain_m_per_v:=-1.0"],
                         env=plugin_env(), capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == ["valve_hardware: loopback.gain_m_per_v must be a number > 0, got -1.0"]
    unknown = subprocess.run([hw_exe, "--ros-args", "-p", "backend:=nope"], env=plugin_env(), capture_output=True,
                             text=True, timeout=60)
    assert unknown.returncode == 2 and "unknown backend 'nope'; available: loopback, sim" in unknown.stderr
    # a misspelt backend parameter (rclpy would ignore it, leaving the default in force) is refused by name
    misspelt = subprocess.run([hw_exe, "--ros-args", "-p", "backend:=loopback", "-p", "loopback.gain_m_per_vv:=1e-5"],
                              env=plugin_env(), capture_output=True, text=True, timeout=60)
    assert misspelt.returncode == 2, misspelt
    assert misspelt.stderr.strip().startswith("valve_hardware: unknown parameter(s) loopback.gain_m_per_vv (did you mean loopback.gain_m_per_v?) (the "
                                              "loopback backend's own: loopback.gain_m_per_v,"), misspelt.stderr

    ns = f"/daq{os.getpid()}"
    bag = tmp_path / "loop"
    with ProcessGroup() as procs:
        hw_log = open(tmp_path / "hw.log", "w")
        procs.start("hw", [hw_exe, "--ros-args", "-r", f"__ns:={ns}", "-p", "backend:=loopback",
                           "-p", "loopback.gain_m_per_v:=12e-6", "-p", "clock:=realtime"],
                    env=plugin_env(), stdout=hw_log, stderr=subprocess.STDOUT)
        procs.start("ctl", [os.path.join(BIN, "valve_controller"), "--ros-args", "-r", f"__ns:={ns}",
                            "-p", "gain_set:=pid_1"], env=plugin_env(), stdout=subprocess.DEVNULL,
                    stderr=subprocess.STDOUT)
        wait_for_text(tmp_path / "hw.log", "valve_hardware up: backend=loopback", timeout_s=60)
        got = tool("valve_command", "--namespace", ns, "get", "hardware", "backend", "loopback.gain_m_per_v")
        assert got.returncode == 0 and "backend: 'loopback'" in got.stdout and "loopback.gain_m_per_v: 1.2e-05" in got.stdout
        rec = procs.start("rec", [os.path.join(BIN, "valve_record"), "--namespace", ns, "--duration", "6", str(bag)],
                          env=ros_env(), stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        step = tool("valve_command", "--namespace", ns, "--wait-readers", "2", "step", "20e-6")
        assert step.returncode == 0, step
        assert rec.wait(60) == 0
    rows, _ = read_samples(bag)
    late = rows[rows[:, 0] > rows[-1, 0] - 0.5]  # the last half second: settled on the step
    assert np.abs(late[:, 2] - 20e-6).max() < 0.5e-6
    assert np.allclose(late[:, 2], 12e-6 * (late[:, 1] - 5.0), atol=0.3e-6)  # the loopback's own law


def test_valve_rig_with_a_backend_that_is_not_installed_ends_at_once_with_the_hardwares_reason():
    """The hardware refuses the backend and exits; the rig notices while it comes up, says which node ended, and
    exits non-zero (it used to wait for the hardware forever, the controller reporting 'waiting for spool_position')."""
    started = time.monotonic()
    proc = tool("valve_rig", "--demo", "none", "--backend", "my_daq", "--namespace", f"/nodaq{os.getpid()}",
                timeout_s=60)
    took = time.monotonic() - started
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "valve_hardware: unknown backend 'my_daq'" in proc.stderr, proc.stderr
    assert "valve_hardware exited with code 2 while the rig came up" in proc.stderr, proc.stderr
    assert "rig up" not in proc.stdout
    assert took < 15.0, took


def test_a_misspelt_parameter_of_the_sim_backend_or_of_the_hardware_is_refused_where_it_was_given():
    """valve_hardware refuses every name its command line gives it that it does not declare; valve_composed, whose
    unprefixed names go to both nodes, refuses a backend's misspelt one and leaves the controller's to it."""
    for args, says in [(["-p", "sim.sed:=3"], "unknown parameter(s) sim.sed (did you mean sim.seed?) (the sim backend's own: sim.seed,"),
                       (["-p", "clok:=lockstep"], "unknown parameter(s) clok ")]:
        out = tool("valve_hardware", "--ros-args", *args)
        assert out.returncode == 2 and says in out.stderr, (args, out.stderr)
    out = tool("valve_composed", "--ros-args", "-p", "sim.sed:=3")
    assert out.returncode == 2 and "unknown parameter(s) sim.sed" in out.stderr, out.stderr


@pytest.mark.parametrize("node, typo, meant", [
    ("valve_controller", "gain_sett:=pid_1", "gain_set"),
    ("valve_monitor", "windw_s:=10.0", "window_s"),
    ("valve_identification", "plann:=train", "plan"),
    ("valve_composed", "gain_sett:=pid_1", "gain_set"),
    ("valve_hardware", "safe_voltag:=5.0", "safe_voltage"),
])
def test_every_node_refuses_a_misspelt_parameter_naming_the_one_meant(node, typo, meant, tmp_path):
    """A misspelt parameter (rclpy would ignore it, leaving the default in force: a misspelt ``plan`` would run the
    default plan and drive the valve) ends the node at start-up with exit 2, naming the parameter and the nearest
    declared one, before anything is driven; the same typo in a rig file's section for the node too."""
    name = typo.partition(":=")[0]
    out = tool(node, "--ros-args", "-p", typo, timeout_s=60)
    assert out.returncode == 2, (node, out.stdout, out.stderr)
    assert f"{name} (did you mean {meant}?)" in out.stderr and "unknown parameter(s)" in out.stderr, (node, out.stderr)
    assert f"{node} up" not in out.stdout + out.stderr and "valve_controller up" not in out.stdout + out.stderr
    # (refused before the node said it was up, let alone drove; composed, its hardware is up at the safe voltage)
    section = "/**/" + {"valve_composed": "valve_controller"}.get(node, node)   # as config/rig.yaml writes them
    rig_file = tmp_path / "rig.yaml"
    value = typo.partition(":=")[2]
    rig_file.write_text(f"{section}:\n  ros__parameters:\n    {name}: {value}\n")
    out = tool(node, "--ros-args", "--params-file", str(rig_file), timeout_s=60)
    assert out.returncode == 2 and name in out.stderr and "unknown parameter(s)" in out.stderr, (node, out.stderr)


def test_valve_rig_stops_when_its_identification_plan_ends(tmp_path):
    """valve_rig --identify ends with the plan; a plan that fails ends the rig with exit 1 and says so."""
    proc = tool("valve_rig", "--demo", "none", "--namespace", f"/ident{os.getpid()}", "--identify", "refit",
                "--bag-dir", str(tmp_path / "bags"), timeout_s=120)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "valve_identification: plan: " in proc.stderr, proc.stderr  # the node's own one-line reason
    assert "identification plan failed (exit 2); stopping the rig" in proc.stderr, proc.stderr


def test_one_samples_decoder_for_bags_and_messages():
    from types import SimpleNamespace as NS
    from piezo_valve_ros.io import SamplesLayoutError, decode_samples
    data = [1.0, 5.0, 2e-6, 9.0, 1.1, 6.0, 3e-6, 9.0]  # columns in another order, and an extra one
    dims = [NS(size=2, label="sample"), NS(size=4, label="time,voltage_command,spool_position,extra")]
    np.testing.assert_array_equal(decode_samples(dims, data), [[1.0, 5.0, 2e-6], [1.1, 6.0, 3e-6]])
    dims[1] = NS(size=4, label="spool_position,time,extra,voltage_command")
    np.testing.assert_array_equal(decode_samples(dims, data)[0], [5.0, 9.0, 1.0])
    for bad_dims, bad_data, says in [(dims[:1], data, "1 layout dimensions"),
                                     ([dims[0], NS(size=2, label="time,position")], data[:4], "lack voltage_command"),
                                     (dims, data[:7], "7 values, its layout says 2x4")]:
        with pytest.raises(SamplesLayoutError, match=says):
            decode_samples(bad_dims, bad_data)


@pytest.mark.slow
@pytest.mark.wall_clock(seconds=10)
def test_valve_rig_brings_up_your_backend_from_one_parameters_file(tmp_path):
    """The path onto a real rig, with the loopback DAQ as the backend: one parameters file for hardware and
    controller, `valve_rig --params-file` (the file's backend, clock and period; --backend on the command
    line would win), a step with valve_command, a fitted model loaded whole with valve_command load, and
    ~/controller_state and /diagnostics read from the graph."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import Float64MultiArray
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.model import GPIMParams
    from piezo_valve_ros.identify import parameters_yaml
    ns = f"/bringup{os.getpid()}"
    params = tmp_path / "my_rig.yaml"
    params.write_text("valve_hardware:\n  ros__parameters:\n    backend: loopback\n    clock: realtime\n"
                      "    realtime.busy_poll_s: 0.0\n    control_period_s: 0.001\n    loopback.gain_m_per_v: 1.2e-05\n    diagnostics_period_s: 0.2\n"
                      "valve_controller:\n  ros__parameters:\n    gain_set: pid_1\n    control_period_s: 0.001\n"
                      "    state_period_s: 0.05\n    diagnostics_period_s: 0.2\n")
    fitted = tmp_path / "fitted.yaml"
    model = CompensationModel(GPIMParams(a0=0.9647, a1=0.1014, alpha=0.40, rho=4.0, tau=0.9, n=9,
                                         offset_um=-80.0).model()).to_parameters()
    fitted.write_text(parameters_yaml(model, ["a refit with 9 operators"]))
    context = rclpy.Context()
    rclpy.init(context=context)
    probe = rclpy.create_node("bringup_probe", namespace=ns, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    states, health = [], {}
    probe.create_subscription(Float64MultiArray, f"{ns}/valve_controller/controller_state", states.append, 10)
    probe.create_subscription(DiagnosticArray, "/diagnostics",
                              lambda m: health.update({s.name: s for s in m.status if s.name.startswith(ns)}), 10)
    log = tmp_path / "rig.log"
    try:
        with ProcessGroup() as procs, open(log, "w") as out:
            procs.start("rig", [os.path.join(BIN, "valve_rig"), "--params-file", str(params), "--demo", "none",
                                "--namespace", ns], env=plugin_env(), stdout=out, stderr=subprocess.STDOUT)
            wait_for_text(log, "rig up", timeout_s=90)
            got = tool("valve_command", "--namespace", ns, "get", "hardware", "backend", "clock", "control_period_s")
            assert "backend: 'loopback'" in got.stdout and "clock: 'realtime'" in got.stdout, got.stdout
            step = tool("valve_command", "--namespace", ns, "step", "20e-6")
            assert step.returncode == 0, step.stdout + step.stderr
            loaded = tool("valve_command", "--namespace", ns, "load", "controller", str(fitted))
            assert loaded.returncode == 0 and "applied together" in loaded.stdout, loaded.stdout + loaded.stderr
            def model_of_controller():
                status = health.get(f"{ns}/valve_controller")
                return {kv.key: kv.value for kv in status.values}["model"] if status is not None else ""
            deadline = time.monotonic() + 20   # reports queued before the load are read first
            while time.monotonic() < deadline and not (len(states) > 5 and len(health) >= 2
                                                       and "GPIM 9 operators" in model_of_controller()):
                executor.spin_once(timeout_sec=0.05)
            assert len(health) >= 2, health.keys()
            hw_health, ctl_health = health[f"{ns}/valve_hardware"], health[f"{ns}/valve_controller"]
            # the hardware's level says how many commands came in time on this machine (WARN below 99 %):
            # never ERROR while the controller commands; the watchdog armed
            assert hw_health.level != b"\x02" and {kv.key: kv.value for kv in hw_health.values}["watchdog"] == "armed"
            # the controller OK, or WARN from its oscillation guard: where this machine's load made the commands
            # late the loop swings like one with a delay, and holding it on feedforward is the right answer (what
            # load cannot change: never ERROR, and the reference followed unless the guard holds the loop)
            guarded = ctl_health.level == b"\x01" and ctl_health.message.startswith("oscillation guard")
            assert ctl_health.level == b"\x00" or guarded, ctl_health.message
            assert "GPIM 9 operators" in {kv.key: kv.value for kv in health[f"{ns}/valve_controller"].values}["model"]
            row = np.asarray(states[-1].data)
            assert row[1] == pytest.approx(20e-6)   # reference
            assert guarded or abs(row[2] - 20e-6) < 1e-6, row   # measured
            # the same, read by a user: valve_command status
            shown = tool("valve_command", "--namespace", ns, "status", "--listen", "10")
            assert f"{ns}/valve_hardware: " in shown.stdout, shown.stdout
            assert (f"{ns}/valve_controller: OK: " in shown.stdout
                    or f"{ns}/valve_controller: WARN: oscillation guard" in shown.stdout), shown.stdout
            assert "    watchdog: armed" in shown.stdout and "controller state: time_s " in shown.stdout, shown.stdout
            assert "reference_m 2e-05" in shown.stdout, shown.stdout
    finally:
        executor.remove_node(probe)
        probe.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)
    assert "valve_hardware up: backend=loopback clock=realtime period=1.000 ms" in log.read_text()


def test_valve_rig_knows_which_options_the_command_line_gave():
    """A parameters file's values give way only to options the command line gave, even when given at their
    default value (--clock lockstep), never to the rig's defaults."""
    from piezo_valve_ros.cli.rig import given_options, merged_parameters, parse_args, rig_parameters
    assert given_options([]) == set()
    given = given_options(["--clock", "lockstep", "--pin", "--params-file", "f.yaml"])
    assert given == {"clock", "pin", "params_file"}
    hw, _ = rig_parameters(parse_args(["--clock", "lockstep"]))
    merged = merged_parameters(hw, {"clock": "realtime", "control_period_s": 1e-3}, given)
    assert merged["clock"] == "lockstep" and merged["control_period_s"] == 1e-3


def test_valve_record_summary_says_what_went_into_the_bag(tmp_path):
    """valve_record's closing summary (the line, and the object --json prints): duration, messages per topic,
    size, samples rows and rows dropped between the first and the last."""
    from piezo_valve_ros.io import write_samples_bag
    from piezo_valve_ros.cli.record import parse_args, summary, summary_line
    rows = np.column_stack([np.arange(1000) * 1e-3, np.full(1000, 5.0), np.zeros(1000)])
    rows = np.delete(rows, [500, 501], axis=0)                    # two rows lost
    write_samples_bag(tmp_path / "bag", rows, topic="/v/samples")
    s = summary(tmp_path / "bag", 2.5, {"/v/samples": 1})
    assert (s["samples_rows"], s["dropped"], s["messages"], s["duration_s"]) == (998, 2, {"/v/samples": 1}, 2.5)
    assert s["bytes"] > 0 and "samples rows 998, dropped 2" in summary_line(tmp_path / "bag", 2.5, {"/v/samples": 1})
    assert parse_args(["out", "--json"]).json


@contextlib.contextmanager
def recorder_and_rig_nodes(ns: str):
    """A recorder node and a rig node in namespace ``ns``, in their own ROS context, on one executor: (recorder node,
    rig node, executor); everything shut down after."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    context = rclpy.Context()
    rclpy.init(context=context)
    nodes = [rclpy.create_node(name, namespace=ns, context=context) for name in ("recorder", "rig")]
    executor = SingleThreadedExecutor(context=context)
    for node in nodes:
        executor.add_node(node)
    try:
        yield nodes[0], nodes[1], executor
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_valve_record_reads_references_only_once_it_records_samples(tmp_path):
    """valve_record's reader of position_reference opens with the first recorded samples message: a sender that
    waits for it (valve_command --wait-readers) sends nothing the bag cannot place on the samples' time axis, however
    late discovery matches the samples topic on a loaded computer."""
    from std_msgs.msg import Float64, Float64MultiArray
    from piezo_valve_ros.io import read_run
    from piezo_valve_ros.ros import REFERENCE_QOS, SAMPLES_QOS, samples_message
    from piezo_valve_ros.rig import RigRecorder
    ns = f"/deferred{os.getpid()}"
    with recorder_and_rig_nodes(ns) as (recorder_node, rig, executor):
        reference = rig.create_publisher(Float64, "position_reference", REFERENCE_QOS)
        recorder = RigRecorder(recorder_node, reference_after_samples=True)
        try:
            recorder.start(tmp_path / "bag")
            deadline = time.monotonic() + 2.0            # no samples yet: nobody reads the references
            while time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            assert not recorder.reading_references and reference.get_subscription_count() == 0
            samples = rig.create_publisher(Float64MultiArray, "samples", SAMPLES_QOS)
            rows = np.column_stack([np.arange(100) * 1e-3, np.full(100, 5.0), np.zeros(100)])
            deadline = time.monotonic() + 20.0
            while time.monotonic() < deadline and reference.get_subscription_count() == 0:
                samples.publish(samples_message(rows))
                rows[:, 0] += 0.1
                executor.spin_once(timeout_sec=0.05)
            assert recorder.reading_references and reference.get_subscription_count() == 1
            time.sleep(0.3)
            reference.publish(Float64(data=20e-6))
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:
                samples.publish(samples_message(rows))
                rows[:, 0] += 0.1
                executor.spin_once(timeout_sec=0.05)
        finally:
            counts = recorder.stop()
    assert counts[f"{ns}/position_reference"] == 1, counts
    rows, ref_t, ref_m, _ = read_run(tmp_path / "bag")
    assert ref_m.tolist() == [20e-6] and rows[0, 0] < ref_t[0] < rows[-1, 0]


def test_a_recorder_reader_says_when_a_publisher_offers_a_qos_it_cannot_read(tmp_path, capfd):
    """Each of the recorder's readers watches for a publisher whose QoS it cannot read (one line: nothing of it is
    recorded) and for nothing else (every event handler is waited on in each executor round)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float64
    from piezo_valve_ros.rig import RigRecorder
    ns = f"/qos{os.getpid()}"
    with recorder_and_rig_nodes(ns) as (recorder_node, rig, executor):
        RigRecorder(recorder_node)
        assert all(len(s.event_handlers) == 1 for s in recorder_node.subscriptions), \
            [len(s.event_handlers) for s in recorder_node.subscriptions]
        # the recorder reads voltage_command reliably: a best-effort publisher cannot be matched
        rig.create_publisher(Float64, "voltage_command", QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        deadline, seen = time.monotonic() + 20.0, ""
        while time.monotonic() < deadline and "offers a QoS" not in seen:
            executor.spin_once(timeout_sec=0.05)
            seen += capfd.readouterr().err
    assert f"a publisher of {ns}/voltage_command offers a QoS this recorder cannot read (RELIABILITY)" in seen, seen
