"""Write the decimated copies of the records other teams made (``../shared/data`` beside the repository), for the
suite: ``python test/data/external_records/make.py [SHARED_DATA_DIR]``.

* ``external_<case>.npz``: the training and validation sessions of three valves another team simulated with its
  own code (``external_valves/<case>/{train,validate}``, rosbag2 mcap, topic ``/samples``), as means of
  consecutive samples down to 1 kHz (``records.analysis_record``: a mean rather than every other sample, so the
  sensor noise is not aliased); a 1 kHz record is copied as it is.
* ``micromanipulator.npz``: the two sessions of the MIT-licensed micromanipulator record
  (``micromanipulator/Model_Vi_Do.dat``, ``Test_Vi_Do_Di.dat``: command col 0 [V], displacement col 4 [um],
  200 Hz), every row, as they are.

Each file holds, per session (``train``, ``validate``): ``<session>_t0`` [s], ``dt`` [s], ``<session>_v`` [V] and
``<session>_y`` [um]; ``source`` names the files and their sha256.  ``records.py`` beside it reads them.
"""
import hashlib
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))

from piezo_valve_ros.core.identification.records import Record, analysis_record   # noqa: E402
from piezo_valve_ros.io.bags import read_samples                                    # noqa: E402

CASES = ("asymmetric", "thermal_drift", "rate_mild")
RATE_HZ = 1000.0


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def save(name: str, sessions: dict[str, Record], sources: list[Path]) -> None:
    arrays = {"dt": np.float64(next(iter(sessions.values())).dt),
              "source": np.array("; ".join(f"{p.name} sha256 {sha256(p)}" for p in sources))}
    for key, r in sessions.items():
        arrays[f"{key}_t0"] = np.float64(r.time_s[0])
        arrays[f"{key}_v"] = r.voltage_v.astype(np.float64)
        arrays[f"{key}_y"] = r.position_um.astype(np.float64)
    np.savez_compressed(HERE / f"{name}.npz", **arrays)
    print(f"wrote {name}.npz ({(HERE / f'{name}.npz').stat().st_size // 1024} kB)")


def main(shared: Path) -> None:
    for case in CASES:
        sessions, sources = {}, []
        for key in ("train", "validate"):
            folder = shared / "external_valves" / case / key
            rows, _ = read_samples(folder)
            sessions[key] = analysis_record(Record.from_rows(rows), RATE_HZ)
            sources += sorted(folder.glob("*.mcap"))
        save(f"external_{case}", sessions, sources)
    micro = shared / "micromanipulator"
    sessions = {}
    for key, name in (("train", "Model_Vi_Do.dat"), ("validate", "Test_Vi_Do_Di.dat")):
        a = np.loadtxt(micro / name)
        sessions[key] = Record(np.arange(len(a)) * 0.005, a[:, 0], a[:, 4])
    save("micromanipulator", sessions, [micro / "Model_Vi_Do.dat", micro / "Test_Vi_Do_Di.dat"])


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parents[3] / "shared" / "data")
