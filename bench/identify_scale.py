"""Identification of long records: wall time and peak memory as the record grows.

    python bench/identify_scale.py [--cases 1,5,30,120] [--markdown docs/results/identify_scale.md]

Each record is one bag of the package's default simulated valve (creep, loop-end flattening, G_v, noise) driven
by the identification experiment over and over, simulated and written in chunks: 1, 5 and 30 minutes at 10 kHz
and 2 hours at 1 kHz.  ``valve_identify``'s library face (``identify_bags``, no validation bag: the last 30 % of
what it analyses is held out) runs on each in a fresh process, so its peak RSS (``resource.getrusage``) is its
own.  Targets (issue 35): at most 2 GB and 3 min for the 30-minute record, and a judgement that names the
valve's own effects and nothing else: its creep, and its loop-end flattening (``saturation``) where the record
shows it.  The loop analyses at most the first ``MAX_ANALYSED_S`` of a record and reads no
more of the bag than that (the report's ``analysed`` and ``source.train_window`` say what), so beyond that
length the cost is reading the bag's index, not its samples.  Compare within one run: the machine is shared.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from piezo_valve_ros.io.bags import SAMPLES_TYPE, BagRecorder, qos_profile, serialize_samples
from piezo_valve_ros.runtime.memory import keep_freed_memory
from piezo_valve_ros.core.identification.records import MAX_ANALYSED_S
from piezo_valve_ros.core.sim.signals import identification_voltage
from piezo_valve_ros.core.sim.simulator import SimulatedValve, ValveSimConfig

from harness import Lines

CASES = {1: ("1 min at 10 kHz", 60.0, 1e-4), 5: ("5 min at 10 kHz", 300.0, 1e-4),
         30: ("30 min at 10 kHz", 1800.0, 1e-4), 120: ("2 h at 1 kHz", 7200.0, 1e-3)}
CHUNK_S = 10.0              # simulated and written this long at a time
BATCH = 1000                # samples per message, as the hardware node publishes at 10 kHz / 10 Hz
MEMORY_TARGET_MB = 2048.0
TIME_TARGET_S = 180.0
TOPIC = "/valve1/samples"


def write_long_bag(path: Path, duration_s: float, dt: float, seed: int = 1) -> int:
    """A bag of the default valve driven by the identification experiment repeated for ``duration_s`` [s],
    simulated and written CHUNK_S at a time (the writer's memory does not grow with the record).  Returns rows."""
    valve = SimulatedValve(replace(ValveSimConfig(), dt=dt, seed=seed))
    experiment = identification_voltage(dt)
    total = int(round(duration_s / dt))
    clock = [0.0]
    rec = BagRecorder(path, {TOPIC: (SAMPLES_TYPE, qos_profile(True, 100))}, segment_s=float("inf"),
                      clock=lambda: clock[0])
    chunk = int(round(CHUNK_S / dt))
    for start in range(0, total, chunk):
        k = np.arange(start, min(start + chunk, total))
        v = experiment[k % experiment.size]
        rows = np.column_stack((k * dt, v, valve.run(v)))
        for i in range(0, rows.shape[0], BATCH):
            block = rows[i:i + BATCH]
            rec.write(TOPIC, 1_700_000_000_000_000_000 + int(round(block[-1, 0] * 1e9)), serialize_samples(block))
    rec.close()
    return total


def identify_one(bag: str) -> None:
    """In a fresh process: identify_bags on ``bag``; one JSON line with the seconds, peak RSS and judgement."""
    import resource
    from piezo_valve_ros.identify import identify_bags
    t0 = time.perf_counter()
    analysis, _ = identify_bags(bag, log=lambda s: None)
    seconds = time.perf_counter() - t0
    r = analysis.report.to_json()
    print(json.dumps({"seconds": seconds, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "effects": r["effects_added"], "unexplained": r["unexplained"], "analysed": r["analysed"],
                      "held_out_rms_um": [r["baseline"]["validate"]["rms_um"], r["final"]["validate"]["rms_um"]]}))


def main() -> None:
    keep_freed_memory()   # as valve_identify (runtime.memory)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(map(str, CASES)), help="record lengths in minutes, of "
                    f"{', '.join(map(str, CASES))}")
    ap.add_argument("--markdown", help="also write the table here")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        identify_one(args.one)
        return
    print = Lines()
    print(f"the loop analyses at most the first {MAX_ANALYSED_S:g} s of a record; targets for 30 min at 10 kHz: "
          f"<= {MEMORY_TARGET_MB:.0f} MB peak, <= {TIME_TARGET_S:.0f} s")
    print(f"{'record':18s} {'samples':>11s} {'bag MB':>8s} {'write s':>8s} {'identify s':>11s} {'peak RSS MB':>12s}  "
          "judgement (held-out RMS baseline -> final)")
    with tempfile.TemporaryDirectory() as tmp:
        for minutes in (int(c) for c in args.cases.split(",")):
            label, duration_s, dt = CASES[minutes]
            bag = Path(tmp) / f"bag_{minutes}"
            t0 = time.perf_counter()
            rows = write_long_bag(bag, duration_s, dt)
            written_s = time.perf_counter() - t0
            size_mb = sum(f.stat().st_size for f in bag.iterdir()) / 2 ** 20
            out = subprocess.run([sys.executable, __file__, "--one", str(bag)], capture_output=True, text=True)
            if out.returncode:
                print(f"{label:18s} {rows:11d}: identification failed: {out.stderr.strip().splitlines()[-1]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            a = r["analysed"]["train"]
            judgement = (f"{', '.join(r['effects']) or 'none'}{' (unexplained)' if r['unexplained'] else ''} "
                         f"({r['held_out_rms_um'][0]:.3f} -> {r['held_out_rms_um'][1]:.3f} um; analysed "
                         f"{a['to_s'] - a['from_s']:.0f} s, {a['samples']} samples)")
            print(f"{label:18s} {rows:11d} {size_mb:8.0f} {written_s:8.1f} {r['seconds']:11.1f} "
                  f"{r['peak_rss_mb']:12.0f}  {judgement}")
            for f in bag.iterdir():
                f.unlink()
    if args.markdown:
        print.write_markdown(args.markdown, "bench/identify_scale.py",
                             " (each identification in a fresh process; the bag written beforehand, in chunks)")


if __name__ == "__main__":
    main()
