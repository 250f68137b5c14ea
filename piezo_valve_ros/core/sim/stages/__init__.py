"""The simulated valve's stages, one module each (its parameters, its stage class, its switch): ``STAGE_SWITCHES``
is every switchable stage, from which the ``sim`` backend makes its ``sim.<name>`` parameters.  A new stage is a
module here, its switch below, its parameters on ``ValveSimConfig`` and its place in ``SimulatedValve``'s chain."""
from __future__ import annotations

from . import amplifier, backlash, creep, drift, dynamics, hysteresis, rate_dependence, saturation, sensor
from .base import StageSwitch

__all__ = ["StageSwitch", "STAGE_SWITCHES"]

STAGE_SWITCHES: tuple[StageSwitch, ...] = (amplifier.SWITCH, creep.SWITCH, saturation.SWITCH, sensor.SWITCH,
                                           dynamics.SWITCH, rate_dependence.SWITCH, drift.SWITCH, backlash.SWITCH,
                                           hysteresis.SWITCH)
