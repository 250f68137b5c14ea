"""A node's process: rclpy set up with our own signal handling, the spin loop (and a real-time node's paced
tick in it), a clean shutdown with a deadline, and the console-script body ``run_node``."""
from __future__ import annotations

import faulthandler
import gc
import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from ..core.blas import one_blas_thread_for_process
from ..runtime.realtime import leave_realtime, rank_threads
from .parameters import _ROS_ARGV, refuse_undeclared


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
