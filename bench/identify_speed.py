"""Identification speed: a training + validation bag pair through ``identify_bags`` (bag reading included).

    python bench/identify_speed.py [--skip-straightforward] [--load] [--markdown docs/results/identify_speed.md]

Target (issue 9): under 10 s per pair of 50-60 s records at 2-10 kHz.  Two valves of the package's
simulator: the default one (creep, loop-end flattening, G_v, noise) and one with drift and an asymmetric
envelope as well (more effects, more refits).  Beside ours, in the same run:

* straightforward, full rate: the same algorithm with every fit at the record's own rate (no block means);
* straightforward, exact search: every subset of the catalogue refitted exactly instead of scored by one
  linear solve each from the baseline (on the 2 kHz pair).

Ours is also timed with its refits on one thread (``analyse(threads=1)``, without bag reading).  Then the
records users have (``analyse`` on each, no bag reading): closed-loop operation of a creeping valve under
PI and PID HC (train + validate, and held-out tail), a +-150 V drive warming up, and the measured piezo
record of ``test/data/smart_hysteresis`` at its own 5 kHz.
``--load`` repeats the measurement of ours (bag pairs and users' records) with two busy loops running beside
it (this machine has two cores).  Compare ratios within one run: the machine is shared.
"""
import argparse
import itertools
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from piezo_valve_ros.io import read_samples, write_samples_bag
from piezo_valve_ros.runtime import keep_freed_memory
from piezo_valve_ros.core.identification import CATALOGUE
from piezo_valve_ros.core.sim import simulate_rows
from piezo_valve_ros.core.identification import FitCache, fit_model
from piezo_valve_ros.core.identification import Record
from piezo_valve_ros.core.identification import analyse
from piezo_valve_ros.core.sim import identification_voltage, validation_voltage
from piezo_valve_ros.core.sim import DriftParams, ValveSimConfig
from piezo_valve_ros.identify import identify_bags
from threadpoolctl import threadpool_limits

from harness import Lines, loaded

VALVES = {
    "default valve": ValveSimConfig(),
    "default + drift + asymmetric envelope": replace(ValveSimConfig(), drift=DriftParams(enabled=True),
                                                     descending_envelope=(0.95, 0.2)),
}


def make_pair(directory: Path, config: ValveSimConfig, dt: float, training_s: float = 40.0):
    cfg = replace(config, dt=dt)
    train, val = directory / "train", directory / "validate"
    write_samples_bag(train, simulate_rows(identification_voltage(dt, training_s), replace(cfg, seed=1)))
    write_samples_bag(val, simulate_rows(validation_voltage(dt, 40.0), replace(cfg, seed=2)))
    return train, val


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def exhaustive_exact(train: Record, validate: Record) -> list:
    """The straightforward search: from ``analyse``'s baseline, every subset of the catalogue refitted exactly
    (one after another, BLAS on one thread as in ``analyse``)."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _exhaustive_exact(train, validate)


def _exhaustive_exact(train: Record, validate: Record) -> list:
    a = analyse(train, validate)
    fit = a.split.fit
    effects = [e for e in (cls.prepare(fit, a.baseline.context(fit).H) for cls in CATALOGUE) if e is not None]
    cache = FitCache()
    scores = []
    for r in range(len(effects) + 1):
        for subset in itertools.combinations(effects, r):
            m = fit_model(fit, a.baseline, list(subset), cache=cache) if subset else a.baseline
            e = a.held_out_error(m)
            scores.append(([x.name for x in subset], float((e ** 2).mean() ** 0.5)))
    return scores


def users_records():
    """(label, train, validate or None) of the records users have (see the module docstring)."""
    import importlib.util
    import os
    import sys
    import numpy as np
    from piezo_valve_ros.core.control import PIDGains
    from piezo_valve_ros.core.sim import CreepParams, SensorParams
    test_dir = Path(__file__).resolve().parent.parent / "test"
    spec = importlib.util.spec_from_file_location("valve_battery", test_dir / "valve_battery.py")
    vb = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = vb
    spec.loader.exec_module(vb)
    plain = replace(ValveSimConfig(dt=1e-3).ideal(), dynamics_enabled=True, sensor=SensorParams())
    creep = replace(plain, creep=CreepParams(True, (0.03, 0.03, 0.03), (0.1, 1.0, 10.0)))
    out = []
    for strategy, gains in (("pid", PIDGains(0.5992, 237.2552, 0.0)), ("pid_hc", PIDGains(0.4823, 213.8982, 0.0))):
        train = Record.from_rows(vb.closed_loop_rows(creep, strategy, gains, 1))
        out.append((f"closed loop under {strategy}, creeping valve, train + validate", train,
                    Record.from_rows(vb.closed_loop_rows(creep, strategy, gains, 2))))
        out.append((f"closed loop under {strategy}, creeping valve, held-out tail", train, None))
    warm = vb.WIDE[[k for k in vb.WIDE if "warming" in k][0]]
    tv = vb.training_voltage(vb.DT)
    out.append(("+-150 V drive warming up, train + validate", Record.from_rows(warm.rows(vb.wide_drive(tv), 1)),
                Record.from_rows(warm.rows(vb.wide_drive(vb.validation_voltage_(vb.DT)), 2))))
    a = np.genfromtxt(os.path.join(test_dir, "data", "smart_hysteresis", "hysteresis_v_150_1hz.csv.xz"),
                      delimiter=",")[:, 1:]
    out.append(("measured piezo record, whole, 5 kHz, held-out tail", Record(a[:, 0], a[:, 2], a[:, 1]), None))
    return out


def timed_under_load(fn):
    """``timed(fn)`` with two busy loops running beside it (this machine has two cores)."""
    return loaded(lambda: timed(fn))


def main():
    keep_freed_memory()   # as valve_identify (runtime.memory)
    ap = argparse.ArgumentParser()
    ap.add_argument("--skip-straightforward", action="store_true")
    ap.add_argument("--load", action="store_true", help="also measure with two busy loops running")
    ap.add_argument("--markdown", metavar="FILE", help="also write what is printed here")
    args = ap.parse_args()
    print = Lines(timing=True)   # noqa: A001  (printed and kept for --markdown)

    with tempfile.TemporaryDirectory() as tmp:
        for rate_hz in (10000, 2000):
            dt = 1.0 / rate_hz
            for name, cfg in VALVES.items():
                d = Path(tmp) / f"{rate_hz}_{name.replace(' ', '_')}"
                d.mkdir()
                train, val = make_pair(d, cfg, dt)
                n = read_samples(train)[0].shape[0] + read_samples(val)[0].shape[0]
                t_ours, (analysis, _) = timed(lambda: identify_bags(train, val, log=lambda s: None))
                r = analysis.report.to_json()
                print(f"{rate_hz:5d} Hz, {name}: {n} samples in the pair")
                print(f"   ours                          {t_ours:6.2f} s  (target < 10 s): added {r['effects_added']}, "
                      f"held-out RMS {r['baseline']['validate']['rms_um']:.3f} -> {r['final']['validate']['rms_um']:.3f} um")
                tr = Record.from_rows(read_samples(train)[0])
                va = Record.from_rows(read_samples(val)[0])
                t_one, one = timed(lambda: analyse(tr, va, threads=1))
                same = one.report.to_json()["effects_added"] == r["effects_added"]
                print(f"   ours, refits on one thread    {t_one:6.2f} s  ({t_one / t_ours:.1f}x; same effects: {same})")
                if args.load:
                    t_load, _ = timed_under_load(lambda: identify_bags(train, val, log=lambda s: None))
                    print(f"   ours, two busy loops beside   {t_load:6.2f} s  ({t_load / t_ours:.1f}x the quiet run)")
                if args.skip_straightforward:
                    continue
                if rate_hz == 10000:
                    t_full, full = timed(lambda: analyse(tr, va, max_rate_hz=float("inf")))
                    print(f"   straightforward, full rate    {t_full:6.2f} s  -> ours is {t_full / t_ours:4.1f}x faster; "
                          f"added {full.report.to_json()['effects_added']}")
                else:
                    t_ex, scores = timed(lambda: exhaustive_exact(tr, va))
                    best = min(scores, key=lambda s: s[1])
                    print(f"   straightforward, exact search {t_ex:6.2f} s  -> ours is {t_ex / t_ours:4.1f}x faster; "
                          f"{len(scores)} exact refits, lowest held-out RMS {best[1]:.3f} um with {best[0]}")
    print("records users have (analyse, no bag reading; target < 10 s per pair):")
    for label, train, validate in users_records():
        n = len(train) + (len(validate) if validate is not None else 0)
        t, a = timed(lambda: analyse(train, validate))
        t_one, _ = timed(lambda: analyse(train, validate, threads=1))
        r = a.report.to_json()
        print(f"   {label}: {n} samples, {t:6.2f} s ({t_one:6.2f} s on one thread); added {r['effects_added']}, "
              f"held-out RMS {r['baseline']['validate']['rms_um']:.3f} -> {r['final']['validate']['rms_um']:.3f} um")
        if args.load:
            t_load, loaded = timed_under_load(lambda: analyse(train, validate))
            print(f"      two busy loops beside {t_load:6.2f} s ({t_load / t:.1f}x the quiet run; same effects: "
                  f"{loaded.report.to_json()['effects_added'] == r['effects_added']})")
    if args.markdown:
        print.write_markdown(args.markdown, "bench/identify_speed.py",
                             " (seconds on this shared 2-core machine; compare ratios within one run)")


if __name__ == "__main__":
    main()
