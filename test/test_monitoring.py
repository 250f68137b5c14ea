"""The health monitor's core (core/monitoring/health.py): the controller's model run on the applied voltage
of closed-loop operation, judged on sliding windows against the sensor noise; seeded simulations."""
from dataclasses import replace

import numpy as np
import pytest

from piezo_valve_ros.core.control.compensation import CompensationModel
from piezo_valve_ros.core.control.strategies import ControllerConfig, PIDGains, ValveController
from piezo_valve_ros.core.monitoring.health import HealthLimits, HealthMonitor, Level
from piezo_valve_ros.core.model.hysteresis import GPIM
from piezo_valve_ros.core.sim.experiments import run_closed_loop
from piezo_valve_ros.core.sim.simulator import DriftParams, SensorParams, SimulatedValve, ValveSimConfig
from valve_battery import staircase_and_sines_um

DT = 1e-3
PLAIN = replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=True, sensor=SensorParams())
PID_HC = PIDGains(0.4823, 213.8982, 0.0)
ONSET_S = 60.0
DRIFT = DriftParams(True, offset_um=1.5, gain_change=0.0, time_constant_s=10.0, start_s=ONSET_S)


def operating_rows(config: ValveSimConfig, seconds: float, seed: int = 5, hold_after_s: float = np.inf) -> np.ndarray:
    """``samples`` rows of the simulated valve under PID HC following levels and slow sines (the reference
    held at its last value after ``hold_after_s``)."""
    valve = SimulatedValve(replace(config, seed=seed))
    controller = ValveController(ControllerConfig(strategy="pid_hc", gains=PID_HC, dt=DT), CompensationModel())
    controller.reset(5.0)
    ref = np.concatenate([staircase_and_sines_um(seed + k, DT, 60.0) for k in range(int(np.ceil(seconds / 60.0)))])
    ref = ref[:int(round(seconds / DT))]
    hold = int(round(min(hold_after_s, seconds) / DT))
    ref[hold:] = ref[hold - 1] if hold else ref[0]
    rec = run_closed_loop(valve, controller, ref * 1e-6)
    return np.column_stack((np.arange(rec.command_v.size - 1) * DT, rec.command_v[:-1], rec.position_m[1:]))


def verdicts(monitor: HealthMonitor, rows: np.ndarray, chunk: int = 100):
    return [h for k in range(0, len(rows), chunk) for h in monitor.add(rows[k:k + chunk])]


def test_a_valve_that_matches_its_model_stays_ok():
    health = verdicts(HealthMonitor(CompensationModel(), DT), operating_rows(PLAIN, 180.0))
    assert len(health) == 31                                   # a window every 5 s once 20 s are held (5 s settle)
    assert all(h.level is Level.OK for h in health), [(h.end_s, h.level, h.ratio) for h in health]
    assert max(h.ratio for h in health) < 1.0
    assert all(0.04 < h.noise_um < 0.06 for h in health)       # the simulated LVDT's 0.05 um


def test_a_drift_that_sets_in_is_warned_within_ten_seconds_named_and_cleared_by_a_refit():
    """A 1.5 um drift sets in at 60 s (10 s time constant): OK before, WARN then ERROR within 15 s, named as
    an offset the model lacks; a refit that takes the offset in (pushed at 150 s) brings it back to OK."""
    rows = operating_rows(replace(PLAIN, drift=DRIFT), 210.0)
    monitor = HealthMonitor(CompensationModel(), DT)
    split = int(round(150.0 / DT))
    before = verdicts(monitor, rows[:split])
    assert all(h.level is Level.OK for h in before if h.end_s <= ONSET_S)
    after = [h for h in before if h.end_s > ONSET_S]
    first_warning = next(h for h in after if h.level is not Level.OK)
    first_error = next(h for h in after if h.level is Level.ERROR)
    assert first_warning.end_s - ONSET_S <= 10.0 and first_error.end_s - ONSET_S <= 15.0
    assert all(h.level is Level.ERROR for h in after if h.end_s >= first_error.end_s)
    assert after[-1].resembles.startswith("drift: an offset of +1.4") or after[-1].resembles.startswith("drift: an offset of +1.5"), after[-1].resembles
    assert after[-1].residual_mean_um == pytest.approx(1.5, abs=0.1)
    g = CompensationModel().gpim
    refit = CompensationModel(GPIM(g.thresholds, g.weights, g.a0, g.a1, g.offset_um + 1.5))
    monitor.set_model(refit)
    cleared = verdicts(monitor, rows[split:])
    assert cleared and all(h.level is Level.OK for h in cleared), [(h.end_s, h.level, h.ratio) for h in cleared]


def test_a_valve_held_still_is_not_judged():
    health = verdicts(HealthMonitor(CompensationModel(), DT), operating_rows(PLAIN, 90.0, hold_after_s=30.0))
    late = [h for h in health if h.start_s > 31.0]
    assert late and all(h.level is Level.STALE and "not enough excitation" in h.message for h in late)


def test_bad_limits_and_rows_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="error_ratio .* must exceed warn_ratio"):
        HealthMonitor(CompensationModel(), DT, HealthLimits(warn_ratio=3.0, error_ratio=2.0))
    with pytest.raises(ValueError, match="step_s .* must not exceed window_s"):
        HealthMonitor(CompensationModel(), DT, HealthLimits(window_s=5.0, step_s=10.0))
    with pytest.raises(ValueError, match="dt must be > 0"):
        HealthMonitor(CompensationModel(), 0.0)
    with pytest.raises(ValueError, match=r"rows must be \(N, 3\)"):
        HealthMonitor(CompensationModel(), DT).add(np.zeros((10, 2)))
