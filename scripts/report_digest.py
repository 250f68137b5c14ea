"""Digests of the identification's reports on a fixed set of records, for telling whether a change to the code moved
any judgement or figure: the 2 kHz default valve and its drift + asymmetric-envelope variant (training and validation
sessions), and the records other teams made (``test/data/external_records``).  Each report's JSON, less its
``seconds``, is hashed and written to ``OUT/<record>.json``; run it on two trees and compare.

    python scripts/report_digest.py OUT [NAME ...]        # NAME: only the records whose name holds it
    # another tree (e.g. a git worktree of the commit before):  PYTHONPATH=/tmp/before python scripts/report_digest.py OUT2
    diff -r OUT OUT2                                       # nothing: the same reports

A bit-identical speed-up leaves every digest as it was; a judgement change shows which records it moved.
"""
from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "test"))   # the records others made, with their reader (test/external_records.py)


def records() -> dict:
    """name -> a function returning (training, validation) records."""
    from piezo_valve_ros.core.identification import Record
    from piezo_valve_ros.core.sim import (DriftParams, ValveSimConfig, identification_voltage, simulate_rows,
                                          validation_voltage)
    from external_records import EXTERNAL
    dt = 5e-4
    out = {}
    for name, config in (("default valve, 2 kHz", ValveSimConfig(dt=dt)),
                         ("drift + asymmetric envelope, 2 kHz", ValveSimConfig(dt=dt, drift=DriftParams(enabled=True),
                                                                                descending_envelope=(0.95, 0.2)))):
        out[name] = lambda c=config: (Record.from_rows(simulate_rows(identification_voltage(dt, 40.0), replace(c, seed=1))),
                                      Record.from_rows(simulate_rows(validation_voltage(dt, 40.0), replace(c, seed=2))))
    for name, external in EXTERNAL.items():
        out[name] = external.records
    return out


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    from piezo_valve_ros.core.identification import analyse
    folder, only = Path(argv[0]), argv[1:]
    folder.mkdir(parents=True, exist_ok=True)
    for name, make in records().items():
        if only and not any(o in name for o in only):
            continue
        train, validate = make()
        started = time.perf_counter()
        report = analyse(train, validate, log=lambda line: None).report.to_json()
        report.pop("seconds", None)
        text = json.dumps(report, sort_keys=True, indent=1)
        safe = "".join(c if c.isalnum() else "_" for c in name)
        (folder / f"{safe}.json").write_text(text + "\n")
        print(f"{name:42s} {hashlib.sha1(text.encode()).hexdigest()[:12]}  {time.perf_counter() - started:5.1f} s  "
              f"{', '.join(report['effects_added']) or 'none'}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
