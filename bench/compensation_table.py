"""Issue 11's table: for the default simulated valve and for each effect switched on, identify -> compensate ->
track the paper's validation reference (eq. 12, 60 um peak, held out: neither record the model was fitted on),
under OL HC and PID HC, with the baseline model (the paper's: GPIM + G_v) against the extended one (every
effect the controller can invert, dynamic feedforward on).

    python bench/compensation_table.py [--dt 5e-4] [--only NAME ...] [--markdown FILE] [--gains pid_hc_5]
                                       [--no-tuned]

Errors of the measured position (LVDT noise and quantisation included, as a rig sees them) and, in the
"spool" columns, of the spool's true position in the same runs (the simulator's: the tracking beneath the
sensor's noise floor).  Besides OL HC and the Table 1 set, PID HC with gains the tuner chose on each valve's extended model (the
identification's ``tune`` step), with both models.  Runs in-process on the core (no ROS); one to three minutes
per valve at the default 2 kHz.
"""
import argparse
import sys
import time

from evaluation import SIMULATED_EFFECTS, compare_compensations
from piezo_valve_ros.core.sim import ValveSimConfig
from piezo_valve_ros.core.control import ControllerConfig, PIDGains, gain_set


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dt", type=float, default=5e-4, help="sample and control period [s] (default 5e-4)")
    ap.add_argument("--only", nargs="+", choices=list(SIMULATED_EFFECTS), help="these valves only")
    ap.add_argument("--gains", default="pid_hc_5", help="Table 1 set for PID HC (default pid_hc_5)")
    ap.add_argument("--markdown", metavar="FILE", help="also write the table as Markdown")
    ap.add_argument("--no-tuned", action="store_true", help="leave out the PID HC rows with tuned gains")
    args = ap.parse_args(argv)
    strategy, gains = gain_set(args.gains)
    strategies = {"OL HC": ControllerConfig(strategy="ol_hc", gains=PIDGains(0.0, 0.0)),
                  f"{args.gains.upper().replace('_', ' ')}": ControllerConfig(strategy=strategy, gains=gains)}
    head = ("| valve | effects found | not compensated | strategy | RMS baseline [um] | RMS extended [um] | "
            "peak baseline [um] (% range) | peak extended [um] (% range) | RMS ratio | peak ratio | "
            "spool RMS [um] | spool peak [um] | spool peak ratio |")
    lines = [head, "|" + "---|" * 13]
    print(head)
    for name in args.only or SIMULATED_EFFECTS:
        t0 = time.perf_counter()
        sim = SIMULATED_EFFECTS[name](ValveSimConfig(dt=args.dt))
        result = compare_compensations(sim, strategies, log=lambda s: None,
                                       tuned=() if args.no_tuned else ("pid_hc",))
        for label, config in result.strategies.items():
            b, e = result.errors[("baseline", label)], result.errors[("extended", label)]
            sb, se = result.spool_errors[("baseline", label)], result.spool_errors[("extended", label)]
            g = config.gains
            shown = label if label in strategies else f"{label} (kp {g.kp:.3g}, ki {g.ki:.4g}, kd {g.kd:.2g})"
            row = (f"| {name} | {', '.join(result.effects_added) or 'none'} | {', '.join(n + (' (in part)' if n in result.kept_in_part else '') for n in result.refused) or '-'} | "
                   f"{shown} | {b.rms_um:.3f} | {e.rms_um:.3f} | {b.peak_um:.3f} ({b.peak_pct:.2f} %) | "
                   f"{e.peak_um:.3f} ({e.peak_pct:.2f} %) | {e.rms_um / b.rms_um:.2f} | {e.peak_um / b.peak_um:.2f} | "
                   f"{sb.rms_um:.3f} -> {se.rms_um:.3f} | {sb.peak_um:.3f} -> {se.peak_um:.3f} | "
                   f"{se.peak_um / sb.peak_um:.2f} |")
            print(row, flush=True)
            lines.append(row)
        f = result.model_floor
        print(f"    OL HC extended on its own model (the feedforward's floor): RMS {f.rms_um:.3f} um, peak "
              f"{f.peak_um:.3f} um", flush=True)
        lines.append(f"| {name} | | | OL HC extended on its own model (no noise, no missing effect) | | {f.rms_um:.3f} | "
                     f"| {f.peak_um:.3f} ({f.peak_pct:.2f} %) | | | | | |")
        for effect, why in result.refused.items():
            print(f"    {name}: not compensated: {why}")
        print(f"    ({time.perf_counter() - t0:.0f} s)", flush=True)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(f"Written by `python bench/compensation_table.py {' '.join(sys.argv[1:])}`.\n\n"
                    + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
