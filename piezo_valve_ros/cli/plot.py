"""``valve_plot``: look at a recorded run (any bag with a ``samples`` topic, e.g. from ``valve_record``).

    valve_plot run1                  # figures into run1_plots/
    valve_plot run1 --out figs --topic /valve1/samples
    valve_plot day1 --from 600 --to 660   # one minute of a long run (only that minute is kept in memory)

Writes ``run_time.png`` (position and reference, command, tracking error) and ``hysteresis_loop.png``
(command vs position), prints the run's extent and the tracking error, and for every step found in the
reference (a change of at least 1 um held at least 50 ms) its settling time (5 % band) and overshoot.
Needs matplotlib for the figures (the numbers are printed without it, with a one-line note).  No ROS
import; a thin face over ``io.bags.read_run``, ``core.runs`` and ``io.plots.write_run``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..io.bags import BagError, read_run
from ..core.metrics import error_figures
from ..core.runs import (STEP_MIN_HOLD_S, STEP_MIN_JUMP_M, WHOLE_RECORD, TimeWindow, align_jumps, find_steps,
                         reference_on_samples)
from .tool import add_window_arguments, window_from

__all__ = ["main"]


def reference_moves(reference_m: np.ndarray) -> bool:
    """Whether a reference changes at all: a fit (NRMSE) and a peak as a share of its range need it to."""
    return bool(np.ptp(reference_m) > 0)


def summary_lines(rows: np.ndarray, reference_m: np.ndarray, topic: str,
                  window: TimeWindow = WHOLE_RECORD) -> list[str]:
    """The run's extent (the stretch's, for a window) and, where a reference is known, its tracking error."""
    t, v, y = rows[:, 0], rows[:, 1], rows[:, 2]
    rate = 1.0 / float(np.median(np.diff(t))) if t.size > 1 else float("nan")
    extent = (f"over {t[-1] - t[0]:.2f} s" if window.whole
              else f"over {t[-1] - t[0]:.2f} s, the stretch {window.describe()} (not the whole record)")
    out = [f"{topic}: {t.size} samples at {rate:.0f} Hz {extent}; command {v.min():.2f} .. "
           f"{v.max():.2f} V, position {y.min() * 1e6:.2f} .. {y.max() * 1e6:.2f} um"]
    known = np.isfinite(reference_m)
    if known.any():
        f = error_figures(y[known] * 1e6, reference_m[known] * 1e6, float(np.ptp(reference_m[known])) * 1e6)
        fit = (f"fit {f.fit_pct:.1f} % (NRMSE)" if reference_moves(reference_m[known])
               else "no fit figure (the reference is constant: nothing to fit)")
        out.append(f"tracking error over {known.mean() * 100:.0f} % of the run (where a reference was in force): "
                   f"RMS {f.rms_um:.3f} um, peak {f.peak_um:.3f} um, {fit}")
    elif window.whole:
        out.append("no position_reference in the bag: no tracking error, no steps")
    else:   # (a reference sent before the stretch counts: it is in force in it)
        out.append("no position_reference sent by the stretch's end: no tracking error, no steps")
    return out


def run_figures(rows: np.ndarray, reference_m: np.ndarray, topic: str, steps) -> dict:
    """The run's extent, tracking error and steps as plain values (``--json``); SI but positions in um."""
    t, v, y = rows[:, 0], rows[:, 1], rows[:, 2]
    known = np.isfinite(reference_m)
    tracking = None
    if known.any():
        f = error_figures(y[known] * 1e6, reference_m[known] * 1e6, float(np.ptp(reference_m[known])) * 1e6)
        tracking = {**f.as_dict(), "share_of_run": float(known.mean())}
        if not reference_moves(reference_m[known]):
            tracking["fit_pct"] = tracking["peak_pct"] = None   # shares of a range the reference does not have
    return {"topic": topic, "samples": int(t.size),
            "rate_hz": 1.0 / float(np.median(np.diff(t))) if t.size > 1 else None,
            "duration_s": float(t[-1] - t[0]), "command_v": [float(v.min()), float(v.max())],
            "position_um": [float(y.min() * 1e6), float(y.max() * 1e6)], "tracking": tracking,
            "steps": [{"at_s": float(s.time_s - t[0]), "start_um": float(s.start_um), "end_um": float(s.end_um),
                       "settling_time_s": float(s.settling_time_s) if s.settling_time_s < s.hold_s - 1e-9 else None,
                       "hold_s": float(s.hold_s), "overshoot_pct": float(s.overshoot_pct)} for s in steps]}


def default_figures_dir(bag: str) -> Path:
    """BAG_plots beside the bag, named as the user named the bag (relative stays relative)."""
    path = Path(bag)
    if path.name in ("", ".", ".."):
        path = path.resolve()
    return path.with_name(path.name + "_plots")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="valve_plot", description=__doc__.split("\n\n")[0])
    ap.add_argument("bag", help="bag directory (valve_record, valve_identification, ros2 bag record)")
    ap.add_argument("--out", help="directory for the PNGs (default: BAG_plots next to the bag)")
    ap.add_argument("--topic", help="samples topic (default: the one named .../samples)")
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object (the PNGs are "
                    "still written where matplotlib is installed)")
    add_window_arguments(ap, "plot this stretch of the run only")
    args = ap.parse_args(argv)
    window = window_from(ap, args)
    try:
        rows, ref_t, ref_m, topic = read_run(args.bag, args.topic, window)
    except BagError as exc:
        print(f"valve_plot: {exc}", file=sys.stderr)
        return 2
    reference = reference_on_samples(rows[:, 0], align_jumps(rows[:, 0], rows[:, 1], ref_t, ref_m), ref_m)
    steps = find_steps(rows[:, 0], rows[:, 2], reference)
    out = Path(args.out) if args.out else default_figures_dir(args.bag)
    if args.json:
        try:
            from ..io.plots import write_run
            written = write_run(rows[:, 0], rows[:, 1], rows[:, 2], reference, out,
                                title=f"{Path(args.bag).name} ({topic})")
        except RuntimeError:  # no matplotlib: the numbers without figures
            written = []
        print(json.dumps({**run_figures(rows, reference, topic, steps), "window": window.as_dict(),
                          "figures": written}))
        return 0
    for line in summary_lines(rows, reference, topic, window):
        print(line)
    if steps:
        print(f"steps (a change >= {STEP_MIN_JUMP_M * 1e6:g} um held >= {STEP_MIN_HOLD_S * 1e3:g} ms; "
              "settling in the 5 % band, from the moment the reference changed):")
        print(f"{'at [s]':>8} {'step [um]':>18} {'settling [ms]':>14} {'overshoot [%]':>14}")
        for s in steps:
            settled = s.settling_time_s < s.hold_s - 1e-9
            settling = f"{s.settling_time_s * 1e3:14.1f}" if settled else f"{'> ' + format(s.hold_s * 1e3, '.0f'):>14}"
            print(f"{s.time_s - rows[0, 0]:8.2f} {round(s.start_um, 2) + 0.0:7.2f} -> {round(s.end_um, 2) + 0.0:7.2f} {settling} "
                  f"{s.overshoot_pct:14.2f}")
    elif np.isfinite(reference).any():
        print("no steps in the reference")
    try:
        from ..io.plots import write_run
        written = write_run(rows[:, 0], rows[:, 1], rows[:, 2], reference, out, title=f"{Path(args.bag).name} ({topic})")
    except RuntimeError as exc:  # no matplotlib
        print(f"valve_plot: no figures: {exc}", file=sys.stderr)
        return 1
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
