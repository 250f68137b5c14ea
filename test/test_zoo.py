"""The residual loop on valves written from the literature's equations (``valve_zoo.py``: nothing of the package's
catalogue, simulator or signals), each recorded in two sessions that start after an excitation nobody recorded.

Each must be judged right: the names it may give and no other, every one it must give unless it says unexplained.
Cases it does not yet judge right are marked so, with why: strict, so a fix shows as an unexpected pass.
"""
import pytest

from shared import computed_once
from valve_zoo import CASES

from piezo_valve_ros.core.identification import Record
from piezo_valve_ros.core.identification import check_report
from piezo_valve_ros.core.identification import analyse

NOT_YET: dict[str, str] = {}


def _run(case):
    """(report, log lines) of the case's first record, computed once per test run."""
    def compute():
        train, validate = case.records(1)
        lines: list[str] = []
        analysis = analyse(Record(train[:, 0], train[:, 1], train[:, 2]),
                           Record(validate[:, 0], validate[:, 1], validate[:, 2]), log=lines.append)
        return analysis.report.to_json(), lines
    name = next(n for n, c in CASES.items() if c is case)
    return computed_once(f"test_zoo._run({name!r})", compute)


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(strict=True, reason=NOT_YET[n]))
                                  if n in NOT_YET else n for n in CASES])
def test_a_valve_from_the_literature_is_judged_right(name):
    case = CASES[name]
    report, lines = _run(case)
    assert check_report(report) == []
    # one decision, stated once: what the decisions compared is what the report says (no later re-scoring)
    assert not any("worse on held-out data than the baseline" in line for line in lines), lines
    assert report["final"]["validate"]["rms_um"] <= report["baseline"]["validate"]["rms_um"] + 1e-9
    assert case.judged_right(report["effects_added"], report["unexplained"]), (
        report["effects_added"], report["unexplained"], report["residual"])


def test_a_two_session_200_hz_record_names_the_delay_each_sessions_offset_and_the_validation_start():
    """The micromanipulator at 200 Hz: the training session and a validation session recorded after an unrecorded
    excitation with the sensor re-zeroed 1.2 um off, a 10 ms transport delay.  The report names the delay (the
    dynamics effect's, 5-15 ms with the valve's own lag), the validation session's offset against the training
    one's, and that its start was estimated; the 200 Hz warning says what the rate cannot show, not that it
    cannot identify."""
    report, lines = _run(CASES["200 Hz micromanipulator, two sessions, re-zeroed sensor, 10 ms delay"])
    assert "dynamics" in report["effects_added"]
    assert 0.005 <= report["transport_delay_s"] <= 0.015
    # one 1 Hz sine cannot tell the delay from a lag and the loop's width: the delay is chosen on held-out data
    assert any(line.startswith("dynamics: transport delay ") and "chosen on held-out data" in line for line in lines)
    training, validation = report["sessions"]
    assert training["record"] == "training" and training["offset_um"] == 0.0
    assert validation["record"] == "validation" and validation["offset_um"] == pytest.approx(1.2, abs=0.2)
    assert validation["start"].startswith("its own, estimated for the model")
    assert any(w.startswith("the record is sampled at 200 Hz") and "identified as at any rate" in w
               for w in report["warnings"])
    # the unknown start no longer stands as the record's peak error (it was 21 % of the range from outside)
    assert report["final"]["validate"]["peak_pct"] < 5.0
    assert any(line.startswith("validation session: sensor offset +1.") for line in lines), lines


@pytest.mark.slow
@pytest.mark.parametrize("name", ["rate-dependent PI, multiplicative thresholds",
                                  "modified PI with rate-dependent slopes (Ang)"])
def test_rate_dependence_in_the_literatures_forms_is_named_dynamics(name):
    """Thresholds in proportion to the input rate (Al Janaideh & Krejci) and a loading slope that steepens with it
    (Ang et al.) are named `dynamics`, the contract's name, and its rate structures take most of the error; the
    slope is left to the feedback by the controller, and says so."""
    report, _ = _run(CASES[name])
    assert report["effects_added"] == ["dynamics"], (report["effects_added"], report["residual"])
    assert report["final"]["validate"]["rms_um"] < 0.7 * report["baseline"]["validate"]["rms_um"]
    dynamics = report["final_model"]["dynamics"]
    assert dynamics["form"] in ("slope", "rates") and any(c != 0.0 for c in dynamics["rate_slope_um"]), dynamics


def test_a_rate_dependent_slope_is_left_to_the_feedback():
    """The controller's inverse has no rate-dependent slope: the dynamics effect says so when it has one, and gives
    the widening alone when it has none."""
    import numpy as np
    from piezo_valve_ros.core.identification import NotCompensable
    from piezo_valve_ros.core.identification import Dynamics
    from piezo_valve_ros.core.identification import ValveModel
    from piezo_valve_ros.core.model import PAPER_GPIM
    model = ValveModel(PAPER_GPIM.model(), rate_widening_v=(0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(NotCompensable, match="rate-dependent slope"):
        Dynamics(form="rates").compensation(model, np.array([0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert Dynamics(form="rates").compensation(model, np.zeros(9)) == {
        "rate_widening_v": (0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)}
    # what of it the controller can take, for the refit without the slope (to_controller)
    assert Dynamics(form="rates").compensable() == Dynamics(form="rate")
    assert Dynamics(form="delay+poles+rate+slope").compensable() == Dynamics(form="delay+poles+rate")
    assert Dynamics(form="slope").compensable() is None


@pytest.mark.slow
@pytest.mark.parametrize("name, seed, share", [("Hammerstein with a 0.7 ms transport delay", 5, 0.95),
                                               ("Hammerstein with an extra 35 Hz lag", 2, 0.85)])
def test_another_record_of_the_same_valve_gets_the_same_names(name, seed, share):
    """Records of these valves (other noise, a shorter training session, another unrecorded excitation before
    each session) that were once judged apart from the valve's other records: the training record's start,
    which held-out data cannot tell from rest, is taken from its first rows (a start they refute bends every
    later fit), and the validation session's start is estimated until every operator it moves is wiped (its
    first rows then fit to the noise, not to an offset of their own: within 1.6 times the floor, which the sessions'
    holds give as the sensor's own 0.050 um)."""
    case = CASES[name]
    train, validate = case.records(seed, share)
    lines: list[str] = []
    report = analyse(Record(train[:, 0], train[:, 1], train[:, 2]),
                     Record(validate[:, 0], validate[:, 1], validate[:, 2]), log=lines.append).report.to_json()
    assert report["effects_added"] == ["dynamics"] and not report["unexplained"], (report["effects_added"], lines)
    assert any(line.startswith("initial state: rest") and line.endswith("chosen estimated") for line in lines), lines
    _, validation = report["sessions"]
    assert validation["start_rows_rms_um"] < 1.6 * report["noise_floor_um"], (validation, report["noise_floor_um"])


@pytest.mark.slow
def test_a_linear_drift_is_named_drift_alone_in_its_linear_form():
    """A thermal drift that grows linearly with time, on a record (seed 5, 95 % training) where the drift's rich form
    (exponential approaches and self-heating besides the time) fitted a share of the hysteresis' slow misfit: its
    slope, carried to the validation session, was off by some 13 %, and the rate-dependent dynamics took the trend
    that left (dynamics and drift named).  The forms are nested, so the held-out record chooses: the linear one."""
    case = CASES["thermal drift, 0.05 um/s"]
    train, validate = case.records(5, 0.95)
    lines: list[str] = []
    report = analyse(Record(train[:, 0], train[:, 1], train[:, 2]),
                     Record(validate[:, 0], validate[:, 1], validate[:, 2]), log=lines.append).report.to_json()
    assert report["effects_added"] == ["drift"] and not report["unexplained"], (report["effects_added"], lines)
    drift = report["final_model"]["drift"]
    assert drift["form"] == "linear" and drift["functions"] == ["t/T"], drift


@pytest.mark.slow
def test_an_effect_standing_in_for_the_grid_is_not_named():
    """The asymmetric valve's seed-3 record: on the (symmetric) baseline the paper's 15-operator grid wins, and with
    it the asymmetry leaves 0.16 um, of which creep takes a share (it was named beside asymmetry) but pays for a tenth
    of its gain in the held-out stretches it does worse in: refused.  With the asymmetry in the model the sizes are
    compared again, and the largest takes what creep took: asymmetry alone, near the noise."""
    case = CASES["asymmetric envelopes (generalized PI)"]
    train, validate = case.records(3, 1.0)
    lines: list[str] = []
    report = analyse(Record(train[:, 0], train[:, 1], train[:, 2]),
                     Record(validate[:, 0], validate[:, 1], validate[:, 2]), log=lines.append).report.to_json()
    assert report["effects_added"] == ["asymmetry"] and not report["unexplained"], (report["effects_added"], lines)
    assert any(line.startswith("exact check on top of asymmetry: creep ") and "not supported" in line
               and "losing" in line for line in lines), lines
    assert any(line.startswith("capacity with asymmetry: ") and "the effects chosen again on 60 operators" in line
               for line in lines), lines
    assert report["baseline"]["fit"] == report["baseline_fits"]["chosen"]            # the baseline keeps its own size
    assert "the effects are fitted on 60 operators" in report["baseline_fits"]["chosen_on"]
    assert report["final_model"]["gpim"]["thresholds"].__len__() == 60
    assert report["final"]["validate"]["rms_um"] < 0.07


@pytest.mark.slow
def test_an_effect_the_search_credits_with_nothing_is_refitted_where_structure_remains():
    """The asymmetric valve with a slow pole, its seed-3 record: on top of asymmetry the first-order search credits
    the pole with nothing (-1 %), so it was never refitted, and the story ended with structure above twice the noise
    left (asymmetry named, unexplained).  Where none of the effects the search credits is supported on top and the
    model leaves structure that would be reported unexplained, every other effect is refitted exactly on top: the
    pole cuts a third of the held-out RMS and is named."""
    case = CASES["asymmetric envelopes and a slow pole"]
    train, validate = case.records(3, 1.0)
    lines: list[str] = []
    report = analyse(Record(train[:, 0], train[:, 1], train[:, 2]),
                     Record(validate[:, 0], validate[:, 1], validate[:, 2]), log=lines.append).report.to_json()
    assert sorted(report["effects_added"]) == ["asymmetry", "dynamics"], (report["effects_added"], lines)
    assert any(line.startswith("exact check: dynamics cuts") for line in lines), lines
