"""The valve's models: the GPIM and its inverse, G_v, the drive, the output map, rate dependence, and the filter
banks the identification runs them through."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "GPIM": "hysteresis",
    "GPIMParams": "hysteresis",
    "PAPER_GPIM": "hysteresis",
    "PlayOperatorBank": "hysteresis",
    "play_batch": "hysteresis",
    "NotInvertibleError": "hysteresis",
    "ContinuousTF": "dynamics",
    "PAPER_VALVE_MODEL": "dynamics",
    "filter_rows": "iir",
    "filter_rows_at_rest": "at_rest",
    "discretised": "at_rest",
    "first_order_bank": "iir",
})
