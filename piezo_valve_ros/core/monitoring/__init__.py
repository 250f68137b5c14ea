"""The health monitor: a running valve judged against its model."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "HealthMonitor": "health",
    "HealthLimits": "health",
    "Health": "health",
    "Level": "health",
    "RefitPolicy": "refits",
    "RefitDecision": "refits",
    "GAIN": "refits",
    "GAIN_PREFIX": "health",
    "OFFSET_PREFIX": "health",
    "PUSH_COLUMNS": "refits",
    "UNDO": "refits",
    "push_row": "refits",
})
