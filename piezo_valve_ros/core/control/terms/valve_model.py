"""G_v(s): the valve's linear dynamics, which the dynamic feedforward inverts and FF PID G shapes with."""
from __future__ import annotations

from ...model.dynamics import PAPER_VALVE_MODEL, ContinuousTF
from ...validation import as_float_list
from .base import Term, floats


def _read(get):
    num, den = get("valve_model.num", as_float_list), get("valve_model.den", as_float_list)
    return None if num is None or den is None else ContinuousTF(tuple(num), tuple(den))


TERM = Term(
    field="valve_model",
    default=PAPER_VALVE_MODEL,
    place="dynamics",
    parameters={"valve_model.num": (list(PAPER_VALVE_MODEL.num), "G_v(s) numerator"),
                "valve_model.den": (list(PAPER_VALVE_MODEL.den), "G_v(s) denominator")},
    write=lambda tf: {"valve_model.num": floats(tf.num), "valve_model.den": floats(tf.den)},
    read=_read,
)
