"""The README's identification run: simulated 10 kHz bags of the default valve, then ``valve_identify``.

    python bench/identification_demo.py [--out docs/identification]

Writes training and validation bags (rosbag2, mcap) of the default simulated valve (creep, loop-end
flattening, G_v dynamics, amplifier slew limit, LVDT noise: none of it declared to the analyser), runs
``valve_identify`` on them with a report, a controller parameters file and the figures.
"""
import argparse
import os
import sys
import tempfile
from dataclasses import replace

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from piezo_valve_ros import identify_cli  # noqa: E402
from piezo_valve_ros.bagio import write_samples_bag  # noqa: E402
from piezo_valve_ros.core.experiments import simulate_rows  # noqa: E402
from piezo_valve_ros.core.signals import identification_voltage, validation_voltage  # noqa: E402
from piezo_valve_ros.core.simulator import ValveSimConfig  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="docs/identification")
    args = ap.parse_args()
    dt = 1e-4
    cfg = ValveSimConfig(dt=dt)
    with tempfile.TemporaryDirectory() as tmp:
        train, val = os.path.join(tmp, "train"), os.path.join(tmp, "validate")
        write_samples_bag(train, simulate_rows(identification_voltage(dt, 30.0), replace(cfg, seed=1)),
                          topic="/valve1/samples")
        write_samples_bag(val, simulate_rows(validation_voltage(dt), replace(cfg, seed=2)), topic="/valve1/samples")
        return identify_cli.main([train, "--validate", val, "--report", os.path.join(args.out, "report.json"),
                                  "--params-out", os.path.join(args.out, "fitted.yaml"), "--plots", args.out])


if __name__ == "__main__":
    sys.exit(main())
