"""Per-sample controller cost (each strategy, inverse included), inverse GPIM step cost and batch GPIM speed.

Prints figures; compare as ratios within one run (the machine is shared).
    python bench/core_speed.py
"""
import time

import numpy as np

from piezo_valve_ros.core.control.compensation import CompensationModel
from piezo_valve_ros.core.model.hysteresis import GPIM, PAPER_GPIM
from piezo_valve_ros.core.model.rate_dependence import hysteresis_inverse, hysteresis_stream
from piezo_valve_ros.core.sim.signals import training_voltage
from piezo_valve_ros.core.sim.simulator import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control.strategies import STRATEGIES, ControllerConfig, PIDGains, ValveController


RATE_WIDENING_V = (-0.006, -0.37, 1.79, -0.028, 0.44, -1.25)   # as identified on the simulated rate valve


def best_of(fn, repeats=3):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def controller_cost(n=50_000):
    t = np.arange(n) * 1e-4
    ref = 40e-6 * np.sin(2 * np.pi * 5 * t)
    meas = SimulatedValve(ValveSimConfig()).run(5 + ref * 1e6 / 13.5)
    print(f"controller step cost over {n} samples at 10 kHz (inverse GPIM n=15 included), best of 3:")
    rate_model = CompensationModel(rate_widening_v=RATE_WIDENING_V)
    cases = [(s, CompensationModel()) for s in STRATEGIES] + [(s, rate_model) for s in ("ol_hc", "pid_hc")]
    for s, model in cases:
        def loop():
            ctl = ValveController(ControllerConfig(strategy=s, gains=PIDGains(1.1987, 474.509)), model)
            step = ctl.step
            for r, y in zip(ref.tolist(), meas.tolist()):
                step(r, y)
        sec = best_of(loop)
        name = s + (" rate" if model is rate_model else "")
        print(f"  {name:14s} {sec / n * 1e6:6.2f} us/sample  (target < 20 us; max rate {n / sec / 1e3:5.1f} kHz)")


def inverse_cost(n=20_000, dt=5e-4):
    """One inverse step: symmetric (closed form), asymmetric with a dead band (closed form), with envelopes
    that cross and with rate-dependent thresholds (solved each step, usually on one envelope in closed form),
    in the same run; a random walk of the input at ``dt``."""
    m = PAPER_GPIM.model()
    crossing = GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, 0.95, 0.2)
    cases = {"symmetric": (m, ()),
             "dead band": (GPIM(m.thresholds, m.weights, m.a0, m.a1, m.offset_um, m.a0 * 1.03, m.a1 + 0.08), ()),
             "crossing": (crossing, ()),
             "rate": (m, RATE_WIDENING_V),
             "rate+cross": (crossing, RATE_WIDENING_V)}
    walk = np.cumsum(np.random.default_rng(1).normal(0.0, 0.05, n))
    v = 5.0 + 4.5 * np.tanh((walk - walk.mean()) / (3.0 * walk.std()))
    print(f"inverse GPIM step (n=15), {n} samples, best of 3:")
    base = None
    for name, (model, widening) in cases.items():
        forward = hysteresis_stream(model, widening, dt, 5.0)
        y = [forward.step(x) for x in v.tolist()]

        def loop():
            step = hysteresis_inverse(model, widening, dt, v0=5.0).step
            for x in y:
                step(x)
        sec = best_of(loop) / n
        base = base or sec
        kind = type(hysteresis_inverse(model, widening, dt)).__name__
        print(f"  {name:10s} {kind:24s} {sec * 1e6:7.2f} us/step  x{sec / base:.1f}")


def gpim_batch():
    v = training_voltage(1e-4, 60.0, synchronise=False)  # 600,000 samples
    m = PAPER_GPIM.model()
    sec_batch = best_of(lambda: m.run(v))
    def naive():
        r, p, z = m.thresholds, m.weights, m.virgin_state(v[0])
        out = np.empty(v.size)
        for k, x in enumerate((m.a0 * v + m.a1).tolist()):
            z = np.minimum(np.maximum(z, x - r), x + r)
            out[k] = p @ z
        return out
    sec_naive = best_of(naive, 1)
    y_fast, _ = m.run(v)
    assert np.max(np.abs(y_fast - (naive() + m.offset_um))) < 1e-9
    print(f"batch GPIM, 600,000 samples, n=15: {sec_batch:.3f} s (target < 0.2 s); "
          f"per-sample loop {sec_naive:.2f} s; speed-up x{sec_naive / sec_batch:.0f}")
    rng = np.random.default_rng(0)
    noisy = v + rng.normal(0, 0.01, v.size)
    sec_noisy = best_of(lambda: m.run(noisy), 1)
    print(f"batch GPIM on a noisy command (every sample a reversal): {sec_noisy:.3f} s")


if __name__ == "__main__":
    controller_cost()
    inverse_cost()
    gpim_batch()
