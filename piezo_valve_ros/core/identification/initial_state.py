"""The operators' state before a record, estimated from its first rows (before its input wiped it out): rest,
cycled, rested at another voltage, or back from an excursion (a training record, ``estimate_state``); and a
separate session's start and sensor zero, for one model (``session_start``).  Nothing here imports ROS."""
from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np
from scipy import optimize

from ..metrics import rms
from ..model.hysteresis import play_batch, play_bounds
from .records import Record, analysis_record
from .split import SessionStart, first_rows
from ..model.at_rest import filter_rows_at_rest
from .valve_model import REST, InitialState, ValveModel

__all__ = ["estimate_state", "session_start", "SessionStart", "WIPE_STATE_GAIN", "ESTIMATE_STATE_GAIN",
           "ESTIMATE_ROUNDS"]

WIPE_STATE_GAIN = 0.5       # a state before the record must halve the misfit of the rows before the wipe
REMANENT_GRID = 201  # voltages tried when estimating a remanent state before the record ...
ESTIMATE_SHORT_S = 0.1   # ... on its first rows this long; the best ESTIMATE_REFINED of each kind refined
ESTIMATE_REFINED = 2
ESTIMATE_STATE_GAIN = 0.2   # an estimated start is taken when it cuts the first rows' misfit by >= 20 % (and
                            # the held-out RMS by WIPE_GAIN); a drift's early misfit is not cut at all
ESTIMATE_ROUNDS = 2   # estimate the start, fit, estimate again: at most this many fits
EXCURSION_GAIN = 0.1  # "back from an excursion" replaces "rested at a voltage" only if 10 % closer to the data


def estimate_state(model: ValveModel, rows: Record, whole: Record, with_effects: bool = False,
                   range_v: Optional[tuple[float, float]] = None, grid_points: int = 0) -> tuple[InitialState, dict]:
    """The state before a record, estimated on its first ``rows`` (before its input wiped it out) with
    ``model``'s GPIM and G: rest, cycled, or remanent with one voltage e on the ``whole`` record's range and
    half a span beyond: at rest at e and moved to the first voltage v0 (a valve that rested elsewhere, e.g. a
    closed-loop record whose controller's first command left the rest voltage), or at rest at v0 and
    back from an excursion to e (a valve left off its loop).  The GPIM and G alone, unless ``with_effects``
    (a final model's creep, e.g., has settled at rest too).  ``grid_points``: voltages tried for e (default
    REMANENT_GRID).  ``range_v``: the voltages [V] to search instead
    of the whole record's (the health monitor's first rows move little; the drive's range bounds e).
    Returns (the best state, figures)."""
    v0 = float(rows.voltage_v[0])
    lo, hi = range_v if range_v is not None else (float(np.min(whole.voltage_v)), float(np.max(whole.voltage_v)))
    half = 0.5 * max(hi - lo, 1e-9)
    grid = [float(e) for e in np.linspace(lo - half, hi + half, grid_points or REMANENT_GRID) if e != v0]
    options = {"rest": REST, "cycled": InitialState("cycled")}
    bare = model if with_effects else replace(model, effects=(), coefs=())
    # the misfit is sharp in the voltage (where the valve rested sets the first samples through G): a fine
    # grid on the first ESTIMATE_SHORT_S, ranked by the GPIM and G alone (``grid_misfits``: every candidate at
    # once), then each family's best few refined on all the rows with the model as asked
    short = rows.slice(0, min(len(rows), max(int(ESTIMATE_SHORT_S / rows.dt), 20)))

    def misfit(state: InitialState, on: Record = rows) -> float:
        return rms(on.position_um - replace(bare, history=state).predict(on))

    scores = {name: misfit(state) for name, state in options.items()}
    step = (grid[1] - grid[0]) if len(grid) > 1 else half
    for family, make in (("rested at", lambda e: InitialState("remanent", (e,))),
                         ("back from", lambda e: InitialState("remanent", (v0, e)))):
        quick = [grid[i] for i in np.argsort(grid_misfits(model, [make(e) for e in grid], short),
                                             kind="stable")[:ESTIMATE_REFINED]]
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


GRID_BANK_VALUES = 4_000_000   # operator states (starts x operators x rows) grid_misfits holds at once (32 MB)


def grid_misfits(model: ValveModel, starts: list[InitialState], rows: Record) -> np.ndarray:
    """RMS misfits [um] (len(starts),) on ``rows`` of ``model``'s GPIM and G alone (no effects) from each of
    ``starts``, many at once: the operators of each bunch of starts side by side in one play bank
    (``GRID_BANK_VALUES``), their outputs through G as one bank of rows.  What ``estimate_state``'s grid ranks its
    candidate starts by: to rounding, what ``replace(model, effects=(), history=start).predict(rows)`` gives."""
    g = model.gpim
    ctx = replace(model, effects=(), coefs=(), history=REST).context(rows)
    lower, upper = ctx.drives
    n_rows = len(rows)
    bunch = max(1, GRID_BANK_VALUES // max(g.n * n_rows, 1))
    out = np.empty(len(starts))
    for first in range(0, len(starts), bunch):
        some = starts[first:first + bunch]
        k = len(some)
        initial = np.concatenate([start.states(g, rows.voltage_v) for start in some])
        states, _ = play_batch(lower, upper, np.tile(g.thresholds, k), initial, compiled=True)
        H = (states.reshape(n_rows, k, g.n) @ g.weights + g.offset_um).T                  # (k, N)
        rest = np.array([H[j, 0] if start.rested_at_v is None
                         else float(g.weights @ g.state_after((start.rested_at_v,)) + g.offset_um)
                         for j, start in enumerate(some)])
        error = rows.position_um[None, :] - filter_rows_at_rest(*ctx.filter, H, rest)
        out[first:first + k] = np.sqrt(np.mean(error * error, axis=1))
    return out


SESSION_GRID = 41             # voltages tried for the simple story a separate session starts from (then refined)
SESSION_BOUNDS_KEPT = 8       # clamp bounds of this many hysteresis structures are kept
SESSION_RATE_HZ = 500.0       # a separate session's start is estimated on block means at most this rate
SESSION_RIDGE = 1e-4          # ridge on the standardised state changes: what the record cannot tell stays at rest
SESSION_ROUNDS = 8            # Gauss-Newton rounds at most (the clamps' active sets settle in a few)
SESSION_TOLERANCE = 1e-3     # ... until a round cuts the squared error by less than this share
SESSION_WINDOW_S = 60.0       # ... and at most this long (shorter, the operators wiped after it would count as
                              # constants there, which the in-window offset takes, and the rows before the wipe
                              # would keep that offset less the whole record's as error)
SESSION_WINDOW_SHARE = 0.5    # ... and at most this share of the record: the rest scores the models (a closed-loop
                              # record may leave an operator unwiped to its end: the start would be fitted on it all)
SESSION_SETTLE_S = 0.05       # rows the start is estimated on: until every operator it can move is wiped, and this


def session_start(model: ValveModel, record: Record, t0: float, bounds: Optional[dict] = None) -> SessionStart:
    """A separate session's unknown start and sensor zero, for ``model`` on ``record`` (analysis rate, time origin
    ``t0``): every operator's state at the first sample and the static output G had settled to before it, by
    bounded Gauss-Newton (the GPIM's sensitivities through G; the whole model's error), from the simple story that
    fits the first rows best, on the rows (at most ``SESSION_WINDOW_S``) until the input has wiped out every
    operator it
    moves (``hysteresis.play_bounds``: an operator's state counts until then, and only then); an operator the
    record never moves acts as a constant, which the session's offset takes.  That offset is the mean error of the
    whole model from that start over the whole record (a re-zeroed sensor, a mount that moved).  What rested before
    the record, what the valve went through before it and a sensor zero of its own are covered, as a simulation of
    a record is started from initial conditions estimated for it.  ``bounds``: a dict in which the operators' clamp
    bounds on the record are kept for the next model of the same hysteresis structure."""
    g = model.gpim
    full = record
    record = analysis_record(record, SESSION_RATE_HZ)   # the states are slow: estimated on block means
    bare = replace(model, effects=(), coefs=(), history=REST)
    ctx = bare.context(record, t0)
    key = (id(full.time_s), len(full), bare.structure_key)
    if bounds is not None and key in bounds:
        L, U = bounds[key]
    else:
        lower, upper = ctx.drives
        L, U = play_bounds(lower, upper, g.thresholds)
        if bounds is not None:
            while len(bounds) >= SESSION_BOUNDS_KEPT:
                bounds.pop(next(iter(bounds)))    # the oldest structure first
            bounds[key] = (L, U)
    open_ = U > L
    wiped = ~open_[-1]                                   # moved by the record (its start wiped out at some point)
    starts_open = open_[0] & wiped
    collapse = np.where(open_.any(axis=0), open_.shape[0] - np.argmax(open_[::-1], axis=0), 0)
    free_states = np.flatnonzero(starts_open)
    n_rows = int(min(len(record), int(SESSION_WINDOW_S / record.dt), int(SESSION_WINDOW_SHARE * len(record)),
                     (np.max(collapse[free_states]) if free_states.size else 0) + max(int(SESSION_SETTLE_S / record.dt), 20)))
    L, U = L[:n_rows], U[:n_rows]
    window = record.slice(0, n_rows)
    b, a = ctx.filter
    free = ctx.free_response[:n_rows]
    y = window.position_um
    # from the simple story that fits the first rows best (rest, cycled, rested at another voltage, back from an
    # excursion: ``estimate_state``), refined operator by operator below
    simple, _ = estimate_state(model, first_rows(record), record, with_effects=True, grid_points=SESSION_GRID)
    z = np.clip(simple.states(g, record.voltage_v), L[0], U[0])
    simple_model = replace(model, history=simple)
    simple_ctx = simple_model.context(record.slice(0, 2), t0)
    _, rest = simple_model.static_output_and_rest(simple_ctx)
    rest = float(simple_model.static_output(simple_ctx)[0]) if rest is None else float(rest)
    offset = 0.0   # the static output G had settled to before the record (rest) [um], the session's offset
    k = free_states.size

    def started(z_, rest_) -> ValveModel:
        return replace(model, history=InitialState("given", states_v=tuple(z_), rest_output_um=rest_))

    def error(z_, rest_, offset_) -> np.ndarray:
        """The model's error on the window from this start, less the offset: the GPIM and G alone for a model
        without effects, else the whole model (a creep left out of the start would bend every state)."""
        if model.effects:
            return y - started(z_, rest_).predict(window, t0) - offset_
        H_ = np.clip(z_, L, U) @ g.weights + g.offset_um
        return y - filter_rows_at_rest(b, a, H_[None, :])[0] - (rest_ - H_[0]) * free - offset_

    sse = float(np.sum(error(z, rest, offset) ** 2))
    L_free, U_free = L[:, free_states], U[:, free_states]   # the states estimated: their bounds alone
    open_free, w_free = L_free < U_free, g.weights[free_states]
    for _ in range(SESSION_ROUNDS):
        z_free = z[free_states]
        active = ((L_free <= z_free) & (z_free <= U_free) & open_free) * w_free   # dH / dz_j while the start counts
        columns = filter_rows_at_rest(b, a, np.ascontiguousarray(active.T))   # through G, at rest at the first row
        design = np.vstack((columns, free[None, :], np.ones((1, n_rows))))
        scale = np.sqrt(np.mean(design * design, axis=1))
        scale[scale == 0] = 1.0
        A = (design / scale[:, None]).T
        ridge = np.concatenate((np.full(k, SESSION_RIDGE), [0.0, 0.0])) * n_rows
        lower_step = np.concatenate(((L[0] - z)[free_states], [-np.inf, -np.inf])) * scale
        upper_step = np.concatenate(((U[0] - z)[free_states], [np.inf, np.inf])) * scale
        factor = np.linalg.cholesky(A.T @ A + np.diag(ridge))      # the ridge problem as a square bounded one
        step = optimize.lsq_linear(factor.T, np.linalg.solve(factor, A.T @ error(z, rest, offset)), method="bvls",
                                   bounds=(lower_step, np.maximum(upper_step, lower_step + 1e-12))).x / scale
        for fraction in (1.0, 0.5, 0.25):   # the clamps bend the straight line: take the part that pays
            trial_z = z.copy()
            trial_z[free_states] = np.clip(z[free_states] + fraction * step[:k], L[0][free_states], U[0][free_states])
            trial = (trial_z, rest + fraction * float(step[k]), offset + fraction * float(step[k + 1]))
            trial_sse = float(np.sum(error(*trial) ** 2))
            if trial_sse < sse:
                break
        if trial_sse >= sse:
            break
        gain = 1.0 - trial_sse / sse
        (z, rest, offset), sse = trial, trial_sse
        if gain < SESSION_TOLERANCE:
            break
    # the session's zero: the whole model from that start, over the whole record
    scored = started(z, rest)
    error_full = full.position_um - scored.predict(full, t0)
    mean = float(np.mean(error_full))
    rows_full = min(n_rows * record.block // max(full.block, 1), len(full))
    return SessionStart(scored.history, mean, rows_full, rms(error_full[:rows_full] - mean))

