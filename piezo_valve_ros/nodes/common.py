"""Shared ROS plumbing: QoS profiles, parameter helpers, spinning with clean shutdown."""
from __future__ import annotations

import array
import faulthandler
import gc
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy, qos_profile_sensor_data
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from ..core.blas import one_blas_thread_for_process
from ..core.defaults import CONTROL_PERIOD_S
from ..io.samples import SAMPLES_LABEL, decode_samples
from ..core.validation import ParameterSpec, as_float
from ..runtime.realtime import leave_realtime, rank_threads

MAX_CONTROL_PERIOD_S = 0.1      # slower than 10 Hz is no control loop for this valve

SENSOR_QOS = qos_profile_sensor_data  # spool_position: best effort, keep last
LATEST_SENSOR_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST,
                               durability=DurabilityPolicy.VOLATILE)  # a reader that wants only the newest sample
COMMAND_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
REFERENCE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
SAMPLES_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.VOLATILE)
# hardware_state: the latest state, kept for readers that join later
STATE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declare(node: Node, name: str, default: Any, description: str, *, read_only: bool = False,
            low: Optional[float] = None, high: Optional[float] = None, choices: tuple[str, ...] = ()):
    """Declare a parameter with a typed descriptor.

    Booleans and strings are statically typed (``enabled: 'false'`` is refused by rclpy with its reason);
    numbers and lists stay dynamically typed so ``kp: 1`` works as well as ``kp: 1.0`` (the node validates
    them itself).  ``read_only`` parameters can be given at start-up only; ``low``/``high`` document the
    admissible range in the descriptor (``ros2 param describe``) and are checked by rclpy for doubles;
    ``choices`` go into its additional constraints (the node checks them: ``ParameterSpec.checked``).
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=f"one of {', '.join(choices)}" if choices else "")
    if isinstance(default, bool):
        descriptor.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, str):
        descriptor.type = ParameterType.PARAMETER_STRING
    else:
        descriptor.dynamic_typing = True
        if low is not None and high is not None:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high))]
    return node.declare_parameter(name, default, descriptor)


CONTROL_PERIOD = ParameterSpec(
    "control_period_s", CONTROL_PERIOD_S, "control period [s]: one spool_position and one command per period (a whole number "
    "of the hardware's sample periods); every node of a rig must use the same", read_only=True,
    low=0.0, high=MAX_CONTROL_PERIOD_S)


def realtime_specs() -> tuple[ParameterSpec, ...]:
    """The read-only ``realtime.*`` scheduling parameters of a real-time node (see :mod:`..realtime`)."""
    from ..runtime.realtime import (CPU_LATENCY_DEVICE, DEFAULT_SWITCH_INTERVAL_S, LEAVE_IDLE_STATES, PRIORITY_RANGE,
                                    SWITCH_INTERVAL_RANGE_S)
    lo, hi = SWITCH_INTERVAL_RANGE_S
    return (
        ParameterSpec("realtime.switch_interval_s", DEFAULT_SWITCH_INTERVAL_S,
                      "CPython's GIL switch interval in this process [s] (the interpreter's default 5 ms lets another "
                      "thread, e.g. DDS's, hold it for several control periods)", read_only=True, low=lo, high=hi),
        ParameterSpec("realtime.priority", 0, "SCHED_FIFO priority of the node's loop thread, the process's other "
                      "threads (DDS's) one below, at 1 on the normal scheduler (0 = the normal "
                      f"scheduler; {PRIORITY_RANGE[0]}..{PRIORITY_RANGE[1]}); refused at start-up when the OS does not "
                      "allow it", read_only=True),
        ParameterSpec("realtime.cpus", [], "CPUs the process may run on (e.g. [1]; empty = any)", read_only=True),
        ParameterSpec("realtime.cpu_wakeup_latency_us", LEAVE_IDLE_STATES,
                      f"the longest an idle CPU may take to wake [us], requested for every CPU while the process runs "
                      f"({CPU_LATENCY_DEVICE}); 0 keeps idle CPUs polling (as cyclictest does); {LEAVE_IDLE_STATES} = no "
                      "request; refused at start-up when the OS does not allow it", read_only=True),
    )


DIAGNOSTICS_PERIOD = ParameterSpec(
    "diagnostics_period_s", 1.0, "publish this node's health on /diagnostics (diagnostic_msgs) this often [s]; "
    "0: never", read_only=True, low=0.0, high=60.0)
DIAGNOSTICS_LEVELS = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN, "ERROR": DiagnosticStatus.ERROR,
                      "STALE": DiagnosticStatus.STALE}


def period_parameter(spec: ParameterSpec, value) -> float:
    """A reporting period [s] within the spec's range (0: off); ValueError naming the parameter otherwise (a
    negative, NaN or a string would otherwise switch the report off without a word)."""
    period = as_float(spec.name, value)
    if not spec.low <= period <= spec.high:
        raise ValueError(f"{spec.name} must lie in [{spec.low:g}, {spec.high:g}] s (0: off), got {period}")
    return period


class Diagnostics:
    """A node's health on ``/diagnostics`` (the ROS convention: a DiagnosticArray, one DiagnosticStatus named
    after the node) every ``period_s``; ``status()`` gives (level "OK"/"WARN"/"ERROR", one-line message, values
    by name).  Logs one line when the level or the message's kind changes."""

    def __init__(self, node: Node, period_s: float, status: Callable[[], tuple[str, str, dict]]):
        self.node, self.status = node, status
        self.publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.last_level: Optional[str] = None
        self.timer = node.create_timer(period_s, self.publish) if period_s > 0 else None

    def publish(self) -> DiagnosticArray:
        level, message, values = self.status()
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [DiagnosticStatus(level=DIAGNOSTICS_LEVELS[level], name=self.node.get_fully_qualified_name(),
                                       message=message, hardware_id="piezo_valve",
                                       values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])]
        self.publisher.publish(msg)
        if level != self.last_level:
            if level == "OK":   # rclpy ties a call site to one severity: one call per severity
                self.node.get_logger().info(f"health {level}: {message}")
            elif level == "ERROR":
                self.node.get_logger().error(f"health {level}: {message}")
            else:
                self.node.get_logger().warning(f"health {level}: {message}")
            self.last_level = level
        return msg


def declare_all(node: Node, specs) -> None:
    """Declare every parameter of ``specs`` on ``node`` (:func:`declare`)."""
    for s in specs:
        declare(node, s.name, s.default, s.description, read_only=s.read_only, low=s.low, high=s.high,
                choices=s.choices)


def realtime_settings(p: dict):
    """Validated :class:`..realtime.RealtimeSettings` from a node's parameter values (ValueError)."""
    from ..runtime.realtime import RealtimeSettings
    return RealtimeSettings.from_values(p["realtime.switch_interval_s"], p["realtime.priority"],
                                        p["realtime.cpus"], p["realtime.cpu_wakeup_latency_us"])


def parameter_values(node: Node) -> dict[str, Any]:
    """Every parameter of ``node`` by name (public API)."""
    return {name: prm.value for name, prm in node.get_parameters_by_prefix("").items()}


def refuse(node: Node, reason: str) -> SetParametersResult:
    """One log line and the refusal a parameter client sees."""
    node.get_logger().warning(f"rejected parameter update: {reason}")
    return SetParametersResult(successful=False, reason=reason)


def samples_message(rows: np.ndarray, label: str = SAMPLES_LABEL) -> Float64MultiArray:
    """Pack (N, k) rows as the contract's row-major ``samples`` matrix."""
    msg = Float64MultiArray()
    n, k = rows.shape
    msg.layout.dim = [MultiArrayDimension(label="sample", size=n, stride=n * k),
                      MultiArrayDimension(label=label, size=k, stride=k)]
    data = array.array("d")  # an array.array is taken as it is; a list is checked element by element
    data.frombytes(np.ascontiguousarray(rows, dtype=np.float64).tobytes())
    msg.data = data
    return msg


class SamplesBuffer:
    """One ``samples``-layout message of ``n`` rows by ``k`` columns, made once and refilled in place: ``rows`` is a
    writable (n, k) view of its data.  For what a real-time loop publishes on a period (the hardware's full batches,
    the controller's state): building the message anew (its dimensions, its data array) costs tens of microseconds
    there, where the loop's caches are cold for it, and a publication that outlasts the slack of a 10 kHz period
    costs that period.  rclpy copies the message when it publishes, so refilling it after ``publish`` returns is
    safe."""

    def __init__(self, n: int, k: int, label: str = SAMPLES_LABEL):
        self.message = samples_message(np.zeros((n, k)), label)
        self.rows = np.frombuffer(self.message.data, dtype=np.float64).reshape(n, k)   # the message's own data


def samples_from_message(msg: Float64MultiArray) -> np.ndarray:
    """Inverse of :func:`samples_message`: (N, 3) rows time [s], voltage [V], position [m]
    (``samples.decode_samples``; SamplesLayoutError, a ValueError, when the layout is not the contract's)."""
    return decode_samples(msg.layout.dim, msg.data)


def tighten_timer_slack(slack_ns: int = 1000) -> bool:
    """Linux lets a thread's timed waits end up to ``timerslack_ns`` (default 50 us) late; a 10 kHz
    loop cannot live with that (its timer then fires in late/catch-up pairs).  Sets the slack of the
    calling thread, which threads it creates afterwards inherit (the executor's timer thread);
    returns False where that is not possible (not Linux)."""
    import ctypes
    import sys
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(29, int(slack_ns), 0, 0, 0) == 0  # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        return False


def make_executor(context=None):
    """EventsExecutor where available (about 2.5x the round trips of SingleThreadedExecutor)."""
    try:
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    except Exception:  # pragma: no cover - older rclpy
        return SingleThreadedExecutor(context=context)


@dataclass(frozen=True)
class Pacing:
    """A periodic job the spin loop runs itself: ``tick()`` every ``period_s`` seconds; during the last
    ``busy_poll_s`` before a tick the loop polls for messages instead of sleeping."""
    period_s: float
    tick: Callable[[], None]
    busy_poll_s: float = 0.0


class Throttle:
    """Whether a repeated log line is due: the first time, then at most once per ``period_s`` [s].  Asked before
    the logger is called: rclpy's logger looks up its caller's source file on every call, throttled or not
    (about a millisecond), so a throttled warning on a per-command path stalled the 10 kHz loop at every call,
    and a stall that made commands late made the next ones late through their warnings."""

    __slots__ = ("period_s", "_next", "_clock")

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic):
        self.period_s, self._next, self._clock = float(period_s), -math.inf, clock

    def due(self) -> bool:
        now = self._clock()
        if now < self._next:
            return False
        self._next = now + self.period_s
        return True


def claim_pacing(nodes) -> Optional[Pacing]:
    """The pacing a node hands to the spin loop (``claim_pacing()``, e.g. the real-time hardware tick)."""
    pacings = [p for p in (n.claim_pacing() for n in nodes if hasattr(n, "claim_pacing")) if p is not None]
    if len(pacings) > 1:
        raise ValueError("only one node per spin loop can be paced (one real-time hardware node per process)")
    return pacings[0] if pacings else None


RANK_THREADS_S = 1.0   # how often a real-time loop puts threads started since below its own priority


def spin_loop(executor, keep_going: Callable[[], bool], pacing: Optional[Pacing] = None,
              clock: Callable[[], float] = time.perf_counter) -> None:
    """Run callbacks (and the ``pacing`` tick on its period) while ``keep_going()``.

    Waits happen inside ``executor.spin_once(timeout)``, so a message is handled as soon as it
    arrives, also between ticks; with EventsExecutor and a tight timer slack this costs about half
    the CPU of an rclpy timer at 10 kHz (bench/realtime_loop.py).  Waking from a sleep takes tens of
    microseconds on a virtual machine (now and then milliseconds), so within ``busy_poll_s`` of a
    tick the loop polls (``spin_once(0)``) instead: a core's worth of CPU for a punctual tick and a
    quicker answer to messages.
    A tick more than a period late skips the periods it missed and stays on its grid.  Before the
    loop starts, everything allocated so far is moved out of the garbage collector's sight
    (``gc.freeze``): a full collection over all that the imported libraries allocated would stop a
    paced loop for many periods, and on a lockstep rig at 1 kHz the collections cost ~10 % of the
    nodes' CPU.
    EventsExecutor's blocking ``spin()`` ignores signals, hence the ``spin_once`` loop.  In a process given a
    real-time priority, threads started since (lazily, by the executor or DDS) are put below the loop's priority
    every RANK_THREADS_S (``realtime.rank_threads``).
    """
    gc.collect()
    gc.freeze()
    next_rank = clock() + RANK_THREADS_S
    if pacing is None:
        while keep_going():
            executor.spin_once(timeout_sec=0.1)
            if clock() >= next_rank:
                rank_threads()
                next_rank = clock() + RANK_THREADS_S
        return
    period, tick, busy_poll = pacing.period_s, pacing.tick, pacing.busy_poll_s
    next_tick = clock() + period
    while keep_going():
        now = clock()
        if now >= next_rank:   # threads started since (lazily, by the executor or DDS) below the loop's priority
            rank_threads()
            next_rank = now + RANK_THREADS_S
        if now < next_tick:
            if next_tick - now > busy_poll:
                executor.spin_once(timeout_sec=min(next_tick - now - busy_poll, 0.1))
            else:
                executor.spin_once(timeout_sec=0.0)
            continue
        tick()
        next_tick += period
        now = clock()
        if now >= next_tick:  # preempted for longer than a period: skip, but let callbacks run
            next_tick += math.ceil((now - next_tick) / period) * period
            executor.spin_once(timeout_sec=0.0)


class _StopRequest:
    """Set by the Ctrl-C/SIGTERM handler of :func:`init_ros`.  A plain attribute and no lock: a Python signal
    handler runs in the main thread between two bytecodes, possibly inside another run of itself (a parent's
    death brings two SIGTERMs, the kernel's and the parent watcher's), and a handler that takes a lock
    (``threading.Event.set`` does) then waits for itself for ever: the node hung before its safe shutdown."""
    requested = False
    deadline_s: Optional[float] = None   # init_ros's shutdown_deadline_s

    @classmethod
    def set(cls, *_signal_args) -> None:
        if not cls.requested:
            cls.requested = True
            _arm_shutdown_deadline(cls.deadline_s)


SHUTDOWN_DEADLINE_S = 4.5   # a node still alive this long after the first Ctrl-C/SIGTERM dumps its stacks and exits
# (a node's shutdown takes well under a second; below a ProcessGroup's SIGKILL, two STOP_GRACE_S after its Ctrl-C)


def _arm_shutdown_deadline(deadline_s: Optional[float]) -> None:
    """From the stop signal's handler: every thread back on the normal scheduler (a shutdown is not time-critical,
    and a thread at one FIFO priority that waits for another by spinning starves it for good), then faulthandler's
    own timer (a thread of C that needs no GIL, started here on the normal scheduler): if the process has not ended
    ``deadline_s`` later (None: no deadline) it writes every thread's stack to stderr and exits 1, so a hung
    shutdown says where it hung and never holds the valve or a CPU.  Takes no Python lock (a handler may run inside
    itself)."""
    leave_realtime()
    if deadline_s is not None:
        faulthandler.dump_traceback_later(deadline_s, exit=True)


_STOP_REQUESTED = _StopRequest


_ROS_ARGV: list[str] = []   # the process's command line as init_ros saw it (given_parameter_names)


def given_parameter_names(node_name: str, argv=None) -> tuple[set[str], set[str]]:
    """The parameter names a process's command line gives a node by name, as (for this node alone, for every node
    of the process): ``-p``/``--param NODE:NAME:=VALUE`` for this node and the sections of ``--params-file`` files
    for this node alone, then ``-p NAME:=VALUE`` (every node of the process takes it; a file's ``/**`` sections,
    which serve every node of every process, are left out).  rclpy ignores a name a node does not declare without
    a word: the nodes refuse it (a misspelt parameter)."""
    from ..io.params_yaml import node_section
    tokens = list(_ROS_ARGV if argv is None else argv)
    own: set[str] = set()
    shared: set[str] = set()
    in_ros = False
    k = 0
    while k < len(tokens):
        token = tokens[k]
        if token == "--ros-args":
            in_ros = True
        elif token == "--":
            in_ros = False
        elif in_ros and token in ("-p", "--param") and k + 1 < len(tokens):
            k += 1
            node, _, name = tokens[k].split(":=", 1)[0].rpartition(":")
            if not node:
                shared.add(name)
            elif node.rstrip("/").split("/")[-1] == node_name:
                own.add(name)
        elif in_ros and token == "--params-file" and k + 1 < len(tokens):
            k += 1
            try:
                own |= set(node_section(tokens[k], node_name, wildcard=False))
            except (OSError, ValueError):
                pass   # rclpy reports an unreadable file itself; a file without a section for this node gives none
        k += 1
    return own, shared


def init_ros(args=None, shutdown_deadline_s: Optional[float] = SHUTDOWN_DEADLINE_S) -> None:
    """``rclpy.init`` for a node process, with signal handling of our own: Ctrl-C/SIGTERM only ask the spin
    loop to stop (within its 0.1 s wait), so no callback is interrupted half-way (rclpy's handler raises
    into whatever callback runs, which the executor reports as a FATAL exception) and the shutdown path
    (safe voltage, flushing the samples) runs with the ROS context still valid.  A process still alive
    ``shutdown_deadline_s`` after the first of them dumps every thread's stack and exits 1 (None: a process whose
    shutdown may take long, a recorder closing a large bag)."""
    import signal
    import sys
    _ROS_ARGV[:] = list(sys.argv if args is None else args)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    _STOP_REQUESTED.requested = False
    _STOP_REQUESTED.deadline_s = shutdown_deadline_s
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, _STOP_REQUESTED.set)
        faulthandler.register(signal.SIGUSR1, all_threads=True)   # SIGUSR1: every thread's stack to stderr


def stop_requested() -> bool:
    """True once Ctrl-C/SIGTERM arrived in a process set up by :func:`init_ros`."""
    return _STOP_REQUESTED.requested


def split_ros_args(argv) -> tuple[list[str], list[str]]:
    """(a tool's own arguments, ``--ros-args`` and everything after it: ROS's)."""
    argv = list(argv)
    cut = argv.index("--ros-args") if "--ros-args" in argv else len(argv)
    return argv[:cut], argv[cut:]


def close(nodes=(), executor=None) -> None:
    """End a ROS session: each node out of the executor and destroyed, the executor shut down, then rclpy;
    every step runs even if an earlier one fails (a session ends once, whatever broke it)."""
    for node in nodes:
        try:
            if executor is not None:
                executor.remove_node(node)
            node.destroy_node()
        except Exception:
            pass
    if executor is not None:
        try:
            executor.shutdown()
        except Exception:
            pass
    if rclpy.ok():
        rclpy.try_shutdown()


def spin(nodes, on_exit: Optional[Callable[[], None]] = None, executor=None) -> int:
    """Spin until shutdown (Ctrl-C / SIGTERM); ``on_exit`` runs whatever ends the loop.

    A node that offers ``claim_pacing()`` (the real-time hardware) has its tick run by the loop.
    """
    executor = executor or make_executor()
    for node in nodes:
        executor.add_node(node)
    rank_threads()   # the executor's own threads below the loop's priority, as DDS's
    code = 0
    try:
        spin_loop(executor, lambda: rclpy.ok() and not _STOP_REQUESTED.requested, claim_pacing(nodes))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            code = 1
            raise
        # a callback ran into the context a signal had just shut down: that is the shutdown itself
    finally:
        _ignore_signals_while_cleaning_up()
        leave_realtime()   # the teardown is not time-critical, and at SCHED_FIFO on one CPU it can starve itself
        if on_exit is not None:
            on_exit()
        close(nodes, executor)
    return code


def _ignore_signals_while_cleaning_up() -> None:
    """The loop has ended: a second Ctrl-C/SIGTERM must not interrupt the cleanup half-way (it would abort
    inside rclpy's C++ destructors)."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)


def wants_help(args=None) -> bool:
    """``-h``/``--help`` before any ``--ros-args`` (what follows those belongs to ROS)."""
    import sys
    own, _ = split_ros_args(sys.argv[1:] if args is None else args)
    return "-h" in own or "--help" in own


def print_help(name: str, doc: Optional[str], specs=()) -> None:
    """What a node executable prints for ``--help`` (it does not start the node): usage, its docstring and
    every parameter of ``specs`` with type, default, range and whether it is read-only."""
    import sys
    lines = [f"usage: {name} [--ros-args [-p NAME:=VALUE]... [--params-file FILE] [-r __ns:=/NAMESPACE]]\n",
             (doc or "").strip()]
    if specs:
        lines.append("\nparameters (read-only ones are taken at start-up only):")
        lines += [s.help_line() for s in specs]
    try:
        sys.stdout.write("\n".join(lines) + "\n")
        sys.stdout.flush()
    except BrokenPipeError:   # the reader stopped early (``--help | head``): nothing more to say, and no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def start_node_process(args=None) -> None:
    """What a process that hosts nodes does before it builds them: it dies with its parent (a launcher's Ctrl-C
    reaches it), holds BLAS to one thread (a worker spinning beside a real-time loop takes its CPU: core.blas), and
    brings ROS up (``init_ros``)."""
    from ..runtime.processes import die_with_parent
    die_with_parent()
    one_blas_thread_for_process()
    init_ros(args)


def nearest_parameter(name: str, nodes: Sequence[Node]) -> Optional[str]:
    """The declared parameter of ``nodes`` whose name is nearest ``name`` (a typo's intended name), or None."""
    import difflib
    declared = sorted({n for node in nodes for n in node.get_parameters_by_prefix("")})
    close_ = difflib.get_close_matches(name, declared, n=1, cutoff=0.6)
    return close_[0] if close_ else None


def undeclared_parameters(nodes: Sequence[Node], argv=None) -> list[str]:
    """Each parameter the process's command line (``-p``, ``--params-file`` sections) gives the nodes of this process
    that none of them declares, with the nearest declared name: rclpy ignores such a name without a word, so a
    misspelt one (``gain_sett``, ``plann``) would leave its default in force.  Names for one node by name are its own
    alone; names for every node of the process count where no node of it declares them."""
    unknown: list[str] = []
    shared_names: set[str] = set()
    for node in nodes:
        own, shared = given_parameter_names(node.get_name(), argv)
        unknown += [f"{node.get_name()}:{n}" if len(nodes) > 1 else n for n in sorted(own) if not node.has_parameter(n)]
        shared_names |= shared
    unknown += sorted(n for n in shared_names if not any(node.has_parameter(n) for node in nodes))
    return [named_with_nearest(u, nodes) for u in unknown]


def named_with_nearest(name: str, nodes: Sequence[Node]) -> str:
    """``name`` (``NODE:NAME`` or ``NAME``) with the nearest declared parameter of ``nodes``, if any, as a hint."""
    near = nearest_parameter(name.rpartition(":")[2], nodes)
    return name + (f" (did you mean {near}?)" if near else "")


def refuse_undeclared(nodes: Sequence[Node], tool: str, argv=None) -> None:
    """ValueError naming every parameter the command line gives ``nodes`` that none of them declares
    (``undeclared_parameters``), at start-up, before anything runs."""
    unknown = undeclared_parameters(nodes, argv)
    if unknown:
        raise ValueError(f"unknown parameter(s): {'; '.join(unknown)} (every parameter: {tool} --help)")


def run_node(factory: Callable[[], Node], name: str, args=None, on_exit_of=None, specs=()) -> int:
    """Console-script body: init, build the node (one clear line and exit 2 if that fails: a parameter it refuses, or
    one it does not declare), spin.

    ``on_exit_of(node)`` gives the callable run when spinning ends (e.g. apply safe_voltage).
    """
    import sys
    if wants_help(args):
        print_help(name, sys.modules[getattr(factory, "__module__", __name__)].__doc__, specs)
        return 0
    start_node_process(args)
    node = None
    try:
        node = factory()
        refuse_undeclared([node], name)
    except Exception as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        if node is not None:
            stop = on_exit_of(node) if on_exit_of else None
            if stop is not None:
                stop()
            node.destroy_node()
        close()
        return 2
    return spin([node], on_exit=on_exit_of(node) if on_exit_of else None)
