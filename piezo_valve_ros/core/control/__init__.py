"""The controller: the paper's six strategies (a registry), the compensation model and its inverse."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "ValveController": "strategies",
    "ControllerConfig": "strategies",
    "PIDGains": "strategies",
    "REGISTRY": "strategies",
    "STRATEGIES": "strategies",
    "Strategy": "strategies",
    "gain_set": "strategies",
    "TABLE1_GAINS": "strategies",
    "CompensationModel": "compensation",
    "BacklashModel": "terms.backlash",
    "CreepModel": "compensation",
    "DynamicFeedforward": "compensation",
    "FITTED_RANGE_MARGIN": "compensation",
    "GUARD_HOLD_S": "strategies",
    "GUARD_MAX_HOLD_S": "strategies",
    "GUARD_WINDOW_S": "strategies",
    "MIN_FITTED_SPAN_SHARE": "compensation",
    "MODEL_DEFAULTS": "compensation",
    "MODEL_PARAMETERS": "compensation",
    "ModelValve": "forward",
    "PlayInverse": "terms.backlash",
    "SAFE_PERIOD_S": "strategies",
    "StaticInverse": "compensation",
    "TERMS": "terms",
    "command_range_for": "compensation",
    "default_gain_set": "strategies",
    "fitted_range_problems": "compensation",
    "has_feedback": "strategies",
})
