"""The operators' state before a record, estimated from its first rows (before its input wiped it out): rest,
cycled, rested at another voltage, or back from an excursion.  Nothing here imports ROS."""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np
from scipy import optimize

from ..metrics import rms
from .records import Record
from .split import Split
from .valve_model import REST, InitialState, ValveModel

__all__ = ["estimate_state", "own_start", "WIPE_STATE_GAIN", "ESTIMATE_STATE_GAIN", "ESTIMATE_ROUNDS"]

WIPE_STATE_GAIN = 0.5       # a state before the record must halve the misfit of the rows before the wipe
REMANENT_GRID = 201  # voltages tried when estimating a remanent state before the record ...
ESTIMATE_SHORT_S = 0.1   # ... on its first rows this long; the best ESTIMATE_REFINED of each kind refined
ESTIMATE_REFINED = 2
ESTIMATE_STATE_GAIN = 0.2   # an estimated start is taken when it cuts the first rows' misfit by >= 20 % (and
                            # the held-out RMS by WIPE_GAIN); a drift's early misfit is not cut at all
ESTIMATE_ROUNDS = 2   # estimate the start, fit, estimate again: at most this many fits
EXCURSION_GAIN = 0.1  # "back from an excursion" replaces "rested at a voltage" only if 10 % closer to the data


def estimate_state(model: ValveModel, rows: Record, whole: Record, with_effects: bool = False,
                   range_v: Optional[tuple[float, float]] = None) -> tuple[InitialState, dict]:
    """The state before a record, estimated on its first ``rows`` (before its input wiped it out) with
    ``model``'s GPIM and G: rest, cycled, or remanent with one voltage e on the ``whole`` record's range and
    half a span beyond: at rest at e and moved to the first voltage v0 (a valve that rested elsewhere, e.g. a
    closed-loop record whose controller's first command left the rest voltage), or at rest at v0 and
    back from an excursion to e (a valve left off its loop).  The GPIM and G alone, unless ``with_effects``
    (a final model's creep, e.g., has settled at rest too).  ``range_v``: the voltages [V] to search instead
    of the whole record's (the health monitor's first rows move little; the drive's range bounds e).
    Returns (the best state, figures)."""
    v0 = float(rows.voltage_v[0])
    lo, hi = range_v if range_v is not None else (float(np.min(whole.voltage_v)), float(np.max(whole.voltage_v)))
    half = 0.5 * max(hi - lo, 1e-9)
    grid = [float(e) for e in np.linspace(lo - half, hi + half, REMANENT_GRID) if e != v0]
    options = {"rest": REST, "cycled": InitialState("cycled")}
    bare = model if with_effects else replace(model, effects=(), coefs=())
    # the misfit is sharp in the voltage (where the valve rested sets the first samples through G): a fine
    # grid on the first ESTIMATE_SHORT_S, then each family's best few refined on all the rows
    short = rows.slice(0, min(len(rows), max(int(ESTIMATE_SHORT_S / rows.dt), 20)))

    def misfit(state: InitialState, on: Record = rows) -> float:
        return rms(on.position_um - replace(bare, history=state).predict(on))

    scores = {name: misfit(state) for name, state in options.items()}
    step = (grid[1] - grid[0]) if len(grid) > 1 else half
    for family, make in (("rested at", lambda e: InitialState("remanent", (e,))),
                         ("back from", lambda e: InitialState("remanent", (v0, e)))):
        quick = sorted(grid, key=lambda e: misfit(make(e), short))[:ESTIMATE_REFINED]
        for e in quick:
            found = optimize.minimize_scalar(lambda x: misfit(make(x)), bounds=(e - step, e + step), method="bounded",
                                             options={"xatol": 1e-3 * half})
            x = float(found.x) if found.x != v0 else e
            name = f"{family} {x:.6g} V"
            options[name], scores[name] = make(x), misfit(make(x))
    # the simpler story first: rested somewhere (G then also starts from rest there) unless an excursion
    # explains the first rows clearly better
    simple = min((n for n in scores if not n.startswith("back from")), key=scores.get)
    excursion = min((n for n in scores if n.startswith("back from")), key=scores.get, default=simple)
    best = excursion if scores[excursion] < (1 - EXCURSION_GAIN) * scores[simple] else simple
    return options[best], {"estimate": options[best].describe(), "rms_before_wipe_um": round(scores[best], 6),
                           "rms_before_wipe_from_rest_um": round(scores["rest"], 6), "samples_before_wipe": len(rows)}


def own_start(model: ValveModel, split: Split, always: bool) -> Optional[InitialState]:
    """A validation record's own start, estimated on its first rows with ``model`` (``_estimate_state``):
    taken ``always``, or where it halves those rows' misfit from the model's own initial state
    (WIPE_STATE_GAIN, as a state before a wipe must: a closed-loop record whose controller's first command
    left the rest voltage, cut 89 %; an unmodelled creep's early misfit is cut ~20 % by a wrong start).  The
    misfit a slow effect leaves all over the record does not hide a wrong start.  None otherwise."""
    rows = split.first_rows(split.score)
    state, figures = estimate_state(model, rows, split.score)
    if always:
        return state
    first = rms(rows.position_um - model.predict(rows, split.score_t0))
    return state if figures["rms_before_wipe_um"] <= (1 - WIPE_STATE_GAIN) * first else None
