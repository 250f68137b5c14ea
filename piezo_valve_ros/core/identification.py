"""Identification of the valve from measured records: GPIM fits and the extended model.

Two baseline fits of the GPIM (input V, output um):

* ``fit_paper_gpim`` -- the paper's 5-parameter nonlinear least squares (a0, a1, alpha, rho, tau;
  n fixed, offset projected out).  Over-parameterised: a0 trades against alpha/rho/tau and a1
  against the offset, so its Jacobian is badly conditioned (the condition number is reported).
* ``fit_linear_gpim`` -- fixed thresholds spread over the input range and weights found by
  linear least squares in the partial sums ``P_j = p_0 + ... + p_j`` with ``P_j >= eps``: exactly
  the invertibility condition of the analytic inverse, so the fitted model is always invertible.

The extended model adds effects of the catalogue (``creep``, ``dynamics``, ``asymmetry``, ``drift``,
``saturation``) as terms that are linear in their coefficients given the hysteresis output, so the
GPIM weights and every effect are fitted jointly by one bounded linear least-squares problem
(re-linearised a few times where a term depends on the hysteresis output).  Nothing here imports ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
from scipy import optimize

from .dynamics import first_order_lag
from .hysteresis import GPIM, GPIMParams, play_batch

__all__ = ["IdentificationError", "Record", "FitQuality", "ValveModel", "Effect", "EFFECTS", "effect",
           "fit_linear_gpim", "fit_paper_gpim", "fit_model", "analysis_record", "lag_bank", "quality",
           "PaperFit", "default_thresholds"]


class IdentificationError(ValueError):
    """Data that cannot be identified from (the message says why, in one line)."""


# --------------------------------------------------------------------------- records
@dataclass(frozen=True)
class Record:
    """A measured record: time [s], applied voltage [V], spool position [um]."""

    time_s: np.ndarray
    voltage_v: np.ndarray
    position_um: np.ndarray

    def __post_init__(self):
        t, v, y = (np.asarray(a, float).reshape(-1) for a in (self.time_s, self.voltage_v, self.position_um))
        if not (t.size == v.size == y.size):
            raise IdentificationError(f"record columns differ in length ({t.size}, {v.size}, {y.size})")
        object.__setattr__(self, "time_s", t)
        object.__setattr__(self, "voltage_v", v)
        object.__setattr__(self, "position_um", y)

    @classmethod
    def from_rows(cls, rows: np.ndarray) -> "Record":
        """From ``samples`` rows (time [s], voltage [V], position [m])."""
        rows = np.asarray(rows, float)
        return cls(rows[:, 0], rows[:, 1], rows[:, 2] * 1e6)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.time_s))) if len(self) > 1 else float("nan")

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0] + self.dt) if len(self) > 1 else 0.0

    @property
    def range_um(self) -> float:
        return float(np.ptp(self.position_um)) if len(self) else 0.0

    def slice(self, start: int, stop: Optional[int] = None) -> "Record":
        return Record(self.time_s[start:stop], self.voltage_v[start:stop], self.position_um[start:stop])

    def check(self, what: str = "record", min_samples: int = 200) -> "Record":
        """Raise IdentificationError unless the record can be fitted; returns it (time-ordered)."""
        if len(self) < min_samples:
            raise IdentificationError(f"{what} has {len(self)} samples; at least {min_samples} are needed")
        bad = ~(np.isfinite(self.time_s) & np.isfinite(self.voltage_v) & np.isfinite(self.position_um))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise IdentificationError(f"{what} has {int(bad.sum())} non-finite samples (first at row {k}, "
                                      f"t={self.time_s[k]!r})")
        if np.any(np.diff(self.time_s) <= 0):
            order = np.argsort(self.time_s, kind="stable")
            t = self.time_s[order]
            if np.any(np.diff(t) <= 0):
                raise IdentificationError(f"{what} has repeated sample times")
            return Record(t, self.voltage_v[order], self.position_um[order]).check(what, min_samples)
        v_span = float(np.ptp(self.voltage_v))
        v_scale = max(float(np.max(np.abs(self.voltage_v))), 1e-12)
        if v_span <= 1e-6 * v_scale or v_span == 0.0:
            raise IdentificationError(f"{what}: the voltage is constant ({self.voltage_v[0]:.6g} V): "
                                      "no excitation to fit a hysteresis model")
        reversals = np.count_nonzero(np.diff(np.sign(np.diff(self.voltage_v))[np.diff(self.voltage_v) != 0]))
        if reversals < 2:
            raise IdentificationError(f"{what}: the voltage reverses direction {reversals} time(s); a hysteresis "
                                      "fit needs at least one full cycle")
        if self.range_um <= 0:
            raise IdentificationError(f"{what}: the position is constant: nothing to fit")
        return self


def analysis_record(record: Record, max_rate_hz: float = 2000.0) -> Record:
    """Block means down to at most ``max_rate_hz`` (hysteresis is rate-independent; the effects' time
    constants are continuous-time, so they carry over to any rate)."""
    dt = record.dt
    k = max(int(math.floor(1.0 / (max_rate_hz * dt) + 1e-9)), 1)
    if k == 1:
        return record
    n = len(record) // k * k
    blocks = lambda a: a[:n].reshape(-1, k).mean(axis=1)  # noqa: E731
    return Record(blocks(record.time_s), blocks(record.voltage_v), blocks(record.position_um))


# --------------------------------------------------------------------------- helpers
def lag_bank(x: np.ndarray, time_constants_s: Sequence[float], dt: float) -> np.ndarray:
    """First-order lags 1/(tau s + 1) of ``x`` (ZOH-exact, started at rest at x[0]); shape (N, k)."""
    out = np.empty((x.size, len(time_constants_s)))
    for i, tau in enumerate(time_constants_s):
        lag = first_order_lag(tau, dt)
        lag.reset(float(x[0]))
        out[:, i] = lag.run(x)
    return out


def _bounded_lstsq(A: np.ndarray, y: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                   ridge: float = 1e-9) -> np.ndarray:
    """min ||A x - y|| subject to lower <= x <= upper, through a QR reduction (A is tall)."""
    scale = np.sqrt(np.mean(A * A, axis=0))
    scale[scale == 0] = 1.0
    M = np.column_stack((A / scale, y))
    R = np.linalg.qr(M, mode="r")
    m = A.shape[1]
    R11, r12 = R[:m, :m], R[:m, m]
    R11 = np.vstack((R11, math.sqrt(ridge * len(y)) * np.eye(m)))
    r12 = np.concatenate((r12, np.zeros(m)))
    lo, hi = lower * scale, upper * scale
    if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
        x = np.linalg.lstsq(R11, r12, rcond=None)[0]
    else:
        x0 = np.linalg.lstsq(R11, r12, rcond=None)[0]
        if np.all((x0 >= lo) & (x0 <= hi)):
            x = x0
        else:
            x = optimize.lsq_linear(R11, r12, bounds=(lo, hi), method="bvls", lsmr_tol="auto").x
    return x / scale


# --------------------------------------------------------------------------- quality
@dataclass(frozen=True)
class FitQuality:
    rms_um: float
    peak_um: float
    peak_pct: float

    def as_dict(self) -> dict:
        return {"rms_um": round(self.rms_um, 6), "peak_um": round(self.peak_um, 6),
                "peak_pct": round(self.peak_pct, 6)}


def quality(measured_um: np.ndarray, predicted_um: np.ndarray, range_um: float) -> FitQuality:
    e = np.asarray(measured_um) - np.asarray(predicted_um)
    peak = float(np.max(np.abs(e)))
    return FitQuality(float(np.sqrt(np.mean(e * e))), peak, 100.0 * peak / range_um if range_um > 0 else float("nan"))


# --------------------------------------------------------------------------- context of one evaluation
class _Context:
    """Everything the effect terms are built from, for one record and one hysteresis model."""

    def __init__(self, record: Record, gpim: GPIM, t0: float):
        self.record = record
        self.v = record.voltage_v
        self.t = record.time_s - t0
        self.dt = record.dt
        self.gpim = gpim
        self.H, _ = gpim.run(self.v)


# --------------------------------------------------------------------------- the catalogue
@dataclass(frozen=True)
class Effect:
    """One effect of the catalogue: the signature it looks for and the terms that model it.

    ``settings`` holds what the terms need beyond their coefficients (time constants, scales),
    fixed from the training record by :meth:`prepare`.
    """

    name: str
    signature: str
    settings: tuple = ()

    def prepare(self, train: Record, H_range: tuple[float, float]) -> list["Effect"]:
        """Candidate settings for this effect on ``train`` (more than one: the fit picks)."""
        dur = train.duration_s
        dt = train.dt
        lo, hi = H_range
        centre, half = 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-9)
        if self.name == "creep":
            taus = tuple(t for t in (0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0) if 3 * dt <= t <= dur / 2)
            return [Effect(self.name, self.signature, (taus,))] if taus else []
        if self.name == "dynamics":
            taus = tuple(t for t in (2e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2, 2e-2) if t >= dt / 2)
            return [Effect(self.name, self.signature, (taus,))] if taus else []
        if self.name == "asymmetry":  # plus the descending envelope, fitted by fit_model
            return [Effect(self.name, self.signature, (centre, half))]
        if self.name == "saturation":
            return [Effect(self.name, self.signature, (centre, half))]
        if self.name == "drift":
            out = [Effect(self.name, self.signature, ("linear", dur, centre, half))]
            out += [Effect(self.name, self.signature, ("exp", f * dur, centre, half)) for f in (0.1, 0.25, 0.5, 1.0)]
            return out
        raise KeyError(self.name)

    def columns(self, ctx: _Context) -> np.ndarray:
        H = ctx.H
        if self.name in ("creep", "dynamics"):
            (taus,) = self.settings
            return lag_bank(H, taus, ctx.dt) - H[:, None]
        if self.name == "asymmetry":
            centre, half = self.settings
            h = (H - centre) / half
            return (h * h)[:, None]
        if self.name == "saturation":
            centre, half = self.settings
            h = (H - centre) / half
            return np.column_stack((h ** 3, h ** 5))
        if self.name == "drift":
            kind, tau, centre, half = self.settings
            k = ctx.t / tau if kind == "linear" else 1.0 - np.exp(-ctx.t / tau)
            return np.column_stack((k, k * (H - centre) / half))
        raise KeyError(self.name)

    def describe(self, coefs: np.ndarray) -> dict:
        c = [float(x) for x in coefs]
        if self.name in ("creep", "dynamics"):
            return {"time_constants_s": list(self.settings[0]), "gains": c}
        if self.name == "asymmetry":
            return {"even_term_um": c[0], "centre_um": self.settings[0], "half_range_um": self.settings[1]}
        if self.name == "saturation":
            return {"cubic_um": c[0], "quintic_um": c[1], "centre_um": self.settings[0],
                    "half_range_um": self.settings[1]}
        kind, tau = self.settings[:2]
        return {"form": kind, "time_scale_s": tau, "offset_um": c[0], "gain_um": c[1]}


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("creep", "slow approach after steps and reversals: residual follows slow lags (0.03-30 s) of the model output"),
    Effect("dynamics", "lag after fast moves, loop changing with frequency: residual follows fast lags (0.2-20 ms) of the model output"),
    Effect("asymmetry", "ascending and descending branches differ: a separate descending envelope of the operators "
                        "(b0, b1) and an even term of the output"),
    Effect("drift", "slow change of offset or gain with time: residual trends with time since start"),
    Effect("saturation", "loop ends flattened: residual is an odd function of the output about its centre (cubic, quintic)"),
)}


def effect(name: str) -> Effect:
    if name not in EFFECTS:
        raise KeyError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
    return EFFECTS[name]


# --------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class ValveModel:
    """GPIM plus effect terms: ``y = H + sum_effects columns(H, v, t) @ coefs``  [um]."""

    gpim: GPIM
    terms: tuple[tuple[Effect, np.ndarray], ...] = ()
    t0: float = 0.0  # record time at which drift terms start [s]

    @property
    def effects(self) -> list[str]:
        return [e.name for e, _ in self.terms]

    @property
    def name(self) -> str:
        return "+".join(["gpim"] + self.effects)

    def predict(self, record: Record, t0: Optional[float] = None) -> np.ndarray:
        """Position [um] the model predicts for the record's voltages (operators virgin at v[0])."""
        ctx = _Context(record, self.gpim, self.t0 if t0 is None else t0)
        y = ctx.H.copy()
        for eff, coefs in self.terms:
            y += eff.columns(ctx) @ coefs
        return y

    def term(self, name: str) -> Optional[tuple[Effect, np.ndarray]]:
        for eff, coefs in self.terms:
            if eff.name == name:
                return eff, coefs
        return None

    def creep_compensation(self) -> Optional[tuple[list[float], list[float]]]:
        """(time constants [s], gains) of the creep term, for the controller's creep compensation."""
        t = self.term("creep")
        if t is None:
            return None
        eff, coefs = t
        return list(eff.settings[0]), [float(c) for c in coefs]

    def describe(self) -> dict:
        g = self.gpim
        out = {"model": self.name,
               "gpim": {"thresholds": [float(x) for x in g.thresholds], "weights": [float(x) for x in g.weights],
                        "a0": g.a0, "a1": g.a1, "offset_um": g.offset_um}}
        if not g.symmetric:
            out["gpim"].update({"b0": g.b0, "b1": g.b1})
        for eff, coefs in self.terms:
            out[eff.name] = eff.describe(coefs)
        return out


# --------------------------------------------------------------------------- fitting
def default_thresholds(voltage_v: np.ndarray, n: int = 20) -> np.ndarray:
    """n thresholds evenly over [0, half the input span) (an operator with a larger one never moves)."""
    span = float(np.ptp(voltage_v))
    return np.arange(n) * (0.5 * span / n)


def _design(record: Record, thresholds: np.ndarray, descending: Optional[tuple[float, float]] = None
            ) -> np.ndarray:
    """Partial-sum basis Z D (N, n) of the operator states Z (identity ascending envelope).

    y = Z p with p = D q (q = partial sums): column j of Z D is Z_j - Z_{j+1}, the last is Z_{n-1}.
    """
    shape = GPIM(thresholds, np.ones(thresholds.size), 1.0, 0.0, 0.0,
                 *(descending if descending is not None else (None, None)))
    v = record.voltage_v
    upper = shape.descending_envelope(v) if descending is not None else v
    Z, _ = play_batch(v, upper, thresholds, shape.virgin_state(float(v[0])))
    Z[:, :-1] -= Z[:, 1:]
    return Z


def _gpim_from_partial_sums(thresholds: np.ndarray, q: np.ndarray, offset: float,
                            descending: Optional[tuple[float, float]] = None) -> GPIM:
    p = np.diff(np.concatenate(([0.0], q)))
    b0, b1 = (float(descending[0]), float(descending[1])) if descending is not None else (None, None)
    return GPIM(thresholds, p, 1.0, 0.0, float(offset), b0, b1)


def _solve(train: Record, r: np.ndarray, descending, extra_cols: list[np.ndarray]):
    """One joint bounded LS: partial sums q >= eps, free offset and effect coefficients."""
    y = train.position_um
    n = r.size
    slope = max(float(np.ptp(y)) / max(float(np.ptp(train.voltage_v)), 1e-12), 1e-12)
    A = np.column_stack([_design(train, r, descending), np.ones(y.size)] + extra_cols)
    lo = np.concatenate((np.full(n, 1e-4 * slope), np.full(A.shape[1] - n, -np.inf)))
    x = _bounded_lstsq(A, y, lo, np.full(A.shape[1], np.inf))
    return x, A


def _fit_descending_envelope(train: Record, r: np.ndarray, extra_cols: list[np.ndarray]) -> tuple[float, float]:
    """Descending envelope (b0, b1) by variable projection: the weights are re-solved for every trial."""
    v_scale = max(float(np.ptp(train.voltage_v)), 1e-12)
    rec = analysis_record(train, 500.0)
    k = max(len(train) // len(rec), 1)
    cols = [c[: len(rec) * k].reshape(len(rec), k, -1).mean(axis=1) for c in extra_cols]

    def residual(b):
        x, A = _solve(rec, r, (b[0], b[1] * v_scale), cols)
        return A @ x - rec.position_um

    sol = optimize.least_squares(residual, [1.0, 0.0], bounds=([0.5, -0.5], [2.0, 0.5]), x_scale=[0.05, 0.05],
                                 diff_step=1e-4, max_nfev=60)
    return float(sol.x[0]), float(sol.x[1] * v_scale)


def fit_model(train: Record, effects: Sequence[Effect] = (), thresholds: Optional[np.ndarray] = None,
              n_operators: int = 20, iterations: int = 3, t0: Optional[float] = None) -> ValveModel:
    """Joint bounded linear least squares of GPIM weights (partial sums >= eps: invertible when symmetric)
    and the coefficients of ``effects`` (already prepared, see :meth:`Effect.prepare`).  With ``asymmetry``
    the descending envelope (b0, b1) is fitted too, by variable projection."""
    r = default_thresholds(train.voltage_v, n_operators) if thresholds is None else np.asarray(thresholds, float)
    t0 = float(train.time_s[0]) if t0 is None else t0
    n = r.size
    if r[0] != 0:
        raise ValueError("the first threshold must be 0")
    x, _ = _solve(train, r, None, [])
    gpim = _gpim_from_partial_sums(r, x[:n], x[n])
    if not effects:
        return ValveModel(gpim, (), t0)
    descending = None
    asymmetric = any(e.name == "asymmetry" for e in effects)
    for i in range(max(iterations, 1)):
        ctx = _Context(train, gpim, t0)
        cols = [eff.columns(ctx) for eff in effects]
        if asymmetric and i < 2:
            descending = _fit_descending_envelope(train, r, cols)
        x, _ = _solve(train, r, descending, cols)
        gpim = _gpim_from_partial_sums(r, x[:n], x[n], descending)
    # final pass: effect coefficients consistent with the final hysteresis output
    ctx = _Context(train, gpim, t0)
    cols = [eff.columns(ctx) for eff in effects]
    c = np.linalg.lstsq(np.column_stack(cols), train.position_um - ctx.H, rcond=None)[0]
    coefs = np.split(c, np.cumsum([k.shape[1] for k in cols])[:-1])
    return ValveModel(gpim, tuple(zip(effects, coefs)), t0)


def fit_linear_gpim(train: Record, n_operators: int = 20) -> ValveModel:
    """The better-conditioned baseline: fixed thresholds, invertible weights by bounded linear LS."""
    return fit_model(train, (), n_operators=n_operators)


@dataclass(frozen=True)
class PaperFit:
    params: GPIMParams
    condition_number: float
    evaluations: int

    @property
    def model(self) -> ValveModel:
        return ValveModel(self.params.model())


def fit_paper_gpim(train: Record, n: int = 15, max_rate_hz: float = 200.0, max_evaluations: int = 400) -> PaperFit:
    """The paper's 5-parameter NLS (a0, a1, alpha, rho, tau), offset projected out, on a record decimated to
    ``max_rate_hz`` (the hysteresis is rate-independent)."""
    rec = analysis_record(train, max_rate_hz)
    v, y = rec.voltage_v, rec.position_um
    span = float(np.ptp(v))
    v_min = float(np.min(v))
    # start: paper-like shape scaled to this input range
    alpha0 = 0.5 * span / n
    x0 = np.array([1.0, -v_min, alpha0, 1.0, 1.0 / (0.25 * span)])

    def model_of(x) -> Optional[GPIM]:
        a0, a1, alpha, rho, tau = x
        try:
            return GPIMParams(a0=a0, a1=a1, alpha=alpha, rho=rho, tau=tau, n=n, offset_um=0.0).model()
        except ValueError:
            return None

    def residual(x):
        m = model_of(x)
        if m is None:
            return np.full(y.size, 1e6)
        h, _ = m.run(v)
        e = y - h
        return e - e.mean()

    # rho from a linear fit at the start shape
    m0 = model_of(x0)
    h0, _ = m0.run(v)
    hc = h0 - h0.mean()
    x0[3] = max(float(np.dot(hc, y - y.mean()) / max(np.dot(hc, hc), 1e-12)), 1e-6)
    lower = [1e-6, -np.inf, 1e-6 * span, 1e-9, -10.0 / span]
    res = optimize.least_squares(residual, x0, bounds=(lower, np.inf), x_scale="jac", max_nfev=max_evaluations,
                                 diff_step=1e-6)
    a0, a1, alpha, rho, tau = res.x
    h, _ = GPIMParams(a0=a0, a1=a1, alpha=alpha, rho=rho, tau=tau, n=n, offset_um=0.0).model().run(v)
    offset = float(np.mean(y - h))
    sv = np.linalg.svd(res.jac, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    return PaperFit(GPIMParams(a0=float(a0), a1=float(a1), alpha=float(alpha), rho=float(rho), tau=float(tau), n=n,
                               offset_um=offset), cond, int(res.nfev))
