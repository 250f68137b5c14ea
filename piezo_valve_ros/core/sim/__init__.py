"""The simulated valve, its experiments and signals."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "SimulatedValve": "simulator",
    "ValveSimConfig": "simulator",
    "simulate_rows": "experiments",
    "run_closed_loop": "experiments",
    "paper_step_tests": "experiments",
    "identification_voltage": "signals",
    "validation_voltage": "signals",
    "training_voltage": "signals",
})
