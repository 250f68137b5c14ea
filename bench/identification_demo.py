"""The identification handbook's runs (docs/handbook/identification.md): ``valve_identify`` on simulated bags and on a measured record.

    python bench/identification_demo.py [--out docs/identification]

1. Training and validation bags (rosbag2, mcap, 10 kHz) of the default simulated valve (creep, loop-end
   flattening, G_v dynamics, amplifier slew limit, LVDT noise: none of it declared to the analyser):
   report, controller parameters file and figures in OUT.
2. The public measured piezo record in ``test/data/smart_hysteresis`` (CSV, 1 kHz, held-out last 30 %):
   report, parameters and figures in OUT/real_record.
"""
import argparse
import os
import sys
import tempfile
from dataclasses import replace

from piezo_valve_ros import identify_cli
from piezo_valve_ros.bagio import write_samples_bag
from piezo_valve_ros.core.sim.experiments import simulate_rows
from piezo_valve_ros.core.sim.signals import identification_voltage, validation_voltage
from piezo_valve_ros.core.sim.simulator import ValveSimConfig

REAL_RECORD = os.path.join(os.path.dirname(__file__), "..", "test", "data", "smart_hysteresis",
                           "hysteresis_v_150_1hz_1khz.csv")


def outputs(directory):
    return ["--report", os.path.join(directory, "report.json"), "--params-out", os.path.join(directory, "fitted.yaml"),
            "--plots", directory]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="docs/results/identification")
    args = ap.parse_args()
    dt = 1e-4
    cfg = ValveSimConfig(dt=dt)
    with tempfile.TemporaryDirectory() as tmp:
        train, val = os.path.join(tmp, "train"), os.path.join(tmp, "validate")
        write_samples_bag(train, simulate_rows(identification_voltage(dt, 30.0), replace(cfg, seed=1)),
                          topic="/valve1/samples")
        write_samples_bag(val, simulate_rows(validation_voltage(dt), replace(cfg, seed=2)), topic="/valve1/samples")
        status = identify_cli.main([train, "--validate", val, *outputs(args.out)])
    if status:
        return status
    print()
    return identify_cli.main([os.path.relpath(REAL_RECORD), *outputs(os.path.join(args.out, "real_record"))])


if __name__ == "__main__":
    sys.exit(main())
