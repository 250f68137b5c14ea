"""Gains chosen on an identified model."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "tune": "tuner",
    "TuningLimits": "tuner",
    "TuningResult": "tuner",
    "TuningError": "tuner",
    "TUNABLE_STRATEGIES": "tuner",
    "DERIVATIVE_STARTS_S": "tuner",
    "LoopMargins": "tuner",
    "MIN_GAIN_MARGIN_DB": "tuner",
    "MIN_PHASE_MARGIN_DEG": "tuner",
    "OVERSHOOT_LIMIT_PCT": "tuner",
    "StepScore": "tuner",
    "dynamics_variants": "tuner",
    "linear_step": "tuner",
    "loop_margins": "tuner",
    "outside_limits": "tuner",
    "plant_gain_range": "tuner",
    "robust_overshoot_pct": "tuner",
    "step_score": "tuner",
    "time_scaled": "tuner",
})
