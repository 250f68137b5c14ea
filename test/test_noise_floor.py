"""The sensor's noise floor from evidence alone (``core.identification.noise``): holds, repeated periods, a band the
drive cannot echo; unknown where a record offers none of them."""
import numpy as np
import pytest

from piezo_valve_ros.core.identification import (band_noise, beyond_response_noise, estimate_noise_floor, hold_noise,
                                                 period_noise, welch_density)
from piezo_valve_ros.core.identification import Record, noise_floor_um

DT = 5e-4
NOISE = 0.05


def _record(v: np.ndarray, y: np.ndarray, seed: int = 0, noise: float = NOISE) -> Record:
    rng = np.random.default_rng(seed)
    return Record(np.arange(v.size) * DT, v, y + noise * rng.standard_normal(v.size))


def _smooth_valve(v: np.ndarray) -> np.ndarray:
    """A valve's position for drive ``v``: a gain, a 2 ms lag and a slow creep-like approach (no noise)."""
    from scipy.signal import lfilter
    a, c = np.exp(-DT / 2e-3), np.exp(-DT / 1.0)
    fast = lfilter([1 - a], [1, -a], 14.0 * v, zi=[14.0 * v[0] * a])[0]
    return fast + lfilter([1 - c], [1, -c], 0.5 * v, zi=[0.5 * v[0] * c])[0]


def test_holds_give_the_noise_whatever_the_valve_does_smoothly_in_them():
    levels = np.repeat([2.0, 7.0, 4.0, 9.0, 1.0], int(2.0 / DT))
    for seed in (1, 2):
        e = hold_noise([_record(levels, _smooth_valve(levels), seed)])
        assert e.rms_um == pytest.approx(NOISE, rel=0.05) and "5 holds" in e.detail


def test_repeated_periods_give_the_noise_of_a_drive_that_is_never_still():
    rng = np.random.default_rng(4)
    period = rng.uniform(0, 10, 400)
    v = np.tile(period, 12)   # a periodic drive with broadband content: second differences are all signal
    y = _smooth_valve(v) + 0.002 * np.arange(v.size) * DT    # and a slow drift between the periods
    r = _record(v, y, 5)
    e = period_noise([r])
    assert e.rms_um == pytest.approx(NOISE, rel=0.05) and "0.2 s periods" in e.detail
    assert noise_floor_um(r.position_um) > 10 * NOISE        # what the old estimate called noise
    floor = estimate_noise_floor([r])
    assert floor.source == "repeated periods" and floor.rms_um == pytest.approx(NOISE, rel=0.05)


def test_a_band_the_drive_has_no_power_in_gives_the_noise():
    t = np.arange(int(20.0 / DT)) * DT
    v = 5.0 + 4.0 * np.sin(2 * np.pi * 0.3 * t) * np.sin(2 * np.pi * 0.05 * t + 0.3)   # smooth, never still
    e = band_noise([_record(v, _smooth_valve(v), 6)])
    assert e.rms_um == pytest.approx(NOISE, rel=0.1)
    assert hold_noise([_record(v, _smooth_valve(v), 6)]).rms_um is None


def test_a_record_with_no_evidence_has_no_floor_and_says_why():
    rng = np.random.default_rng(7)
    v = 5.0 + np.cumsum(rng.standard_normal(int(10.0 / DT))) * 0.05      # a random walk: no holds, no period
    v = np.clip(v, 0.0, 10.0) + rng.uniform(-0.005, 0.005, v.size)      # with power up to the Nyquist rate
    floor = estimate_noise_floor([_record(v, 14.0 * v, 8)])
    assert not floor.known and floor.source == "none" and floor.rms_um is None
    assert "no hold" in floor.detail and "does not repeat" in floor.detail and "could echo" in floor.detail
    assert floor.describe().startswith("no evidence for the sensor noise")
    # a valve that cannot follow the drive's fast part (a 10 ms lag): the band beyond its response is noise
    from scipy.signal import lfilter
    a = np.exp(-DT / 1e-2)
    y = lfilter([1 - a], [1, -a], 14.0 * v, zi=[14.0 * v[0] * a])[0]
    slow = estimate_noise_floor([_record(v, y, 9)], response=lambda f: 1.0 / (1.0 + (2 * np.pi * f * 1e-2) ** 2))
    assert slow.source == "band beyond the valve's response" and slow.rms_um == pytest.approx(NOISE, rel=0.2)
    assert beyond_response_noise([_record(v, y, 9)], lambda f: np.ones_like(f)).rms_um is None


def test_the_lowest_direct_estimate_is_the_floor_and_every_kind_is_reported():
    levels = np.repeat([2.0, 7.0, 4.0], int(2.0 / DT))
    periodic = np.tile(np.concatenate([np.linspace(1, 9, 200), np.linspace(9, 1, 200)]), 10)
    v = np.concatenate([levels, periodic])
    floor = estimate_noise_floor([_record(v, _smooth_valve(v), 10), None])
    assert [e.source for e in floor.evidence] == ["holds", "repeated periods", "input-free band"]
    assert floor.rms_um == min(e.rms_um for e in floor.evidence[:2])
    assert floor.as_dict()["evidence"]["holds"]["rms_um"] == pytest.approx(NOISE, rel=0.1)


@pytest.mark.parametrize("n, segment", [(20000, 1024), (5003, 256), (777, 128), (300, 64)])
def test_the_band_s_spectra_are_scipy_s_welch_with_a_line_off_each_segment(n, segment):
    """welch_density is scipy.signal.welch(nperseg=segment, detrend="linear") written with one projection for all
    segments: the same frequencies and densities to rounding (a random walk: a line in every segment to take off)."""
    from scipy.signal import welch
    x = np.cumsum(np.random.default_rng(n).standard_normal(n)) + 3.0
    f_ref, p_ref = welch(x, 2000.0, nperseg=segment, detrend="linear")
    f, p = welch_density(x, 2000.0, segment)
    assert np.array_equal(f, f_ref)
    assert np.allclose(p, p_ref, rtol=1e-9, atol=1e-12 * p_ref.max())
