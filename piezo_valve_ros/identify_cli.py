"""``valve_identify``: offline analysis of recorded bags (fit, residual loop, report, parameters, plots).

    valve_identify TRAIN_BAG [--validate VAL_BAG] [--report report.json] [--params-out fitted.yaml]
                   [--plots DIR] [--topic /valve1/samples]

Progress goes to stdout; any failure ends with one line on stderr and exit code 2 (bad input) or 1.
Nothing is written unless the analysis succeeded, and files are replaced atomically, so a failed
refit never overwrites the last good parameters.  No ROS import: it runs wherever ``rosbags`` does.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Optional


from .bagio import BagError, read_samples
from .core.identification import IdentificationError, Record, ValveModel, fit_model
from .core.residual import Analysis, analyse

__all__ = ["main", "controller_parameters_yaml", "compensation_model", "write_atomically", "identify_bags"]


def write_atomically(path: str | os.PathLike, text: str) -> None:
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
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def compensation_model(analysis: Analysis) -> ValveModel:
    """The model the controller can invert: the final one, refitted with a symmetric envelope when
    ``asymmetry`` was added (separate envelopes have no analytic inverse)."""
    model = analysis.final
    if model.gpim.symmetric:
        return model
    others = [eff for eff, _ in model.terms if eff.name != "asymmetry"]
    return fit_model(analysis.train, others, thresholds=model.gpim.thresholds, t0=model.t0)


def _floats(values) -> str:
    return "[" + ", ".join(repr(float(x)) for x in values) + "]"


def controller_parameters_yaml(model: ValveModel, source: str, report: dict) -> str:
    """ROS parameters file for ``valve_controller``: the free-form GPIM and the creep compensation."""
    g = model.gpim
    creep = model.creep_compensation()
    lines = [
        f"# Fitted by valve_identify from {source}",
        f"# model {report['final']['model']}; held-out RMS {report['baseline']['validate']['rms_um']:.3f} um "
        f"(baseline) -> {report['final']['validate']['rms_um']:.3f} um (final)",
    ]
    if model.name != report["final"]["model"]:
        lines.append(f"# compensation model: {model.name} (asymmetric envelopes have no analytic inverse)")
    if creep is None:
        lines.append("# no creep found: zero creep compensation")
        creep = ([1.0], [0.0])
    lines += [
        "/**/valve_controller:",
        "  ros__parameters:",
        f"    gpim.thresholds: {_floats(g.thresholds)}",
        f"    gpim.weights: {_floats(g.weights)}",
        f"    gpim.a0: {float(g.a0)!r}",
        f"    gpim.a1: {float(g.a1)!r}",
        f"    gpim.offset_um: {float(g.offset_um)!r}",
        f"    creep.time_constants_s: {_floats(creep[0])}",
        f"    creep.gains: {_floats(creep[1])}",
    ]
    return "\n".join(lines) + "\n"


def identify_bags(train_bag, validate_bag=None, topic: Optional[str] = None, log=print) -> tuple[Analysis, str]:
    """Read the bag(s) and run the analysis; returns (analysis, samples topic name)."""
    rows, name = read_samples(train_bag, topic)
    log(f"{train_bag}: {rows.shape[0]} samples on {name}")
    train = Record.from_rows(rows)
    validate = None
    if validate_bag is not None:
        vrows, vname = read_samples(validate_bag, topic)
        log(f"{validate_bag}: {vrows.shape[0]} samples on {vname}")
        validate = Record.from_rows(vrows)
    return analyse(train, validate, log=log), name


def _summary(report: dict) -> str:
    b, f = report["baseline"], report["final"]
    rows = [("baseline (" + b["fit"] + ")", b), (f["model"], f)]
    out = [f"range {report['range_um']:.1f} um; effects added: {', '.join(report['effects_added']) or 'none'}; "
           f"unexplained: {str(report['unexplained']).lower()}",
           f"{'model':28s} {'train rms':>10s} {'train peak':>11s} {'held-out rms':>13s} {'held-out peak':>14s} {'peak %':>7s}"]
    for label, r in rows:
        out.append(f"{label:28s} {r['train']['rms_um']:10.3f} {r['train']['peak_um']:11.3f} "
                   f"{r['validate']['rms_um']:13.3f} {r['validate']['peak_um']:14.3f} {r['validate']['peak_pct']:7.2f}")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="valve_identify", description=__doc__.split("\n\n")[0])
    ap.add_argument("train_bag", help="bag directory with a samples topic")
    ap.add_argument("--validate", metavar="VAL_BAG", help="validation bag (default: hold out the last 30 %%)")
    ap.add_argument("--report", metavar="FILE", help="write report.json here")
    ap.add_argument("--params-out", metavar="FILE", help="write a valve_controller parameters file here")
    ap.add_argument("--plots", metavar="DIR", help="write PNG figures here (needs matplotlib)")
    ap.add_argument("--topic", help="samples topic to read (default: the one topic named .../samples)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    args = ap.parse_args(argv)
    log = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    try:
        if args.plots:
            from . import plots  # fail before the work, with the reason
            plots.require()
        analysis, name = identify_bags(args.train_bag, args.validate, args.topic, log)
        report = dict(analysis.report)
        report["source"] = {"train_bag": str(args.train_bag), "validate_bag": args.validate, "topic": name}
        outputs = []
        if args.params_out:
            text = controller_parameters_yaml(compensation_model(analysis), str(args.train_bag), report)
        if args.plots:
            outputs += plots.write_all(analysis, args.plots)
        if args.report:
            write_atomically(args.report, json.dumps(report, indent=2) + "\n")
            outputs.append(args.report)
        if args.params_out:
            write_atomically(args.params_out, text)
            outputs.append(args.params_out)
    except (BagError, IdentificationError) as exc:
        print(f"valve_identify: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("valve_identify: interrupted; nothing written", file=sys.stderr)
        return 130
    except Exception as exc:  # one clear line, never a traceback
        print(f"valve_identify: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    if not args.quiet:
        print(_summary(report))
        for path in outputs:
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
