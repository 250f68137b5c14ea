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
    "BacklashParams": "simulator",
    "CreepParams": "simulator",
    "DEFAULT_SWEEP_HZ": "experiments",
    "DriftParams": "simulator",
    "Hysteresis": "stages.hysteresis",
    "PAPER_STEPS_UM": "signals",
    "RateDependenceParams": "simulator",
    "STAGE_SWITCHES": "simulator",
    "SaturationParams": "simulator",
    "SensorParams": "simulator",
    "frequency_response": "experiments",
    "load_profile": "signals",
    "ramp_profile": "signals",
    "responses": "experiments",
    "rig_training_voltage": "signals",
    "run_delayed_loop": "experiments",
    "sine_profile": "signals",
    "step_reference_m": "signals",
    "validation_reference_m": "signals",
})
