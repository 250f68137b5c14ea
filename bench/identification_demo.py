"""The identification handbook's runs (docs/handbook/identification.md): ``valve_identify`` on simulated bags and on a measured record.

    python bench/identification_demo.py [--out docs/identification]

1. Training and validation bags (rosbag2, mcap, 10 kHz) of the default simulated valve (creep, loop-end
   flattening, G_v dynamics, amplifier slew limit, LVDT noise: none of it declared to the analyser):
   report, controller parameters file and figures in OUT.
2. The public measured piezo record in ``test/data/smart_hysteresis`` (CSV, 1 kHz, held-out last 30 %):
   report, parameters and figures in OUT/real_record.

What ``valve_identify`` prints goes to the terminal and to ``output.txt`` beside each report.
"""
import argparse
import contextlib
import os
import sys
import tempfile
from dataclasses import replace

from piezo_valve_ros.cli import identify as identify_cli
from piezo_valve_ros.io import write_samples_bag
from piezo_valve_ros.core.sim import simulate_rows
from piezo_valve_ros.core.sim import identification_voltage, validation_voltage
from piezo_valve_ros.core.sim import ValveSimConfig

REPOSITORY = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
REAL_RECORD = os.path.join(REPOSITORY, "test", "data", "smart_hysteresis", "hysteresis_v_150_1hz_1khz.csv")


def outputs(directory):
    return ["--report", os.path.join(directory, "report.json"), "--params-out", os.path.join(directory, "fitted.yaml"),
            "--plots", directory]


class _Tee:
    """Writes to the terminal and to a file."""

    def __init__(self, *streams):
        self.streams = streams

    def write(self, text):
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self):
        for s in self.streams:
            s.flush()


def identify(argv, directory):
    """``valve_identify`` with ``argv`` and its outputs in ``directory``; what it prints also to output.txt."""
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, "output.txt")
    with open(path, "w") as fh, contextlib.redirect_stdout(_Tee(sys.stdout, fh)):
        status = identify_cli.main([*argv, *outputs(directory)])
    with open(path) as fh:   # paths relative to the repository, not to this machine
        text = fh.read().replace(REPOSITORY + os.sep, "")
    with open(path, "w") as fh:
        fh.write(text)
    return status


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/results/identification")
    args = ap.parse_args()
    out = os.path.abspath(args.out)
    dt = 1e-4
    cfg = ValveSimConfig(dt=dt)
    with tempfile.TemporaryDirectory() as tmp:
        train, val = os.path.join(tmp, "train"), os.path.join(tmp, "validate")
        write_samples_bag(train, simulate_rows(identification_voltage(dt, 30.0), replace(cfg, seed=1)),
                          topic="/valve1/samples")
        write_samples_bag(val, simulate_rows(validation_voltage(dt), replace(cfg, seed=2)), topic="/valve1/samples")
        with contextlib.chdir(tmp):   # the bags' names print as "train" and "validate"
            status = identify(["train", "--validate", "validate"], out)
    if status:
        return status
    print()
    return identify([REAL_RECORD], os.path.join(out, "real_record"))


if __name__ == "__main__":
    sys.exit(main())
