"""What a busy computer does to the loop, and what the oscillation guard makes of it (no ROS; deterministic).

    python bench/loop_delay.py [--markdown docs/results/loop_delay.md]

A 1 kHz loop on the simulated valve tracks a 2 Hz, 30 um sine; for 0.8 s in the middle of a 3 s run every
measurement reaches the controller ``d`` periods late (two processes on a loaded machine: the position and
the command wait in queues).  Printed per Table 1 set and delay: the peak tracking error, the share of periods
more than ``FAR_OFF_UM`` off the demand and the share with the command on a rail, during the episode and the
0.5 s after it, and the guard's trips.
The guard cannot be switched off in the controller; the "unguarded" rows run a copy whose guard is
disabled, to show what it prevents.
"""
from __future__ import annotations

import argparse
import numpy as np

from piezo_valve_ros.core.sim import run_delayed_loop
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import ControllerConfig, ValveController, gain_set

from harness import Lines

EPISODE_S = (1.0, 1.8)
FAR_OFF_UM = 10.0   # a tracking error beyond this is counted [um] (the sine's amplitude is 30 um)


class UnguardedController(ValveController):
    """For comparison only: the same controller with its oscillation guard disabled."""

    def _guard(self) -> None:
        pass


def run(cls, gains_name: str, delay: int, dt: float = 1e-3, duration_s: float = 3.0):
    cfg = ValveSimConfig(seed=0)
    strategy, gains = gain_set(gains_name)
    ctl = cls(ControllerConfig(strategy=strategy, gains=gains, dt=dt))
    t = np.arange(int(duration_s / dt)) * dt
    ref = 30.0 * np.sin(2 * np.pi * 2.0 * t)
    rec = run_delayed_loop(SimulatedValve(cfg), ctl, ref * 1e-6,
                           lambda k: delay if EPISODE_S[0] <= t[k] < EPISODE_S[1] else 0,
                           samples_per_period=int(round(dt / cfg.dt)))
    y_um, v_all = rec.position_m * 1e6, rec.command_v
    window = (t >= EPISODE_S[0]) & (t < EPISODE_S[1] + 0.5)
    rails = (v_all <= 0.0) | (v_all >= 10.0)
    err = np.abs(y_um - ref)[window]
    return float(err.max()), float(np.mean(err > FAR_OFF_UM)), float(rails[window].mean()), ctl.guard_trips


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default="pid_hc_5,pid_1,ff_pid_1", help="Table 1 gain sets")
    ap.add_argument("--delays", default="0,1,2,3,4,6", help="extra delay during the episode [periods]")
    ap.add_argument("--markdown", metavar="FILE", help="also write what is printed here")
    args = ap.parse_args(argv)
    print = Lines()   # noqa: A001  (printed and kept for --markdown)
    print(f"1 kHz loop, 2 Hz 30 um sine, delay episode {EPISODE_S[0]}-{EPISODE_S[1]} s; figures over the episode "
          f"and 0.5 s after it")
    far = f"> {FAR_OFF_UM:g} um"
    print(f"{'set':10s} {'delay':>5s}   {'unguarded: peak err':>20s} {far:>9s} {'on rails':>9s}   "
          f"{'guarded: peak err':>18s} {far:>9s} {'on rails':>9s} {'trips':>6s}")
    for name in args.sets.split(","):
        for d in (int(x) for x in args.delays.split(",")):
            e0, f0, r0, _ = run(UnguardedController, name, d)
            e1, f1, r1, trips = run(ValveController, name, d)
            print(f"{name:10s} {d:5d}   {e0:17.2f} um {100 * f0:7.1f} % {100 * r0:7.1f} %   "
                  f"{e1:15.2f} um {100 * f1:7.1f} % {100 * r1:7.1f} % {trips:6d}")
    if args.markdown:
        print.write_markdown(args.markdown, "bench/loop_delay.py", " (deterministic: no ROS, simulated time)")


if __name__ == "__main__":
    main()
