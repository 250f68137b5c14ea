"""How a real-time process asks the operating system for its time: CPython's GIL switch interval, the CPUs
it may run on, a real-time scheduling priority, and how long an idle CPU may take to wake.  No ROS import (the
nodes declare the parameters, ``ros.parameters.realtime_specs``).

Measured on the 2-core development machine (``python bench/realtime_loop.py --only-conditions``, README):
pinning the hardware and the controller to their own CPUs raises the share of 2 kHz commands in time on a
quiet computer; with one busy loop per CPU beside the rig only a real-time priority keeps the loop.  On a
quiet computer an idle CPU sleeps in an idle state and wakes late (on a virtual machine it halts, and the host
wakes it): holding the CPUs' wake-up latency at 0 (the kernel's PM QoS request, as cyclictest does) keeps them
polling instead (section 7, "awake": 5 kHz across processes at priority 50, pinned, met its target in more runs).
"""
from __future__ import annotations

import os
import struct
import sys
import threading
from dataclasses import dataclass
from typing import Any, Sequence

from ..core.errors import PiezoValveError
from ..core.validation import as_float, as_int

DEFAULT_SWITCH_INTERVAL_S = 5e-5           # CPython's GIL switch interval in real-time processes (its default: 5 ms)
SWITCH_INTERVAL_RANGE_S = (1e-6, 0.005)
PRIORITY_RANGE = (0, 98)                   # SCHED_FIFO priority; 0 = the normal scheduler; 99 is left to the kernel
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"  # the kernel's PM QoS request for every CPU's wake-up latency
LEAVE_IDLE_STATES = -1                     # cpu_wakeup_latency_us: make no request (the OS's idle states)
MAX_WAKEUP_LATENCY_US = 2_000_000_000      # the largest request the kernel takes (PM QoS: a signed 32-bit us)
_held_requests: list[int] = []             # open request descriptors: a request lasts while its file is open


class RealtimeError(PiezoValveError, ValueError):
    """A real-time setting that is invalid, or that this process may not have (the reason says which)."""


@dataclass(frozen=True)
class RealtimeSettings:
    """What a real-time process asks for.

    switch_interval_s: CPython's GIL switch interval [s] (``sys.setswitchinterval``).
    priority: SCHED_FIFO priority (1..98) of the thread that applies the settings (a node's loop); every other
        thread of the process (DDS's, the BLAS libraries') one below (at priority 1: on the normal scheduler); 0
        leaves the normal scheduler.  At one priority a thread runs until it blocks: Fast DDS's asynchronous writer thread, spinning,
        starved a node's loop on its pinned CPU for good (SIGTERM, even SIGUSR1, never handled); one below, the
        loop preempts it, while it still preempts everything on the normal scheduler.
    cpus: CPU numbers every thread of the process may run on; empty = all.
    cpu_wakeup_latency_us: the longest an idle CPU may take to wake [us], requested from the kernel (PM QoS,
        ``CPU_LATENCY_DEVICE``) for every CPU while the process runs; 0 keeps idle CPUs polling instead of
        sleeping; -1 (``LEAVE_IDLE_STATES``) makes no request.
    """

    switch_interval_s: float = DEFAULT_SWITCH_INTERVAL_S
    priority: int = 0
    cpus: tuple[int, ...] = ()
    cpu_wakeup_latency_us: int = LEAVE_IDLE_STATES

    @staticmethod
    def from_values(switch_interval_s: Any, priority: Any, cpus: Any,
                    cpu_wakeup_latency_us: Any = LEAVE_IDLE_STATES) -> "RealtimeSettings":
        """Validated settings from parameter values; :class:`RealtimeError` with the reason."""
        try:
            interval = as_float("realtime.switch_interval_s", switch_interval_s)
            prio = as_int("realtime.priority", priority)
            wakeup = as_int("realtime.cpu_wakeup_latency_us", cpu_wakeup_latency_us)
            try:
                cpu_list = tuple(as_int("realtime.cpus", c) for c in list(cpus or ()))
            except TypeError:
                raise ValueError(f"realtime.cpus must be a list of CPU numbers, got {cpus!r}") from None
        except ValueError as exc:
            raise RealtimeError(str(exc)) from None
        lo, hi = SWITCH_INTERVAL_RANGE_S
        if not lo <= interval <= hi:
            raise RealtimeError(f"realtime.switch_interval_s must lie in [{lo:g}, {hi:g}] s, got {interval}")
        if not PRIORITY_RANGE[0] <= prio <= PRIORITY_RANGE[1]:
            raise RealtimeError(f"realtime.priority must lie in {PRIORITY_RANGE[0]}..{PRIORITY_RANGE[1]} "
                                f"(0 = normal scheduler), got {prio}")
        if not LEAVE_IDLE_STATES <= wakeup <= MAX_WAKEUP_LATENCY_US:
            raise RealtimeError(f"realtime.cpu_wakeup_latency_us must lie in 0..{MAX_WAKEUP_LATENCY_US} us, or be "
                                f"{LEAVE_IDLE_STATES} (no request), got {wakeup}")
        if cpu_list:
            available = available_cpus()
            missing = sorted(set(cpu_list) - available)
            if missing:
                raise RealtimeError(f"realtime.cpus: no CPU {', '.join(map(str, missing))} on this machine "
                                    f"(it has {', '.join(map(str, sorted(available)))})")
        return RealtimeSettings(interval, prio, tuple(sorted(set(cpu_list))), wakeup)

    def describe(self) -> str:
        """One phrase for a start-up line."""
        prio = f"SCHED_FIFO {self.priority}" if self.priority else "normal scheduler"
        cpus = f"CPUs {','.join(map(str, self.cpus))}" if self.cpus else "any CPU"
        wake = ("" if self.cpu_wakeup_latency_us == LEAVE_IDLE_STATES
                else ", idle CPUs polling" if self.cpu_wakeup_latency_us == 0
                else f", idle CPUs awake within {self.cpu_wakeup_latency_us} us")
        return f"{prio}, {cpus}, GIL switch interval {self.switch_interval_s * 1e6:g} us{wake}"


def available_cpus() -> set[int]:
    """CPUs the machine has (a process pinned by its parent may still widen its own set; a container's
    cpuset may forbid some, which :func:`pin` reports)."""
    cpus = set(range(os.cpu_count() or 1))
    try:
        cpus |= set(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        pass
    return cpus


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def apply(settings: RealtimeSettings) -> None:
    """Apply ``settings`` to every thread of this process (threads started later inherit them from their
    creator); the priority as ``RealtimeSettings.priority`` says (this thread's, the others one below).
    :class:`RealtimeError` when the OS refuses, with what to do about it."""
    sys.setswitchinterval(settings.switch_interval_s)
    if settings.cpus:
        pin(settings.cpus)
    if settings.priority:
        if not hasattr(os, "sched_setscheduler"):
            raise RealtimeError("realtime.priority needs Linux (os.sched_setscheduler)")
        global _applied_priority
        own, tids = threading.get_native_id(), _threads()
        loop, others = (os.SCHED_FIFO, os.sched_param(settings.priority)), _below(settings.priority)
        for tid in sorted(tids, key=lambda t: t != own):   # this thread first: it then preempts the others
            try:
                os.sched_setscheduler(tid, *(loop if tid == own else others))
            except ProcessLookupError:
                pass  # the thread ended meanwhile
            except PermissionError as exc:
                raise RealtimeError(
                    f"realtime.priority {settings.priority}: the OS refused SCHED_FIFO ({exc.strerror}); allow "
                    "it (e.g. '@realtime - rtprio 98' in /etc/security/limits.conf and the user in group "
                    "realtime, or CAP_SYS_NICE), or use realtime.priority 0") from None
        _applied_priority = settings.priority
        _ranked.update(tids)
    if settings.cpu_wakeup_latency_us != LEAVE_IDLE_STATES:
        hold_cpu_wakeup_latency(settings.cpu_wakeup_latency_us)


_applied_priority = 0     # the SCHED_FIFO priority ``apply`` gave this process's loop thread (0: none)
_ranked: set[int] = set()  # threads whose priority ``apply`` or ``rank_threads`` has set


def _below(priority: int) -> tuple[int, os.sched_param]:
    """(policy, priority) of a real-time process's threads other than its loop's: SCHED_FIFO one below; below FIFO 1,
    the normal scheduler (at the loop's own priority a spinning thread would starve the loop, as above)."""
    return (os.SCHED_FIFO, os.sched_param(priority - 1)) if priority > 1 else (os.SCHED_OTHER, os.sched_param(0))


def rank_threads() -> None:
    """After ``apply`` gave a priority: the threads started since by the loop's thread (an executor's timer thread,
    say), which inherited the loop's priority, one below it as every other thread.  From the loop's thread; a
    thread already ranked is not looked at again (on a real-time loop's path: one directory read when none is new)."""
    if not _applied_priority:
        return
    own, others = threading.get_native_id(), _below(_applied_priority)
    for tid in _threads():
        if tid in _ranked:
            continue
        _ranked.add(tid)
        try:
            if tid != own and os.sched_getscheduler(tid) == os.SCHED_FIFO:
                os.sched_setscheduler(tid, *others)
        except OSError:
            pass  # the thread ended meanwhile


def leave_realtime() -> None:
    """Every thread of this process that runs on SCHED_FIFO back on the normal scheduler: for a node's shutdown,
    which is not time-critical.  Threads at one FIFO priority on one CPU run until they block, so one that waits
    for another by spinning starves it for good (the process then holds the CPU at the kernel's real-time share,
    95 %, and never ends); the normal scheduler shares the CPU among them.  Lowering a priority needs no privilege."""
    global _applied_priority
    if not hasattr(os, "sched_setscheduler"):
        return
    _applied_priority = 0
    _ranked.clear()
    for tid in _threads():
        try:
            if os.sched_getscheduler(tid) == os.SCHED_FIFO:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass  # the thread ended meanwhile


def hold_cpu_wakeup_latency(latency_us: int, device: str = CPU_LATENCY_DEVICE) -> None:
    """Ask the kernel to keep every CPU's wake-up latency at most ``latency_us`` [us] for the rest of this
    process's life (Linux PM QoS: the request holds while its file stays open; the kernel takes the smallest of
    all requests).  :class:`RealtimeError` when the device cannot be written, with what to do about it."""
    try:
        fd = os.open(device, os.O_WRONLY)
    except OSError as exc:
        raise RealtimeError(
            f"realtime.cpu_wakeup_latency_us {latency_us}: cannot open {device} ({exc.strerror}); give the rig's "
            "user write access (e.g. the udev rule KERNEL==\"cpu_dma_latency\", GROUP=\"realtime\", MODE=\"0660\"), "
            f"or use {LEAVE_IDLE_STATES} (no request)") from None
    try:
        os.write(fd, struct.pack("=i", int(latency_us)))
    except OSError as exc:
        os.close(fd)
        raise RealtimeError(f"realtime.cpu_wakeup_latency_us {latency_us}: {device} refused it "
                            f"({exc.strerror})") from None
    _held_requests.append(fd)


def release_cpu_wakeup_latency() -> None:
    """Withdraw this process's wake-up latency requests (a process that ran a real-time node and goes on with
    other work: a bench, a test)."""
    while _held_requests:
        os.close(_held_requests.pop())


def pin(cpus: Sequence[int]) -> None:
    """Restrict every thread of this process to ``cpus`` (Linux; elsewhere RealtimeError)."""
    if not hasattr(os, "sched_setaffinity"):
        raise RealtimeError("realtime.cpus needs Linux (os.sched_setaffinity)")
    for tid in _threads():
        try:
            os.sched_setaffinity(tid, set(cpus))
        except ProcessLookupError:
            pass
        except OSError as exc:  # EINVAL: none of them in this container's cpuset
            raise RealtimeError(f"realtime.cpus {list(cpus)}: the OS refused ({exc.strerror})") from None
