"""Backlash on the spool's path, compensated on the reference path: the reference moved on by the clearance in
the direction it last moved (the right inverse of a play, ``PlayInverse``), before the inverse dynamics and
hysteresis."""
from __future__ import annotations

import math
from dataclasses import dataclass

from ...model.hysteresis import PlayOperatorBank
from ...validation import as_float
from .base import Term

MAX_BACKLASH_SHARE = 0.1    # a clearance wider than this share of the valve's output span is not a backlash to invert
DIRECTION_DEADBAND_UM = 1e-9   # a reference change smaller than this keeps the direction it had


@dataclass(frozen=True)
class BacklashModel:
    """A play of half-width ``width_um`` [um] between the actuator and the spool (0: none)."""

    width_um: float = 0.0

    @property
    def active(self) -> bool:
        return self.width_um > 0.0

    def problems(self, output_span_um: float = math.inf) -> list[str]:
        if not math.isfinite(self.width_um) or self.width_um < 0:
            return [f"backlash.width_um must be a finite width >= 0, got {self.width_um}"]
        if self.width_um > MAX_BACKLASH_SHARE * output_span_um:
            return [f"backlash.width_um {self.width_um:g} is more than {MAX_BACKLASH_SHARE:g} of the valve's output span "
                    f"{output_span_um:.4g} um: not a clearance the controller can jump across"]
        return []


class PlayInverse:
    """Streaming right inverse of the play: ``x = y_ref + width * direction``, the direction the reference last moved
    (+1 up, -1 down, 0 before it moved).  No allocation per step."""

    def __init__(self, model: BacklashModel, y0_um: float = 0.0, direction: int = 0):
        self.width = float(model.width_um)
        self.reset(y0_um, direction)

    def reset(self, y0_um: float, direction: int = 0) -> None:
        self._last = float(y0_um)
        self.direction = direction

    def step(self, y_ref_um: float) -> float:
        change = y_ref_um - self._last
        if change > DIRECTION_DEADBAND_UM:
            self.direction = 1
        elif change < -DIRECTION_DEADBAND_UM:
            self.direction = -1
        self._last = y_ref_um
        return y_ref_um + self.width * self.direction


class Play:
    """The play run forwards (``ModelValve``): the spool's position [um] for G's output, at rest at ``x0_um``."""

    def __init__(self, model: BacklashModel, x0_um: float):
        self._bank = PlayOperatorBank([model.width_um], [x0_um])

    def step(self, x: float) -> float:
        return float(self._bank.step(x, x)[0])

    def run(self, x):
        return self._bank.run(x, x)[:, 0]


def _inverse(model: BacklashModel, y0_um: float, previous):
    """The reference path's inverse; the direction the reference last moved carried into a new clearance."""
    if not model.active:
        return None
    return PlayInverse(model, y0_um, previous.direction if isinstance(previous, PlayInverse) else 0)


def _read(get):
    width = get("backlash.width_um", as_float)
    return None if width is None else BacklashModel(width)


TERM = Term(
    field="backlash",
    default=BacklashModel(),
    place="output",
    forward=lambda model, x0_um: Play(model, x0_um) if model.active else None,
    inverse=_inverse,
    problems=lambda model, span_um: model.problems(span_um),
    parameters={"backlash.width_um": (0.0, "backlash on the spool's path: clearance either side [um] (the play's "
                                           "half-width), added to the reference in the direction it moves; 0: none")},
    write=lambda b: {"backlash.width_um": float(b.width_um)},
    read=_read,
)
