"""The control loop through ROS: where the time goes, real-time rates, lockstep speed, composed mode.

    python bench/realtime_loop.py                 # everything (about 3 min)
    python bench/realtime_loop.py --seconds 10 --json loop.json
    python bench/realtime_loop.py --conditions --only-conditions   # sections 6 and 7 alone
    python bench/realtime_loop.py --only-misses --seconds 10   # section 8 alone
    python bench/realtime_loop.py --conditions --json docs/results/realtime_loop.json \
        --markdown docs/results/realtime_loop.md   # the results page

Sections (figures from this run; the machine is shared, so compare them with each other):
  1. cost per period without DDS: hardware tick (sim backend + publishing) and controller callback
  2. DDS floor: plain Float64 ping-pong between two processes (EventsExecutor on both sides)
  3. real-time loop across processes (position -> controller -> command) at 500 Hz .. 5 kHz, the
     hardware sleeping or polling between ticks: achieved rate, share of periods whose command
     arrived within one period, latency p50/p99
  4. lockstep across processes: control steps per second
  5. composed mode (hardware and controller in one process) at the paper's 10 kHz in real time:
     polling, sleeping, and ticked by an rclpy timer
  6. (--conditions) 2 kHz across processes on a quiet and on a loaded computer (one pure-Python busy
     loop per CPU beside the rig), the two processes floating or pinned to their own CPUs, with the
     GIL switch interval at CPython's 5 ms or the nodes' 50 us
  7. (--conditions) the edge: composed 10 kHz and 5 kHz across processes, quiet and loaded, with the
     options the handbook recommends (quiet: polling; any: realtime.priority 50 with the processes pinned
     to their own CPUs, sleeping between ticks) and, for comparison, priority 50 floating
  8. (--conditions, or --only-misses) where the edge's missed periods go: the loop's thread traced
     (bench/loop_trace.py), each late tick given to garbage collection, the tick itself, node callbacks,
     a wake-up later than its timeout, or nothing the process saw

The hardware node runs in this process exactly as ``valve_hardware`` runs it (same executor, same
spin loop); the controller is a separate ``valve_controller`` process.  Latency is measured by the
hardware: from publishing ``spool_position`` to receiving the answering ``voltage_command``.
"""
from __future__ import annotations

import argparse
import json
from contextlib import contextmanager
from dataclasses import replace
import os
import subprocess
import sys
import time

import numpy as np

os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import rclpy
import rclpy.node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64

from piezo_valve_ros.ros import COMMAND_QOS, SENSOR_QOS, claim_pacing, make_executor, spin_loop
from piezo_valve_ros.runtime import ProcessGroup, node_command
from harness import Lines
from loop_trace import LoopTrace, attribute_misses

print = Lines(timing=True)   # noqa: A001  (printed and kept for --markdown)

ECHO = """
import sys, rclpy
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Float64
from piezo_valve_ros.ros import COMMAND_QOS, SENSOR_QOS, make_executor
rclpy.init()
node = rclpy.create_node("bench_echo")
pub = node.create_publisher(Float64, "voltage_command", COMMAND_QOS)
node.create_subscription(Float64, "spool_position", lambda m: pub.publish(Float64(data=m.data)), SENSOR_QOS)
ex = SingleThreadedExecutor() if sys.argv[1] == "single" else make_executor()
ex.add_node(node)
try:
    while rclpy.ok():
        ex.spin_once(timeout_sec=0.1)
except (KeyboardInterrupt, Exception):
    pass
finally:
    rclpy.try_shutdown()
"""


def env() -> dict:
    e = dict(os.environ)
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
    e["PYTHONPATH"] = root + os.pathsep + e.get("PYTHONPATH", "")
    return e


def spin_for(executor, seconds: float, until=None, pacing=None) -> None:
    """The nodes' own spin loop (ros.spin.spin_loop), for ``seconds`` or until ``until()``."""
    end = time.monotonic() + seconds
    spin_loop(executor, lambda: time.monotonic() < end and rclpy.ok() and not (until is not None and until()),
              pacing)


def context_switches() -> dict:
    """Voluntary / involuntary context switches of the calling thread so far (Linux; else empty)."""
    try:
        with open("/proc/thread-self/status") as f:
            return {k.split("_")[0]: int(v) for k, v in (line.split(":") for line in f if "ctxt_switches" in line)}
    except OSError:
        return {}


def wake_up_lateness(sleep_s: float = 8e-5, seconds: float = 2.0) -> dict:
    """How late a thread wakes from a short sleep, with the 1 us timer slack the hardware node sets."""
    from piezo_valve_ros.ros import tighten_timer_slack
    tighten_timer_slack()
    late = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        time.sleep(sleep_s)
        late.append(time.perf_counter() - t0 - sleep_s)
    a = np.asarray(late)
    return {"p50_us": float(np.percentile(a, 50) * 1e6), "p99_us": float(np.percentile(a, 99) * 1e6),
            "max_ms": float(a.max() * 1e3), "over_1ms": int(np.count_nonzero(a > 1e-3)), "sleeps": a.size}


def per_period_costs(n: int = 5000) -> dict:
    """Section 1: CPU per control period with no DDS partner (publishers have no subscriber)."""
    from piezo_valve_ros.nodes.controller import ValveControllerNode
    from piezo_valve_ros.nodes.hardware import ValveHardwareNode
    out = {}
    hw = ValveHardwareNode(parameter_overrides=[Parameter("clock", value="lockstep"),
                                                Parameter("control_period_s", value=1e-4)])
    t0 = time.perf_counter()
    for _ in range(n):
        hw.loop.apply_lockstep(5.0)
    out["hardware_lockstep_period_us"] = (time.perf_counter() - t0) / n * 1e6
    hw.backend.prepare_realtime()   # as a real-time hardware node does before its loop (the batch path's import)
    for period in (2e-3, 1e-3, 5e-4, 2e-4, 1e-4):
        k = int(round(period / hw.backend.sample_period_s))
        t0 = time.perf_counter()
        for _ in range(n // 5):
            hw.loop.publish(hw.backend.advance(k))
        out[f"hardware_realtime_tick_{int(1 / period)}hz_us"] = (time.perf_counter() - t0) / (n // 5) * 1e6
    flush = []
    for _ in range(50):
        hw.loop.collect(np.zeros((hw.settings.samples_batch - 1, 3)))
        t0 = time.perf_counter()
        hw.loop.collect(np.zeros((1, 3)))  # completes the batch: one samples message of 1000 rows goes out
        flush.append(time.perf_counter() - t0)
    out["hardware_samples_flush_1000_rows_us"] = float(np.median(flush) * 1e6)
    backend = hw.backend
    for label, below in (("per_sample", backend.per_sample_below), ("batch_path", 0)):
        backend.per_sample_below = below
        t0 = time.perf_counter()
        for _ in range(n // 5):
            backend.advance(2)
        out[f"sim_advance_2_samples_{label}_us"] = (time.perf_counter() - t0) / (n // 5) * 1e6
    backend.per_sample_below = type(backend).per_sample_below
    hw.destroy_node()
    ctl = ValveControllerNode(parameter_overrides=[Parameter("gain_set", value="pid_hc_5")])
    listener = rclpy.create_node("bench_listener")  # the controller steps only when its command has a reader
    listener.create_subscription(Float64, "voltage_command", lambda m: None, COMMAND_QOS)
    deadline = time.monotonic() + 10
    while not ctl.command_has_listener:
        if time.monotonic() > deadline:
            raise TimeoutError("the controller's command writer never matched a reader")
        time.sleep(0.01)
    msg = Float64(data=1e-6)
    t0 = time.perf_counter()
    for _ in range(n):
        ctl._on_position(msg)
    out["controller_callback_us"] = (time.perf_counter() - t0) / n * 1e6
    listener.destroy_node()
    ctl.destroy_node()
    return out


def ping_pong(seconds: float, executor_kind: str = "events") -> dict:
    """Section 2: DDS round trips between two processes, nothing else in the loop; both sides use
    EventsExecutor (what the nodes use) or SingleThreadedExecutor."""
    from rclpy.executors import SingleThreadedExecutor
    node = rclpy.create_node("bench_ping")
    lat = []
    state = {"t": 0.0}
    pub = node.create_publisher(Float64, "spool_position", SENSOR_QOS)

    def on_echo(_msg):
        now = time.perf_counter()
        lat.append(now - state["t"])
        state["t"] = time.perf_counter()
        pub.publish(Float64(data=1.0))
    node.create_subscription(Float64, "voltage_command", on_echo, COMMAND_QOS)
    executor = SingleThreadedExecutor() if executor_kind == "single" else make_executor()
    executor.add_node(node)
    with ProcessGroup() as procs:
        procs.start("echo", [sys.executable, "-c", ECHO, executor_kind], env=env())
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 or node.count_publishers("voltage_command") == 0:
            if time.monotonic() > deadline:
                raise TimeoutError("echo process did not come up")
            spin_for(executor, 0.05)
        while not lat:  # best effort: resend until the first echo comes back
            state["t"] = time.perf_counter()
            pub.publish(Float64(data=1.0))
            spin_for(executor, 0.05, until=lambda: bool(lat))
        spin_for(executor, 1.0)
        lat.clear()
        t0 = time.perf_counter()
        spin_for(executor, seconds)
        wall = time.perf_counter() - t0
        a = np.asarray(lat)
    executor.remove_node(node)
    node.destroy_node()
    executor.shutdown()
    return {"round_trips_per_s": a.size / wall, "p50_ms": float(np.percentile(a, 50) * 1e3),
            "p99_ms": float(np.percentile(a, 99) * 1e3)}


BUSY_LOOP = "import signal\nsignal.signal(signal.SIGINT, signal.SIG_DFL)\nwhile True:\n    pass\n"


@contextmanager
def busy_loops_beside(count: int):
    """``count`` pure-Python busy loops in processes of their own while the block runs (a loaded computer)."""
    with ProcessGroup() as load:
        for _ in range(count):
            load.start("load", [sys.executable, "-c", BUSY_LOOP], env=env())
        yield


def back_to_normal_scheduling() -> None:
    """Undo what a case's hardware node (in this process) asked for: any CPU, the normal scheduler, no wake-up
    latency request."""
    from piezo_valve_ros.runtime import available_cpus, pin, release_cpu_wakeup_latency
    release_cpu_wakeup_latency()
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setscheduler(int(tid), os.SCHED_OTHER, os.sched_param(0))
        except (ProcessLookupError, PermissionError):
            pass
    pin(sorted(set(range(os.cpu_count() or 1)) | available_cpus()))


def rig_loop(clock: str, period_s: float, seconds: float, composed: bool = False, tick: str = "loop",
             busy_poll_s: float = 0.0, switch_interval_s: float | None = None, priority: int = 0,
             hardware_cpus: list[int] | None = None, controller_cpus: list[int] | None = None,
             cpu_wakeup_latency_us: int = -1, trace: LoopTrace | None = None) -> dict:
    """Sections 3-8: the hardware node here, the controller in another process (or here, composed);
    ``priority``, ``*_cpus`` and ``cpu_wakeup_latency_us`` are the nodes' realtime.priority / realtime.cpus /
    realtime.cpu_wakeup_latency_us (its request withdrawn at the end: ``back_to_normal_scheduling``).  ``trace``
    (section 8) records what the loop's thread did in the measured time (``loop_trace``)."""
    from piezo_valve_ros.nodes.composed import build
    from piezo_valve_ros.nodes.hardware import ValveHardwareNode
    hw_params = {"clock": clock, "control_period_s": period_s, "command_timeout_s": 0.5,
                 "realtime.busy_poll_s": busy_poll_s}
    ctl_params = {"gain_set": "pid_hc_5", "control_period_s": period_s, "reference_ramp_s": 0.002}
    if switch_interval_s is not None:
        hw_params["realtime.switch_interval_s"] = ctl_params["realtime.switch_interval_s"] = switch_interval_s
    hw_params["realtime.priority"] = ctl_params["realtime.priority"] = priority
    hw_params["realtime.cpu_wakeup_latency_us"] = ctl_params["realtime.cpu_wakeup_latency_us"] = cpu_wakeup_latency_us
    if hardware_cpus:
        hw_params["realtime.cpus"] = hardware_cpus
    if controller_cpus:
        ctl_params["realtime.cpus"] = controller_cpus
    overrides = (lambda d: [Parameter(k, value=v) for k, v in d.items()])
    executor = make_executor()
    untrace = trace.time_callbacks_of(rclpy.node.Node) if trace is not None else (lambda: None)
    spun = trace.executor(executor) if trace is not None else executor
    try:
        with ProcessGroup() as procs:
            if composed:  # exactly what valve_composed runs (direct link on the real-time clock)
                nodes = list(build(overrides(hw_params), overrides(ctl_params)))
                hw = nodes[0]
            else:
                hw = ValveHardwareNode(parameter_overrides=overrides(hw_params))
                nodes = [hw]
                procs.start("valve_controller", node_command("valve_controller", ctl_params), env=env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            untrace()   # the nodes' callbacks are timed; nodes made later elsewhere are not
            for n in nodes:
                executor.add_node(n)
            pacing = claim_pacing(nodes) if tick == "loop" else None  # "timer": the node's rclpy timer ticks
            if trace is not None and pacing is not None:
                pacing = replace(pacing, tick=trace.tick(pacing.tick))
            spin_for(spun, 30.0, until=lambda: hw.loop_timing.answered > 0, pacing=pacing)
            if hw.loop_timing.answered == 0:
                raise TimeoutError("the controller never answered")
            spin_for(spun, 1.0, pacing=pacing)  # warm-up
            hw.loop_timing.reset()
            untrace_collections = trace.time_collections() if trace is not None else (lambda: None)
            try:
                if trace is not None:
                    trace.clear()
                cpu0 = time.process_time()
                switches0 = context_switches()
                spin_for(spun, seconds, pacing=pacing)
                switches = {k: v - switches0.get(k, 0) for k, v in context_switches().items()}
                cpu = time.process_time() - cpu0
            finally:
                untrace_collections()
            summary = hw.loop_timing.summary().as_dict()
            summary["cpu_share_of_hardware_process"] = cpu / max(summary["elapsed_s"], 1e-9)
            summary["loop_thread_context_switches"] = switches
            hw.shutdown_safely()
    finally:
        untrace()
    for n in nodes:
        executor.remove_node(n)
        n.destroy_node()
    executor.shutdown()
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=5.0, help="measured time per case [s]")
    ap.add_argument("--rates", default="500,1000,2000,5000", help="real-time rates across processes [Hz]")
    ap.add_argument("--repeats", type=int, default=3,
                    help="runs of each target case (2 kHz across processes, lockstep, composed 10 kHz)")
    ap.add_argument("--json", help="write all figures to this file")
    ap.add_argument("--markdown", metavar="FILE", help="also write what is printed here")
    ap.add_argument("--conditions", action="store_true", help="also run sections 6-8 (load, pinning, switch interval; the edge; where its missed periods go)")
    ap.add_argument("--only-conditions", action="store_true", help="run sections 6 and 7 alone")
    ap.add_argument("--only-misses", action="store_true", help="run section 8 alone (where the missed periods go)")
    args = ap.parse_args(argv)
    rclpy.init()
    results: dict = {}
    try:
        if args.only_conditions:
            results["conditions"] = conditions(args.seconds, args.repeats)
            results["edge"] = edge(args.seconds, args.repeats)
            return 0
        if args.only_misses:
            results["misses"] = misses(args.seconds, args.repeats)
            return 0
        print("1. cost per period in this process, no DDS partner:")
        costs = per_period_costs()
        results["costs_us"] = costs
        for k, v in costs.items():
            print(f"   {k:40s} {v:7.1f} us")

        w = wake_up_lateness()
        results["wake_up_lateness"] = w
        print(f"   waking from an 80 us sleep is late by p50 {w['p50_us']:.0f} us, p99 {w['p99_us']:.0f} us, "
              f"max {w['max_ms']:.2f} ms ({w['over_1ms']} of {w['sleeps']} sleeps > 1 ms)")

        print("\n2. DDS floor: Float64 ping-pong between two processes:")
        for kind, label in (("events", "EventsExecutor (the nodes')"), ("single", "SingleThreadedExecutor")):
            r = ping_pong(args.seconds, kind)
            results[f"ping_pong_{kind}"] = r
            print(f"   {label:28s} {r['round_trips_per_s']:7.0f} round trips/s, p50 {r['p50_ms']:.3f} ms, "
                  f"p99 {r['p99_ms']:.3f} ms")
        pp = results["ping_pong_events"]

        print("\n3. real-time loop across processes (hardware here, valve_controller in its own process);\n"
              "   hardware sleeping between ticks (realtime.busy_poll_s 0) / polling (busy_poll_s = period):")
        results["realtime"] = {}
        for rate in [float(x) for x in args.rates.split(",")]:
            for mode, busy in (("sleep", 0.0), ("poll", 1.0 / rate)):
                runs = [rig_loop("realtime", 1.0 / rate, args.seconds, busy_poll_s=busy)
                        for _ in range(args.repeats if rate == 2000 else 1)]
                results["realtime"][f"{int(rate)}_{mode}"] = runs
                for s in runs:
                    print(f"   {rate:6.0f} Hz {mode:5s}: achieved {s['achieved_rate_hz']:7.1f} Hz, in time "
                          f"{100 * s['in_time_share']:6.2f} %, unanswered {s['unanswered']}, latency p50 "
                          f"{s['latency_p50_s'] * 1e3:.3f} ms p99 {s['latency_p99_s'] * 1e3:.3f} ms, "
                          f"hardware process CPU {100 * s['cpu_share_of_hardware_process']:.0f} %")

        print("\n4. lockstep across processes (10 kHz sim time, one period per command):")
        results["lockstep"] = []
        for _ in range(args.repeats):
            s = rig_loop("lockstep", 1e-4, args.seconds)
            results["lockstep"].append(s)
            print(f"   {s['achieved_rate_hz']:7.0f} control steps/s (target >= 3000), round trip p50 "
                  f"{s['latency_p50_s'] * 1e3:.3f} ms p99 {s['latency_p99_s'] * 1e3:.3f} ms "
                  f"(DDS floor {pp['round_trips_per_s']:.0f}/s)")

        s = rig_loop("lockstep", 1e-4, args.seconds, composed=True)
        results["lockstep_composed"] = s
        print(f"   {s['achieved_rate_hz']:7.0f} control steps/s composed (both nodes in one process, loop on topics)")

        print("\n5. composed (both nodes in one process, valve_composed), real time at the paper's 10 kHz:")
        results["composed"] = {}
        cases = [("poll", "loop", 1e-4)] * args.repeats + [("sleep", "loop", 0.0), ("rclpy timer", "timer", 0.0)]
        for label, tick, busy in cases:
            s = rig_loop("realtime", 1e-4, args.seconds, composed=True, tick=tick, busy_poll_s=busy)
            results["composed"].setdefault(label, []).append(s)
            print(f"   {label:11s}: achieved {s['achieved_rate_hz']:7.1f} Hz, in time {100 * s['in_time_share']:6.2f} %, "
                  f"unanswered {s['unanswered']}, latency p50 {s['latency_p50_s'] * 1e3:.3f} ms p99 "
                  f"{s['latency_p99_s'] * 1e3:.3f} ms, interval p99 {s['interval_p99_s'] * 1e3:.3f} ms, "
                  f"CPU {100 * s['cpu_share_of_hardware_process']:.0f} %")
            sw = s["loop_thread_context_switches"]
            print(f"   {'':11s}  {s['stalls']} stalls > 0.2 ms (longest {s['longest_gap_s'] * 1e3:.2f} ms); loop thread "
                  f"context switches: voluntary {sw.get('voluntary', '?')}, involuntary {sw.get('nonvoluntary', '?')}")
        if args.conditions:
            results["conditions"] = conditions(args.seconds, args.repeats)
            results["edge"] = edge(args.seconds, args.repeats)
            results["misses"] = misses(args.seconds, args.repeats)
    finally:
        rclpy.try_shutdown()
        if args.json:
            with open(args.json, "w") as f:
                json.dump(results, f, indent=2)
        if args.markdown:
            print.write_markdown(args.markdown, "bench/realtime_loop.py",
                                 " (this shared 2-core machine; compare figures within one run)")
    return 0


def conditions(seconds: float, repeats: int) -> list[dict]:
    """Section 6: the 2 kHz loop across processes, quiet or loaded, floating or pinned (realtime.cpus),
    GIL switch interval 5 ms or 50 us, normal scheduler or SCHED_FIFO (realtime.priority)."""
    cpus = sorted(os.sched_getaffinity(0))
    print(f"\n6. 2 kHz across processes on {len(cpus)} CPUs, hardware sleeping between ticks: quiet / loaded (one "
          "busy loop per CPU beside),\n   floating / pinned (realtime.cpus: hardware [%d], controller [%d]), GIL "
          "switch interval 5 ms / 50 us, normal scheduler / realtime.priority 50:" % (cpus[0], cpus[-1]))
    plan = [(loaded, pinned, interval, 0) for loaded in (False, True) for pinned in (False, True)
            for interval in (5e-3, 5e-5)] + [(True, pinned, 5e-5, 50) for pinned in (False, True)]
    out = []
    for loaded in (False, True):
        with busy_loops_beside(len(cpus) if loaded else 0):
            for _, pinned, interval, priority in [c for c in plan if c[0] == loaded]:
                for _ in range(repeats):
                    try:
                        s = rig_loop("realtime", 5e-4, seconds, switch_interval_s=interval, priority=priority,
                                     hardware_cpus=[cpus[0]] if pinned else None,
                                     controller_cpus=[cpus[-1]] if pinned else None)
                    except ValueError as exc:  # e.g. no permission for SCHED_FIFO here
                        print(f"   {'loaded' if loaded else 'quiet':6s} priority {priority}: not run: {exc}")
                        break
                    finally:
                        back_to_normal_scheduling()
                    out.append({"loaded": loaded, "pinned": pinned, "switch_interval_s": interval,
                                "priority": priority, **s})
                    print(f"   {'loaded' if loaded else 'quiet ':6s} {'pinned  ' if pinned else 'floating'} "
                          f"{interval * 1e6:5.0f} us {'FIFO 50' if priority else 'normal ':7s}: in time "
                          f"{100 * s['in_time_share']:6.2f} %, achieved {s['achieved_rate_hz']:7.1f} Hz, latency "
                          f"p50 {s['latency_p50_s'] * 1e3:.3f} ms p99 {s['latency_p99_s'] * 1e3:.3f} ms", flush=True)
    return out


EDGE_TARGETS = {"composed 10 kHz": 0.995, "5 kHz across processes": 0.99}   # share of commands in time (issue 35)


def edge_run(period_s: float, seconds: float, composed: bool, priority: int, pinned: bool,
             cpu_wakeup_latency_us: int = -1, trace: LoopTrace | None = None) -> dict:
    """One run at the edge (sections 7 and 8) with the handbook's options: polling on the normal scheduler, or at
    ``priority`` sleeping between ticks; ``pinned``: composed on the first CPU, across processes the hardware on
    the first and the controller on the last.  ValueError where an option is not permitted here."""
    cpus = sorted(os.sched_getaffinity(0))
    try:
        return rig_loop("realtime", period_s, seconds, composed=composed, busy_poll_s=0.0 if priority else period_s,
                        priority=priority, hardware_cpus=[cpus[0]] if pinned else None,
                        controller_cpus=([cpus[0]] if composed else [cpus[-1]]) if pinned else None,
                        cpu_wakeup_latency_us=cpu_wakeup_latency_us, trace=trace)
    finally:
        back_to_normal_scheduling()


def edge(seconds: float, repeats: int) -> list[dict]:
    """Section 7: composed 10 kHz and 5 kHz across processes, quiet and loaded (one busy loop per CPU), polling
    on the normal scheduler, or at realtime.priority 50 sleeping between ticks, pinned (composed: one CPU;
    across: the hardware on the first, the controller on the last) or floating; quiet, also with the idle CPUs
    kept awake (realtime.cpu_wakeup_latency_us 0, "awake")."""
    cpus = sorted(os.sched_getaffinity(0))
    print(f"\n7. the edge on {len(cpus)} CPUs (targets: composed 10 kHz {100 * EDGE_TARGETS['composed 10 kHz']:.1f} % "
          f"in time, 5 kHz across processes {100 * EDGE_TARGETS['5 kHz across processes']:.0f} %), quiet / loaded "
          "(one busy loop per CPU beside):")
    # (label, priority, pinned, realtime.cpu_wakeup_latency_us): 0 keeps idle CPUs polling (quiet only: the busy
    # loops of a loaded computer keep them awake already)
    options = [("poll, normal", 0, False, -1), ("FIFO 50, pinned", 50, True, -1), ("FIFO 50, floating", 50, False, -1),
               ("poll, normal, awake", 0, False, 0), ("FIFO 50, pinned, awake", 50, True, 0)]
    out = []
    for loaded in (False, True):
        with busy_loops_beside(len(cpus) if loaded else 0):
            for case, period, composed in (("composed 10 kHz", 1e-4, True), ("5 kHz across processes", 2e-4, False)):
                for label, priority, pinned, wakeup_us in options:
                    if loaded and (not priority or wakeup_us >= 0):
                        continue   # the normal scheduler gives a loop a slice now and then (section 6)
                    shares = []
                    for _ in range(repeats):
                        try:
                            s = edge_run(period, seconds, composed, priority, pinned, wakeup_us)
                        except ValueError as exc:  # e.g. no permission for SCHED_FIFO or the PM QoS file here
                            print(f"   {case} {label}: not run: {exc}")
                            break
                        shares.append(s["in_time_share"])
                        out.append({"case": case, "loaded": loaded, "options": label, **s})
                    if shares:
                        met = sum(x >= EDGE_TARGETS[case] for x in shares)
                        print(f"   {case:22s} {'loaded' if loaded else 'quiet ':6s} {label:23s}: in time "
                              + " / ".join(f"{100 * x:6.2f}" for x in shares)
                              + f" %  ({met} of {len(shares)} runs at the target)", flush=True)
    return out


def misses(seconds: float, repeats: int) -> list[dict]:
    """Section 8: where the edge's missed periods go (``loop_trace``): composed 10 kHz quiet polling, and composed
    10 kHz and 5 kHz across processes loaded at priority 50 pinned, each run traced."""
    cpus = sorted(os.sched_getaffinity(0))
    print("\n8. where the missed periods go (the loop's thread traced: bench/loop_trace.py; a traced run costs ~1 us "
          "per tick more):\n   each gap between ticks over 1.5 periods, its periods given to what filled the time "
          "after the tick was due")
    cases = [("composed 10 kHz", 1e-4, True, False, 0), ("composed 10 kHz", 1e-4, True, True, 50),
             ("5 kHz across processes", 2e-4, False, True, 50)]
    out = []
    for case, period, composed, loaded, priority in cases:
        label = f"{case:22s} {'loaded' if loaded else 'quiet ':6s} {'FIFO 50, pinned' if priority else 'poll, normal'}"
        with busy_loops_beside(len(cpus) if loaded else 0):
            for _ in range(repeats):
                trace = LoopTrace()
                try:
                    s = edge_run(period, seconds, composed, priority, pinned=bool(priority), trace=trace)
                except ValueError as exc:  # e.g. no permission for SCHED_FIFO here
                    print(f"   {label}: not run: {exc}")
                    break
                m = attribute_misses(trace, period)
                due = int(s["elapsed_s"] / period + 0.5) + 1
                out.append({"case": case, "loaded": loaded, "priority": priority, **s,
                            "missed_periods": m.periods, "missed_excess_s": m.excess_s,
                            "missed_to_callbacks": m.by_callback})
                print(f"   {label}: in time {100 * s['in_time_share']:6.2f} %, {due - s['periods']} periods short, "
                      f"{s['answered'] - s['in_time']} answers later than a period;\n      traced: {m.line()}",
                      flush=True)
    return out

if __name__ == "__main__":
    sys.exit(main())
