"""The compensator's terms besides the GPIM, one module each: the ``CompensationModel`` value it fills, its
``valve_controller`` parameters, how its value is written to and read from them, and its place in the chain
(``base.Term``).  ``CompensationModel`` (its values by name, its checks, ``to_parameters``/``from_parameters``),
``MODEL_PARAMETERS``, the controller's reference path and ``ModelValve`` fold over ``TERMS`` (read from this module
when they run, so a registry extended after import counts): a new compensable term is a module here and an entry
below."""
from __future__ import annotations

from .backlash import TERM as BACKLASH
from .base import PLACES, Term
from .creep import TERM as CREEP
from .feedforward import TERM as FEEDFORWARD
from .fitted_range import TERM as FITTED_RANGE
from .rate_widening import TERM as RATE_WIDENING
from .saturation import TERM as SATURATION
from .valve_model import TERM as VALVE_MODEL

__all__ = ["Term", "TERMS", "PLACES"]

TERMS: tuple[Term, ...] = (RATE_WIDENING, VALVE_MODEL, CREEP, SATURATION, BACKLASH, FEEDFORWARD, FITTED_RANGE)
