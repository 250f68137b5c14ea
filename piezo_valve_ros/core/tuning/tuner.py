"""PID gains for a strategy, chosen on the identified model (the paper's came from a proprietary tuner).

The tuner only knows what identification found (a :class:`~.compensation.CompensationModel`: GPIM, G_v,
creep, saturation map).  It

1. screens a grid of PID gains on the *linearised* loop: the controller's exact discrete PID (integrator,
   filtered derivative) times the plant the PID sees, ``z^-1 G_v(z)`` (ZOH) with the creep lags: the
   command of period k is answered at k + 1, one period of computation delay, the lockstep rig's timing.
   For ``pid``, ``ff_pid`` and ``ff_pid_g`` the PID acts through the nominal static gain k, so the plant's
   gain is the local slope of the hysteresis (and the saturation map) over k: from one operator's weight
   just after a reversal to all of them on a long sweep; the margins must hold over that whole range.
   ``pid_hc`` acts through the inverse, so its plant gain is 1.  A candidate passes when the loop is stable
   (closed-loop poles), its gain margin >= ``min_gain_margin_db``, phase margin >= ``min_phase_margin_deg``
   and its noise gain (the PID's gain at the Nyquist frequency, um of command per um of measurement noise)
   <= ``max_noise_gain``, and its gain crossover >= ``min_crossover_hz`` (feedback that corrects creep, drift
   or a load in tens of ms, not a PID tuned down to nothing because the feedforward alone steps fastest);
2. ranks the passing sets by the paper's step on that linearised loop (:func:`linear_step`: settling time,
   overshoot on the plant and on its dynamics ``DYNAMICS_SCALES`` times faster and slower) and refines the
   fastest there by a pattern search, within several shares of the overshoot budget (the linearised loop
   misses what the hysteresis inverse leaves; it ranks sets well but is optimistic on overshoot);
3. runs the paper's three steps (2 ms ramps) with the real controller (``strategies.ValveController``) on
   the identified model as a valve (:class:`ModelValve`), commands clamped to the command limits with the
   controller's anti-windup as on the rig, for the ``VERIFIED_RUNS`` fastest on the linearised loop and the
   paper's Table 1 sets for the strategy (a tuner should never do worse on its own model than the gains it
   replaces), and takes the ``REFINE_STARTS`` best within the limits: overshoot <= ``max_overshoot_pct`` on
   every step, on the model and on the model with the dynamics varied (an identified G_v is not the valve's:
   a PI zero placed on the fitted pole overshoots on the real one).  Where the PID acts through the
   hysteresis (``pid``) the linearised loop orders the sets well overall but not at the top (the fastest
   on the real steps lie tens of places down its ranking), hence a fine grid (x1.19 in kp) and many runs;
4. refines each of those by a pattern search on the real steps (:func:`_moves`: the overall gain, the PI
   zero ki/kp and the derivative time kd/kp, halving steps) under the same constraints, and keeps the best.

What it minimises (nominal performance under robust constraints): the average settling time on the model,
resolved below the sample period (``StepMetrics.band_exit_s``: the paper's settling time moves in whole
periods, which leaves a search on flat steps), times ``1 + OVERSHOOT_COST`` x (its worst overshoot / the
limit); ties go to less time on a command limit,
then less overshoot.  The dynamics variants are constraints (overshoot within the limit), not part of the
cost: taking their slowest settling time as the cost (robust performance) bought robustness the limits
already ensure with speed on the valve, and with identification's G_v within a few per cent of the valve's
the nominal model is the one to be fast on.

Nothing here imports ROS: ``valve_tune`` and the identification node's ``tune`` step are faces over
:func:`tune`.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Callable, Optional, Sequence

import numpy as np

from ..blas import one_blas_thread
from ..defaults import CONTROL_PERIOD_S
from ..errors import PiezoValveError
from ..control.compensation import CompensationModel, reference_filters
from ..control.forward import ModelValve
from ..model.dynamics import ContinuousTF, first_order_lag, scipy_signal
from ..sim.experiments import responses, run_closed_loop
from ..metrics import StepMetrics, step_metrics
from ..sim.signals import PAPER_STEPS_UM, step_reference_m
from ..validation import NON_NEGATIVE, field_problems, ruled
from ..control.strategies import (FEEDBACK_STRATEGIES, FEEDFORWARD_INVERSE, IN_LOOP_INVERSE, REGISTRY, TABLE1_GAINS,
                                  ControllerConfig, PIDGains, ValveController, nominal_static_gain)

__all__ = ["TUNABLE_STRATEGIES", "TuningLimits", "LoopMargins", "StepScore", "TuningResult", "TuningError",
           "plant_gain_range", "loop_margins", "linear_step", "step_score", "dynamics_variants",
           "variant_scores", "robust_overshoot_pct", "outside_limits", "tune"]

TUNABLE_STRATEGIES = FEEDBACK_STRATEGIES   # every strategy with a feedback loop
OVERSHOOT_LIMIT_PCT = 2.0      # default: no step may overshoot by more than this [% of the step]
MIN_GAIN_MARGIN_DB = 6.0       # default: the loop gain may double before the loop goes unstable ...
MIN_PHASE_MARGIN_DEG = 45.0    # ... and this much extra phase lag is tolerated
MAX_NOISE_GAIN = 3.0           # default: |PID| at the Nyquist frequency [um/um]; the most aggressive Table 1
#                                set (PID 2) has 2.4 at 10 kHz, 2.9 at 1 kHz
MIN_CROSSOVER_HZ = 5.0         # default: the slowest gain crossover [Hz] over the plant-gain range (Table 1's
#                                slowest set, FF PID 6, crosses at 7.9 Hz on the paper's model)
GAIN_POINTS = 5                # plant gains checked across the slope range (pid, ff_pid, ff_pid_g)
FREQUENCY_POINTS = 600         # frequencies of the margin computation, log-spaced up to Nyquist
MARGIN_BATCH = 256             # gain sets whose loop responses are evaluated in one array (~12 MB)
KP_GRID = np.geomspace(0.005, 20.0, 49)    # proportional gains screened [-] (x1.19)
ZERO_GRID_RATIO = np.geomspace(0.05, 4.0, 19)  # PI zero ki/kp as a share of the plant's slowest pole [-] (x1.28)
DERIVATIVE_GRID_S = (0.0, 1e-4, 2e-4, 3e-4, 4e-4)  # kd/kp screened [s] (0: PI, as all of Table 1)
LINEAR_STARTS = 3              # the fastest grid sets on the linearised loop refined there by pattern search ...
LINEAR_BUDGET_SHARES = (1.0, 0.5, 0.25, 0.1)  # ... within these shares of the overshoot limit (the linearised loop
#                                misses what the hysteresis inverse leaves: the real steps overshoot more)
VERIFIED_RUNS = 60             # the fastest grid sets on the linearised loop run through the real steps
REFINE_STARTS = 3              # the best of those within the limits refined on the real steps
REFINE_ROUNDS = 4              # pattern-search rounds (the step halves each round)
REFINE_START_STEP = 0.4        # first pattern step in natural-log units (x1.5)
OVERSHOOT_COST = 0.4           # a set's settling time counts (1 + this x its worst overshoot / the limit) times
#                                (on the model): overshoot at the limit costs 40 % more time,
#                                so of two sets about equally fast the one overshooting less wins (the model is
#                                noise-free: the valve's sensor noise adds its peaks on top)
DYNAMICS_SCALES = (0.9, 1.1)   # the overshoot limit must also hold with G_v this much slower and faster
RAIL_MARGIN_V = 1e-9           # a command this close to a limit is on it
LINEAR_HOLD_S = 0.1            # the linearised step's hold after the ramp [s] (the paper steps' 0.1 s)
DERIVATIVE_STARTS_S = (0.5e-4, 1e-4, 3e-4)  # kd/kp the search tries on a set without derivative action [s]
MIN_DERIVATIVE_S = 1e-6        # kd/kp below this [s] is no derivative action: the search sets kd = 0


class TuningError(PiezoValveError, ValueError):
    """The tuner cannot tune this strategy on this model (with the reason)."""


@dataclass(frozen=True)
class TuningLimits:
    """The tuner's constraints (defaults: the module's named constants)."""

    max_overshoot_pct: float = ruled(OVERSHOOT_LIMIT_PCT, NON_NEGATIVE)
    min_gain_margin_db: float = ruled(MIN_GAIN_MARGIN_DB, NON_NEGATIVE)
    min_phase_margin_deg: float = ruled(MIN_PHASE_MARGIN_DEG, NON_NEGATIVE)
    max_noise_gain: float = ruled(MAX_NOISE_GAIN, NON_NEGATIVE)
    min_crossover_hz: float = ruled(MIN_CROSSOVER_HZ, NON_NEGATIVE)

    def problems(self) -> list[str]:
        out = field_problems(self)
        if not out and self.min_phase_margin_deg >= 90:
            out.append("min_phase_margin_deg must be < 90")
        if not out and self.max_noise_gain == 0:
            out.append("max_noise_gain must be > 0")
        return out


@dataclass(frozen=True)
class LoopMargins:
    """Worst case over the plant-gain range: gain margin [dB] (inf: the phase never reaches -180 deg), phase
    margin [deg], gain crossover [Hz] (the lowest of the range), noise gain [um/um], stable or not."""

    stable: bool
    gain_margin_db: float
    phase_margin_deg: float
    crossover_hz: float
    noise_gain: float

    def meets(self, limits: TuningLimits) -> bool:
        return (self.stable and self.gain_margin_db >= limits.min_gain_margin_db
                and self.phase_margin_deg >= limits.min_phase_margin_deg and self.noise_gain <= limits.max_noise_gain
                and self.crossover_hz >= limits.min_crossover_hz)

    def text(self) -> str:
        if not self.stable:
            return f"unstable (noise gain {self.noise_gain:.2f})"
        gm = "inf" if math.isinf(self.gain_margin_db) else f"{self.gain_margin_db:.1f}"
        return (f"gain margin {gm} dB, phase margin {self.phase_margin_deg:.1f} deg, crossover "
                f"{self.crossover_hz:.0f} Hz, noise gain {self.noise_gain:.2f}")


@dataclass(frozen=True)
class StepScore:
    """The paper's three steps on one valve: each step's metrics and the time the command spent on a command
    limit from the ramps on [s, all steps together]."""

    steps: tuple[StepMetrics, ...]
    rail_time_s: float
    complete: bool = True      # False: the run gave up after a step overshot too far (the rest not run)

    @property
    def settling_time_s(self) -> float:
        """Average settling time [s] (inf for a run given up)."""
        if not self.complete:
            return math.inf
        return float(np.mean([m.settling_time_s for m in self.steps]))

    @property
    def band_exit_s(self) -> float:
        """Average band exit time [s] (the settling time resolved below the sample period; inf for a run given
        up)."""
        if not self.complete:
            return math.inf
        return float(np.mean([m.band_exit_s for m in self.steps]))

    @property
    def overshoot_pct(self) -> float:
        """Average overshoot [%] (the paper's Table 1 column)."""
        return float(np.mean([m.overshoot_pct for m in self.steps]))

    @property
    def worst_overshoot_pct(self) -> float:
        return float(max(m.overshoot_pct for m in self.steps))


@dataclass(frozen=True)
class TuningResult:
    strategy: str
    gains: PIDGains
    margins: LoopMargins
    score: StepScore            # on the identified model (what the tuner optimised)
    limits: TuningLimits
    screened: int               # candidates whose margins were computed
    simulated: int              # candidates run through the steps
    derivative_filter_s: float = ControllerConfig.derivative_filter_s   # the D filter the gains were tuned with
    variant_scores: tuple[StepScore, ...] = ()   # on the model with G_v DYNAMICS_SCALES times faster

    @property
    def worst_settling_time_s(self) -> float:
        """The average settling time [s] on the model or a dynamics variant, whichever is longest (how much the
        speed hangs on the fitted G_v being exact)."""
        return max([self.score.settling_time_s] + [v.settling_time_s for v in self.variant_scores])

    def parameters(self) -> dict:
        """``valve_controller`` parameters selecting these gains (a Table 1 gain set cleared) and the D filter
        they were tuned with."""
        return {"strategy": self.strategy, "kp": float(self.gains.kp), "ki": float(self.gains.ki),
                "kd": float(self.gains.kd), "gain_set": "", "derivative_filter_s": float(self.derivative_filter_s)}

    def as_dict(self) -> dict:
        """The result as plain values (``valve_tune --json``): gains, margins (null for an infinite gain
        margin), the steps on the model and on the dynamics variants."""
        s, m = self.score, self.margins
        finite = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731
        return {"strategy": self.strategy, "kp": float(self.gains.kp), "ki": float(self.gains.ki),
                "kd": float(self.gains.kd), "derivative_filter_s": float(self.derivative_filter_s),
                "margins": {"stable": bool(m.stable), "gain_margin_db": finite(m.gain_margin_db),
                            "phase_margin_deg": finite(m.phase_margin_deg), "crossover_hz": finite(m.crossover_hz),
                            "noise_gain": finite(m.noise_gain)},
                "on_the_model": {"settling_time_s": finite(s.settling_time_s), "overshoot_pct": finite(s.overshoot_pct),
                                 "worst_overshoot_pct": finite(s.worst_overshoot_pct), "rail_time_s": finite(s.rail_time_s)},
                "worst_settling_time_s_with_G_v_off": finite(self.worst_settling_time_s),
                "limits": {k: float(getattr(self.limits, k)) for k in ("max_overshoot_pct", "min_gain_margin_db",
                                                                      "min_phase_margin_deg", "max_noise_gain",
                                                                      "min_crossover_hz")},
                "screened": int(self.screened), "simulated": int(self.simulated)}

    def summary(self) -> str:
        s = self.score
        return (f"{self.strategy}: kp {self.gains.kp:.4g}, ki {self.gains.ki:.4g} 1/s, kd {self.gains.kd:.3g} s; "
                f"on the model: settling {1e3 * s.settling_time_s:.2f} ms, overshoot {s.overshoot_pct:.2f} % "
                f"(worst {s.worst_overshoot_pct:.2f} %), {1e3 * s.rail_time_s:.1f} ms on a command limit; with G_v "
                f"{_spread()} slower or faster: settling up to {1e3 * self.worst_settling_time_s:.2f} ms; "
                f"{self.margins.text()}")


# ---------------------------------------------------------------------- the identified model as a valve
# ---------------------------------------------------------------------- the linearised loop
def _poly_mul(*polys: np.ndarray) -> np.ndarray:
    out = np.ones(1)
    for p in polys:
        out = np.convolve(out, p)
    return out


def _poly_add(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    n = max(p.size, q.size)
    return np.pad(p, (0, n - p.size)) + np.pad(q, (0, n - q.size))


def _pid_polynomials_of(gains: Sequence[PIDGains], dt: float, derivative_filter_s: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The controller's discrete PID (``ValveController.step``) for each gain set as (num (N, 3), den (3,)) in
    powers of z^-1: kp + ki dt / (1 - z^-1) + (alpha kd / dt) (1 - z^-1) / (1 - (1 - alpha) z^-1),
    alpha = dt / (T_f + dt); the denominator is the same for every set."""
    alpha = dt / (derivative_filter_s + dt)
    den = _poly_mul(np.array([1.0, -1.0]), np.array([1.0, -(1.0 - alpha)]))
    kp, ki, kd = (np.array([getattr(g, name) for g in gains], float)[:, None] for name in ("kp", "ki", "kd"))
    num = kp * den + (ki * dt) * np.array([1.0, -(1.0 - alpha), 0.0]) + (alpha * kd / dt) * np.array([1.0, -2.0, 1.0])
    return num, den


def _pid_polynomials(gains: PIDGains, dt: float, derivative_filter_s: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_pid_polynomials_of` for one gain set: (num, den) in powers of z^-1."""
    num, den = _pid_polynomials_of([gains], dt, derivative_filter_s)
    return num[0], den


@functools.lru_cache(maxsize=64)
def _discrete_plant(valve_model: ContinuousTF, dt: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """z^-1 G_v(z) at unit gain, (num, den) in powers of z^-1 (each G_v and period discretised once: the
    tuner asks for the same few thousands of times)."""
    g = valve_model.discretise(dt)
    return (0.0,) + tuple(float(x) for x in g.b), tuple(float(x) for x in g.a)     # one period of delay


def _plant_polynomials(model: CompensationModel, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """z^-1 G_v(z) at unit gain, (num, den) in powers of z^-1."""
    num, den = _discrete_plant(model.valve_model, float(dt))
    return np.array(num), np.array(den)


def _creep_response(model: CompensationModel, dt: float, zinv: np.ndarray) -> np.ndarray:
    """The creep's frequency response (1 - sum c) + sum c_i lag_i(z), each lag evaluated on its own (one
    rational function of all of them loses its precision near z = 1)."""
    out = np.full(zinv.shape, 1.0 - model.creep.gain_sum, complex)
    for tau, c in zip(model.creep.time_constants_s, model.creep.gains):
        if c:
            lag = first_order_lag(tau, dt)
            out += c * np.polyval(lag.b[::-1], zinv) / np.polyval(lag.a[::-1], zinv)
    return out


def plant_gain_range(strategy: str, model: CompensationModel, command_min_v: float, command_max_v: float
                     ) -> tuple[float, float]:
    """(lowest, highest) gain of the plant the PID sees [um/um]: 1 for ``pid_hc`` (it acts through the
    inverse); for the others the local slope of map(GPIM) over the nominal static gain k: one operator's
    weight on the flattest envelope just after a reversal, all weights on the steepest on a long sweep."""
    if REGISTRY[strategy].inverse == IN_LOOP_INVERSE:   # it acts through the inverse
        return 1.0, 1.0
    g = model.gpim
    v = np.linspace(command_min_v, command_max_v, 201)
    env_slopes = [np.full_like(v, g.a0)]
    if not g.symmetric:
        env_slopes.append(g.b0 + 2.0 * g.b2 * v)
    env_lo = float(min(s.min() for s in env_slopes))
    env_hi = float(max(s.max() for s in env_slopes))
    first = float(g.weights[0]) if g.thresholds[0] == 0 else 0.0
    lo_um, hi_um = g.output_range(command_min_v, command_max_v)
    map_slopes = model.output_map.slopes(np.linspace(lo_um, hi_um, 201))
    k = nominal_static_gain(g, command_min_v, command_max_v)
    low = max(first, 0.0) * env_lo * float(map_slopes.min()) / k
    high = float(np.sum(g.weights)) * env_hi * float(map_slopes.max()) / k
    return max(low, 1e-3 * high), high


def _rows_polyval(coefs: np.ndarray, x) -> np.ndarray:
    """np.polyval for each row of ``coefs`` (N, m; highest power first) at ``x``: Horner's scheme exactly as
    numpy runs it, N polynomials at once."""
    y = np.zeros((coefs.shape[0],) + np.shape(x), np.result_type(coefs, x))
    for j in range(coefs.shape[1]):
        y = y * x + coefs[:, j].reshape((-1,) + (1,) * np.ndim(x))
    return y


def _margins_rows(L: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(gain margin dB, phase margin deg, lowest crossover rad/s) of each row of loop responses L (N, len(w)),
    w ascending [rad/s]; inf where the magnitude (phase) never crosses 0 dB (-180 deg), nan crossover where
    the magnitude never crosses."""
    logmag = np.log(np.abs(L))
    phase = np.unwrap(np.angle(L), axis=1)
    phase -= 2 * np.pi * np.round((phase[:, :1] + np.pi / 2) / (2 * np.pi))  # the integrator: -90 deg at w[0]
    lo, hi = logmag[:, :-1], logmag[:, 1:]
    cross = (lo >= 0) & (hi < 0) | (lo < 0) & (hi >= 0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        f = lo / (lo - hi)
        ph = phase[:, :-1] + f * (phase[:, 1:] - phase[:, :-1])
        pm = np.where(cross, np.degrees(ph) + 180.0, np.inf).min(axis=1)
        wc = np.where(cross, w[:-1] * (w[1:] / w[:-1]) ** f, np.inf).min(axis=1)
        # phase crossings of -180 deg (and -540, ...)
        k = np.floor((phase + np.pi) / (2 * np.pi))
        pcross = np.diff(k, axis=1) != 0
        level = 2 * np.pi * np.maximum(k[:, :-1], k[:, 1:]) - np.pi
        fp = (phase[:, :-1] - level) / (phase[:, :-1] - phase[:, 1:])
        lm = lo + fp * (hi - lo)
        gm = np.where(pcross, -20.0 * lm / math.log(10.0), np.inf).min(axis=1)
    return gm, pm, np.where(np.isinf(wc), np.nan, wc)



class _LoopPlant:
    """The plant the PID of ``strategy`` sees (``z^-1 G_v(z)`` with the creep lags, over its gain range),
    evaluated once on the margin frequencies; :meth:`margins` then rates any number of gain sets."""

    def __init__(self, strategy: str, model: CompensationModel, dt: float, command_min_v: float,
                 command_max_v: float, derivative_filter_s: float, gain_range: Optional[tuple[float, float]] = None):
        if strategy not in TUNABLE_STRATEGIES:
            raise TuningError(f"{strategy} has no feedback loop; tunable: {', '.join(TUNABLE_STRATEGIES)}")
        lo, hi = gain_range or plant_gain_range(strategy, model, command_min_v, command_max_v)
        self.plant_gains = np.geomspace(lo, hi, GAIN_POINTS) if hi > lo else np.array([hi])
        self.dt, self.derivative_filter_s = dt, derivative_filter_s
        self.pnum, self.pden = _plant_polynomials(model, dt)
        self.w = np.geomspace(1e-3 * _slowest_pole(model), math.pi / dt, FREQUENCY_POINTS)
        self.zinv = np.exp(-1j * self.w * dt)
        self.p_resp = (np.polyval(self.pnum[::-1], self.zinv) / np.polyval(self.pden[::-1], self.zinv)
                       * _creep_response(model, dt, self.zinv))

    def margins(self, gains: Sequence[PIDGains]) -> list[LoopMargins]:
        """:class:`LoopMargins` of each gain set, worst case over the plant gains."""
        out: list[LoopMargins] = []
        for first in range(0, len(gains), MARGIN_BATCH):
            out += self._margins_batch(gains[first:first + MARGIN_BATCH])
        return out

    def _margins_batch(self, gains: Sequence[PIDGains]) -> list[LoopMargins]:
        cnum, cden = _pid_polynomials_of(gains, self.dt, self.derivative_filter_s)
        c_resp = _rows_polyval(cnum[:, ::-1], self.zinv) / np.polyval(cden[::-1], self.zinv)
        noise = np.abs(_rows_polyval(cnum[:, ::-1], -1.0) / np.polyval(cden[::-1], -1.0))
        # closed-loop poles of the loop without the creep lags (slow, a few % of the gain: in the margins)
        open_num = np.stack([np.convolve(row, self.pnum) for row in cnum])
        open_den = _poly_mul(cden, self.pden)
        size = max(open_num.shape[1], open_den.size)
        open_num = np.pad(open_num, ((0, 0), (0, size - open_num.shape[1])))
        open_den = np.pad(open_den, (0, size - open_den.size))
        stable = np.ones(len(gains), bool)
        gm = np.full(len(gains), np.inf)
        pm = np.full(len(gains), np.inf)
        wc = np.full(len(gains), np.nan)
        companion = np.zeros((len(gains), size - 1, size - 1))
        companion[:, 1:, :-1] = np.eye(size - 2)
        for g in self.plant_gains:
            char = open_den + g * open_num                      # char[:, 0] = 1: monic in z
            companion[:, 0, :] = -char[:, 1:] / char[:, :1]
            stable &= ~np.any(np.abs(np.linalg.eigvals(companion)) >= 1.0, axis=1)
            gm_g, pm_g, wc_g = _margins_rows(g * c_resp * self.p_resp, self.w)
            gm, pm, wc = np.minimum(gm, gm_g), np.minimum(pm, pm_g), np.fmin(wc, wc_g)
        return [LoopMargins(True, float(a), float(b), float(c) / (2 * math.pi), float(n)) if ok
                else LoopMargins(False, -math.inf, -math.inf, math.nan, float(n))
                for ok, a, b, c, n in zip(stable, gm, pm, wc, noise)]


def loop_margins(strategy: str, gains: PIDGains, model: CompensationModel, dt: float,
                 command_min_v: float = ControllerConfig.command_min_v,
                 command_max_v: float = ControllerConfig.command_max_v,
                 derivative_filter_s: float = ControllerConfig.derivative_filter_s,
                 gain_range: Optional[tuple[float, float]] = None) -> LoopMargins:
    """Margins of ``strategy`` with ``gains`` on ``model`` sampled every ``dt`` [s], worst case over the plant
    gain range (see :func:`plant_gain_range`)."""
    return _LoopPlant(strategy, model, dt, command_min_v, command_max_v, derivative_filter_s,
                      gain_range).margins([gains])[0]


def linear_step(strategy: str, gains: PIDGains, model: CompensationModel, dt: float,
                derivative_filter_s: float = ControllerConfig.derivative_filter_s, plant_gain: float = 1.0,
                hold_s: float = LINEAR_HOLD_S) -> StepMetrics:
    """The paper's step (2 ms ramp, unit amplitude) through the *linearised* loop of ``strategy``: the
    controller's discrete PID, the plant ``plant_gain z^-1 G_v(z)`` as in :func:`loop_margins`, and for
    ``ff_pid``/``ff_pid_g`` the feedforward path as the controller runs it (``G_v`` or, with the dynamic
    feedforward on, ``G_v W``; ``ff_pid_g``'s error against the reference shaped by ``G_v`` or ``F``).  The
    hysteresis inverse is taken as exact, creep and the command limits are left out: a cheap ranking of many
    gain sets (a few hundred per second), which the tuner then runs through :func:`step_score`.

    Returns the step's metrics (settling time [s], overshoot [%] of the unit step)."""
    ref, k0 = step_reference_m(dt, 0.0, 1.0, hold_before_s=dt, hold_after_s=hold_s)
    cnum, cden = _pid_polynomials(gains, dt, derivative_filter_s)
    pnum, pden = _plant_polynomials(model, dt)
    loop_num, loop_den = plant_gain * _poly_mul(cnum, pnum), _poly_mul(cden, pden)
    char = _poly_add(loop_den, loop_num)
    lfilter = scipy_signal().lfilter
    law = REGISTRY[strategy]
    if law.feedback and law.inverse == FEEDFORWARD_INVERSE:
        shaping, inverse = reference_filters(model, dt)
        u_ff = ref if inverse is None else lfilter(inverse.b, inverse.a, ref)
        y_ff = lfilter(pnum, pden, u_ff)                      # the feedforward through the plant
        demand = lfilter(shaping.b, shaping.a, ref) if law.shaped_reference else ref
        y = lfilter(loop_den, char, y_ff) + lfilter(loop_num, char, demand)
    else:
        y = lfilter(loop_num, char, ref)
    return step_metrics(y, k0, 0.0, 1.0, dt)    # ref and y in m: a 1 um step


def _slowest_pole(model: CompensationModel) -> float:
    """The slowest pole of G_v [rad/s]."""
    poles = np.roots(model.valve_model.den)
    return float(np.min(np.abs(poles)))


def _gains(kp: float, zero_rad_s: float, derivative_s: float) -> PIDGains:
    """PID gains from kp, the PI zero ki/kp [rad/s] and kd/kp [s]."""
    return PIDGains(float(kp), float(kp * zero_rad_s), float(kp * derivative_s))


def time_scaled(model: CompensationModel, factor: float) -> CompensationModel:
    """``model`` with G_v ``factor`` times faster: G(s / factor) (poles and zeros times ``factor``, same DC)."""
    def scaled(coefs):
        n = len(coefs) - 1
        return tuple(float(c) * factor ** -(n - i) for i, c in enumerate(coefs))
    num, den = scaled(model.valve_model.num), scaled(model.valve_model.den)
    return replace(model, valve_model=type(model.valve_model)(tuple(n / den[0] for n in num),
                                                              tuple(d / den[0] for d in den)))


# ---------------------------------------------------------------------- the steps
def step_score(config: ControllerConfig, model: CompensationModel, valve_factory: Callable[[], object],
               initial_voltage_v: float, steps=PAPER_STEPS_UM, give_up_above_pct: Optional[float] = None
               ) -> StepScore:
    """The paper's step tests (2 ms ramps, fresh valve each) with ``config`` on valves from ``valve_factory``
    (anything with ``step(v) -> m``).  ``give_up_above_pct``: stop after a step that overshoots more than this
    [%] (the tuner's limit: the set is out whatever the other steps do); the score says it is incomplete."""
    metrics, rail_periods = [], 0
    for i, (start_um, end_um) in enumerate(steps):
        valve = valve_factory()
        controller = ValveController(config, model)
        controller.reset(initial_voltage_v)
        ref, k0 = step_reference_m(config.dt, start_um, end_um)
        rec = run_closed_loop(valve, controller, ref, first_position_m=valve.step(initial_voltage_v))
        y = responses(valve, rec)
        metrics.append(step_metrics(y, k0, start_um, end_um, config.dt))
        v = rec.command_v[k0:]
        rail_periods += int(np.count_nonzero((v <= config.command_min_v + RAIL_MARGIN_V)
                                             | (v >= config.command_max_v - RAIL_MARGIN_V)))
        if give_up_above_pct is not None and metrics[-1].overshoot_pct > give_up_above_pct and i + 1 < len(steps):
            return StepScore(tuple(metrics), rail_periods * config.dt, complete=False)
    return StepScore(tuple(metrics), rail_periods * config.dt)


def dynamics_variants(plant: CompensationModel) -> list[CompensationModel]:
    """``plant`` with G_v ``DYNAMICS_SCALES`` times faster (the tuner's robustness check)."""
    return [time_scaled(plant, f) for f in DYNAMICS_SCALES]


def variant_scores(config: ControllerConfig, model: CompensationModel, variants: Sequence[CompensationModel],
                   initial_voltage_v: float, give_up_above_pct: Optional[float] = None) -> list[StepScore]:
    """The paper's steps with ``config`` (the controller on ``model``) on each of ``variants`` run as valves
    (:class:`ModelValve`), one :class:`StepScore` each.  ``give_up_above_pct``: as :func:`step_score`, and no
    further variant is run after one that overshoots more than this [%]."""
    out = []
    for p in variants:
        out.append(step_score(config, model, lambda: ModelValve(p, config.dt, initial_voltage_v), initial_voltage_v,
                              give_up_above_pct=give_up_above_pct))
        if give_up_above_pct is not None and out[-1].worst_overshoot_pct > give_up_above_pct:
            break
    return out


def robust_overshoot_pct(config: ControllerConfig, model: CompensationModel, variants: Sequence[CompensationModel],
                         initial_voltage_v: float, give_up_above_pct: Optional[float] = None) -> float:
    """The worst step overshoot [%] of :func:`variant_scores`: what the tuner holds to its overshoot limit
    besides the nominal run (with ``give_up_above_pct`` the result is then only known to exceed it)."""
    return max((s.worst_overshoot_pct for s in variant_scores(config, model, variants, initial_voltage_v,
                                                              give_up_above_pct)), default=0.0)


def _spread() -> str:
    """DYNAMICS_SCALES as text ("10 %")."""
    slower, faster = (round(abs(1.0 - f) * 100) for f in DYNAMICS_SCALES)
    return f"{slower:g} %" if slower == faster else f"{slower:g} % / {faster:g} %"


def outside_limits(margins: LoopMargins, robust_overshoot: float, limits: TuningLimits) -> Optional[str]:
    """Why a gain set with ``margins`` and worst step overshoot ``robust_overshoot`` [%] on the
    :func:`dynamics_variants` is outside the tuner's ``limits`` (None: it is within them)."""
    if not margins.meets(limits):
        return f"misses the margins ({margins.text()})"
    if robust_overshoot > limits.max_overshoot_pct:
        return f"overshoots {robust_overshoot:.2f} % with G_v {_spread()} slower or faster"
    return None


def _moves(g: PIDGains, step: float) -> list[PIDGains]:
    """The pattern search's trial sets around ``g`` in the loop's natural coordinates, each ``exp(+-step)``
    times: the overall gain (kp, ki, kd together: the crossover moves, the PI zero and derivative time stay),
    the PI zero ki/kp, the derivative time kd/kp (from none: ``DERIVATIVE_STARTS_S`` times kp)."""
    out = []
    for sign in (1.0, -1.0):
        f = math.exp(sign * step)
        out.append(PIDGains(g.kp * f, g.ki * f, g.kd * f))
        out.append(replace(g, ki=g.ki * f))
        if g.kd == 0.0:
            if sign > 0:
                out += [replace(g, kd=g.kp * td) for td in DERIVATIVE_STARTS_S]
        else:
            kd = g.kd * f
            out.append(replace(g, kd=0.0 if kd < MIN_DERIVATIVE_S * g.kp else kd))
    return out


def _pattern_search(start: PIDGains, better: Callable[[PIDGains, PIDGains], bool], rounds: int = REFINE_ROUNDS,
                    first_step: float = REFINE_START_STEP,
                    prepare: Callable[[list[PIDGains]], object] = lambda trials: None) -> PIDGains:
    """Compass search from ``start`` over :func:`_moves`: take any trial ``better`` than the present set, halve
    the step when none is, ``rounds`` times.  ``prepare`` sees each round's trials before they are judged (to
    compute what they share at once)."""
    best, step = start, first_step
    for _ in range(rounds):
        improved = True
        while improved:
            improved = False
            trials = _moves(best, step)
            prepare(trials)
            for trial in trials:
                if better(trial, best):
                    best, improved = trial, True
        step /= 2
    return best


def tune(strategy: str, model: CompensationModel, dt: float, limits: TuningLimits = TuningLimits(),
         config: Optional[ControllerConfig] = None, plant: Optional[CompensationModel] = None,
         starts: Optional[Sequence[PIDGains]] = None, log: Callable[[str], None] = lambda s: None) -> TuningResult:
    """PID gains for ``strategy`` with the controller running on ``model`` at control period ``dt`` [s] (see
    the module docstring).  The valve is ``plant`` (what identification found; default ``model`` itself, the
    controller inverting all of it); ``config`` gives the command range and derivative filter (default
    ControllerConfig's); ``starts``: gain sets tried besides the grid (default: Table 1's for the strategy).
    Raises TuningError when the strategy has no loop, the inputs are bad or no
    candidate meets ``limits``.  BLAS runs on one thread meanwhile (``core.blas``: the candidates' thousands of
    small discretisations would keep a second core spinning for nothing)."""
    tuner = _Tuner(strategy, model, dt, limits, config, plant, log)
    with one_blas_thread():
        return tuner.run(starts)


class _Tuner:
    """One tuning run: the checked inputs, the figures of every gain set tried (each computed once), and the
    stages of the module docstring as methods."""

    def __init__(self, strategy: str, model: CompensationModel, dt: float, limits: TuningLimits,
                 config: Optional[ControllerConfig], plant: Optional[CompensationModel], log: Callable[[str], None]):
        if strategy not in TUNABLE_STRATEGIES:
            raise TuningError(f"{strategy!r} has no feedback loop to tune; tunable: {', '.join(TUNABLE_STRATEGIES)}")
        problems = limits.problems()
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            problems.append(f"dt must be > 0, got {dt!r}")
        base = replace(config or ControllerConfig(), strategy=strategy, dt=float(dt) if not problems else CONTROL_PERIOD_S)
        plant = model if plant is None else plant
        problems += base.problems() + model.problems(base.command_min_v, base.command_max_v, base.dt)
        problems += ([f"plant: {p}" for p in plant.problems(base.command_min_v, base.command_max_v)]
                     if plant is not model else [])
        if problems:
            raise TuningError("; ".join(problems))
        self.strategy, self.model, self.plant, self.dt, self.limits, self.base, self.log = (
            strategy, model, plant, dt, limits, base, log)
        self.v0 = base.centre_voltage_v
        self.gain_range = plant_gain_range(strategy, plant, base.command_min_v, base.command_max_v)
        self.loop = _LoopPlant(strategy, plant, dt, base.command_min_v, base.command_max_v,
                               base.derivative_filter_s, self.gain_range)
        self.variants = dynamics_variants(plant)
        self.margins_cache: dict[PIDGains, LoopMargins] = {}
        self.scores: dict[PIDGains, StepScore] = {}
        self.on_variants: dict[PIDGains, list[StepScore]] = {}
        self.linear_cache: dict[PIDGains, tuple[float, float]] = {}
        log(f"tune {strategy}: plant gain {self.gain_range[0]:.3g}..{self.gain_range[1]:.3g}, period "
            f"{1e3 * dt:.3g} ms; limits: overshoot <= {limits.max_overshoot_pct:g} %, gain margin >= "
            f"{limits.min_gain_margin_db:g} dB, phase margin >= {limits.min_phase_margin_deg:g} deg, noise gain <= "
            f"{limits.max_noise_gain:g}, crossover >= {limits.min_crossover_hz:g} Hz")

    # ------------------------------------------------------------------ figures of one gain set (each once)
    def margins(self, g: PIDGains) -> LoopMargins:
        return self.margins_of([g])[0]

    def margins_of(self, gains: Sequence[PIDGains]) -> list[LoopMargins]:
        """The margins of each set, those not yet known computed together."""
        new = list(dict.fromkeys(g for g in gains if g not in self.margins_cache))
        self.margins_cache.update(zip(new, self.loop.margins(new)))
        return [self.margins_cache[g] for g in gains]

    def score(self, g: PIDGains) -> StepScore:
        """The paper's steps with the controller on the model and the plant as the valve."""
        if g not in self.scores:
            self.scores[g] = step_score(replace(self.base, gains=g), self.model,
                                        lambda: ModelValve(self.plant, self.dt, self.v0), self.v0,
                                        give_up_above_pct=self.limits.max_overshoot_pct)
        return self.scores[g]

    def variant_runs(self, g: PIDGains) -> list[StepScore]:
        if g not in self.on_variants:
            self.on_variants[g] = variant_scores(replace(self.base, gains=g), self.model, self.variants, self.v0,
                                                 self.limits.max_overshoot_pct)
        return self.on_variants[g]

    def linear(self, g: PIDGains) -> tuple[float, float]:
        """(settling time [s], worst overshoot [%] on the plant and the dynamics variants) on the linearised loop."""
        if g not in self.linear_cache:
            f = self.base.derivative_filter_s
            nominal = linear_step(self.strategy, g, self.plant, self.dt, f)
            worst = max([nominal.overshoot_pct] + [linear_step(self.strategy, g, p, self.dt, f).overshoot_pct
                                                   for p in self.variants])
            self.linear_cache[g] = (nominal.band_exit_s, worst)
        return self.linear_cache[g]

    # ------------------------------------------------------------------ orders and tests
    def key(self, g: PIDGains) -> tuple[float, float, float]:
        """What the tuner minimises: the average band exit time on the plant times (1 + OVERSHOOT_COST x its
        worst overshoot / the limit); then the time on a command limit and the overshoot."""
        nominal = self.score(g)
        factor = 1.0 + OVERSHOOT_COST * nominal.worst_overshoot_pct / max(self.limits.max_overshoot_pct, 1e-9)
        return nominal.band_exit_s * factor, nominal.rail_time_s, nominal.worst_overshoot_pct

    def feasible(self, g: PIDGains) -> bool:
        """The margins, then the nominal steps (a run given up overshot), then the dynamics variants."""
        limit = self.limits.max_overshoot_pct
        if not self.margins(g).meets(self.limits) or self.score(g).worst_overshoot_pct > limit:
            return False
        return all(s.worst_overshoot_pct <= limit for s in self.variant_runs(g))

    def better(self, g: PIDGains, than: Optional[PIDGains]) -> bool:
        """Feasible and better than ``than``; the dynamics variants are only run for a set that would win."""
        if not self.margins(g).meets(self.limits) or (than is not None and not self.key(g) < self.key(than)):
            return False
        return self.feasible(g)

    def linear_rank(self, g: PIDGains) -> tuple[bool, float, float]:
        return (self.linear(g)[1] > self.limits.max_overshoot_pct,) + self.linear(g)

    def linear_better(self, budget_pct: float) -> Callable[[PIDGains, PIDGains], bool]:
        return lambda g, than: (self.margins(g).meets(self.limits) and self.linear(g)[1] <= budget_pct
                                and self.linear(g) < self.linear(than))

    # ------------------------------------------------------------------ the stages
    def linear_candidates(self) -> tuple[list[PIDGains], list[PIDGains]]:
        """1. the grid screened on the margins; 2. the fastest sets refined on the linearised loop (cheap:
        settling time of the paper's step there, within shares of the overshoot limit on the plant and the
        dynamics variants).  Returns (candidates, fastest on the linearised loop first; the grid sets that
        pass the margins)."""
        pole = _slowest_pole(self.plant)
        grid = [_gains(kp, ratio * pole, td) for ratio in ZERO_GRID_RATIO for td in DERIVATIVE_GRID_S for kp in KP_GRID]
        passing = [g for g, m in zip(grid, self.margins_of(grid)) if m.meets(self.limits)]
        ranked = sorted(passing, key=self.linear_rank)
        refined = []
        for share in LINEAR_BUDGET_SHARES:
            budget = share * self.limits.max_overshoot_pct
            refined += [_pattern_search(g, self.linear_better(budget), prepare=self.margins_of)
                        for g in [g for g in ranked if self.linear(g)[1] <= budget][:LINEAR_STARTS]]
        candidates = list(dict.fromkeys(sorted(refined, key=self.linear_rank) + ranked))
        self.log(f"tune {self.strategy}: screened {len(grid)} gain sets on the margins, {len(passing)} pass; "
                 f"{len(refined)} refined on the linearised loop ({len(self.linear_cache)} linear runs); running the "
                 f"paper's steps on the identified model, fastest on the linearised loop first")
        return candidates, passing

    def within_limits(self, candidates: list[PIDGains], passing: list[PIDGains],
                      starts: Sequence[PIDGains]) -> list[PIDGains]:
        """3. the nominal steps (cheap: a set overshooting on a step is given up) for the VERIFIED_RUNS fastest on
        the linearised loop and the starts; then the dynamics variants, best key first, until REFINE_STARTS sets
        are within the limits (further down the linear ranking when none is)."""
        limits = self.limits
        pool = list(dict.fromkeys(candidates[:VERIFIED_RUNS] + list(starts)))
        within: list[PIDGains] = []
        for g in sorted(pool, key=lambda g: self.key(g) if self.margins(g).meets(limits) else (math.inf,) * 3):
            if self.feasible(g):
                within.append(g)
                if len(within) == REFINE_STARTS:
                    break
        for i, g in enumerate(candidates[VERIFIED_RUNS:] if not within else []):
            if self.feasible(g):
                within.append(g)
                break
            if (i + 1) % 20 == 0:
                self.log(f"tune {self.strategy}: {VERIFIED_RUNS + i + 1}/{len(candidates)} sets run, none within "
                         f"the limits")
        if not within:
            if not passing and not any(self.margins(g).meets(limits) for g in starts):
                raise TuningError(f"no PID gains for {self.strategy} meet the margins on this model ({limits})")
            raise TuningError(f"no PID gains for {self.strategy} that meet the margins keep the overshoot <= "
                              f"{limits.max_overshoot_pct:g} % on this model")
        return within

    def run(self, starts: Optional[Sequence[PIDGains]] = None) -> TuningResult:
        candidates, passing = self.linear_candidates()
        if starts is None:
            starts = [g for s, g in TABLE1_GAINS.values() if s == self.strategy]
        within = self.within_limits(candidates, passing, starts)
        self.log(f"tune {self.strategy}: {len(self.scores)} sets run on the identified model; refining the best "
                 f"within the limits (" + ", ".join(f"{1e3 * self.score(g).settling_time_s:.2f} ms" for g in within) + ")")
        # 4. the best of those refined within the limits on the real steps
        best = min((_pattern_search(g, self.better, prepare=self.margins_of) for g in within), key=self.key)
        result = TuningResult(self.strategy, best, self.margins(best), self.score(best), self.limits,
                              len(self.margins_cache), len(self.scores) + sum(len(v) for v in self.on_variants.values()),
                              self.base.derivative_filter_s, tuple(self.variant_runs(best)))
        self.log(f"tune {self.strategy}: {result.summary()}")
        return result
