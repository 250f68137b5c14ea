"""The residual loop's judgement on the test battery, as a table (the README's figures come from here).

    python bench/residual_battery.py [--markdown docs/identification/battery.md]

Every valve of ``test/valve_battery.py`` (effects written unlike the catalogue's regressors, all with G_v
and sensor noise; three with structure outside the catalogue), analysed twice: with a separate validation
record, and with the last 30 % of the training record held out.  Then the measured piezo record of
``test/data/smart_hysteresis``.  Prints, per case: what was declared, what the loop named, whether it
reported unexplained structure, and the held-out RMS and peak before (the baseline, GPIM + refitted G_v)
and after.
"""
import argparse
import importlib.util
import os
import sys
import time

from piezo_valve_ros.core.records import Record, read_csv
from piezo_valve_ros.core.residual import analyse

HERE = os.path.dirname(os.path.abspath(__file__))
TEST_DIR = os.path.join(HERE, "..", "test")


def load_battery():
    """The battery module, loaded from its file (it is test code, not part of the package)."""
    spec = importlib.util.spec_from_file_location("valve_battery", os.path.join(TEST_DIR, "valve_battery.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def row(case, declared, report):
    b, f = report["baseline"]["validate"], report["final"]["validate"]
    return (case, declared, ", ".join(report["effects_added"]) or "none", "yes" if report["unexplained"] else "no",
            f"{b['rms_um']:.3f} -> {f['rms_um']:.3f}", f"{b['peak_um']:.2f} -> {f['peak_um']:.2f}",
            f"{report['seconds']:.1f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--markdown", help="also write the table here")
    args = ap.parse_args()
    vb = load_battery()
    train_v, valid_v = vb.training_voltage(vb.DT), vb.validation_voltage_(vb.DT)
    header = ("case", "declared", "named", "unexplained", "held-out RMS [um]", "held-out peak [um]", "s")
    rows = []
    started = time.monotonic()
    cases = [(name, valve, ", ".join(valve.effects) or "none") for name, valve in vb.BATTERY.items()]
    cases += [(name, valve, "outside the catalogue") for name, valve in vb.OUTSIDE.items()]
    for mode in ("validation record", "held-out last 30 %"):
        for name, valve, declared in cases:
            train = Record.from_rows(valve.rows(train_v, 1))
            validate = Record.from_rows(valve.rows(valid_v, 2)) if mode == "validation record" else None
            report = analyse(train, validate).report
            rows.append(row(f"{name} ({mode})", declared, report))
            print(" | ".join(rows[-1]), flush=True)
    real = os.path.join(TEST_DIR, "data", "smart_hysteresis", "hysteresis_v_150_1hz_1khz.csv")
    report = analyse(read_csv(real)).report
    rows.append(row("measured piezo record, 1 kHz (held-out last 30 %)", "unknown", report))
    print(" | ".join(rows[-1]))
    print(f"total {time.monotonic() - started:.0f} s")
    if args.markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        with open(args.markdown, "w") as fh:
            fh.write("Output of `python bench/residual_battery.py --markdown docs/identification/battery.md` "
                     "(held-out figures at the record's rate; before = GPIM + refitted G_v).\n\n")
            fh.write("\n".join(lines) + "\n")
        print(f"wrote {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
