"""Creep, compensated on the feedforward path: ``S = H + sum_i g_i (lag_{tau_i}[H] - H)`` (``StaticInverse``)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from ...validation import as_float_list
from .base import Term, floats

MAX_CREEP_GAIN_SUM = 0.9     # creep gains must sum below this (the inverse divides by 1 - sum)


@dataclass(frozen=True)
class CreepModel:
    """Creep as identified: ``S = H + sum_i g_i (lag_{tau_i}[H] - H)`` (H: hysteresis output [um])."""

    time_constants_s: tuple[float, ...] = ()
    gains: tuple[float, ...] = ()

    def problems(self) -> list[str]:
        taus, gains = self.time_constants_s, self.gains
        if len(taus) != len(gains):
            return [f"creep: {len(taus)} time constants but {len(gains)} gains"]
        if not all(math.isfinite(x) for x in tuple(taus) + tuple(gains)):
            return ["creep: non-finite value"]
        out = []
        if any(t <= 0 for t in taus):
            out.append("creep: time constants must be > 0")
        if sum(gains) >= MAX_CREEP_GAIN_SUM:
            out.append(f"creep: gains sum to {sum(gains):.3g}; compensation needs a sum < {MAX_CREEP_GAIN_SUM}")
        return out

    @property
    def active(self) -> bool:
        return any(g != 0.0 for g in self.gains)

    @property
    def gain_sum(self) -> float:
        return float(sum(self.gains))


def _read(get):
    taus, gains = get("creep.time_constants_s", as_float_list), get("creep.gains", as_float_list)
    return None if taus is None or gains is None else CreepModel(tuple(taus), tuple(gains))


TERM = Term(
    field="creep",
    default=CreepModel(),
    place="static",
    parameters={"creep.time_constants_s": ([], "creep compensation (feedforward path): lag time constants [s]"),
                "creep.gains": ([], "creep compensation: gains [-] (empty or all 0: none)")},
    # one neutral lag rather than []: an empty list has no element type for a ROS parameter
    write=lambda c: {"creep.time_constants_s": floats(c.time_constants_s) or [1.0], "creep.gains": floats(c.gains) or [0.0]},
    read=_read,
)
