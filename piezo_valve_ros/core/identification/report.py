"""The identification report's schema: one typed definition (TypedDicts with a description per key) from which
``check_report`` checks a report and ``scripts/report_schema.py`` writes the handbook's report page.

The report stays a plain mapping (it goes to JSON as it is); these types say what it holds.  Units: um, V, s,
Hz; shares are fractions (0.2 = 20 %) unless a key ends in ``_pct``.  Nothing here imports ROS.
"""
from __future__ import annotations

import typing
from typing import Optional, TypedDict, Union

__all__ = ["IdentificationReport", "DESCRIPTIONS", "check_report", "schema_tables"]


class ErrorFigures(TypedDict):
    rms_um: float
    peak_um: float
    peak_pct: float
    fit_pct: float


class Figures(TypedDict):
    train: ErrorFigures
    validate: ErrorFigures
    validate_analysis_rate: ErrorFigures


class Baseline(Figures):
    model: str
    fit: str
    G_v: dict
    operators: int


class Final(Figures):
    model: str


class Decision(TypedDict):
    effect: str
    added: bool
    statistic: float
    threshold: float
    margin: float
    held_out_gain: float
    explained_rms_um: float
    evidence: str


class Indistinguishable(TypedDict):
    effect: str
    alternative: str
    held_out_rms_um: dict
    share: Optional[float]
    why: str
    experiment: str


class ResidualStructure(TypedDict):
    rms_um: float
    structured_rms_um: float
    noise_here_um: float
    lag1: float
    line_hz: float
    line_share: float
    ratio_to_noise: float
    pct_of_range: float
    peak_um: float
    expected_noise_peak_um: float
    peak_ratio: float
    peak_pct_of_range: float
    held_out_noise_peak_um: float
    held_out_noise_peak_pct: float


class Capacity(TypedDict):
    grid: str
    operators: int
    held_out_rms_um: float
    held_out_rms_about_trend_um: float


class SearchRow(TypedDict):
    effects: list
    held_out_rms_um: float
    held_out_peak_um: float
    supported: bool


class ConfirmRound(TypedDict):
    effects: list
    held_out_rms_um: float
    drop_one: dict


class Session(TypedDict):
    record: str
    offset_um: float
    start: str
    start_rows: int
    start_rows_rms_um: float


class BaselineFits(TypedDict):
    capacity: list[Capacity]
    chosen: str
    chosen_on: str
    initial_state: dict
    linear: dict
    paper_nls: dict


class IdentificationReport(TypedDict, total=False):
    range_um: float
    baseline: Baseline
    effects_added: list[str]
    diagnosis: list[Decision]
    indistinguishable: list[Indistinguishable]
    final: Final
    unexplained: bool
    residual: str
    residual_structure: ResidualStructure
    baseline_fits: BaselineFits
    search: list[SearchRow]
    confirm: list[ConfirmRound]
    rounds: list[ConfirmRound]
    validation: str
    held_out_fraction: Optional[float]
    held_out_samples: int
    analysed: dict
    validate_range_um: float
    sample_rate_hz: float
    analysis_rate_hz: float
    noise_floor_um: float
    thresholds: dict
    sessions: list[Session]
    transport_delay_s: float
    warnings: list[str]
    final_model: dict
    seconds: float
    source: dict          # added by identify.identify_bags (bags and topic read)
    schema: dict          # added by identify.report_json (name, version, package version, time)


OPTIONAL_KEYS = {"source", "schema"}   # present in written reports, not in analyse()'s own

DESCRIPTIONS: dict[str, str] = {
    "schema": "name, version, package_version, created_utc of the report file",
    "range_um": "range of the measured position the peak shares are taken of [um]",
    "baseline": "the paper's model (GPIM + second-order G_v) fitted to the record: its error figures on the "
                "training part, the held-out data at the record's rate and at the analysis rate, G_v, operators",
    "effects_added": "the effects the loop added, in catalogue order",
    "diagnosis": "every catalogue effect's decision: the held-out RMS cut it gives (statistic), the threshold, "
                 "the margin (statistic - threshold) and the evidence in words",
    "indistinguishable": "added effects the record cannot tell from another one (that one, in its place, does at "
                         "least SEPARATION_SHARE of the cut), with the figures and why",
    "final": "the final model's error figures (as baseline)",
    "unexplained": "structure remains in the held-out residual that no catalogue effect explains (by its RMS "
                   "or its peaks)",
    "residual": "the final held-out residual described in words",
    "residual_structure": "its figures: RMS, structured RMS above the noise, lag-1 autocorrelation, strongest "
                          "line, peaks against what the noise gives, the held-out measurement's own noise peak",
    "baseline_fits": "how the baseline was chosen: GPIM capacities tried, the initial state (rest, cycled, "
                     "estimated, wiped, with what was assumed), the linear fit, the paper's 5-parameter fit",
    "search": "every subset of the catalogue scored by one linear solve from the baseline",
    "confirm": "the exact refits and drop-one checks, round by round",
    "rounds": "the same as confirm (earlier reports' name)",
    "validation": "what the held-out data are: a separate validation record or the training record's tail",
    "held_out_fraction": "the share held out of the training record (null with a validation record)",
    "held_out_samples": "held-out samples at the record's rate",
    "analysed": "what of each record the loop analysed: train (and validate) with from_s, to_s (sample times), "
                "samples, of_samples and record_duration_s; a record longer than MAX_ANALYSED_S (100 s) is "
                "analysed on its first 100 s, and a warning says so",
    "validate_range_um": "range of the held-out position [um]",
    "sample_rate_hz": "the record's sampling rate [Hz]",
    "analysis_rate_hz": "the rate fits and decisions run at (block means) [Hz]",
    "noise_floor_um": "the sensor noise measured on the record [um]",
    "thresholds": "every threshold the decisions used, by name",
    "sessions": "each record as a session of its own, for the final model: the training record (the model's own "
                "offset and start), and a separate validation record with its sensor offset relative to the "
                "training record's and how its unknown start was handled",
    "transport_delay_s": "the final model's transport delay between drive and sensor [s] (0: none; the dynamics "
                         "effect's)",
    "warnings": "what the reader should know (undersampled record, damaged bag files left out)",
    "final_model": "the final model: GPIM, G_v, initial state and one entry per added effect",
    "seconds": "wall time of the analysis [s]",
    "source": "the bags (or CSV) and topic read, and the stretch of the training record used (train_window: from_s, "
              "to_s, axis, first_sample_s, last_sample_s, samples)",
}


def _python_type(t) -> tuple:
    """The runtime types a value of annotation ``t`` may have."""
    origin = typing.get_origin(t)
    if origin is Union:
        return tuple(x for a in typing.get_args(t) for x in _python_type(a))
    if origin is list or t is list:
        return (list,)
    if t is float:
        return (float, int)
    if t is type(None):
        return (type(None),)
    if isinstance(t, type) and issubclass(t, dict):
        return (dict,)
    return (t,)


def check_report(report: dict, typed: type = IdentificationReport, where: str = "report") -> list[str]:
    """Where ``report`` departs from the schema (missing or unknown keys, values of another type, nested
    typed mappings and list items checked too); empty when it conforms."""
    hints = typing.get_type_hints(typed)
    problems = []
    optional = OPTIONAL_KEYS if typed is IdentificationReport else set()
    for key in sorted(set(hints) - set(report) - optional):
        problems.append(f"{where}: {key} missing")
    for key in sorted(set(report) - set(hints)):
        problems.append(f"{where}: {key} is not in the schema")
    for key, value in report.items():
        if key not in hints:
            continue
        t = hints[key]
        if not isinstance(value, _python_type(t)):
            problems.append(f"{where}.{key}: {type(value).__name__}, expected {getattr(t, '__name__', t)}")
            continue
        if isinstance(t, type) and issubclass(t, dict) and hasattr(t, "__annotations__") and t is not dict:
            problems += check_report(value, t, f"{where}.{key}")
        args = typing.get_args(t)
        if typing.get_origin(t) is list and args and hasattr(args[0], "__annotations__"):
            for i, item in enumerate(value):
                problems += check_report(item, args[0], f"{where}.{key}[{i}]")
    return problems


FIELD_DESCRIPTIONS: dict[str, str] = {
    "ErrorFigures.rms_um": "RMS of the error [um]", "ErrorFigures.peak_um": "largest |error| [um]",
    "ErrorFigures.peak_pct": "peak_um as % of the range", "ErrorFigures.fit_pct": "NRMSE fit, 100 (1 - |e| / "
    "|y - mean y|) [%]: 100 perfect, 0 no better than the mean (MATLAB compare's)",
    "Figures.train": "on the training part (record rate)", "Figures.validate": "on the held-out data (record "
    "rate)", "Figures.validate_analysis_rate": "on the held-out data at the analysis rate",
    "Baseline.model": "model name", "Baseline.fit": "the GPIM grid chosen", "Baseline.G_v": "num, den, "
    "poles_rad_s, source", "Baseline.operators": "number of play operators", "Final.model": "model name",
    "Decision.statistic": "held-out RMS cut the effect gives, added last (exactly for an added one, by the "
    "linear search otherwise)", "Decision.margin": "statistic - threshold: how far from the knife edge",
    "Decision.explained_rms_um": "RMS the effect explains [um]", "Decision.evidence": "the decision in words",
    "Indistinguishable.share": "the alternative's cut as a share of the added effect's",
    "Indistinguishable.experiment": "the excitation that would tell the two apart, from each effect's own "
                                    "telling_experiment",
    "Indistinguishable.held_out_rms_um": "without either, with the effect, with the alternative [um]",
    "ResidualStructure.held_out_noise_peak_um": "the held-out measurement's own deviation from its 2 ms local "
    "cubic: the peak its noise alone puts there [um]",
    "ResidualStructure.peak_ratio": "the 3rd largest 5 ms peak over what the noise gives",
    "ResidualStructure.ratio_to_noise": "structured RMS over the sensor noise",
    "Session.record": "training or validation", "Session.offset_um": "the session's sensor offset relative to the "
    "training record's [um] (0 for the training record)", "Session.start": "how the session's unknown start was "
    "handled, in words", "Session.start_rows": "rows (record rate) the start counts on: until the input wiped it out",
    "Session.start_rows_rms_um": "the final model's held-out error RMS over those rows [um]",
    "BaselineFits.initial_state": "held_out_rms_um per start tried, chosen, assumed (in words), fit_starts_at_s, "
    "before_the_record / validation_record_start where estimated",
}


def _type_name(t) -> str:
    args = typing.get_args(t)
    if typing.get_origin(t) is list:
        return f"list of {args[0].__name__}" if args and isinstance(args[0], type) else "list"
    if typing.get_origin(t) is Union:
        return " or ".join("null" if a is type(None) else a.__name__ for a in args)
    return getattr(t, "__name__", str(t))


def schema_tables(typed: type = IdentificationReport) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """(type name, [(key, type, description)]) for the report and every typed mapping in it, each once."""
    out, seen, todo = [], set(), [typed]
    while todo:
        cls = todo.pop(0)
        if cls in seen:
            continue
        seen.add(cls)
        rows = []
        for key, t in typing.get_type_hints(cls).items():
            owner = next((c.__name__ for c in cls.__mro__ if key in getattr(c, "__annotations__", {})), cls.__name__)
            text = DESCRIPTIONS.get(key, "") if cls is IdentificationReport else FIELD_DESCRIPTIONS.get(
                f"{owner}.{key}", FIELD_DESCRIPTIONS.get(f"{cls.__name__}.{key}", ""))
            rows.append((key, _type_name(t), text))
            args = typing.get_args(t)
            for nested in ([t] + list(args)):
                if isinstance(nested, type) and issubclass(nested, dict) and nested is not dict \
                        and hasattr(nested, "__annotations__"):
                    todo.append(nested)
        out.append((cls.__name__, rows))
    return out
