"""Writes hysteresis_v_150_1hz_1khz_full.csv from the source file (see README.md): 5-sample means.

    python test/data/smart_hysteresis/decimate.py ../shared/data/smarthysteresis/hysteresis_v_150_1hz.csv
"""
import sys
from pathlib import Path

import numpy as np

BLOCK = 5   # 5 kHz -> 1 kHz; a mean, not every fifth sample, so the sensor noise is not aliased


def main(source: str) -> None:
    a = np.genfromtxt(source, delimiter=",")[:, 1:]          # the source's first column is empty
    n = len(a) // BLOCK * BLOCK
    t, y, v = (a[:n, k].reshape(-1, BLOCK).mean(axis=1) for k in (0, 1, 2))
    out = Path(__file__).with_name("hysteresis_v_150_1hz_1khz_full.csv")
    with open(out, "w") as f:
        f.write("# SmartHysteresis Data/hysteresis_v_150_1hz.csv (MIT, see README.md and LICENSE): 5-sample means\n")
        f.write("time_s,position_um,voltage_v\n")
        for row in zip(t, y, v):
            f.write("%.7f,%.6f,%.6f\n" % row)
    print(f"{out}: {n // BLOCK} rows")


if __name__ == "__main__":
    main(sys.argv[1])
