"""Gains chosen on an identified model."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "tune": "tuner",
    "TuningLimits": "tuner",
    "TuningResult": "tuner",
    "TuningError": "tuner",
    "TUNABLE_STRATEGIES": "tuner",
})
