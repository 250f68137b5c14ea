"""When the health monitor asks for a refit, and what it pushes itself (``valve_monitor``'s ``refit_when``).

What the operating data determine, an offset the model lacks (a drift), is pushed: the controller's
``gpim.offset_um`` moved by the window's mean residual, only while the controller is enabled with its oscillation
guard off and at most once a window.  A push made while a drift was still settling leaves the rest of it: the next
windows, judged on the new model, show a smaller offset, often below the level that asked for the push (WARN where
``refit_when`` is error).  That rest is followed up at WARN, push after push, until a verdict is OK again; without
the follow-up the valve would stay at WARN for good.  Anything else (a gain change, creep, the loop's shape) needs a
designed experiment: the monitor says once which plan to run.  No ROS import here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional

from .health import OFFSET_PREFIX, Health, Level

__all__ = ["RefitPolicy", "RefitDecision", "REFIT_LEVELS"]

REFIT_LEVELS = {"never": None, "warn": Level.WARN, "error": Level.ERROR}


@dataclass(frozen=True)
class RefitDecision:
    """What one verdict asks for: move ``gpim.offset_um`` by ``offset_change_um`` [um] (not None), or not now and
    why (``not_now``), or the identification plan to run (``advice``, said once)."""
    offset_change_um: Optional[float] = None
    not_now: str = ""
    advice: str = ""

    def offset_after(self, model_offset_um: float) -> float:
        """The model's ``gpim.offset_um`` [um] once the push is applied: the valve reads ``offset_change_um`` above
        what the model predicts (the window's mean residual, measured less predicted), so the offset moves up by it."""
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
        self.following_up = False        # a push was made and no verdict has been OK since
        self._advised = False

    def decide(self, health: Health, controller_state: Mapping[str, float]) -> Optional[RefitDecision]:
        """The decision for ``health`` (None: nothing to do or say); ``controller_state`` the controller's latest
        ``~/controller_state`` row by column name (empty: not known)."""
        if self.refit_at is None:
            return None
        if health.level is Level.OK:
            self.following_up = False
            return None
        if health.level not in (Level.WARN, Level.ERROR):
            return None
        offset = health.resembles.startswith(OFFSET_PREFIX)
        if health.level < self.refit_at and not (self.following_up and offset):
            return None
        if not offset:
            if self._advised:
                return None
            self._advised = True
            return RefitDecision(advice=f"a refit is needed ({health.resembles}): the operating data do not determine "
                                        "it; run the identification plan (valve_identification --ros-args -p "
                                        "plan:=validate,train,refit,validate)")
        unsafe = ("the controller's state is not known (~/controller_state)" if not controller_state else
                  "the controller is disabled" if controller_state.get("enabled", 0.0) < 0.5 else
                  "the controller's oscillation guard is active" if controller_state.get("guard_active", 0.0) > 0.5
                  else "a refit was pushed less than a window ago" if health.end_s - self.last_push_s < self.window_s
                  else "")
        if unsafe:
            return RefitDecision(not_now=unsafe)
        self.last_push_s = health.end_s
        self.following_up = True
        return RefitDecision(offset_change_um=health.residual_mean_um)
