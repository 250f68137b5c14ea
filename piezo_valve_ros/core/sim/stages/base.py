"""What a stage of the simulated valve's chain is: a small class with ``step`` (one sample) and ``run`` (a whole
record, vectorised) on one state; its ``Link`` (its place in the chain: how a config builds it), and, where it can
be switched, its ``StageSwitch``."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

SimConfig = Any   # a ``simulator.ValveSimConfig`` (the stages sit below the simulator and do not import it)


@dataclass(frozen=True)
class StageSwitch:
    """A stage of the chain that can be switched on and off, in one place: the simulated backend's parameter
    ``sim.<name>`` and its description, whether a config has it on, and a config with it on or off."""

    name: str
    description: str
    is_on: Callable[[SimConfig], bool]
    set: Callable[[SimConfig, bool], SimConfig]


@dataclass(frozen=True)
class Link:
    """A stage's place in the simulated valve's chain (``stages.CHAIN``, in the order the signal passes them):
    ``build(config, x0) -> (stage, x)`` makes the stage for ``config`` (None where it is switched off) at rest at
    ``x0``, the value entering it at rest (volts into the amplifier, um after the hysteresis), and gives ``x``, the
    value it passes on at rest.  ``SimulatedValve`` folds the chain over a config once per reset."""

    name: str
    build: Callable[[SimConfig, float], tuple[Optional[Any], float]]
