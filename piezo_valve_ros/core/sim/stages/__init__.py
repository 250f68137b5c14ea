"""The simulated valve's stages, one module each (its parameters, its stage class, its link, its switch, its backend
parameters): ``CHAIN`` is every stage in the order the signal passes them, which ``SimulatedValve`` folds over a
config (each link builds its stage, or none where it is switched off); ``STAGE_SWITCHES`` is every switchable stage
and ``STAGE_PARAMETERS`` every stage's backend settings, from which the ``sim`` backend makes its ``sim.<name>``
parameters.  A new stage is a module here, its link and switch (and settings) below and its parameters on
``ValveSimConfig`` (a stage from outside the package keeps them in ``ValveSimConfig.added``; the chain is read when a
valve resets, so one added to it after import counts)."""
from __future__ import annotations

from . import amplifier, backlash, creep, drift, dynamics, hysteresis, rate_dependence, saturation, sensor
from .base import Link, StageParameters, StageSwitch

__all__ = ["Link", "StageSwitch", "StageParameters", "STAGE_SWITCHES", "STAGE_PARAMETERS", "CHAIN"]

STAGE_SWITCHES: tuple[StageSwitch, ...] = (amplifier.SWITCH, creep.SWITCH, saturation.SWITCH, sensor.SWITCH,
                                           dynamics.SWITCH, rate_dependence.SWITCH, drift.SWITCH, backlash.SWITCH,
                                           hysteresis.SWITCH)

# the chain before the spool (the spool's true position is read there) and after it (what the sensor adds)
CHAIN: tuple[Link, ...] = (amplifier.LINK, hysteresis.LINK, creep.LINK, rate_dependence.LINK, saturation.LINK,
                           dynamics.LINK, backlash.LINK, drift.LINK)
SENSING: tuple[Link, ...] = (sensor.DELAY_LINK, sensor.LINK)

# the stages the ``sim`` backend sets by parameters (besides their switches), in the order it declares them
STAGE_PARAMETERS: tuple[StageParameters, ...] = (sensor.PARAMETERS, drift.PARAMETERS, backlash.PARAMETERS,
                                                  hysteresis.PARAMETERS)
