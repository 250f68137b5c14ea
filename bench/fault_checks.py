"""The hardware's sample checks (``piezo_valve_ros.backends.faults``) on long healthy operation: do they ever trip?

    python bench/fault_checks.py [--hours 1.0] [--markdown docs/results/fault_checks.md]

The simulated valve under PID HC following levels and slow sines (bench/monitor_health.py's operation, 1 kHz
samples) for ``--hours``, three ways: with the LVDT's noise, without it (quantised only: readings repeat while
the valve rests), and with every effect of the default simulated valve (creep, saturation, slew limit, rate
dependence, noise).  Each period's rows go through ``SampleCheck`` as ``valve_hardware`` checks them; a trip is
a false alarm.  Also the nearest approach to a stuck-sensor trip: the longest stretch of identical readings, and the longest
a reading stayed unchanged after the command had moved over ``fault.stuck_command_span_v`` (what the check
compares with ``fault.stuck_time_s``).
"""
import argparse
import os
import sys
import time
from dataclasses import replace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "..", "test"))

from monitor_health import operation  # noqa: E402  (the operating run)
from piezo_valve_ros.core.sim import SensorParams, ValveSimConfig  # noqa: E402
from piezo_valve_ros.backends import FaultLimits, SampleCheck  # noqa: E402

DT = 1e-3


def nearest_stuck(rows: np.ndarray, span_v: float) -> tuple[float, float]:
    """(longest stretch of identical readings [s], and the longest any reading stayed unchanged after the command
    had moved over ``span_v`` within its stretch [s]: what the stuck-sensor check compares with its time)."""
    same = np.r_[False, np.diff(rows[:, 2]) == 0.0]
    starts = np.flatnonzero(~same)
    ends = np.r_[starts[1:], len(rows)]
    longest = float(np.max(ends - starts) - 1) * DT
    after_move = 0.0
    for a, b in zip(starts, ends):
        if b - a < 3:
            continue
        command = rows[a:b, 1]
        span = np.maximum.accumulate(command) - np.minimum.accumulate(command)
        moved = np.flatnonzero(span >= span_v)
        if moved.size:
            after_move = max(after_move, (b - 1 - (a + int(moved[0]))) * DT)
    return longest, after_move


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--markdown", help="also write the table here")
    args = ap.parse_args()
    seconds = args.hours * 3600.0
    limits = FaultLimits()
    plain = replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=True, sensor=SensorParams())
    runs = (("LVDT noise", {}),
            ("no noise, quantised 5 nm", {"sensor": SensorParams(noise_enabled=False)}),
            ("every default effect", "default"))
    lines = [f"Output of `python bench/fault_checks.py --hours {args.hours:g}`: the simulated valve under PID HC following "
             f"levels and slow sines, {args.hours:g} h at 1 kHz each; every period's rows through the hardware's "
             f"sample checks with the default limits (stuck: {limits.stuck_time_s:g} s of identical readings since "
             f"the command has moved over {limits.stuck_command_span_v:g} V; positions beyond "
             f"{1e6 * limits.position_limit_m:.0f} um; non-finite).", "",
             "| run | samples | trips | longest identical readings [s] | longest unchanged after a "
             f"{limits.stuck_command_span_v:g} V move [s] | check cost [us/period] |",
             "|---|---|---|---|---|---|"]
    for name, change in runs:
        rows = operation(seconds, DT, config=(ValveSimConfig(dt=DT) if change == "default" else replace(plain, **change)))
        check = SampleCheck(limits)
        trips = []
        started = time.process_time()
        for k in range(len(rows)):
            problem = check.check(rows[k:k + 1])
            if problem is not None:
                trips.append((k * DT, problem))
                check.reset()
        cost = (time.process_time() - started) / len(rows) * 1e6
        longest, after_move = nearest_stuck(rows, limits.stuck_command_span_v)
        lines.append(f"| {name} | {len(rows)} | {len(trips)} | {longest:.3f} | {after_move:.3f} | {cost:.1f} |")
        print(lines[-1], *(f"  trip at {t:.1f} s: {p}" for t, p in trips[:5]), sep="\n", flush=True)
    print("\n".join(lines))
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
