"""What a stage of the simulated valve's chain is: a small class with ``step`` (one sample) and ``run`` (a whole
record, vectorised) on one state; its ``Link`` (its place in the chain: how a config builds it), where it can be
switched its ``StageSwitch``, and where the ``sim`` backend sets it its ``StageParameters``."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

from ...validation import ParameterSpec

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


@dataclass(frozen=True)
class StageParameters:
    """A stage's parameters of the ``sim`` backend (the hardware node declares them as ``sim.<name>``, read-only):
    their ``specs`` (type, range, description, in one place) and ``settings``, a frozen ``validation.Settings``
    dataclass read from them (``Settings.from_specs``: every reason in one refusal) whose ``apply(config,
    sample_period_s)`` gives the config with them, or raises ValueError where they do not suit it together."""

    specs: tuple[ParameterSpec, ...]
    settings: type


def spec(name: str, default: Any, description: str, low: Optional[float] = None,
         high: Optional[float] = None) -> ParameterSpec:
    """A stage's backend parameter (read-only: the backend is made once, at start-up)."""
    return ParameterSpec(name, default, description, read_only=True, low=low, high=high)
