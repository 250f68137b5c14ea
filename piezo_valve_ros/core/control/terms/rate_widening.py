"""Rate-dependent thresholds of the inverse GPIM (``rate_dependence``): the widening coefficients [V]."""
from __future__ import annotations

from ...model.rate_dependence import RATE_FILTERS_S, RATE_SCALES_V_S, TERM_COUNT
from ...validation import as_float_list
from .base import Term, floats


def _read(get):
    widening = get("gpim.rate_widening_v", as_float_list)
    return None if widening is None else (tuple(widening) if any(widening) else ())


TERM = Term(
    field="rate_widening_v",
    parameters={"gpim.rate_widening_v": (
        [], f"rate-dependent GPIM: every threshold widens by sum c rho_f / (rho_f + s_k) [V], rho_f = |dv/dt| through "
            f"the lags {list(RATE_FILTERS_S)} s, s_k = {list(RATE_SCALES_V_S)} V/s; {TERM_COUNT} coefficients c [V], "
            "filter-major (empty or all 0: none)")},
    # zeros rather than []: an empty list has no element type for a ROS parameter
    write=lambda widening: {"gpim.rate_widening_v": floats(widening) or [0.0] * TERM_COUNT},
    read=_read,
)
