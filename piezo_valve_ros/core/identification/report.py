"""The identification report: one tree of frozen dataclasses (``IdentificationReport`` and the records in it),
which the residual loop returns and ``to_json()`` turns into report.json.  The same definition checks a report
read back from JSON (``check_report``) and gives the handbook's report page (``schema_tables``, written by
``scripts/report_schema.py``): each field's ``doc`` metadata says what it holds.

Units: um, V, s, Hz; shares are fractions (0.2 = 20 %) unless a key ends in ``_pct``.  Mappings whose keys
vary with the record (G_v, the initial state, the final model, the thresholds) stay dicts.  Nothing here
imports ROS.
"""
from __future__ import annotations

import typing
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Optional, Union

from ..metrics import ErrorFigures

__all__ = ["IdentificationReport", "Figures", "Baseline", "Final", "Decision", "Indistinguishable",
           "ResidualStructure", "NoiseEstimate", "WholeRecordReport", "Analysed", "AnalysedRecord",
           "AnalysedWhole", "SchemaBlock", "ValveDynamics", "LeftOut", "LinearFit", "PaperParams", "PaperNLS", "Source", "TrainWindow", "TrendRMS", "Stretch", "FiguresFrom", "NoiseFloorReport", "Capacity", "SearchRow", "ConfirmRound", "Session", "BaselineFits", "ErrorFigures",
           "check_report", "schema_tables", "to_json"]


def _item(doc: str, **kwargs):
    """A report field with what it holds (``doc``, for the report page)."""
    return field(metadata={"doc": doc, **kwargs.pop("metadata", {})}, **kwargs)


def _optional(doc: str):
    """A field only written reports have (None in ``analyse``'s own, left out of its JSON)."""
    return field(default=None, kw_only=True, metadata={"doc": doc, "optional": True})


def to_json(value):
    """``value`` as JSON data: a report dataclass as a mapping in field order (optional fields that are None
    left out), tuples as lists; ``IdentificationReport`` adds its aliases."""
    if isinstance(value, _Node):
        return value.to_json()
    if is_dataclass(value) and not isinstance(value, type):   # a record of the core's (ErrorFigures)
        return _fields_json(value)
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, dict):
        return {k: to_json(v) for k, v in value.items()}
    return value


def _fields_json(record) -> dict:
    """A dataclass record's fields as JSON data, in field order (optional fields that are None left out)."""
    return {f.name: to_json(getattr(record, f.name)) for f in fields(record)
            if not (f.metadata.get("optional") and getattr(record, f.name) is None)}


class _Node:
    def to_json(self) -> dict:
        """This record as JSON data (field order)."""
        return _fields_json(self)


@dataclass(frozen=True)
class Figures(_Node):
    train: ErrorFigures = _item("on the training part (record rate)")
    validate: ErrorFigures = _item("on the held-out data (record rate)")
    validate_analysis_rate: ErrorFigures = _item("on the held-out data at the analysis rate")


@dataclass(frozen=True)
class ValveDynamics(_Node):
    """G_v(s) as the report gives it."""
    num: tuple[float, ...] = _item("numerator of G_v(s), highest power first")
    den: tuple[float, ...] = _item("denominator of G_v(s), highest power first")
    poles_rad_s: tuple[tuple[float, float], ...] = _item("its poles as [real, imaginary] [rad/s], the slowest first")
    source: str = _item("where it comes from, in words (fitted, or the paper's and why)")

    @classmethod
    def of(cls, described: dict) -> "ValveDynamics":
        """From ``dynamics.describe_dynamics``'s mapping."""
        return cls(tuple(described["num"]), tuple(described["den"]),
                   tuple(tuple(p) for p in described["poles_rad_s"]), described["source"])


@dataclass(frozen=True)
class Baseline(Figures):
    model: str = _item("model name")
    fit: str = _item("the GPIM grid chosen")
    G_v: ValveDynamics = _item("G_v(s) of the baseline")
    operators: int = _item("number of play operators")


@dataclass(frozen=True)
class Final(Figures):
    model: str = _item("model name")


@dataclass(frozen=True)
class Decision(_Node):
    effect: str = _item("")
    added: bool = _item("")
    statistic: float = _item("the share of the structured held-out residual (its RMS above the noise floor) the "
                             "effect removes, added last (exactly for an added one and for one refitted exactly on top "
                             "of the final set, by the linear search otherwise)")
    threshold: float = _item("")
    margin: float = _item("statistic - threshold: how far from the knife edge")
    held_out_gain: float = _item("the held-out RMS cut it gives (a share)")
    explained_rms_um: float = _item("RMS the effect explains [um]")
    better_share: float = _item("the share of the held-out data's stretches (search.SEGMENTS) where the model with it "
                                "does better")
    loss_ratio: float = _item("what it loses in the stretches it does worse in, as a share of what it gains in the "
                              "others (mean squares)")
    t: float = _item("the paired t statistic of its mean-square cut over those stretches")
    decided_by: str = _item("the rule that supported it: share, small but consistent, or empty (not supported)")
    evidence: str = _item("the decision in words")


@dataclass(frozen=True)
class Indistinguishable(_Node):
    effect: str = _item("")
    alternative: str = _item("")
    held_out_rms_um: dict = _item("without either, with the effect, with the alternative [um]")
    share: Optional[float] = _item("the alternative's cut as a share of the added effect's")
    why: str = _item("")
    experiment: str = _item("the excitation that would tell the two apart, from each effect's own telling_experiment")


@dataclass(frozen=True)
class ResidualStructure(_Node):
    rms_um: float = _item("")
    structured_rms_um: float = _item("")
    noise_here_um: float = _item("")
    lag1: float = _item("")
    line_hz: float = _item("")
    line_share: float = _item("")
    ratio_to_noise: float = _item("structured RMS over the sensor noise")
    pct_of_range: float = _item("")
    peak_um: float = _item("")
    expected_noise_peak_um: float = _item("")
    peak_ratio: float = _item("the 3rd largest 5 ms peak over what the noise gives")
    peak_pct_of_range: float = _item("")
    held_out_noise_peak_um: float = _item("the held-out measurement's own deviation from its 2 ms local cubic: the "
                                          "peak its noise alone puts there [um]")
    held_out_noise_peak_pct: float = _item("")
    share_of_spread: float = _item("the held-out RMS over the held-out output's own standard deviation (1 - fit_pct / "
                                   "100): at SPREAD_SHARE or more the residual is never called noise")


@dataclass(frozen=True)
class NoiseEstimate(_Node):
    source: str = _item("the kind of evidence: holds, repeated periods or input-free band")
    rms_um: Optional[float] = _item("the noise RMS it gives [um] (null: the records offer no such evidence)")
    detail: str = _item("what it was taken from, or why there is none, in words")
    samples: int = _item("the degrees of freedom (or samples) behind it")


@dataclass(frozen=True)
class NoiseFloorReport(_Node):
    rms_um: Optional[float] = _item("the sensor noise RMS at the record's rate [um]; null where the records offer no "
                                    "evidence for it (then no residual is called noise)")
    source: str = _item("the evidence it was taken from: holds, repeated periods, input-free band, or none")
    detail: str = _item("what it was taken from, in words")
    evidence: tuple[NoiseEstimate, ...] = _item("every kind of evidence looked for, with its estimate")


@dataclass(frozen=True)
class Capacity(_Node):
    grid: str = _item("")
    operators: int = _item("")
    held_out_rms_um: float = _item("")
    held_out_rms_about_trend_um: float = _item("")


@dataclass(frozen=True)
class SearchRow(_Node):
    effects: tuple[str, ...] = _item("")
    held_out_rms_um: float = _item("")
    held_out_peak_um: float = _item("")
    supported: bool = _item("")


@dataclass(frozen=True)
class ConfirmRound(_Node):
    effects: tuple[str, ...] = _item("")
    held_out_rms_um: float = _item("")
    drop_one: dict = _item("")


@dataclass(frozen=True)
class LeftOut(_Node):
    """The first rows of a session that starts in motion, left out of the held-out figures."""
    rows: int = _item("rows at the record's rate")
    seconds: float = _item("their length [s]")
    peak_error_um: float = _item("the final model's largest error over them [um]")
    spread_um: float = _item("the session's output spread after them [um]: what that error is set against")


@dataclass(frozen=True)
class Session(_Node):
    record: str = _item("training or validation")
    offset_um: float = _item("the session's sensor offset relative to the training record's [um] (0 for the "
                             "training record)")
    start: str = _item("how the session's unknown start was handled, in words")
    start_rows: int = _item("rows (record rate) the start counts on: until the input wiped it out")
    start_rows_rms_um: float = _item("the final model's held-out error RMS over those rows [um]")
    left_out: Optional["LeftOut"] = _item("a session that starts in motion (settling from a voltage before it): its "
                                          "first rows left out of the held-out figures; null where none are",
                                          default=None)


@dataclass(frozen=True)
class TrendRMS(_Node):
    without_trend: float = _item("the stretch's model's error RMS as it is [um]")
    with_trend: float = _item("... less the whole record's trend [um]")


@dataclass(frozen=True)
class Stretch(_Node):
    from_s: float = _item("first block's time [s]")
    to_s: float = _item("last block's time [s]")
    rms_um: float = _item("the error RMS at the analysis rate there [um]")
    rms_with_trend_um: float = _item("... less the trend [um]")


@dataclass(frozen=True)
class FiguresFrom(_Node):
    baseline: str = _item("the stretch the baseline's figures come from")
    final: str = _item("... the final model's")
    diagnosis: str = _item("... the diagnosis'")
    residual_structure: str = _item("... the residual's structure")
    whole_record: Optional[str] = _item("... the whole record's trend (null where the loop saw all of the record)",
                                        default=None)


@dataclass(frozen=True)
class WholeRecordReport(_Node):
    from_s: float = _item("the whole record's (or its window's) first sample time [s]")
    to_s: float = _item("its last sample time [s]")
    rows: int = _item("rows at the analysis rate the stretch's model ran over")
    rate_hz: float = _item("their rate [Hz]")
    block_s: float = _item("the residual's block means the trend is fitted to [s]")
    segment_s: float = _item("cross-validation: alternate stretches this long fit and score each other [s]")
    resolution_s: float = _item("the trend's spline intervals span at least this long [s]")
    trend_terms: int = _item("the best trend's cubic spline intervals over the record")
    trend_gain: bool = _item("whether the best trend has a gain term besides the offset")
    tried: dict = _item("cross-validated error RMS [um] of every trend tried: its spline intervals and its terms "
                        "(offset, or offset and gain)")
    held_out_rms_um: TrendRMS = _item("the cross-validated error RMS (analysis rate) without and with the best "
                                      "trend, judged_beside refitted in both [um]")
    judged_beside: str = _item("what was refitted over the whole record on both sides of the judgement, so a trend "
                               "must explain what it does not (creep's slow terms, where the model has creep; "
                               "'' none)")
    drift_added: bool = _item("whether the trend is supported (search.support): drift over the whole record")
    decided_by: str = _item("the rule that supported it, or empty")
    evidence: str = _item("the decision in words")
    peak_to_peak_um: float = _item("the fitted trend's size [um]")
    onset_s: float = _item("the first time it departs from its start by a tenth of its size [s]")
    rms_um: TrendRMS = _item("the stretch's model's error RMS at the analysis rate over the whole record [um]")
    beyond_stretch_rms_um: Optional[TrendRMS] = _item("the same over what lies beyond the analysed stretch (never "
                                                      "fitted there: all of it out of sample) [um]; null where nothing "
                                                      "does")
    stretches: tuple[Stretch, ...] = _item("the error RMS at the analysis rate by tenth of the record, without and "
                                           "with the trend")


@dataclass(frozen=True)
class AnalysedWhole(_Node):
    from_s: float = _item("the whole training record's first sample time [s]")
    to_s: float = _item("its last sample time [s]")
    rows: int = _item("its rows at the analysis rate")
    rate_hz: float = _item("the analysis rate [Hz]")
    samples: Optional[int] = _optional("its samples at the record's own rate (where it was in memory whole)")


@dataclass(frozen=True)
class AnalysedRecord(_Node):
    from_s: float = _item("the analysed stretch's first sample time [s]")
    to_s: float = _item("its last sample time [s]")
    samples: int = _item("its samples at the record's rate")
    of_samples: int = _item("the record's samples (the window's, with --from/--to)")
    record_duration_s: float = _item("the record's duration [s]")
    whole_record: Optional[AnalysedWhole] = _optional("the training record longer than MAX_ANALYSED_S: all of it, at "
                                                      "the analysis rate, for a slow trend")


@dataclass(frozen=True)
class Analysed(_Node):
    train: AnalysedRecord = _item("the training record's")
    validate: Optional[AnalysedRecord] = _optional("the validation record's (where there is one)")


@dataclass(frozen=True)
class SchemaBlock(_Node):
    name: str = _item("what the file is (e.g. piezo_valve_ros/identification-report)")
    version: int = _item("its schema version")
    package_version: str = _item("the piezo_valve_ros version that wrote it")
    created_utc: str = _item("when (ISO 8601, UTC)")


@dataclass(frozen=True)
class TrainWindow(_Node):
    from_s: Optional[float] = _item("the window's start [s] on its axis (null: the record's start)")
    to_s: Optional[float] = _item("its end [s] (null: the record's end)")
    axis: str = _item("record_start (seconds from the first sample) or stamps (the samples' own time axis)")
    first_sample_s: float = _item("the first sample read in it [s]")
    last_sample_s: float = _item("the last sample read in it [s]")
    samples: int = _item("samples read in it (at most MAX_ANALYSED_S of them; the rest streamed for the whole record)")


@dataclass(frozen=True)
class Source(_Node):
    train_bag: str = _item("the training bag (or CSV) as given")
    validate_bag: Optional[str] = _item("the validation bag (or CSV) as given (null: none, a held-out tail)")
    topic: Optional[str] = _item("the samples topic read (null: a CSV)")
    train_window: TrainWindow = _item("the stretch of the training record used")


@dataclass(frozen=True)
class LinearFit(Figures):
    """The baseline as the bounded linear fit gives it."""
    operators: int = _item("number of play operators")
    invertible: bool = _item("whether the controller can invert it (the weights' bounds keep it so)")


@dataclass(frozen=True)
class PaperParams(_Node):
    """The paper's 5-parameter GPIM (``GPIMParams``) as its NLS fitted it."""
    a0: float = _item("envelope slope [1]")
    a1: float = _item("envelope offset [V]")
    alpha: float = _item("threshold spacing [V]")
    rho: float = _item("weight scale [um/V]")
    tau: float = _item("weight decay [1/V]")
    n: int = _item("number of operators")
    offset_um: float = _item("output offset [um]")


@dataclass(frozen=True)
class PaperNLS(Figures):
    """The paper's 5-parameter NLS fit, beside the linear one."""
    params: PaperParams = _item("its parameters")
    fixed: str = _item("the parameters held, and why")
    condition_number: float = _item("of its Jacobian")
    evaluations: int = _item("model evaluations it took")
    failed: Optional[str] = _item("why it cannot be used (null: it can)")


@dataclass(frozen=True)
class BaselineFits(_Node):
    capacity: tuple[Capacity, ...] = _item("")
    chosen: str = _item("")
    chosen_on: str = _item("")
    initial_state: dict = _item("held_out_rms_um per start tried, chosen, assumed (in words), fit_starts_at_s, "
                                "before_the_record / validation_record_start where estimated")
    linear: LinearFit = _item("the bounded linear fit (the baseline)")
    paper_nls: PaperNLS = _item("the paper's 5-parameter NLS")


@dataclass(frozen=True)
class IdentificationReport(_Node):
    """What one run of the residual loop found (``residual.analyse``), as report.json holds it
    (``to_json``)."""

    schema: Optional[SchemaBlock] = _optional("what the report file is and which version of the package wrote it")
    range_um: float = _item("range of the measured position the peak shares are taken of [um]")
    baseline: Baseline = _item("the paper's model (GPIM + second-order G_v) fitted to the record: its error figures "
                               "on the training part, the held-out data at the record's rate and at the analysis "
                               "rate, G_v, operators")
    effects_added: tuple[str, ...] = _item("the effects the loop added, in catalogue order")
    diagnosis: tuple[Decision, ...] = _item("every catalogue effect's decision: the held-out RMS cut it gives "
                                            "(statistic), the threshold, the margin (statistic - threshold) and the "
                                            "evidence in words")
    indistinguishable: tuple[Indistinguishable, ...] = _item(
        "added effects the record cannot tell from another one (that one, in its place, does at least "
        "SEPARATION_SHARE of the cut), with the figures and why")
    final: Final = _item("the final model's error figures (as baseline)")
    unexplained: bool = _item("structure remains in the held-out residual that no catalogue effect explains (by "
                              "its RMS or its peaks)")
    residual: str = _item("the final held-out residual described in words")
    residual_structure: ResidualStructure = _item(
        "its figures: RMS, structured RMS above the noise, lag-1 autocorrelation, strongest line, peaks against "
        "what the noise gives, the held-out measurement's own noise peak")
    baseline_fits: BaselineFits = _item("how the baseline was chosen: GPIM capacities tried, the initial state "
                                        "(rest, cycled, estimated, wiped, with what was assumed), the linear fit, "
                                        "the paper's 5-parameter fit")
    search: tuple[SearchRow, ...] = _item("every subset of the catalogue scored by one linear solve from the "
                                          "baseline")
    confirm: tuple[ConfirmRound, ...] = _item("the exact refits and drop-one checks, round by round")
    validation: str = _item("what the held-out data are: a separate validation record or the training record's "
                            "tail")
    held_out_fraction: Optional[float] = _item("the share held out of the training record (null with a validation "
                                               "record)")
    held_out_samples: int = _item("held-out samples at the record's rate")
    analysed: Analysed = _item("what of each record the loop analysed; a record longer than MAX_ANALYSED_S (100 s) is "
                               "analysed on its first 100 s, its whole length (the training record's) for a slow "
                               "trend (whole_record), and a warning says so")
    figures_from: FiguresFrom = _item("which stretch of which record each figure comes from, in words")
    validate_range_um: float = _item("range of the held-out position [um]")
    sample_rate_hz: float = _item("the record's sampling rate [Hz]")
    analysis_rate_hz: float = _item("the rate fits and decisions run at (block means) [Hz]")
    noise_floor_um: Optional[float] = _item("the sensor noise measured on the records from what the input cannot "
                                            "explain (noise_floor says how) [um]; null where they offer no evidence")
    noise_floor: NoiseFloorReport = _item("the noise floor's evidence: holds, repeated periods of the drive, or a band "
                                          "where the drive has no power (each tried, the floor's source named)")
    summary: str = _item("the story in one line: effects added, unexplained, held-out RMS and fit before and after, "
                         "and the noise floor's source")
    thresholds: dict = _item("every threshold the decisions used, by name")
    sessions: tuple[Session, ...] = _item(
        "each record as a session of its own, for the final model: the training record (the model's own offset "
        "and start), and a separate validation record with its sensor offset relative to the training record's "
        "and how its unknown start was handled")
    transport_delay_s: float = _item("the final model's transport delay between drive and sensor [s] (0: none; the "
                                     "dynamics effect's)")
    warnings: tuple[str, ...] = _item("what the reader should know (undersampled record, damaged bag files left "
                                      "out)")
    final_model: dict = _item("the final model: GPIM, G_v, initial state and one entry per added effect")
    seconds: float = _item("wall time of the analysis [s]")
    whole_record: Optional[WholeRecordReport] = _optional(
        "a training record longer than MAX_ANALYSED_S: the stretch's model run over all of it, and the slow trend "
        "searched there (present only then)")
    source: Optional[Source] = _optional("the bags (or CSV) and topic read, and the stretch of the training record "
                                         "used")

    def to_json(self) -> dict:
        """report.json's content (without the schema block unless set)."""
        return _fields_json(self)


# --------------------------------------------------------------------------- checking a report read as JSON
def _python_type(t) -> tuple:
    """The JSON-side runtime types a value of annotation ``t`` may have."""
    origin = typing.get_origin(t)
    if origin is Union:
        return tuple(x for a in typing.get_args(t) for x in _python_type(a))
    if origin in (list, tuple) or t in (list, tuple):
        return (list,)
    if t is float:
        return (float, int)
    if t is type(None):
        return (type(None),)
    if is_dataclass(t) or t is dict or typing.get_origin(t) is dict:
        return (dict,)
    return (t,)


def _keys(typed: type) -> dict[str, tuple[object, bool]]:
    """key -> (annotation, optional) of ``typed`` as JSON has it."""
    hints = typing.get_type_hints(typed)
    return {f.name: (hints[f.name], bool(f.metadata.get("optional"))) for f in fields(typed)}


def _item_type(t):
    """The element type of a list/tuple annotation (None when it has none)."""
    args = [a for a in typing.get_args(t) if a is not Ellipsis]
    return args[0] if typing.get_origin(t) in (list, tuple) and args else None


def check_report(report: dict, typed: type = IdentificationReport, where: str = "report") -> list[str]:
    """Where ``report`` (JSON data) departs from the definition: missing or unknown keys, values of another type,
    nested records and list items checked too; empty when it conforms."""
    keys = _keys(typed)
    problems = [f"{where}: {key} missing" for key in sorted(k for k, (_, opt) in keys.items()
                                                             if not opt and k not in report)]
    problems += [f"{where}: {key} is not in the schema" for key in sorted(set(report) - set(keys))]
    for key, value in report.items():
        if key not in keys:
            continue
        t = keys[key][0]
        if not isinstance(value, _python_type(t)):
            problems.append(f"{where}.{key}: {type(value).__name__}, expected {_type_name(t)}")
            continue
        record = next((a for a in (t, *typing.get_args(t)) if is_dataclass(a)), None)   # (Optional[...]'s too)
        if record is not None and isinstance(value, dict):
            problems += check_report(value, record, f"{where}.{key}")
        item = _item_type(t)
        if item is not None and is_dataclass(item):
            for i, entry in enumerate(value):
                problems += (check_report(entry, item, f"{where}.{key}[{i}]") if isinstance(entry, dict)
                             else [f"{where}.{key}[{i}]: {type(entry).__name__}, expected {item.__name__}"])
    return problems


# --------------------------------------------------------------------------- the report page
def _type_name(t) -> str:
    item = _item_type(t)
    if typing.get_origin(t) in (list, tuple) or t in (list, tuple):
        return f"list of {item.__name__}" if isinstance(item, type) else "list"
    if typing.get_origin(t) is Union:
        return " or ".join("null" if a is type(None) else a.__name__ for a in typing.get_args(t))
    return getattr(t, "__name__", str(t))


def schema_tables(typed: type = IdentificationReport) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """(type name, [(key, type, description)]) for the report and every record in it, each once (written
    reports' optional fields and the aliases last, as the page has always listed them)."""
    out, seen, todo = [], set(), [typed]
    while todo:
        cls = todo.pop(0)
        if cls in seen:
            continue
        seen.add(cls)
        hints = typing.get_type_hints(cls)
        own = [f for f in fields(cls) if not f.metadata.get("optional")]
        rows = []
        for f in own:
            rows.append((f.name, _type_name(hints[f.name]), f.metadata.get("doc", "")))
        rows += [(f.name, _type_name(hints[f.name]).replace(" or null", "").replace("null or ", ""),
                  f.metadata.get("doc", "")) for f in fields(cls) if f.metadata.get("optional")][::-1]
        for f in fields(cls):
            t = hints[f.name]
            for nested in [t, _item_type(t)] + list(typing.get_args(t)):
                if isinstance(nested, type) and is_dataclass(nested):
                    todo.append(nested)
        out.append((cls.__name__, rows))
    return out
