"""What the controller gets from an identification: the final model reduced to what it can invert, as the
controller's :class:`CompensationModel` and its parameters (ROS-free, no files: ``identify`` writes them)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..control.compensation import CompensationModel
from ..model.dynamics import unity_dc_poles
from ..model.hysteresis import GPIM
from .effects import NotCompensable
from .fitting import fit_model
from .residual import Analysis
from .valve_model import ValveModel

__all__ = ["Compensation", "compensation", "baseline_compensation", "base_model", "base_parameters", "controller_parameters",
           "fitted_range"]


@dataclass(frozen=True)
class Compensation:
    """What the controller gets from an identification: the identified model reduced to what it can invert,
    that model as the controller's :class:`CompensationModel`, and what it had to leave (effect -> why)."""

    model: ValveModel
    controller_model: CompensationModel
    refused: dict[str, str]


def fitted_range(analysis: Analysis) -> tuple[float, float]:
    """The voltages [V] the training record drove: the range the controller may command with the model."""
    v = analysis.split.fit_full.voltage_v
    return float(np.min(v)), float(np.max(v))


def base_model(model: ValveModel, dynamic_feedforward: bool, fitted_range_v: tuple[float, ...] = ()) -> CompensationModel:
    """The controller's model of a model's GPIM and G (all its sections) with no effect compensated, and the
    voltages [V] it was fitted on."""
    g = model.gpim
    symmetric = GPIM(g.thresholds, g.weights, g.a0, g.a1, g.offset_um)  # the asymmetry effect adds the envelope
    return CompensationModel(symmetric, unity_dc_poles(list(model.sections)), dynamic_feedforward=dynamic_feedforward,
                             fitted_range_v=tuple(fitted_range_v))


def base_parameters(model: ValveModel, dynamic_feedforward: bool, fitted_range_v: tuple[float, ...] = ()) -> dict:
    """``base_model``'s controller parameters; every model parameter written (``CompensationModel.to_parameters``),
    so a push replaces a whole older model."""
    return base_model(model, dynamic_feedforward, fitted_range_v).to_parameters()


def compensation(analysis: Analysis, dynamic_feedforward: bool = True) -> Compensation:
    """The final model reduced to what the controller compensates.

    Each effect's ``compensation`` gives the parts of the controller's model it fills (typed values) or the reason
    it has none; an effect is taken only if the model with it still passes ``CompensationModel.problems`` as a
    whole on the fitted voltages (e.g. a saturation map that stays invertible together with the creep).  When
    anything is left out the model is refitted without it, so the GPIM the controller inverts is the best one
    without that structure; an effect whose ``compensation`` refuses part of it (a rate-dependent slope) is refitted
    without that part (``Effect.compensable``) and the rest compensated, unless the refitted model does not pass
    as a whole (then without the effect).  With ``dynamic_feedforward`` the feedforward also inverts the fitted G
    (``compensation.DynamicFeedforward``).
    """
    final = analysis.final
    drive = fitted_range(analysis)
    controller = base_model(final, dynamic_feedforward, drive)
    usable, refused, reduced = [], {}, []
    for e, c in zip(final.effects, final.coefs):
        try:
            trial = replace(controller, **e.controller_fields(final, c))
        except NotCompensable as exc:
            refused[e.name] = str(exc)
            part = e.compensable()   # what of it the controller can take, refitted below without the rest
            if part is not None:
                reduced.append(part)
            continue
        problems = trial.problems(*drive)
        if problems:
            refused[e.name] = f"{e.name}: with the rest of the model: {'; '.join(problems)}"
            continue
        usable.append(e)
        controller = trial
    if not refused:
        return Compensation(final, controller, refused)
    if reduced:
        try:
            model, controller = _refitted(analysis, usable + reduced, dynamic_feedforward, drive)
        except ValueError as exc:   # the parts do not pass with the rest of the model: left out whole
            for part in reduced:
                refused[part.name] += f" (without it, the rest of {part.name} does not pass with the model: {exc})"
        else:
            for part in reduced:
                refused[part.name] += f" (the rest of {part.name} refitted without it and compensated)"
            return Compensation(model, controller, refused)
    model, controller = _refitted(analysis, usable, dynamic_feedforward, drive)
    return Compensation(model, controller, refused)


def _refitted(analysis: Analysis, effects: list, dynamic_feedforward: bool, drive) -> tuple[ValveModel, CompensationModel]:
    """The model refitted with ``effects`` (in the forms given) and the controller's model of it; ValueError with
    the problems where that does not pass as a whole."""
    model = fit_model(analysis.split.fit, analysis.baseline, effects, try_forms=False) if effects else analysis.baseline
    controller = base_model(model, dynamic_feedforward, drive)
    for e, c in zip(model.effects, model.coefs):
        try:
            controller = replace(controller, **e.controller_fields(model, c))
        except NotCompensable as exc:
            raise ValueError(str(exc)) from exc
    problems = controller.problems(*drive)
    if problems:
        raise ValueError("; ".join(problems))
    return model, controller


def baseline_compensation(analysis: Analysis) -> Compensation:
    """The paper's compensation of the paper's model: the baseline GPIM (G_v for ff_pid_g), no effect, no
    dynamic feedforward."""
    base, drive = analysis.baseline, fitted_range(analysis)
    controller = base_model(base, False, drive)
    problems = controller.problems(*drive)
    if problems:
        raise ValueError("; ".join(problems))
    return Compensation(base, controller, {})


def controller_parameters(comp: Compensation) -> dict:
    """``valve_controller`` parameters (name -> value) for a compensation."""
    return comp.controller_model.to_parameters()
