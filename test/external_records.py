"""The records other teams made (``test/data/external_records``, see its README): each as (training, validation)
``Record``s, with what is right for it."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from piezo_valve_ros.core.identification import Record

HERE = Path(__file__).resolve().parent / "data" / "external_records"


@dataclass(frozen=True)
class External:
    """A record pair and what is right for it: ``names`` the effects to add, exactly (None: no truth given)."""
    file: str
    names: Optional[tuple[str, ...]]
    about: str

    def records(self) -> tuple[Record, Record]:
        with np.load(HERE / self.file) as z:
            dt = float(z["dt"])
            return tuple(Record(float(z[f"{s}_t0"]) + np.arange(z[f"{s}_v"].size) * dt, z[f"{s}_v"], z[f"{s}_y"])
                         for s in ("train", "validate"))

    def source(self) -> str:
        with np.load(HERE / self.file) as z:
            return str(z["source"])


EXTERNAL: dict[str, External] = {
    "external: asymmetric": External("external_asymmetric.npz", ("asymmetry",),
                                     "another team's GPIM valve, descending envelope a steeper shifted line"),
    "external: thermal drift": External("external_thermal_drift.npz", ("drift",),
                                        "another team's paper valve with an exponential warm-up and a slow wander"),
    "external: mild rate dependence": External("external_rate_mild.npz", ("dynamics",),
                                               "another team's paper valve with additive rate-dependent thresholds"),
    "micromanipulator (measured, 200 Hz)": External("micromanipulator.npz", None,
                                                    "a real piezo micromanipulator, two sessions after unrecorded jumps"),
}
MICRO_RMS_UM = 0.30      # the micromanipulator's held-out RMS must be at most this ...
MICRO_PEAK_PCT = 5.0     # ... its peak at most this % of the range, and the delay or lag named (dynamics)


def judged_right(name: str, report: dict) -> bool:
    """Whether ``report`` is right for the external record ``name``: the truth's names exactly; for the
    micromanipulator, the held-out RMS and peak within what a good analysis achieves and the delay or lag named."""
    case = EXTERNAL[name]
    if case.names is not None:
        return sorted(report["effects_added"]) == sorted(case.names)
    f = report["final"]["validate"]
    return f["rms_um"] <= MICRO_RMS_UM and f["peak_pct"] <= MICRO_PEAK_PCT and "dynamics" in report["effects_added"]
