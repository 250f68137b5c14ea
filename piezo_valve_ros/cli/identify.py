"""``valve_identify``: offline analysis of recorded bags (fit, residual loop, report, parameters, plots).

    valve_identify TRAIN_BAG [--validate VAL_BAG] [--report report.json] [--params-out fitted.yaml]
                   [--plots DIR] [--topic /valve1/samples] [--from S] [--to S [--stamps]]
    valve_identify DAY_BAG --monitor fitted.yaml [--report health.json]   # the health monitor, offline

A record may also be a ``.csv`` file whose header names time_s, voltage_v and position_m or position_um.

Progress goes to stdout; any failure ends with one line on stderr and exit code 2 (bad input) or 1.
The report and the parameters file are written together or not at all (every path is checked before
either is replaced, and each is replaced atomically), so a failed refit never overwrites the last good
parameters.  A thin face over ``piezo_valve_ros.identify``; no ROS import.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from dataclasses import replace

from ..core.defaults import analysis_threads
from ..core.identification.records import HELD_OUT_FRACTION
from ..core.identification.report import IdentificationReport
from ..core.monitoring.health import WINDOW_S, HealthLimits
from ..runtime.memory import keep_freed_memory
from .tool import add_window_arguments, run_tool, window_from
from ..identify import (command_range_note, compensation, controller_parameters_yaml, health_json,
                       check_output_paths, identify_bags, monitor_record, report_json, write_outputs)

__all__ = ["main"]


def _summary(report: IdentificationReport) -> str:
    b, f = report.baseline, report.final
    rows = [(f"baseline {b.model} ({b.operators} operators)", b), (f.model, f)]
    out = [f"range {report.range_um:.1f} um; effects added: {', '.join(report.effects_added) or 'none'}; "
           f"unexplained: {str(report.unexplained).lower()}",
           f"held-out errors at the record's rate ({report.sample_rate_hz:.0f} Hz), {report.validation}:",
           f"{'model':36s} {'train rms':>10s} {'train peak':>11s} {'held-out rms':>13s} {'held-out peak':>14s} {'peak %':>7s}"]
    for label, r in rows:
        out.append(f"{label:36s} {r.train.rms_um:10.4f} {r.train.peak_um:11.4f} "
                   f"{r.validate.rms_um:13.4f} {r.validate.peak_um:14.4f} {r.validate.peak_pct:7.3f}")
    for w in report.warnings:
        out.append(f"warning: {w}")
    return "\n".join(out)


def main(argv=None) -> int:
    keep_freed_memory()   # before any thread starts (runtime.memory)
    ap = argparse.ArgumentParser(prog="valve_identify", description=__doc__.split("\n\n")[0])
    ap.add_argument("train_bag", help="bag directory with a samples topic, or a .csv record")
    ap.add_argument("--validate", metavar="VAL_BAG", help=f"validation bag or .csv (default: hold out the last {100 * HELD_OUT_FRACTION:.0f} %%)")
    ap.add_argument("--report", metavar="FILE", help="write report.json here")
    ap.add_argument("--params-out", metavar="FILE", help="write a valve_controller parameters file here")
    ap.add_argument("--plots", metavar="DIR", help="write PNG figures here (needs matplotlib)")
    ap.add_argument("--topic", help="samples topic to read (default: the one topic named .../samples)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines (the summary is printed)")
    add_window_arguments(ap, "identify this stretch of the training record only (the validation record is used "
                             "whole); the report's source.train_window says what was used")
    ap.add_argument("--monitor", metavar="PARAMS", help="instead of identifying: judge the record's health against "
                    "the model of this controller parameters file, as valve_monitor does live (--report writes "
                    "the verdicts)")
    ap.add_argument("--window-s", type=float, default=WINDOW_S, help=f"with --monitor: each verdict judges this "
                    f"long of the record [s] (default {WINDOW_S:g}, as valve_monitor's window_s)")
    args = ap.parse_args(argv)
    log = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    window = window_from(ap, args)
    if args.window_s != WINDOW_S and not args.monitor:
        ap.error("--window-s applies to --monitor")
    if args.monitor:
        if args.validate or args.params_out or args.plots or not window.whole:
            ap.error("--monitor takes a record, the parameters file and --report only")
        limits = replace(HealthLimits(), window_s=args.window_s, step_s=min(HealthLimits().step_s, args.window_s))
        if limits.problems():
            ap.error("; ".join(limits.problems()))

        def judge() -> list[str]:
            check_output_paths([args.report] if args.report else [])
            verdicts = monitor_record(args.train_bag, args.monitor, args.topic, limits, log=log)
            counts = {lv: sum(h.level.name == lv for h in verdicts) for lv in ("OK", "WARN", "ERROR", "STALE")}
            worst = max(verdicts, key=lambda h: (h.level.name in ("WARN", "ERROR"), h.ratio), default=None)
            lines = [f"{len(verdicts)} verdicts: " + ", ".join(f"{n} {lv}" for lv, n in counts.items())
                     + (f"; largest structured residual {worst.ratio:.1f}x the noise at {worst.end_s:.1f} s"
                        + (f" ({worst.resembles})" if worst.resembles else "") if worst else "")]
            if args.report:
                lines += [f"wrote {p}" for p in write_outputs({args.report: health_json(verdicts, str(args.train_bag))})]
            return lines
        return run_tool("valve_identify", judge)

    def work() -> list[str]:
        check_output_paths([p for p in (args.params_out, args.report) if p])   # before the work, not after it
        analysis_threads()   # a bad PIEZO_ANALYSIS_THREADS ends here, before the record is read
        if args.plots:
            from ..io import plots  # fail before the work, with the reason
            plots.require()
            if Path(args.plots).exists() and not Path(args.plots).is_dir():
                raise OSError(f"--plots {args.plots}: not a directory")
        analysis, name = identify_bags(args.train_bag, args.validate, args.topic, log, window)
        report = analysis.report
        outputs, notes = {}, []
        if args.params_out:
            comp = compensation(analysis)
            outputs[args.params_out] = controller_parameters_yaml(comp, str(args.train_bag), report)
            note = command_range_note(comp)[1]
            notes = [f"note: {note}"] if note else []
        if args.report:
            outputs[args.report] = report_json(analysis)
        written = write_outputs(outputs)
        if args.plots:
            written += plots.write_all(analysis, args.plots, log)
        return [_summary(report)] + notes + [f"wrote {path}" for path in written]
    return run_tool("valve_identify", work)

if __name__ == "__main__":
    sys.exit(main())
