"""The hardware's loop without ROS: read -> check -> write, the watchdog, the fault latch, the samples batch and the
lockstep pacing, over a ``ValveBackend``.

``valve_hardware`` (``nodes.hardware``) is a thin ROS face over a :class:`HardwareLoop`: it gives the loop its
settings and three outlets (a position, a full batch of sample rows, the valve's time after a lockstep period) and
runs it from a timer, the spin loop's pacing or the command's callback; parameters, the lifecycle, the topics and
/diagnostics stay the node's.  Tested without rclpy (``test/test_lifecycle.py``).

Clocks
  realtime  ``tick()`` each control period reads what the backend sampled; a command is written when it comes
  lockstep  each accepted command is written and advances the backend one control period (``step_budget``: -1 runs
            free, n > 0 runs n periods and pauses, 0 holds the latest command until budget is granted); ``max_speed``
            keeps the valve's time from running ahead of the wall clock by more than that factor

Faults: a backend call that raises is retried once at once (a glitch, counted and said); a second failure, or rows
that are non-finite, implausible or frozen, or no rows for ``missing_samples_s`` (real-time clock), latch a fault
(``backends.faults``): the safe voltage is written (retried every period while writes fail), commands are refused
until ``reset()`` finds the backend sound again.
"""
from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional

import numpy as np

from ..backends.base import ValveBackend
from ..backends.faults import Fault, FaultLimits, SampleCheck
from .loop_timing import LoopTiming
from .throttle import Throttle

__all__ = ["HardwareLoop", "LoopSettings", "GLITCH_WINDOW_S", "PACE_SLACK_S"]

GLITCH_WINDOW_S = 60.0       # glitches_in_last_minute counts this last stretch
PACE_SLACK_S = 0.1           # lockstep max_speed: a loop this far behind its pace starts afresh (no sprint) [s]


@dataclass(frozen=True)
class LoopSettings:
    """What the loop needs of the node's settings: the clock ("realtime" or "lockstep"), the safe voltage and the
    command range [V], rows per samples batch, lockstep's max_speed (0: as fast as commands come) and the fault
    limits."""
    clock: str
    safe_voltage: float
    command_min_v: float
    command_max_v: float
    samples_batch: int
    max_speed: float = 0.0
    fault_limits: FaultLimits = FaultLimits()


class HardwareLoop:
    """One valve's loop over ``backend`` (see the module's docstring).  Outlets: ``on_position(y_m)`` each period
    (may call ``accept_command`` from within: a direct controller link), ``on_batch(rows)`` for each full batch of
    rows (time [s], voltage [V], position [m]; a view valid during the call), ``on_advanced(t_next_s)`` after each
    lockstep period, ``on_fault(fault)`` when one is latched.  ``logger()`` gives an object with ``info``,
    ``warning`` and ``error`` (looked up at each line); ``clock()`` the monotonic wall clock [s].  ``active`` False: commands refused (a managed node outside
    its active state)."""

    def __init__(self, backend: ValveBackend, settings: LoopSettings, samples_per_period: int, command_timeout_s: float,
                 logger: Callable[[], Any], on_position: Callable[[float], None] = lambda y: None,
                 on_batch: Callable[[np.ndarray], None] = lambda rows: None,
                 on_advanced: Optional[Callable[[float], None]] = None,
                 on_fault: Callable[[Fault], None] = lambda fault: None,
                 clock: Callable[[], float] = time.monotonic):
        self.clock = clock   # the wall clock the watchdog and the checks measure [s] (a test's own: simulated time)
        self.backend, self.settings = backend, settings
        self.samples_per_period = samples_per_period
        self.control_period_s = samples_per_period * backend.sample_period_s
        self.command_timeout_s = command_timeout_s
        self.logger = logger
        self.on_position, self.on_batch, self.on_advanced, self.on_fault = on_position, on_batch, on_advanced, on_fault
        self.loop_timing = LoopTiming(self.control_period_s)
        # the per-command warnings, each at most this often (their counts say how many there were)
        self._say_rejected, self._say_clamped = Throttle(1.0, clock), Throttle(1.0, clock)
        self._say_refused_in_fault, self._say_late = Throttle(2.0, clock), Throttle(5.0, clock)
        self._say_glitch, self._say_refused_inactive = Throttle(1.0, clock), Throttle(2.0, clock)
        self.glitches, self._unsaid_glitches = 0, 0   # backend calls that raised once and succeeded when retried
        self._glitch_times: collections.deque = collections.deque()
        self.refused_inactive = 0
        self.active = False
        self.opened = False
        self.step_budget = -1
        self.inactive_state = "inactive"   # how a refusal outside active names the state
        self.reset_counters()

    def reset_counters(self) -> None:
        """The loop's state before the first period: no command held, the watchdog not armed, nothing counted."""
        s = self.settings
        self._batch = np.empty((s.samples_batch + self.samples_per_period, 3))   # rows awaiting a batch
        # a batch fills a period at a time: it goes out at the first whole number of periods >= samples_batch
        self.full_batch_rows = -(-s.samples_batch // self.samples_per_period) * self.samples_per_period
        self._batch_rows = 0
        self.held_command: Optional[float] = None
        now = self.clock()
        self.last_valid_command_wall = now
        self.timed_out = False
        self.armed = False  # the watchdog runs from the first valid command on (until then: safe voltage)
        self.command_since_publish = False
        self.last_publish_wall = now
        self._pace_due: Optional[float] = None   # max_speed: the wall time the next period may start
        self.rejected = self.clamped = self.late_commands = self.periods = 0
        self.last_position_m = float("nan")   # the last position published [m]
        self.fault: Optional[Fault] = None
        self.safe_written = True          # while in fault: whether the safe voltage was written
        self._sample_check = SampleCheck(s.fault_limits)
        self.last_rows_wall = now
        self.refused_in_fault = 0

    # ------------------------------------------------------------------ open, close
    def open(self) -> None:
        """Open the backend at the safe voltage (nothing driven: commands wait for ``active``)."""
        self.backend.open()
        self.opened = True
        self.backend.write_voltage(self.settings.safe_voltage)

    def close(self, publish: bool = True, say: Optional[Callable[[str], None]] = None) -> bool:
        """The safe voltage, the batch flushed (``publish`` False: not, its outlet is gone, e.g. after Ctrl-C), the
        backend closed; whether the safe voltage was written (True when the backend was not open).  A backend that
        raises as it closes is said (``say``, default the logger's error line) and the loop is closed all the same."""
        if not self.opened:
            return True
        self.opened = False
        written = self.try_safe_voltage()
        try:
            if publish:
                self.flush_samples()
        finally:
            try:
                self.backend.close()
            except Exception as exc:
                (say or self.logger().error)(f"closing the backend raised {exc!r}")
        return written

    def start(self) -> None:
        """Commands applied from now on (at the safe voltage until the first valid one: the watchdog not armed)."""
        now = self.clock()
        self.armed, self.timed_out = False, False
        self.last_valid_command_wall = self.last_rows_wall = now
        self.active = True

    def stop(self) -> bool:
        """Commands refused from now on; the batch flushed and the safe voltage written (whether it was)."""
        self.active = False
        self.flush_samples()
        return self.try_safe_voltage()

    # ------------------------------------------------------------------ commands
    def validate(self, v: float) -> Optional[float]:
        """``v`` [V] clamped to the command range (counted, said); None for a non-finite one (rejected)."""
        s = self.settings
        if not math.isfinite(v):
            self.rejected += 1
            if self._say_rejected.due():
                self.logger().warning(f"rejected non-finite voltage command {v!r} ({self.rejected} so far)")
            return None
        if v < s.command_min_v or v > s.command_max_v:
            self.clamped += 1
            clamped = min(max(v, s.command_min_v), s.command_max_v)
            if self._say_clamped.due():
                self.logger().warning(f"clamped voltage command {v:.4g} V to {clamped:.4g} V ({self.clamped} so far)")
            return clamped
        return v

    def accept_command(self, v: float) -> None:
        """A voltage command [V]: refused in fault and outside active (counted, said), checked, then written (the
        real-time clock) or run for a period (lockstep)."""
        if self.fault is not None:
            self.refused_in_fault += 1
            if self._say_refused_in_fault.due():
                self.logger().warning(f"command refused: in fault ({self.fault.kind}; {self.refused_in_fault} "
                                      f"refused so far): valve_command reset once the cause is gone")
            return
        if not self.active:
            self.refused_inactive += 1
            if self._say_refused_inactive.due():
                self.logger().warning(f"command refused: valve_hardware is {self.inactive_state}, not active "
                                      f"({self.refused_inactive} refused so far): ~/change_state activate")
            return
        v = self.validate(v)
        if v is None:
            return
        realtime = self.settings.clock == "realtime"
        if self.loop_timing.commanded() is False and realtime and self.periods > 1:
            self.late_commands += 1
            if self._say_late.due():
                self.logger().warning(f"command arrived more than a period after its measurement "
                                      f"({self.late_commands} so far): the loop runs with extra delay")
        self.last_valid_command_wall = self.clock()
        self.command_since_publish = True
        self.armed = True
        if self.timed_out:
            self.timed_out = False
            self.logger().info("valid command received: resuming")
        if realtime:
            self.write(v)
            return
        if self.periods == 0:
            self.advance_and_publish()  # y_0 first: a commander that did not wait for it
        if self.step_budget == 0:
            self.held_command = v
            return
        self.apply_lockstep(v)

    def apply_lockstep(self, v: float) -> None:
        if not self.write(v):
            return
        if self.settings.max_speed:
            self.keep_pace()
        self.advance_and_publish()
        if self.step_budget > 0:
            self.step_budget -= 1
            if self.step_budget == 0:
                self.flush_samples()

    def set_step_budget(self, budget: int) -> None:
        """Lockstep: run ``budget`` more periods and pause (-1: free-running; 0: paused, the batch flushed); a
        command held while paused is applied once budget is granted."""
        if budget == self.step_budget:
            return
        if budget == -1:                       # free-running <-> paced (a pacer's grants are not logged)
            self.logger().info("lockstep: free-running")
        elif self.step_budget == -1:
            self.logger().info(f"lockstep: paced, {budget} period(s) granted" if budget else "lockstep: paused")
        self.step_budget = budget
        if budget == 0:
            self.flush_samples()  # paused: everything so far goes out
        else:
            self.last_valid_command_wall = self.clock()
            if self.held_command is not None:
                v, self.held_command = self.held_command, None
                self.apply_lockstep(v)

    # ------------------------------------------------------------------ time
    def keep_pace(self) -> None:
        """max_speed: wait until the next period may start (at most a period of the valve's time over max_speed:
        this runs in the command's callback).  A loop more than PACE_SLACK_S behind its pace (paused, or slower
        than it) starts afresh from now instead of running flat out to catch up."""
        step = self.control_period_s / self.settings.max_speed
        now = self.clock()
        if self._pace_due is None or now - self._pace_due > PACE_SLACK_S:
            self._pace_due = now
        elif self._pace_due > now:
            time.sleep(self._pace_due - now)
            # the watchdog measures the commander's silence, and it cannot answer before this period's position
            # goes out: the wait is ours (a pace slower than command_timeout_s would otherwise trip it)
            self.last_valid_command_wall = self.clock()
        self._pace_due += step

    def advance_and_publish(self) -> None:
        """Lockstep: the backend one control period on, its rows checked and published."""
        try:
            rows = self.backend.advance(self.samples_per_period)
        except Exception as exc:  # a backend's failure, whatever its type: the fault names it
            self.enter_fault("read_failed", f"advance raised {exc!r}")
            return
        if not self.sound(rows):
            return
        self.publish(rows)
        if self.on_advanced is not None:
            self.on_advanced(float(rows[-1, 0]) + self.backend.sample_period_s)

    def publish(self, rows: np.ndarray) -> None:
        """A period's rows out: the last position to ``on_position``, the rows into the batch."""
        if rows.shape[0] == 0:
            return
        self.periods += 1
        self.command_since_publish = False
        self.last_publish_wall = self.clock()
        y = float(rows[-1, 2])
        self.last_position_m = y
        self.loop_timing.measured()
        self.on_position(y)
        self.collect(rows)

    def collect(self, rows: np.ndarray) -> None:
        """Copy rows into the preallocated batch; a full batch goes to ``on_batch``."""
        k, n = rows.shape[0], self._batch_rows
        if n + k > self._batch.shape[0]:
            self.flush_samples()
            n = 0
            if k > self._batch.shape[0]:  # more than a batch at once (a long stall): sent as it is
                self.on_batch(rows)
                return
        self._batch[n:n + k] = rows
        self._batch_rows = n + k
        if self._batch_rows >= self.settings.samples_batch:
            self.flush_samples()

    def flush_samples(self) -> None:
        if self._batch_rows == 0:
            return
        n, self._batch_rows = self._batch_rows, 0
        self.on_batch(self._batch[:n])

    def check_watchdog(self) -> bool:
        """True when the watchdog fired just now (the safe voltage written)."""
        if self.timed_out or not self.armed or self.step_budget == 0:
            return False
        silent = self.clock() - self.last_valid_command_wall
        if silent < self.command_timeout_s:
            return False
        self.timed_out = True
        self.logger().warning(f"no valid command for {silent:.3f} s (timeout {self.command_timeout_s} s): "
                              f"applying safe_voltage {self.settings.safe_voltage} V")
        self.write(self.settings.safe_voltage)
        return True

    def tick(self) -> None:
        """The real-time clock's period: in fault the safe voltage retried; outside active the backend drained;
        else the watchdog, then the backend's new rows checked and published."""
        if self.fault is not None:
            self.while_in_fault()
            return
        if not self.active:
            if self.opened:
                try:
                    self.backend.read_samples()
                except Exception:   # checked again once active
                    pass
            return
        self.check_watchdog()
        rows = self.read()
        if rows is None or not self.sound(rows):
            return
        self.publish(rows)

    # ------------------------------------------------------------------ faults
    def write(self, v: float) -> bool:
        """Write ``v`` [V]; a write that raises is retried once at once (a glitch: said and counted), a second
        failure latches the fault (False)."""
        try:
            self.backend.write_voltage(v)
            return True
        except Exception as first:  # a backend's failure, whatever its type
            try:
                self.backend.write_voltage(v)
            except Exception as exc:  # the fault names it
                self.enter_fault("write_failed", f"write_voltage({v:.4g} V) raised {exc!r} twice in a row")
                return False
            self.glitch(f"write_voltage({v:.4g} V)", first)
            return True

    def read(self) -> Optional[np.ndarray]:
        """The backend's new rows; a read that raises is retried once at once (a glitch: said and counted), a second
        failure latches the fault (None)."""
        try:
            return self.backend.read_samples()
        except Exception as first:
            try:
                rows = self.backend.read_samples()
            except Exception as exc:
                self.enter_fault("read_failed", f"read_samples raised {exc!r} twice in a row")
                return None
            self.glitch("read_samples", first)
            return rows

    def glitch(self, what: str, exc: BaseException) -> None:
        """A backend call that raised and succeeded when retried at once: counted (``glitches_in_last_minute`` and
        ``glitches``) and said at WARN, at most once a second (with the count since the last line): a DAQ that
        glitches every few seconds must not look healthy."""
        now = self.clock()
        self.glitches += 1
        self._glitch_times.append(now)
        self._unsaid_glitches += 1
        if self._say_glitch.due():
            more = f" ({self._unsaid_glitches} since the last line)" if self._unsaid_glitches > 1 else ""
            self.logger().warning(f"DAQ glitch: {what} raised {exc!r}, retried at once and done{more}; "
                                  f"{self.glitches_in_last_minute(now)} in the last minute, {self.glitches} in all "
                                  f"(two in a row latch a fault)")
            self._unsaid_glitches = 0

    def glitches_in_last_minute(self, now: float) -> int:
        while self._glitch_times and self._glitch_times[0] < now - GLITCH_WINDOW_S:
            self._glitch_times.popleft()
        return len(self._glitch_times)

    def sound(self, rows: np.ndarray) -> bool:
        """Whether a read's rows may be published: finite, plausible, not frozen; samples arriving at all on the
        real-time clock.  Otherwise the fault is latched."""
        now = self.clock()
        if rows.shape[0] == 0:
            silent = now - self.last_rows_wall
            if self.settings.clock == "realtime" and self.periods and silent >= self.settings.fault_limits.missing_samples_s:
                self.enter_fault("no_samples", f"no samples from the backend for {silent:.2f} s")
            return False
        self.last_rows_wall = now
        problem = self._sample_check.check(rows)
        if problem is not None:
            self.enter_fault(*problem)
            return False
        return True

    def enter_fault(self, kind: str, detail: str) -> None:
        """Latch a fault (a further one while latched is counted): the batch out, the safe voltage, said; then
        ``on_fault``."""
        if self.fault is not None:
            self.fault = Fault(self.fault.kind, self.fault.detail, self.fault.first_at_s, self.fault.count + 1)
            return
        self.fault = Fault(kind, detail, self.clock())
        self.flush_samples()
        self.safe_written = self.try_safe_voltage()
        safe = self.settings.safe_voltage
        held = (f"safe voltage {safe} V applied" if self.safe_written else
                f"the safe voltage {safe} V could NOT be written: retrying every period")
        self.logger().error(f"fault {kind}: {detail}; {held}; commands refused until ~/reset")
        self.on_fault(self.fault)

    def try_safe_voltage(self) -> bool:
        try:
            self.backend.write_voltage(self.settings.safe_voltage)
            return True
        except Exception:
            return False

    def retry_safe_voltage(self) -> None:
        if not self.safe_written and self.try_safe_voltage():
            self.safe_written = True
            self.logger().error(f"in fault {self.fault.kind}: safe voltage {self.settings.safe_voltage} V applied "
                                f"at last")

    def while_in_fault(self) -> None:
        """Each period in fault: the safe voltage again until a write succeeds; the backend drained."""
        self.retry_safe_voltage()
        try:
            self.backend.read_samples()
        except Exception:
            pass

    def reset(self) -> tuple[bool, str]:
        """Leave the fault once the backend writes the safe voltage and reads sound samples again: (cleared, what
        happened in words).  No fault: (True, "no fault")."""
        if self.fault is None:
            return True, "no fault"
        fault = self.fault
        try:
            self.backend.write_voltage(self.settings.safe_voltage)
            rows = self.backend.read_samples() if self.settings.clock == "realtime" else np.zeros((0, 3))
        except Exception as exc:
            return False, f"fault {fault.kind} kept: the backend still fails ({exc!r})"
        problem = SampleCheck(self.settings.fault_limits).check(rows)
        if problem is not None:
            return False, f"fault {fault.kind} kept: {problem[0]}: {problem[1]}"
        self.fault, self.safe_written = None, True
        self._sample_check.reset()
        now = self.clock()
        self.last_rows_wall = now
        self.armed, self.timed_out = False, False   # at the safe voltage until the next valid command
        self.last_valid_command_wall = now
        return True, (f"fault {fault.kind} cleared ({fault.count} occurrence(s)); safe voltage applied, commands "
                      f"accepted" + ("" if rows.shape[0] else "; no samples to check yet: the next period's are "
                                                               "checked as every period's"))
