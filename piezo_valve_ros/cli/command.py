"""``valve_command``: send references to a running rig and get or set its nodes' parameters (no ros2cli
needed).  Positions in metres, times in seconds (SI, as on the topics).

    valve_command step 20e-6                                  # hold 20 um
    valve_command ramp 0 30e-6 --duration 2                   # 0 -> 30 um in 2 s
    valve_command sine --amplitude 40e-6 --frequency 1 --duration 10
    valve_command file demand.csv                             # rows: time_s, position_m
    valve_command get controller strategy kp ki               # all parameters without names
    valve_command set controller gain_set:=ff_pid_1           # each answer: accepted, or refused and why
    valve_command --namespace /rig2 set hardware command_timeout_s:=0.2
    valve_command load controller fitted.yaml                 # a whole file in one update: all or nothing
    valve_command status                                      # the rig's /diagnostics and controller state

Nodes are ``hardware``, ``controller``, ``identification`` (the rig's, in ``--namespace``) or any node
name.  ``status`` listens (until each node has reported, ``--listen`` seconds at most) and prints the latest health every node of the namespace
published on ``/diagnostics`` (hardware, controller, ``valve_monitor``) and the controller's latest
``~/controller_state``; it exits 1 when a status is not OK or none came.  Values of ``set`` are read as YAML, like ``ros2 param set`` (``1`` an integer, ``1.0`` a double,
``true`` a bool, ``'1'`` a string).  Exit status: 0 done, 1 a value refused or the rig not answering,
2 bad arguments.  The rig may run on another machine in the same ROS domain.
"""
from __future__ import annotations

import argparse
import re
import sys
import time

import numpy as np

from ..runtime.dds import use_fast_acknowledgements
from ..io.params_yaml import YAMLError, load as load_yaml, node_section
from ..core.sim.signals import load_profile, ramp_profile, sine_profile
from ..rig.client import RIG_NODES, RigClient, run_in_background
from ..ros import close, init_ros, split_ros_args, stop_requested

MAX_REFERENCE_M = 5e-4     # refused before sending: beyond any piezo ring bender's travel (a unit mistake)
PROFILE_HISTORY = 10_000   # references kept for readers that fall behind (the nodes keep 10)


class _Parser(argparse.ArgumentParser):
    """Takes ``-20e-6`` for a number, as Python 3.13's argparse does (3.11 reads it as an option)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")


def parse_args(argv=None) -> argparse.Namespace:
    ap = _Parser(prog="valve_command", description=__doc__.split("\n\n")[0],
                                 epilog="ROS arguments may follow --ros-args.")
    ap.add_argument("--namespace", default="", help="the rig's namespace (default: the root)")
    ap.add_argument("--timeout", type=float, default=10.0, metavar="S",
                    help="wait this long for the rig to answer (default 10 s)")
    ap.add_argument("--wait-readers", type=int, default=1, metavar="N",
                    help="send references once N nodes read them (default 1, the controller; 2 with a recorder)")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("step", help="send one reference (the controller ramps to it)")
    p.add_argument("position_m", type=float)
    p = sub.add_parser("ramp", help="a straight line from one position to another")
    p.add_argument("start_m", type=float)
    p.add_argument("end_m", type=float)
    p.add_argument("--duration", type=float, required=True, metavar="S")
    p.add_argument("--rate", type=float, default=100.0, metavar="HZ", help="references per second (100)")
    p = sub.add_parser("sine", help="offset + amplitude * sin(2 pi f t)")
    p.add_argument("--amplitude", type=float, required=True, metavar="M")
    p.add_argument("--frequency", type=float, required=True, metavar="HZ")
    p.add_argument("--duration", type=float, required=True, metavar="S")
    p.add_argument("--offset", type=float, default=0.0, metavar="M")
    p.add_argument("--rate", type=float, default=200.0, metavar="HZ", help="references per second (200)")
    p = sub.add_parser("file", help="a profile from a text file of 'time_s, position_m' rows")
    p.add_argument("path")
    p = sub.add_parser("get", help="print parameters of a node")
    p.add_argument("node")
    p.add_argument("names", nargs="*")
    p = sub.add_parser("set", help="set parameters of a node (NAME:=VALUE ...; several go in one atomic update, "
                                   "all applied or none, e.g. strategy:=pid gain_set:= (nothing after := is the empty string)")
    p.add_argument("node")
    p.add_argument("assignments", nargs="+", metavar="NAME:=VALUE")
    p = sub.add_parser("load", help="load a ROS parameters file into a running node in one atomic update (all "
                                    "applied or none: e.g. a fitted model from valve_identify --params-out)")
    p.add_argument("node")
    p.add_argument("path")
    sub.add_parser("reset", help="leave the hardware's latched fault (its ~/reset service) once its cause is gone")
    p = sub.add_parser("status", help="print the rig's health (/diagnostics) and the controller's state")
    p.add_argument("--listen", type=float, default=6.0, metavar="S",
                   help="listen at most this long for every node to report (default 6 s; the nodes report every "
                        "second)")
    return ap.parse_args(argv)


def parse_assignment(text: str) -> tuple[str, object]:
    """``name:=value`` (or ``name=value``) with the value read as YAML; ``name:=`` (nothing after it, as a shell
    leaves ``name:=''``) is the empty string; ValueError when malformed."""
    sep = ":=" if ":=" in text else "="
    name, found, value = text.partition(sep)
    if not found or not name.strip():
        raise ValueError(f"expected NAME:=VALUE, got {text!r}")
    if not value.strip():
        return name.strip(), ""   # a parameter that is not a string refuses it by its type, with its reason
    try:
        parsed = load_yaml(value)
    except YAMLError as exc:
        raise ValueError(f"{name}: value {value!r} is not YAML ({str(exc).splitlines()[0]})") from None
    if parsed is None:
        raise ValueError(f"{name}: {value!r} is no value")
    return name.strip(), parsed


def profile(args) -> tuple[np.ndarray, np.ndarray]:
    """(times [s], positions [m]) for a reference command; ValueError with the reason."""
    if args.command == "step":
        times, values = np.zeros(1), np.array([args.position_m])
    elif args.command == "ramp":
        times, values = ramp_profile(args.start_m, args.end_m, args.duration, args.rate)
    elif args.command == "sine":
        times, values = sine_profile(args.amplitude, args.frequency, args.duration, args.offset, args.rate)
    else:
        times, values = load_profile(args.path)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{args.command}: positions must be finite")
    worst = float(np.max(np.abs(values)))
    if worst > MAX_REFERENCE_M:
        raise ValueError(f"{args.command}: a position of {worst:.6g} m: no piezo valve's spool travels more than "
                         f"{MAX_REFERENCE_M:g} m (positions are in metres: 20 um is 2e-05); nothing sent")
    return times, values


def checked_request(args):
    """What a parsed command will send, checked before ROS starts: the assignments of ``set``, the
    (times, positions) of a reference command, None for ``get``; ValueError (or OSError) with the reason."""
    if not (np.isfinite(args.timeout) and args.timeout > 0):
        raise ValueError(f"--timeout must be > 0 s, got {args.timeout}")
    if args.command == "get":
        return None
    if args.command == "reset":
        return None
    if args.command == "status":
        if not (np.isfinite(args.listen) and args.listen > 0):
            raise ValueError(f"--listen must be > 0 s, got {args.listen}")
        return None
    if args.command == "set":
        return dict(parse_assignment(a) for a in args.assignments)
    if args.command == "load":
        return node_section(args.path, f"valve_{args.node}" if args.node in RIG_NODES else args.node)
    if args.wait_readers < 1:
        raise ValueError(f"--wait-readers must be >= 1, got {args.wait_readers}")
    return profile(args)


LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}
STATUS_DISCOVERY_S = 1.5   # status: the namespace's nodes have stayed the same this long: all are found
REPORTING_NODES = {"valve_hardware", "valve_controller", "valve_monitor"}   # they publish on /diagnostics


def same_value(a, b) -> bool:
    """Whether a node's parameter value and a file's are the same (lists and tuples alike, ints and floats alike)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same_value(x, y) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    return a == b


def status(args, client: RigClient, out=sys.stdout) -> int:
    """The latest /diagnostics status of each node in the rig's namespace and the latest controller state,
    heard until every such node (the hardware and the controller always) has reported, at most ``args.listen``
    seconds; 1 when a status is not OK or one did not come."""
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float64MultiArray
    ns = client.get_namespace().rstrip("/") + "/"
    latest, state = {}, []
    subs = [client.create_subscription(DiagnosticArray, "/diagnostics", lambda m: latest.update(
                {s.name: s for s in m.status if s.name.startswith(ns)}), 10),
            client.create_subscription(Float64MultiArray, client.node_name("controller") + "/controller_state",
                                       state.append, 10)]
    # until every node of the namespace that publishes /diagnostics has been heard (and the controller's
    # state, when it publishes one), or --listen has passed: a new reader hears nothing before discovery
    started = changed = time.monotonic()
    known: tuple = ()
    rig = {client.node_name("hardware"), client.node_name("controller")}   # a rig has both, found or not yet
    while time.monotonic() - started < args.listen:
        time.sleep(0.05)
        # the package's reporting nodes in the namespace (a node is seen before its publishers are)
        nodes = {f"{space.rstrip('/')}/{name}" for name, space in client.get_node_names_and_namespaces()
                 if name in REPORTING_NODES}
        publishers = {f"{i.node_namespace.rstrip('/')}/{i.node_name}"
                      for i in client.get_publishers_info_by_topic("/diagnostics")}
        expected = {p for p in nodes | publishers if p.startswith(ns)} | rig
        state_publishers = client.count_publishers(client.node_name("controller") + "/controller_state")
        if (sorted(expected), state_publishers) != known:     # discovery still finding nodes
            known, changed = (sorted(expected), state_publishers), time.monotonic()
        settled = time.monotonic() - changed >= STATUS_DISCOVERY_S
        if settled and expected and expected <= set(latest) and (state or not state_publishers):
            break
    for sub in subs:
        client.destroy_subscription(sub)
    if not latest:
        print(f"valve_command: no node in {ns} published on /diagnostics within {args.listen:g} s", file=out)
        return 1
    silent = sorted(rig - set(latest))
    for name in silent:
        print(f"{name}: no status within {args.listen:g} s", file=out)
    for name in sorted(latest):
        s = latest[name]
        level = LEVELS.get(s.level[0] if isinstance(s.level, bytes) else s.level, str(s.level))
        print(f"{name}: {level}: {s.message}", file=out)
        for kv in s.values:
            print(f"    {kv.key}: {kv.value}", file=out)
    if state:
        msg = state[-1]
        labels = msg.layout.dim[1].label.split(",") if len(msg.layout.dim) == 2 else []
        row = dict(zip(labels, msg.data))
        print("controller state: " + ", ".join(f"{k} {v:.6g}" for k, v in row.items()), file=out)
    return 0 if not silent and all((s.level[0] if isinstance(s.level, bytes) else s.level) == 0
                                   for s in latest.values()) else 1


def run(args, client: RigClient, request, out=sys.stdout) -> int:
    """Carry out one parsed command (``request`` from :func:`checked_request`) against a rig reachable
    through ``client`` (spun elsewhere)."""
    if args.command == "status":
        return status(args, client, out)
    if args.command == "reset":
        ok, message = client.reset_hardware(args.timeout)
        print(f"{client.node_name('hardware')}: {'reset: ' if ok else 'reset refused: '}{message}", file=out)
        return 0 if ok else 1
    if args.command == "get":
        values = client.get_params(client.wait_for_node(args.node, args.timeout), args.names, args.timeout)
        for name, value in values.items():
            print(f"{name}: {value!r}" if value is not None else f"{name}: (not set)", file=out)
        return 0 if all(v is not None for v in values.values()) else 1
    if args.command == "set" and len(request) > 1:   # values that belong together: one update, all or none
        values = request
        result = client.set_params_atomically(client.wait_for_node(args.node, args.timeout), values, args.timeout)
        who, names = client.node_name(args.node), ", ".join(f"{k} := {v!r}" for k, v in values.items())
        if result.successful:
            print(f"{who}: {names} accepted together", file=out)
            return 0
        print(f"{who}: {names} refused, nothing changed: {result.reason}", file=out)
        return 1
    if args.command == "set":
        values = request
        results = client.set_params(client.wait_for_node(args.node, args.timeout), values, args.timeout)
        refused = 0
        for (name, value), result in zip(values.items(), results):
            if result.successful:
                print(f"{client.node_name(args.node)}: {name} := {value!r} accepted", file=out)
            else:
                refused += 1
                print(f"{client.node_name(args.node)}: {name} := {value!r} refused: {result.reason}", file=out)
        return 1 if refused else 0
    if args.command == "load":
        node = client.wait_for_node(args.node, args.timeout)
        # values already in force are left out: a file the tools wrote carries start-up-only ones (control_period_s)
        current = client.get_params(node, list(request), args.timeout)
        values = {k: v for k, v in request.items() if not same_value(current.get(k), v)}
        who = client.node_name(args.node)
        kept = len(request) - len(values)
        if not values:
            print(f"{who}: every one of the {len(request)} parameters in {args.path} is in force already", file=out)
            return 0
        result = client.set_params_atomically(node, values, args.timeout)
        if result.successful:
            print(f"{who}: {len(values)} parameters from {args.path} applied together"
                  + (f" ({kept} already in force)" if kept else ""), file=out)
            return 0
        print(f"{who}: {args.path} refused, nothing changed: {result.reason}", file=out)
        return 1
    times, values = request

    def progress(sent, total, elapsed):
        print(f"valve_command: {sent}/{total} references sent, {elapsed:.1f} of {times[-1]:.1f} s", file=out,
              flush=True)
    played = client.play_reference(times, values, args.timeout, progress=progress,
                                   keep_going=lambda: not stop_requested(), min_readers=args.wait_readers)
    if played.sent < len(values):
        print(f"valve_command: {args.command}: stopped after {played.sent} of {len(values)} references "
              f"({played.sending_s:.2f} s); the controller holds the last one", file=out)
        return 130
    span = (f"{values[0] * 1e6:.2f} um" if len(values) == 1 else
            f"{values.min() * 1e6:.2f} .. {values.max() * 1e6:.2f} um over {played.sending_s:.2f} s")
    print(f"valve_command: {args.command}: {played.sent} reference(s), {span}, on {client.reference_pub.topic_name}; "
          f"acknowledged by {played.readers} reader(s) {played.acknowledged_after_s:.2f} s later", file=out)
    return 0


def main(argv=None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = parse_args(own)
    try:  # bad input is refused before touching ROS
        request = checked_request(args)
    except (ValueError, OSError) as exc:
        print(f"valve_command: {exc}", file=sys.stderr)
        return 2
    use_fast_acknowledgements()   # a reference's acknowledgement within ms, not at the next 3 s heartbeat
    init_ros(["valve_command"] + ros_args)
    client = RigClient(args.namespace, with_samples=False, name="valve_command", reference_history=PROFILE_HISTORY)
    thread, stop, executor = run_in_background([client])
    try:
        return run(args, client, request)
    except (TimeoutError, ValueError) as exc:
        print(f"valve_command: {exc}", file=sys.stderr)
        return 1
    finally:
        stop.set()
        thread.join(2.0)
        close([client], executor)


if __name__ == "__main__":
    sys.exit(main())
