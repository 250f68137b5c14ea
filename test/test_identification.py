"""Identification core: fits, the residual loop on data with undeclared effects, creep compensation."""
import math
import re
from dataclasses import replace

import numpy as np
import pytest

from piezo_valve_ros.core.experiments import run_closed_loop, simulate_rows
from piezo_valve_ros.core.hysteresis import inverse_problems
from piezo_valve_ros.core.identification import (IdentificationError, Record, fit_linear_gpim, fit_paper_gpim,
                                                 quality)
from piezo_valve_ros.core.residual import analyse
from piezo_valve_ros.core.signals import identification_voltage, validation_voltage
from piezo_valve_ros.core.simulator import (CreepParams, DriftParams, RateDependenceParams, SaturationParams,
                                            SensorParams, SimulatedValve, ValveSimConfig)
from piezo_valve_ros.core.strategies import ControllerConfig, CreepModel, PIDGains, ValveController

DT = 1e-3  # 1 kHz records keep the suite fast; the 10 kHz path is exercised by the CLI test and the benchmark
CLEAN = replace(ValveSimConfig(dt=DT).ideal(), dynamics_enabled=False, sensor=SensorParams())  # hysteresis + LVDT noise
TRAIN_V = identification_voltage(DT, 30.0)
VALID_V = validation_voltage(DT)


def records(config, post=None):
    """(training, validation) records of a fresh simulated valve; ``post(rows)`` adds an effect the simulator lacks."""
    out = []
    for v, seed in ((TRAIN_V, 11), (VALID_V, 12)):
        rows = simulate_rows(v, replace(config, seed=seed))
        if post is not None:
            post(rows)
        out.append(Record.from_rows(rows))
    return out


def linear_drift(rows):  # a drift form the detector does not use (its exponential/linear family is in time
    rows[:, 2] += 0.06e-6 * rows[:, 0] - 1.0e-6 * np.sin(2 * np.pi * rows[:, 0] / 400.0)  # since start)


def arctan_flattening(rows):  # end-stop flattening of another shape than tanh
    s = 120e-6
    rows[:, 2] = s * (2 / np.pi) * np.arctan(np.pi * rows[:, 2] / (2 * s))


CASES = {
    # effect -> (simulator config, extra post-processing)
    "creep (exponential, one 0.7 s lag)": ("creep", replace(CLEAN, creep=CreepParams(True, (0.06,), (0.7,))), None),
    "creep (logarithmic, four lags)": ("creep", replace(CLEAN, creep=CreepParams(True, (0.02,) * 4,
                                                                                  (0.05, 0.5, 5.0, 50.0))), None),
    "dynamics (the valve's G_v)": ("dynamics", replace(CLEAN, dynamics_enabled=True), None),
    "dynamics (rate dependence, 8 ms)": ("dynamics", replace(CLEAN, rate=RateDependenceParams(True, 0.1, 0.008)), None),
    "asymmetry (descending envelope)": ("asymmetry", replace(CLEAN, descending_envelope=(0.90, 0.45)), None),
    "drift (thermal, exponential)": ("drift", replace(CLEAN, drift=DriftParams(True, 3.0, 0.02, 30.0)), None),
    "drift (linear plus slow wave)": ("drift", CLEAN, linear_drift),
    "saturation (tanh, 150 um)": ("saturation", replace(CLEAN, saturation=SaturationParams(True, 150.0)), None),
    "saturation (arctan end stop)": ("saturation", CLEAN, arctan_flattening),
}


@pytest.mark.parametrize("case", list(CASES))
def test_undeclared_effect_is_named_and_halves_the_held_out_peak(case):
    expected, config, post = CASES[case]
    train, validate = records(config, post)
    report = analyse(train, validate).report
    assert report["effects_added"][:1] == [expected], report["effects_added"]
    assert report["final"]["validate"]["peak_um"] <= 0.5 * report["baseline"]["validate"]["peak_um"]
    assert report["final"]["validate"]["rms_um"] < report["baseline"]["validate"]["rms_um"]
    assert report["unexplained"] is False
    d = [x for x in report["diagnosis"] if x["effect"] == expected][0]
    assert d["added"] and d["statistic"] >= d["threshold"] and "threshold" in d["evidence"]


@pytest.mark.parametrize("held_out", [False, True])
def test_clean_data_adds_nothing(held_out):
    train, validate = records(CLEAN)
    report = analyse(train, None if held_out else validate).report
    assert report["effects_added"] == []
    assert report["unexplained"] is False
    assert report["final"]["validate"]["peak_pct"] < 0.6
    for key in ("range_um", "baseline", "effects_added", "diagnosis", "final", "unexplained"):
        assert key in report
    assert set(report["baseline"]["validate"]) == {"rms_um", "peak_um", "peak_pct"}


def test_two_effects_are_both_found_on_held_out_data():
    config = replace(CLEAN, creep=CreepParams(True, (0.04, 0.04), (0.3, 3.0)),
                     saturation=SaturationParams(True, 160.0))
    train, _ = records(config)
    report = analyse(train).report  # last 30 % held out
    assert sorted(report["effects_added"]) == ["creep", "saturation"]
    assert report["final"]["validate"]["peak_um"] <= 0.5 * report["baseline"]["validate"]["peak_um"]


def test_structure_outside_the_catalogue_is_reported_unexplained():
    def hum(rows):  # a 7.3 Hz mechanical hum, unrelated to the input
        rows[:, 2] += 1.5e-6 * np.sin(2 * np.pi * 7.3 * rows[:, 0])
    train, validate = records(CLEAN, hum)
    report = analyse(train, validate).report
    assert report["unexplained"] is True
    line_hz = float(re.search(r"strongest spectral line ([0-9.]+) Hz", report["residual"]).group(1))
    assert abs(line_hz - 7.3) < 0.1
    assert report["effects_added"] == []


def test_default_simulated_valve_finds_its_effects():
    train, validate = records(ValveSimConfig(dt=DT))
    report = analyse(train, validate).report
    assert {"dynamics", "creep"} <= set(report["effects_added"])
    assert "asymmetry" not in report["effects_added"] and "drift" not in report["effects_added"]
    assert report["final"]["validate"]["rms_um"] < 0.2 * report["baseline"]["validate"]["rms_um"]


def test_baseline_fits_linear_is_invertible_and_paper_nls_is_reported():
    train, validate = records(replace(CLEAN, gpim=replace(CLEAN.gpim, rho=6.5, tau=0.9)))
    linear = fit_linear_gpim(train)
    assert inverse_problems(linear.gpim) == []
    paper = fit_paper_gpim(train)
    q_lin = quality(validate.position_um, linear.predict(validate), validate.range_um)
    q_nls = quality(validate.position_um, paper.model.predict(validate), validate.range_um)
    assert q_lin.peak_pct < 1.0 and q_nls.peak_pct < 1.5
    assert paper.condition_number > 1e6  # the 5-parameter form is over-parameterised (a0 vs alpha/rho/tau)
    report = analyse(train, validate).report
    assert set(report["baseline_fits"]) == {"linear", "paper_nls"}


@pytest.mark.parametrize("bad, message", [
    (lambda r: Record(r.time_s, np.full(len(r), 5.0), r.position_um), "constant"),
    (lambda r: Record(r.time_s, r.voltage_v, np.where(np.arange(len(r)) == 500, np.nan, r.position_um)), "non-finite"),
    (lambda r: r.slice(0, 50), "at least"),
    (lambda r: Record(r.time_s[:3000], np.linspace(0, 10, 3000), r.position_um[:3000]), "reverses"),
])
def test_records_that_cannot_be_fitted_say_why(bad, message):
    train, _ = records(CLEAN)
    with pytest.raises(IdentificationError, match=message):
        analyse(bad(train))


def test_creep_compensation_cuts_the_step_and_hold_error():
    config = replace(CLEAN, creep=CreepParams(True, (0.03, 0.03, 0.03), (0.1, 1.0, 10.0)), sensor=SensorParams())
    train, validate = records(config)
    analysis = analyse(train, validate)
    assert analysis.report["effects_added"][0] == "creep"
    model = analysis.final
    taus, gains = model.creep_compensation()
    # OL HC with the identified GPIM, with and without its creep compensation, on a step-and-hold demand
    levels_um = (30.0, -40.0, 45.0, -10.0)
    ref = np.concatenate([np.full(int(2.0 / DT), x) for x in levels_um]) * 1e-6
    errors = {}
    for name, creep in (("without", CreepModel()), ("with", CreepModel(tuple(taus), tuple(gains)))):
        valve = SimulatedValve(replace(config, seed=5))
        ctl = ValveController(ControllerConfig(strategy="ol_hc", gains=PIDGains(0, 0), dt=DT), model.gpim,
                              creep=creep)
        ctl.reset(5.0)
        rec = run_closed_loop(valve, ctl, ref)
        y = np.append(rec.position_m[1:], np.nan)[:-1] * 1e6
        hold = np.concatenate([np.arange(k * 2000 + 100, (k + 1) * 2000 - 1) for k in range(len(levels_um))])
        errors[name] = np.abs(y[hold] - ref[:-1][hold] * 1e6)
    assert errors["with"].max() < 0.5 * errors["without"].max()
    assert np.sqrt(np.mean(errors["with"] ** 2)) < 0.35 * np.sqrt(np.mean(errors["without"] ** 2))


def test_creep_model_rejects_bad_values():
    assert CreepModel((1.0,), (0.95,)).problems()
    assert CreepModel((1.0, 2.0), (0.1,)).problems()
    assert CreepModel((-1.0,), (0.1,)).problems()
    assert CreepModel((1.0,), (math.nan,)).problems()
    with pytest.raises(ValueError):
        ValveController(creep=CreepModel((1.0,), (0.95,)))
