"""Issue 11.2: the rate-dependent GPIM (thresholds that widen with the input rate) and its exact inverse, in the
controller too (with model swaps that keep the valve's memory)."""
from dataclasses import replace

import numpy as np
import pytest

from piezo_valve_ros.core.control import CompensationModel
from piezo_valve_ros.core.model import GPIM, PAPER_GPIM, PlayOperatorBank, play_batch
from piezo_valve_ros.core.model import (RateDependentGPIMStream, RateDependentInverseGPIM, RateWidening,
                                        hysteresis_inverse, rate_terms, swap_inverse)
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import ControllerConfig, ValveController, gain_set

DT = 5e-4
PAPER = PAPER_GPIM.model()
MODELS = {
    "symmetric": PAPER,
    "dead band": GPIM(PAPER.thresholds, PAPER.weights, PAPER.a0, PAPER.a1, PAPER.offset_um, PAPER.a0 * 1.02,
                      PAPER.a1 + 0.1),
    "crossing": GPIM(PAPER.thresholds, PAPER.weights, PAPER.a0, PAPER.a1, PAPER.offset_um, PAPER.a0 * 1.05,
                     PAPER.a1 - 0.2, -0.002),
}
WIDENINGS = {"widens": (2.0, 1.0, 0.5, 1.0, 0.3, -0.5, 0.4, 0.0, 0.2), "narrows": (-1.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0),
             "mixed": (-0.006, -0.37, 1.79, -0.028, 0.44, -1.25, 0.0, 0.0, 0.0)}   # the last as identified on the
                                                                                   # rate valve (before the 5 ms filter)


def _demand(model: GPIM, n: int, seed: int) -> np.ndarray:
    """Long random admissible demand [um]: two beating sines and a random walk inside the output range."""
    rng = np.random.default_rng(seed)
    lo, hi = model.output_range()
    t = np.arange(n) * DT
    walk = np.cumsum(rng.normal(0.0, 0.01, n))
    y = 0.5 * (lo + hi) + 0.4 * (hi - lo) * np.sin(2 * np.pi * 3 * t) * np.sin(2 * np.pi * 0.37 * t) + walk
    return np.clip(y, lo + 1.0, hi - 1.0)


def test_rate_terms_batch_equals_the_stream_and_are_causal():
    rng = np.random.default_rng(0)
    v = 5.0 + np.cumsum(rng.normal(0, 0.05, 5000))
    c = np.array(WIDENINGS["mixed"])
    batch = rate_terms(v, DT, v_before=5.0) @ c
    stream = RateWidening(c, DT, 5.0)
    w = np.empty(v.size)
    for k, x in enumerate(v):
        w[k] = stream.value
        stream.advance(x)
    np.testing.assert_allclose(w, batch, atol=1e-12)
    changed = v.copy()
    changed[3000:] += 1.0     # a change at sample 3000 shows from sample 3001 on: known before the input is chosen
    after = rate_terms(changed, DT, v_before=5.0) @ c
    assert np.array_equal(after[:3001], batch[:3001]) and after[3001] != batch[3001]


def test_play_batch_follows_thresholds_that_narrow_until_the_bounds_cross():
    """While an operator's bounds cross (L - w - r > U + w + r) the upper one wins and its state forgets the
    past; the batch scan must restart after such a stretch (it once kept the state from before it)."""
    rng = np.random.default_rng(3)
    n = 6000
    v = 5.0 + 3.0 * np.sin(np.arange(n) * 0.003) + np.cumsum(rng.normal(0, 0.01, n))
    w = -0.42 + 0.05 * np.sin(np.arange(n) * 0.05)      # r_1 + w changes sign again and again
    lower, upper = PAPER.ascending_envelope(v) - w, PAPER.ascending_envelope(v) + w
    bank = PlayOperatorBank(PAPER.thresholds, PAPER.virgin_state(v[0]))
    stepped = np.array([bank.step(a, b).copy() for a, b in zip(lower, upper)])
    states, final = play_batch(lower, upper, PAPER.thresholds, PAPER.virgin_state(v[0]))
    assert np.max(np.abs(states - stepped)) < 1e-12 and np.array_equal(final, stepped[-1])


@pytest.mark.parametrize("widening", list(WIDENINGS))
@pytest.mark.parametrize("name", list(MODELS))
def test_forward_of_the_rate_dependent_inverse_is_the_demand(name, widening):
    """forward(inverse(y)) = y to 1e-9 um over a long random admissible demand, through a reset and a parameter
    update (another GPIM and other rate coefficients) mid-run; the forward model is run independently (batch
    play operators and rate terms over the first stretch, a streaming model after each change)."""
    model, c = MODELS[name], WIDENINGS[widening]
    n, reset_at, update_at = 24000, 9000, 16000
    y = _demand(model, n, seed=len(name) + len(widening))
    inv = hysteresis_inverse(model, c, DT, v0=5.0)
    assert isinstance(inv, RateDependentInverseGPIM)
    v = np.empty(n)
    forward = RateDependentGPIMStream(model, c, DT, 5.0)
    out = np.empty(n)
    refit = GPIM(model.thresholds * 1.01, model.weights * 0.98, model.a0, model.a1, model.offset_um + 0.5,
                 model.b0, model.b1, model.b2)
    c_refit = tuple(0.8 * x for x in c)
    for k in range(n):
        if k == reset_at:
            inv.reset(v[k - 1])
            forward = RateDependentGPIMStream(model, c, DT, v[k - 1])
        if k == update_at:
            inv = swap_inverse(inv, refit, c_refit, DT, v[k - 1])
            forward = RateDependentGPIMStream(refit, c_refit, DT, v[k - 1])
            forward.bank.state[:] = inv.forward_state()
            forward.rate.set_state(inv.rate.state())
        v[k] = inv.step(y[k])
        out[k] = forward.step(v[k])
    inside = (v > 0.0) & (v < 10.0)    # a demand beyond the reachable output gives the range's end
    assert inside.mean() > 0.6
    assert np.max(np.abs(out - y)[inside]) <= 1e-9
    # the first stretch through the batch forward model (play_batch with the rate terms): the same
    w = rate_terms(v[:reset_at], DT, v_before=5.0) @ np.array(c)
    h, _ = play_batch(model.ascending_envelope(v[:reset_at]) - w, model.descending_envelope(v[:reset_at]) + w,
                      model.thresholds, model.virgin_state(5.0), model.weights)
    assert np.max(np.abs(h + model.offset_um - y[:reset_at])[inside[:reset_at]]) <= 1e-9


def test_every_step_is_exact_for_widenings_that_jump_about():
    """Fuzz the step solver: each step under its own widening (drawn from -1..2 V, so bands that narrow, widen,
    cross and uncross between steps, as they do when the widening comes from another inverse), random
    demands near and far; the forward model from the state before the step gives back the demand."""
    from types import SimpleNamespace
    rng = np.random.default_rng(7)
    for name, model in MODELS.items():
        leader = SimpleNamespace(applied_widening_v=0.0)
        inv = RateDependentInverseGPIM(model, WIDENINGS["widens"], DT, v0=5.0, follow=leader)
        lo, hi = model.output_range()
        y, worst = 0.5 * (lo + hi), 0.0
        for k in range(4000):
            leader.applied_widening_v = float(rng.uniform(-1.0, 2.0)) if rng.random() < 0.5 else \
                leader.applied_widening_v + float(rng.normal(0.0, 0.01))
            y = float(np.clip(y + rng.normal(0.0, 0.3 if rng.random() < 0.8 else 20.0), lo + 2.0, hi - 2.0))
            z, r = inv.forward_state(), model.thresholds + leader.applied_widening_v
            v = inv.step(y)
            z = np.minimum(np.maximum(z, model.ascending_envelope(v) - r), model.descending_envelope(v) + r)
            if 0.0 < v < 10.0:
                worst = max(worst, abs(float(model.weights @ z) + model.offset_um - y))
        assert worst <= 1e-9, (name, worst)


def test_a_follower_predicts_the_output_it_just_produced():
    """Between steps a follower keeps the widening it was given: peek_forward at its last input gives back the
    demand it just met (the controller's bumpless transfer into PID HC reads it), not a value under a widening
    computed from its own outputs."""
    from types import SimpleNamespace
    leader = SimpleNamespace(applied_widening_v=0.8)
    inv = RateDependentInverseGPIM(PAPER, WIDENINGS["narrows"], DT, v0=5.0, follow=leader)   # its own: narrower
    y = _demand(PAPER, 400, seed=3)
    for k in range(y.size):
        leader.applied_widening_v = 0.8 + 0.3 * np.sin(0.05 * k)
        v = inv.step(y[k])
        assert abs(inv.peek_forward(v) - y[k]) < 1e-9, k


def test_without_widening_the_closed_form_inverse_is_kept():
    assert not isinstance(hysteresis_inverse(PAPER, (0.0,) * 9, DT), RateDependentInverseGPIM)
    assert not isinstance(hysteresis_inverse(PAPER, (), DT), RateDependentInverseGPIM)


RATE_MODEL = CompensationModel(PAPER, rate_widening_v=WIDENINGS["mixed"])


@pytest.mark.parametrize("strategy", ["ol_hc", "pid_hc", "ff_pid"])
def test_a_rate_dependent_model_swap_keeps_the_valves_memory(strategy):
    """Issue 11.4 with the rate-dependent model: the same model swapped in mid-run changes nothing (operator
    states and rate history carried), a refit with other coefficients moves the command by < 0.01 V."""
    config = ControllerConfig(strategy=strategy, dt=DT, gains=gain_set(f"{strategy}_5")[1] if strategy != "ol_hc"
                              else gain_set("pid_hc_1")[1])
    sim_config = replace(ValveSimConfig(dt=DT).ideal())
    n, swap = 6000, 3000
    t = np.arange(n) * DT
    ref = 40e-6 * np.sin(2 * np.pi * 2.0 * t) + 5e-6 * np.sin(2 * np.pi * 7.0 * t)

    def run(new_model, same=False):
        ctl, sim = ValveController(config, RATE_MODEL), SimulatedValve(sim_config)
        v, y = np.empty(n), sim.step(sim_config.initial_voltage_v)
        for k in range(n):
            if k == swap and new_model is not None:
                before = ctl.ff_inverse.peek_forward(ctl._last_ff_v)
                before_loop = ctl.loop_inverse.peek_forward(ctl.last_command_v)
                ctl.set_model(new_model)
                if same:   # the same model predicts the same output from the carried state (the in-loop inverse
                    # too: a follower keeps the widening it was given, its own outputs' rate is never used)
                    assert abs(ctl.ff_inverse.peek_forward(ctl._last_ff_v) - before) < 1e-9
                    assert abs(ctl.loop_inverse.peek_forward(ctl.last_command_v) - before_loop) < 1e-9
            v[k] = ctl.step(ref[k], y)
            y = sim.step(v[k])
        return v, ctl

    plain, _ = run(None)
    same, ctl = run(RATE_MODEL, same=True)
    np.testing.assert_allclose(same, plain, atol=1e-9)
    assert ctl.loop_inverse.follow is ctl.ff_inverse    # the in-loop inverse takes the feedforward's widening
    g = RATE_MODEL.gpim
    refit, _ = run(replace(RATE_MODEL, gpim=GPIM(g.thresholds, 1.02 * g.weights, g.a0, g.a1, g.offset_um + 0.3),
                           rate_widening_v=tuple(0.9 * x for x in WIDENINGS["mixed"])))
    # the command's step at the swap, beyond the step the demand's motion makes anyway
    assert abs((refit[swap] - refit[swap - 1]) - (plain[swap] - plain[swap - 1])) < 0.01
    # and back to a model without rate dependence (closed-form inverse, states made consistent with it)
    plain_model, _ = run(CompensationModel(PAPER))
    assert abs((plain_model[swap] - plain_model[swap - 1]) - (plain[swap] - plain[swap - 1])) < 0.01


def test_pid_hc_with_the_rate_dependent_model_is_not_misled_by_sensor_noise():
    """The in-loop inverse follows the feedforward's widening (the demand's cycling rate): with its own, the
    noisy feedback command's |dv/dt| widened the thresholds and PID HC's error doubled."""
    sim_config = ValveSimConfig(dt=DT)
    t = np.arange(8000) * DT
    ref = 40e-6 * np.sin(2 * np.pi * 2.0 * t)
    errors = {}
    for label, model in (("plain", CompensationModel(PAPER)), ("rate", RATE_MODEL)):
        ctl = ValveController(ControllerConfig(strategy="pid_hc", dt=DT, gains=gain_set("pid_hc_5")[1]), model)
        sim = SimulatedValve(sim_config)
        y, err = sim.step(sim_config.initial_voltage_v), []
        for k in range(t.size):
            y_next = sim.step(ctl.step(ref[k], y))
            err.append(y_next - ref[k])     # the position the command of period k produced
            y = y_next
        errors[label] = float(np.sqrt(np.mean(np.square(err[2000:]))))
    assert errors["rate"] <= 1.1 * errors["plain"], errors
