"""GPIM, play operator and exact inverse."""
import numpy as np
import pytest

from piezo_valve_ros.core.model import (GPIM, GPIMParams, InverseGPIM, NotInvertibleError, PAPER_GPIM,
                                        PlayOperatorBank, play_batch, inverse_problems)


def random_walk(n, seed, step=0.05, centre=5.0):
    rng = np.random.default_rng(seed)
    return np.clip(centre + np.cumsum(rng.normal(0, step, n)), -2, 12)


def naive_play(x, r, z0):
    z = np.array(z0, float)
    out = np.empty((x.size, r.size))
    for k, xk in enumerate(x):
        z = np.minimum(np.maximum(z, xk - r), xk + r)
        out[k] = z
    return out


def test_play_batch_matches_definition_smooth_noisy_and_flat():
    r = np.array([0.0, 0.3, 1.0, 2.5])
    rng = np.random.default_rng(3)
    for x in (np.sin(np.linspace(0, 20, 3000)) * 3, rng.normal(size=5000),
              np.repeat(rng.normal(size=50), 40), np.zeros(10), np.array([1.0])):
        z0 = rng.normal(size=r.size) * 0.1
        ref = naive_play(x, r, z0)
        out, final = play_batch(x, x, r, z0)
        np.testing.assert_allclose(out, ref, atol=1e-12)
        np.testing.assert_allclose(final, ref[-1], atol=1e-12)


def test_scan_handles_many_reversals():
    # over 4*64 reversals exercises the two-level scan
    x = np.random.default_rng(0).normal(size=200_000)
    r = np.array([0.0, 0.1, 0.5, 1.5])
    out, _ = play_batch(x, x, r, np.zeros(4))
    np.testing.assert_allclose(out[-1000:], naive_play(x, r, np.zeros(4))[-1000:], atol=1e-12)


@pytest.mark.parametrize("count", [1, 100, 129, 1000, 16383, 16384, 70001])
def test_the_clamp_scan_is_the_composition_clamp_after_clamp_to_the_bit(count):
    """Every prefix of the scan is the clamps composed one after another (min and max do not round, so any
    grouping gives the same bits), across the block sizes and levels of the scan."""
    from piezo_valve_ros.core.model.hysteresis import _compose_clamps_scan
    rng = np.random.default_rng(count)
    lo = rng.normal(size=(count, 3))
    hi = lo + rng.uniform(0, 1, size=(count, 3)) * (rng.uniform(size=(count, 3)) > 0.2)   # some lo == hi
    A, B = _compose_clamps_scan(lo, hi)
    a, b = np.full(3, -np.inf), np.full(3, np.inf)
    for k in range(count):
        a, b = np.minimum(np.maximum(a, lo[k]), hi[k]), np.minimum(np.maximum(b, lo[k]), hi[k])
        if k in (0, count // 2, count - 1) or k % 997 == 0:
            assert np.array_equal(A[k], a) and np.array_equal(B[k], b), k


def test_streaming_equals_batch_with_state_carried():
    m = PAPER_GPIM.model()
    v = random_walk(20_000, 1)
    s = m.stream(v0=v[0])
    ys = np.array([s.step(x) for x in v[:7000]])
    yb = s.run(v[7000:])
    full, _ = m.run(v)
    np.testing.assert_allclose(np.concatenate((ys, yb)), full, atol=1e-10)


def test_asymmetric_envelopes_batch_equals_streaming():
    base = PAPER_GPIM.model()
    m = GPIM(base.thresholds, base.weights, base.a0, base.a1, base.offset_um, b0=0.9, b1=0.6)
    v = random_walk(10_000, 2)
    s = m.stream(v0=v[0])
    ys = np.array([s.step(x) for x in v])
    np.testing.assert_allclose(ys, m.run(v)[0], atol=1e-10)
    with pytest.raises(NotInvertibleError, match="no closed-form inverse"):
        InverseGPIM(m)


def test_paper_model_loop_span_width_and_centring():
    m = PAPER_GPIM.model()
    v, up, down = m.major_loop()
    span = up.max() - up.min()
    assert 130 < span < 140  # 134.9 um: the major loop of the paper's parameters
    width = np.max(down - up) / span
    assert 0.15 < width < 0.19
    # the default offset centres the major loop on 0 um
    assert abs((up.max() + up.min()) / 2) < 0.01
    # the initial-loading curve from a virgin state at 0 V spans the 147.6 um of paper.md
    y, _ = m.run(np.linspace(0, 10, 1001), m.virgin_state(0.0))
    assert abs((y[-1] - y[0]) - 147.6) < 0.1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_of_inverse_is_identity_long_random_demand(seed):
    m = PAPER_GPIM.model()
    rng = np.random.default_rng(seed)
    y = 65 * np.tanh(np.cumsum(rng.normal(0, 1.0, 200_000)) / 65)
    inv = InverseGPIM(m, v0=5.0)
    v = inv.run(y)
    y_back, _ = m.run(v, m.virgin_state(5.0))
    assert np.max(np.abs(y_back - y)) <= 1e-9


def test_inverse_streaming_equals_batch_and_identity_after_history_and_reset():
    m = PAPER_GPIM.model()
    # arbitrary history of the forward model, then the inverse takes over its state
    z = m.stream(v0=5.0)
    z.run(random_walk(5000, 4))
    inv = InverseGPIM(m, z.state.copy())
    y = 50 * np.sin(np.linspace(0, 30, 6000)) + np.random.default_rng(5).normal(0, 3, 6000)
    v_stream = np.array([inv.step(q) for q in y])
    y_back, _ = m.run(v_stream, z.state.copy())
    assert np.max(np.abs(y_back - y)) <= 1e-9
    # round-trip of the state mapping
    np.testing.assert_allclose(InverseGPIM(m, inv.forward_state()).bank.state, inv.bank.state, atol=1e-10)
    inv.reset(3.0)
    v2 = inv.run(y)
    y2, _ = m.run(v2, m.virgin_state(3.0))
    assert np.max(np.abs(y2 - y)) <= 1e-9


def test_inverse_identity_after_parameter_update():
    m = PAPER_GPIM.model()
    inv = InverseGPIM(m)
    inv.run(40 * np.sin(np.linspace(0, 10, 3000)))
    m2 = GPIMParams(a0=1.0, a1=0.0, alpha=0.38, rho=6.2, tau=1.1, n=12, offset_um=-80.0).model()
    v_now = (float(inv.weights @ inv.bank.state) - m.a1) / m.a0
    inv2 = inv.with_model(m2, v_now)
    z = inv2.forward_state()
    y = 30 * np.cos(np.linspace(0, 15, 4000))
    v = inv2.run(y)
    y_back, _ = m2.run(v, z)
    assert np.max(np.abs(y_back - y)) <= 1e-9


def test_not_invertible_sets_are_rejected_with_reason():
    r = np.array([0.0, 0.5, 1.0])
    assert "first weight" in inverse_problems(GPIM(r, [-1.0, 2.0, 1.0]))[0]
    assert any("partial sum" in p for p in inverse_problems(GPIM(r, [1.0, -2.0, 0.5])))
    assert any("first threshold" in p for p in inverse_problems(GPIM(r + 0.1, [1.0, 1.0, 1.0])))
    with pytest.raises(ValueError, match="non-finite"):
        GPIM(r, [1.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="strictly increasing"):
        GPIM([0.0, 1.0, 1.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="alpha"):
        GPIMParams(alpha=0.0).model()
    with pytest.raises(NotInvertibleError, match="first weight"):
        InverseGPIM(GPIM(r, [-1.0, 2.0, 1.0]))


def test_play_bank_step_does_not_allocate_new_state():
    bank = PlayOperatorBank([0.0, 1.0], [0.0, 0.0])
    state = bank.state
    bank.step(2.0, 2.0)
    assert bank.state is state
    np.testing.assert_allclose(state, [2.0, 1.0])


def _play_by_definition(lower, upper, r, z0, scale=None):
    """The play recursion written out sample by sample, as the paper writes it (the reference for the batch scan):
    ``min(max(z, L - r), U + r)``, so the upper bound wins where the bounds cross."""
    m = np.ones(lower.size) if scale is None else scale
    z = np.array(z0, float)
    out = np.empty((lower.size, r.size))
    for k in range(lower.size):
        z = np.minimum(np.maximum(z, lower[k] - r * m[k]), upper[k] + r * m[k])
        out[k] = z
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_play_batch_with_widening_and_scaled_thresholds_matches_the_definition(seed):
    from piezo_valve_ros.core.model import play_batch
    rng = np.random.default_rng(seed)
    v = np.cumsum(rng.standard_normal(4000)) * 0.3
    r = np.linspace(0, 3, 7)
    rho = np.abs(np.convolve(np.gradient(v), np.ones(5) / 5, "same"))
    lower, upper = v - 0.2 * rho, 1.03 * v + 0.1 + 0.2 * rho  # asymmetric and widening
    z0 = np.zeros(r.size)
    out, final = play_batch(lower, upper, r, z0, chunk=700)
    assert np.array_equal(out, _play_by_definition(lower, upper, r, z0))
    scale = 1.0 + 0.4 * rho
    out, final = play_batch(lower, upper, r, z0, threshold_scale=scale, chunk=900)
    ref = _play_by_definition(lower, upper, r, z0, scale)
    assert np.max(np.abs(out - ref)) < 1e-12 and np.max(np.abs(final - ref[-1])) < 1e-12


def test_last_contact_gives_the_exact_sensitivities():
    """dH/dtheta from the last contacts equals central finite differences, for the descending envelope
    (asymmetry) and for thresholds widened by a rate term (rate dependence)."""
    from piezo_valve_ros.core.model import last_contact, play_batch
    rng = np.random.default_rng(4)
    v = np.cumsum(rng.standard_normal(5000)) * 0.3
    r = np.linspace(0, 3, 9)
    p = rng.uniform(0.5, 1.5, r.size)
    z0 = np.zeros(r.size)
    rho = np.abs(np.gradient(v))
    eps = 1e-6

    def weighted(lower, upper):
        return play_batch(lower, upper, r, z0, p)[0]
    # widening c * rho of every threshold
    c = 0.2
    states, _ = play_batch(v - c * rho, v + c * rho, r, z0)
    side, idx = last_contact(states, v - c * rho, v + c * rho, r)
    exact = (side * rho[np.maximum(idx, 0)]) @ p
    fd = (weighted(v - (c + eps) * rho, v + (c + eps) * rho) - weighted(v - (c - eps) * rho, v + (c - eps) * rho)) / (2 * eps)
    assert np.max(np.abs(exact - fd)) < 1e-6 * max(1.0, np.max(np.abs(fd)))
    # slope b0 of the descending envelope b0 * v
    b0 = 1.05
    states, _ = play_batch(v, b0 * v, r, z0)
    side, idx = last_contact(states, v, b0 * v, r)
    exact = ((side > 0) * v[np.maximum(idx, 0)]) @ p
    fd = (weighted(v, (b0 + eps) * v) - weighted(v, (b0 - eps) * v)) / (2 * eps)
    assert np.max(np.abs(exact - fd)) < 1e-6 * max(1.0, np.max(np.abs(fd)))


def test_last_contact_is_the_same_whatever_its_block_size():
    """last_contact works block by block, carrying each operator's last contact across blocks: blocks of 1, 7 and
    1000 rows and one block give the same sides and samples, with equal drives (threshold 0: both bounds at
    once, the side follows the input's direction), with a descending envelope of its own and with a rate term;
    an operator never touched keeps side 0 and sample -1."""
    from piezo_valve_ros.core.model import hysteresis
    from piezo_valve_ros.core.model import last_contact, play_batch
    rng = np.random.default_rng(8)
    v = np.cumsum(rng.standard_normal(3000)) * 0.3
    r = np.append(np.linspace(0, 3, 9), 1e6)   # the last operator is never touched
    z0 = np.zeros(r.size)
    rho = np.abs(np.gradient(v))
    for lower, upper in ((v, v), (v, 1.05 * v + 0.1), (v - 0.2 * rho, v + 0.2 * rho)):
        states, _ = play_batch(lower, upper, r, z0)
        results = []
        for block in (1, 7, 1000, 10 ** 6):
            hysteresis.ROW_BLOCK, saved = block, hysteresis.ROW_BLOCK
            try:
                results.append(last_contact(states, lower, upper, r))
            finally:
                hysteresis.ROW_BLOCK = saved
        for side, idx in results[:-1]:
            assert np.array_equal(side, results[-1][0]) and np.array_equal(idx, results[-1][1])
        side, idx = results[-1]
        assert (side[:, -1] == 0).all() and (idx[:, -1] == -1).all()
        assert (side[:, 0] != 0).all()   # threshold 0: in contact from the first move on
        assert set(np.unique(side)) <= {-1, 0, 1} and (np.diff(idx, axis=0) >= 0).all()


@pytest.mark.parametrize("n", [3, 8, 15, 90, 128, 130])
def test_contact_sensitivity_compiled_gives_the_numpy_paths_bits(n):
    """contact_sensitivity's sums (the Gauss-Newton sensitivities of the descending envelope and of rate-dependent
    thresholds): compiled, each row's terms formed and summed as numpy forms and sums them (its pairwise sum), so
    the two paths agree to the bit for every operator count (above 128 the numpy path runs), each bound choice and
    one or several columns; and both equal the sum written out, to rounding."""
    from piezo_valve_ros.core.model import contact_sensitivity, last_contact, play_batch
    rng = np.random.default_rng(n)
    v = np.cumsum(rng.standard_normal(6000)) * 0.3
    r = np.linspace(0, 3, n)
    w = rng.uniform(0.0, 1.5, n) * 10.0 ** rng.integers(-3, 3, n)
    rho = np.abs(np.gradient(v))
    states, _ = play_batch(v - 0.2 * rho, v + 0.2 * rho, r, np.zeros(n))
    side, idx = last_contact(states, v - 0.2 * rho, v + 0.2 * rho, r)
    for change in (rho, rng.standard_normal((v.size, 4))):
        for bounds, on in (("lower", side < 0), ("upper", side > 0), ("both", side)):
            fast = contact_sensitivity(side, idx, w, change, bounds, compiled=True)
            slow = contact_sensitivity(side, idx, w, change, bounds)
            assert fast.shape == slow.shape == change.shape and np.array_equal(fast, slow), (bounds, change.ndim)
            c = change if change.ndim == 2 else change[:, None]
            written = np.stack([(on * w * c[np.maximum(idx, 0), k]).sum(axis=1) for k in range(c.shape[1])], axis=1)
            assert np.allclose(fast, written.reshape(fast.shape), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="bounds must be one of lower, upper, both"):
        contact_sensitivity(side, idx, w, rho, "sideways")


@pytest.mark.parametrize("method, delay", [("zoh", 0.0), ("foh", 0.0), ("foh", 5e-5), ("zoh", 3e-4)])
def test_closed_form_discretisation_matches_scipy(method, delay):
    from scipy import signal
    from piezo_valve_ros.core.model import ContinuousTF, PAPER_VALVE_MODEL, discretise
    from piezo_valve_ros.core.model import unity_dc_poles
    x = np.random.default_rng(0).standard_normal(3000).cumsum()
    for tf in (PAPER_VALVE_MODEL, unity_dc_poles([(1095.0, 1.32), (3000.0, 0.2)]), ContinuousTF((1.0,), (0.03, 1.0)),
               unity_dc_poles([(1095.0, 1.32), (600.0, 1.01)])):   # (real poles 15 % apart beside a delay's fast one)
        num, den = np.asarray(tf.num), np.asarray(tf.den)
        if delay:
            num, den = np.polymul(num, [-delay / 2, 1]), np.polymul(den, [delay / 2, 1])
        b0, a0, _ = signal.cont2discrete((num, den), 5e-4, method=method)
        b1, a1 = discretise(tf, 5e-4, method, delay)
        assert np.max(np.abs(signal.lfilter(np.squeeze(b0), a0, x) - signal.lfilter(b1, a1, x))) < 1e-8


def test_an_integrator_is_discretised_without_a_warning():
    """A pole at 0 has no partial-fraction form (nor a scale for the poles' gap): scipy's, silently."""
    import warnings
    from piezo_valve_ros.core.model import ContinuousTF, discretise
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b, a = discretise(ContinuousTF((1.0,), (1.0, 0.0)), 1e-3)
    assert np.allclose(b, [0.0, 1e-3]) and np.allclose(a, [1.0, -1.0])


def test_discretisation_of_a_repeated_pole_pair_keeps_unity_dc_gain():
    """Two equal critically damped pairs (a feedforward target whose poles both sit at the Nyquist cap): a
    4-fold pole, which np.roots splits by ~1e-4; partial fractions over it gave a DC gain of 8e6 and a
    controller banging between its rails.  The sampled filter matches scipy's and has unity DC gain."""
    from scipy import signal
    from piezo_valve_ros.core.control import DynamicFeedforward
    from piezo_valve_ros.core.model import ContinuousTF, discretise, unity_dc_poles
    wf = 1570.8
    quad = ContinuousTF((wf ** 4,), tuple(np.polymul([1.0, 2 * wf, wf * wf], [1.0, 2 * wf, wf * wf])))
    b, a = discretise(quad, 1e-3)
    b0, a0, _ = signal.cont2discrete((quad.num, quad.den), 1e-3, method="zoh")
    np.testing.assert_allclose(b, np.squeeze(b0), atol=1e-12)
    assert np.sum(b) / np.sum(a) == pytest.approx(1.0, abs=1e-9)
    # a fitted G with a second section far above the 1 kHz controller's reach: W stays a unity-DC filter
    w, f = DynamicFeedforward(unity_dc_poles([(1230.7, 1.46), (62831.9, 2.42)]), 1e-3).filters()
    assert np.sum(w.b) / np.sum(w.a) == pytest.approx(1.0, abs=1e-9)
    assert np.sum(f.b) / np.sum(f.a) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("phase", [0.3, 2.0, 4.0])  # starts rising, near the top, falling
def test_cycled_state_is_the_state_of_running_operation(phase):
    # a record cut from a periodic drive: its operators must start as they stood after the previous
    # cycles, so the model run from the cycled state continues the long run sample for sample
    model = GPIMParams(a0=1.0, a1=0.0, alpha=9.0, rho=0.08, tau=0.01, n=15).model()
    t = np.arange(0.0, 3.0, 1e-3)
    v_long = 150.0 * np.sin(2 * np.pi * t - np.pi / 2)         # from rest at -150 V, three cycles
    y_long, _ = model.run(v_long)
    cut = int(np.searchsorted(t, 1.0 + phase / (2 * np.pi)))
    v = v_long[cut:]
    y, _ = model.run(v, model.cycled_state(v))
    np.testing.assert_allclose(y, y_long[cut:], atol=1e-9)
    y_rest, _ = model.run(v)                                    # the virgin state gets the first swing wrong
    assert np.max(np.abs(y_rest - y_long[cut:])) > 1.0


def asymmetric(b0_gain=1.03, b1_shift=0.08, b2=0.0):
    """The paper's model with a descending envelope above the ascending one on 0..10 V (a dead band)."""
    m = PAPER_GPIM.model()
    return GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, m.a0 * b0_gain, m.a1 + b1_shift, b2)


@pytest.mark.parametrize("model", [asymmetric(), asymmetric(1.0, 0.15, 0.002), asymmetric(1.05, 0.02, -0.002)],
                         ids=["linear", "curved up", "curved down"])
def test_asymmetric_inverse_is_exact_streaming_and_batch(model):
    """Issue 11.2: separate ascending/descending envelopes, forward(inverse(y)) == y to rounding, after an
    arbitrary history, streaming and batch alike, and through a held output (the dead band)."""
    assert inverse_problems(model) == []
    fwd = model.stream(v0=5.0)
    fwd.run(random_walk(4000, 11, centre=5.0).clip(0.0, 10.0))
    z = fwd.state.copy()
    rng = np.random.default_rng(12)
    y = 40 * np.sin(np.linspace(0, 25, 6000)) + rng.normal(0, 2, 6000)
    y[2000:2300] = y[1999]                                   # held: the input stays put
    inv_a, inv_b = InverseGPIM(model, z), InverseGPIM(model, z)
    v_stream = np.array([inv_a.step(q) for q in y])
    v_batch = inv_b.run(y)
    np.testing.assert_allclose(v_batch, v_stream, atol=1e-12)
    y_back, _ = model.run(v_stream, z)
    assert np.max(np.abs(y_back - y)) <= 1e-9
    assert np.ptp(v_stream[2000:2300]) == 0.0
    # the prediction without advancing equals the forward step
    v_next = 6.3
    ahead = inv_a.peek_forward(v_next)
    probe = model.stream(inv_a.forward_state().copy())
    assert ahead == pytest.approx(probe.step(v_next), abs=1e-12)


def test_the_per_step_inverse_never_leaves_the_drive_range_whatever_the_demand():
    """A demand beyond what the model reaches gives the end of the input range, never beyond it: every input the
    per-step inverse returns, by its closed form or its general solve, on every model and from every state, lies in
    0..10 V (the other tests skip samples at the ends)."""
    from piezo_valve_ros.core.model import MonotoneInverseGPIM, inverse_gpim
    from piezo_valve_ros.core.model import RateDependentInverseGPIM
    rng = np.random.default_rng(11)
    models = (asymmetric(0.95 / 0.9647, 0.2 - 0.1014), asymmetric(1.06, -0.35, -0.0005))
    for model in models:
        lo, hi = model.output_range()
        for inv in (inverse_gpim(model, v0=5.0),
                    RateDependentInverseGPIM(model, (0.5, 0.0, 0.2, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0), 1e-3, v0=5.0)):
            assert isinstance(inv, MonotoneInverseGPIM)
            demands = np.concatenate([rng.uniform(lo - 60.0, hi + 60.0, 3000), np.full(50, hi + 40.0),
                                      np.full(50, lo - 40.0), np.linspace(lo, hi + 80.0, 400)])
            v = np.array([inv.step(y) for y in demands])
            assert np.all((v >= 0.0) & (v <= 10.0)), (float(v.min()), float(v.max()))
            assert np.any(v == 10.0) and np.any(v == 0.0)


def test_envelopes_that_cross_are_inverted_exactly_step_by_step():
    """Issue 11.2: a descending envelope below the ascending one on part of the range has no closed-form
    inverse (InverseGPIM refuses it, saying where), but the per-step solve inverts it to rounding over long
    random admissible demands, linear and curved, after a reset, a state take-over and a model update."""
    from piezo_valve_ros.core.model import MonotoneInverseGPIM, dead_band_problems, inverse_gpim
    crossing = asymmetric(0.95 / 0.9647, 0.2 - 0.1014)      # U < L above 6.7 V
    assert "below the ascending one from 6.7" in dead_band_problems(crossing)[0]
    assert not inverse_problems(crossing)
    with pytest.raises(NotInvertibleError, match="no closed-form inverse"):
        InverseGPIM(crossing)
    assert "not rising" in inverse_problems(asymmetric(1.0, 0.5, -0.06))[0]
    rng = np.random.default_rng(4)
    curved = asymmetric(1.06, -0.35, -0.0005)                # below for low voltages, curved
    for model in (crossing, curved):
        inv = inverse_gpim(model, v0=5.0)
        assert isinstance(inv, MonotoneInverseGPIM)
        walk = np.cumsum(rng.normal(0.0, 0.3, 6000))
        v = 5.0 + 4.9 * np.tanh((walk - walk.mean()) / (3.0 * walk.std()))
        z0 = model.virgin_state(5.0)
        y, _ = model.run(v, z0)
        v_inv = np.concatenate((inv.run(y[:3000]), [inv.step(x) for x in y[3000:]]))
        assert np.max(np.abs(model.run(v_inv, z0)[0] - y)) <= 1e-9
        # after a reset
        inv.reset(2.0)
        y2, _ = model.run(v[::-1], model.virgin_state(2.0))
        assert np.max(np.abs(model.run(inv.run(y2), model.virgin_state(2.0))[0] - y2)) <= 1e-9
        # after a model update (its state carried over): the new model reproduces its demands
        other = asymmetric(model.b0 / model.a0 * 1.01, model.b1 - model.a1 + 0.02)
        swapped = inv.with_model(other, float(v[0]))
        z = swapped.forward_state()
        y3 = other.run(v[:2000], z)[0]
        assert np.max(np.abs(other.run(swapped.run(y3), z)[0] - y3)) <= 1e-9
        # peek does not advance, peek_forward agrees with a forward step
        before = swapped.forward_state()
        swapped.peek(float(y3[-1]) + 3.0)
        np.testing.assert_array_equal(swapped.forward_state(), before)
        probe = other.stream(before.copy())
        assert swapped.peek_forward(6.3) == pytest.approx(probe.step(6.3), abs=1e-12)


def test_ol_hc_with_the_asymmetric_inverse_tracks_an_asymmetric_valve_exactly():
    """The controller's feedforward on an ideal simulated valve (hysteresis only, no G_v) with separate
    envelopes: the exact asymmetric inverse tracks to rounding, the symmetric model does not."""
    from dataclasses import replace
    from piezo_valve_ros.core.sim import run_closed_loop
    from piezo_valve_ros.core.sim import validation_reference_m
    from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.control import ControllerConfig, ValveController
    model = asymmetric()
    sim_config = replace(ValveSimConfig().ideal(), dynamics_enabled=False,
                         descending_envelope=(model.b0, model.b1))
    ref = validation_reference_m(1e-4, 8.0, 40.0)
    errors = {}
    for label, m in (("asymmetric", model), ("symmetric", PAPER_GPIM.model())):
        ctl = ValveController(ControllerConfig(strategy="ol_hc", dt=1e-4), CompensationModel(m))
        rec = run_closed_loop(SimulatedValve(sim_config), ctl, ref)
        errors[label] = np.abs(rec.position_m[1:] - ref[:-1]).max() * 1e6
    assert errors["asymmetric"] < 1e-6 and errors["symmetric"] > 1.0, errors


def test_the_turning_points_of_a_path_leave_the_operators_as_the_whole_path_does():
    """``InitialState`` keeps only where an input path turned: the states after it are the same, for a
    symmetric and an asymmetric GPIM."""
    from piezo_valve_ros.core.model import GPIM
    from piezo_valve_ros.core.identification import InitialState
    from piezo_valve_ros.core.model import turning_points
    g = PAPER_GPIM.model()
    asymmetric = GPIM(g.thresholds, g.weights, g.a0, g.a1, g.offset_um, 1.1, 0.3, 0.01)
    rng = np.random.default_rng(3)
    for _ in range(100):
        v = np.round(np.cumsum(rng.standard_normal(rng.integers(2, 300))) * 0.3 + 5.0, 1)
        path = turning_points(v)
        assert len(path) <= v.size
        for model in (g, asymmetric):
            assert np.allclose(model.state_after(v), model.state_after(path), atol=1e-12)
            assert np.allclose(InitialState("remanent", path[:-1]).states(model, v[-1:]), model.state_after(v),
                               atol=1e-12)
    with pytest.raises(ValueError):
        InitialState("remanent")
    with pytest.raises(ValueError):
        InitialState("rest", (1.0,))


def test_play_bounds_give_every_start_s_states_as_one_clamp():
    """A play bank's states from any start are that start clipped to (L, U) (clamps compose into one), for
    symmetric and for asymmetric drives: what a separate session's unknown start is estimated through."""
    from piezo_valve_ros.core.model import play_batch, play_bounds
    rng = np.random.default_rng(3)
    g = PAPER_GPIM.model()
    v = 5.0 + np.cumsum(rng.normal(0.0, 0.05, 4000))
    lower = g.ascending_envelope(v)
    for upper in (lower, lower + 0.3 + 0.05 * (v - 5.0)):
        L, U = play_bounds(lower, upper, g.thresholds)
        for _ in range(4):
            z0 = rng.uniform(lower[0] - g.thresholds, upper[0] + g.thresholds)
            states, _ = play_batch(lower, upper, g.thresholds, z0)
            assert np.array_equal(np.clip(z0, L, U), states)


@pytest.mark.parametrize("seed", range(12))
def test_play_batch_gives_the_same_bits_by_composed_clamps_and_by_the_compiled_recursion(seed, monkeypatch):
    """Long records run the recursion compiled (``KERNEL_MIN_WORK``), short ones the composed clamps: the same states
    and weighted sums bit for bit, with symmetric and crossing asymmetric drives, flat stretches and scaled
    thresholds, in blocks of any size; and so do the last contacts."""
    from piezo_valve_ros.core.model import hysteresis
    rng = np.random.default_rng(seed)
    N, n = int(rng.integers(50, 3000)), int(rng.integers(1, 30))
    v = np.cumsum(rng.standard_normal(N)) * 0.1
    if seed % 3 == 0:
        v = np.round(v, 1)
    r = np.sort(rng.uniform(0, 1, n))
    r[0] = 0.0
    upper = v if seed % 2 == 0 else v * 0.9 + rng.uniform(-0.5, 0.5) + 0.02 * rng.standard_normal(N)
    scale = None if seed % 4 else 1 + 0.3 * np.abs(np.sin(np.arange(N) / 50))
    z0, w = rng.uniform(-1, 1, n), rng.uniform(0, 1, n)
    for weights in (None, w):
        monkeypatch.setattr(hysteresis, "KERNEL_MIN_WORK", 10 ** 12)
        composed, composed_final = hysteresis.play_batch(v, upper, r, z0, weights, chunk=700, threshold_scale=scale)
        monkeypatch.setattr(hysteresis, "KERNEL_MIN_WORK", 0)
        compiled, compiled_final = hysteresis.play_batch(v, upper, r, z0, weights, chunk=700, threshold_scale=scale,
                                                         compiled=True)
        assert np.array_equal(composed, compiled) and np.array_equal(composed_final, compiled_final)
    # the contacts' scan, compiled and in numpy
    states = hysteresis.play_batch(v, upper, r, z0, threshold_scale=scale)[0]
    found = {}
    for work in (10 ** 12, 0):
        monkeypatch.setattr(hysteresis, "KERNEL_MIN_WORK", work)
        found[work] = hysteresis.last_contact(states, v, upper, r, scale, compiled=True)
    side_np, index_np = found[10 ** 12]
    side_nb, index_nb = found[0]
    assert side_np.dtype == side_nb.dtype and index_np.dtype == index_nb.dtype
    assert np.array_equal(side_np, side_nb) and np.array_equal(index_np, index_nb)
