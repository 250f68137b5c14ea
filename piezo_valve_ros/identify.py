"""Identification as a library: bags (or CSV records) -> analysis -> the model the controller can use -> its
parameters.

``valve_identify`` (``cli.identify``) and the ``valve_identification`` node are thin faces over this
module.  No ROS import: it runs wherever ``rosbags`` does.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from .core.errors import PiezoValveError
from .io.bags import read_samples
from .core.control.compensation import CompensationModel, command_range_for
from .core.model.drive import CENTRE_VOLTAGE_V, COMMAND_MAX_V, COMMAND_MIN_V
from .core.monitoring.health import Health, HealthLimits, HealthMonitor, Level
from .io.params_yaml import node_section, yaml_value
from .core.identification.records import MAX_ANALYSED_S, Record, read_csv
from .core.identification.report import IdentificationReport, SchemaBlock, Source, TrainWindow
from .core.identification.whole_record import BlockMeans
from .core.runs import WHOLE_RECORD, TimeWindow, WindowError
from .core.identification.residual import Analysis, analyse
from .core.identification.to_controller import (Compensation, base_parameters, baseline_compensation, compensation,
                                                 controller_parameters)

__all__ = ["identify_bags", "read_record", "Compensation", "compensation", "baseline_compensation", "base_parameters",
           "controller_parameters", "controller_parameters_yaml", "command_range_note", "parameters_yaml", "read_parameters_file",
           "ParametersFileError", "report_json", "write_atomically", "check_output_paths", "write_outputs", "monitor_record", "health_json", "summary_json"]

CONTROLLER_NODE = "valve_controller"   # the node whose section a parameters file carries


class ParametersFileError(PiezoValveError, ValueError):
    """A parameters file that cannot be read or has no usable ``valve_controller`` section."""


def read_record(path, topic: Optional[str] = None, log: Callable[[str], None] = print,
                warnings: Optional[list[str]] = None, window: TimeWindow = WHOLE_RECORD,
                longest_s: Optional[float] = None, whole: Optional[BlockMeans] = None) -> tuple[Record, Optional[str]]:
    """A record from a bag directory (its samples topic) or from a ``.csv`` file (``records.read_csv``), the
    stretch ``window`` of it (no window: its first ``longest_s`` [s] where given, said in ``warnings`` when that is
    not all of it; ``whole`` then receives all of the bag as it is read, reduced to the analysis rate); returns
    (record, topic name or None).  Storage files of a damaged bag that had to be
    left out are logged and appended to ``warnings``.  Raises BagError or WindowError (the window holds no samples
    or is malformed) with a one-line reason."""
    if window.problems():
        raise WindowError("; ".join(window.problems()))
    if str(path).lower().endswith(".csv") and not Path(path).is_dir():
        record = read_csv(path)
        lo, hi = window.bounds(float(record.time_s[0]))
        inside = np.flatnonzero((record.time_s >= lo) & (record.time_s <= hi))
        if inside.size == 0:
            raise WindowError(f"{path}: no samples from {window.describe()} (its samples run from "
                              f"{record.time_s[0]:.3f} s to {record.time_s[-1]:.3f} s)")
        record = record if window.whole else record.slice(int(inside[0]), int(inside[-1]) + 1)
        log(f"{path}: {len(record)} samples (CSV){_window_note(record, window)}")
        return record, None
    skipped: list[str] = []
    extent: dict = {}
    capped = window.whole and longest_s is not None
    rows, name = read_samples(path, topic, skipped, TimeWindow(to_s=longest_s) if capped else window, extent,
                              each_block=whole.add if capped and whole is not None else None)
    record = Record.from_rows(rows)
    log(f"{path}: {rows.shape[0]} samples on {name}{_window_note(record, window)}")
    if capped and extent["last_s"] > record.time_s[-1]:
        text = (f"{path}: the record runs {extent['last_s'] - extent['first_s']:.0f} s; its first {longest_s:g} s were "
                f"read at its own rate (the loop fits the fast parts on no more: MAX_ANALYSED_S; --from/--to choose "
                f"another stretch)" + (", and all of it reduced to the analysis rate (a slow trend is judged on the "
                                       "whole record)" if whole is not None else ""))
        log(f"warning: {text}")
        if warnings is not None:
            warnings.append(text)
    if skipped:
        text = (f"{path}: {len(skipped)} damaged storage file(s) left out, the rest used: "
                + "; ".join(skipped))
        log(f"warning: {text}")
        if warnings is not None:
            warnings.append(text)
    return record, name


def _window_note(record: Record, window: TimeWindow) -> str:
    if window.whole:
        return ""
    return (f", the window {window.describe()}: {record.time_s[0]:.3f} .. {record.time_s[-1]:.3f} s on the samples' "
            f"own time axis")


def identify_bags(train_bag, validate_bag=None, topic: Optional[str] = None,
                  log: Callable[[str], None] = print, window: TimeWindow = WHOLE_RECORD) -> tuple[Analysis, Optional[str]]:
    """Read the bag(s) or CSV record(s) and run the residual loop on the training record's stretch ``window``
    (the validation record whole); returns (analysis, samples topic name, None for CSV).  The report's
    ``source`` names the window and the samples it held.  Raises BagError, WindowError or IdentificationError
    with a one-line reason."""
    damaged: list[str] = []
    # no more than the loop analyses is read: an hour-long bag costs what its first minutes do
    # (a long training bag: all of it streamed to the analysis rate as it is read, for the slow trend)
    reduced = BlockMeans()
    train, name = read_record(train_bag, topic, log, damaged, window, longest_s=MAX_ANALYSED_S, whole=reduced)
    whole = reduced.record() if reduced.rows > len(train) else None
    if whole is not None and reduced.dropped:
        damaged.append(f"{train_bag}: {reduced.dropped} rows out of time order or delivered twice were left out of the "
                       f"whole record's reduction")
        log("warning: " + damaged[-1])
    validate = (None if validate_bag is None
                else read_record(validate_bag, topic, log, damaged, longest_s=MAX_ANALYSED_S)[0])
    analysis = analyse(train, validate, log=log, whole=whole)
    source = Source(train_bag=str(train_bag), validate_bag=None if validate_bag is None else str(validate_bag),
                    topic=name, train_window=TrainWindow(**window.as_dict(), first_sample_s=float(train.time_s[0]),
                                                         last_sample_s=float(train.time_s[-1]), samples=len(train)))
    analysis.report = replace(analysis.report, warnings=tuple(damaged) + analysis.report.warnings, source=source)
    return analysis, name


HEALTH_SCHEMA = "piezo_valve_ros/health-report"
HEALTH_SCHEMA_VERSION = 1


def monitor_record(path, params_file, topic: Optional[str] = None, limits: Optional[HealthLimits] = None,
                   log: Callable[[str], None] = print) -> list[Health]:
    """The health monitor (``core.monitoring.health``) over a recorded bag or CSV, with the model of a
    controller parameters file (its ``model.fitted_range_v`` or the controller's default command range);
    one log line per change of level.  Raises BagError, IdentificationError or ParametersFileError."""
    params = read_parameters_file(params_file)
    low, high = params.get("command_min_v", COMMAND_MIN_V), params.get("command_max_v", COMMAND_MAX_V)
    try:
        model = CompensationModel.from_parameters(params, float(low), float(high))
    except ValueError as exc:
        raise ParametersFileError(f"{params_file}: {exc}") from None
    record, _ = read_record(path, topic, log)
    rows = np.column_stack([record.time_s, record.voltage_v, record.position_um * 1e-6])
    limits = limits or HealthLimits()
    monitor = HealthMonitor(model, record.dt, limits, (float(low), float(high)))
    if record.duration_s < limits.window_s:
        log(f"no verdict possible: the record spans {record.duration_s:.1f} s, shorter than one window of "
            f"{limits.window_s:g} s (valve_identify --window-s sets a shorter one)")
    chunk = max(int(round(0.1 / record.dt)), 1)
    verdicts: list[Health] = []
    for k in range(0, len(rows), chunk):
        for h in monitor.add(rows[k:k + chunk]):
            if not verdicts or h.level is not verdicts[-1].level:
                log(f"{h.start_s:9.1f}..{h.end_s:9.1f} s: {h.level.name}: {h.message}")
            verdicts.append(h)
    return verdicts


def health_json(verdicts: list[Health], source: str) -> str:
    """The monitor's verdicts as JSON, with a schema block (name, version, package version, time)."""
    counts = {lv.name: sum(h.level is lv for h in verdicts) for lv in Level}
    return json.dumps({"schema": _schema_block(HEALTH_SCHEMA, HEALTH_SCHEMA_VERSION).to_json(), "source": source,
                       "counts": counts,
                       "verdicts": [h.as_dict() for h in verdicts]}, indent=2) + "\n"


def parameters_yaml(values: dict, comments: list[str]) -> str:
    """A ROS parameters file for ``valve_controller``: ``comments`` (one line each) then ``values``."""
    lines = [f"# {c}" for c in comments] + [f"/**/{CONTROLLER_NODE}:", "  ros__parameters:"]
    for key, value in values.items():
        lines.append(f"    {key}: {yaml_value(value)}")
    return "\n".join(lines) + "\n"


def command_range_note(comp: Compensation) -> tuple[dict, str]:
    """The command range a controller may use with this model (``compensation.command_range_for``) as parameters,
    and one line that says why, when it is not the whole 0..10 V drive ({} and '' when it is)."""
    fitted = comp.controller_model.fitted_range_v
    allowed = command_range_for(fitted, COMMAND_MIN_V, COMMAND_MAX_V, CENTRE_VOLTAGE_V)
    if allowed == (COMMAND_MIN_V, COMMAND_MAX_V) or not fitted:
        return {}, ""
    lo, hi = fitted
    if allowed is None:
        return {}, (f"the record drove the valve over {lo:.3g}..{hi:.3g} V only: too narrow to control it with this "
                    f"model (the controller and valve_tune refuse it for commands {COMMAND_MIN_V:g}..{COMMAND_MAX_V:g} V); "
                    f"record a training run across the range the valve will see (valve_identification's train step, or "
                    f"valve_command sine --amplitude 50e-6 --frequency 0.5 --duration 10)")
    # rounded inwards: a limit rounded outwards lies beyond what the controller and valve_tune accept
    inside = math.ceil(allowed[0] * 1e4) / 1e4, math.floor(allowed[1] * 1e4) / 1e4
    return ({"command_min_v": inside[0], "command_max_v": inside[1]},
            f"the record drove the valve over {lo:.3g}..{hi:.3g} V: commands limited to {allowed[0]:.3g}..{allowed[1]:.3g} V "
            f"(a model is trusted a quarter of its span beyond it); a training run across {COMMAND_MIN_V:g}..{COMMAND_MAX_V:g} V "
            f"gives a model for the whole drive")


def controller_parameters_yaml(comp: Compensation, source: str, report: IdentificationReport,
                               extra: Optional[dict] = None,
                               extra_comments: Optional[list[str]] = None) -> str:
    """A ROS parameters file for ``valve_controller`` with the compensation model (and ``extra`` parameters,
    e.g. tuned gains), and comments that say what it is and what was left out.  Where the record drove only part
    of the 0..10 V drive, the file limits the commands to what the model knows (``command_range_note``)."""
    comments = [f"Fitted by valve_identify from {source}",
                f"final model {report.final.model}; held-out RMS {report.baseline.validate.rms_um:.4f} "
                f"um (baseline {report.baseline.model}) -> {report.final.validate.rms_um:.4f} um",
                f"compensation model: {comp.model.name}"]
    limits, note = command_range_note(comp)
    comments += [f"not compensated: {why}" for why in comp.refused.values()] + ([note] if note else [])
    comments += list(extra_comments or [])
    return parameters_yaml({**controller_parameters(comp), **limits, **(extra or {})}, comments)


def read_parameters_file(path: str | os.PathLike) -> dict:
    """The ``valve_controller`` parameters of a ROS parameters file, read as ROS reads it
    (``params_yaml.node_section``: the ``/**`` section, then every ``valve_controller``, ``/**/valve_controller``
    or namespaced section ending in it, later ones winning).  Raises ParametersFileError with the reason."""
    try:
        return node_section(path, CONTROLLER_NODE)
    except OSError as exc:
        raise ParametersFileError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ParametersFileError(str(exc)) from None


def write_atomically(path: str | os.PathLike, text: str) -> None:
    """Replace ``path`` with ``text`` in one step (a temporary file in the same directory, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # an ordinary file, not mkstemp's private 0600
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError):  # name the user's path, not the temporary file
            raise OSError(f"cannot write {path}: {exc.strerror or exc}") from None
        raise


def check_output_paths(paths) -> None:
    """OSError naming the first of ``paths`` that cannot be written as a file (a directory, or under a directory
    that is not writable or cannot be made), without making or writing anything: a tool checks its outputs
    before a long piece of work, not after it."""
    for path in paths:
        p = Path(path)
        if p.is_dir():
            raise OSError(f"{path} is a directory")
        existing = p.parent if str(p.parent) else Path(".")
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        if not existing.is_dir():
            raise OSError(f"cannot create the directory of {path}: {existing} is not a directory")
        if not os.access(existing, os.W_OK):
            raise OSError(f"cannot write {path}: {existing} is not writable")


def write_outputs(outputs: dict[str, str]) -> list[str]:
    """Write several files all or nothing: every path is checked to be writable first (a directory, a
    missing parent that cannot be made, ...) so a bad path fails before anything is replaced; then each is
    replaced atomically.  Returns the paths written."""
    check_output_paths(outputs)
    for path in outputs:
        p = Path(path)
        parent = p.parent if str(p.parent) else Path(".")
        if not parent.exists():
            try:
                parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise OSError(f"cannot create the directory of {path}: {exc.strerror}") from None
    written = []
    for path, text in outputs.items():
        write_atomically(path, text)
        written.append(str(path))
    return written


REPORT_SCHEMA = "piezo_valve_ros/identification-report"
REPORT_SCHEMA_VERSION = 3   # 1: the keys before the schema block; 2: adds schema, fit_pct, indistinguishable;
                            # 3: 'rounds' retired (it repeated 'confirm' under an earlier name)


def package_version() -> str:
    """The installed package's version ("unknown" when run from a source tree without metadata)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("piezo_valve_ros")
    except PackageNotFoundError:
        return "unknown"


SUMMARY_SCHEMA = "piezo_valve_ros/identification-summary"
SUMMARY_SCHEMA_VERSION = 1   # an object: schema and the plan's steps (before: the bare list of steps)


def _schema_block(name: str, version: int) -> SchemaBlock:
    """What a written file is: its schema's name and version, the package's version, when."""
    return SchemaBlock(name=name, version=version, package_version=package_version(),
                       created_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"))


def summary_json(steps: list[dict]) -> str:
    """The identification node's ``summary.json``: a schema block and the figures of each step done."""
    return json.dumps({"schema": _schema_block(SUMMARY_SCHEMA, SUMMARY_SCHEMA_VERSION).to_json(), "steps": steps},
                      indent=2) + "\n"


def report_json(analysis: Analysis) -> str:
    """The report as JSON, opened by what it is: schema name and version, the package's version, when."""
    return json.dumps(replace(analysis.report, schema=_schema_block(REPORT_SCHEMA, REPORT_SCHEMA_VERSION)).to_json(),
                      indent=2) + "\n"
