"""What a compensator term is: a part of ``CompensationModel`` with its own ``valve_controller`` parameters and its
place in the valve's chain."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional, Protocol

Getter = Callable[[str, Callable[[str, Any], Any]], Optional[Any]]   # (name, conversion) -> value, None if refused

PLACES = ("gpim", "static", "dynamics", "output", "")
"""Where a term acts, in the order the valve's signal passes them: in the hysteresis (``gpim``), on its output before
G_v (``static``: creep and the saturation map), in G_v (``dynamics``), on the spool's path after G_v (``output``); ""
for what is no part of the chain (the voltages a model was fitted on).  The first three places are one step each in
the controller, built from all their terms together (the inverse GPIM with its rate widening; the static inverse,
which solves creep and the map as one equation; W = F/G); the output place is folded term by term."""


class Step(Protocol):
    """A streaming step of the chain: one value in, one out [um], once per period; no allocation per step."""

    def step(self, x: float) -> float: ...


class BlockStep(Step, Protocol):
    """A forward step that also runs over a block (``ModelValve.run``), its state carried on as with ``step``."""

    def run(self, x): ...


@dataclass(frozen=True)
class Term:
    """One term of the compensation model besides the GPIM, declared in its own module: the ``CompensationModel``
    field it fills and its value where the model has none (``default``), its ``valve_controller`` parameters
    (name -> (default, description)), how its value is written to them (``write``: value -> {name: value}, every
    parameter, so applying them replaces an older value) and read from them (``read``: a getter -> value, None
    where a parameter was refused; the getter collects the reasons), and its ``place`` in the chain (``PLACES``).

    A term at the ``output`` place brings its own streaming steps, which the controller and ``ModelValve`` fold
    in the order of ``TERMS`` (the reference path inverts them in the opposite order):
      ``forward(value, x0_um) -> BlockStep or None``: the spool's position for G's output, at rest at ``x0_um``
      (None: the value does nothing);
      ``inverse(value, y0_um, previous) -> Step or None``: the reference path's inverse, at rest at the reference
      ``y0_um``, carrying on from ``previous`` (the step of the value before a model swap, or None);
      ``problems(value, output_span_um) -> [reason]``: why the controller cannot invert it on a valve of that
      output span (math.inf: unknown)."""

    field: str
    parameters: dict[str, tuple[Any, str]]
    write: Callable[[Any], dict[str, Any]]
    read: Callable[[Getter], Optional[Any]]
    default: Any = None
    place: str = ""
    forward: Optional[Callable[[Any, float], Optional[BlockStep]]] = None
    inverse: Optional[Callable[[Any, float, Optional[Step]], Optional[Step]]] = None
    problems: Optional[Callable[[Any, float], list[str]]] = None

    def __post_init__(self):
        if self.place not in PLACES:
            raise ValueError(f"term {self.field}: place must be one of {PLACES}, got {self.place!r}")
        if self.place == "output" and (self.forward is None or self.inverse is None):
            raise ValueError(f"term {self.field}: a term at the output place brings its forward and inverse steps")


def floats(values) -> list[float]:
    return [float(x) for x in values]
