"""``valve_rig``: one command brings up a simulated rig (hardware + controller) and runs a demo.

    valve_rig                       # separate processes, lockstep, PID HC 5, the paper's three steps
    valve_rig --gain-set ff_pid_1   # another Table 1 set
    valve_rig --composed            # both nodes in this process (fastest loop)
    valve_rig --composed --clock realtime --demo none   # the paper's 10 kHz loop on the wall clock
    valve_rig --demo none           # just run the rig until Ctrl-C / SIGTERM
    valve_rig --demo none --monitor # and valve_monitor beside it (the valve's health on /diagnostics)

Every process it starts is stopped on exit (Ctrl-C, SIGTERM, error): SIGINT, then SIGTERM, then
SIGKILL, each after a grace period.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Optional

import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter

from ..core.blas import one_blas_thread_for_process
from ..core.errors import PiezoValveError
from ..core.validation import same_period
from ..runtime.dds import use_fast_acknowledgements
from ..core.metrics import step_metrics
from ..core.sim.signals import PAPER_STEPS_UM
from ..core.control.strategies import NO_SAFE_SET_STRATEGY, default_gain_set
from ..core.sim.simulator import ValveSimConfig
from ..runtime.processes import ProcessGroup, node_command
from ..rig.client import RigClient, run_in_background
from ..ros import close


# ---------------------------------------------------------------------------- demo


def step_demo(client: RigClient, dt: float, hold_periods: int, after_periods: int,
              steps=PAPER_STEPS_UM) -> list[tuple[float, float, float, float]]:
    """The paper's step tests through the ROS graph; returns (start, end, settling s, overshoot %)."""
    out = []
    client.run_periods(1)  # apply the held first command; the rig is live
    for start_um, end_um in steps:
        client.set_reference(start_um * 1e-6)
        client.run_periods(hold_periods)
        client.set_reference(end_um * 1e-6)
        rows = client.run_periods(after_periods)
        # rows[0] applies the command computed before the new reference; the ramp starts at rows[1]
        m = step_metrics(rows[:, 2], 1, start_um, end_um, dt)
        out.append((start_um, end_um, m.settling_time_s, m.overshoot_pct))
    return out


# ---------------------------------------------------------------------------- main
def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="valve_rig", description="A piezo-valve rig (simulated, or your backend) "
                                 "with a demonstration.")
    ap.add_argument("--gain-set", help="Table 1 gain set, e.g. ff_pid_g_2 (default: the fastest PID HC set whose "
                    "margins hold at the control period: pid_hc_5 at the paper's 0.1 ms, pid_hc_2 at 1 ms; beyond "
                    "2 ms none is safe and the rig runs ol_hc)")
    ap.add_argument("--strategy", help="strategy without Table 1 gains: ol or ol_hc")
    ap.add_argument("--clock", choices=("lockstep", "realtime"), default="lockstep")
    ap.add_argument("--control-period-s", type=float, default=1e-4,
                    help="control period [s] (default 1e-4 = the paper's 10 kHz; realtime across processes: 5e-4 "
                         "(2 kHz) or longer, composed: 1e-4 works)")
    ap.add_argument("--composed", action="store_true", help="hardware and controller in this process")
    ap.add_argument("--busy-poll-s", type=float,
                    help="realtime: the hardware polls instead of sleeping this long before each tick [s] "
                         "(default: all the time at periods under 1 ms, which costs a core; sleep at 1 ms and longer "
                         "and with --priority; 0 = sleep)")
    ap.add_argument("--priority", type=int, default=0, metavar="N",
                    help="realtime: run hardware and controller at SCHED_FIFO priority N (1..98; needs the "
                         "permission, see README); the hardware then sleeps between ticks")
    ap.add_argument("--pin", action="store_true",
                    help="realtime: hardware on the first CPU, controller on the last (realtime.cpus)")
    ap.add_argument("--cpu-wakeup-latency-us", type=int, metavar="US",
                    help="realtime: idle CPUs wake within US microseconds while the rig runs, 0 = they poll instead "
                         "of sleeping (realtime.cpu_wakeup_latency_us; needs write access to /dev/cpu_dma_latency)")
    ap.add_argument("--lockstep-speed", type=float, metavar="X",
                    help="lockstep: the valve's time runs at most X times as fast as the wall clock (default: as fast "
                         "as the loop goes, which keeps two cores busy; 1 = the wall clock's pace)")
    ap.add_argument("--demo", choices=("steps", "none"), default="steps")
    ap.add_argument("--hold-s", type=float, default=0.1, help="hold before and after each step [s]")
    ap.add_argument("--sim-seed", type=int, default=0)
    ap.add_argument("--identify", metavar="PLAN",
                    help="also start valve_identification with this plan (e.g. validate,train,refit,validate) "
                         "and stop the rig when it is done (exit 1 if it failed); needs --demo none")
    ap.add_argument("--bag-dir", default="identification_runs", help="where --identify writes its bags")
    ap.add_argument("--monitor", action="store_true", help="also start valve_monitor (the valve's health on "
                    "/diagnostics, see the monitor handbook)")
    ap.add_argument("--namespace", default="", help="put the rig's nodes and topics in this namespace (e.g. /valve1)")
    ap.add_argument("--backend", default="sim", help="the hardware node's backend: sim (default) or an installed one "
                    "(entry-point group piezo_valve_ros.backends); the step demo needs one that runs in lockstep")
    ap.add_argument("--params-file", metavar="FILE", help="a ROS parameters file with sections for valve_hardware, "
                    "valve_controller (and valve_identification): its values replace the rig's defaults; options "
                    "given on this command line replace its values")
    return ap


def parse_args(argv=None):
    return _parser().parse_args(argv)


def given_options(argv) -> set[str]:
    """The options (by dest) the command line gives, whatever their value: argparse fills in a default only
    where the namespace has no value yet, so each starts as a marker the command line alone replaces."""
    ap, unset = _parser(), object()
    marked = argparse.Namespace(**{dest: unset for dest in vars(ap.parse_args([]))})
    return {dest for dest, value in vars(ap.parse_args(argv, namespace=marked)).items() if value is not unset}


# the nodes' parameters each option sets (an option given on the command line wins over the parameters file)
OPTION_PARAMETERS = {"clock": {"clock"}, "control_period_s": {"control_period_s"}, "sim_seed": {"sim.seed"},
                     "busy_poll_s": {"realtime.busy_poll_s"}, "priority": {"realtime.priority", "realtime.busy_poll_s"},
                     "pin": {"realtime.cpus"}, "cpu_wakeup_latency_us": {"realtime.cpu_wakeup_latency_us"},
                     "gain_set": {"gain_set", "strategy"}, "strategy": {"strategy", "gain_set"},
                     "backend": {"backend"}, "lockstep_speed": {"lockstep.max_speed"}}
RIG_OWNED = {"lockstep.step_budget"}   # the demo's pacing: always the rig's
GAIN_KEYS = {"gain_set", "strategy", "kp", "ki", "kd"}


def merged_parameters(rig: dict, from_file: dict, given: set[str]) -> dict:
    """A node's parameters: the rig's defaults, then the file's values, then what the command line gave."""
    keys = set().union(*(OPTION_PARAMETERS.get(o, set()) for o in given)) | RIG_OWNED
    if GAIN_KEYS & set(from_file) and not keys & GAIN_KEYS:
        rig = {k: v for k, v in rig.items() if k not in GAIN_KEYS}   # the file's gains, not the default set
    return {**{k: v for k, v in rig.items() if k not in keys}, **from_file,
            **{k: v for k, v in rig.items() if k in keys}}


POLL_BELOW_PERIOD_S = 1e-3   # the rig's hardware polls between ticks at control periods shorter than this [s]


def default_busy_poll(control_period_s: float, priority: int) -> float:
    """The rig's realtime.busy_poll_s where neither the command line nor the parameters file sets it [s]: poll the
    whole period below POLL_BELOW_PERIOD_S, sleep at longer periods (bench/realtime_loop.py, section 3: at 1 kHz
    and slower a sleeping hardware keeps as many commands in time at about a quarter of the CPU, where polling
    costs a core) and at a real-time priority (a polling thread at that priority starves its CPU)."""
    if priority or control_period_s > POLL_BELOW_PERIOD_S or same_period(control_period_s, POLL_BELOW_PERIOD_S):
        return 0.0
    return control_period_s


def rig_parameters(args) -> tuple[dict, dict]:
    """The hardware's and the controller's parameters for these command-line options."""
    busy_poll = default_busy_poll(args.control_period_s, args.priority) if args.busy_poll_s is None else args.busy_poll_s
    hw = {"backend": args.backend, "clock": args.clock, "control_period_s": args.control_period_s,
          "realtime.busy_poll_s": busy_poll if args.clock == "realtime" else 0.0,
          "lockstep.step_budget": 0 if (args.clock == "lockstep" and args.demo == "steps") else -1}
    if args.lockstep_speed is not None:
        hw["lockstep.max_speed"] = args.lockstep_speed
    if args.backend == "sim":
        hw["sim.seed"] = args.sim_seed
    ctl = {"control_period_s": args.control_period_s, "reference_ramp_s": 0.002}
    if args.clock == "realtime":
        hw["realtime.priority"] = ctl["realtime.priority"] = args.priority
        if args.cpu_wakeup_latency_us is not None:
            hw["realtime.cpu_wakeup_latency_us"] = ctl["realtime.cpu_wakeup_latency_us"] = args.cpu_wakeup_latency_us
        if args.pin:
            from ..runtime.realtime import available_cpus
            cpus = sorted(available_cpus())
            # separate processes: one CPU each; composed: one process, one CPU (the last, away from CPU 0's chores)
            hw["realtime.cpus"] = [cpus[-1]] if args.composed else [cpus[0]]
            ctl["realtime.cpus"] = [cpus[-1]]
    ctl.update(rig_gains(args))
    return hw, ctl


def rig_gains(args) -> dict:
    """The controller's strategy or gain set: the command line's, else the default for the control period."""
    if args.strategy:
        return {"strategy": args.strategy, "gain_set": ""}
    if args.gain_set:
        return {"gain_set": args.gain_set}
    name = default_gain_set(args.control_period_s)
    return {"gain_set": name} if name else {"strategy": NO_SAFE_SET_STRATEGY, "gain_set": ""}


class UsageError(PiezoValveError, ValueError):
    """Options or a parameters file the rig cannot run with (exit 2, one line)."""


def apply_parameters_file(args, given: set[str], hw: dict, ctl: dict, ident: dict,
                          monitor: Optional[dict] = None) -> tuple[dict, dict, dict]:
    """The nodes' parameters with ``args.params_file``'s sections merged in (``merged_parameters``); the loop
    the file chose (clock, control period) becomes the rig's, in ``args`` too; ``monitor`` takes the
    valve_monitor section.  UsageError when the file cannot be read or a node's section is wrong."""
    from ..io.params_yaml import node_section
    sections = {}
    for node in ("valve_hardware", "valve_controller", "valve_identification", "valve_monitor"):
        try:
            sections[node] = node_section(args.params_file, node)
        except ValueError as exc:
            if node not in ("valve_identification", "valve_monitor") and "no section" not in str(exc):
                raise UsageError(str(exc)) from None
            sections[node] = {}
        except OSError as exc:
            raise UsageError(f"cannot read {args.params_file}: {exc.strerror or exc}") from None
    hw = merged_parameters(hw, sections["valve_hardware"], given)
    if hw["backend"] != "sim" and "sim_seed" not in given and "sim.seed" not in sections["valve_hardware"]:
        hw.pop("sim.seed", None)   # the rig's default seed is the sim backend's: another backend refuses it
    args.control_period_s = float(hw["control_period_s"])   # the default gains are for the period the rig runs at
    ctl = {**{k: v for k, v in ctl.items() if k not in GAIN_KEYS}, **rig_gains(args)}
    ctl = merged_parameters(ctl, sections["valve_controller"], given)
    ident = {**sections["valve_identification"], **ident}
    if monitor is not None:
        monitor.update(sections["valve_monitor"])
    # what the file chose for the loop is what the rig runs
    args.clock, args.control_period_s = str(hw["clock"]), float(hw["control_period_s"])
    ctl["control_period_s"] = ident["control_period_s"] = args.control_period_s
    if args.clock == "realtime" and not {"busy_poll_s", "priority"} & given \
            and "realtime.busy_poll_s" not in sections["valve_hardware"]:
        hw["realtime.busy_poll_s"] = default_busy_poll(args.control_period_s, hw.get("realtime.priority", 0))
    hw["lockstep.step_budget"] = 0 if (args.clock == "lockstep" and args.demo == "steps") else -1
    return hw, ctl, ident


def check_options(args) -> None:
    """UsageError for options that do not go together."""
    if args.identify and args.demo != "none":
        raise UsageError("--identify drives the rig itself; use it with --demo none")
    if args.demo == "steps" and args.clock != "lockstep":
        raise UsageError("the step demo needs --clock lockstep (use --demo none for a real-time rig)")
    if (args.priority or args.pin or args.cpu_wakeup_latency_us is not None) and args.clock != "realtime":
        raise UsageError("--priority, --pin and --cpu-wakeup-latency-us apply to --clock realtime")
    if args.lockstep_speed is not None and (args.clock != "lockstep" or not 0 <= args.lockstep_speed < math.inf):
        raise UsageError("--lockstep-speed takes a finite speed >= 0 and applies to --clock lockstep")


def _print_step_demo(client: RigClient, args, label: str, samples_per_period: int) -> None:
    periods = int(round(args.hold_s / args.control_period_s))
    t0 = time.monotonic()
    results = step_demo(client, args.control_period_s, periods, periods)
    wall = time.monotonic() - t0
    print(f"\nPaper step tests under {label} (2 ms ramps, 5 % settling band):")
    print(f"{'step [um]':>18} {'settling [ms]':>14} {'overshoot [%]':>14}")
    for a, b, ts, os_ in results:
        print(f"{a:7.1f} -> {b:6.1f} {ts * 1e3:14.1f} {os_:14.2f}")
    periods_run = client.rows_count // samples_per_period
    print(f"\n{periods_run} control periods in {wall:.1f} s wall time "
          f"({periods_run / wall:.0f} periods/s including pauses)")


RIG_NODES = ("valve_hardware", "valve_controller")   # the nodes the rig waits for (the others end as they end)
READY_TIMEOUT_S = 30.0      # the rig's nodes must answer within this long ...
READY_CHECK_S = 0.5         # ... and a node that exits meanwhile is noticed within about this long
STOP_RACE_S = 1.0           # a node that ends this long before the rig sees a Ctrl-C/SIGTERM ended by that signal


class StartUpError(PiezoValveError, RuntimeError):
    """A node of the rig ended while the rig came up (one line; the node said why on stderr)."""


def rig_client(args, samples_per_period: int) -> RigClient:
    """The launcher's own client of its rig.  It keeps the rig's samples only for the step demo, which reads them:
    with ``--demo none`` the rig runs for as long as it is left, and a client keeping every sample (24 bytes a
    sample and more) would grow without end and decode every batch on the loop's thread for nothing."""
    return RigClient(namespace=args.namespace, samples_per_period=samples_per_period,
                     with_samples=args.demo == "steps")


def wait_until_up(client: RigClient, procs: ProcessGroup, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Wait until the rig answers (``RigClient.wait_ready``); StartUpError as soon as one of ``procs`` ends
    (a node that refused its parameters exits at once: the rig must not wait for it), TimeoutError after
    ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        ended = [(name, code) for name, code in procs.exited() if name in RIG_NODES]
        if ended:
            raise StartUpError("; ".join(f"{name} exited with code {code} while the rig came up (its reason is the "
                                         f"line it printed above)" for name, code in ended))
        try:
            client.wait_ready(READY_CHECK_S)
            return
        except TimeoutError:
            if time.monotonic() > deadline:
                raise


def _run_until_stopped(args, procs: ProcessGroup, identification) -> int:
    """Until Ctrl-C / SIGTERM, a node exits, or the identification plan ends; the exit code."""
    if args.identify:
        print(f"running the identification plan {args.identify}; the rig stops when it is done "
              f"(bags and summary.json in {args.bag_dir}); Ctrl-C or SIGTERM to stop earlier", flush=True)
    else:
        print("running; Ctrl-C or SIGTERM to stop", flush=True)
    while rclpy.ok():
        time.sleep(0.2)
        if identification is not None and identification.poll() is not None:
            code = identification.returncode
            print(f"valve_rig: identification plan {'done' if code == 0 else f'failed (exit {code})'}; "
                  f"stopping the rig", file=sys.stderr if code else sys.stdout, flush=True)
            return 0 if code == 0 else 1
        if any(p.poll() is not None for _, p in procs.procs):
            if _stop_arriving(STOP_RACE_S):
                return 0
            print("valve_rig: a node exited; stopping the rig", file=sys.stderr)
            return 1
    return 0


def _stop_arriving(grace_s: float) -> bool:
    """Whether a Ctrl-C or SIGTERM reaches the rig within ``grace_s`` [s] (True; a Ctrl-C may also raise
    KeyboardInterrupt here).  A terminal's Ctrl-C goes to the whole process group: on a loaded machine a node can
    stop and exit before the rig has handled the same signal, and that node's exit is the stop, not a failure."""
    deadline = time.monotonic() + grace_s
    while rclpy.ok() and time.monotonic() < deadline:
        time.sleep(0.02)
    return not rclpy.ok()


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    hw_params, ctl_params = rig_parameters(args)
    ident_params = {"plan": args.identify, "control_period_s": args.control_period_s, "bag_dir": args.bag_dir,
                    "exit_when_done": True}
    monitor_params: dict = {}
    try:
        if args.params_file:
            hw_params, ctl_params, ident_params = apply_parameters_file(args, given_options(argv), hw_params,
                                                                        ctl_params, ident_params, monitor_params)
        check_options(args)
    except UsageError as exc:
        print(f"valve_rig: {exc}", file=sys.stderr)
        return 2
    use_fast_acknowledgements()   # the step demo's references acknowledged within ms (its nodes: DDS defaults)
    one_blas_thread_for_process()   # it hosts the nodes with --composed, as every node's process (core.blas)
    rclpy.init()
    procs = ProcessGroup()
    nodes: list[Node] = []
    stop = thread = executor = None
    hardware = identification = None
    code = 0
    try:
        if args.composed:
            from ..nodes.composed import build
            hardware, controller = build([Parameter(k, value=v) for k, v in hw_params.items()],
                                         [Parameter(k, value=v) for k, v in ctl_params.items()],
                                         **({"namespace": args.namespace} if args.namespace else {}))
            nodes += [hardware, controller]
        else:
            procs.start("valve_hardware", node_command("valve_hardware", hw_params, args.namespace))
            procs.start("valve_controller", node_command("valve_controller", ctl_params, args.namespace))
        if args.identify:
            identification = procs.start("valve_identification", node_command(
                "valve_identification", namespace=args.namespace, params=ident_params))
        if args.monitor:
            procs.start("valve_monitor", node_command("valve_monitor", monitor_params, args.namespace))
        samples_per_period = max(int(round(args.control_period_s / ValveSimConfig().dt)), 1)
        client = rig_client(args, samples_per_period)
        nodes.append(client)
        thread, stop, executor = run_in_background(nodes)
        wait_until_up(client, procs)
        label = ctl_params.get("gain_set") or ctl_params.get("strategy") or "the parameters file's strategy"
        print(f"rig up ({'composed' if args.composed else 'separate processes'}, {args.clock}); "
              f"controller {label}", flush=True)
        if args.demo == "steps":
            _print_step_demo(client, args, label, samples_per_period)
        else:
            code = _run_until_stopped(args, procs, identification)
    except KeyboardInterrupt:
        pass
    except Exception as exc:  # one clear line, the processes are stopped in finally
        if rclpy.ok():
            print(f"valve_rig: {exc}", file=sys.stderr)
            code = 1
    finally:
        if stop is not None:
            stop.set()
            thread.join(2.0)
        if hardware is not None:
            hardware.shutdown_safely()
        procs.stop()
        close(nodes, executor)
    return code


if __name__ == "__main__":
    sys.exit(main())
