"""Rate-dependent thresholds of the inverse GPIM (``rate_dependence``): the widening coefficients [V]."""
from __future__ import annotations

from ...model.rate_dependence import EARLIER_TERM_COUNT, RATE_FILTERS_S, RATE_SCALES_V_S, TERM_COUNT
from ...validation import as_float_list
from .base import Term, floats


def _read(get):
    widening = get("gpim.rate_widening_v", as_float_list)
    if widening is not None and len(widening) == EARLIER_TERM_COUNT:
        # a file written before the 5 ms filter was added (filter-major, appended last): the same widening
        widening = list(widening) + [0.0] * (TERM_COUNT - EARLIER_TERM_COUNT)
    return None if widening is None else (tuple(widening) if any(widening) else ())


TERM = Term(
    field="rate_widening_v",
    default=(),
    place="gpim",
    parameters={"gpim.rate_widening_v": (
        [], f"rate-dependent GPIM: every threshold widens by sum c rho_f / (rho_f + s_k) [V], rho_f = |dv/dt| through "
            f"the lags {list(RATE_FILTERS_S)} s, s_k = {list(RATE_SCALES_V_S)} V/s; {TERM_COUNT} coefficients c [V], "
            f"filter-major (empty or all 0: none; {EARLIER_TERM_COUNT}, as files before the 5 ms filter have them, "
            "are the first filters' and the 5 ms filter's are 0)")},
    # zeros rather than []: an empty list has no element type for a ROS parameter
    write=lambda widening: {"gpim.rate_widening_v": floats(widening) or [0.0] * TERM_COUNT},
    read=_read,
)
