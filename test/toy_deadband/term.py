"""The dead band's compensation term: the reference moved out by the width on its side of the centre (the dead
band's right inverse), on the spool's path (the ``output`` place)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from piezo_valve_ros.core.control.terms import Term
from piezo_valve_ros.core.validation import as_float


@dataclass(frozen=True)
class DeadBandModel:
    width_um: float = 0.0     # half-width [um]; 0: none
    centre_um: float = 0.0

    @property
    def active(self) -> bool:
        return self.width_um > 0.0

    def problems(self, output_span_um: float) -> list[str]:
        if not (math.isfinite(self.width_um) and self.width_um >= 0 and math.isfinite(self.centre_um)):
            return [f"deadband.width_um must be a finite width >= 0 and its centre finite, got {self}"]
        if self.width_um > 0.1 * output_span_um:
            return [f"deadband.width_um {self.width_um:g} is more than a tenth of the output span {output_span_um:.4g} um"]
        return []


class Forward:
    def __init__(self, model: DeadBandModel):
        self.centre, self.width = model.centre_um, model.width_um

    def step(self, x: float) -> float:
        d = x - self.centre
        return self.centre + (d - self.width if d > self.width else d + self.width if d < -self.width else 0.0)

    def run(self, x):
        import numpy as np
        d = x - self.centre
        return self.centre + np.sign(d) * np.maximum(np.abs(d) - self.width, 0.0)


class Inverse:
    def __init__(self, model: DeadBandModel):
        self.centre, self.width = model.centre_um, model.width_um

    def step(self, y: float) -> float:
        d = y - self.centre
        return y + self.width if d > 0.0 else y - self.width if d < 0.0 else y


def _read(get):
    width, centre = get("deadband.width_um", as_float), get("deadband.centre_um", as_float)
    return None if None in (width, centre) else DeadBandModel(width, centre)


TERM = Term(
    field="deadband",
    default=DeadBandModel(),
    place="output",
    parameters={"deadband.width_um": (0.0, "dead band at the spool's centre: half-width [um]; 0: none"),
                "deadband.centre_um": (0.0, "dead band: its centre [um]")},
    write=lambda m: {"deadband.width_um": float(m.width_um), "deadband.centre_um": float(m.centre_um)},
    read=_read,
    forward=lambda m, x0: Forward(m) if m.active else None,
    inverse=lambda m, y0, previous: Inverse(m) if m.active else None,
    problems=lambda m, span: m.problems(span),
)
