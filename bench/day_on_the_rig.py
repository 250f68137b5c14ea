"""A day on the rig: a valve that drifts over 20 min of everyday operation, with the monitor off and on.

    python bench/day_on_the_rig.py [--minutes 20] [--out docs/results/day_on_the_rig]

The simulated valve (the paper's GPIM and G_v, LVDT noise) loses 8 % of its gain and its offset rises by 2 um over
the run, smoothly (an exponential approach from the start, 95 % of it by the end), while the controller follows
levels and slow sines (a new stretch every minute).  Under OL HC and under PID HC, each twice:

* monitor off: the controller keeps the model it started with;
* monitor on: ``HealthMonitor`` judges the applied voltage against the model in force (20 s windows every 5 s) and
  ``RefitPolicy`` (``refit_when: warn``) pushes what the operating data determine (an offset; a gain change the
  window's held-out part confirms) to the controller, each push checked on the next window and undone where worse.
  A push takes effect at the end of the 5 s chunk its verdict closes (the node's latency is well under that).

It runs the core in lockstep (controller and valve stepped together, faster than real time: no ROS) and prints
and writes (``--out``/monitor_day.md, monitor_day.png where matplotlib is there) the tracking RMS [um] of the first
and the last two minutes, their ratio, and every push with its evidence.  Then it writes the day's bag (OL HC with
the monitor on: the samples as the hardware node publishes them, and the monitor's pushes as ``~/pushes`` rows) and
runs ``valve_identify``'s library face on the whole bag: its first ``MAX_ANALYSED_S`` for the model's fast parts,
all of it for the slow trend, which must be named ``drift``.
"""
import argparse
import math
import os
import sys
import tempfile
import time
from dataclasses import replace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "test"))

from valve_battery import staircase_and_sines_um  # noqa: E402  (test helpers: the operating reference)
from piezo_valve_ros.core.control import CompensationModel  # noqa: E402
from piezo_valve_ros.core.control import STRATEGIES, ControllerConfig, PIDGains, ValveController
from piezo_valve_ros.core.monitoring import HealthLimits, HealthMonitor, Level  # noqa: E402
from piezo_valve_ros.core.monitoring import PUSH_COLUMNS, UNDO, RefitPolicy, push_row  # noqa: E402
from piezo_valve_ros.core.sim import run_closed_loop  # noqa: E402
from piezo_valve_ros.core.sim import DriftParams, SensorParams, SimulatedValve, ValveSimConfig  # noqa: E402
from piezo_valve_ros.identify import identify_bags  # noqa: E402
from piezo_valve_ros.io import SAMPLES_TYPE, BagRecorder, qos_profile, serialize_samples  # noqa: E402

DT = 1e-3
CHUNK_S = 5.0                  # the loop runs this long between the monitor's looks (its step)
GAIN_LOSS = 0.08               # over the run ...
OFFSET_RISE_UM = 2.0           # ... and this offset rise
APPROACH = 3.0                 # the run lasts this many time constants of the exponential approach (95 %)
EDGE_S = 120.0                 # tracking is compared over the first and the last this long
PID_HC = PIDGains(0.4823, 213.8982, 0.0)
STRATEGY_GAINS = {"ol_hc": None, "pid_hc": PID_HC}


def drift_for(seconds: float) -> DriftParams:
    """The day's drift: GAIN_LOSS and OFFSET_RISE_UM reached at the end of ``seconds`` of an exponential approach."""
    reached = 1.0 - math.exp(-APPROACH)
    return DriftParams(True, offset_um=OFFSET_RISE_UM / reached, gain_change=-GAIN_LOSS / reached,
                       time_constant_s=seconds / APPROACH, start_s=0.0)


def day(strategy: str, monitor_on: bool, seconds: float, seed: int = 11) -> dict:
    """One run: the tracking error [um] per sample, the pushes and the verdicts."""
    config = replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=True, sensor=SensorParams(),
                     drift=drift_for(seconds), seed=seed)
    valve = SimulatedValve(config)
    model = CompensationModel()
    controller = ValveController(ControllerConfig(strategy=strategy, gains=STRATEGY_GAINS[strategy] or PID_HC, dt=DT),
                                 model)
    controller.reset(5.0)
    monitor = HealthMonitor(model, DT, HealthLimits(step_s=CHUNK_S)) if monitor_on else None
    policy = RefitPolicy(Level.WARN, HealthLimits().window_s)
    state = {"enabled": 1.0, "guard_active": 0.0, "strategy_index": float(STRATEGIES.index(strategy))}
    reference = np.concatenate([staircase_and_sines_um(seed + k, DT, 60.0)
                                for k in range(int(math.ceil(seconds / 60.0)))])[:int(round(seconds / DT))]
    chunk = int(round(CHUNK_S / DT))
    errors, pushes, verdicts, rows, position = [], [], [], [], None
    for start in range(0, reference.size, chunk):
        ref_um = reference[start:start + chunk]
        rec = run_closed_loop(valve, controller, ref_um * 1e-6,
                              **({} if position is None else {"first_position_m": position}))
        position = valve.step(rec.command_v[-1])   # the answer to the chunk's last command
        measured = np.append(rec.position_m[1:], position)
        errors.append(ref_um - measured * 1e6)
        t = (start + np.arange(ref_um.size)) * DT
        rows.append(np.column_stack((t, rec.command_v, measured)))
        if monitor is None:
            continue
        for health in monitor.add(np.column_stack((t, rec.command_v, measured))):
            verdicts.append(health)
            decision = policy.decide(health, state, monitor.model)
            if decision is None:
                continue
            if decision.kept:
                pushes[-1]["checked"] = decision.kept
            if decision.pushes:
                if decision.kind == UNDO and pushes:
                    pushes[-1]["checked"] = "undone: " + decision.evidence
                pushes.append({"t_s": health.end_s, "kind": decision.kind, "gain_change": decision.gain_change,
                               "row": push_row(health, decision, monitor.model),
                               "offset_change_um": decision.offset_change_um, "evidence": decision.evidence,
                               "checked": ""})
                controller.set_model(decision.model)
                monitor.set_model(decision.model)
                policy.pushed(True)
    return {"error_um": np.concatenate(errors), "pushes": pushes, "verdicts": verdicts, "rows": np.concatenate(rows)}


def write_day_bag(path: str, run: dict) -> None:
    """The day as a rig records it: ``samples`` (time [s], voltage [V], position [m]; 100 rows a message, as the
    hardware node publishes at 1 kHz) and the monitor's ``~/pushes`` rows (PUSH_COLUMNS) when they were made."""
    samples, pushes = "/valve1/samples", "/valve1/valve_monitor/pushes"
    stamp = 1_700_000_000_000_000_000
    rec = BagRecorder(path, {samples: (SAMPLES_TYPE, qos_profile(True, 100)),
                             pushes: (SAMPLES_TYPE, qos_profile(True, 10))}, segment_s=float("inf"), clock=lambda: 0.0)
    due = iter(run["pushes"])
    nxt = next(due, None)
    rows = run["rows"]
    for i in range(0, rows.shape[0], 100):
        block = rows[i:i + 100]
        rec.write(samples, stamp + int(round(block[-1, 0] * 1e9)), serialize_samples(block))
        while nxt is not None and nxt["t_s"] <= block[-1, 0]:
            rec.write(pushes, stamp + int(round(nxt["t_s"] * 1e9)),
                      serialize_samples(np.array([nxt["row"]]), ",".join(PUSH_COLUMNS)))
            nxt = next(due, None)
    rec.close()


def identify_the_day(run: dict, keep: str | None) -> list[str]:
    """Write the day's bag (to ``keep``, or a temporary directory) and identify on all of it; the lines to report."""
    with tempfile.TemporaryDirectory() as tmp:
        path = keep or os.path.join(tmp, "day")
        write_day_bag(path, run)
        t0 = time.perf_counter()
        analysis, _ = identify_bags(path, log=lambda s: None)
        took = time.perf_counter() - t0
    r = analysis.report
    w = r.whole_record
    lines = [f"The day's bag (OL HC, monitor on; {run['rows'].shape[0]} samples at {1 / DT:.0f} Hz"
             + (f", kept at {keep}" if keep else "") + f"), identified whole by valve_identify ({took:.0f} s):", "",
             "```", r.summary]
    if w is not None:
        lines += [f"whole record {w.from_s:.0f}..{w.to_s:.0f} s at {w.rate_hz:.0f} Hz: drift "
                  f"{'named' if w.drift_added else 'not named'} ({w.evidence}); the trend {w.peak_to_peak_um:.2f} um "
                  f"peak to peak, departing from its start from {w.onset_s:.0f} s",
                  "error RMS at the analysis rate by tenth of the day, without -> with the trend [um]: "
                  + ", ".join(f"{s.rms_um:.3f} -> {s.rms_with_trend_um:.3f}" for s in w.stretches)]
    lines += [f"{key}: {text}" for key, text in r.figures_from.to_json().items() if text] + ["```"]
    return lines


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=20.0, help="length of the day [min] (default 20)")
    ap.add_argument("--out", default=os.path.join(HERE, "..", "docs", "results", "day_on_the_rig"))
    ap.add_argument("--bag", help="keep the day's bag here (default: a temporary directory, removed after)")
    args = ap.parse_args()
    seconds = 60.0 * args.minutes
    edge = int(round(EDGE_S / DT))
    lines = [f"Output of `python bench/day_on_the_rig.py --minutes {args.minutes:g}` (the core in lockstep, "
             f"{1 / DT:.0f} Hz; the valve loses {100 * GAIN_LOSS:.0f} % of its gain and its offset rises "
             f"{OFFSET_RISE_UM:g} um over the run):", "", "```",
             f"{'strategy':8s} {'monitor':8s} {'first 2 min':>12s} {'last 2 min':>11s} {'last/first':>10s} "
             f"{'pushes':>6s} {'undone':>6s} {'run s':>6s}"]
    runs = {}
    for strategy in STRATEGY_GAINS:
        for monitor_on in (False, True):
            t0 = time.perf_counter()
            run = day(strategy, monitor_on, seconds)
            took = time.perf_counter() - t0
            runs[(strategy, monitor_on)] = run
            first, last = rms(run["error_um"][:edge]), rms(run["error_um"][-edge:])
            undone = sum(1 for p in run["pushes"] if p["kind"] == UNDO)
            lines.append(f"{strategy:8s} {'on' if monitor_on else 'off':8s} {first:10.3f} um {last:8.3f} um "
                         f"{last / first:9.2f}x {len(run['pushes']):6d} {undone:6d} {took:6.0f}")
            print(lines[-1], flush=True)
    lines += ["```", "", "Pushes (monitor on):", "", "```"]
    for (strategy, monitor_on), run in runs.items():
        for p in run["pushes"]:
            lines.append(f"{strategy:6s} {p['t_s']:7.1f} s {p['kind']:6s} "
                         + (f"gain {100 * p['gain_change']:+.2f} %: " if p["gain_change"] is not None else
                            f"offset {p['offset_change_um']:+.3f} um: " if p["offset_change_um"] is not None else "")
                         + p["evidence"] + (f"; then: {p['checked']}" if p["checked"] else "; then: not checked "
                                            "(the run ended first, or a newer push replaced it)"))
    lines.append("```")
    bad = [(s, p) for (s, on), run in runs.items() for p in run["pushes"]
           if "made things worse" in p["checked"] and not p["checked"].startswith("undone")]
    lines += ["", f"Pushes whose next window was worse and that were not undone: {len(bad)}.", ""]
    lines += identify_the_day(runs[("ol_hc", True)], args.bag)
    print("\n".join(lines[-8:]))
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "monitor_day.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines[lines.index("Pushes (monitor on):"):]))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return 0
    fig, axes = plt.subplots(len(STRATEGY_GAINS), 1, figsize=(10, 6), sharex=True)
    for ax, strategy in zip(axes, STRATEGY_GAINS):
        for monitor_on in (False, True):
            e = runs[(strategy, monitor_on)]["error_um"]
            n = int(round(5.0 / DT))
            windowed = np.sqrt(np.mean(np.square(e[:e.size // n * n].reshape(-1, n)), axis=1))
            ax.plot(np.arange(windowed.size) * 5.0 / 60.0, windowed, label=f"monitor {'on' if monitor_on else 'off'}")
        for p in runs[(strategy, True)]["pushes"]:
            ax.axvline(p["t_s"] / 60.0, color="grey", lw=0.5)
        ax.set_ylabel(f"{strategy}: tracking RMS [um]")
        ax.legend()
    axes[-1].set_xlabel("time [min] (5 s RMS; grey: pushes)")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "monitor_day.png"), dpi=100)
    return 0


if __name__ == "__main__":
    sys.exit(main())
