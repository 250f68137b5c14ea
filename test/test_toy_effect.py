"""The registries carry the chain: a toy dead band written as three modules (``toy_deadband``: its effect, its
compensation term, its stage), with nothing else in the package edited, is simulated, identified and compensated."""
from dataclasses import replace

import numpy as np
import pytest

import toy_deadband
from toy_deadband.stage import DeadBandParams

from piezo_valve_ros.core.control import CompensationModel, ControllerConfig, ModelValve, PIDGains, ValveController
from piezo_valve_ros.core.identification import Record, analyse
from piezo_valve_ros.core.sim import SensorParams, SimulatedValve, ValveSimConfig, run_closed_loop, simulate_rows
from piezo_valve_ros.core.sim import identification_voltage, validation_voltage

DT = 1e-3
WIDTH_UM = 1.5
PLAIN = replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=True, sensor=SensorParams())


@pytest.fixture
def toy(monkeypatch):
    toy_deadband.install(monkeypatch)
    # the band at the middle of the spool's travel on the training run
    y = simulate_rows(identification_voltage(DT), replace(PLAIN, sensor=SensorParams(noise_enabled=False)))[:, 2] * 1e6
    centre = 0.5 * (y.min() + y.max())
    return replace(PLAIN, added=(("deadband", DeadBandParams(True, centre, WIDTH_UM)),)), centre


def test_the_toy_effect_has_its_three_homes(toy):
    from test_architecture import check_three_homes
    from piezo_valve_ros.core.control import terms
    check_three_homes()
    assert "deadband" in CompensationModel().terms and terms.TERMS[-1].place == "output"


def test_the_toy_stage_is_folded_into_the_simulated_valve_and_switched_by_its_own_switch(toy):
    from piezo_valve_ros.core.sim.stages import STAGE_SWITCHES
    valve, centre = toy
    switch = next(s for s in STAGE_SWITCHES if s.name == "deadband")
    assert switch.is_on(valve) and not switch.is_on(switch.set(valve, False))
    v = 5.0 + 4.0 * np.sin(np.linspace(0.0, 20.0, 4000))
    quiet = replace(valve, sensor=SensorParams(noise_enabled=False))
    with_band = SimulatedValve(quiet).run(v) * 1e6
    without = SimulatedValve(switch.set(quiet, False)).run(v) * 1e6
    inside = np.abs(without - centre) < WIDTH_UM - 0.05
    assert inside.any() and np.allclose(with_band[inside], centre)
    stepped = SimulatedValve(quiet)
    assert np.allclose([stepped.step(x) * 1e6 for x in v], with_band, atol=1e-9)


def test_the_toy_effect_is_identified_compensated_and_cuts_the_error_where_the_reference_crosses_it(toy):
    valve, centre = toy
    train = Record.from_rows(simulate_rows(identification_voltage(DT), replace(valve, seed=1)))
    validate = Record.from_rows(simulate_rows(validation_voltage(DT), replace(valve, seed=2)))
    analysis = analyse(train, validate)
    report = analysis.report.to_json()
    assert report["effects_added"] == ["deadband"], (report["effects_added"], report["residual"])
    width = report["final_model"]["deadband"]["width_um"]
    assert 0.7 * WIDTH_UM < width < 1.3 * WIDTH_UM, width

    from piezo_valve_ros.identify import compensation
    model = compensation(analysis, dynamic_feedforward=False).controller_model
    assert model.deadband.width_um == pytest.approx(width)
    # the controller's parameters carry it, and read back
    params = model.to_parameters()
    assert params["deadband.width_um"] == width
    assert CompensationModel.from_parameters(params).to_parameters() == params
    # the model run forwards holds still in the band as the valve does
    v = 5.0 + 3.0 * np.sin(np.linspace(0.0, 30.0, 6000))
    block = ModelValve(model, DT, 5.0).run(v)
    stepped = ModelValve(model, DT, 5.0)
    assert np.allclose(block, [stepped.step(x) for x in v], atol=1e-15)

    t = np.arange(int(6.0 / DT)) * DT
    ref = centre * 1e-6 + 10e-6 * np.sin(2.0 * np.pi * 0.5 * t)     # crossing the band twice a second
    errors = {}
    for name, m in (("without", replace(model, deadband=toy_deadband.term.DeadBandModel())), ("with", model)):
        sim = SimulatedValve(replace(valve, seed=5, sensor=SensorParams(noise_enabled=False)))
        ctl = ValveController(ControllerConfig(strategy="ol_hc", gains=PIDGains(0, 0), dt=DT), m)
        ctl.reset(5.0)
        rec = run_closed_loop(sim, ctl, ref)
        y = rec.position_m[1:] * 1e6
        errors[name] = (y - ref[:-1] * 1e6)[int(2.0 / DT):]
    rms = {k: float(np.sqrt(np.mean((e - e.mean()) ** 2))) for k, e in errors.items()}
    assert rms["with"] < 0.6 * rms["without"], rms
