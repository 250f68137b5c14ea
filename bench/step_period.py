"""Table 1's gains at another control period (no ROS; deterministic; a few seconds).

    python bench/step_period.py [--sets pid_hc_5,ff_pid_1] [--step-um -20]

The paper tuned its gains for a 10 kHz loop; a rig run through ROS across processes runs at 1-2 kHz.  For each
gain set: a step from 0 um (2 ms ramp) on the default simulated valve (sampled at 10 kHz), with the controller
running every 0.1 ms and every 1 ms; settling time (5 % band) and overshoot, as valve_plot reports them.
"""
from __future__ import annotations

import argparse

import numpy as np

from piezo_valve_ros.core import step_metrics
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import ControllerConfig, ValveController, gain_set

PERIODS_S = (1e-4, 1e-3)
RAMP_S = 2e-3


def step_at_period(name: str, period_s: float, step_um: float, hold_s: float = 0.3) -> tuple[float, float]:
    """(settling time [s], overshoot [%]) of a step of ``step_um`` from 0 with the gain set ``name``."""
    sim_config = ValveSimConfig()
    samples_per_period = int(round(period_s / sim_config.dt))
    strategy, gains = gain_set(name)
    ctl = ValveController(ControllerConfig(strategy=strategy, gains=gains, dt=period_s))
    sim = SimulatedValve(sim_config)
    y = sim.step(sim_config.initial_voltage_v)
    n, k0 = int(round(2 * hold_s / period_s)), int(round(hold_s / period_s))
    ramp_n = max(int(round(RAMP_S / period_s)), 1)
    ref = np.zeros(n)
    ref[k0:] = step_um * 1e-6
    ref[k0:k0 + ramp_n] = step_um * 1e-6 * np.arange(1, ramp_n + 1) / ramp_n
    positions = np.empty(n)
    for k in range(n):
        v = ctl.step(ref[k], y)
        for _ in range(samples_per_period):
            y = sim.step(v)
        positions[k] = y
    m = step_metrics(positions, k0, 0.0, step_um, period_s)
    return m.settling_time_s, m.overshoot_pct


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="pid_hc_5,ff_pid_1", help="Table 1 gain sets, comma-separated")
    ap.add_argument("--step-um", type=float, default=-20.0)
    args = ap.parse_args(argv)
    print(f"step 0 -> {args.step_um:g} um, 2 ms ramp, default simulated valve (10 kHz samples):")
    print(f"{'gain set':>12} {'period':>8} {'settling [ms]':>14} {'overshoot [%]':>14}")
    for name in args.sets.split(","):
        for period in PERIODS_S:
            settling, overshoot = step_at_period(name.strip(), period, args.step_um)
            print(f"{name:>12} {period * 1e3:6.1f} ms {settling * 1e3:14.1f} {overshoot:14.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
