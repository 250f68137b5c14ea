"""The residual loop judged on valves it was not written for (``valve_battery``: effect forms unlike the
catalogue's regressors, all with G_v and sensor noise), and the pieces it decides with."""
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from shared import computed_once
from valve_battery import (BATTERY, NOMINAL, OUTSIDE, PRE_HISTORIES, rows_after, training_voltage,
                           validation_voltage_)

from piezo_valve_ros.core.identification import residual, search
from piezo_valve_ros.core.identification import check_report
from piezo_valve_ros.core.sim import run_closed_loop
from piezo_valve_ros.core.identification import fit_paper_gpim
from piezo_valve_ros.core.model import PAPER_GPIM, inverse_problems
from piezo_valve_ros.core.identification import HELD_OUT_FRACTION, IdentificationError, Record, noise_floor_um, read_csv
from piezo_valve_ros.core.identification import (CAPACITY_EXTENSION, CAPACITY_OPERATORS, GAIN_THRESHOLD,
                                                 MIN_EFFECT_NOISE_RATIO, PEAK_TOLERANCE, UNEXPLAINED_NOISE_RATIO,
                                                 analyse)
from piezo_valve_ros.core.sim import CreepParams, SensorParams, SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import CompensationModel, CreepModel
from piezo_valve_ros.core.control import ControllerConfig, PIDGains, ValveController

DT = 5e-4
TRAIN_V, VALID_V = training_voltage(DT), validation_voltage_(DT)


def records(name: str):
    valve = {**BATTERY, **OUTSIDE}[name]
    return Record.from_rows(valve.rows(TRAIN_V, 1)), Record.from_rows(valve.rows(VALID_V, 2))


def analysed(name: str, held_out: bool = False):
    """(analysis, its log lines) of the battery valve ``name`` (on its validation record, or on a held-out tail),
    once per test run."""
    def compute():
        train, validate = records(name)
        lines: list[str] = []
        return analyse(train, None if held_out else validate, log=lines.append), lines
    return computed_once(f"test_identification.analysed({name!r}, held_out={held_out})", compute)


def analysis_of(name: str, held_out: bool = False):
    """The battery valve ``name`` analysed (see ``analysed``)."""
    return analysed(name, held_out)[0]


def assert_every_name_is_supported(report):
    """Each added effect, removed from the final model and refitted, must raise the held-out error: its
    drop-one cut of the held-out RMS (the statistic that decided) is at least GAIN_THRESHOLD, it explains
    at least MIN_EFFECT_NOISE_RATIO times the sensor noise, and the report says so."""
    for d in report["diagnosis"]:
        if d["effect"] in report["effects_added"]:
            assert d["added"]
            assert d["decided_by"] in ("share", "small but consistent"), d
            assert d["statistic"] >= (GAIN_THRESHOLD if d["decided_by"] == "share" else search.SMALL_SHARE), d
            assert d["margin"] == pytest.approx(d["statistic"] - GAIN_THRESHOLD, abs=2e-4)
            assert d["explained_rms_um"] >= MIN_EFFECT_NOISE_RATIO * (report["noise_floor_um"] or 0.0), d
            assert "exact refit without it" in d["evidence"] and "decided by: " + d["decided_by"] in d["evidence"]


CATALOGUE_CASES = [name for name, valve in BATTERY.items() if valve.effects]


@pytest.mark.parametrize("name", CATALOGUE_CASES)
def test_each_undeclared_effect_is_named_exactly_and_halves_the_held_out_peak(name):
    report = analysis_of(name).report.to_json()
    assert sorted(report["effects_added"]) == sorted(BATTERY[name].effects), report["effects_added"]
    assert report["final"]["validate"]["peak_um"] <= 0.5 * report["baseline"]["validate"]["peak_um"]
    assert report["final"]["validate"]["rms_um"] < report["baseline"]["validate"]["rms_um"]
    assert report["indistinguishable"] == []   # a designed multisine separates the catalogue's signatures
    assert_every_name_is_supported(report)


def test_a_record_that_cannot_separate_two_effects_says_which_and_why():
    """A creeping valve stepped once and held for 30 s with a small dither, the validation record the same:
    creep after the step and a drift from the record's start (a warm-up of seconds: the drift's fast form) are the
    same curve here.  The better of the two is named, and the report says the other would do most of its work in
    its place, with the figures."""
    t = np.arange(int(round(30.6 / DT))) * DT
    volts = np.clip((t - 0.2) / 0.1, 0.0, 1.0) * 3.0 + 5.0 + 0.3 * np.sin(2 * np.pi * 3.0 * t)
    valve = BATTERY["creep, level-dependent log kernel"]
    report = analyse(Record.from_rows(valve.rows(volts, 1)), Record.from_rows(valve.rows(volts, 2))).report.to_json()
    named, = report["effects_added"]
    assert named in ("creep", "drift")
    other = {"creep": "drift", "drift": "creep"}[named]
    pair, = report["indistinguishable"]
    assert (pair["effect"], pair["alternative"]) == (named, other)
    rms = pair["held_out_rms_um"]
    assert rms["with_" + named] <= rms["with_" + other] < rms["without_either"]
    assert pair["share"] >= residual.SEPARATION_SHARE
    assert f"{other} cuts the held-out RMS" in pair["why"]
    # the experiment that would tell them apart, from each effect's own description of what shows it
    from piezo_valve_ros.core.identification import Creep, Drift
    assert pair["experiment"].startswith(f"to tell {named} from {other}, record ")
    assert Creep.telling_experiment in pair["experiment"] and Drift.telling_experiment in pair["experiment"]
    assert check_report(report) == []          # the typed schema, its indistinguishable entries too


def test_the_report_is_a_frozen_typed_tree_whose_json_is_report_json():
    """``Analysis.report`` is the typed tree (attribute access, frozen); ``to_json`` gives what report.json holds:
    the schema's keys and the earlier reports' aliases, JSON-serialisable, and a written report's own blocks
    only where they are set."""
    import dataclasses
    import json
    from piezo_valve_ros.core import ErrorFigures
    from piezo_valve_ros.core.identification import (Analysed, AnalysedRecord, ConfirmRound, Decision,
                                                     IdentificationReport, SchemaBlock, SearchRow, Source,
                                                     TrainWindow)
    report = analysis_of("masking pair: creep + drift").report
    assert isinstance(report, IdentificationReport) and report.effects_added == ("creep", "drift")
    assert isinstance(report.final.validate, ErrorFigures) and report.final.validate.rms_um < report.baseline.validate.rms_um
    assert all(isinstance(d, Decision) for d in report.diagnosis) and {d.effect for d in report.diagnosis if d.added} == {"creep", "drift"}
    assert all(isinstance(r, SearchRow) for r in report.search) and all(isinstance(r, ConfirmRound) for r in report.confirm)
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.unexplained = True
    data = report.to_json()
    assert json.loads(json.dumps(data)) == data and check_report(data) == []
    assert "source" not in data and "schema" not in data
    assert data["thresholds"]["signature"] == data["thresholds"]["held_out_gain"]
    assert "rounds" not in data   # retired (it repeated "confirm" under an earlier report's name)
    assert data["final"]["validate"] == dataclasses.asdict(report.final.validate)
    schema = SchemaBlock(name="x", version=1, package_version="0", created_utc="2026-01-01T00:00:00+00:00")
    source = Source(train_bag="a", validate_bag=None, topic=None, train_window=TrainWindow(
        from_s=None, to_s=None, axis="record_start", first_sample_s=0.0, last_sample_s=1.0, samples=2))
    written = dataclasses.replace(report, source=source, schema=schema).to_json()
    assert list(written)[0] == "schema" and written["schema"]["version"] == 1
    assert written["source"] == {"train_bag": "a", "validate_bag": None, "topic": None, "train_window": {
        "from_s": None, "to_s": None, "axis": "record_start", "first_sample_s": 0.0, "last_sample_s": 1.0, "samples": 2}}
    assert check_report(written) == []
    assert "report.schema: version missing" in check_report({**written, "schema": {"name": "x"}})   # (nested, optional)
    # what the loop analysed, typed: the training record's stretch, the validation record's (no whole record here)
    assert isinstance(report.analysed, Analysed) and isinstance(report.analysed.validate, AnalysedRecord)
    assert data["analysed"]["train"]["samples"] == report.analysed.train.samples > 0
    assert "whole_record" not in data["analysed"]["train"]
    assert check_report({**data, "diagnosis": [{"effect": "creep"}]})[0].startswith("report.diagnosis[0]: added missing")


@pytest.mark.parametrize("name", ["nominal", "creep, level-dependent log kernel",
                                  "dynamics, lightly damped spool mode", "dynamics, loop width growing with the input rate",
                                  "asymmetry, curved descending envelope", "saturation, one-sided soft end stop",
                                  "masking pair: creep + drift", "masking pair: gain drift + transport delay",
                                  "drift with its own hysteresis (temperature through a play)"])
def test_held_out_tail_gives_the_same_names(name):
    """(The drift cases: fitting only after the input's wipe cuts their held-out error too, since a drift
    shows most early on, but no state before the record explains their first rows: a slow effect, not a
    remanent start, so the whole record is fitted and the drift named.)"""
    report = analysis_of(name, held_out=True).report.to_json()
    assert sorted(report["effects_added"]) == sorted(BATTERY[name].effects)
    if BATTERY[name].effects:
        assert report["final"]["validate"]["peak_um"] <= 0.5 * report["baseline"]["validate"]["peak_um"]
    assert_every_name_is_supported(report)


@pytest.mark.parametrize("held_out", [False, True])
def test_nominal_valve_adds_nothing_and_final_is_the_baseline(held_out):
    a = analysis_of("nominal", held_out)
    report = a.report.to_json()
    assert report["effects_added"] == [] and report["unexplained"] is False
    for part in ("train", "validate"):
        assert report["final"][part] == report["baseline"][part]
    assert report["baseline"]["model"] == report["final"]["model"] == "gpim+G_v"
    # the paper model at the noise floor: held-out RMS within 10 % of the sensor noise, at the record's rate
    assert report["final"]["validate"]["rms_um"] < 1.1 * report["noise_floor_um"]
    for key in ("range_um", "baseline", "effects_added", "diagnosis", "final", "unexplained"):
        assert key in report
    assert set(report["baseline"]["validate"]) == {"rms_um", "peak_um", "peak_pct", "fit_pct"}


def test_the_baseline_fits_g_v_and_says_where_its_poles_came_from():
    g = analysis_of("nominal").report.to_json()["baseline"]["G_v"]
    assert g["source"].startswith("paper (fitted poles")  # the valve has the paper's G_v: nothing to gain
    poles = sorted(abs(complex(*p)) for p in g["poles_rad_s"])
    assert poles == pytest.approx([500.0, 2400.0], rel=1e-6)
    # a valve whose G_v is not the paper's: fitted
    other = replace(NOMINAL, dynamics=replace(NOMINAL.dynamics, den=(1.0, 2150.0, 630000.0), num=(630000.0,)))
    train = Record.from_rows(other.rows(TRAIN_V, 1))
    report = analyse(train).report.to_json()
    g = report["baseline"]["G_v"]
    assert g["source"].startswith("fitted")
    fitted = sorted(abs(complex(*p)) for p in g["poles_rad_s"])
    assert fitted == pytest.approx(sorted(np.abs(np.roots([1.0, 2150.0, 630000.0]))), rel=0.05)
    assert report["effects_added"] == []


def test_a_slow_record_falls_back_to_the_paper_g_v_and_warns():
    valve = NOMINAL
    rows = valve.rows(training_voltage(2e-3), 1, dt=2e-3)  # 500 Hz
    report = analyse(Record.from_rows(rows)).report.to_json()
    # G_v's poles are tried at any rate; the paper's (poles near 80 and 380 Hz) are kept where 500 Hz cannot tell
    assert report["baseline"]["G_v"]["source"].startswith("paper (")
    assert any(w.startswith("the record is sampled at 500 Hz, below 1000 Hz: what happens faster than its Nyquist "
                            "rate (250 Hz) goes unseen") for w in report["warnings"])


def test_capacity_is_chosen_on_held_out_data():
    report = analysis_of("nominal").report.to_json()
    cap = report["baseline_fits"]["capacity"]
    assert len(cap) >= 5
    best = min(c["held_out_rms_um"] for c in cap)
    chosen = [c for c in cap if c["grid"] == report["baseline_fits"]["chosen"]][0]
    assert chosen["held_out_rms_um"] <= (1 + residual.CAPACITY_TOLERANCE) * best
    assert chosen["operators"] == report["baseline"]["operators"]
    # the chosen baseline is invertible (nonnegative weights, positive first weight)
    assert inverse_problems(analysis_of("nominal").baseline.gpim) == []


def test_paper_nls_in_identifiable_form_is_well_conditioned_and_recovers_the_paper():
    train, _ = records("nominal")
    fit = fit_paper_gpim(train)
    assert fit.failed is None
    assert fit.condition_number < 1e6  # the 5-parameter form's Jacobian: ~4e10 (a0 trades against alpha/rho/tau)
    p = PAPER_GPIM  # the same model up to the exact invariance a0 -> 1
    assert fit.params.alpha == pytest.approx(p.alpha / p.a0, rel=0.03)
    assert fit.params.rho == pytest.approx(p.rho * p.a0, rel=0.05)
    assert fit.params.tau == pytest.approx(p.tau * p.a0, rel=0.05)


def test_a_degenerate_paper_fit_is_reported_failed_and_not_used():
    # no hysteresis at all: a straight line; the 5-parameter fit can only run its thresholds to a bound
    t = np.arange(TRAIN_V.size) * DT
    y = 13.0 * (TRAIN_V - 5.0) + 0.05 * np.random.default_rng(3).standard_normal(t.size)
    report = analyse(Record(t, TRAIN_V, y)).report.to_json()
    nls = report["baseline_fits"]["paper_nls"]
    assert nls["failed"] and "bound" in nls["failed"]
    assert not any(c["grid"].startswith("paper grid") for c in report["baseline_fits"]["capacity"])
    assert np.isfinite(report["final"]["validate"]["rms_um"])


def test_dead_zone_of_a_micrometre_is_flagged_unexplained():
    report = analysis_of("dead zone, 1 um").report.to_json()
    assert report["unexplained"] is True
    assert report["residual_structure"]["ratio_to_noise"] > UNEXPLAINED_NOISE_RATIO
    assert "closest catalogue effect" in report["residual"]
    # a catalogue effect may match part of it (a static map of the output), but only if held-out data
    # support it
    assert_every_name_is_supported(report)


@pytest.mark.parametrize("held_out", [False, True])
def test_backlash_of_a_micrometre_is_flagged_by_its_peaks_not_its_rms(held_out):
    """A backlash on the output leaves an RMS near the noise (no effect pays for it) but a peak at every
    reversal, three times what the noise gives: unexplained, and the report says it was the peaks."""
    report = analysis_of("backlash, 1 um", held_out).report.to_json()
    structure = report["residual_structure"]
    assert report["final"]["validate"]["rms_um"] < 1.5 * report["noise_floor_um"]
    assert structure["ratio_to_noise"] < UNEXPLAINED_NOISE_RATIO                  # not by its RMS ...
    assert structure["peak_ratio"] > residual.PEAK_NOISE_RATIO                     # ... by its peaks
    assert report["unexplained"] is True and "x what the noise gives" in report["residual"]


def test_peaks_of_a_well_explained_valve_stay_at_the_noise():
    for name in ("nominal", "saturation, off-centre tanh", "masking pair: creep + drift"):
        structure = analysis_of(name).report.to_json()["residual_structure"]
        assert structure["peak_ratio"] < 0.8 * residual.PEAK_NOISE_RATIO, (name, structure)


def test_structure_outside_the_catalogue_is_reported_with_its_spectral_line():
    report = analysis_of("mechanical hum, 7.3 Hz").report.to_json()
    assert report["unexplained"] is True and report["effects_added"] == []
    assert report["residual_structure"]["line_hz"] == pytest.approx(7.3, abs=0.1)


def test_held_out_split_is_the_contract_s_last_30_percent():
    assert HELD_OUT_FRACTION == 0.3  # CONTRACT.md: "holds out the last 30 % of the record in time"
    a = analysis_of("nominal", held_out=True)
    report = a.report.to_json()
    n = len(TRAIN_V)
    assert report["held_out_fraction"] == 0.3
    assert abs(report["held_out_samples"] - 0.3 * n) <= a.split.fit.block + 1
    assert report["validation"] == "held-out last 30 % of the training record"
    assert analysis_of("nominal").report.to_json()["held_out_fraction"] is None


@pytest.mark.parametrize("rate_hz", [1000.0, 2000.0, 5000.0, 10000.0])
def test_the_held_out_part_and_the_fit_part_share_no_sample_at_any_rate(rate_hz):
    """The last 30 % held out of one record: at the record's rate and at the analysis rate (block means), every
    held-out sample comes after every sample the fit sees, and the two parts together are the record."""
    from piezo_valve_ros.core.identification import split_records
    n = int(round(17.3 * rate_hz)) + 7          # a length no block size divides
    t = np.arange(n) / rate_hz
    v = 5.0 + 4.0 * np.sin(2 * np.pi * 0.7 * t) * np.exp(-t / 20.0)
    split = split_records(Record(t, v, 10.0 * v + 0.01 * np.sin(t)), None, residual.ANALYSIS_RATE_HZ)
    fit_last = split.fit_full.time_s[-1]
    assert split.score_full.time_s[split.start_full] > fit_last
    assert len(split.fit_full) + len(split.score_full) - split.start_full == n
    block = split.fit.block
    assert split.fit.time_s[-1] < split.score.time_s[split.start]
    # each analysis row is the mean of its block of the record: the first held-out one starts after the fit part
    assert split.start * block == split.start_full and len(split.fit) * block <= len(split.fit_full)


def test_the_held_out_figures_come_from_the_held_out_part():
    """The held-out error of the report's models, on the record with its fit part's positions spoilt and its
    held-out tail moved by 0.3 um: unchanged by the first, moved by exactly 0.3 um by the second; and the
    report's held-out RMS is that error's."""
    from dataclasses import replace as replaced
    a = analysis_of("nominal", held_out=True)
    split = a.split
    rec = split.score_full
    tail = np.arange(len(rec)) >= split.start_full
    for model in (a.baseline, a.final):
        e = split.held_out_error(model, full=True)
        assert e.size == int(tail.sum())
        spoilt = replaced(split, score_full=Record(rec.time_s, rec.voltage_v, np.where(tail, rec.position_um, 1e3)))
        assert np.array_equal(spoilt.held_out_error(model, full=True), e)
        moved = replaced(split, score_full=Record(rec.time_s, rec.voltage_v, rec.position_um + np.where(tail, 0.3, 0.0)))
        assert np.allclose(moved.held_out_error(model, full=True), e + 0.3)
    assert a.report.to_json()["final"]["validate"]["rms_um"] == pytest.approx(float(np.sqrt(np.mean(
        split.held_out_error(a.final, full=True) ** 2))), abs=5e-7)   # (the report gives 6 decimals)


def test_an_effect_checked_exactly_and_refused_is_reported_by_that_check_once():
    """The valve whose loop widens with the input rate: on top of dynamics the other effects are refitted exactly,
    and each is refused.  The log says so in one line with each refit's figures, and the report's decision on each
    is that refit's (the share of the structured residual it removes), not the first-order figure the search gave."""
    import re
    a, lines = analysed("dynamics, loop width growing with the input rate")
    assert a.report.effects_added == ("dynamics",)
    checks = [x for x in lines if x.startswith("exact check")]
    assert len(checks) == 1 and checks[0].endswith("nothing added"), checks
    noise = a.report.noise_floor_um
    refused = re.findall(r"(\w+) ([0-9.]+) -> ([0-9.]+) um, not supported", checks[0])
    assert {n for n, _, _ in refused} == {"creep", "asymmetry", "drift", "saturation", "backlash"}, refused
    for name, without, with_ in refused:
        decision = next(d for d in a.report.diagnosis if d.effect == name)
        assert not decision.added and "refitted exactly on top of the final model" in decision.evidence
        structured = [np.sqrt(max(float(x) ** 2 - noise ** 2, 0.0)) for x in (without, with_)]
        assert decision.statistic == pytest.approx(1.0 - structured[1] / structured[0], abs=3e-3), (name, decision)
    assert not any(x.endswith("; added") for x in lines if x.startswith("exact check"))


def _segments(ms: float, spread: float = 0.0, seed: int = 0) -> tuple[float, ...]:
    """Held-out mean squares over search.SEGMENTS stretches about ``ms`` (each off by up to ``spread`` of it)."""
    rng = np.random.default_rng(seed)
    return tuple(ms * (1.0 + spread * rng.uniform(-1.0, 1.0, search.SEGMENTS)))


def _score(rms: float, peak: float = 1.0, known: float = None, spread: float = 0.0, seed: int = 0) -> search.Score:
    """A held-out score of RMS ``rms`` whose stretches agree with it (within ``spread``)."""
    return search.Score(rms, peak, known, _segments(rms * rms, spread, seed))


NOISE = search.NoiseLevels.same(0.05)


def test_no_exact_refit_is_run_where_no_effect_could_be_supported():
    """An effect must explain MIN_EFFECT_NOISE_RATIO x the sensor noise and explains at most the RMS it starts
    from: below that nothing can be added (``room_for_an_effect`` never says no where ``support`` could say yes).
    The nominal valve's baseline is at its noise: the exact checks on top are skipped with one line saying so
    (they were six refits, one of them six dynamics forms), and nothing is added."""
    import re
    from piezo_valve_ros.core.identification import room_for_an_effect, support
    for without_rms in (0.01, 0.049, 0.0499, 0.05, 0.051, 0.2):
        without = _score(without_rms)
        for with_rms in (0.0, 1e-6, 0.5 * without_rms, without_rms):
            if support(_score(with_rms, 0.5), without, NOISE).supported:
                assert room_for_an_effect(without, NOISE), (without_rms, with_rms)
    assert support(_score(0.0, 0.5), _score(0.1), NOISE).supported and room_for_an_effect(_score(0.1), NOISE)
    # a residual at the noise floor has no structure to remove: taking it to nothing is fitting the noise
    assert not support(_score(0.0, 0.5), _score(0.05), NOISE).supported
    analysis, lines = analysed("nominal")
    report = analysis.report
    assert report.effects_added == ()
    skipped = [x for x in lines if x.startswith("exact check on top of the baseline: none, ")]
    assert len(skipped) == 1, lines
    rms, structured, floor = map(float, re.search(r"held-out RMS ([0-9.]+) um stands ([0-9.]+) um above the noise "
                                                  r"\(structured\), below 1x the sensor noise ([0-9.]+) um",
                                                  skipped[0]).groups())
    assert structured < floor and floor == pytest.approx(report.noise_floor_um, abs=1e-4)
    assert structured == pytest.approx(np.sqrt(max(rms ** 2 - floor ** 2, 0.0)), abs=2e-4)
    assert not any("not supported" in x for x in lines if x.startswith("exact check"))


def test_confirmation_drops_an_effect_its_exact_drop_one_refit_does_not_support():
    """The confirmation step on exact refits given by hand: creep + drift at 0.50 um held-out, without drift
    0.51 um (2 % of the structured residual: drift is not supported), without creep 1.0 um.  Drift is dropped (and
    said why), creep is confirmed alone, with the evidence that decided; with every effect supported nothing is
    dropped."""
    class Refits:
        def __init__(self, table):
            self.table, self.confirm_log, self.lines, self.baseline = table, [], [], "baseline"
            self.noise, self.levels = 0.05, NOISE

        def refit_many(self, requests):
            return [(frozenset(subset), _score(self.table[frozenset(subset)])) for subset, _ in requests]

        def exact_options(self, current):
            return []

        def log(self, line):
            self.lines.append(line)

    weak_drift = Refits({frozenset({"creep", "drift"}): 0.50, frozenset({"creep"}): 0.51, frozenset({"drift"}): 1.0,
                         frozenset(): 1.2})
    model, _, verdicts, kept = residual._EffectChoice.confirm(weak_drift, ["creep", "drift"])
    assert kept == ["creep"] and model == frozenset({"creep"}) and verdicts["creep"].support.supported
    assert weak_drift.lines[0].startswith("confirm: drift not supported by the exact refit (removes 2.0 % of the "
                                          "structured residual (threshold 20 %)"), weak_drift.lines
    assert weak_drift.lines[1].startswith("confirm: creep kept, supported by share: "), weak_drift.lines
    both = Refits({frozenset({"creep", "drift"}): 0.50, frozenset({"creep"}): 0.8, frozenset({"drift"}): 1.0})
    assert residual._EffectChoice.confirm(both, ["creep", "drift"])[3] == ["creep", "drift"]
    assert all(line.startswith("confirm: ") and " kept, supported by share" in line for line in both.lines)


def test_a_costly_exact_check_is_skipped_only_where_a_cheap_one_leaves_it_nothing_to_show():
    """Exact checks on top of a set, refits given by hand (noise 0.05 um): the cheap ones first; dynamics (six forms,
    each a nonlinear fit: ``Effect.costly_refit``) is refitted only when no cheap one is supported, or the best
    supported one leaves room for an effect (``room_for_an_effect``).  Where it leaves none, dynamics could not be
    supported against it either (the property ``room_for_an_effect`` is tested for above), so the record could
    not tell which is better: the cheap one is taken, with one line saying why dynamics was not refitted."""
    from piezo_valve_ros.core.identification import CATALOGUE

    class Checks:
        def __init__(self, table):
            self.table, self.lines, self.refitted, self.levels = table, [], [], NOISE

        def refit_many(self, requests):
            self.refitted += [n for subset, _ in requests for n in subset if n != "creep"]
            return [(frozenset(subset), _score(self.table[frozenset(subset) - {"creep"}])) for subset, _ in requests]

        def _best_supported(self, options, refits, base):
            return residual._EffectChoice._best_supported(self, options, refits, base)

        def log(self, line):
            self.lines.append(line)

    assert [c.name for c in CATALOGUE if c.costly_refit] == ["dynamics"]
    base = _score(0.2)
    settle = residual._EffectChoice._costly_unless_settled
    cheap = Checks({frozenset({"saturation"}): 0.06, frozenset({"dynamics"}): 0.055})   # 0.06: 0.033 above the noise
    first = cheap.refit_many([(["creep", "saturation"], None)])
    options, refits, best = settle(cheap, ["creep"], None, ["saturation"], first, ["dynamics"], base)
    assert best[0] == "saturation" and options == ["saturation"] and cheap.refitted == ["saturation"]
    assert cheap.lines[0].startswith("exact check on top of creep: dynamics not refitted: with saturation its "
                                     "held-out RMS 0.0600 um stands"), cheap.lines
    assert "nor could it be told from saturation" in cheap.lines[0]
    roomy = Checks({frozenset({"saturation"}): 0.15, frozenset({"dynamics"}): 0.07})   # saturation leaves room
    first = roomy.refit_many([(["creep", "saturation"], None)])
    options, _, best = settle(roomy, ["creep"], None, ["saturation"], first, ["dynamics"], base)
    assert best[0] == "dynamics" and options == ["saturation", "dynamics"] and not roomy.lines
    none = Checks({frozenset({"saturation"}): 0.199, frozenset({"dynamics"}): 0.06})   # no cheap one supported
    first = none.refit_many([(["creep", "saturation"], None)])
    assert settle(none, ["creep"], None, ["saturation"], first, ["dynamics"], base)[2][0] == "dynamics"


def test_held_out_figures_are_at_the_record_s_rate():
    a = analysis_of("nominal")
    e = a.held_out_error(full=True)
    assert a.report.to_json()["final"]["validate"]["rms_um"] == pytest.approx(float(np.sqrt(np.mean(e ** 2))), rel=1e-5)
    assert e.size == len(VALID_V)


def test_noise_floor_is_the_sensor_noise():
    train, _ = records("nominal")
    assert noise_floor_um(train.position_um) == pytest.approx(0.05, rel=0.1)


def test_effect_support_needs_a_consistent_share_of_the_structured_residual_and_no_worse_peak():
    """The rule an effect added last must pass (``search.support``): it removes GAIN_THRESHOLD of the structured
    residual (the RMS above the noise floor) without paying for it in other held-out stretches (MAX_LOSS_RATIO); or
    a small share of a large residual, in nearly every stretch and with a large paired t; it explains the noise's RMS
    and does not raise the peak, nor the RMS where the fit knows the valve."""
    support, noise = search.support, NOISE
    assert support(_score(0.5), _score(1.0), noise).by == "share"
    # 15 % of the total RMS, 15.2 % of the structured residual: not the share, but small and consistent on a large
    # residual (every stretch better); the same cut spread unevenly over the stretches is not supported
    assert support(_score(0.85), _score(1.0), noise).by == "small but consistent"
    assert not support(_score(0.85, spread=0.8, seed=4), _score(1.0, spread=0.8, seed=5), noise).supported
    # near the floor a small cut of the total is a large share of the structure: 0.10 -> 0.085 um is 18 % of the RMS
    # and 21 % of the structure (and explains 0.053 um, more than the noise)
    near = support(_score(0.085), _score(0.10), noise)
    assert near.supported and near.share > 0.2 > near.cut
    assert not support(_score(0.05), _score(0.07), noise).supported           # explains less than the noise
    assert not support(_score(0.5, PEAK_TOLERANCE * 1.01), _score(1.0), noise).supported  # peak worse
    # a cut in two stretches paid for in the other eight (it loses a third of what it gains there): not consistent;
    # the same cut where the other eight barely move (a lag in the fast stretches) is
    lumpy = (0.3,) * 8 + (2.0, 2.0)
    assert support(search.Score(0.6, 1.0, None, (0.31,) * 8 + (0.05, 0.05)),
                   search.Score(float(np.sqrt(np.mean(lumpy))), 1.0, None, lumpy), noise).by == "share"
    cut_in_two = (0.45,) * 8 + (0.05, 0.05)
    assert not support(search.Score(float(np.sqrt(np.mean(cut_in_two))), 1.0, None, cut_in_two),
                       search.Score(float(np.sqrt(np.mean(lumpy))), 1.0, None, lumpy), noise).supported
    # a small share of a large residual: only where it holds in nearly every stretch with a large t
    big = _score(1.0, spread=0.02, seed=1)
    assert support(_score(0.9, spread=0.02, seed=1), big, noise).by == "small but consistent"
    assert not support(_score(0.9, spread=0.02, seed=2), _score(1.0, spread=0.3, seed=3), noise).supported
    assert not support(_score(0.97), _score(1.0), noise).supported                  # below SMALL_SHARE
    # held-out data that leave the fit part's range: no worse before they first do, where the fit knows the valve
    assert support(_score(0.5, known=0.3), _score(1.0, known=0.3), noise).supported
    assert not support(_score(0.5, known=0.31), _score(1.0, known=0.3), noise).supported
    assert "within the fit part's range" in search.unsupported_because(_score(0.5, known=0.31), _score(1.0, known=0.3),
                                                                      noise)
    # the reason in words: a cut that rounds to nothing reads 0.0 %, never -0.0 %
    why = search.unsupported_because(_score(0.0503001), _score(0.0503), search.NoiseLevels.same(0.0514))
    assert why.startswith("removes 0.0 % of the structured residual (threshold 20 %)") and "-0.0" not in why
    assert search.percent(-0.3314) == "-33.1" and search.percent(0.0004, sign=True) == "+0.0"



def test_where_the_noise_is_not_known_a_share_must_also_hold_in_nearly_every_stretch():
    """A closed-loop record gives no evidence for its noise: every residual counts as structure, and a share of it
    alone is no evidence (a slow effect fits part of the loop's wandering).  There the "share" rule also needs the
    effect better in STRONG_SHARE of the held-out stretches; where the noise is known the same figures pass."""
    support = search.support
    unknown = search.NoiseLevels(1e-6, 1e-6, known=False)
    without = search.Score(1.0, 1.0, None, (1.0,) * search.SEGMENTS)
    # 30 % of the residual gone in eight stretches of ten, the other two no worse
    eight = search.Score(float(np.sqrt(np.mean((0.4,) * 8 + (1.0, 1.0)))), 1.0, None, (0.4,) * 8 + (1.0, 1.0))
    assert support(eight, without, search.NoiseLevels(1e-6, 1e-6)).by == "share"
    refused = support(eight, without, unknown)
    assert not refused.supported and refused.share >= search.GAIN_THRESHOLD
    why = search.unsupported_because(eight, without, unknown)
    assert "no evidence for the noise" in why and "only 80 % of the held-out stretches (needs 90 %" in why
    nine = search.Score(float(np.sqrt(np.mean((0.4,) * 9 + (1.0,)))), 1.0, None, (0.4,) * 9 + (1.0,))
    assert support(nine, without, unknown).by == "share"

def test_consistency_counts_the_stretches_a_model_does_better_in():
    """``search.consistency``: the share of held-out stretches with a lower mean square, what it loses in the others
    as a share of what it gains, and the paired t."""
    without = search.Score(1.0, 1.0, None, (1.0,) * search.SEGMENTS)
    even = search.consistency(search.Score(0.9, 1.0, None, (0.81,) * search.SEGMENTS), without)
    assert even.better_share == 1.0 and even.t == float("inf")
    assert even.loss_ratio == 0.0
    one = search.consistency(search.Score(0.9, 1.0, None, (1.0,) * (search.SEGMENTS - 1) + (0.0,)), without)
    assert one.better_share == pytest.approx(1.0 / search.SEGMENTS) and one.t == pytest.approx(1.0)
    paid = search.consistency(search.Score(0.9, 1.0, None, (1.1,) * (search.SEGMENTS - 1) + (0.0,)), without)
    assert paid.loss_ratio == pytest.approx(0.1 * (search.SEGMENTS - 1))
    errors = np.concatenate([np.full(100, k + 1.0) for k in range(search.SEGMENTS)])
    assert search.Score.of(errors).segments == tuple(float((k + 1.0) ** 2) for k in range(search.SEGMENTS))


@pytest.mark.parametrize("bad, message", [
    (lambda r: Record(r.time_s, np.full(len(r), 5.0), r.position_um), "constant"),
    (lambda r: Record(r.time_s, r.voltage_v, np.where(np.arange(len(r)) == 500, np.nan, r.position_um)), "non-finite"),
    (lambda r: r.slice(0, 50), "at least"),
    (lambda r: Record(r.time_s[:3000], np.linspace(0, 10, 3000), r.position_um[:3000]), "reverses"),
    (lambda r: Record(np.where(np.arange(len(r)) > 5000, r.time_s + 3.0, r.time_s), r.voltage_v, r.position_um), "gap"),
])
def test_records_that_cannot_be_fitted_say_why(bad, message):
    train, _ = records("nominal")
    with pytest.raises(IdentificationError, match=message):
        analyse(bad(train))


def test_identified_creep_compensation_cuts_the_step_and_hold_error():
    dt = 1e-3
    config = replace(ValveSimConfig(dt=dt).ideal(), dynamics_enabled=True, sensor=SensorParams(),
                     creep=CreepParams(True, (0.03, 0.03, 0.03), (0.1, 1.0, 10.0)))
    from piezo_valve_ros.core.sim import simulate_rows
    from piezo_valve_ros.core.sim import identification_voltage, validation_voltage
    train = Record.from_rows(simulate_rows(identification_voltage(dt), replace(config, seed=1)))
    validate = Record.from_rows(simulate_rows(validation_voltage(dt), replace(config, seed=2)))
    a = analyse(train, validate)
    assert a.report.to_json()["effects_added"] == ["creep"]
    from piezo_valve_ros.identify import compensation
    with_creep = compensation(a, dynamic_feedforward=False).controller_model
    assert with_creep.creep.active
    levels_um = (30.0, -40.0, 45.0, -10.0)
    ref = np.concatenate([np.full(int(2.0 / dt), x) for x in levels_um]) * 1e-6
    errors = {}
    for name, c in (("without", replace(with_creep, creep=CreepModel())), ("with", with_creep)):
        valve = SimulatedValve(replace(config, seed=5))
        ctl = ValveController(ControllerConfig(strategy="ol_hc", gains=PIDGains(0, 0), dt=dt), c)
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
    assert CreepModel((1.0,), (float("nan"),)).problems()
    with pytest.raises(ValueError):
        ValveController(compensation=CompensationModel(creep=CreepModel((1.0,), (0.95,))))


REAL_RECORD = Path(__file__).parent / "data" / "smart_hysteresis" / "hysteresis_v_150_1hz_1khz.csv"


def test_a_real_piezo_record_is_fitted_to_its_noise_and_nothing_is_invented():
    """Measured data no code of ours produced (a piezo actuator, 150 V 1 Hz sine, 1 kHz; see the data's
    README): the record is cut from running operation, so the operators must start "cycled" (from rest they
    get the first swing wrong by far more than the noise); the baseline then fits to about the sensor noise,
    and the loop neither adds an effect nor reports unexplained structure."""
    report = analyse(read_csv(REAL_RECORD)).report.to_json()
    start = report["baseline_fits"]["initial_state"]
    assert start["chosen"] == "cycled"
    assert start["held_out_rms_um"]["rest"] > 5 * start["held_out_rms_um"]["cycled"]
    noise = report["noise_floor_um"]
    assert 0.02 < noise < 0.1                                      # the sensor's noise, not a fit artefact
    assert report["baseline"]["validate"]["rms_um"] < 1.5 * noise   # 0.06 um of a 39 um stroke
    assert report["effects_added"] == [] and report["unexplained"] is False
    assert report["warnings"] == []                                 # 1 kHz is the supported rate, not below it


FULL_REAL_RECORD = Path(__file__).parent / "data" / "smart_hysteresis" / "hysteresis_v_150_1hz_1khz_full.csv"


def _full_real_record_report() -> dict:
    """The report on the whole measured record (computed once per test run: two tests judge it)."""
    return computed_once("test_identification.full_real_record",
                         lambda: analyse(read_csv(FULL_REAL_RECORD)).report.to_json())


def test_a_real_record_that_starts_remanent_is_judged_after_its_input_wiped_the_state_out():
    """The whole measured record: 3.26 s at 0 V with the actuator 1.6 um off its loop's centre (left there by
    an earlier, unrecorded excitation), then the 1 Hz sine.  Neither rest nor cycled describes that start;
    the fit starts where the sine has reached both extremes, the report says so and estimates the state
    before the record, nothing is added, and the held-out error is at the noise (the issue's bound)."""
    report = _full_real_record_report()
    start = report["baseline_fits"]["initial_state"]
    assert start["chosen"] == "wiped"
    assert 3.9 < start["fit_starts_at_s"] < 4.3                     # the sine reached -150 V then +150 V
    assert "unknown before the record" in start["assumed"]
    before = start["before_the_record"]
    assert before["estimate"].startswith("remanent")                # came back to 0 V from a negative drive
    assert before["rms_before_wipe_um"] < 0.3 * before["rms_before_wipe_from_rest_um"]
    assert start["held_out_rms_um"]["rest"] > 10 * start["held_out_rms_um"]["wiped"]
    assert report["effects_added"] == [] and report["unexplained"] is False
    held_out = report["final"]["validate"]
    assert held_out["rms_um"] <= 0.053 and held_out["peak_pct"] <= 0.55, held_out


@pytest.mark.parametrize("envelopes", [{}, {"b0": 0.9, "b1": 0.6}], ids=["symmetric", "asymmetric"])
def test_the_start_grid_ranks_every_candidate_start_as_one_prediction_each_would(envelopes):
    """``grid_misfits`` scores all the grid's candidate starts at once (one play bank, one filter bank): for
    both families of ``estimate_state`` (rested at e, back from an excursion to e), on a model with asymmetric
    envelopes, thresholds that widen with the rate and a transport delay, each misfit is the one its own
    prediction gives (to rounding), so the grid picks the same starts to refine."""
    from piezo_valve_ros.core.identification import grid_misfits
    from piezo_valve_ros.core.identification import InitialState, ValveModel
    from piezo_valve_ros.core import rms
    m = PAPER_GPIM.model()
    gpim = replace(m, **envelopes) if envelopes else m
    model = ValveModel(gpim, rate_widening_v=(0.02, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), delay_s=0.0007)
    t = np.arange(400) * 5e-4
    v = 5.0 + 3.0 * np.sin(2 * np.pi * 2.0 * t) + 0.5 * np.sin(2 * np.pi * 9.0 * t)
    truth = replace(model, history=InitialState("remanent", (1.5,))).predict(Record(t, v, np.zeros_like(t)))
    rows = Record(t, v, truth + 0.01 * np.random.default_rng(3).standard_normal(t.size))
    grid = np.linspace(-2.0, 12.0, 29)
    for make in (lambda e: InitialState("remanent", (e,)), lambda e: InitialState("remanent", (v[0], e))):
        starts = [make(float(e)) for e in grid]
        one_by_one = np.array([rms(rows.position_um - replace(model, history=s).predict(rows)) for s in starts])
        together = grid_misfits(model, starts, rows)
        np.testing.assert_allclose(together, one_by_one, rtol=1e-12, atol=1e-12)
        assert list(np.argsort(together, kind="stable")[:3]) == list(np.argsort(one_by_one, kind="stable")[:3])
    assert np.argmin(grid_misfits(model, [InitialState("remanent", (float(e),)) for e in grid], rows)) == \
        np.argmin(np.abs(grid - 1.5))


@pytest.mark.parametrize("end_s", [7.0, 7.5])
def test_a_shorter_cut_of_the_real_record_is_judged_the_same(end_s):
    """The whole record's 1 kHz means cut at 7.0 or 7.5 s: the sine wipes the remanent start out late in the
    fit part (78-89 % of it).  Judged from where it did, as the whole record is: nothing added, nothing
    unexplained, and the held-out error within the issue's bound, as the whole record's.  (Fitted from an
    estimated start instead, the misfit of the
    first cycle bent the weights, and dynamics + asymmetry or creep + saturation were "justified" against
    that poor baseline.)"""
    full = read_csv(FULL_REAL_RECORD)
    report = analyse(full.slice(0, int(np.sum(full.time_s <= end_s)))).report.to_json()
    assert report["baseline_fits"]["initial_state"]["chosen"] == "wiped"
    assert report["effects_added"] == [] and report["unexplained"] is False
    held_out = report["final"]["validate"]
    assert held_out["rms_um"] <= 0.053 and held_out["peak_pct"] <= 0.55, held_out


def test_a_drift_on_the_real_record_does_not_hide_the_loop_structure_from_the_capacity_choice():
    """The whole measured record (1 kHz means) with a drift of 0.1 um/s added: the held-out error is then
    mostly the drift's trend, alike for every GPIM size (0.31 um from 12 to 60 operators), and the smallest
    won, 12 operators where the record itself takes 135; the final model kept 0.08 um of loop structure
    unexplained.  Compared about their trend the sizes differ as on the record itself: the largest is chosen,
    drift is named, and the held-out error comes down to the record's own (0.037 um without the drift)."""
    full = read_csv(FULL_REAL_RECORD)
    drifting = Record(full.time_s, full.voltage_v, full.position_um + 0.1 * (full.time_s - full.time_s[0]))
    report = analyse(drifting).report.to_json()
    fits = report["baseline_fits"]
    assert fits["chosen_on"] == "held-out RMS about its trend"
    assert report["baseline"]["operators"] > max(CAPACITY_OPERATORS)
    as_is = [c["held_out_rms_um"] for c in fits["capacity"]]
    assert max(as_is) < 1.05 * min(as_is)                        # the trend swamps the sizes' differences
    assert "drift" in report["effects_added"]
    assert report["final"]["validate"]["rms_um"] < 0.045, report["final"]["validate"]
    # the record itself, without a trend to dominate, is compared as it is
    assert _full_real_record_report()["baseline_fits"]["chosen_on"] == "held-out RMS"


SOURCE_RECORD = Path(__file__).parent / "data" / "smart_hysteresis" / "hysteresis_v_150_1hz.csv.xz"


def test_the_whole_real_record_at_its_own_5_khz_is_fitted_to_its_noise():
    """The source file itself, at 5 kHz: the same judgement as on the 1 kHz means (wiped start, nothing added,
    nothing unexplained), and a held-out error at the noise the record carries at that rate.  The peak is
    judged against the held-out measurement's own noise peak (its deviation from a 2 ms local cubic), which
    on this record lies above 0.55 % of the range: no model reaches a lower peak, so that target cannot be
    met at 5 kHz, and the test says so rather than pinning a figure no predictor reaches."""
    a = np.genfromtxt(SOURCE_RECORD, delimiter=",")[:, 1:]         # the source's first column is empty
    report = analyse(Record(a[:, 0], a[:, 2], a[:, 1])).report.to_json()
    assert report["sample_rate_hz"] == pytest.approx(5000.0, rel=1e-3)
    start = report["baseline_fits"]["initial_state"]
    assert start["chosen"] == "wiped" and 3.9 < start["fit_starts_at_s"] < 4.3
    assert report["effects_added"] == [] and report["unexplained"] is False
    held_out, structure = report["final"]["validate"], report["residual_structure"]
    noise = report["noise_floor_um"]
    assert 0.04 < noise < 0.06
    assert held_out["rms_um"] <= 1.3 * noise, held_out                 # 0.056 um at 0.046 um noise
    # the measured loop has finer structure than 60 operators take: the ladder goes on while it pays
    tried = {c["operators"]: c["held_out_rms_um"] for c in report["baseline_fits"]["capacity"]
             if c["grid"].endswith(" operators")}
    assert set(CAPACITY_EXTENSION) <= set(tried) and report["baseline"]["operators"] > max(CAPACITY_OPERATORS)
    assert tried[report["baseline"]["operators"]] < (1 - 0.05) * tried[max(CAPACITY_OPERATORS)]
    assert structure["held_out_noise_peak_pct"] > 0.55                 # the noise alone peaks above the target
    assert held_out["peak_um"] <= 1.35 * structure["held_out_noise_peak_um"], (held_out, structure)
    assert check_report(report) == []


@pytest.mark.parametrize("pre_history", sorted(PRE_HISTORIES))
def test_a_simulated_valve_with_an_unrecorded_pre_history_adds_nothing(pre_history):
    """The nominal valve driven before the record starts (not recorded), then held at the centre: the record
    starts off the loop.  The loop must not blame an effect for it, and its held-out error stays within 1.5x
    of the same valve's error on a record started from rest.  After the largest excursion (to the top of
    the range) the start is judged unknown, and the state before the record is estimated near 10 V."""
    rows = rows_after(NOMINAL, PRE_HISTORIES[pre_history], TRAIN_V, 11)
    remanent = analyse(Record.from_rows(rows)).report.to_json()
    from_rest = computed_once("test_identification.from_rest",
                              lambda: analyse(Record.from_rows(NOMINAL.rows(TRAIN_V, 11))).report.to_json())
    assert from_rest["baseline_fits"]["initial_state"]["chosen"] == "rest"
    assert remanent["effects_added"] == [] and remanent["unexplained"] is False
    assert remanent["final"]["validate"]["rms_um"] <= 1.5 * from_rest["final"]["validate"]["rms_um"]
    if pre_history == "to 10 V and back":
        start = remanent["baseline_fits"]["initial_state"]
        assert start["chosen"] in ("estimated", "wiped")
        turning = float(start["before_the_record"]["estimate"].split(" to ")[1].split(" V")[0])
        assert 9.0 <= turning <= 11.0, start["before_the_record"]


@pytest.mark.slow
def test_a_closed_loop_record_of_a_nominal_valve_judged_on_its_own_tail_adds_nothing():
    """The battery's closed loop under PID HC 2 (bench/residual_battery.py), judged on the last 30 % of its
    own record, which drives the valve 1.56 V beyond the fit part's range (warned): creep's lags change how the
    model extrapolates there and cut the held-out RMS 0.109 -> 0.076 um, but they raise it 0.067 -> 0.083 um
    before the input first leaves the range, where the fit knows the valve.  A cut made only by the
    extrapolation names nothing (``search.support``) on a valve with no effect beyond the GPIM and G_v.
    The first-order search scores the baseline as its exact fit does: its GPIM weights keep the exact fit's bounds
    (unbounded, weights of either sign fit the training part as well and put the baseline 3.13 um off there)."""
    from valve_battery import closed_loop_rows
    config = replace(ValveSimConfig(dt=1e-3).ideal(), dynamics_enabled=True, sensor=SensorParams())
    lines: list[str] = []
    typed = analyse(Record.from_rows(closed_loop_rows(config, "pid_hc", PIDGains(0.4823, 213.8982, 0.0), 1)),
                    log=lines.append).report
    searched_baseline = next(row for row in typed.search if not row.effects).held_out_rms_um
    assert searched_baseline == pytest.approx(typed.baseline.validate.rms_um, rel=0.01), searched_baseline
    report = typed.to_json()
    assert any("beyond the fit part's" in w and "do no worse on its first 5.67 s" in w for w in report["warnings"]), \
        report["warnings"]
    assert report["effects_added"] == [], report["effects_added"]
    assert any("creep" in line and "raises the held-out RMS" in line and "within the fit part's range" in line
               for line in lines), lines
    # the report's decision on creep is that exact refit and why it was refused (not the first-order search's figure)
    creep = next(d for d in report["diagnosis"] if d["effect"] == "creep")
    assert not creep["added"] and creep["statistic"] > GAIN_THRESHOLD, creep
    assert "refitted exactly on top of the final model; not supported: " in creep["evidence"]
    assert "raises the held-out RMS" in creep["evidence"] and "within the fit part's range" in creep["evidence"]
    # a closed loop's drive is never still and carries the sensor's noise back: no floor, nothing called noise
    assert report["noise_floor"]["source"] == "none" and report["unexplained"] is True


@pytest.mark.slow
@pytest.mark.parametrize("strategy, gains", [("pid", PIDGains(0.5992, 237.2552, 0.0)),
                                             ("pid_hc", PIDGains(0.4823, 213.8982, 0.0))])
def test_a_closed_loop_record_of_a_nominal_valve_adds_nothing(strategy, gains):
    """A day's operation under PI (PID 6) or PID HC (PID HC 2) following levels and slow sines: the voltage
    is the controller's output (never still: the records give no evidence for the sensor noise, and the report
    calls nothing noise), its first command leaves the rest voltage at once.  From rest at that first command the
    operators are wrong until the input wipes them (held-out 0.88 um RMS on the validation record); the
    validation record's own start, estimated from its first rows (the valve rested at the centre, and G
    with it), and the training record's, estimated the same way, bring it to the noise's order, and nothing
    is blamed on an effect."""
    from valve_battery import closed_loop_rows
    config = replace(ValveSimConfig(dt=1e-3).ideal(), dynamics_enabled=True, sensor=SensorParams())
    train, validate = (Record.from_rows(closed_loop_rows(config, strategy, gains, seed)) for seed in (1, 2))
    report = analyse(train, validate).report.to_json()
    # nothing added; but a closed loop's drive is never still, never repeats and carries the sensor's noise back at
    # every frequency: the records give no evidence for the noise floor, so the residual is not called noise
    assert report["effects_added"] == [] and report["unexplained"] is True
    assert report["noise_floor"]["source"] == "none" and "noise floor unknown" in report["summary"]
    start = report["baseline_fits"]["initial_state"]
    assert start["chosen"] == "estimated" and start["held_out_rms_um"]["estimated"] < 0.9 * start["held_out_rms_um"]["rest"]
    rested_at = float(start["assumed"].split("rest at ")[1].split(" V")[0])
    assert abs(rested_at - 5.0) < 0.3, start["assumed"]            # the controller's centre voltage
    validation = report["sessions"][1]                              # its own start, estimated for each model
    assert validation["start"].startswith("its own, estimated") and abs(validation["offset_um"]) < 0.2
    assert report["final"]["validate"]["rms_um"] < 0.1
    # G starts at rest at the voltage the valve rested at, not at the first command (15-18 um peak at t = 0)
    assert report["final"]["validate"]["peak_um"] < 1.0


@pytest.mark.slow
@pytest.mark.parametrize("strategy, gains", [("pid", PIDGains(0.5992, 237.2552, 0.0)),
                                             ("pid_hc", PIDGains(0.4823, 213.8982, 0.0))])
def test_a_closed_loop_record_of_a_creeping_valve_names_creep(strategy, gains):
    """The same under PI or PID HC on a valve that creeps (3 % each at 0.1, 1 and 10 s): the controller's
    voltage drifts at constant position.  Both records rested at the centre until their first command moved
    them; that start, estimated on each record's first rows, halves their misfit (a baseline without creep
    scores no better from it on held-out data, but creep fitted from rest at the first command bends its
    lags to the wrong start and made things worse: nothing was named under PID HC).  Creep is named, and
    nothing else, and the held-out RMS falls to under 40 %."""
    from valve_battery import closed_loop_rows
    plain = replace(ValveSimConfig(dt=1e-3).ideal(), dynamics_enabled=True, sensor=SensorParams())
    config = replace(plain, creep=CreepParams(True, (0.03, 0.03, 0.03), (0.1, 1.0, 10.0)))
    train, validate = (Record.from_rows(closed_loop_rows(config, strategy, gains, seed)) for seed in (1, 2))
    report = analyse(train, validate).report.to_json()
    assert report["effects_added"] == ["creep"]
    start = report["baseline_fits"]["initial_state"]
    assert start["chosen"] == "estimated"
    rested_at = float(start["assumed"].split("rest at ")[1].split(" V")[0])
    assert abs(rested_at - 5.0) < 0.3, start["assumed"]
    validation = report["sessions"][1]                 # the validation record's own start, estimated for each model
    assert validation["start"].startswith("its own, estimated") and abs(validation["offset_um"]) < 0.2
    assert report["final"]["validate"]["rms_um"] < 0.4 * report["baseline"]["validate"]["rms_um"]
    assert_every_name_is_supported(report)


WIDE_CASES = {"+-150 V drive, nominal": [], "+-150 V drive, warming up": ["drift"]}


@pytest.mark.parametrize("held_out", [False, True])
@pytest.mark.parametrize("case", sorted(WIDE_CASES))
def test_a_150_v_drive_is_judged_in_its_own_volts(case, held_out):
    """The paper's valve behind a +-150 V amplifier, recorded in the drive's volts (thresholds, rates and
    range 30x the paper's): nominal, nothing is added; warming up (an S-shaped offset and gain rise, a form
    unlike the catalogue's time functions), drift alone is named and the held-out RMS falls to the noise's
    order."""
    from valve_battery import WIDE, wide_drive
    name, = [n for n in WIDE if n.startswith(case)]
    valve = WIDE[name]
    train = Record.from_rows(valve.rows(wide_drive(TRAIN_V), 1))
    validate = None if held_out else Record.from_rows(valve.rows(wide_drive(VALID_V), 2))
    report = analyse(train, validate).report.to_json()
    assert report["effects_added"] == WIDE_CASES[case] and report["unexplained"] is False
    assert report["final"]["validate"]["rms_um"] < 1.6 * report["noise_floor_um"]
    assert_every_name_is_supported(report)


@pytest.mark.slow
@pytest.mark.parametrize("held_out", [False, True])
def test_a_mild_additive_rate_dependence_is_named_dynamics(held_out):
    """Thresholds a few hundredths of a volt wider at the training rates (a form unlike the catalogue's
    scales): the loop names dynamics alone, and the held-out RMS falls."""
    from valve_battery import mild_rate_widening
    valve = replace(NOMINAL, threshold_add=mild_rate_widening(0.06))
    train = Record.from_rows(valve.rows(TRAIN_V, 1))
    report = analyse(train, None if held_out else Record.from_rows(valve.rows(VALID_V, 2))).report.to_json()
    assert report["effects_added"] == ["dynamics"]
    assert report["final"]["validate"]["rms_um"] < 0.5 * report["baseline"]["validate"]["rms_um"]
    assert_every_name_is_supported(report)


@pytest.mark.slow
def test_the_report_does_not_depend_on_the_number_of_threads():
    """Refits run on a thread pool; the judgement and every figure must be the same on one thread."""
    train, validate = records("masking pair: creep + drift")
    reports = [analyse(train, validate, threads=n).report.to_json() for n in (1, 3)]
    for r in reports:
        r.pop("seconds")
    assert reports[0] == reports[1]
    with pytest.raises(ValueError, match="threads must be >= 1"):
        analyse(train, validate, threads=0)


def test_parts_of_a_fit_run_beside_it_where_a_thread_is_free_and_in_turn_where_none_is():
    """A new pole pair's placements and refinements (``fit_model``'s ``beside``) are handed to the refit pool from
    whatever thread runs the fit: a free thread takes them, else the fit's own thread runs them in turn.  So a job
    of a pool whose threads are all busy (its only one: the job itself) finishes; results come in order; an error
    cancels what was not taken and reaches the caller."""
    import threading
    from concurrent.futures import ThreadPoolExecutor
    from piezo_valve_ros.core.identification._stages import _beside

    with ThreadPoolExecutor(2) as pool:
        both = threading.Barrier(2, timeout=10)   # the first job waits for the second: they must run side by side
        assert _beside(pool, [lambda: both.wait() >= 0 and "a", lambda: both.wait() >= 0 and "b", lambda: "c"]) \
            == ["a", "b", "c"]
    with ThreadPoolExecutor(1) as pool:   # the pool's one thread runs the job that hands work to it
        outer = pool.submit(lambda: _beside(pool, [lambda: threading.current_thread().name] * 3))
        names = outer.result(timeout=10)
        assert len(set(names)) == 1                     # all in turn, in the job's own thread
    ran = []
    with ThreadPoolExecutor(1) as pool:
        blocker = threading.Event()
        pool.submit(blocker.wait, 10)                   # the pool busy: what is handed to it is not taken

        def fail():
            raise RuntimeError("placement failed")
        with pytest.raises(RuntimeError, match="placement failed"):
            _beside(pool, [fail, lambda: ran.append("second")])
        blocker.set()
    assert ran == []                                    # cancelled, never run


def test_the_analysis_threads_come_from_the_environment_or_the_cpus_this_process_may_use(monkeypatch):
    """PIEZO_ANALYSIS_THREADS sets them (the suite's workers, which fill the cores, use one); unset, the CPUs
    of the process' affinity, at most four; anything but a whole number >= 1 is refused with what it was."""
    from piezo_valve_ros.core import defaults
    from piezo_valve_ros.core import PiezoValveError
    assert defaults.available_cpu_count() == len(os.sched_getaffinity(0))
    assert defaults.analysis_threads({}) == min(4, len(os.sched_getaffinity(0)))
    assert defaults.analysis_threads({"PIEZO_ANALYSIS_THREADS": "3"}) == 3
    assert defaults.analysis_threads({"PIEZO_ANALYSIS_THREADS": " 1 "}) == 1
    monkeypatch.setattr(defaults, "available_cpu_count", lambda: 64)   # a many-core host
    assert defaults.analysis_threads({}) == defaults.analysis_threads({"PIEZO_ANALYSIS_THREADS": ""}) == 4
    monkeypatch.setattr(defaults, "available_cpu_count", lambda: 1)    # a process pinned to one CPU
    assert defaults.analysis_threads({}) == 1
    for bad in ("0", "-2", "1.5", "all"):
        with pytest.raises(PiezoValveError, match=f"PIEZO_ANALYSIS_THREADS={bad!r}: .* whole number >= 1"):
            defaults.analysis_threads({"PIEZO_ANALYSIS_THREADS": bad})
    # analyse() asks for them where it is given no number: a bad value ends it before any work
    monkeypatch.setenv("PIEZO_ANALYSIS_THREADS", "none")
    train, validate = records("masking pair: creep + drift")
    with pytest.raises(ValueError, match="PIEZO_ANALYSIS_THREADS='none'"):
        analyse(train, validate)


def test_asymmetry_is_compensated_only_where_the_controller_can_invert_it():
    from types import SimpleNamespace
    from piezo_valve_ros.core.identification import NotCompensable
    from piezo_valve_ros.core.identification import Asymmetry
    from piezo_valve_ros.core.model import GPIM, PAPER_GPIM
    m = PAPER_GPIM.model()
    effect = Asymmetry()
    above = GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, m.a0 * 1.03, m.a1 + 0.08, 0.0)
    # the controller's model takes the GPIM with its envelope (typed: no parameter names in the handoff)
    assert effect.compensation(SimpleNamespace(gpim=above), None)["gpim"] is above
    crossing = GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, 0.95, 0.2)   # inverted step by step
    assert effect.compensation(SimpleNamespace(gpim=crossing), None)["gpim"] is crossing
    falling = GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, 1.0, 0.5, -0.06)
    with pytest.raises(NotCompensable, match="asymmetry: descending envelope not rising"):
        effect.compensation(SimpleNamespace(gpim=falling), None)


def test_asymmetry_steps_keep_the_descending_envelope_rising_on_a_record_of_part_of_the_range():
    """A record that drove only 5..7 V puts the asymmetry's centre far from 0 V: however far a Gauss-Newton step
    pushes the curvature, the descending envelope it proposes is a valid GPIM that rises from 0 V to the end of
    the range (it once stopped valve_identify with "envelope slope a0 (and b0) must be > 0")."""
    from piezo_valve_ros.core.identification import MIN_SLOPE_SHARE, Asymmetry
    from piezo_valve_ros.core.identification import ValveModel
    from piezo_valve_ros.core.model import PAPER_GPIM
    m = PAPER_GPIM.model()
    effect = Asymmetry(centre_v=6.0, half_span_v=1.0)
    model = ValveModel(m)
    for delta in [(0.0, 0.0, 5.0), (0.0, 0.0, -5.0), (0.1, -5.0, 5.0), (-0.1, -5.0, -5.0), (0.0, 5.0, 5.0)]:
        stepped = effect.step(model, delta).gpim
        assert not stepped.problems()
        v = np.linspace(0.0, 7.0, 71)
        slope = stepped.b0 + 2.0 * stepped.b2 * v
        assert np.all(slope >= MIN_SLOPE_SHARE * m.a0 - 1e-12), (delta, slope.min())
    assert abs(effect.betas(effect.step(model, (0.0, 0.0, 0.03)).gpim)[2] - 0.03) < 1e-12   # a mild one is kept



@pytest.mark.parametrize("shift_v", [-0.3, -0.05, 0.25])
def test_a_descending_shift_alone_is_a_symmetric_loop_on_moved_thresholds(shift_v):
    """An asymmetry of shift only (no slope or curvature change) is no asymmetry: the loop is, to rounding, a
    symmetric GPIM's on the thresholds ``symmetric_thresholds`` gives (each moved by half the shift, those moved to
    zero or below merged into the zero-threshold one, zero kept) plus an offset, on a random walk over 0..10 V;
    the residual loop's ``revisit_placement`` rests on it."""
    from piezo_valve_ros.core.identification import Asymmetry
    from piezo_valve_ros.core.model import GPIM, play_batch
    rng = np.random.default_rng(7)
    v = np.clip(5.0 + np.cumsum(rng.normal(0.0, 0.2, 6000)), 0.0, 10.0)
    thresholds = np.arange(10) * 0.45
    weights = 3.0 * np.exp(-0.5 * thresholds)
    effect = Asymmetry(centre_v=5.0, half_span_v=5.0)
    shifted = effect.with_betas(GPIM(thresholds, weights), shift_v, 0.0, 0.0)
    H = play_batch(shifted.ascending_envelope(v), shifted.descending_envelope(v), thresholds,
                   shifted.virgin_state(v[0]), weights)[0]
    placed = effect.symmetric_thresholds(shifted)
    assert placed[0] == 0.0 and np.all(np.diff(placed) > 0)
    moved = thresholds[1:] + 0.5 * shift_v
    assert np.allclose(placed[-moved[moved > 0].size:], moved[moved > 0])
    states = play_batch(v, v, placed, GPIM(placed, np.ones(placed.size)).virgin_state(v[0]))[0]
    design = np.column_stack((states, np.ones(v.size)))
    coefs = np.linalg.lstsq(design, H, rcond=None)[0]
    assert np.max(np.abs(design @ coefs - H)) < 1e-9 * np.ptp(H)
    assert effect.shift_share(shifted) == 1.0   # all of its departure is the shift: the loop tries the placement
    # ... which a slope change is not: the branches then differ, and no placement gives the loop
    sloped = effect.with_betas(GPIM(thresholds, weights), shift_v, 0.1, 0.0)
    H_sloped = play_batch(sloped.ascending_envelope(v), sloped.descending_envelope(v), thresholds,
                          sloped.virgin_state(v[0]), weights)[0]
    placed = effect.symmetric_thresholds(sloped)
    states = play_batch(v, v, placed, GPIM(placed, np.ones(placed.size)).virgin_state(v[0]))[0]
    design = np.column_stack((states, np.ones(v.size)))
    misfit = design @ np.linalg.lstsq(design, H_sloped, rcond=None)[0] - H_sloped
    assert np.max(np.abs(misfit)) > 1e-3 * np.ptp(H_sloped)
    assert effect.shift_share(sloped) == pytest.approx(abs(shift_v) / (abs(shift_v) + 0.5))   # slope 0.1 over +-5 V

def test_a_models_bound_sensitivities_match_finite_differences_column_by_column():
    """The Gauss-Newton sensitivities of a fitted model on a record (``Context.bound_sensitivity`` for the
    descending envelope, ``widening_sensitivity`` for rate-dependent thresholds), several changes at once, equal
    central finite differences of the hysteresis output with the bounds moved (every threshold above zero: an
    operator of zero threshold has both bounds at once, and any widening changes which one it follows)."""
    from piezo_valve_ros.core.identification import Record
    from piezo_valve_ros.core.identification import ValveModel
    from piezo_valve_ros.core.model import PAPER_GPIM, play_batch
    rng = np.random.default_rng(11)
    t = np.arange(4000) * 1e-3
    v = 5.0 + 4.0 * np.sin(2 * np.pi * 1.3 * t) * np.exp(-0.3 * t) + 0.3 * np.cumsum(rng.standard_normal(t.size)) / 20
    paper = PAPER_GPIM.model()
    gpim = type(paper)(paper.thresholds + 0.05, paper.weights, paper.a0, paper.a1, paper.offset_um)
    ctx = ValveModel(gpim).context(Record(t, v, np.zeros(t.size)))
    lower, upper = ctx.drives
    g = ctx.model.gpim
    changes = np.column_stack((np.abs(np.gradient(v, t)) / 50, np.full(t.size, 0.1), (v - 5.0) / 5))
    eps = 1e-6

    def H(lo, hi):
        return play_batch(lo, hi, g.thresholds, ctx.initial_state, g.weights)[0]
    widened = ctx.widening_sensitivity(changes)
    upper_only = ctx.bound_sensitivity(None, changes)
    assert widened.shape == upper_only.shape == (t.size, 3)
    for k in range(3):
        c = changes[:, k]
        fd = (H(lower - eps * c, upper + eps * c) - H(lower + eps * c, upper - eps * c)) / (2 * eps)
        assert np.max(np.abs(widened[:, k] - fd)) < 1e-6 * max(1.0, np.max(np.abs(fd)))
        assert np.allclose(ctx.bound_sensitivity(-c, c), widened[:, k], atol=1e-12)
        fd = (H(lower, upper + eps * c) - H(lower, upper - eps * c)) / (2 * eps)
        assert np.max(np.abs(upper_only[:, k] - fd)) < 1e-6 * max(1.0, np.max(np.abs(fd)))
    assert np.abs(widened).max() > 0.0 and np.abs(upper_only).max() > 0.0
    # gathered block by block: the blocks' size changes no bit (4000 rows in one block of 4096, blocks of 333, one row)
    from piezo_valve_ros.core.model import hysteresis
    side = ((ctx.contacts[0] > 0).astype(float) - (ctx.contacts[0] < 0).astype(float)) * g.weights
    whole = np.column_stack([(changes[:, k][np.maximum(ctx.contacts[1], 0)] * side).sum(axis=1) for k in range(3)])
    assert np.array_equal(widened, whole)
    for block in (333, 1):
        hysteresis.ROW_BLOCK, saved = block, hysteresis.ROW_BLOCK
        try:
            assert np.array_equal(ctx.widening_sensitivity(changes), widened)
            assert np.array_equal(ctx.bound_sensitivity(None, changes), upper_only)
        finally:
            hysteresis.ROW_BLOCK = saved


@pytest.mark.slow
def test_where_the_first_order_search_is_not_trusted_the_effects_are_chosen_by_exact_refits():
    """A valve unlike the paper's (the end-to-end test's: rho 6.6, tau 1, offset -75 um; creep, flattening,
    slew limit, noise) through the rig's training experiment at a quarter of its length, 1 kHz commands held
    for 10 samples.  The first-order search's best set (creep, saturation) does worse by its exact refit than the
    search's figure for it by more than SEARCH_TRUST, so the effects are chosen forward by exact refits: creep,
    then saturation, each supported on top of the ones before, and confirmed by the exact drop-one refits.  Dynamics
    (a 5 V step in one 1 ms period meets the amplifier's slew limit: a rate effect) removes 28 % of the structured
    residual on top of them, but pays for a tenth of it in the held-out stretches it does worse in: not named (with
    G_v's poles refitted through creep and saturation it removes 4 %)."""
    from piezo_valve_ros.core.sim import simulate_rows
    from piezo_valve_ros.core.sim import identification_voltage
    from piezo_valve_ros.core.sim import rig_training_voltage
    base = ValveSimConfig(dt=1e-4, seed=7)
    config = replace(base, gpim=replace(base.gpim, rho=6.6, tau=1.0, offset_um=-75.0))
    rows = simulate_rows(np.repeat(rig_training_voltage(1e-3, 30.0, 0.25), 10), config)
    said = []
    report = analyse(Record.from_rows(rows), log=said.append).report.to_json()
    chosen = [line.split(":")[1].split()[0] for line in said
              if line.startswith("exact selection: ") and " cuts the held-out RMS " in line]
    assert chosen == ["creep", "saturation"], said
    assert all("(the first-order search is not trusted here)" in line for line in said
               if "exact selection" in line and " cuts the held-out RMS " in line)
    # where it stops, each effect left out says why (one reason per effect)
    stop, = [line for line in said if line.startswith("exact selection: nothing more on top of creep, ")]
    assert "asymmetry (" in stop and "drift (" in stop and "dynamics (removes" in stop and "losing" in stop, stop
    assert report["effects_added"] == ["creep", "saturation"]
    assert report["confirm"][-1]["effects"] == report["effects_added"]
    assert_every_name_is_supported(report)


def test_held_out_data_beyond_the_training_range_are_warned_of():
    """The nominal valve trained on the paper's signal squeezed into 2.5-7.5 V and judged on the full-range
    validation record: the fit cannot know the valve outside 2.5-7.5 V, and the report warns so; trained on
    the full range, the same validation record gives no warning."""
    squeezed = 5.0 + 0.5 * (TRAIN_V - 5.0)
    validate = Record.from_rows(NOMINAL.rows(VALID_V, 2))
    report = analyse(Record.from_rows(NOMINAL.rows(squeezed, 1)), validate).report.to_json()
    warned = [w for w in report["warnings"] if "beyond the fit part's" in w]
    assert len(warned) == 1 and warned[0].startswith("the validation record drives the valve to "), report["warnings"]
    assert check_report(report) == []
    assert analysis_of("nominal").report.to_json()["warnings"] == []


def test_an_effects_refit_is_settled_not_one_solve_deep():
    """Creep's columns are lags of the GPIM's output, which the weights being solved make: a refit solves
    until the weights agree with the columns (``fitting._settled``), so one more solve leaves them put.  A
    single solve from the baseline does not, and on the direction-dependent creep valve its held-out error is
    several times the settled fit's at nearly the same training error: a judgement made on it (the exact
    drop-one check) would turn on how many solves were run, not on the valve."""
    from piezo_valve_ros.core.identification import CATALOGUE
    from piezo_valve_ros.core.identification import SETTLE_TOLERANCE, FitCache, fit_model
    from piezo_valve_ros.core.identification.fitting import _linear_solve
    a = analysis_of("creep, direction-dependent log kernel")
    fit, base = a.split.fit, a.baseline
    creep = next(e for e in (cls.prepare(fit, base.context(fit).H) for cls in CATALOGUE) if e.name == "creep")
    fixed = np.zeros(2 * len(base.sections), bool)

    def solve(model):
        return _linear_solve(fit, model, steps=False, free=fixed, cache=FitCache())[0]

    def moved(model):
        return np.linalg.norm(solve(model).gpim.weights - model.gpim.weights) / np.linalg.norm(model.gpim.weights)

    def held_out_rms(model):
        return float(np.sqrt(np.mean(a.held_out_error(model) ** 2)))

    settled = fit_model(fit, base, [creep])
    one = solve(replace(base, effects=(creep,), coefs=(np.zeros(0),)))
    assert moved(settled) < SETTLE_TOLERANCE
    assert moved(one) > 5 * SETTLE_TOLERANCE
    assert held_out_rms(one) > 3 * held_out_rms(settled)


def test_a_settle_that_swings_is_damped_until_it_agrees():
    """Creep alone on a drifting valve (the default valve with drift and an asymmetric envelope, 40 s at 2 kHz, the
    paper's GPIM and G_v refitted as the baseline): solving again and again from one solve does not settle, each
    solve moves the weights by about their whole norm, back and forth, and further each time; the refit
    (``fitting._settled``) damps the swing and ends where one more solve leaves the weights put."""
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.identification import CATALOGUE
    from piezo_valve_ros.core.identification import SETTLE_TOLERANCE, FitCache, fit_model
    from piezo_valve_ros.core.identification.fitting import _linear_solve
    from piezo_valve_ros.core.identification import analysis_record
    from piezo_valve_ros.core.identification import ValveModel
    from piezo_valve_ros.core.model import sections
    from piezo_valve_ros.core.sim import simulate_rows
    from piezo_valve_ros.core.sim import identification_voltage
    from piezo_valve_ros.core.sim import DriftParams
    config = replace(ValveSimConfig(), drift=DriftParams(enabled=True), descending_envelope=(0.95, 0.2), dt=DT, seed=1)
    rows = simulate_rows(identification_voltage(DT, 40.0), config)
    fit = analysis_record(Record(rows[:, 0], rows[:, 1], rows[:, 2] * 1e6))
    paper = CompensationModel()
    base = fit_model(fit, ValveModel(paper.gpim, tuple(sections(paper.valve_model)), t0=float(fit.time_s[0])), [])
    creep = next(e for e in (cls.prepare(fit, base.context(fit).H) for cls in CATALOGUE) if e.name == "creep")
    fixed = np.zeros(2 * len(base.sections), bool)

    def solve(model):
        return _linear_solve(fit, model, steps=False, free=fixed, cache=FitCache())[0]

    def moved(model, after):
        return np.linalg.norm(after.gpim.weights - model.gpim.weights) / np.linalg.norm(model.gpim.weights)

    model, swings = solve(replace(base, effects=(creep,), coefs=(np.zeros(0),))), []
    for _ in range(6):
        after = solve(model)
        swings.append(moved(model, after))
        model = after
    assert min(swings) > 0.5 and swings[-1] > swings[0], swings
    settled = fit_model(fit, base, [creep])
    assert moved(settled, solve(settled)) < SETTLE_TOLERANCE


def test_a_valve_slower_than_its_g_v_gets_the_extra_pole_pair():
    """The slow-dynamics valve (a 60 Hz section, zeta 0.6, times the paper's 500/2400 rad/s poles): the
    baseline's one section stretches to 260 rad/s to cover both, and an extra pair placed with that
    section held only found a resonance near 1400 rad/s (held-out RMS cut 14 %, dropped: the valve was
    left "unexplained").  Placed with G_v's poles free as well, the fit finds the 60 Hz section and the
    dynamics effect is added."""
    from evaluation import SIMULATED_EFFECTS, simulated_analysis
    a = simulated_analysis(SIMULATED_EFFECTS["slow dynamics"](ValveSimConfig(dt=1e-3)), log=lambda s: None)
    r = a.report.to_json()
    assert "dynamics" in r["effects_added"] and not r["unexplained"], r["residual"]
    assert len(a.final.sections) == 2
    resonant = min(a.final.sections, key=lambda s: s[1])
    assert resonant[0] == pytest.approx(2 * np.pi * 60.0, rel=0.05) and resonant[1] == pytest.approx(0.6, abs=0.05)
    assert r["final"]["validate"]["rms_um"] < 0.3 * r["baseline"]["validate"]["rms_um"]


def test_a_fast_creep_does_not_bend_the_identified_g_v():
    """Creep with a 30 ms lag takes part of the static gain away within a few samples, which bent the
    baseline's poles to 462/3248 rad/s; refitted with creep in the model they are the valve's 500/2400."""
    from shared import default_valve_analysis_1khz
    a = default_valve_analysis_1khz()
    assert "creep" in a.report.to_json()["effects_added"]
    true = [500.0, 2400.0]
    baseline = sorted(np.abs(np.roots(a.baseline.dynamics.den)))
    final = sorted(np.abs(np.roots(a.final.dynamics.den)))
    assert final == pytest.approx(true, rel=0.03)
    assert baseline != pytest.approx(true, rel=0.1)   # what the refit with the effects corrects
    assert a.final.dynamics_note.startswith("fitted with the effects")
    # each effect's drop-one model (the plots' "without it") is on the same poles: the difference is the effect
    assert set(a.drop_one) == set(a.report.to_json()["effects_added"])
    assert all(m.sections == a.final.sections for m in a.drop_one.values())


def test_the_bounded_solve_keeps_its_bounds_exactly():
    """Weights bounded at 0 come out >= 0, not -5e-19: a bounded solver may leave such rounding (BVLS did on a
    few of these problems), and a negative weight makes a model with crossing envelopes uninvertible."""
    from piezo_valve_ros.core.identification import solve_gram
    for seed in range(200):
        rng = np.random.default_rng(seed)
        A = np.cumsum(rng.normal(size=(400, 30)), axis=0)
        y = A @ np.where(rng.random(30) < 0.5, 0.0, rng.random(30)) + rng.normal(0.0, 5.0, 400)
        x = solve_gram(A.T @ A, A.T @ y, 400, np.zeros(30), np.zeros(30))
        assert np.all(x >= 0.0), (seed, x.min())


def _bounded_problem(seed: int):
    """A fit-like bounded problem: a standardised Gram (cumulated columns: strongly correlated, as the operators'
    are) with its ridge, a target that puts about half the bounded coefficients on their bounds, bounds at 0 and
    elsewhere, and the last four coefficients free (lower -inf: an offset, an effect's terms)."""
    rng = np.random.default_rng(seed)
    A = np.cumsum(rng.normal(size=(500, 40)), axis=0)
    A /= np.sqrt(np.mean(A ** 2, axis=0))
    lower = np.where(rng.random(40) < 0.3, rng.normal(0.0, 0.5, 40), 0.0)
    lower[-4:] = -np.inf
    truth = np.where(rng.random(40) < 0.5, np.where(np.isfinite(lower), lower, 0.0) - rng.random(40), rng.random(40))
    y = A @ truth + rng.normal(0.0, 2.0, 500)
    gram = A.T @ A
    gram[np.diag_indices_from(gram)] += 1e-10 * 500
    return gram, A.T @ y, lower


def test_the_bounded_solve_is_the_unique_minimiser_with_free_coefficients_and_bounds_off_zero(monkeypatch):
    """solve_standardised's bounded branch (free coefficients eliminated, NNLS on the rest) meets the optimality
    conditions of the bounded problem (gradient zero off the bounds, >= 0 on them) and gives what BVLS gives on
    the same problem; where NNLS cannot finish, the solve falls back to BVLS with the same answer."""
    from scipy import linalg, optimize
    from piezo_valve_ros.core.identification import fitting
    on_bounds = 0
    for seed in range(40):
        gram, rhs, lower = _bounded_problem(seed)
        x = fitting.solve_standardised(gram, rhs, lower)
        assert np.all(x >= lower)
        grad = gram @ x - rhs
        at = np.isfinite(lower) & (x == lower)
        scale = np.max(np.abs(rhs))
        assert np.max(np.abs(grad[~at])) < 1e-9 * scale and np.min(grad[at], initial=0.0) > -1e-9 * scale, seed
        on_bounds += int(at.sum())
        R = linalg.cholesky(gram)
        bvls = optimize.lsq_linear(R, linalg.solve_triangular(R, rhs, trans="T"), bounds=(lower, np.inf),
                                   method="bvls").x
        assert np.allclose(x, bvls, rtol=1e-6, atol=1e-6 * np.max(np.abs(bvls))), seed
    assert on_bounds > 200   # the problems do put coefficients on their bounds

    def stuck(*args, **kwargs):
        raise RuntimeError("too many iterations")
    monkeypatch.setattr(fitting.optimize, "nnls", stuck)
    gram, rhs, lower = _bounded_problem(0)
    fallback = fitting.solve_standardised(gram, rhs, lower)
    monkeypatch.undo()
    assert np.allclose(fallback, fitting.solve_standardised(gram, rhs, lower), rtol=1e-6, atol=1e-9)


def test_a_transport_delay_in_fractional_samples_shifts_the_prediction_by_that_much():
    """discretise_for's delay: whole samples, then the fraction by linear interpolation; a model with delay_s
    predicts its undelayed prediction that much later (a ramp: exactly)."""
    from piezo_valve_ros.core.model import delay_taps
    assert list(delay_taps(0.0)) == [1.0, 0.0] and list(delay_taps(2.25)) == [0.0, 0.0, 0.75, 0.25]
    train, _ = records("nominal")
    model = analysis_of("nominal").baseline
    rec = train.slice(0, 4000)
    plain = model.predict(rec)
    late = replace(model, delay_s=2.5 * rec.dt).predict(rec)
    middle = slice(100, 3900)
    expected = 0.5 * (np.roll(plain, 2) + np.roll(plain, 3))
    assert np.allclose(late[middle], expected[middle], atol=1e-9)


def test_every_catalogue_effect_says_what_it_looks_like_and_what_experiment_shows_it():
    """Each effect's one home carries its residual signature and the excitation that tells it from its
    look-alikes (the report's indistinguishable entries quote them)."""
    from piezo_valve_ros.core.identification import CATALOGUE
    for effect in CATALOGUE:
        assert effect.signature and effect.telling_experiment, effect.name
    assert len({e.telling_experiment for e in CATALOGUE}) == len(CATALOGUE)


def test_the_handbooks_python_example_runs_as_written():
    """The handbook's identification page shows the loop from Python; its code block runs as written and ends
    with a controller model."""
    import re
    from pathlib import Path
    page = (Path(__file__).resolve().parent.parent / "docs" / "handbook" / "identification.md").read_text()
    block, = re.findall(r"```python\n(.*?)```", page, re.S)
    scope: dict = {}
    exec(compile(block, "identification.md", "exec"), {"print": lambda *a, **k: None}, scope)
    from piezo_valve_ros.core.control import CompensationModel
    assert isinstance(scope["controller_model"], CompensationModel)
    assert scope["analysis"].report.final.validate.rms_um < scope["analysis"].report.baseline.validate.rms_um
    assert scope["report_json"] == scope["analysis"].report.to_json()
