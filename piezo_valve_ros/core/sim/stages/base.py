"""What a stage of the simulated valve's chain is: a small class with ``step`` (one sample) and ``run`` (a whole
record, vectorised) on one state, and, where it can be switched, its ``StageSwitch``."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

SimConfig = Any   # a ``simulator.ValveSimConfig`` (the stages sit below the simulator and do not import it)


@dataclass(frozen=True)
class StageSwitch:
    """A stage of the chain that can be switched on and off, in one place: the simulated backend's parameter
    ``sim.<name>`` and its description, whether a config has it on, and a config with it on or off."""

    name: str
    description: str
    is_on: Callable[[SimConfig], bool]
    set: Callable[[SimConfig, bool], SimConfig]
