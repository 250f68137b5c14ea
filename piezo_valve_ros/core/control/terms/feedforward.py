"""Whether the feedforward inverts G_v too (W = F / G_v, ``compensation.DynamicFeedforward``)."""
from __future__ import annotations

from ...validation import as_bool
from .base import Term

TERM = Term(
    field="dynamic_feedforward",
    default=False,
    place="dynamics",
    parameters={"feedforward.dynamics": (False, "the feedforward also inverts G_v (W = F/G_v, F critically damped 3x "
                                                "faster); ff_pid_g then shapes its reference with F")},
    write=lambda on: {"feedforward.dynamics": bool(on)},
    read=lambda get: get("feedforward.dynamics", as_bool),
)
