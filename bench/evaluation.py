"""Identify a simulated valve, compensate it, and measure the tracking error on held-out data.

The loop of issue 11 in one place (no ROS): a training record and a separate validation record of the
simulated valve -> the residual loop (``residual.analyse``) -> the compensation the controller would be
pushed (``identify.compensation``; the paper's model as the baseline) -> the paper's validation
reference (eq. 12) tracked by the controller on a fresh valve, under any strategy.  ``bench/
compensation_table.py`` prints the README's table from it; a test runs one case.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable, Optional, Sequence

import numpy as np

from piezo_valve_ros.core.control import CompensationModel
from piezo_valve_ros.core.control import ModelValve
from piezo_valve_ros.core.sim import responses, run_closed_loop, simulate_rows
from piezo_valve_ros.core import ErrorFigures, error_figures
from piezo_valve_ros.core.identification import Record
from piezo_valve_ros.core.sim import rig_training_voltage, validation_reference_m, validation_voltage
from piezo_valve_ros.core.sim import CreepParams, RateDependenceParams, SaturationParams, SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import ControllerConfig, PIDGains, ValveController
from piezo_valve_ros.core.model import PAPER_SECTION, unity_dc_poles

if TYPE_CHECKING:
    from piezo_valve_ros.core.tuning import LoopMargins, StepScore, TuningResult

__all__ = ["SIMULATED_EFFECTS", "SETTLE_S", "simulated_analysis", "Tracking", "tracking_test", "model_tracking_test",
           "CompensationResult",
           "compare_compensations", "TuningComparison", "compare_tuning"]

SETTLE_S = 2.0   # the first seconds of a tracking run are left out of its error (the start from the centre)
VALIDATION_SEED, TRACKING_SEED = 1, 2   # noise seeds of the validation record and of the tracking run


def _with_default(**changes) -> Callable[[ValveSimConfig], ValveSimConfig]:
    return lambda base: replace(base, **changes)


# The simulated valves of the README's table: the default valve (creep, mild end flattening, amplifier slew,
# LVDT noise) and, on top of it, one effect each switched on or made stronger.
SIMULATED_EFFECTS: dict[str, Callable[[ValveSimConfig], ValveSimConfig]] = {
    "default": _with_default(),
    "creep": _with_default(creep=CreepParams(gains=(0.03, 0.03, 0.03, 0.03))),
    "asymmetry": _with_default(descending_envelope=(1.02, 0.35)),
    "saturation": _with_default(saturation=SaturationParams(scale_um=150.0)),
    "rate dependence": _with_default(rate=RateDependenceParams(enabled=True)),
    "slow dynamics": _with_default(valve_model=unity_dc_poles([(2 * np.pi * 60.0, 0.6), PAPER_SECTION])),
}


def simulated_analysis(sim_config: ValveSimConfig, training_s: float = 30.0, log: Callable[[str], None] = print):
    """The residual loop on a training record (the identification node's experiment) and a validation record
    (``signals.validation_voltage``, another noise seed) of the simulated valve; returns the Analysis."""
    from piezo_valve_ros.core.identification import (analyse)  # the residual loop is heavy to import; the rest of this module is not
    dt = sim_config.dt
    train = Record.from_rows(simulate_rows(rig_training_voltage(dt, training_s), sim_config))
    validate = Record.from_rows(simulate_rows(validation_voltage(dt), replace(sim_config, seed=VALIDATION_SEED)))
    return analyse(train, validate, log=log)


@dataclass(frozen=True)
class Tracking:
    """One tracking run's error [um]: of the measured position (what a rig sees: LVDT noise and quantisation
    included) and of the spool's true position (the simulator's: the tracking beneath the noise floor)."""

    measured: ErrorFigures
    spool: ErrorFigures


class _SpoolLog:
    """A simulated valve for ``run_closed_loop`` that also keeps the spool's true position after each sample."""

    def __init__(self, valve: SimulatedValve):
        self.valve, self.config, self.spool_m = valve, valve.config, []

    def step(self, voltage_v: float) -> float:
        y = self.valve.step(voltage_v)
        self.spool_m.append(self.valve.spool_position_m)
        return y


def _after_settling(position_m: np.ndarray, reference_m: np.ndarray, dt: float, settle_s: float) -> ErrorFigures:
    """The error [um] of positions against the demands they answer after ``settle_s``, peak as % of the
    demand's range."""
    k = int(round(settle_s / dt))
    return error_figures(position_m[k:] * 1e6, reference_m[k:] * 1e6, float(np.ptp(reference_m)) * 1e6)


def tracking_test(ctl_config: ControllerConfig, compensation: CompensationModel, sim_config: ValveSimConfig,
                  reference_m: np.ndarray, settle_s: float = SETTLE_S) -> Tracking:
    """Track ``reference_m`` (one value per period ``sim_config.dt``) on a fresh simulated valve (seed
    TRACKING_SEED); the error of each position against the demand it answers (the command of period k shows
    at k + 1), after ``settle_s``, its peak as % of the demand's range; measured and true spool position."""
    valve = _SpoolLog(SimulatedValve(replace(sim_config, seed=TRACKING_SEED)))
    controller = ValveController(replace(ctl_config, dt=sim_config.dt), compensation)
    controller.reset(sim_config.initial_voltage_v, float(reference_m[0]))
    rec = run_closed_loop(valve, controller, reference_m)
    y = responses(valve, rec)
    n = rec.command_v.size
    spool = np.asarray(valve.spool_m)
    spool = np.append(spool[1:n], spool[-1])   # as ``responses``: y_1 .. y_{n-1}, then the extra sample
    return Tracking(_after_settling(y, reference_m, sim_config.dt, settle_s),
                    _after_settling(spool, reference_m, sim_config.dt, settle_s))


def model_tracking_test(compensation: CompensationModel, sim_config: ValveSimConfig, reference_m: np.ndarray,
                        settle_s: float = SETTLE_S) -> ErrorFigures:
    """OL HC's error (as ``tracking_test``) when the valve is exactly the model it compensates
    (``control.forward.ModelValve``: no noise, no amplifier, no effect the model lacks): what the feedforward's own
    design leaves, chiefly the lag of the dynamic feedforward's target F."""
    valve = ModelValve(compensation, sim_config.dt, sim_config.initial_voltage_v)
    controller = ValveController(ControllerConfig(strategy="ol_hc", gains=PIDGains(0.0, 0.0), dt=sim_config.dt),
                                 compensation)
    controller.reset(sim_config.initial_voltage_v, float(reference_m[0]))
    rec = run_closed_loop(valve, controller, reference_m, first_position_m=valve.step(sim_config.initial_voltage_v))
    return _after_settling(responses(valve, rec), reference_m, sim_config.dt, settle_s)


@dataclass(frozen=True)
class CompensationResult:
    effects_added: list[str]
    refused: dict[str, str]
    kept_in_part: list[str]   # refused effects compensated without what was refused (Effect.compensable)
    errors: dict[tuple[str, str], ErrorFigures]   # (model "baseline"/"extended", strategy label) -> error
    spool_errors: dict[tuple[str, str], ErrorFigures]   # the same runs, the spool's true position's error
    strategies: dict[str, ControllerConfig]         # strategy label -> the settings it ran with (tuned ones too)
    model_floor: ErrorFigures   # OL HC with the extended compensation on its own model (model_tracking_test)


def compare_compensations(sim_config: ValveSimConfig, strategies: dict[str, ControllerConfig],
                          validation_s: float = 53.0, amplitude_um: float = 60.0,
                          log: Callable[[str], None] = print, tuned: Sequence[str] = ()) -> CompensationResult:
    """Identify the simulated valve, then track the paper's validation reference under each strategy with the
    baseline compensation (the paper's: GPIM, G_v for ff_pid_g) and the extended one (every effect the
    controller can invert, dynamic feedforward on).  ``tuned``: strategies whose gains are also chosen by the
    tuner on the extended model (``tuning.tune``, default limits), as the identification's ``tune`` step
    would; they run with both models under the label ``"<STRATEGY> tuned"``."""
    from piezo_valve_ros.core.identification import baseline_compensation, compensation
    analysis = simulated_analysis(sim_config, log=log)
    extended = compensation(analysis)
    models = {"baseline": baseline_compensation(analysis).controller_model, "extended": extended.controller_model}
    if tuned:
        from piezo_valve_ros.core.tuning import tune
        strategies = dict(strategies)
        for strategy in tuned:
            gains = tune(strategy, extended.controller_model, sim_config.dt, log=log).gains
            strategies[f"{strategy.upper().replace('_', ' ')} tuned"] = ControllerConfig(strategy=strategy, gains=gains)
    reference = validation_reference_m(sim_config.dt, validation_s, amplitude_um)
    runs = {(name, label): tracking_test(config, model, sim_config, reference)
            for name, model in models.items() for label, config in strategies.items()}
    return CompensationResult(list(analysis.report.effects_added), dict(extended.refused),
                              [n for n in extended.refused if n in [e.name for e in extended.model.effects]],
                              {key: run.measured for key, run in runs.items()},
                              {key: run.spool for key, run in runs.items()}, strategies,
                              model_tracking_test(models["extended"], sim_config, reference))


@dataclass(frozen=True)
class TuningComparison:
    """The tuner's gains against the paper's Table 1 sets for one strategy on one simulated valve: the paper's
    three steps on the valve (``tuning.StepScore``) and the loop margins on the model, per set name."""

    result: "TuningResult"
    scores: dict[str, "StepScore"]      # "tuned" and the Table 1 set names
    margins: dict[str, "LoopMargins"]
    robust_overshoot_pct: dict[str, float]   # worst step overshoot on the model with G_v 10 % slower / faster [%]

    def outside_limits(self, name: str) -> Optional[str]:
        """Why set ``name`` is outside the tuner's limits on the model (margins, the overshoot limit with G_v
        slower and faster; the nominal run is the valve's here), None when it is within them."""
        from piezo_valve_ros.core.tuning import outside_limits
        return outside_limits(self.margins[name], self.robust_overshoot_pct[name], self.result.limits)

    def best_table1(self, max_overshoot_pct: float) -> Optional[str]:
        """The Table 1 set with the shortest average settling time among those whose average overshoot on the
        valve is <= ``max_overshoot_pct`` (None: none is)."""
        ok = [n for n, s in self.scores.items() if n != "tuned" and s.overshoot_pct <= max_overshoot_pct]
        return min(ok, key=lambda n: self.scores[n].settling_time_s) if ok else None

    def verdict(self) -> str:
        """How the tuned set compares with the best Table 1 set within the tuner's overshoot limit."""
        tuned = self.scores["tuned"]
        limit = self.result.limits.max_overshoot_pct
        best = self.best_table1(limit)
        if best is None:
            if tuned.overshoot_pct <= limit:
                return f"no Table 1 set stays within {limit:g} % overshoot on this valve; the tuned one does"
            return (f"no Table 1 set stays within {limit:g} % overshoot on this valve, nor does the tuned one "
                    f"({tuned.overshoot_pct:.2f} %: the valve is not the model it was tuned on)")
        b = self.scores[best]
        if tuned.settling_time_s < b.settling_time_s and tuned.overshoot_pct <= b.overshoot_pct:
            return f"tuned beats {best} (faster at equal or lower overshoot)"
        out = (f"tuned does not beat {best} ({1e3 * tuned.settling_time_s:.2f} vs {1e3 * b.settling_time_s:.2f} ms, "
               f"{tuned.overshoot_pct:.2f} vs {b.overshoot_pct:.2f} %)")
        why = self.outside_limits(best)
        if why:
            out += f"; {best} is outside the tuner's limits: it {why}"
        return out


def compare_tuning(strategy: str, sim_config: ValveSimConfig, model: CompensationModel,
                   log: Callable[[str], None] = print, **tune_kwargs) -> TuningComparison:
    """Tune ``strategy`` on ``model`` (what identification found, the controller running on it) at the valve's
    period, then run the paper's steps on the simulated valve with the tuned gains and each Table 1 set."""
    from piezo_valve_ros.core.control import TABLE1_GAINS
    from piezo_valve_ros.core.tuning import dynamics_variants, loop_margins, robust_overshoot_pct, step_score, tune
    dt, v0 = sim_config.dt, sim_config.initial_voltage_v
    result = tune(strategy, model, dt, log=log, **tune_kwargs)
    sets = {"tuned": result.gains, **{n: g for n, (s, g) in TABLE1_GAINS.items() if s == strategy}}
    base = ControllerConfig(strategy=strategy, dt=dt)
    scores = {n: step_score(replace(base, gains=g), model, lambda: SimulatedValve(sim_config), v0)
              for n, g in sets.items()}
    margins = {n: loop_margins(strategy, g, model, dt) for n, g in sets.items()}
    variants = dynamics_variants(tune_kwargs.get("plant") or model)
    robust = {n: robust_overshoot_pct(replace(base, gains=g), model, variants, v0) for n, g in sets.items()}
    return TuningComparison(result, scores, margins, robust)
