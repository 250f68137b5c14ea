"""Identification as a library: bags (or CSV records) -> analysis -> the model the controller can use -> its
parameters.

``valve_identify`` (``identify_cli``) and the ``valve_identification`` node are thin faces over this
module.  No ROS import: it runs wherever ``rosbags`` does.
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from .bagio import read_samples
from .core.effects import NotCompensable
from .core.fitting import fit_model
from .core.records import Record, read_csv
from .core.residual import Analysis, analyse
from .core.valve_model import ValveModel, unity_dc_poles

__all__ = ["identify_bags", "read_record", "Compensation", "compensation", "controller_parameters", "controller_parameters_yaml",
           "report_json", "write_atomically", "write_outputs"]


def read_record(path, topic: Optional[str] = None, log: Callable[[str], None] = print,
                warnings: Optional[list[str]] = None) -> tuple[Record, Optional[str]]:
    """A record from a bag directory (its samples topic) or from a ``.csv`` file (``records.read_csv``);
    returns (record, topic name or None).  Storage files of a damaged bag that had to be left out are logged
    and appended to ``warnings``."""
    if str(path).lower().endswith(".csv") and not Path(path).is_dir():
        record = read_csv(path)
        log(f"{path}: {len(record)} samples (CSV)")
        return record, None
    skipped: list[str] = []
    rows, name = read_samples(path, topic, skipped)
    log(f"{path}: {rows.shape[0]} samples on {name}")
    if skipped:
        text = (f"{path}: {len(skipped)} damaged storage file(s) left out, the rest used: "
                + "; ".join(skipped))
        log(f"warning: {text}")
        if warnings is not None:
            warnings.append(text)
    return Record.from_rows(rows), name


def identify_bags(train_bag, validate_bag=None, topic: Optional[str] = None,
                  log: Callable[[str], None] = print) -> tuple[Analysis, Optional[str]]:
    """Read the bag(s) or CSV record(s) and run the residual loop; returns (analysis, samples topic name, None
    for CSV).  Raises BagError or IdentificationError with a one-line reason."""
    damaged: list[str] = []
    train, name = read_record(train_bag, topic, log, damaged)
    validate = None if validate_bag is None else read_record(validate_bag, topic, log, damaged)[0]
    analysis = analyse(train, validate, log=log)
    analysis.report["warnings"] = damaged + list(analysis.report.get("warnings", []))
    analysis.report["source"] = {"train_bag": str(train_bag), "validate_bag": None if validate_bag is None
                                 else str(validate_bag), "topic": name}
    return analysis, name


@dataclass(frozen=True)
class Compensation:
    """What the controller gets from an identification: a model it can invert, and what it had to leave."""

    model: ValveModel
    refused: dict[str, str]   # effect name -> why the controller cannot use it


def compensation(analysis: Analysis) -> Compensation:
    """The final model reduced to what the controller compensates: the GPIM (asymmetric when its envelopes
    allow the exact inverse), G_v (its first pole pair) and the effects whose ``compensation`` the controller
    takes (creep, asymmetry); the others are listed
    with their reasons.  When anything is left out the model is refitted without it, so the GPIM the
    controller inverts is the best one without that structure."""
    final = analysis.final
    usable, refused = [], {}
    for e, c in zip(final.effects, final.coefs):
        try:
            e.compensation(final, c)
            usable.append(e)
        except NotCompensable as exc:
            refused[e.name] = str(exc)
    if not refused:
        return Compensation(final, refused)
    base = analysis.baseline
    model = fit_model(analysis.split.fit, base, usable, try_forms=False) if usable else base
    return Compensation(model, refused)


def controller_parameters(comp: Compensation) -> dict:
    """``valve_controller`` parameters (name -> value) for a compensation model."""
    m = comp.model
    g = m.gpim
    gv = unity_dc_poles([m.sections[0]])
    values = {"gpim.thresholds": [float(x) for x in g.thresholds], "gpim.weights": [float(x) for x in g.weights],
              "gpim.a0": float(g.a0), "gpim.a1": float(g.a1), "gpim.offset_um": float(g.offset_um),
              # symmetric unless the asymmetry effect says otherwise (written out, so a push replaces an older one)
              "gpim.descending_envelope": [float(g.a0), float(g.a1), 0.0],
              "valve_model.num": [float(x) for x in gv.num], "valve_model.den": [float(x) for x in gv.den],
              "creep.time_constants_s": [1.0], "creep.gains": [0.0]}
    for e, c in zip(m.effects, m.coefs):
        values.update(e.compensation(m, c))
    return values


def _floats(values) -> str:
    return "[" + ", ".join(repr(float(x)) for x in values) + "]"


def controller_parameters_yaml(comp: Compensation, source: str, report: dict) -> str:
    """A ROS parameters file for ``valve_controller`` with the compensation model, and comments that say what
    it is and what was left out."""
    lines = [f"# Fitted by valve_identify from {source}",
             f"# final model {report['final']['model']}; held-out RMS {report['baseline']['validate']['rms_um']:.4f} um "
             f"(baseline {report['baseline']['model']}) -> {report['final']['validate']['rms_um']:.4f} um",
             f"# compensation model: {comp.model.name}"]
    for name, why in comp.refused.items():
        lines.append(f"# not compensated: {why}")
    lines += ["/**/valve_controller:", "  ros__parameters:"]
    for key, value in controller_parameters(comp).items():
        lines.append(f"    {key}: {_floats(value) if isinstance(value, list) else repr(float(value))}")
    return "\n".join(lines) + "\n"


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


def write_outputs(outputs: dict[str, str]) -> list[str]:
    """Write several files all or nothing: every path is checked to be writable first (a directory, a
    missing parent that cannot be made, ...) so a bad path fails before anything is replaced; then each is
    replaced atomically.  Returns the paths written."""
    for path in outputs:
        p = Path(path)
        if p.is_dir():
            raise OSError(f"{path} is a directory")
        parent = p.parent if str(p.parent) else Path(".")
        if parent.exists() and not os.access(parent, os.W_OK):
            raise OSError(f"cannot write {path}: its directory is not writable")
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


def report_json(analysis: Analysis) -> str:
    return json.dumps(analysis.report, indent=2) + "\n"
