"""Identification speed: a training + validation bag pair through ``identify_bags`` (bag reading included).

    python bench/identify_speed.py [--skip-straightforward] [--load]

Target (issue 9): under 10 s per pair of 50-60 s records at 2-10 kHz.  Two valves of the package's
simulator: the default one (creep, loop-end flattening, G_v, noise) and one with drift and an asymmetric
envelope as well (more effects, more refits).  Beside ours, in the same run:

* straightforward, full rate: the same algorithm with every fit at the record's own rate (no block means);
* straightforward, exact search: every subset of the catalogue refitted exactly instead of scored by one
  linear solve each from the baseline (on the 2 kHz pair).

Ours is also timed with its refits on one thread (``analyse(threads=1)``, without bag reading).
``--load`` repeats the measurement of ours with two busy loops running beside it (this machine has two
cores).  Compare ratios within one run: the machine is shared.
"""
import argparse
import itertools
import multiprocessing
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from piezo_valve_ros.bagio import read_samples, write_samples_bag
from piezo_valve_ros.core.identification.effects import CATALOGUE
from piezo_valve_ros.core.sim.experiments import simulate_rows
from piezo_valve_ros.core.identification.fitting import FitCache, fit_model
from piezo_valve_ros.core.identification.records import Record
from piezo_valve_ros.core.identification.residual import analyse
from piezo_valve_ros.core.sim.signals import identification_voltage, validation_voltage
from piezo_valve_ros.core.sim.simulator import DriftParams, ValveSimConfig
from piezo_valve_ros.identify import identify_bags
from threadpoolctl import threadpool_limits

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
            e = a.split.held_out_error(m)
            scores.append(([x.name for x in subset], float((e ** 2).mean() ** 0.5)))
    return scores


def _burn(stop):
    while not stop.is_set():
        pass


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--skip-straightforward", action="store_true")
    ap.add_argument("--load", action="store_true", help="also measure with two busy loops running")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for rate_hz in (10000, 2000):
            dt = 1.0 / rate_hz
            for name, cfg in VALVES.items():
                d = Path(tmp) / f"{rate_hz}_{name.replace(' ', '_')}"
                d.mkdir()
                train, val = make_pair(d, cfg, dt)
                n = read_samples(train)[0].shape[0] + read_samples(val)[0].shape[0]
                t_ours, (analysis, _) = timed(lambda: identify_bags(train, val, log=lambda s: None))
                r = analysis.report
                print(f"{rate_hz:5d} Hz, {name}: {n} samples in the pair")
                print(f"   ours                          {t_ours:6.2f} s  (target < 10 s): added {r['effects_added']}, "
                      f"held-out RMS {r['baseline']['validate']['rms_um']:.3f} -> {r['final']['validate']['rms_um']:.3f} um")
                tr = Record.from_rows(read_samples(train)[0])
                va = Record.from_rows(read_samples(val)[0])
                t_one, one = timed(lambda: analyse(tr, va, threads=1))
                same = one.report["effects_added"] == r["effects_added"]
                print(f"   ours, refits on one thread    {t_one:6.2f} s  ({t_one / t_ours:.1f}x; same effects: {same})")
                if args.load:
                    stop = multiprocessing.Event()
                    burners = [multiprocessing.Process(target=_burn, args=(stop,)) for _ in range(2)]
                    for b in burners:
                        b.start()
                    try:
                        t_load, _ = timed(lambda: identify_bags(train, val, log=lambda s: None))
                    finally:
                        stop.set()
                        for b in burners:
                            b.join()
                    print(f"   ours, two busy loops beside   {t_load:6.2f} s  ({t_load / t_ours:.1f}x the quiet run)")
                if args.skip_straightforward:
                    continue
                if rate_hz == 10000:
                    t_full, full = timed(lambda: analyse(tr, va, max_rate_hz=float("inf")))
                    print(f"   straightforward, full rate    {t_full:6.2f} s  -> ours is {t_full / t_ours:4.1f}x faster; "
                          f"added {full.report['effects_added']}")
                else:
                    t_ex, scores = timed(lambda: exhaustive_exact(tr, va))
                    best = min(scores, key=lambda s: s[1])
                    print(f"   straightforward, exact search {t_ex:6.2f} s  -> ours is {t_ex / t_ours:4.1f}x faster; "
                          f"{len(scores)} exact refits, lowest held-out RMS {best[1]:.3f} um with {best[0]}")


if __name__ == "__main__":
    main()
