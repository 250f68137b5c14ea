"""A zoo of piezo valves and actuators written from the literature's equations, for judging the residual loop.

Nothing here comes from the package: no model, operator, signal, simulator or effect of ``piezo_valve_ros`` is
imported or copied (only numpy and scipy, and numba to compile the sample-by-sample loops), so a detector cannot
pass by recognising its own columns.  Each valve is simulated on a fine time grid (the "continuous" valve: a DAQ's
zero-order hold on the drive, the sensor sampled at the record's instants), with sensor noise and quantisation, and
recorded in separate sessions: each session starts after an excitation nobody recorded, and a re-zeroed sensor may
read another zero in each.

The equations:
* Prandtl-Ishlinskii (PI) hysteresis: play operators ``z_j = min(max(z_j, v - r_j), v + r_j)`` summed with weights
  (Krasnosel'skii & Pokrovskii; Kuhnen 2003);
* Bouc-Wen (Low & Guo 1995, the piezo form): ``y = d v - h``, ``dh/dt = alpha d dv/dt - beta |dv/dt| h - gamma dv/dt |h|``;
* Preisach: relays ``gamma_{alpha,beta}`` with a density over (alpha >= beta) that is not a PI one (a Gaussian in the
  interaction field (alpha + beta) / 2 and an exponential in the coercivity (alpha - beta) / 2; Mayergoyz);
* rate-dependent PI (Al Janaideh & Krejci 2013): thresholds ``r_j + beta |dv/dt|`` (additive) or
  ``r_j (1 + beta |dv/dt|)`` (multiplicative), the rate taken as it is;
* modified PI with rate-dependent slopes (Ang, Khosla & Riviere 2007): each weight ``p_j (1 + c |dv/dt|)``;
* generalized PI with different envelopes on the two branches (Al Janaideh, Rakheja & Su 2009): asymmetry;
* Hammerstein: rate-independent hysteresis followed by linear dynamics, a transport delay or an extra lag;
* backlash (a play) before the hysteresis (on the drive) or after it (on the spool);
* creep as the logarithmic law ``y(t) = y0 (1 + gamma log10(t / t0))`` after each change (Jung & Gweon 2000),
  superposed over the moves;
* drift: an offset that grows linearly with time (thermal).

``CASES`` lists every valve with what is right for it: the effect names the loop may name (``names``: any subset,
with ``need`` the ones it must name unless it says ``unexplained``), or nothing when the baseline can represent it
(input backlash: a play before a PI model is a PI model with every threshold larger; Bouc-Wen of this form has the
branch shape of a PI model).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np
from scipy import signal

FINE_RATE_HZ = 20000.0   # the "continuous" valve is simulated at this rate
TRAIN_MAIN_S = 20.0      # the training experiment's main segment (a decaying 0.2 Hz sine) lasts this long
NOISE_UM = 0.05
QUANTUM_UM = 0.005


# ---------------------------------------------------------------------------- signals (designed experiments)
def _ramp_join(parts: list[np.ndarray], n_ramp: int) -> np.ndarray:
    out = [parts[0]]
    for p in parts[1:]:
        a, b = float(out[-1][-1]), float(p[0])
        if a != b:
            out.append(a + (b - a) * np.arange(1, n_ramp) / n_ramp)
        out.append(p)
    return np.concatenate(out)


def training_drive(rate_hz: float, lo: float = 0.0, hi: float = 10.0, main_s: float = 20.0) -> np.ndarray:
    """A designed identification experiment over ``lo..hi`` [V] at ``rate_hz``: a decaying sine that wipes the
    state, step-and-hold levels, sines of rising frequency, a long decaying 0.2 Hz sine (nested minor loops),
    then steps and sines again at other levels and frequencies."""
    dt = 1.0 / rate_hz
    c, a = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def t(seconds):
        return np.arange(int(round(seconds * rate_hz))) * dt

    def sines(freqs, amp, seconds):
        segs = []
        for f in freqs:
            tt = t(seconds)
            segs.append(c + amp * a * np.minimum(tt / 0.25, 1.0) * np.sin(2 * np.pi * f * tt))
        return segs

    def holds(levels, seconds):
        return [np.full(t(seconds).size, c + x * a) for x in levels]
    sync = c + a * np.exp(-t(1.5) / 0.5) * np.sin(2 * np.pi * 4.0 * t(1.5))
    main = c + a * (1 - 0.035 * t(main_s)) * np.sin(2 * np.pi * 0.2 * t(main_s))
    fast = [f for f in (0.5, 2.0, 8.0, 20.0, 40.0) if f < 0.2 * rate_hz]
    fast2 = [f for f in (1.0, 4.0, 12.0, 30.0) if f < 0.2 * rate_hz]
    parts = ([sync] + holds((0.5, -0.5, 0.7), 1.5) + sines(fast, 0.8, 1.0) + [main] + holds((0.0, -0.7, 0.2), 1.5)
             + sines(fast2, 0.8, 1.0) + holds((0.0,), 0.5))
    return _ramp_join(parts, max(int(round(2e-3 * rate_hz)), 2))


def validation_drive(rate_hz: float, lo: float = 0.0, hi: float = 10.0, seconds: float = 24.0) -> np.ndarray:
    """A validation session unlike the training one: the paper's eq. 12 multisine scaled to the range, decaying and
    growing sines (nested minor loops), two holds, sines at other frequencies."""
    dt = 1.0 / rate_hz
    c, a = 0.5 * (lo + hi), 0.5 * (hi - lo)
    tt = np.arange(int(round(seconds * rate_hz))) * dt
    f = np.sin(2 * np.pi * 0.35 * (tt + 8)) + 2 * np.cos(2 * np.pi * 0.2 * (tt + 8) + np.pi / 2) \
        + 2 * np.sin(2 * np.pi * 0.3 * (tt + 8) + np.pi / 2)
    multisine = c + 0.9 * a * f / np.max(np.abs(f))
    t6 = np.arange(int(round(6.0 * rate_hz))) * dt
    decay = c + 0.85 * a * np.exp(-t6 / 2.5) * np.sin(2 * np.pi * 0.8 * t6)
    grow = c + 0.85 * a * (1 - np.exp(-t6 / 2.5)) * np.sin(2 * np.pi * 0.6 * t6)
    hold = np.full(int(round(2.0 * rate_hz)), c + 0.4 * a)
    hold2 = np.full(int(round(2.0 * rate_hz)), c - 0.3 * a)
    fast = [c + 0.7 * a * np.sin(2 * np.pi * f * np.arange(int(round(1.5 * rate_hz))) * dt)
            for f in (3.0, 10.0, 25.0) if f < 0.2 * rate_hz]
    return _ramp_join([multisine, hold, decay, grow, hold2] + fast + [np.full(int(round(0.5 * rate_hz)), c)],
                      max(int(round(2e-3 * rate_hz)), 2))


def unrecorded_excitation(rate_hz: float, rng: np.random.Generator, lo: float = 0.0, hi: float = 10.0) -> np.ndarray:
    """What the valve went through before a session was recorded: two excursions to random levels and a rest at a
    random voltage (the session starts there, in a state nobody recorded)."""
    c, a = 0.5 * (lo + hi), 0.5 * (hi - lo)
    levels = [c + a * rng.uniform(0.5, 0.95), c - a * rng.uniform(0.3, 0.9), c + a * rng.uniform(-0.3, 0.3)]
    parts, prev = [], c
    for x in levels:
        n = int(round(0.4 * rate_hz))
        parts.append(prev + (x - prev) * np.arange(1, n + 1) / n)
        parts.append(np.full(int(round(0.3 * rate_hz)), x))
        prev = x
    return np.concatenate(parts)


# ---------------------------------------------------------------------------- hysteresis models
def play_operators(v: np.ndarray, lower_r: np.ndarray, upper_r: Optional[np.ndarray] = None,
                   thresholds_t: Optional[np.ndarray] = None, lower_env: Optional[np.ndarray] = None,
                   upper_env: Optional[np.ndarray] = None) -> np.ndarray:
    """States (N, n) of play operators with thresholds ``lower_r`` (n,) (or per sample ``thresholds_t`` (N, n)),
    on envelopes ``lower_env``/``upper_env`` (default: the input itself), started relaxed at the first input."""
    v = np.asarray(v, float)
    lo_env = np.ascontiguousarray(v if lower_env is None else lower_env, dtype=float)
    hi_env = np.ascontiguousarray(v if upper_env is None else upper_env, dtype=float)
    r = np.asarray(lower_r, float)
    z = np.full(r.size, 0.5 * (lo_env[0] + hi_env[0]))
    out = np.empty((v.size, r.size))
    per_sample = thresholds_t is not None
    thresholds = np.ascontiguousarray(thresholds_t if per_sample else r[None, :], dtype=float)
    _loops().play(lo_env, hi_env, thresholds, per_sample, z, out)
    return out


@functools.cache
def _loops():
    """The sample-by-sample recursions below, compiled (numba, cached on disk): the same arithmetic, operation by
    operation, as numpy's ``maximum``/``minimum`` and Python's floats, so the records are the same to the bit."""
    import numba

    @numba.njit(cache=True)
    def play(lo_env, hi_env, thresholds, per_sample, z, out):
        for k in range(lo_env.size):
            row = k if per_sample else 0
            for j in range(z.size):
                r = thresholds[row, j]
                lo = lo_env[k] - r
                hi = hi_env[k] + r
                x = z[j] if z[j] >= lo else lo      # np.maximum(z, lo)
                x = x if x <= hi else hi            # np.minimum(x, hi)
                z[j] = x
                out[k, j] = x

    @numba.njit(cache=True)
    def bouc_wen(dv, h, d_alpha, beta, gamma, out):
        for k in range(dv.size):
            step = dv[k] / 4.0
            for _ in range(4):
                h += d_alpha * step - beta * abs(step) * h - gamma * step * abs(h)
            out[k] = h

    @numba.njit(cache=True)
    def relays(v, up, down, relay, out):
        for k in range(v.size):
            total = 0.0
            for i in range(relay.size):
                if v[k] >= up[i]:
                    relay[i] = 1.0
                if v[k] <= down[i]:
                    relay[i] = -1.0
                total += relay[i]
            out[k] = total
    return type("Loops", (), {"play": staticmethod(play), "bouc_wen": staticmethod(bouc_wen),
                              "relays": staticmethod(relays)})


@dataclass(frozen=True)
class PI:
    """A PI model: ``n`` thresholds ``r_j = j * spacing_v``, weights ``p0 exp(-decay r_j)`` [um/V], an offset."""
    n: int = 12
    spacing_v: float = 0.4
    p0: float = 5.5
    decay: float = 0.9
    offset_um: float = -95.0

    @property
    def thresholds(self) -> np.ndarray:
        return np.arange(self.n) * self.spacing_v

    @property
    def weights(self) -> np.ndarray:
        return self.p0 * np.exp(-self.decay * self.thresholds)

    def __call__(self, v: np.ndarray, dt: float) -> np.ndarray:
        return play_operators(v, self.thresholds) @ self.weights + self.offset_um


def rate(v: np.ndarray, dt: float) -> np.ndarray:
    """|dv/dt| [V/s] of the drive sampled every ``dt``."""
    return np.abs(np.gradient(v, dt))


def rate_smoothed(v: np.ndarray, dt: float, tau_s: float = 2e-3) -> np.ndarray:
    """|dv/dt| [V/s] through a first-order lag of ``tau_s`` (the drive's amplifier cannot follow a DAQ's step)."""
    a = math.exp(-dt / max(tau_s, dt))
    return signal.lfilter([1 - a], [1, -a], rate(v, dt))


def additive_rate_pi(pi: PI, beta_s: float) -> Callable:
    def model(v, dt):
        thresholds_t = pi.thresholds[None, :] + beta_s * rate_smoothed(v, dt)[:, None]
        return play_operators(v, pi.thresholds, thresholds_t=thresholds_t) @ pi.weights + pi.offset_um
    return model


def multiplicative_rate_pi(pi: PI, beta_s: float) -> Callable:
    def model(v, dt):
        thresholds_t = pi.thresholds[None, :] * (1.0 + beta_s * rate_smoothed(v, dt))[:, None]
        return play_operators(v, pi.thresholds, thresholds_t=thresholds_t) @ pi.weights + pi.offset_um
    return model


def rate_slopes_pi(pi: PI, c_s: float) -> Callable:
    """Ang et al.: the loading curve's slope (every weight) grows with the input rate."""
    def model(v, dt):
        z = play_operators(v, pi.thresholds)
        gain = 1.0 + c_s * rate_smoothed(v, dt, 0.05)
        centre = 0.5 * (np.max(v) + np.min(v))
        return (z - centre) @ pi.weights * gain + centre * pi.weights.sum() + pi.offset_um
    return model


def asymmetric_pi(pi: PI, shift_v: float, slope: float, curvature: float) -> Callable:
    """Generalized PI: the descending branch on its own envelope ``v + shift + slope (v - c) + curvature (v - c)^2``."""
    def model(v, dt):
        c = 5.0
        upper = v + shift_v + slope * (v - c) + curvature * (v - c) ** 2
        z = play_operators(v, pi.thresholds, lower_env=v, upper_env=np.maximum(upper, v))
        return z @ pi.weights + pi.offset_um
    return model


def bouc_wen(d_um_per_v: float = 14.0, alpha: float = 0.42, beta: float = 0.035, gamma: float = 0.004,
             offset_um: float = -70.0) -> Callable:
    """Low & Guo's piezo Bouc-Wen model, integrated over each move of the drive in 4 substeps."""
    def model(v, dt):
        v = np.asarray(v, float)
        h = np.empty(v.size)
        # dh = alpha d dv - beta |dv| h - gamma dv |h|, in 4 substeps for accuracy on steep moves
        _loops().bouc_wen(np.diff(v, prepend=v[0]), 0.0, alpha * d_um_per_v, beta, gamma, h)
        return (d_um_per_v * v - h) + offset_um
    return model


def preisach(relays: int = 4000, lo: float = -1.0, hi: float = 11.0, coercivity_v: float = 1.0,
             interaction_v: float = 3.2, scale_um: float = 150.0, offset_um: float = -75.0, seed: int = 5) -> Callable:
    """A Preisach model: ``relays`` relays at (alpha >= beta) drawn from the density exp(-(alpha - beta) / 2 /
    coercivity) * N((alpha + beta) / 2 - centre; interaction) over ``lo..hi`` [V] (so many that each switches a
    hundredth of the noise): a finite interaction width, not a PI one (whose density is uniform along the
    interaction axis)."""
    rng = np.random.default_rng(seed)
    half_width = rng.exponential(2.0 * coercivity_v, relays) / 2.0
    centre = rng.normal(0.5 * (lo + hi), interaction_v, relays)
    a, b = centre + half_width, centre - half_width
    weight = scale_um / relays / 2.0

    def model(v, dt):
        v = np.ascontiguousarray(v, dtype=float)
        relay = np.where(centre <= v[0], 1.0, -1.0)   # demagnetised about the first input
        out = np.empty(v.size)
        _loops().relays(v, a, b, relay, out)   # each relay up where v >= alpha, then down where v <= beta; summed
        return out * weight + offset_um
    return model


def backlash_before(pi: PI, play_v: float) -> Callable:
    def model(v, dt):
        return pi(play_operators(v, np.array([play_v]))[:, 0], dt)
    return model


# ---------------------------------------------------------------------------- linear dynamics, creep, drift
def second_order(f_hz: float, zeta: float) -> tuple[tuple, tuple]:
    w = 2 * np.pi * f_hz
    return (w * w,), (1.0, 2 * zeta * w, w * w)


def first_order(f_hz: float) -> tuple[tuple, tuple]:
    w = 2 * np.pi * f_hz
    return (w,), (1.0, w)


def cascade(*tfs) -> tuple[tuple, tuple]:
    num, den = (1.0,), (1.0,)
    for n, d in tfs:
        num, den = tuple(np.polymul(num, n)), tuple(np.polymul(den, d))
    return num, den


def log_creep(gamma: float, t0_s: float = 0.01, settle_s: float = 30.0) -> Callable:
    """Each move of the static output dH creeps on as dH * gamma * log10(1 + t / t0) (Jung & Gweon), capped at
    ``settle_s``; superposed over the moves."""
    def creep(y, dt):
        n = y.size
        tt = np.arange(n) * dt
        kernel = gamma * np.log10(1.0 + np.minimum(tt, settle_s) / t0_s)
        return signal.fftconvolve(np.diff(y, prepend=y[0]), kernel)[:n]
    return creep


def linear_drift(um_per_s: float) -> Callable:
    def drift(y, t_s):
        return y + um_per_s * t_s
    return drift


def output_backlash(play_um: float) -> Callable:
    def after(y, t_s):
        return play_operators(y, np.array([play_um]))[:, 0]
    return after


# ---------------------------------------------------------------------------- the valve and its sessions
@dataclass(frozen=True)
class ZooValve:
    """A valve: hysteresis (v, dt) -> um on the fine grid, optional creep on it, linear dynamics (num, den), a
    transport delay, optional changes after the dynamics (y, t) -> y, sensor noise; recorded at ``rate_hz`` over
    the drive range ``lo..hi`` [V], with a sensor zero of its own in each session (``zero_um``: one per session)."""

    hysteresis: Callable
    dynamics: tuple = second_order(160.0, 0.85)
    delay_s: float = 0.0
    creep: Optional[Callable] = None
    after: Optional[Callable] = None
    rate_hz: float = 2000.0
    lo: float = 0.0
    hi: float = 10.0
    noise_um: float = NOISE_UM
    zero_um: tuple[float, ...] = (0.0, 0.0)
    closed_loop: bool = False
    creep_gamma: float = 0.0     # the closed loop's creep: log_creep(creep_gamma) stepped block by block

    def simulate(self, drive: np.ndarray, t0_s: float) -> np.ndarray:
        """Position [um] at the record's instants for the record-rate ``drive`` [V] (held between samples: a
        rate-independent hysteresis changes only at the samples, so it runs at the record's rate, a rate-dependent
        one sees the held drive's rate), free of noise; ``t0_s`` the session's clock start."""
        k = int(round(FINE_RATE_HZ / self.rate_hz))
        dt = 1.0 / (self.rate_hz * k)
        static = np.repeat(self.hysteresis(np.asarray(drive, float), 1.0 / self.rate_hz), k)
        return self._after_static(static, dt, k, t0_s)

    def _after_static(self, static: np.ndarray, dt: float, k: int, t0_s: float) -> np.ndarray:
        """Creep, linear dynamics, delay and what follows them, on the fine grid; sampled at the record's instants."""
        y = static + (self.creep(static, dt) if self.creep is not None else 0.0)
        b, a, _ = signal.cont2discrete(self.dynamics, dt, method="zoh")
        b = np.atleast_1d(np.squeeze(b))
        y = signal.lfilter(b, a, y, zi=signal.lfilter_zi(b, a) * y[0])[0]
        shift = int(round(self.delay_s / dt))
        if shift:
            y = np.concatenate((np.full(shift, y[0]), y[:-shift]))
        # the sensor is read at the start of each record period, before that period's command acts (a DAQ's tick:
        # read, then write): row k pairs the command applied from t_k with the position at t_k
        y = y[::k]
        if self.after is not None:   # slow or static changes of the spool's position: at the sampled instants
            y = self.after(y, t0_s + (np.arange(y.size) + 1) / self.rate_hz)
        return y

    def session(self, drive: np.ndarray, seed: int, session: int = 0, t0_s: float = 0.0) -> np.ndarray:
        """(N, 3) rows time [s], voltage [V], position [um] of one recorded session of ``drive`` after an
        unrecorded excitation (seeded), with this session's sensor zero and noise."""
        rng = np.random.default_rng(seed)
        before = unrecorded_excitation(self.rate_hz, rng, self.lo, self.hi)
        y = self.simulate(np.concatenate((before, drive)), t0_s - before.size / self.rate_hz)[before.size:]
        y = y + self.zero_um[session % len(self.zero_um)] + self.noise_um * rng.standard_normal(y.size)
        y = QUANTUM_UM * np.round(y / QUANTUM_UM)
        t = t0_s + np.arange(drive.size) / self.rate_hz
        return np.column_stack((t, drive, y))


@dataclass(frozen=True)
class Case:
    """A zoo valve with what is right for it: the loop may name any of ``names``; it must name every one of ``need``
    unless it reports ``unexplained`` (an honest 'I cannot tell'); nothing named is right only where ``need`` is
    empty.  ``train_s`` sets the main training segment's length (records of other lengths: ``train_scale``)."""

    valve: ZooValve
    names: frozenset = frozenset()
    need: frozenset = frozenset()
    note: str = ""
    train_drive: Callable = training_drive        # (rate_hz, lo, hi, main_s) -> V
    validate_drive: Callable = validation_drive   # (rate_hz, lo, hi) -> V
    must_say_unexplained: bool = False            # structure no effect explains: right only with unexplained

    def records(self, seed: int, train_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(training session, validation session) rows for this seed; ``train_scale`` shortens the main training
        segment (another record length)."""
        v = self.valve
        train = self.train_drive(v.rate_hz, v.lo, v.hi, main_s=TRAIN_MAIN_S * train_scale)
        validate = self.validate_drive(v.rate_hz, v.lo, v.hi)
        if v.closed_loop:
            return (closed_loop_session(v, seed, 0, 45.0 * train_scale),
                    closed_loop_session(v, seed + 1000, 1, 30.0, t0_s=100.0))
        return (v.session(train, seed, 0), v.session(validate, seed + 1000, 1, t0_s=train.size / v.rate_hz + 60.0))

    def judged_right(self, names: list[str], unexplained: bool) -> bool:
        named = set(names)
        if self.must_say_unexplained and not unexplained:
            return False                       # what no effect explains, called noise
        if not named <= self.names:
            return False                       # a wrong name
        if self.need <= named:
            return True
        return unexplained                     # missing what is there: right only when it says it cannot tell


def closed_loop_session(valve: ZooValve, seed: int, session: int, seconds: float, t0_s: float = 0.0) -> np.ndarray:
    """A session of the valve under a slow PI position loop (50 Hz, gains on a static slope, no hysteresis
    compensation) that follows levels held for 2 s, then half-size levels with slow sines on top: the voltage is
    the loop's output.  The valve (a PI model with logarithmic creep and second-order dynamics) is stepped block by
    block: its play operators and filter keep their state, the creep sums the kernel over the moves so far."""
    rng = np.random.default_rng(seed)
    rate_hz, block = valve.rate_hz, max(int(round(0.02 * valve.rate_hz)), 1)
    k = int(round(FINE_RATE_HZ / rate_hz))
    dt = 1.0 / (rate_hz * k)
    n = int(round(seconds * rate_hz)) // block * block
    t = np.arange(n) / rate_hz
    stair = np.repeat(rng.uniform(-45.0, 45.0, int(seconds / 2.0) + 1), int(round(2.0 * rate_hz)))[:n]
    ref = np.where(t < 0.5 * seconds, stair, 0.5 * stair + 22.0 * np.sin(2 * np.pi * 0.13 * t))
    pi = valve.hysteresis
    z = np.full(pi.thresholds.size, 5.0)
    b, a, _ = signal.cont2discrete(valve.dynamics, dt, method="zoh")
    b = np.atleast_1d(np.squeeze(b))
    h0 = float(z @ pi.weights + pi.offset_um)
    zi = signal.lfilter_zi(b, a) * h0
    moves_t, moves_dh, h_prev = [], [], h0
    kp, ki, slope = 0.3, 60.0, 14.0
    integral, y_meas = 0.0, h0
    drive, y = np.empty(n), np.empty(n)
    creep = valve.creep_gamma
    for start in range(0, n, block):
        e = float(ref[start]) - (y_meas + valve.zero_um[session])
        integral += ki * e * block / rate_hz
        v = float(np.clip(5.0 + (kp * e + integral) / slope, valve.lo, valve.hi))
        z = np.minimum(np.maximum(z, v - pi.thresholds), v + pi.thresholds)
        h = float(z @ pi.weights + pi.offset_um)
        moves_t.append(t[start])
        moves_dh.append(h - h_prev)
        h_prev = h
        since = t[start:start + block, None] - np.asarray(moves_t)[None, :]   # the block's samples
        static = h + (creep * np.log10(1.0 + np.minimum(since, 30.0) / 0.01)) @ np.asarray(moves_dh)
        out, zi = signal.lfilter(b, a, np.repeat(static, k), zi=zi)          # on the fine grid
        drive[start:start + block] = v
        y[start:start + block] = out[::k]
        y_meas = float(y[start + block - 1])
    y = y + valve.zero_um[session] + valve.noise_um * rng.standard_normal(n)
    return np.column_stack((t0_s + t, drive, QUANTUM_UM * np.round(y / QUANTUM_UM)))


def slow_sine_drive(rate_hz: float, lo: float, hi: float, main_s: float = 20.0) -> np.ndarray:
    """A quasi-static hysteresis test as labs record it: 40 cycles of a 1 Hz sine over the range (``main_s``
    scales the number of cycles)."""
    c, a = 0.5 * (lo + hi), 0.5 * (hi - lo)
    t = np.arange(int(round(2.0 * main_s * rate_hz))) / rate_hz
    return c - 0.92 * a * np.cos(2 * np.pi * t)


def nested_loops_drive(rate_hz: float, lo: float, hi: float) -> np.ndarray:
    """Another session: decaying and growing 1 Hz sines (nested minor loops), two 5 s holds, and a stretch a
    feedforward compensator drove (a sine with a lead at each reversal)."""
    c, a = 0.5 * (lo + hi), 0.5 * (hi - lo)
    t8 = np.arange(int(round(8.0 * rate_hz))) / rate_hz
    decay = c + 0.9 * a * np.exp(-t8 / 3.0) * np.sin(2 * np.pi * t8)
    grow = c + 0.9 * a * (1.0 - np.exp(-t8 / 3.0)) * np.sin(2 * np.pi * t8)
    hold1, hold2 = np.full(int(round(5.0 * rate_hz)), c + 0.5 * a), np.full(int(round(5.0 * rate_hz)), c - 0.6 * a)
    t6 = np.arange(int(round(6.0 * rate_hz))) / rate_hz
    ff = c + 0.8 * a * np.sin(np.pi * t6) + 0.08 * a * np.tanh(5.0 * np.cos(np.pi * t6))
    return _ramp_join([decay, grow, hold1, ff, hold2, np.full(int(round(1.0 * rate_hz)), c)],
                      max(int(round(2e-3 * rate_hz)), 2))


def multisine(rate_hz: float, lo: float, hi: float, period_s: float, periods: int, top_hz: float,
              seed: int) -> np.ndarray:
    """A periodic multisine over ``lo..hi`` [V]: every harmonic of 1 / ``period_s`` up to ``top_hz`` with equal
    amplitudes and random phases (seeded), repeated ``periods`` times sample for sample (the period a whole number
    of samples)."""
    n = int(round(period_s * rate_hz))
    rng = np.random.default_rng(seed)
    lines = np.arange(1, int(top_hz * period_s) + 1)
    phases = rng.uniform(0.0, 2.0 * np.pi, lines.size)
    tt = np.arange(n) / rate_hz
    x = np.sin(2.0 * np.pi * np.outer(tt, lines) / period_s + phases).sum(axis=1)
    c, a = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return np.tile(c + 0.9 * a * x / np.max(np.abs(x)), periods)


def broadband_training(rate_hz: float, lo: float = 0.0, hi: float = 10.0, main_s: float = 20.0) -> np.ndarray:
    """Twelve periods of a 0.5 s multisine to 1 kHz (``main_s`` sets nothing: the periods are the experiment)."""
    return multisine(rate_hz, lo, hi, 0.5, 12, 1000.0, 11)


def broadband_validation(rate_hz: float, lo: float = 0.0, hi: float = 10.0) -> np.ndarray:
    """Eight periods of another 0.5 s multisine to 1 kHz."""
    return multisine(rate_hz, lo, hi, 0.5, 8, 1000.0, 12)


def unrecorded_input(amplitude_um: float, period_s: float, top_hz: float, seed: int) -> Callable:
    """What a second drive nobody recorded adds to the position: a periodic multisine of its own (the same period as
    the recorded drive's, so the position still repeats period for period), summed at the output."""
    rng = np.random.default_rng(seed)
    lines = np.arange(1, int(top_hz * period_s) + 1)
    phases = rng.uniform(0.0, 2.0 * np.pi, lines.size)
    peak = float(np.max(np.abs(np.sin(2.0 * np.pi * np.outer(np.arange(4096) / 4096.0 * period_s, lines) / period_s
                                      + phases).sum(axis=1))))

    def after(y, t_s):
        w = np.sin(2.0 * np.pi * np.outer(t_s - t_s[0], lines) / period_s + phases).sum(axis=1)
        return y + amplitude_um * w / peak
    return after


BASE = PI()
VALVE = ZooValve(BASE)
MICRO = PI(n=10, spacing_v=0.12, p0=4.0, decay=2.2, offset_um=-16.0)   # a 0..3.6 V micromanipulator, ~40 um

CASES: dict[str, Case] = {
    "nominal PI + second-order dynamics": Case(VALVE),
    "Bouc-Wen (Low & Guo), symmetric": Case(replace(VALVE, hysteresis=bouc_wen()),
                                             note="rate-independent, branches shaped as a PI model's"),
    "Preisach, Gaussian interaction density": Case(replace(VALVE, hysteresis=preisach()), frozenset({"saturation"}),
                                                   frozenset({"saturation"}),
                                                   "a finite interaction width flattens the loop's ends"),
    "rate-dependent PI, additive thresholds": Case(replace(VALVE, hysteresis=additive_rate_pi(BASE, 5e-4)),
                                                   frozenset({"dynamics"}), frozenset({"dynamics"})),
    "rate-dependent PI, multiplicative thresholds": Case(
        replace(VALVE, hysteresis=multiplicative_rate_pi(BASE, 5e-4)), frozenset({"dynamics"}), frozenset({"dynamics"})),
    "modified PI with rate-dependent slopes (Ang)": Case(replace(VALVE, hysteresis=rate_slopes_pi(BASE, 3e-4)),
                                                         frozenset({"dynamics"}), frozenset({"dynamics"})),
    "Hammerstein with a 0.7 ms transport delay": Case(replace(VALVE, delay_s=7e-4), frozenset({"dynamics"}),
                                                      frozenset({"dynamics"})),
    "Hammerstein with an extra 35 Hz lag": Case(replace(VALVE, dynamics=cascade(second_order(160.0, 0.85),
                                                                                first_order(35.0))),
                                                frozenset({"dynamics"}), frozenset({"dynamics"})),
    "backlash before the hysteresis (0.5 V)": Case(replace(VALVE, hysteresis=backlash_before(BASE, 0.5)),
                                                   frozenset({"backlash"}),
                                                   note="a play before a PI model is a PI model: nothing is missing"),
    "backlash after the hysteresis (0.6 um)": Case(replace(VALVE, after=output_backlash(0.6)), frozenset({"backlash"}),
                                                   frozenset({"backlash"})),
    "asymmetric envelopes (generalized PI)": Case(replace(VALVE, hysteresis=asymmetric_pi(BASE, 0.15, 0.08, 0.01)),
                                                  frozenset({"asymmetry"}), frozenset({"asymmetry"})),
    "asymmetric envelopes and a slow pole": Case(
        replace(VALVE, hysteresis=asymmetric_pi(BASE, 0.15, 0.08, 0.01),
                dynamics=cascade(second_order(160.0, 0.85), first_order(30.0))),
        frozenset({"asymmetry", "dynamics"}), frozenset({"asymmetry", "dynamics"})),
    "logarithmic creep (Jung & Gweon)": Case(replace(VALVE, creep=log_creep(0.012)), frozenset({"creep"}),
                                             frozenset({"creep"})),
    "thermal drift, 0.05 um/s": Case(replace(VALVE, after=linear_drift(0.05)), frozenset({"drift"}),
                                     frozenset({"drift"})),
    "200 Hz micromanipulator, two sessions, re-zeroed sensor, 10 ms delay": Case(
        ZooValve(MICRO, dynamics=second_order(60.0, 0.9), delay_s=0.01, rate_hz=200.0, lo=0.0, hi=3.6,
                 noise_um=0.07, zero_um=(0.0, 1.2)),
        frozenset({"dynamics"}), frozenset({"dynamics"}), "the delay is two samples",
        slow_sine_drive, nested_loops_drive),
    "creeping valve in closed loop": Case(replace(VALVE, closed_loop=True, creep_gamma=0.012),
                                          frozenset({"creep"}), frozenset({"creep"})),
    "6.4 kHz broadband periodic drive, a second drive nobody recorded": Case(
        ZooValve(BASE, dynamics=second_order(1200.0, 0.5), rate_hz=6400.0, after=unrecorded_input(12.0, 0.5, 300.0, 13)),
        note="a second periodic drive summed at the output: no catalogue effect explains it, and the record's periods "
             "repeat to its sensor noise", train_drive=broadband_training, validate_drive=broadband_validation,
        must_say_unexplained=True),
}
