"""The simulated valve's stages, one module each (its parameters, its stage class, its link, its switch): ``CHAIN``
is every stage in the order the signal passes them, which ``SimulatedValve`` folds over a config (each link builds
its stage, or none where it is switched off); ``STAGE_SWITCHES`` is every switchable stage, from which the ``sim``
backend makes its ``sim.<name>`` parameters.  A new stage is a module here, its link and switch below and its
parameters on ``ValveSimConfig`` (a stage from outside the package keeps them in ``ValveSimConfig.added``; the chain is
read when a valve resets, so one added to it after import counts)."""
from __future__ import annotations

from . import amplifier, backlash, creep, drift, dynamics, hysteresis, rate_dependence, saturation, sensor
from .base import Link, StageSwitch

__all__ = ["Link", "StageSwitch", "STAGE_SWITCHES", "CHAIN"]

STAGE_SWITCHES: tuple[StageSwitch, ...] = (amplifier.SWITCH, creep.SWITCH, saturation.SWITCH, sensor.SWITCH,
                                           dynamics.SWITCH, rate_dependence.SWITCH, drift.SWITCH, backlash.SWITCH,
                                           hysteresis.SWITCH)

# the chain before the spool (the spool's true position is read there) and after it (what the sensor adds)
CHAIN: tuple[Link, ...] = (amplifier.LINK, hysteresis.LINK, creep.LINK, rate_dependence.LINK, saturation.LINK,
                           dynamics.LINK, backlash.LINK, drift.LINK)
SENSING: tuple[Link, ...] = (sensor.DELAY_LINK, sensor.LINK)
