"""How a real-time process asks the operating system for its time: CPython's GIL switch interval, the CPUs
it may run on, and a real-time scheduling priority.  No ROS import (the nodes declare the parameters,
``nodes.common.realtime_specs``).

Measured on the 2-core development machine (``python bench/realtime_loop.py --only-conditions``, README):
pinning the hardware and the controller to their own CPUs raises the share of 2 kHz commands in time on a
quiet computer; with one busy loop per CPU beside the rig only a real-time priority keeps the loop.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Any, Sequence

from ..core.errors import PiezoValveError
from ..core.validation import as_float, as_int

DEFAULT_SWITCH_INTERVAL_S = 5e-5           # CPython's GIL switch interval in real-time processes (its default: 5 ms)
SWITCH_INTERVAL_RANGE_S = (1e-6, 0.005)
PRIORITY_RANGE = (0, 98)                   # SCHED_FIFO priority; 0 = the normal scheduler; 99 is left to the kernel


class RealtimeError(PiezoValveError, ValueError):
    """A real-time setting that is invalid, or that this process may not have (the reason says which)."""


@dataclass(frozen=True)
class RealtimeSettings:
    """What a real-time process asks for.

    switch_interval_s: CPython's GIL switch interval [s] (``sys.setswitchinterval``).
    priority: SCHED_FIFO priority of every thread of the process (1..98); 0 leaves the normal scheduler.
    cpus: CPU numbers every thread of the process may run on; empty = all.
    """

    switch_interval_s: float = DEFAULT_SWITCH_INTERVAL_S
    priority: int = 0
    cpus: tuple[int, ...] = ()

    @staticmethod
    def from_values(switch_interval_s: Any, priority: Any, cpus: Any) -> "RealtimeSettings":
        """Validated settings from parameter values; :class:`RealtimeError` with the reason."""
        try:
            interval = as_float("realtime.switch_interval_s", switch_interval_s)
            prio = as_int("realtime.priority", priority)
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
        if cpu_list:
            available = available_cpus()
            missing = sorted(set(cpu_list) - available)
            if missing:
                raise RealtimeError(f"realtime.cpus: no CPU {', '.join(map(str, missing))} on this machine "
                                    f"(it has {', '.join(map(str, sorted(available)))})")
        return RealtimeSettings(interval, prio, tuple(sorted(set(cpu_list))))

    def describe(self) -> str:
        """One phrase for a start-up line."""
        prio = f"SCHED_FIFO {self.priority}" if self.priority else "normal scheduler"
        cpus = f"CPUs {','.join(map(str, self.cpus))}" if self.cpus else "any CPU"
        return f"{prio}, {cpus}, GIL switch interval {self.switch_interval_s * 1e6:g} us"


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
    creator).  :class:`RealtimeError` when the OS refuses, with what to do about it."""
    sys.setswitchinterval(settings.switch_interval_s)
    if settings.cpus:
        pin(settings.cpus)
    if settings.priority:
        if not hasattr(os, "sched_setscheduler"):
            raise RealtimeError("realtime.priority needs Linux (os.sched_setscheduler)")
        param = os.sched_param(settings.priority)
        for tid in _threads():
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            except ProcessLookupError:
                pass  # the thread ended meanwhile
            except PermissionError as exc:
                raise RealtimeError(
                    f"realtime.priority {settings.priority}: the OS refused SCHED_FIFO ({exc.strerror}); allow "
                    "it (e.g. '@realtime - rtprio 98' in /etc/security/limits.conf and the user in group "
                    "realtime, or CAP_SYS_NICE), or use realtime.priority 0") from None


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
