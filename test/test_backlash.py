"""Backlash on the spool's path, end to end: simulated (``sim.backlash``), identified (the ``backlash`` effect with
its width) and compensated (the controller's play inverse on the reference path)."""
from dataclasses import replace

import numpy as np
import pytest

from shared import computed_once

from piezo_valve_ros.core.control import CompensationModel
from piezo_valve_ros.core.control import ModelValve
from piezo_valve_ros.core.control import ControllerConfig, PIDGains, ValveController
from piezo_valve_ros.core.control import BacklashModel, PlayInverse
from piezo_valve_ros.core.identification import Record
from piezo_valve_ros.core.identification import analyse
from piezo_valve_ros.core.model import output_play
from piezo_valve_ros.core.sim import run_closed_loop, simulate_rows
from piezo_valve_ros.core.sim import identification_voltage, validation_voltage
from piezo_valve_ros.core.sim import BacklashParams, SensorParams, SimulatedValve, ValveSimConfig

DT = 1e-3       # 1 kHz: G_v resolved, half the samples of the battery's 2 kHz
WIDTH_UM = 1.5
VALVE = replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=True, sensor=SensorParams(),
                backlash=BacklashParams(True, WIDTH_UM))


def _analysis():
    def compute():
        train = Record.from_rows(simulate_rows(identification_voltage(DT), replace(VALVE, seed=1)))
        validate = Record.from_rows(simulate_rows(validation_voltage(DT), replace(VALVE, seed=2)))
        return analyse(train, validate)
    return computed_once("test_backlash._analysis", compute)


def test_the_play_is_linear_in_its_input_and_width_for_its_contacts():
    x = 5.0 * np.sin(np.linspace(0.0, 12.0, 3001)) + np.linspace(0.0, 2.0, 3001)
    for width in (0.0, 0.3, 1.5):
        y, index, side = output_play(x, width)
        assert np.allclose(y, x[index] + side * width, atol=1e-12)
        assert np.all(np.abs(y - x) <= width + 1e-12)


def test_the_play_inverse_takes_up_the_clearance_in_the_direction_the_reference_moves():
    inverse = PlayInverse(BacklashModel(0.5), 0.0)
    assert [inverse.step(y) for y in (0.0, 1.0, 2.0, 2.0, 1.5, 1.0)] == [0.0, 1.5, 2.5, 2.5, 1.0, 0.5]
    ref = 10.0 * np.sin(np.linspace(0.0, 20.0, 4001))
    inverse = PlayInverse(BacklashModel(0.7), ref[0])
    x = np.array([inverse.step(y) for y in ref])
    y = output_play(x, 0.7)[0]
    assert np.max(np.abs(y - ref)) < 1e-9          # the play after its inverse gives the reference back


def test_a_clearance_is_checked_before_the_controller_uses_it():
    for width, says in [(-0.1, ">= 0"), (float("nan"), ">= 0"), (50.0, "output span")]:
        model = replace(CompensationModel(), backlash=BacklashModel(width))
        assert any(says in p for p in model.problems()), model.problems()
        with pytest.raises(ValueError):
            ValveController(compensation=model)
    params = replace(CompensationModel(), backlash=BacklashModel(0.4)).to_parameters()
    assert params["backlash.width_um"] == 0.4
    assert CompensationModel.from_parameters(params).backlash == BacklashModel(0.4)


@pytest.mark.slow
def test_a_valve_with_backlash_is_named_backlash_with_its_width_and_nothing_else():
    report = _analysis().report.to_json()
    assert report["effects_added"] == ["backlash"], (report["effects_added"], report["residual"])
    assert report["final"]["validate"]["rms_um"] < 1.5 * report["noise_floor_um"]
    assert report["final"]["validate"]["rms_um"] < 0.6 * report["baseline"]["validate"]["rms_um"]
    width = report["final_model"]["backlash"]["width_um"]
    assert 0.7 * WIDTH_UM < width < 1.3 * WIDTH_UM, width


@pytest.mark.slow
def test_the_identified_backlash_is_compensated_and_cuts_the_error_after_each_reversal():
    from piezo_valve_ros.identify import compensation
    with_backlash = compensation(_analysis(), dynamic_feedforward=False).controller_model
    assert with_backlash.backlash.width_um > 0.5 * WIDTH_UM
    t = np.arange(int(6.0 / DT)) * DT
    ref = 30e-6 * (2.0 / np.pi) * np.arcsin(np.sin(2.0 * np.pi * 0.5 * t))     # a triangle: a reversal each second
    errors = {}
    for name, model in (("without", replace(with_backlash, backlash=BacklashModel())), ("with", with_backlash)):
        valve = SimulatedValve(replace(VALVE, seed=5, sensor=SensorParams(noise_enabled=False)))
        ctl = ValveController(ControllerConfig(strategy="ol_hc", gains=PIDGains(0, 0), dt=DT), model)
        ctl.reset(5.0)
        rec = run_closed_loop(valve, ctl, ref)
        y = rec.position_m[1:] * 1e6
        errors[name] = (y - ref[:-1] * 1e6)[int(2.0 / DT):]        # after the first cycle
    rms = {k: float(np.sqrt(np.mean((e - e.mean()) ** 2))) for k, e in errors.items()}
    assert rms["with"] < 0.6 * rms["without"], rms


def test_the_model_valve_runs_the_play_step_by_step_as_in_a_block():
    model = replace(CompensationModel(), backlash=BacklashModel(0.6))
    v = 5.0 + 3.0 * np.sin(np.linspace(0.0, 30.0, 6000))
    block = ModelValve(model, DT, 5.0).run(v)
    stepped = ModelValve(model, DT, 5.0)
    assert np.allclose(block, [stepped.step(x) for x in v], atol=1e-15)
    plain = ModelValve(CompensationModel(), DT, 5.0).run(v)
    assert 0.5e-6 < np.max(np.abs(block - plain)) <= 0.6e-6 + 1e-12


def test_the_simulated_backend_takes_a_clearance_and_refuses_a_negative_one():
    from piezo_valve_ros.backends import backend_parameters, sim_config_from_parameters
    names = {p.name for p in backend_parameters("sim")}
    assert {"sim.backlash", "sim.backlash_width_um"} <= names
    assert sim_config_from_parameters({}).backlash.enabled is False           # off unless switched on
    config = sim_config_from_parameters({"backlash": True, "backlash_width_um": 0.3})
    assert config.backlash == BacklashParams(True, 0.3)
    with pytest.raises(ValueError, match="sim.backlash_width_um must be >= 0"):
        sim_config_from_parameters({"backlash_width_um": -0.1})
    # what the stage does: the spool stands still until the actuator has crossed the clearance
    valve = SimulatedValve(replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=False, backlash=BacklashParams(True, 1.0)))
    ideal = SimulatedValve(replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=False))
    up = np.linspace(5.0, 7.0, 400)
    down = np.linspace(7.0, 6.8, 40)
    y, y0 = valve.run(np.concatenate((up, down))) * 1e6, ideal.run(np.concatenate((up, down))) * 1e6
    assert abs(y[399] - (y0[399] - 1.0)) < 1e-9                             # rising: a clearance behind
    assert np.ptp(y[400:]) < 1e-9 < np.ptp(y0[400:])                         # a small reversal: held


def test_a_backlash_model_swapped_in_mid_run_keeps_the_references_direction():
    """A new clearance loaded while the reference rests after a rise: the play inverse goes on adding it on the side
    the reference came from (upwards), as a controller that had the new clearance from the start does; forgetting
    the direction would drop the clearance (the spool ~width short of the reference until the next move)."""
    t = np.arange(int(1.0 / DT)) * DT
    ref = np.concatenate((10e-6 * t, np.full(int(2.0 / DT), 10e-6)))   # a rise over 1 s, then held for 2 s
    config = ControllerConfig(strategy="ol_hc", gains=PIDGains(0, 0), dt=DT)
    swapped = ValveController(config, replace(CompensationModel(), backlash=BacklashModel(0.3)))
    fresh = ValveController(config, replace(CompensationModel(), backlash=BacklashModel(1.2)))
    plain = ValveController(config, CompensationModel())
    commands = {}
    for name, ctl in (("swapped", swapped), ("fresh", fresh), ("plain", plain)):
        ctl.reset(5.0)
        out = []
        for k, r in enumerate(ref):
            if name == "swapped" and k == int(1.5 / DT):    # mid-run, the reference at rest after its rise
                ctl.set_model(replace(CompensationModel(), backlash=BacklashModel(1.2)))
            out.append(ctl.step(r, 0.0))
        commands[name] = np.array(out)
    assert abs(commands["swapped"][-1] - commands["fresh"][-1]) < 1e-6, (commands["swapped"][-1], commands["fresh"][-1])
    assert commands["fresh"][-1] - commands["plain"][-1] > 0.01   # (the clearance moves the command: the check bites)
