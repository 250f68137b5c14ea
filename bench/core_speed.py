"""Per-sample controller cost (each strategy, inverse included), inverse GPIM step cost, batch GPIM speed and the
identification's filter banks.

Prints figures; compare as ratios within one run (the machine is shared).
    python bench/core_speed.py [--load] [--markdown docs/results/core_speed.md]

Models of the paper's size (15 operators) and of the largest size identification tries (135 operators, as
it may choose on a measured record).  ``--load`` repeats every figure with two busy loops running beside.
"""
import argparse
import contextlib
import time
import tracemalloc

import numpy as np

from piezo_valve_ros.core.control import CompensationModel
from piezo_valve_ros.core.control import BacklashModel
from piezo_valve_ros.core.model import hysteresis, iir
from piezo_valve_ros.core.model import GPIM, PAPER_GPIM
from piezo_valve_ros.core.model import hysteresis_inverse, hysteresis_stream
from piezo_valve_ros.core.sim import training_voltage
from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
from piezo_valve_ros.core.control import STRATEGIES, ControllerConfig, PIDGains, ValveController
from piezo_valve_ros.core.identification import CAPACITY_EXTENSION

from harness import Lines, busy_loops

print = Lines(timing=True)   # noqa: A001  (printed and kept for --markdown)


RATE_WIDENING_V = (-0.006, -0.37, 1.79, -0.028, 0.44, -1.25, 0.0, 0.0, 0.0)   # as identified on the simulated rate
# valve (its 5 ms filter's terms 0, as a file from before that filter reads)


def finer(model: GPIM, n: int) -> GPIM:
    """``model`` with ``n`` operators over the same threshold span and the same loop (weights spread)."""
    r = np.linspace(0.0, model.thresholds[-1], n)
    return GPIM(r, np.interp(r, model.thresholds, model.weights) * model.n / n, model.a0, model.a1, model.offset_um)


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
    print(f"controller step cost over {n} samples at 10 kHz (inverse GPIM included), best of 3:")
    rate_model = CompensationModel(rate_widening_v=RATE_WIDENING_V)
    large = CompensationModel(gpim=finer(PAPER_GPIM.model(), max(CAPACITY_EXTENSION)))
    cases = ([(s, CompensationModel(), "") for s in STRATEGIES]
             + [(s, rate_model, " rate") for s in ("ol_hc", "pid_hc")]
             + [(s, large, f" n={large.gpim.n}") for s in ("ol_hc", "pid_hc")]
             + [("ff_pid", CompensationModel(backlash=BacklashModel(0.5)), " backlash")])
    for s, model, label in cases:
        def loop():
            ctl = ValveController(ControllerConfig(strategy=s, gains=PIDGains(1.1987, 474.509)), model)
            step = ctl.step
            for r, y in zip(ref.tolist(), meas.tolist()):
                step(r, y)
        sec = best_of(loop)
        name = s + label
        print(f"  {name:14s} {sec / n * 1e6:6.2f} us/sample  (target < 15 us; max rate {n / sec / 1e3:5.1f} kHz)")


def controller_memory(n=50_000):
    """What the controller's step keeps and how high memory goes while it runs (tracemalloc, after a warm-up): the
    chain is folded into bound steps at reset, so a period allocates nothing that stays, and no buffer."""
    t = np.arange(n) * 1e-4
    ref = (40e-6 * np.sin(2 * np.pi * 5 * t)).tolist()
    meas = (SimulatedValve(ValveSimConfig()).run(5 + np.array(ref) * 1e6 / 13.5)).tolist()
    print(f"controller step memory over {n} samples at 10 kHz (tracemalloc, after 2000 steps' warm-up):")
    cases = [("pid_hc", CompensationModel(), ""), ("ff_pid_g", CompensationModel(dynamic_feedforward=True), " W"),
             ("ff_pid", CompensationModel(backlash=BacklashModel(0.5)), " backlash")]
    for s, model, label in cases:
        ctl = ValveController(ControllerConfig(strategy=s, gains=PIDGains(1.1987, 474.509)), model)
        step = ctl.step
        for r, y in zip(ref[:2000], meas[:2000]):
            step(r, y)
        tracemalloc.start()
        start, _ = tracemalloc.get_traced_memory()
        for r, y in zip(ref, meas):
            step(r, y)
        kept, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"  {s + label:18s} kept {kept - start:6d} B, peak {peak - start:6d} B above the start")


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
             "rate+cross": (crossing, RATE_WIDENING_V),
             f"n={max(CAPACITY_EXTENSION)}": (finer(m, max(CAPACITY_EXTENSION)), ())}
    walk = np.cumsum(np.random.default_rng(1).normal(0.0, 0.05, n))
    v = 5.0 + 4.5 * np.tanh((walk - walk.mean()) / (3.0 * walk.std()))
    print(f"inverse GPIM step (n=15 unless named), {n} samples, best of 3:")
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
    """The batch GPIM as the nodes' simulator and the tools run it (composed clamps in numpy), and as the
    identification runs it (``play_batch(compiled=True)``: the recursion compiled by numba)."""
    v = training_voltage(1e-4, 60.0, synchronise=False)  # 600,000 samples
    m = PAPER_GPIM.model()
    sec_batch = best_of(lambda: m.run(v))
    drive = m.a0 * v + m.a1

    def compiled(x):
        return hysteresis.play_batch(x, x, m.thresholds, m.virgin_state(float(v[0])), m.weights, compiled=True)

    sec_compiled = best_of(lambda: compiled(drive))

    def naive():
        r, p, z = m.thresholds, m.weights, m.virgin_state(v[0])
        out = np.empty(v.size)
        for k, x in enumerate(drive.tolist()):
            z = np.minimum(np.maximum(z, x - r), x + r)
            out[k] = p @ z
        return out
    sec_naive = best_of(naive, 1)
    y_fast, _ = m.run(v)
    assert np.max(np.abs(y_fast - (naive() + m.offset_um))) < 1e-9
    assert np.array_equal(compiled(drive)[0] + m.offset_um, y_fast)
    print(f"batch GPIM, 600,000 samples, n=15: {sec_batch:.3f} s (target < 0.2 s); "
          f"per-sample loop {sec_naive:.2f} s; speed-up x{sec_naive / sec_batch:.0f}; "
          f"compiled (the identification's) {sec_compiled:.3f} s")
    rng = np.random.default_rng(0)
    noisy = v + rng.normal(0, 0.01, v.size)
    sec_noisy = best_of(lambda: m.run(noisy), 1)
    sec_noisy_compiled = best_of(lambda: compiled(m.a0 * noisy + m.a1), 1)
    print(f"batch GPIM on a noisy command (every sample a reversal): {sec_noisy:.3f} s; "
          f"compiled {sec_noisy_compiled:.3f} s")


def filter_banks(n=125_000):
    """What the identification filters most (a 62.5 s record at its 2 kHz analysis rate): G (second order) on the
    design's rows, and creep's first-order lags of one signal; ``iir``'s kernels against scipy's lfilter."""
    from scipy import signal
    rng = np.random.default_rng(0)
    b, a = np.array([0.0, 0.0955, 0.0591]), np.array([1.0, -1.080, 0.2346])
    print(f"filter banks over {n} samples, ns per sample and filter (best of 3):")
    for k in (1, 4, 30, 90):
        rows = rng.standard_normal((k, n)).cumsum(axis=1)
        zi = np.zeros((k, 2))
        ours = best_of(lambda: iir.filter_rows(b, a, rows, zi)) / rows.size * 1e9
        theirs = best_of(lambda: signal.lfilter(b, a, rows, axis=1, zi=zi)) / rows.size * 1e9
        print(f"  G on {k:3d} rows     iir {ours:5.2f}   lfilter {theirs:5.2f}   x{theirs / ours:.1f}")
    # the GPIM's columns as a fit filters them: the operator states (N, n) as the play recursion leaves them, less
    # their first row, through G, out as rows; the columns kernel against the transposed copy and the rows kernel
    states = rng.standard_normal((n, 90)).cumsum(axis=0)
    zi = np.zeros((90, 2))
    ours = best_of(lambda: iir.filter_columns(b, a, states, states[0], zi)) / states.size * 1e9
    theirs = best_of(lambda: iir.filter_rows(b, a, np.ascontiguousarray((states - states[0]).T), zi)) / states.size * 1e9
    print(f"  G on  90 columns  iir {ours:5.2f}   copy+rows {theirs:5.2f}   x{theirs / ours:.1f}   (sample-major states)")
    x = rng.standard_normal(n).cumsum()
    poles = np.exp(-5e-4 / np.array([0.05, 0.15, 0.5, 1.5, 5.0, 15.0]))
    ours = best_of(lambda: iir.first_order_bank(x, poles, 1.0 - poles, x[0])) / (n * poles.size) * 1e9
    theirs = best_of(lambda: [signal.lfilter([0.0, 1.0 - p], [1.0, -p], x, zi=[x[0]]) for p in poles])
    theirs *= 1e9 / (n * poles.size)
    print(f"  6 creep lags      iir {ours:5.2f}   lfilter {theirs:5.2f}   x{theirs / ours:.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--load", action="store_true", help="also measure with two busy loops running beside")
    ap.add_argument("--markdown", metavar="FILE", help="also write what is printed here")
    args = ap.parse_args()
    runs = [("quiet", contextlib.nullcontext)] + ([("two busy loops beside", busy_loops)] if args.load else [])
    for title, context in runs:
        print(f"--- {title}")
        with context():
            controller_cost()
            controller_memory()
            inverse_cost()
            gpim_batch()
            filter_banks()
    if args.markdown:
        print.write_markdown(args.markdown, "bench/core_speed.py",
                             " (this shared 2-core machine; compare ratios within one run)")


if __name__ == "__main__":
    main()
