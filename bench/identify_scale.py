"""Identification of long records: wall time and peak memory as the record grows, and what its whole length shows.

    python bench/identify_scale.py [--cases 1,5,30,120,30w] [--markdown docs/results/identify_scale.md]

Each record is one bag of the package's default simulated valve (creep, loop-end flattening, G_v, noise) driven
by the identification experiment over and over, simulated and written in chunks: 1, 5 and 30 minutes at 10 kHz,
2 hours at 1 kHz, and (``30w``, issue 59) 30 minutes at 2 kHz of the same valve whose thermal offset starts to rise
by 4 um at minute 20 (a warm-up late in the day, 60 s time constant).  ``valve_identify``'s library face
(``identify_bags``, no validation bag: the last 30 % of the stretch it analyses is held out) runs on each in a fresh
process, so its peak RSS (``resource.getrusage``) is its own.  Targets (issues 35 and 59): at most 2 GB and 3 min
for every 30-minute record, and a judgement that names the valve's own effects and nothing else: its creep, its
loop-end flattening (``saturation``) where the record shows it, and ``drift`` on the record that warms up.  The
loop fits the fast parts on the first ``MAX_ANALYSED_S`` of a record read at its own rate; the whole bag is streamed
to the analysis rate as it is read and the stretch's model runs over all of it in chunks, where a slow trend is
searched (the report's ``whole_record``; ``analysed`` and ``figures_from`` say what each figure comes from).
Compare within one run: the machine is shared.
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

from piezo_valve_ros.io import SAMPLES_TYPE, BagRecorder, qos_profile, serialize_samples
from piezo_valve_ros.runtime import keep_freed_memory
from piezo_valve_ros.core.identification import MAX_ANALYSED_S
from piezo_valve_ros.core.sim import identification_voltage
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.sim import DriftParams

from harness import Lines

WARM_UP = DriftParams(True, offset_um=4.0, gain_change=0.0, time_constant_s=60.0, start_s=1200.0)
CASES = {"1": ("1 min at 10 kHz", 60.0, 1e-4, None), "5": ("5 min at 10 kHz", 300.0, 1e-4, None),
         "30": ("30 min at 10 kHz", 1800.0, 1e-4, None), "120": ("2 h at 1 kHz", 7200.0, 1e-3, None),
         "30w": ("30 min at 2 kHz, warm-up at 20 min", 1800.0, 5e-4, WARM_UP)}
CHUNK_S = 10.0              # simulated and written this long at a time
BATCH = 1000                # samples per message, as the hardware node publishes at 10 kHz / 10 Hz
MEMORY_TARGET_MB = 2048.0
TIME_TARGET_S = 180.0
TOPIC = "/valve1/samples"


def write_long_bag(path: Path, duration_s: float, dt: float, seed: int = 1, drift: DriftParams | None = None) -> int:
    """A bag of the default valve (with ``drift`` where given) driven by the identification experiment repeated for
    ``duration_s`` [s], simulated and written CHUNK_S at a time (the writer's memory does not grow with the record).
    Returns rows."""
    config = replace(ValveSimConfig(), dt=dt, seed=seed)
    valve = SimulatedValve(config if drift is None else replace(config, drift=drift))
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
    whole = r.get("whole_record")
    print(json.dumps({"whole": None if whole is None else {k: whole[k] for k in ("from_s", "to_s", "onset_s",
                                                                              "peak_to_peak_um", "drift_added",
                                                                              "beyond_stretch_rms_um")},
                      "seconds": seconds, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "effects": r["effects_added"], "unexplained": r["unexplained"], "analysed": r["analysed"],
                      "held_out_rms_um": [r["baseline"]["validate"]["rms_um"], r["final"]["validate"]["rms_um"]]}))


def main() -> None:
    keep_freed_memory()   # as valve_identify (runtime.memory)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(CASES), help=f"records, of {', '.join(CASES)} (minutes; 30w: the "
                    f"warm-up)")
    ap.add_argument("--markdown", help="also write the table here")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        identify_one(args.one)
        return
    print = Lines(timing=True)
    print(f"the loop fits the fast parts on the first {MAX_ANALYSED_S:g} s of a record and searches all of it for a slow "
          f"trend; targets for every 30-minute record: "
          f"<= {MEMORY_TARGET_MB:.0f} MB peak, <= {TIME_TARGET_S:.0f} s")
    print(f"{'record':34s} {'samples':>11s} {'bag MB':>8s} {'write s':>8s} {'identify s':>11s} {'peak RSS MB':>12s}  "
          "judgement (held-out RMS baseline -> final)")
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases.split(","):
            label, duration_s, dt, drift = CASES[case]
            bag = Path(tmp) / f"bag_{case}"
            t0 = time.perf_counter()
            rows = write_long_bag(bag, duration_s, dt, drift=drift)
            written_s = time.perf_counter() - t0
            size_mb = sum(f.stat().st_size for f in bag.iterdir()) / 2 ** 20
            out = subprocess.run([sys.executable, __file__, "--one", str(bag)], capture_output=True, text=True)
            if out.returncode:
                print(f"{label:34s} {rows:11d}: identification failed: {out.stderr.strip().splitlines()[-1]}")
                continue
            r = json.loads(out.stdout.strip().splitlines()[-1])
            a = r["analysed"]["train"]
            judgement = (f"{', '.join(r['effects']) or 'none'}{' (unexplained)' if r['unexplained'] else ''} "
                         f"({r['held_out_rms_um'][0]:.3f} -> {r['held_out_rms_um'][1]:.3f} um; fast parts on "
                         f"{a['to_s'] - a['from_s']:.0f} s, {a['samples']} samples")
            w = r["whole"]
            judgement += (")" if w is None else
                          f"; whole record {w['to_s'] - w['from_s']:.0f} s: "
                          + (f"a trend of {w['peak_to_peak_um']:.2f} um from {w['onset_s']:.0f} s" if w["drift_added"]
                             else "no trend")
                          + (f", beyond the stretch {w['beyond_stretch_rms_um']['without_trend']:.3f} -> "
                             f"{w['beyond_stretch_rms_um']['with_trend']:.3f} um)" if w["beyond_stretch_rms_um"]
                             else ")"))
            print(f"{label:34s} {rows:11d} {size_mb:8.0f} {written_s:8.1f} {r['seconds']:11.1f} "
                  f"{r['peak_rss_mb']:12.0f}  {judgement}")
            for f in bag.iterdir():
                f.unlink()
    if args.markdown:
        print.write_markdown(args.markdown, "bench/identify_scale.py",
                             " (each identification in a fresh process; the bag written beforehand, in chunks)")


if __name__ == "__main__":
    main()
