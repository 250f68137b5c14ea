"""The voltages a model was fitted on: the command range it may be used with (``compensation.fitted_range_problems``)."""
from __future__ import annotations

from ...validation import as_float_list
from .base import Term, floats


def _read(get):
    fitted = get("model.fitted_range_v", as_float_list)
    return None if fitted is None else (tuple(fitted) if any(fitted) else ())


TERM = Term(
    field="fitted_range_v",
    default=(),
    parameters={"model.fitted_range_v": ([0.0, 0.0], "voltages [lo, hi] the model was fitted on [V] ([0, 0]: unknown); "
                                                     "the command range must lie within them (a quarter of their span "
                                                     "beyond at most) and span at least a quarter of them")},
    write=lambda fitted: {"model.fitted_range_v": floats(fitted) or [0.0, 0.0]},
    read=_read,
)
