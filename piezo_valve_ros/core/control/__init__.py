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
})
