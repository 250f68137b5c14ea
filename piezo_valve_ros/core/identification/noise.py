"""The sensor's noise floor, estimated only from what the input cannot explain.

Three kinds of evidence, each at the record's own rate:

* **holds**: stretches where the drive stands still (after the valve's fast settling): the position there moves
  only smoothly (creep, drift), so its scatter about a local quadratic is the sensor's;
* **repeated periods**: a drive that repeats sample for sample (a periodic excitation): the position of one period
  less the next is the sensor's noise twice (its slow part, a drift between periods, taken off per period);
* **an input-free band**: frequencies where the drive has no power the output could echo (the drive's spectrum
  times the valve's static gain is below ``BAND_INPUT_SHARE`` of the output's): the output's power there is
  the noise's (white, so its level there spans the whole band);
* where none of these exists, **the band beyond the valve's response**: the same with the drive's spectrum
  passed through the valve's fitted G (a closed loop feeds the sensor's noise back into the drive at every
  frequency, where the valve cannot follow it): weaker, as it relies on the fit, and named so.

A record that offers none of these has no evidence for its noise: the floor is then unknown (``NoiseFloor.known``
False) and a residual is never called noise.  Nothing here imports ROS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from .records import Record

__all__ = ["NoiseFloor", "NoiseEvidence", "estimate_noise_floor", "hold_noise", "period_noise", "band_noise",
           "beyond_response_noise",
           "HOLD_MIN_S", "HOLD_SETTLE_S", "PERIOD_TOLERANCE", "BAND_INPUT_SHARE", "SOURCES"]

SOURCES = ("holds", "repeated periods", "input-free band", "band beyond the valve's response")   # the kinds of evidence
HOLD_MIN_S = 0.1            # a hold counts from this long ...
HOLD_MIN_SAMPLES = 24       # ... and this many samples after its settling
HOLD_SETTLE_S = 0.05        # the first this long of a hold (or its first fifth, the longer) is the valve settling
HOLD_WINDOW_SAMPLES = 24    # the local quadratic spans this many samples (or 20 ms, the more)
HOLD_WINDOW_S = 0.02
HOLD_TOLERANCE = 1e-6       # the drive stands still: it moves less than this share of its span per sample
PERIOD_TOLERANCE = 1e-6     # a period repeats: the drive one period on differs by less than this share of its span
PERIOD_MIN_REPEATS = 3      # ... over at least this many periods in a row
PERIOD_MIN_MOTION = 0.1     # ... over which the drive moves by at least this share of its span
PERIOD_MIN_SAMPLES = 8      # the shortest period looked for
PERIOD_LAG_REACH = 25       # ... within this many samples of an autocorrelation peak (1 % of its lag at most)
PERIOD_SEARCH_SAMPLES = 1 << 20   # the drive's period is looked for on at most its first this many samples
BAND_INPUT_SHARE = 0.01     # the drive echoes less than this share of the output's power in a band bin
BAND_MIN_SHARE = 0.2        # ... over at least this share of the bins up to the Nyquist rate
BAND_SEGMENT = 1024         # Welch segments of this many samples (fewer on a short record)
MAD_TO_SIGMA = 1.4826       # the median absolute deviation of a normal variable times this is its standard deviation


@dataclass(frozen=True)
class NoiseEvidence:
    """One estimate of the sensor's noise: its RMS [um] (None: the record offers no such evidence), the kind of
    evidence (one of ``SOURCES``) and what it was taken from, in words."""

    source: str
    rms_um: Optional[float]
    detail: str
    samples: int = 0

    def as_dict(self) -> dict:
        return {"rms_um": None if self.rms_um is None else round(self.rms_um, 6), "detail": self.detail,
                "samples": self.samples}


@dataclass(frozen=True)
class NoiseFloor:
    """The sensor's noise floor [um RMS at the record's rate] and its evidence: ``source`` names the evidence it was
    taken from ("none" where the record offers none; ``rms_um`` is then None and no residual may be called noise)."""

    rms_um: Optional[float]
    source: str
    detail: str
    evidence: tuple[NoiseEvidence, ...] = field(default_factory=tuple)

    @property
    def known(self) -> bool:
        return self.rms_um is not None

    def describe(self) -> str:
        """One phrase: the floor and where it came from."""
        if not self.known:
            return "no evidence for the sensor noise (no holds, no repeated periods, no band free of the drive)"
        return f"{self.rms_um:.4f} um from {self.source} ({self.detail})"

    def as_dict(self) -> dict:
        return {"rms_um": None if self.rms_um is None else round(self.rms_um, 6), "source": self.source,
                "detail": self.detail, "evidence": {e.source: e.as_dict() for e in self.evidence}}


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of True in ``mask``."""
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _about_polynomials(blocks: np.ndarray, degree: int) -> tuple[float, int]:
    """(sum of squared residuals, degrees of freedom) of each row of ``blocks`` (m, w) about its own least-squares
    polynomial of ``degree`` in time (one projection for all rows)."""
    m, w = blocks.shape
    if m == 0 or w <= degree + 1:
        return 0.0, 0
    basis = np.vander(np.linspace(-1.0, 1.0, w), degree + 1)
    q, _ = np.linalg.qr(basis)
    r = blocks - (blocks @ q) @ q.T
    return float(np.einsum("ij,ij->", r, r)), m * (w - degree - 1)


def _local_quadratic_residuals(y: np.ndarray, window: int) -> tuple[float, int]:
    """(sum of squared residuals, degrees of freedom) of ``y`` about a quadratic fitted in each of its windows of
    ``window`` samples (a trailing partial window of at least half as many counts too)."""
    m = y.size // window
    ss, dof = _about_polynomials(y[:m * window].reshape(m, window), 2)
    tail = y[m * window:]
    if tail.size >= max(window // 2, 6):
        s, d = _about_polynomials(tail[None, :], 2)
        ss, dof = ss + s, dof + d
    return ss, dof


def hold_noise(records: Sequence[Record]) -> NoiseEvidence:
    """The noise from the holds of ``records``: the scatter of the position about a local quadratic (windows of
    ``HOLD_WINDOW_S``) where the drive stands still, after each hold's settling."""
    ss, dof, holds, seconds = 0.0, 0, 0, 0.0
    for record in records:
        v, y, dt = record.voltage_v, record.position_um, record.dt
        span = float(np.ptp(v))
        if len(record) < 3 or not span > 0:
            continue
        still = np.abs(np.diff(v)) <= HOLD_TOLERANCE * span
        window = max(HOLD_WINDOW_SAMPLES, int(round(HOLD_WINDOW_S / dt)))
        for a, b in _runs(still):
            first, last = a + 1, b + 1          # samples whose drive equals the one before: the hold's
            length = last - first
            if length * dt < HOLD_MIN_S:
                continue
            settle = max(int(math.ceil(HOLD_SETTLE_S / dt)), length // 5)
            part = y[first + settle:last]
            if part.size < HOLD_MIN_SAMPLES:
                continue
            s, d = _local_quadratic_residuals(part, window)
            if d > 0:
                ss, dof, holds, seconds = ss + s, dof + d, holds + 1, seconds + part.size * dt
    if dof == 0:
        return NoiseEvidence("holds", None, "no hold of the drive long enough to show the sensor alone")
    return NoiseEvidence("holds", math.sqrt(ss / dof),
                         f"{holds} hold{'s' if holds != 1 else ''} of the drive, {seconds:.3g} s in all", dof)


def _period(v: np.ndarray) -> Optional[int]:
    """The shortest period [samples] over which ``v`` repeats sample for sample (within ``PERIOD_TOLERANCE`` of its
    span) for at least ``PERIOD_MIN_REPEATS`` periods in a row somewhere; None when it has none."""
    v = v[:PERIOD_SEARCH_SAMPLES]
    span = float(np.ptp(v))
    n = v.size
    if not span > 0 or n < PERIOD_MIN_REPEATS * PERIOD_MIN_SAMPLES:
        return None
    x = v - v.mean()
    size = 1 << int(math.ceil(math.log2(2 * n)))
    spectrum = np.fft.rfft(x, size)
    acf = np.fft.irfft(spectrum * np.conj(spectrum), size)[:n // PERIOD_MIN_REPEATS + 1]
    if not acf[0] > 0:
        return None
    lags = np.arange(acf.size)
    acf = acf / acf[0] * n / (n - lags)   # unbiased: each lag over the samples it overlaps
    # candidate lags: local maxima of the autocorrelation, the strongest first
    peaks = np.flatnonzero((acf[1:-1] > acf[:-2]) & (acf[1:-1] >= acf[2:]) & (acf[1:-1] > 0.0)) + 1
    peaks = peaks[lags[peaks] >= PERIOD_MIN_SAMPLES]
    tolerance = PERIOD_TOLERANCE * span
    for lag in sorted(peaks[np.argsort(-acf[peaks])][:12].tolist()):
        reach = min(PERIOD_LAG_REACH, max(1, lag // 100))   # a peak of a partly periodic drive sits near its period
        for p in sorted(range(lag - reach, lag + reach + 1), key=lambda q: abs(q - lag)):
            if p >= PERIOD_MIN_SAMPLES and _repeating_runs(v, p, span):
                return p
    return None


def _repeating_runs(v: np.ndarray, p: int, span: Optional[float] = None) -> list[tuple[int, int]]:
    """Runs (a, b) of rows k with v[k + p] = v[k] (within ``PERIOD_TOLERANCE`` of the span) at least
    ``PERIOD_MIN_REPEATS - 1`` periods long over which the drive moves by ``PERIOD_MIN_MOTION`` of its span (a still
    drive repeats any period: that is a hold).  ``span``: ``v``'s (computed when not given)."""
    span = float(np.ptp(v)) if span is None else span
    need = (PERIOD_MIN_REPEATS - 1) * p
    stride = max(1, need // 4)
    # first every stride-th row: a run of ``need`` rows holds at least 4 of them in a row, so where no 3 in a row
    # repeat there is none (one pass over n / stride rows rejects a lag that is no period: most of those tried)
    coarse = np.abs(v[p::stride] - v[:v.size - p:stride]) <= PERIOD_TOLERANCE * span
    if stride > 1 and not any(b - a >= 3 for a, b in _runs(coarse)):
        return []
    same = np.abs(v[p:] - v[:-p]) <= PERIOD_TOLERANCE * span
    return [(a, b) for a, b in _runs(same)
            if b - a >= (PERIOD_MIN_REPEATS - 1) * p and float(np.ptp(v[a:b])) >= PERIOD_MIN_MOTION * span]


def period_noise(records: Sequence[Record]) -> NoiseEvidence:
    """The noise from repeated periods of the drive: one period's position less the next one's, where the drive
    repeats, each period pair's slow part (a line over the period) taken off, divided by sqrt(2).  The first period
    of a repeating stretch is left out (a first cycle differs from the later ones: the valve's own memory)."""
    ss, dof, pairs, found = 0.0, 0, 0, []
    for record in records:
        v, y = record.voltage_v, record.position_um
        p = _period(v)
        if p is None:
            continue
        found.append(p * record.dt)
        for a, b in _repeating_runs(v, p):
            # rows k in [a, b) repeat at k + p: whole pairs of periods from the stretch's second period on
            whole = (b - a - p) // p
            if whole < 1:
                continue
            first = y[a + p:a + p + whole * p].reshape(whole, p)
            second = y[a + 2 * p:a + 2 * p + whole * p].reshape(whole, p)
            s, d = _about_polynomials(second - first, 1)
            ss, dof, pairs = ss + s / 2.0, dof + d, pairs + whole
    if not found:
        return NoiseEvidence("repeated periods", None, "the drive does not repeat a period sample for sample")
    if dof == 0:
        return NoiseEvidence("repeated periods", None, f"the drive repeats every {found[0]:.4g} s, but too few "
                                                       f"times in a row to compare a period with the next")
    return NoiseEvidence("repeated periods", math.sqrt(ss / dof),
                         f"{pairs} pair{'s' if pairs != 1 else ''} of {found[0]:.4g} s periods of a drive that "
                         f"repeats sample for sample", dof)


def band_noise(records: Sequence[Record], response: Optional[Callable[[np.ndarray], np.ndarray]] = None,
               source: str = "input-free band") -> NoiseEvidence:
    """The noise from the band where the drive has no power the output could echo: Welch spectra of drive and
    output; a bin belongs to the band where the drive's power times the valve's static gain squared (the output's
    least-squares slope on the drive) is below ``BAND_INPUT_SHARE`` of the output's; the output's median power
    density there, over the whole band up to the Nyquist rate, is the noise's variance.  ``response``: the valve's
    power gain |G(f)|^2 at frequencies f [Hz] (unity at DC), which the echo is multiplied by (a band beyond the
    valve's own response: a closed loop feeds the sensor's noise back into the drive at every frequency, where
    the valve cannot follow it)."""
    levels, weights, shares = [], [], []
    for record in records:
        n = len(record)
        if n < 64:
            continue
        v, y = record.voltage_v, record.position_um
        vc = v - v.mean()
        gain = float(vc @ (y - y.mean()) / max(vc @ vc, 1e-300))
        segment = min(BAND_SEGMENT, 1 << int(math.floor(math.log2(n // 4))))
        fs = record.rate_hz
        f, s_v = welch_density(v, fs, segment)
        _, s_y = welch_density(y, fs, segment)
        f, s_v, s_y = f[1:], s_v[1:], s_y[1:]   # (the mean's bin)
        echo = gain * gain * s_v * (1.0 if response is None else response(f))
        free = echo < BAND_INPUT_SHARE * s_y
        share = float(np.mean(free))
        shares.append(share)
        if share < BAND_MIN_SHARE:
            continue
        levels.append(float(np.median(s_y[free])) * 0.5 * fs)
        weights.append(n)
    beyond = "" if response is None else " through the valve's fitted G"
    if not levels:
        best = max(shares, default=0.0)
        return NoiseEvidence(source, None,
                             f"the drive has power the output could echo{beyond} over {100 * (1 - best):.0f} % of the "
                             f"band (at most {100 * (1 - BAND_MIN_SHARE):.0f} % allowed)")
    variance = float(np.average(levels, weights=weights))
    return NoiseEvidence(source, math.sqrt(variance),
                         f"the output's power where the drive has none it could echo{beyond} "
                         f"({100 * min(shares):.0f} % of the band or more), taken as white over the whole band",
                         int(sum(weights)))


def welch_density(x: np.ndarray, fs_hz: float, segment: int) -> tuple[np.ndarray, np.ndarray]:
    """(f [Hz], one-sided power spectral density [unit^2/Hz]) of ``x`` by Welch's method: Hann-windowed segments of
    ``segment`` samples overlapping by half, each less its least-squares line, averaged (``scipy.signal.welch(x, fs,
    nperseg=segment, detrend="linear")``, equal to rounding, tested; written out because scipy detrends segment by
    segment, a thousand least-squares solves for a 10 kHz record, where one projection serves them all)."""
    from numpy.lib.stride_tricks import sliding_window_view
    from ..model.dynamics import scipy_signal

    frames = sliding_window_view(np.asarray(x, float), segment)[::segment - segment // 2]
    line = np.vstack((np.ones(segment), np.arange(segment, dtype=float)))   # (2, segment)
    frames = frames - (frames @ np.linalg.pinv(line)) @ line
    window = scipy_signal().get_window("hann", segment)
    spectrum = np.fft.rfft(frames * window, axis=1)
    density = (spectrum.real ** 2 + spectrum.imag ** 2).mean(axis=0) / (fs_hz * float(window @ window))
    density[1:-1 if segment % 2 == 0 else None] *= 2.0   # one-sided: every bin but DC (and Nyquist) twice
    return np.fft.rfftfreq(segment, 1.0 / fs_hz), density


def beyond_response_noise(records: Sequence[Record], response: Callable[[np.ndarray], np.ndarray]) -> NoiseEvidence:
    """:func:`band_noise` with the valve's fitted response (``response``: |G(f)|^2): the band beyond what the valve
    follows, where whatever power the drive has there (a closed loop's fed-back noise) moves the output by less than
    BAND_INPUT_SHARE of what is measured.  Weaker evidence than the others (it relies on the fitted G): taken only
    where they offer none."""
    return band_noise(records, response, "band beyond the valve's response")


def estimate_noise_floor(records: Sequence[Record],
                         response: Optional[Callable[[np.ndarray], np.ndarray]] = None) -> NoiseFloor:
    """The sensor's noise floor from every kind of evidence ``records`` offer (at their own rate): the lowest of the
    direct estimates (holds, repeated periods: each can only be raised by what the valve does that does not
    repeat), else the input-free band's, else (with the valve's fitted ``response`` |G(f)|^2) the band beyond its
    response; unknown where there is none."""
    records = [r for r in records if r is not None and len(r) > 2]
    evidence = [hold_noise(records), period_noise(records), band_noise(records)]
    direct = [e for e in evidence[:2] if e.rms_um is not None]
    chosen = min(direct, key=lambda e: e.rms_um) if direct else (evidence[2] if evidence[2].rms_um is not None
                                                                 else None)
    if chosen is None and response is not None:
        evidence.append(beyond_response_noise(records, response))
        chosen = evidence[3] if evidence[3].rms_um is not None else None
    if chosen is None:
        return NoiseFloor(None, "none", "; ".join(e.detail for e in evidence), tuple(evidence))
    return NoiseFloor(chosen.rms_um, chosen.source, chosen.detail, tuple(evidence))
