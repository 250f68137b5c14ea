"""valve_identify on real bag files, bad input, and the recorder's crash safety."""
import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from unittest import mock

import numpy as np
import pytest
import yaml
from shared import directory_made_once

from piezo_valve_ros.io import (FLOAT64_TYPE, BagRecorder, qos_profile, read_samples, serialize_float64,
                                write_samples_bag)
from piezo_valve_ros.core.control import CompensationModel
from piezo_valve_ros.core.identification import check_report
from piezo_valve_ros.core.sim import simulate_rows
from piezo_valve_ros.core.sim import identification_voltage, validation_voltage
from piezo_valve_ros.core.sim import ValveSimConfig

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def run_cli(*args, timeout=300, env_extra=None, child=False):
    """valve_identify on ``args``: its exit code, stdout and stderr (``returncode``, ``stdout``, ``stderr``).  Its
    ``main`` runs in this process (what the command runs, without a child's ~0.6 CPU-s of start-up), its output
    captured; ``child``: as the command, in a child process (the 10 kHz run every output of which is checked)."""
    argv = [str(a) for a in args]
    if child:
        env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env_extra or {}))
        return subprocess.run([sys.executable, "-m", "piezo_valve_ros.cli.identify", *argv],
                              capture_output=True, text=True, timeout=timeout, env=env)
    from piezo_valve_ros.cli.identify import main
    stdout, stderr = io.StringIO(), io.StringIO()
    with mock.patch.dict(os.environ, env_extra or {}), \
            contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = main(argv)
        except SystemExit as exc:   # argparse's usage errors
            code = exc.code if isinstance(exc.code, int) else 1
    return subprocess.CompletedProcess(["valve_identify", *argv], code, stdout.getvalue(), stderr.getvalue())


@pytest.fixture
def bags_10khz():
    """Training and validation bags of the default simulated valve at the paper's 10 kHz (written once per run;
    the tests only read them)."""
    def write(d):
        cfg = ValveSimConfig(dt=1e-4)
        write_samples_bag(d / "train", simulate_rows(identification_voltage(1e-4, 20.0), replace(cfg, seed=1)),
                          topic="/rig_a/valve1/samples")
        write_samples_bag(d / "validate", simulate_rows(validation_voltage(1e-4, 20.0), replace(cfg, seed=2)),
                          topic="/rig_a/valve1/samples")
    return directory_made_once("test_identify_cli.bags_10khz", write)


@pytest.fixture
def identified_10khz(bags_10khz):
    """valve_identify on the 10 kHz bags with a validation bag and every output: (the outputs' directory, the
    run's returncode, stdout and stderr).  Run once per test run; the tests only read it."""
    def run(d):
        out = run_cli(bags_10khz / "train", "--validate", bags_10khz / "validate", "--report", d / "report.json",
                      "--params-out", d / "fitted.yaml", "--plots", d / "plots", child=True)
        (d / "run.json").write_text(json.dumps({"returncode": out.returncode, "stdout": out.stdout,
                                                "stderr": out.stderr}))
    d = directory_made_once("test_identify_cli.identified_10khz", run)
    return d, subprocess.CompletedProcess([], **json.loads((d / "run.json").read_text()))


@pytest.mark.slow
def test_report_parameters_and_plots_from_10khz_bags(identified_10khz):
    tmp_path, out = identified_10khz
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    # the default simulated valve: creep is undeclared; its G_v is the baseline's own (no "dynamics"); its loop is
    # symmetric, so nothing but its creep and its loop-end flattening is named (on these records the chosen grid sits
    # half a spacing off the valve's thresholds, and asymmetry's descending shift once stood in for the placement)
    assert "creep" in report["effects_added"] and set(report["effects_added"]) <= {"creep", "saturation"}, (
        report["effects_added"], out.stdout)
    assert report["baseline"]["model"] == "gpim+G_v"
    assert report["final"]["validate"]["peak_um"] < 0.5 * report["baseline"]["validate"]["peak_um"]
    assert report["source"]["topic"] == "/rig_a/valve1/samples"
    # held-out figures at the record's own 10 kHz (the sensor noise shows), block means as extra keys
    assert report["sample_rate_hz"] == pytest.approx(10000.0) and report["analysis_rate_hz"] == pytest.approx(2000.0)
    assert report["final"]["validate"]["rms_um"] > report["final"]["validate_analysis_rate"]["rms_um"]
    params = yaml.safe_load((tmp_path / "fitted.yaml").read_text())["/**/valve_controller"]["ros__parameters"]
    assert len(params["gpim.thresholds"]) == len(params["gpim.weights"]) >= 10
    assert min(params["gpim.weights"]) >= 0.0
    assert len(params["creep.gains"]) == len(params["creep.time_constants_s"]) >= 1
    assert len(params["valve_model.den"]) == 3 and params["valve_model.num"][0] == pytest.approx(params["valve_model.den"][2])
    assert all(isinstance(x, float) for x in params["gpim.weights"])
    for name in ("hysteresis_loop", "residual_time", "residual_diagnostic", "step_hold"):
        png = tmp_path / "plots" / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "held-out rms" in out.stdout and "at the record's rate (10000 Hz)" in out.stdout


@pytest.mark.slow
def test_outputs_are_written_together_or_not_at_all(bags_10khz, tmp_path):
    """An output that cannot be written is named before the analysis starts (no "records:" line: no minute lost),
    and nothing is replaced; the same checks run again at the end, where a path may have changed meanwhile."""
    report = tmp_path / "report.json"
    report.write_text("old report\n")
    target_dir = tmp_path / "a_directory"
    target_dir.mkdir()
    out = run_cli(bags_10khz / "train", "--report", report, "--params-out", target_dir)
    _one_error_line(out, str(target_dir), "is a directory")
    assert "records:" not in out.stdout, out.stdout
    assert report.read_text() == "old report\n"
    assert list(tmp_path.glob(".*")) == []  # no temporary file left behind
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for args, says in ((["--report", a_file / "report.json"], "is not a directory"),
                       (["--plots", a_file], "not a directory")):
        out = run_cli(bags_10khz / "train", *args)
        _one_error_line(out, str(a_file), says)
        assert "records:" not in out.stdout, out.stdout
    from piezo_valve_ros.identify import write_outputs
    with pytest.raises(OSError, match="is a directory"):   # the check at the end: a path that became a directory
        write_outputs({str(report): "new\n", str(target_dir): "x"})
    assert report.read_text() == "old report\n"


def test_foreign_rig_sqlite3_plus_minus_150_v_1khz_held_out(tmp_path):
    """Another rig: electrode voltage (-150..+150 V) logged at 1 kHz in sqlite3, no validation bag."""
    rows = simulate_rows(identification_voltage(1e-3, 30.0), ValveSimConfig(dt=1e-3, seed=4))
    rows[:, 1] = 30.0 * rows[:, 1] - 150.0
    write_samples_bag(tmp_path / "bag", rows, topic="/valve7/samples", storage="sqlite3")
    out = run_cli(tmp_path / "bag", "--report", tmp_path / "r.json", "--params-out", tmp_path / "fitted.yaml", "--quiet")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("range ") and "wrote " in out.stdout  # quiet: the summary, no progress
    report = json.loads((tmp_path / "r.json").read_text())
    assert check_report(report) == []          # the written report, schema and source blocks included
    assert report["validation"] == "held-out last 30 % of the training record"
    assert "creep" in report["effects_added"]
    assert report["final"]["validate"]["rms_um"] < 0.5 * report["baseline"]["validate"]["rms_um"]
    # the fitted file carries the drive it was fitted on: a 0-10 V controller refuses it, a +-150 V one takes it
    params = yaml.safe_load((tmp_path / "fitted.yaml").read_text())["/**/valve_controller"]["ros__parameters"]
    lo, hi = params["model.fitted_range_v"]
    assert -151.0 < lo < -140.0 and 140.0 < hi < 151.0
    with pytest.raises(ValueError, match="a model of another drive"):
        CompensationModel.from_parameters(params, 0.0, 10.0)
    CompensationModel.from_parameters(params, -150.0, 150.0)


def _one_error_line(out, *needles):
    assert out.returncode != 0
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, out.stderr
    assert "Traceback" not in out.stderr
    for n in needles:
        assert n in lines[0], lines[0]


@pytest.mark.slow
def test_bad_input_ends_with_one_clear_line_and_keeps_the_last_good_parameters(tmp_path):
    good = tmp_path / "fitted.yaml"
    good.write_text("# last good parameters\n")
    rows = simulate_rows(identification_voltage(1e-3, 10.0), ValveSimConfig(dt=1e-3))
    cases = {}
    cases["missing"] = (tmp_path / "nope", ("no bag at",))
    # a bag without samples
    rec = BagRecorder(tmp_path / "no_samples", {"/spool_position": (FLOAT64_TYPE, qos_profile(False, 5))})
    rec.write("/spool_position", 1, serialize_float64(1e-6))
    rec.close()
    cases["no samples"] = (tmp_path / "no_samples", ("no samples topic", "/spool_position"))
    # truncated storage file
    write_samples_bag(tmp_path / "truncated", rows)
    f = next((tmp_path / "truncated").glob("*.mcap"))
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    cases["truncated"] = (tmp_path / "truncated", ("cannot read bag",))
    # constant input
    const = rows.copy()
    const[:, 1] = 5.0
    write_samples_bag(tmp_path / "constant", const)
    cases["constant"] = (tmp_path / "constant", ("constant", "no excitation"))
    # NaN samples
    nan = rows.copy()
    nan[1234, 2] = np.nan
    write_samples_bag(tmp_path / "nan", nan)
    cases["nan"] = (tmp_path / "nan", ("non-finite",))
    # a directory that is not a bag
    (tmp_path / "empty_dir").mkdir()
    cases["not a bag"] = (tmp_path / "empty_dir", ("cannot read bag",))
    # a good bag, the analysis' thread count set to nonsense
    write_samples_bag(tmp_path / "good", rows)
    cases["threads"] = (tmp_path / "good", ("PIEZO_ANALYSIS_THREADS='0'", "whole number >= 1"))
    for name, (bag, needles) in cases.items():
        out = run_cli(bag, "--params-out", good, "--report", tmp_path / f"{name}.json",
                      env_extra={"PIEZO_ANALYSIS_THREADS": "0"} if name == "threads" else None)
        _one_error_line(out, *needles)
        assert good.read_text() == "# last good parameters\n", name
        assert not (tmp_path / f"{name}.json").exists()


REAL_CSV = os.path.join(ROOT, "test", "data", "smart_hysteresis", "hysteresis_v_150_1hz_1khz.csv")


def test_a_measured_csv_record_from_another_lab(tmp_path):
    """A real piezo actuator's record as CSV (µm, V): the CLI reads it, fits, reports and writes parameters."""
    out = run_cli(REAL_CSV, "--report", tmp_path / "r.json", "--params-out", tmp_path / "p.yaml", "--plots", tmp_path)
    assert out.returncode == 0, out.stderr
    assert "1529 samples (CSV)" in out.stdout and "initial state:" in out.stdout
    # a sine never holds still: no empty step-and-hold figure, and the log says why
    assert (tmp_path / "hysteresis_loop.png").exists() and not (tmp_path / "step_hold.png").exists()
    assert "no step_hold.png: the held-out input never holds still" in out.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    window = report["source"].pop("train_window")   # the whole record: no window asked, all of it analysed
    assert report["source"] == {"train_bag": REAL_CSV, "validate_bag": None, "topic": None}
    assert window["from_s"] is None and window["to_s"] is None and window["samples"] == 1529
    assert report["analysed"]["train"]["samples"] == report["analysed"]["train"]["of_samples"] == 1529
    assert report["baseline_fits"]["initial_state"]["chosen"] == "cycled"
    params = yaml.safe_load((tmp_path / "p.yaml").read_text())["/**/valve_controller"]["ros__parameters"]
    assert min(params["gpim.weights"]) >= 0.0


def test_bad_csv_records_end_with_one_clear_line(tmp_path):
    cases = {"no_position.csv": ("time_s,voltage_v\n0,1\n", ("lacks position_m or position_um",)),
             "bad_row.csv": ("time_s,voltage_v,position_m\n0,1,2e-6\n0.001,x,3e-6\n", ("data row 3",)),
             "header_only.csv": ("time_s,voltage_v,position_um\n", ("a header but no samples",))}
    # the measured record with its position's sign flipped (a sensor mounted the other way round): a GPIM
    # cannot fit a falling valve, so it is refused with what to do, not fitted into a model of wrong effects
    lines = open(REAL_CSV).read().splitlines()
    flipped = [lines[0]] + [",".join([t, str(-float(p)), v]) for t, p, v in (ln.split(",") for ln in lines[1:])]
    (tmp_path / "flipped.csv").write_text("\n".join(flipped) + "\n")
    _one_error_line(run_cli(tmp_path / "flipped.csv"), "training record: the position falls as the voltage rises",
                    "flip the sign")
    for name, (text, needles) in cases.items():
        (tmp_path / name).write_text(text)
        _one_error_line(run_cli(tmp_path / name), name, *needles)
    _one_error_line(run_cli(tmp_path / "missing.csv"), "cannot read")


def test_two_samples_topics_need_a_choice(tmp_path):
    rows = simulate_rows(identification_voltage(1e-3, 10.0), ValveSimConfig(dt=1e-3))
    write_samples_bag(tmp_path / "a", rows, topic="/v1/samples")
    # merge a second namespace into the same bag by writing both topics through one recorder
    rec = BagRecorder(tmp_path / "two", {"/v1/samples": ("std_msgs/msg/Float64MultiArray", qos_profile(True, 100)),
                                         "/v2/samples": ("std_msgs/msg/Float64MultiArray", qos_profile(True, 100))})
    from piezo_valve_ros.io import serialize_samples
    rec.write("/v1/samples", 1, serialize_samples(rows[:1000]))
    rec.write("/v2/samples", 2, serialize_samples(rows[:1000]))
    rec.close()
    _one_error_line(run_cli(tmp_path / "two"), "several samples topics", "--topic")
    got, name = read_samples(tmp_path / "two", "/v2/samples")
    assert name == "/v2/samples" and got.shape == (1000, 3)


RECORDER_SCRIPT = r"""
import sys, time
import numpy as np
from piezo_valve_ros.io.bags import BagRecorder, SAMPLES_TYPE, qos_profile, serialize_samples
rec = BagRecorder(sys.argv[1], {"/samples": (SAMPLES_TYPE, qos_profile(True, 100))}, segment_s=0.5)
t0 = time.monotonic()
k = 0
while True:
    rows = np.column_stack((k * 100 + np.arange(100) * 1.0, np.ones(100), np.zeros(100)))
    rec.write("/samples", time.time_ns(), serialize_samples(rows))
    k += 1
    if k == 1:
        print("recording", flush=True)
    time.sleep(0.01)
"""


def test_recorder_survives_being_killed(tmp_path):
    bag = tmp_path / "crash"
    env = dict(os.environ, PYTHONPATH=ROOT)
    proc = subprocess.Popen([sys.executable, "-c", RECORDER_SCRIPT, str(bag)], stdout=subprocess.PIPE, env=env)
    try:
        assert proc.stdout.readline().strip() == b"recording"
        started = time.monotonic()
        time.sleep(2.6)
        proc.send_signal(signal.SIGKILL)
        killed_after = time.monotonic() - started
        proc.wait(5)
    finally:
        if proc.poll() is None:
            proc.kill()
    rows, _ = read_samples(bag)
    # about 100 messages/s of 100 rows; at most the last segment (0.5 s) plus scheduling slack is lost
    assert rows.shape[0] >= (killed_after - 1.0) * 90 * 100
    assert np.all(np.diff(rows[:, 0]) == 1.0)  # nothing lost in the middle


# every key path of the reports written before the residual loop was rebuilt (CONTRACT.md: keys may be
# added, and removed only with the schema version raised: RETIRED_REPORT_KEYS); final_model's sub-keys depend on the
# effects found and are not listed
EARLIER_REPORT_KEYS = """range_um baseline baseline.model baseline.fit baseline.train.rms_um baseline.train.peak_um
baseline.train.peak_pct baseline.validate.rms_um baseline.validate.peak_um baseline.validate.peak_pct effects_added
diagnosis diagnosis.[].effect diagnosis.[].added diagnosis.[].statistic diagnosis.[].threshold
diagnosis.[].held_out_gain diagnosis.[].evidence final.model final.train.rms_um final.train.peak_um
final.train.peak_pct final.validate.rms_um final.validate.peak_um final.validate.peak_pct unexplained residual
baseline_fits.linear.train.rms_um baseline_fits.linear.validate.peak_pct baseline_fits.linear.operators
baseline_fits.linear.invertible baseline_fits.paper_nls.train.rms_um baseline_fits.paper_nls.validate.peak_pct
baseline_fits.paper_nls.condition_number baseline_fits.paper_nls.evaluations baseline_fits.paper_nls.params.a0
baseline_fits.paper_nls.params.a1 baseline_fits.paper_nls.params.alpha baseline_fits.paper_nls.params.rho
baseline_fits.paper_nls.params.tau baseline_fits.paper_nls.params.n baseline_fits.paper_nls.params.offset_um
validation validate_range_um analysis_rate_hz noise_floor_um thresholds.signature thresholds.held_out_gain
thresholds.unexplained_pct final_model.model final_model.gpim.thresholds final_model.gpim.weights
final_model.gpim.a0 final_model.gpim.a1 final_model.gpim.offset_um seconds source.train_bag source.validate_bag
source.topic""".split()
RETIRED_REPORT_KEYS = {"rounds": 3}   # key -> the schema version that retired it (the alias of "confirm")


def test_report_keeps_every_key_earlier_reports_had(identified_10khz):
    outputs, out = identified_10khz
    assert out.returncode == 0, out.stderr
    report = json.loads((outputs / "report.json").read_text())
    for path in EARLIER_REPORT_KEYS:
        node = report
        for part in path.split("."):
            node = node[0] if part == "[]" else node[part]
    from piezo_valve_ros.identify import REPORT_SCHEMA, REPORT_SCHEMA_VERSION
    schema = report["schema"]   # what the file is, for readers that come later
    assert (schema["name"], schema["version"]) == (REPORT_SCHEMA, REPORT_SCHEMA_VERSION)
    for key, version in RETIRED_REPORT_KEYS.items():   # a key is retired only with the version raised past it
        assert key not in report and schema["version"] >= version
    assert schema["package_version"] != "" and schema["created_utc"].endswith("+00:00")
    assert 0.0 < report["final"]["validate"]["fit_pct"] <= 100.0


def _segmented_bag(path, rows, storage, messages_per_segment=5, batch=1000):
    """A recorder's multi-file bag: a new storage file every ``messages_per_segment`` messages."""
    from piezo_valve_ros.io import SAMPLES_TYPE, serialize_samples
    clock = [0.0]
    rec = BagRecorder(path, {"/valve1/samples": (SAMPLES_TYPE, qos_profile(True, 100))}, storage,
                      segment_s=float(messages_per_segment), clock=lambda: clock[0])
    for i in range(0, rows.shape[0], batch):
        chunk = rows[i:i + batch]
        clock[0] += 1.0
        rec.write("/valve1/samples", 1_700_000_000_000_000_000 + int(round(chunk[-1, 0] * 1e9)),
                  serialize_samples(chunk, "time,voltage_command,spool_position"))
    rec.close()


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_bag_with_one_damaged_segment_is_read_from_the_intact_ones_and_says_what_it_left_out(tmp_path, storage):
    rows = simulate_rows(identification_voltage(1e-3, 30.0), ValveSimConfig(dt=1e-3, seed=4))
    bag = tmp_path / "segmented"
    _segmented_bag(bag, rows, storage)
    files = sorted(f for f in bag.iterdir() if f.suffix in (".mcap", ".db3"))
    assert len(files) >= 5
    damaged = files[2]
    damaged.write_bytes(damaged.read_bytes()[: damaged.stat().st_size // 2])
    skipped: list[str] = []
    got, name = read_samples(bag, skipped=skipped)
    assert name == "/valve1/samples"
    assert len(skipped) == 1 and skipped[0].startswith(damaged.name), skipped
    # every row of the intact files, none of the damaged one's
    assert 0 < rows.shape[0] - got.shape[0] <= 5 * 1000
    assert np.isin(got[:, 0], rows[:, 0]).all()
    # the analyser uses the rest and says so, in its log and in the report
    out = run_cli(bag, "--report", tmp_path / "report.json")
    assert out.returncode == 0, out.stderr
    assert f"1 damaged storage file(s) left out, the rest used: {damaged.name}" in out.stdout
    report = json.loads((tmp_path / "report.json").read_text())
    assert any(damaged.name in w for w in report["warnings"])


def test_a_model_fitted_on_part_of_the_drive_limits_the_commands_to_what_it_knows(tmp_path):
    """A record over 2..8 V: the parameters file limits the commands to 0.5..9.5 V (a quarter of the fitted span
    beyond it), says so, and the controller and valve_tune accept it; the controller refuses the model for
    0..10 V, naming the range to set.  A record over 0.11 V of the drive is too narrow: a note, no limits."""
    from piezo_valve_ros.core.control import command_range_for, fitted_range_problems
    assert command_range_for((2.0, 8.0), 0.0, 10.0, 5.0) == (0.5, 9.5)
    assert command_range_for((1.0, 9.0), 0.0, 10.0, 5.0) == (0.0, 10.0)
    assert command_range_for((6.07, 6.18), 0.0, 10.0, 5.0) is None
    assert "limit command_min_v/command_max_v to 0.5..9.5 V" in fitted_range_problems((2.0, 8.0), 0.0, 10.0)[0]
    v = 5.0 + 0.6 * (identification_voltage(5e-4, 12.0) - 5.0)
    rows = simulate_rows(v, ValveSimConfig(dt=5e-4, seed=3))
    write_samples_bag(tmp_path / "narrow", rows)
    out = run_cli(tmp_path / "narrow", "--params-out", tmp_path / "fitted.yaml", "--quiet")
    assert out.returncode == 0, out.stderr
    assert "note: the record drove the valve over" in out.stdout and "commands limited to" in out.stdout, out.stdout
    params = yaml.safe_load((tmp_path / "fitted.yaml").read_text())["/**/valve_controller"]["ros__parameters"]
    lo, hi = params["model.fitted_range_v"]
    assert params["command_min_v"] == pytest.approx(max(0.0, lo - 0.25 * (hi - lo)), abs=1e-3)
    assert params["command_max_v"] == pytest.approx(min(10.0, hi + 0.25 * (hi - lo)), abs=1e-3)
    CompensationModel.from_parameters(params, params["command_min_v"], params["command_max_v"])
    with pytest.raises(ValueError, match="limit command_min_v/command_max_v to"):
        CompensationModel.from_parameters(params, 0.0, 10.0)


def test_the_offline_monitor_says_why_a_short_record_gives_no_verdict(tmp_path):
    from piezo_valve_ros.core.control import CompensationModel as Model
    from piezo_valve_ros.identify import parameters_yaml
    rows = simulate_rows(identification_voltage(5e-4, 5.0)[: int(12 / 5e-4)], ValveSimConfig(dt=5e-4, seed=4))
    write_samples_bag(tmp_path / "short", rows)
    (tmp_path / "model.yaml").write_text(parameters_yaml(Model().to_parameters(), ["the paper's model"]))
    out = run_cli(tmp_path / "short", "--monitor", tmp_path / "model.yaml")
    assert out.returncode == 0, out.stderr
    assert "no verdict possible: the record spans 12.0 s, shorter than one window of 20 s" in out.stdout, out.stdout
    out = run_cli(tmp_path / "short", "--monitor", tmp_path / "model.yaml", "--window-s", "5")
    assert out.returncode == 0 and "no verdict possible" not in out.stdout and " verdicts: " in out.stdout, out.stdout
    assert run_cli(tmp_path / "short", "--window-s", "5").returncode == 2   # --window-s belongs to --monitor


def test_a_noise_free_record_is_judged_against_its_resolution_not_a_noise_of_1e_minus_14():
    from piezo_valve_ros.core.identification import Record
    from piezo_valve_ros.core.identification import analyse
    rows = simulate_rows(identification_voltage(5e-4, 10.0), ValveSimConfig(dt=5e-4, seed=5).ideal())
    report = analyse(Record.from_rows(rows)).report.to_json()
    assert report["noise_floor_um"] == pytest.approx(1e-6 * report["range_um"], rel=1e-3)
    assert any("shows no sensor noise" in w for w in report["warnings"])
    assert report["residual_structure"]["ratio_to_noise"] < 1e7


def test_the_written_command_limits_are_rounded_inwards_so_the_tools_accept_them():
    """A record over 2.9396..7.009 V puts the quarter-span limit at 1.92225 V: written rounded to 4 decimals it
    must lie inside (1.9223), or valve_tune and the controller refuse the file the tool wrote."""
    from types import SimpleNamespace
    from piezo_valve_ros.core.control import fitted_range_problems
    from piezo_valve_ros.identify import command_range_note
    for fitted in [(2.9396, 7.009), (2.94, 7.0091), (3.00005, 6.99995), (4.12345, 6.54321)]:
        limits, note = command_range_note(SimpleNamespace(controller_model=SimpleNamespace(fitted_range_v=fitted)))
        assert limits and "commands limited to" in note
        assert fitted_range_problems(fitted, limits["command_min_v"], limits["command_max_v"]) == [], (fitted, limits)


def _two_valve_day(path):
    """A 60 s 1 kHz 'day' bag: the default valve for 30 s, then 30 s where the sensor reads a constant (a wire
    fell off): a window of the first half identifies the valve, the whole day cannot be fitted to it.  Its
    samples' own time axis starts at 1000 s."""
    rows = simulate_rows(identification_voltage(1e-3, 30.0), ValveSimConfig(dt=1e-3, seed=3))
    rows = rows[rows[:, 0] - rows[0, 0] < 30.0 - 1e-6]
    late = rows.copy()
    late[:, 0] += rows[-1, 0] + 1e-3 - rows[0, 0]
    late[:, 2] = rows[-1, 2]
    day = np.vstack((rows, late))
    day[:, 0] += 1000.0
    write_samples_bag(path, day, topic="/valve1/samples")
    return day


def test_a_window_of_a_long_bag_is_read_alone(tmp_path):
    """read_samples keeps only the rows of the window (from the record's first sample, or on the samples' own
    time axis); a window that holds nothing or is malformed is refused with one line naming the record's extent."""
    from piezo_valve_ros.io import BagError
    from piezo_valve_ros.core import TimeWindow
    day = _two_valve_day(tmp_path / "day")
    t0 = day[0, 0]
    rows, _ = read_samples(tmp_path / "day", window=TimeWindow(5.0, 8.0))
    assert rows[0, 0] >= t0 + 5.0 - 1e-9 and rows[-1, 0] <= t0 + 8.0 + 1e-9 and abs(rows.shape[0] - 3001) <= 1
    np.testing.assert_array_equal(rows, day[(day[:, 0] >= t0 + 5.0) & (day[:, 0] <= t0 + 8.0)])
    stamped, _ = read_samples(tmp_path / "day", window=TimeWindow(1005.0, 1008.0, on_stamps=True))
    np.testing.assert_array_equal(stamped, rows)
    tail, _ = read_samples(tmp_path / "day", window=TimeWindow(from_s=55.0))
    assert tail[-1, 0] == day[-1, 0] and abs(tail.shape[0] - 5000) <= 1
    with pytest.raises(BagError, match="no samples from 70 to its end"):
        read_samples(tmp_path / "day", window=TimeWindow(from_s=70.0))
    with pytest.raises(BagError, match="run from 1000.000 s"):
        read_samples(tmp_path / "day", window=TimeWindow(to_s=10.0, on_stamps=True))
    assert TimeWindow(5.0, 2.0).problems() == ["--to 2 s must come after --from 5 s"]
    assert "before the record's start" in TimeWindow(-1.0).problems()[0]
    assert TimeWindow(-1.0, on_stamps=True).problems() == []
    assert "finite" in TimeWindow(to_s=float("nan")).problems()[0]


def test_valve_identify_and_valve_plot_take_a_window_of_a_long_run(tmp_path):
    """valve_identify --from/--to identifies one stretch and the report says which (source.train_window); the
    whole day, whose held-out tail is the lost sensor, is refused.  valve_plot --to reads the same stretch.  A malformed
    window ends either tool with one line and exit 2."""
    _two_valve_day(tmp_path / "day")
    out = run_cli(tmp_path / "day", "--to", "30", "--report", tmp_path / "r.json", "--quiet")
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    assert check_report(report) == []
    window = report["source"]["train_window"]
    assert window["from_s"] is None and window["to_s"] == 30.0 and window["axis"] == "record_start"
    assert window["first_sample_s"] == 1000.0 and abs(window["last_sample_s"] - 1030.0) < 2e-3
    assert abs(window["samples"] - 30001) <= 1
    assert report["final"]["validate"]["rms_um"] < 0.2
    # the whole day: its held-out tail is the dead sensor, refused with the reason
    _one_error_line(run_cli(tmp_path / "day", "--quiet"), "position is constant")
    for args, needle in ((("--from", "20", "--to", "10"), "must come after"), (("--stamps",), "--stamps needs")):
        usage = run_cli(tmp_path / "day", *args)   # argparse: its usage line, then the reason
        assert usage.returncode == 2 and needle in usage.stderr.splitlines()[-1] and "Traceback" not in usage.stderr
    _one_error_line(run_cli(tmp_path / "day", "--from", "500"), "no samples from 500 to its end")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    plot = subprocess.run([sys.executable, "-m", "piezo_valve_ros.cli.plot", str(tmp_path / "day"), "--to", "30",
                           "--json", "--out", str(tmp_path / "figs")], capture_output=True, text=True, env=env,
                          timeout=120)
    assert plot.returncode == 0, plot.stderr
    assert abs(json.loads(plot.stdout)["samples"] - 30001) <= 1
    bad = subprocess.run([sys.executable, "-m", "piezo_valve_ros.cli.plot", str(tmp_path / "day"), "--from", "nan"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 2 and "finite" in bad.stderr


def _sine_bag(path, seconds, rate_hz=1000.0, batch=1000):
    """A bag of a 1 Hz sine drive and a position that follows it, written a message at a time (its rows are never
    all in memory here)."""
    from piezo_valve_ros.io import SAMPLES_TYPE, serialize_samples
    rec = BagRecorder(path, {"/samples": (SAMPLES_TYPE, qos_profile(True, 100))}, segment_s=float("inf"),
                      clock=lambda: 0.0)
    for k0 in range(0, int(seconds * rate_hz), batch):
        t = (k0 + np.arange(batch)) / rate_hz
        v = 5.0 + 4.0 * np.sin(2 * np.pi * t)
        rec.write("/samples", 1_700_000_000_000_000_000 + int(round(t[-1] * 1e9)),
                  serialize_samples(np.column_stack((t, v, 13e-6 * v))))
    rec.close()


def test_a_long_bag_is_read_no_further_than_the_loop_analyses(tmp_path):
    """identify_bags reads a training bag only up to MAX_ANALYSED_S (the rest is skipped undecoded): the memory the
    read takes does not grow with the bag (peak traced allocations for a bag 4x longer within 1.3x, and below the
    longer bag's own rows), and a warning says how long the record runs and what was read."""
    import tracemalloc
    from piezo_valve_ros.core.identification import MAX_ANALYSED_S
    from piezo_valve_ros.identify import read_record
    peaks, records = [], []
    for seconds in (1.5 * MAX_ANALYSED_S, 6 * MAX_ANALYSED_S):
        _sine_bag(tmp_path / f"bag{seconds:.0f}", seconds)
        warnings: list[str] = []
        tracemalloc.start()
        record, _ = read_record(tmp_path / f"bag{seconds:.0f}", log=lambda s: None, warnings=warnings,
                                longest_s=MAX_ANALYSED_S)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        records.append(record)
        assert len(record) == int(MAX_ANALYSED_S * 1000) + 1
        assert len(warnings) == 1 and f"runs {seconds - 1e-3:.0f} s; its first {MAX_ANALYSED_S:g} s" in warnings[0]
    assert peaks[1] < 1.3 * peaks[0], peaks
    assert peaks[1] < 6 * MAX_ANALYSED_S * 1000 * 3 * 8, peaks   # less than the longer bag's rows alone
    np.testing.assert_array_equal(records[0].position_um, records[1].position_um)


def test_the_loop_analyses_the_first_part_of_a_long_record_and_says_so():
    """analyse on a record longer than MAX_ANALYSED_S: its first MAX_ANALYSED_S, a warning and the report's
    ``analysed`` say so; a shorter record is analysed whole."""
    from piezo_valve_ros.core.identification import MAX_ANALYSED_S, Record
    from piezo_valve_ros.core.identification import analyse
    rows = simulate_rows(identification_voltage(1e-3, 30.0), ValveSimConfig(dt=1e-3, seed=5))
    n = rows.shape[0]
    reps = int(np.ceil(1.6 * MAX_ANALYSED_S / (n * 1e-3)))
    long = Record(np.arange(n * reps) * 1e-3, np.tile(rows[:, 1], reps), np.tile(rows[:, 2], reps) * 1e6)
    report = analyse(long).report.to_json()
    a = report["analysed"]["train"]
    assert a["from_s"] == 0.0 and a["to_s"] == MAX_ANALYSED_S and a["samples"] == int(MAX_ANALYSED_S * 1000) + 1
    assert a["of_samples"] == n * reps
    assert any(f"its first {MAX_ANALYSED_S:.0f} s" in w for w in report["warnings"])
    assert report["held_out_samples"] == a["samples"] - int(round(0.7 * a["samples"])) or \
        abs(report["held_out_samples"] - 0.3 * a["samples"]) < 2000
    short = analyse(Record(rows[:, 0], rows[:, 1], rows[:, 2] * 1e6)).report.to_json()
    assert short["analysed"]["train"]["samples"] == n == short["analysed"]["train"]["of_samples"]
    assert not any("were analysed" in w for w in short["warnings"])


_REFILL_FAULTS = """
import resource, sys
import numpy as np
from piezo_valve_ros.runtime.memory import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else None
size = 48 << 20   # above glibc's own mmap threshold (32 MB at the most), below MMAP_THRESHOLD_BYTES
a = np.empty(size // 8); a.fill(1.0); del a
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
b = np.empty(size // 8); b.fill(1.0)
print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before, size // (2 << 20))
"""


def test_a_process_that_keeps_freed_memory_refills_an_array_without_faulting_it_in_again():
    """runtime.memory.keep_freed_memory (valve_identify, the identification and monitor nodes, the tests' workers):
    an array freed and made again of the same size reuses the memory it had; without it glibc gave the memory back
    and every page of the second array is faulted in afresh."""
    def run(mode):
        out = subprocess.run([sys.executable, "-c", _REFILL_FAULTS, mode], capture_output=True, text=True,
                             check=True).stdout.split()
        return out[0], int(out[1]), int(out[2])
    kept, faults_kept, huge_pages = run("keep")
    if kept != "True":
        pytest.skip("the C library is not glibc: keep_freed_memory changes nothing")
    _, faults_default, _ = run("default")
    # a fault a page at the least (numpy asks for 2 MB pages where the kernel has them; 4 kB ones: 512x as many)
    assert faults_default >= huge_pages, (faults_default, huge_pages)
    assert faults_kept < huge_pages // 4, (faults_kept, huge_pages)
