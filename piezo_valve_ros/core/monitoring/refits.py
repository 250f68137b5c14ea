"""When the health monitor asks for a refit, and what it pushes itself (``valve_monitor``'s ``refit_when``).

What the operating data determine is pushed, only while the controller is enabled with its oscillation guard off,
under a strategy that runs the model (not OL or PID: there a push cannot help) and at most once a window:

* an offset the model lacks (a drift): the controller's ``gpim.offset_um`` moved by the window's mean residual.
  A push made while a drift was still settling leaves the rest of it: the next windows, judged on the new model,
  show a smaller offset, often below the level that asked for the push (WARN where ``refit_when`` is error).  That
  rest is followed up at WARN, push after push, until a verdict is OK again;
* a gain change (with its offset), where the window determines it: fitted on the window's first part and checked
  on its held-out rest, with the prediction spanning enough of the output range to tell a gain from an offset
  (``health.GainCorrection``).  A window that names a gain change but does not support the push says why.

Each push replaces the whole model in one atomic parameter change, and is checked on the next window: the monitor
runs the model before the push beside the new one from the same state, and a push whose window is worse than the
model it replaced would have left is undone (and a gain push is not tried again until the valve is OK).  Anything
else (creep, the loop's shape) needs a designed experiment: the monitor says once which plan to run.  No ROS import
here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Mapping, Optional

from ..control.compensation import CompensationModel
from ..control.strategies import NO_INVERSE, REGISTRY, STRATEGIES
from .health import GAIN_PREFIX, OFFSET_PREFIX, Health, Level

__all__ = ["RefitPolicy", "RefitDecision", "REFIT_LEVELS", "OFFSET", "GAIN", "UNDO", "PUSH_KINDS", "PUSH_COLUMNS",
           "push_row"]

REFIT_LEVELS = {"never": None, "warn": Level.WARN, "error": Level.ERROR}
OFFSET, GAIN, UNDO = "offset", "gain", "undo"   # what a push does
PUSH_KINDS = (OFFSET, GAIN, UNDO)               # (their index + 1 labels a push on valve_monitor's ~/pushes)
PLAN_ADVICE = ("run the identification plan (valve_identification --ros-args -p "
               "plan:=validate,train,refit,validate)")


@dataclass(frozen=True)
class RefitDecision:
    """What one verdict asks for: a push (``kind`` OFFSET, GAIN or UNDO, ``model`` the whole model to push,
    ``evidence`` what decided it), or not now and why (``not_now``), or the identification plan to run
    (``advice``, said once), or a push checked and kept (``kept``, said once)."""
    kind: str = ""
    model: Optional[CompensationModel] = None
    evidence: str = ""
    not_now: str = ""
    advice: str = ""
    kept: str = ""
    offset_change_um: Optional[float] = None   # an OFFSET push: what the model's gpim.offset_um moves by [um]
    gain_change: Optional[float] = None        # a GAIN push: the share its weights are scaled by, less 1

    @property
    def pushes(self) -> bool:
        return self.model is not None

    def offset_after(self, model_offset_um: float) -> float:
        """The model's ``gpim.offset_um`` [um] once an OFFSET push is applied: the valve reads ``offset_change_um``
        above what the model predicts (the window's mean residual, measured less predicted), so the offset moves
        up by it."""
        if self.offset_change_um is None:
            raise ValueError("this decision pushes no offset")
        return float(model_offset_um) + self.offset_change_um


class RefitPolicy:
    """The refit decisions of one monitor: ``refit_at`` the level that asks for one (None: never), ``window_s`` [s]
    the judged windows' length (pushes at most once a window)."""

    def __init__(self, refit_at: Optional[Level], window_s: float):
        self.refit_at = refit_at
        self.window_s = float(window_s)
        self.last_push_s = -math.inf     # the end [s, the rig's time] of the window the last push came from
        self.following_up = False        # an offset was pushed and no verdict has been OK since
        self.replaced: Optional[CompensationModel] = None   # the model the last push replaced, until it is checked
        self.replaced_kind = ""
        self.gain_undone = False         # a gain push was undone and no verdict has been OK since
        self.awaiting = False            # a push (or an undo) was sent and no window has been judged on its model yet
        self._advised = False

    def pushed(self, ok: bool) -> None:
        """The node's word on the push just decided: applied (``ok``) or refused by the controller, or nothing to
        change (nothing to check or wait for then)."""
        if not ok:
            self.replaced, self.replaced_kind = None, ""
            self.awaiting = False

    def decide(self, health: Health, controller_state: Mapping[str, float],
               model: Optional[CompensationModel] = None,
               judged_on: Optional[CompensationModel] = None) -> Optional[RefitDecision]:
        """The decision for ``health`` (None: nothing to do or say); ``controller_state`` the controller's latest
        ``~/controller_state`` row by column name (empty: not known); ``model`` the model in force (a push is
        built on it); ``judged_on`` the model the verdict was judged on, where known.

        A verdict judged on another model than the one in force decides no push (its residual is not the model's),
        and after a push or an undo nothing is decided until a window judged on the model it made (the first
        carries ``previous_model_rms_um``): windows already waiting to be judged on a loaded machine would otherwise
        push the same offset again, on top of the pushed one."""
        if self.refit_at is None:
            return None
        decision = self._decide(health, controller_state, model, judged_on)
        if decision is not None and decision.pushes:
            self.awaiting = True
        return decision

    def _decide(self, health: Health, controller_state: Mapping[str, float], model: Optional[CompensationModel],
                judged_on: Optional[CompensationModel]) -> Optional[RefitDecision]:
        if self.awaiting:
            if health.previous_model_rms_um is None:
                return RefitDecision(not_now="a refit was pushed: waiting for a window judged on the model it made")
            self.awaiting = False
        checked = self._check_last_push(health)
        if checked is not None:
            return checked
        if health.level is Level.OK:
            self.following_up = self.gain_undone = False
            return None
        if health.level not in (Level.WARN, Level.ERROR):
            return None
        offset = health.resembles.startswith(OFFSET_PREFIX)
        gain = health.resembles.startswith(GAIN_PREFIX) and health.correction is not None and not self.gain_undone
        if health.level < self.refit_at and not (self.following_up and offset):
            return None
        if gain and health.correction.refused:
            return RefitDecision(not_now=f"the gain change is not pushed: {health.correction.refused}"
                                         + self._advice_once(health, "; "))
        if not (offset or gain):
            advice = self._advice_once(health)
            return RefitDecision(advice=advice) if advice else None
        if judged_on is not None and model is not None and judged_on is not model:
            return RefitDecision(not_now="the window was judged on a model no longer in force (the next windows are "
                                         "judged on the model in force)")
        unsafe = self._unsafe(health, controller_state, model)
        if unsafe:
            return RefitDecision(not_now=unsafe)
        self.last_push_s = health.end_s
        self.replaced = model
        if gain:
            c = health.correction
            self.replaced_kind = GAIN
            return RefitDecision(kind=GAIN, model=c.applied_to(model), gain_change=c.gain,
                                 evidence=f"a gain change the window determines: {c.describe()}")
        self.following_up, self.replaced_kind = True, OFFSET
        pushed = replace(model, gpim=replace(model.gpim, offset_um=model.gpim.offset_um + health.residual_mean_um))
        return RefitDecision(kind=OFFSET, model=pushed, offset_change_um=health.residual_mean_um,
                             evidence=f"the offset a drift moved: the window's mean residual "
                                      f"{health.residual_mean_um:+.4f} um ({health.resembles})")

    def _check_last_push(self, health: Health) -> Optional[RefitDecision]:
        """The first verdict after a push (it carries the replaced model's figure on the same rows): the push undone
        where it left the window worse, else kept."""
        if self.replaced is None or health.previous_model_rms_um is None:
            return None
        before, kind = self.replaced, self.replaced_kind
        self.replaced, self.replaced_kind = None, ""
        figures = (f"the window after it {health.start_s:.1f}..{health.end_s:.1f} s: residual RMS "
                   f"{health.residual_rms_um:.4f} um with it, {health.previous_model_rms_um:.4f} um with the model "
                   f"it replaced")
        if health.residual_rms_um > health.previous_model_rms_um:
            self.last_push_s = health.end_s
            self.following_up = False
            self.gain_undone = self.gain_undone or kind == GAIN
            return RefitDecision(kind=UNDO, model=before, evidence=f"the {kind} push made things worse: {figures}")
        return RefitDecision(kept=f"the {kind} push kept: {figures}")

    def _unsafe(self, health: Health, state: Mapping[str, float], model: Optional[CompensationModel]) -> str:
        """Why nothing may be pushed now ("": it may)."""
        if model is None:
            return "the controller's model is not known"
        if not state:
            return "the controller's state is not known (~/controller_state)"
        if state.get("enabled", 0.0) < 0.5:
            return "the controller is disabled"
        if state.get("guard_active", 0.0) > 0.5:
            return "the controller's oscillation guard is active"
        index = state.get("strategy_index", math.nan)
        if not (math.isfinite(index) and 0 <= int(index) < len(STRATEGIES)):
            return "the controller's strategy is not known (~/controller_state)"
        strategy = REGISTRY[STRATEGIES[int(index)]]
        if strategy.inverse == NO_INVERSE:
            return (f"the controller runs {strategy.label}, which does not use the model: a push cannot help "
                    "(it would under OL HC, PID HC, FF PID or FF PID G)")
        if health.end_s - self.last_push_s < self.window_s:
            return "a refit was pushed less than a window ago"
        return ""

    def _advice_once(self, health: Health, lead: str = "") -> str:
        if self._advised:
            return ""
        self._advised = True
        return (f"{lead}a refit is needed ({health.resembles}): the operating data do not determine it; "
                + PLAN_ADVICE)


PUSH_COLUMNS = ("end_s", "kind", "gain_change", "offset_um_before", "offset_um_after", "evidence_rms_before_um",
                "evidence_rms_after_um")   # valve_monitor's ~/pushes: kind 1 offset, 2 gain, 3 undo (PUSH_KINDS); the
# evidence's RMS [um] without and with the push: the window's residual and its rest less the mean (offset), the
# held-out part's (gain), the next window's with the push and with the model it replaced (undo)


def push_row(health: Health, decision: RefitDecision, before: CompensationModel) -> list[float]:
    """One PUSH_COLUMNS row for ``decision`` on ``health`` (``before``: the model it replaces)."""
    if decision.kind == GAIN:
        evidence = (health.correction.held_out_rms_in_force_um, health.correction.held_out_rms_corrected_um)
    elif decision.kind == UNDO:
        evidence = (health.residual_rms_um, health.previous_model_rms_um)
    else:
        evidence = (health.residual_rms_um, math.sqrt(max(health.residual_rms_um ** 2 - health.residual_mean_um ** 2, 0.0)))
    return [health.end_s, float(PUSH_KINDS.index(decision.kind) + 1), decision.gain_change or 0.0,
            before.gpim.offset_um, decision.model.gpim.offset_um, *evidence]
