"""The filter banks of core/model/iir.py give scipy.signal.lfilter's bits, for every filter length and bank size,
and the model's filtering paths (lag_bank, G at rest) run on them."""
import math

import numpy as np
import pytest
from scipy import signal

from piezo_valve_ros.core.model import iir
from piezo_valve_ros.core.model import lag_bank, steady_state
from piezo_valve_ros.core.model import lag_poles
from piezo_valve_ros.core.model import filter_at_rest, filter_rows_at_rest

FILTERS = {
    "first order": ([0.0, 0.3], [1.0, -0.7]),
    "second order (G at 2 kHz)": ([0.05, 0.12, 0.02], [1.0, -1.1, 0.29]),
    "third order": ([0.01, 0.03, 0.03, 0.01], [1.0, -2.2, 1.6, -0.38]),
    "b longer than a (a delay)": ([0.0, 0.0, 0.5, 0.5], [1.0, -0.2]),
    "FIR only": ([0.25, 0.5, 0.25], [1.0]),
    "five taps": ([0.1, 0.2, 0.3, 0.2, 0.1], [1.0, -0.5, 0.1, 0.0, 0.01]),
    "two pole pairs and a fractional delay": ([0.0, 0.0, 0.02, 0.05, 0.03, 0.01], [1.0, -2.4, 2.2, -0.9, 0.14]),
    "eight taps": ([0.05] * 8, [1.0, -0.9, 0.3, -0.1, 0.05, -0.02, 0.01, -0.005]),
    "nine taps (lfilter's own path)": ([0.05] * 9, [1.0, -0.5]),
    "a[0] != 1 (lfilter's own path)": ([0.2, 0.1], [2.0, -0.6]),
    "gain only": ([1.5], [1.0]),
}


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize("k", [1, 3, 17])
def test_filter_rows_gives_lfilters_bits(name, k):
    b, a = FILTERS[name]
    rng = np.random.default_rng(k)
    rows = rng.standard_normal((k, 2001)).cumsum(axis=1)
    taps = max(len(b), len(a))
    zi = rng.standard_normal((k, taps - 1))
    expected = signal.lfilter(b, a, rows, axis=1, zi=zi)[0] if taps > 1 else signal.lfilter(b, a, rows, axis=1)
    got = iir.filter_rows(b, a, rows, zi)
    assert got.shape == rows.shape
    assert np.array_equal(got, expected)


def test_filter_rows_takes_strided_rows_and_an_empty_record():
    b, a = FILTERS["second order (G at 2 kHz)"]
    wide = np.random.default_rng(0).standard_normal((6, 400))
    rows = wide[::2, ::2]   # neither contiguous nor aligned
    zi = np.ones((3, 2))
    assert np.array_equal(iir.filter_rows(b, a, rows, zi), signal.lfilter(b, a, rows, axis=1, zi=zi)[0])
    assert iir.filter_rows(b, a, np.zeros((2, 0)), np.zeros((2, 2))).shape == (2, 0)
    with pytest.raises(ValueError, match=r"\(k, N\)"):
        iir.filter_rows(b, a, np.zeros(5), np.zeros(2))


def test_first_order_bank_gives_lfilters_bits():
    x = np.random.default_rng(3).standard_normal(5000).cumsum()
    poles = np.exp(-1e-3 / np.array([0.005, 0.05, 0.5, 5.0]))
    got = iir.first_order_bank(x, poles, 1.0 - poles, start=2.5)
    expected = np.column_stack([signal.lfilter([0.0, 1.0 - p], [1.0, -p], x, zi=[2.5])[0] for p in poles])
    assert got.shape == (x.size, poles.size)
    assert np.array_equal(got, expected)
    with pytest.raises(ValueError, match="differ in shape"):
        iir.first_order_bank(x, poles, poles[:2], 0.0)


@pytest.mark.parametrize("taus, shaped, offset", [((0.005, 0.015, 0.05, 0.15, 0.5, 1.5), 5, 0.3),
                                                   ((0.005, 0.05, 0.5), 3, 0.0), ((0.005, 0.05), 0, 0.0),
                                                   ((0.005, 0.015, 0.05, 0.15, 0.5), 2, -1.0)])
def test_creeps_rows_in_one_pass_have_the_bits_of_the_banks_and_numpys_steps(taus, shaped, offset):
    """``creep_lag_rows`` against the rows built as creep built them: its lags (``lag_bank``), the direction terms
    from np.diff and np.cumsum of the fastest lag's changes, the level terms a product; on a walk with holds (exact
    zeros among the changes) and at rest elsewhere before the record."""
    dt = 1e-3
    h = np.random.default_rng(5).standard_normal(6000).cumsum()
    h[1000:2500] = h[999]
    before, centre, half = float(h[0]) + offset, 0.7, 12.5
    n, k = len(taus), shaped
    expected = np.empty((n + 2 * k, h.size))
    expected[:n] = lag_bank(h, taus, dt, before).T - h
    if k:
        slow = lag_bank(h, taus[:1], dt, before)[:, 0]
        change = np.diff(slow, prepend=before)
        rising, falling = np.cumsum(np.maximum(change, 0.0)), np.cumsum(np.minimum(change, 0.0))
        expected[n:n + k] = lag_bank(rising, taus[:k], dt).T - rising
        expected[n:n + k] -= lag_bank(falling, taus[:k], dt).T - falling
        expected[n + k:] = expected[:k] * ((h - centre) / half)
    got = iir.creep_lag_rows(h, before, lag_poles(taus, dt), shaped, centre, half)
    assert got.tobytes() == expected.tobytes()
    with pytest.raises(ValueError, match="shaped must be"):
        iir.creep_lag_rows(h, before, lag_poles(taus, dt), n + 1, centre, half)


def test_the_models_filters_run_on_the_banks():
    """lag_bank and G at rest (one row, many rows, columns) are lfilter's figures on a record."""
    dt = 5e-4
    x = np.sin(np.linspace(0, 40, 3000)) * 10 + np.random.default_rng(4).standard_normal(3000)
    taus = (0.05, 0.5, 5.0)
    poles = [math.exp(-dt / t) for t in taus]   # first_order_lag's ZOH pole
    expected = np.column_stack([signal.lfilter([0.0, 1 - p], [1.0, -p], x, zi=[1.0])[0] for p in poles])
    assert np.array_equal(lag_bank(x, taus, dt, initial=1.0), expected)
    b, a = FILTERS["second order (G at 2 kHz)"]
    zi = steady_state(b, a)
    assert np.array_equal(filter_at_rest(b, a, x), signal.lfilter(b, a, x, zi=zi * x[0])[0])
    assert np.array_equal(filter_at_rest(b, a, x, rest=3.0), signal.lfilter(b, a, x, zi=zi * 3.0)[0])
    cols = np.column_stack((x, 2 * x, -x))
    assert np.array_equal(filter_at_rest(b, a, cols, rest=[1.0, 2.0, 3.0])[:, 1],
                          signal.lfilter(b, a, 2 * x, zi=zi * 2.0)[0])
    assert np.array_equal(filter_rows_at_rest(b, a, cols.T)[2], signal.lfilter(b, a, -x, zi=zi * -x[0])[0])


def test_the_kernels_module_is_the_generators_and_covers_the_kernel_lengths():
    """_iir_kernels.py is written by scripts/iir_kernels.py (not edited by hand), with a kernel for every length
    iir.KERNEL_TAPS promises."""
    import subprocess
    import sys
    from pathlib import Path
    script = Path(__file__).resolve().parent.parent / "scripts" / "iir_kernels.py"
    done = subprocess.run([sys.executable, str(script), "--check"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    from piezo_valve_ros.core.model import _iir_kernels
    assert set(_iir_kernels.RUN_ROWS) == set(iir.KERNEL_TAPS)


def test_kernels_load_where_numba_can_write_no_cache_folder(monkeypatch):
    """numba refuses a cached kernel where neither the package's folder nor the user's cache folder can be written;
    the kernels are then cached in a temporary folder for the process, with a warning naming it."""
    import importlib
    import numba
    from piezo_valve_ros.core.model import compiled
    real = importlib.import_module
    refused = []

    def import_module(name, *args):
        if name.endswith("_iir_kernels") and not refused:
            refused.append(name)
            raise RuntimeError(f"cannot cache function 'rows_2': {compiled.NO_CACHE_FOLDER} for file '/opt/x.py'")
        return real(name, *args)
    monkeypatch.setattr(compiled.importlib, "import_module", import_module)
    monkeypatch.setattr(numba.config, "CACHE_DIR", numba.config.CACHE_DIR)   # restored after the test
    with pytest.warns(RuntimeWarning, match="NUMBA_CACHE_DIR"):
        module = compiled.load("piezo_valve_ros.core.model._iir_kernels")
    assert refused == ["piezo_valve_ros.core.model._iir_kernels"] and "piezo_valve_numba_" in numba.config.CACHE_DIR
    b, a = FILTERS["second order (G at 2 kHz)"]
    rows, zi = np.arange(12.0).reshape(2, 6), np.zeros((2, 2))
    out = np.empty(rows.shape)
    module.RUN_ROWS[3](np.asarray(b), np.asarray(a), rows, zi.T.copy(), out)
    assert np.array_equal(out, signal.lfilter(b, a, rows, axis=1, zi=zi)[0])
    def broken(name, *args):
        if name.endswith("_iir_kernels"):
            raise RuntimeError("something else")
        return real(name, *args)
    monkeypatch.setattr(compiled.importlib, "import_module", broken)
    with pytest.raises(RuntimeError, match="something else"):   # any other failure is not taken for the cache's
        compiled.load("piezo_valve_ros.core.model._iir_kernels")


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize("k", [1, 5, 90])
def test_filter_columns_gives_the_rows_bits_of_the_transposed_columns(name, k):
    """A sample-major bank (the operator states, N x n) filtered less its first row, without the transposed copy:
    filter_rows' bits (lfilter's), for every filter length, across the kernel's sample blocks (1000 samples: 15 full
    blocks and a part) and from a rest before the first sample."""
    b, a = FILTERS[name]
    rng = np.random.default_rng(k)
    columns = rng.standard_normal((1000, k)).cumsum(axis=0)
    taps = max(len(b), len(a))
    zi = rng.standard_normal((k, taps - 1))
    got = iir.filter_columns(b, a, columns, columns[0], zi)
    assert got.shape == (k, 1000)
    assert np.array_equal(got, iir.filter_rows(b, a, np.ascontiguousarray((columns - columns[0]).T), zi))
    from piezo_valve_ros.core.model import filter_state_columns_at_rest
    rest = rng.standard_normal(k)
    for before in ((None, rest) if taps > 1 else ()):   # (a gain has no state to rest in)
        expected = filter_rows_at_rest(b, a, np.ascontiguousarray((columns - columns[0]).T), before)
        got = filter_state_columns_at_rest(b, a, columns, before)
        assert np.array_equal(got, expected) and np.array_equal(np.signbit(got), np.signbit(expected))
    with pytest.raises(ValueError, match=r"\(N, k\)"):
        iir.filter_columns(b, a, np.zeros(5), np.zeros(1), np.zeros((1, max(taps - 1, 0))))


@pytest.mark.parametrize("name", FILTERS)
def test_a_bank_filtered_in_parts_into_one_array_has_the_whole_banks_bits(name):
    """``out=``: the rows kernel and the columns kernel (and lfilter's own path) write the rows of one larger
    array; each row's arithmetic is its own, so a bank filtered in two parts gives the whole bank's bits.  The
    states and a design's other columns through G in one array (Context.states_and_columns_through_dynamics)
    give through_dynamics' bits on their stacked copy, from the first sample and from a rest before it, whatever
    the blocks' memory order."""
    b, a = FILTERS[name]
    rng = np.random.default_rng(5)
    states = rng.standard_normal((700, 6)).cumsum(axis=0)
    others = rng.standard_normal((700, 3))
    less = states[3]
    taps = max(len(b), len(a))
    zi = rng.standard_normal((9, taps - 1))
    whole = iir.filter_rows(b, a, np.ascontiguousarray(np.column_stack([states - less, others]).T), zi)
    out = np.full((9, 700), np.nan)
    assert iir.filter_columns(b, a, states, less, zi[:6], out=out[:6]) is not None
    iir.filter_rows(b, a, np.ascontiguousarray(others.T), zi[6:], out=out[6:])
    assert np.array_equal(out, whole)
    with pytest.raises(ValueError, match="C-contiguous float64 array of shape"):
        iir.filter_rows(b, a, np.ascontiguousarray(others.T), zi[6:], out=np.empty((700, 3)).T)
    from types import SimpleNamespace
    from piezo_valve_ros.core.identification import Context
    ctx = SimpleNamespace(filter=(np.asarray(b, float), np.asarray(a, float)), states=states, record=np.zeros(700))
    rest = rng.standard_normal(9)
    for before in ((None, rest) if taps > 1 else ()):   # (a gain has no state to rest in)
        expected = filter_at_rest(b, a, np.column_stack([states - less, others]), before)
        got = Context.states_and_columns_through_dynamics(ctx, less, [others[:, :1], others[:, 1:].T.copy().T], before)
        assert got.shape == (700, 9) and got.T.flags.c_contiguous
        assert np.array_equal(got, expected) and np.array_equal(np.signbit(got), np.signbit(expected))


COMPILE_RACE = """
import os, sys, time
import numpy as np
from piezo_valve_ros.core.model.dynamics import lag_bank
from piezo_valve_ros.core.model import compiled
kernels = compiled.load("piezo_valve_ros.core.model._iir_kernels")
open(sys.argv[2], "w").close()
while not os.path.exists(sys.argv[1]):
    time.sleep(0.001)
lag_bank(np.linspace(0.0, 1.0, 50), [0.01, 0.1], 1e-3)
stats = kernels.first_order_bank.stats
print(sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))
"""


def test_processes_that_start_together_on_a_cold_cache_compile_a_kernel_once(tmp_path):
    """Two processes ask for the same kernel at the same moment on an empty numba cache: one compiles it, the
    other waits for it and loads it from the cache (each compiled it: about 10 s of CPU per process for an
    analysis's kernels)."""
    import os
    import subprocess
    import sys
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    go = tmp_path / "go"
    ready = [tmp_path / f"ready{k}" for k in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", COMPILE_RACE, str(go), str(r)], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in ready]
    try:
        import time
        deadline = time.monotonic() + 60
        while not all(r.exists() for r in ready) and time.monotonic() < deadline:
            time.sleep(0.01)   # both have imported numpy, numba and the kernels' module
        go.touch()
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert all(p.returncode == 0 for p in procs), [err for _, err in outs]
    hits, misses = (sum(int(out.split()[k]) for out, _ in outs) for k in (0, 1))
    assert (hits, misses) == (1, 1), outs


def test_each_kernel_compiles_once_whatever_the_banks_size_or_the_thresholds_flags():
    """A kernel's arguments reach it with one layout and one writability, so numba compiles (or loads) one
    specialisation per kernel: a state array passed as it came (a bank of one row is C-contiguous, of several
    Fortran) or thresholds or weights read-only in one caller and writable in another each cost a second compile on
    a cold cache (about 0.5 s of CPU each, in every process that starts on one; in a test worker that had run the
    GPIM's read-only weights first, this test failed).  It runs in a process of its own, so what the worker ran
    before cannot hide a second layout, nor add one."""
    import json
    import subprocess
    import sys
    b, a = FILTERS["second order (G at 2 kHz)"]
    code = f"""
import json
import numpy as np
from piezo_valve_ros.core.model import iir, hysteresis
b, a = np.array({list(map(float, b))}), np.array({list(map(float, a))})
rng = np.random.default_rng(3)
for k in (1, 3):
    rows = rng.normal(size=(k, 500))
    iir.filter_rows(b, a, rows, np.zeros((k, 2)))
    iir.filter_columns(b, a, np.ascontiguousarray(rows.T), np.zeros(k), np.zeros((k, 2)))
v = np.cumsum(rng.normal(size=30_000))
for writable in (True, False):
    r = np.linspace(0.0, 2.0, 4)
    r.flags.writeable = writable
    states, _ = hysteresis.play_batch(v, v, r, np.zeros(4), compiled=True)
    side, index = hysteresis.last_contact(states, v, v, r, compiled=True)
    weights = np.ones(4)   # a GPIM's are read-only, a caller's may not be
    weights.flags.writeable = writable
    hysteresis.contact_sensitivity(side, index, weights, np.ones(v.size), "both", compiled=True)
iir.creep_lag_rows(v, 0.5, np.array([0.9, 0.99]), 1, 0.0, 1.0)
kernels = [iir._kernels(), hysteresis._kernels(), iir._lag_rows_kernel()]
print(json.dumps({{name: len(f.signatures) for module in kernels for name, f in vars(module).items()
                  if hasattr(f, "signatures") and f.signatures}}))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    used = json.loads(done.stdout.strip().splitlines()[-1])
    assert {"rows_3", "columns_3", "play_rows", "last_contacts", "contact_sums", "creep_rows"} <= set(used), used
    assert all(count == 1 for count in used.values()), used


def test_an_output_decaying_at_rest_is_flushed_to_zero_where_lfilters_sticks_in_subnormals():
    """A slow lag whose input rests at zero: lfilter's output decays into the subnormal range and stays there (the
    last bit's rounding holds it), where every product costs tens of times a normal one (an identification's solves
    ran 20x slower on such rows).  The kernels flush a subnormal output to zero and give lfilter's bits everywhere
    else: the rows, columns and first-order bank kernels alike."""
    tiny = np.finfo(float).tiny
    pole = 0.999
    b, a = [0.0, 1.0 - pole], [1.0, -pole]
    x = np.zeros(800_000)
    x[:100] = 1.0
    expected = signal.lfilter(b, a, x)
    subnormal = (np.abs(expected) < tiny) & (expected != 0.0)
    assert subnormal.sum() > 50_000 and subnormal[-1]       # lfilter's: stuck, to the record's end
    rows = iir.filter_rows(b, a, np.vstack((x, 2 * x)), np.zeros((2, 1)))
    columns = iir.filter_columns(b, a, np.column_stack((x, 2 * x)), np.zeros(2), np.zeros((2, 1)))
    bank = iir.first_order_bank(x, np.array([pole]), np.array([1.0 - pole]), 0.0)[:, 0]
    for got in (rows[0], columns[0], bank):
        assert not np.any((np.abs(got) < tiny) & (got != 0.0))
        assert np.array_equal(got[~subnormal], expected[~subnormal]) and np.all(got[subnormal] == 0.0)
