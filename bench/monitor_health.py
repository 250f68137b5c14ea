"""The health monitor on long simulated operation: false alarms, detection delay, CPU and memory.

    python bench/monitor_health.py [--hours 1.0] [--out docs/results/monitor]

1. A nominal valve (the paper's GPIM and G_v, LVDT noise) under PID HC following levels and slow sines for
   ``--hours``, its model in force exact: every verdict that is not OK is a false alarm.
2. The same valve with a 1.5 um drift setting in after a third of the run (60 s time constant): the delay from
   the onset to the first WARN and ERROR, and what the residual was said to resemble.
3. CPU: process time of ``HealthMonitor.add`` per second of operation, as a share of one core, at 1 kHz and
   10 kHz samples, nominal (no search) and drifting (the subset search on every verdict), quiet and with two
   busy loops beside; memory held.
Writes health.md and health_run.png (residual over the drifting run with the verdicts marked) to ``--out``.
"""
import argparse
import os
import sys
import time
from dataclasses import replace

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "test"))

from valve_battery import staircase_and_sines_um  # noqa: E402  (test helpers: the operating reference)
from harness import loaded  # noqa: E402
from piezo_valve_ros.core.control import CompensationModel  # noqa: E402
from piezo_valve_ros.core.control import ControllerConfig, PIDGains, ValveController  # noqa: E402
from piezo_valve_ros.core.monitoring import HealthLimits, HealthMonitor, Level  # noqa: E402
from piezo_valve_ros.core.sim import run_closed_loop  # noqa: E402
from piezo_valve_ros.core.sim import DriftParams, SensorParams, SimulatedValve, ValveSimConfig  # noqa: E402

PID_HC = PIDGains(0.4823, 213.8982, 0.0)


def operation(seconds: float, dt: float, drift: DriftParams = DriftParams(), seed: int = 7,
              config: ValveSimConfig = None) -> np.ndarray:
    """``samples`` rows of the simulated valve (default: the paper's GPIM and G_v with LVDT noise; ``config``
    another) under PID HC, built a minute at a time (the controller and the valve carry on between minutes)."""
    base = replace(ValveSimConfig(dt=dt).ideal(), dynamics_enabled=True, sensor=SensorParams()) if config is None \
        else config
    config = replace(base, drift=drift, seed=seed)
    valve = SimulatedValve(config)
    controller = ValveController(ControllerConfig(strategy="pid_hc", gains=PID_HC, dt=dt), CompensationModel())
    controller.reset(5.0)
    out, position, minutes = [], None, int(np.ceil(seconds / 60.0))
    for k in range(minutes):
        ref = staircase_and_sines_um(seed + k, dt, 60.0) * 1e-6
        rec = run_closed_loop(valve, controller, ref, **({} if position is None else {"first_position_m": position}))
        position = float(rec.position_m[-1])
        n = rec.command_v.size - 1
        t = (k * 60.0 / dt + np.arange(n)) * dt
        out.append(np.column_stack((t, rec.command_v[:-1], rec.position_m[1:])))
    return np.concatenate(out)[:int(round(seconds / dt))]


def monitored(rows: np.ndarray, dt: float, chunk_s: float = 0.1) -> tuple[list, float, tuple, float]:
    """Verdicts, process seconds spent in the monitor, what it held at the end, wall seconds spent."""
    monitor = HealthMonitor(CompensationModel(), dt, HealthLimits())
    chunk = max(int(round(chunk_s / dt)), 1)
    verdicts, cpu, wall = [], 0.0, 0.0
    for k in range(0, len(rows), chunk):
        t0, w0 = time.process_time(), time.perf_counter()
        verdicts += monitor.add(rows[k:k + chunk])
        cpu += time.process_time() - t0
        wall += time.perf_counter() - w0
    return verdicts, cpu, monitor.held, wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--hours", type=float, default=1.0, help="length of the long runs [h] (default 1)")
    ap.add_argument("--out", default=os.path.join(HERE, "..", "docs", "results", "monitor"))
    args = ap.parse_args()
    seconds = 3600.0 * args.hours
    lines = [f"Written by `python bench/monitor_health.py --hours {args.hours:g}` (simulated operation: the paper's "
             "valve with G_v and LVDT noise under PID HC following levels and slow sines; the monitor's default "
             f"limits: {HealthLimits()}).", ""]
    started = time.monotonic()
    nominal = operation(seconds, 1e-3)
    health, cpu, held, wall = monitored(nominal, 1e-3)
    alarms = [h for h in health if h.level is not Level.OK]
    lines += ["## False alarms", "",
              f"Nominal valve, {seconds / 3600:g} h at 1 kHz: {len(health)} verdicts, {len(alarms)} not OK "
              f"({100 * len(alarms) / max(len(health), 1):.2f} %); largest structured residual "
              f"{max(h.ratio for h in health):.2f}x the noise (WARN at {HealthLimits().warn_ratio:g}x).", ""]
    print(lines[-2], flush=True)
    onset = seconds / 3.0
    drift = DriftParams(True, offset_um=1.5, gain_change=0.0, time_constant_s=60.0, start_s=onset)
    drifting = operation(seconds, 1e-3, drift)
    dhealth, dcpu, dheld, dwall = monitored(drifting, 1e-3)
    first = {lv: next((h for h in dhealth if h.end_s > onset and h.level is lv), None) for lv in (Level.WARN, Level.ERROR)}
    before = [h for h in dhealth if h.end_s <= onset and h.level is not Level.OK]
    named = [h.resembles for h in dhealth if h.level is Level.ERROR]
    lines += ["## Detection", "",
              f"A 1.5 um drift sets in at {onset:.0f} s (60 s time constant): {len(before)} verdicts not OK before it; "
              + ", ".join(f"first {lv.name} {h.end_s - onset:.0f} s after the onset" if h else f"no {lv.name}"
                          for lv, h in first.items())
              + f"; the ERROR verdicts name: {sorted(set(n.split(' of ')[0] for n in named))} "
              f"(last: {named[-1] if named else '-'}).", ""]
    print(lines[-2], flush=True)
    rows = [("1 kHz, nominal", cpu, wall, seconds, held),
            ("1 kHz, drifting (search on every verdict after the onset)", dcpu, dwall, seconds, dheld)]
    _, lcpu, lheld, lwall = loaded(lambda: monitored(drifting, 1e-3))
    rows.append(("1 kHz, drifting, two busy loops beside", lcpu, lwall, seconds, lheld))
    fast_s = 120.0
    for label, d in (("10 kHz, nominal", DriftParams()),
                     ("10 kHz, drifting from 30 s", replace(drift, start_s=30.0, time_constant_s=5.0))):
        rows10 = operation(fast_s, 1e-4, d)
        _, c, h, w = monitored(rows10, 1e-4)
        rows.append((label, c, w, fast_s, h))
        _, c, h, w = loaded(lambda: monitored(rows10, 1e-4))
        rows.append((label + ", two busy loops beside", c, w, fast_s, h))
    lines += ["## CPU and memory", "",
              "Process and wall time spent in `HealthMonitor.add` per second of operation (this machine: 2 cores, "
              "shared; one run each, quiet and with two busy loops beside), and what the monitor held at the end "
              "(rows, turning points):", "",
              "| samples | operation [s] | monitor CPU [s] | share of one core | wall [s] | rows held | turning points |",
              "|---|---|---|---|---|---|---|"]
    for label, c, w, s, h in rows:
        lines.append(f"| {label} | {s:.0f} | {c:.2f} | {100 * c / s:.2f} % | {w:.2f} | {h[0]} | {h[1]} |")
    lines.append("")
    print("\n".join(lines[-len(rows) - 2:]), flush=True)
    os.makedirs(args.out, exist_ok=True)
    try:
        from piezo_valve_ros.io import require
        plt = require()
        fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
        t = np.array([h.end_s for h in dhealth]) / 60.0
        ax.plot(t, [h.residual_mean_um for h in dhealth], lw=0.8, label="window's mean residual [um]")
        ax.plot(t, [h.structured_rms_um for h in dhealth], lw=0.8, label="structured residual RMS [um]")
        ax.axvline(onset / 60.0, color="0.5", ls=":", label="drift sets in")
        ax.set_ylabel("um")
        ax.legend(loc="upper left")
        colours = {Level.OK: "tab:green", Level.WARN: "tab:orange", Level.ERROR: "tab:red", Level.STALE: "0.6"}
        for lv, colour in colours.items():
            sel = [i for i, h in enumerate(dhealth) if h.level is lv]
            ax2.scatter(t[sel], [dhealth[i].ratio for i in sel], s=6, color=colour, label=lv.name)
        ax2.axhline(HealthLimits().warn_ratio, color="tab:orange", lw=0.6)
        ax2.axhline(HealthLimits().error_ratio, color="tab:red", lw=0.6)
        ax2.set_yscale("log")
        ax2.set_ylabel("structured residual / noise")
        ax2.set_xlabel("time [min]")
        ax2.legend(loc="upper left")
        fig.suptitle(f"valve_monitor over {seconds / 3600:g} h of simulated operation, a drift setting in")
        fig.tight_layout()
        fig.savefig(os.path.join(args.out, "health_run.png"), dpi=110)
        lines += ["![residual and verdicts over the drifting run](health_run.png)", ""]
    except RuntimeError as exc:
        print(f"no figure: {exc}")
    with open(os.path.join(args.out, "health.md"), "w") as fh:
        fh.write("# Valve health monitor\n\n" + "\n".join(lines))
    print(f"wrote {args.out}/health.md ({time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
