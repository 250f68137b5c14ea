"""The hardware's loop without ROS (``runtime.hardware_loop``): read -> check -> write, the watchdog, the fault latch,
the batch and the lockstep budget, on the simulated valve behind the fault-injecting backend and a clock the test
moves.  No rclpy here: the loop is what ``valve_hardware`` wraps."""
import math
import subprocess
import sys

import numpy as np
import pytest

from piezo_valve_ros.backends import SimBackend
from piezo_valve_ros.backends import FaultInjectingBackend
from piezo_valve_ros.core.sim import ValveSimConfig
from piezo_valve_ros.runtime import HardwareLoop, LoopSettings

SAFE_V = 5.0
PERIOD_S = 1e-3


class Said:
    """A logger that keeps what it is told, by level."""

    def __init__(self):
        self.lines = []

    def __getattr__(self, level):
        return lambda text: self.lines.append((level, text))


class Bench:
    """A loop over the simulated valve (10 kHz samples, 1 kHz periods) on a clock the test moves; what it puts out."""

    def __init__(self, clock="realtime", batch=50, timeout=0.05):
        self.now = 10.0
        self.daq = FaultInjectingBackend(SimBackend(ValveSimConfig(dt=1e-4, seed=2), clock=lambda: self.now))
        self.said = Said()
        self.positions, self.batches, self.faults, self.advanced = [], [], [], []
        self.loop = HardwareLoop(self.daq, LoopSettings(clock, SAFE_V, 0.0, 10.0, batch), 10, timeout,
                                 logger=lambda: self.said, on_position=self.positions.append,
                                 on_batch=lambda rows: self.batches.append(rows.copy()),
                                 on_advanced=self.advanced.append if clock == "lockstep" else None,
                                 on_fault=self.faults.append, clock=lambda: self.now)

    def periods(self, n, command=None):
        for k in range(n):
            if command is not None:
                self.loop.accept_command(command(k))
            self.now += PERIOD_S
            self.loop.tick()


def test_it_drives_only_once_started_and_publishes_checked_rows_in_batches():
    b = Bench()
    b.loop.accept_command(7.0)                      # not open, not started: refused and said
    assert b.daq.writes == [] and b.loop.refused_inactive == 1 and "not active" in b.said.lines[-1][1]
    b.loop.open()
    assert b.daq.writes == [SAFE_V]
    b.periods(5, lambda k: 7.0)                     # open but not started: drained, nothing published
    assert b.daq.writes == [SAFE_V] and b.positions == [] and b.loop.refused_inactive == 6
    b.loop.start()
    b.periods(12, lambda k: 6.0 + 0.1 * k)
    assert b.daq.writes[-1] == pytest.approx(7.1) and len(b.positions) == 12 and b.loop.periods == 12
    assert [len(rows) for rows in b.batches] == [50, 50]        # 10 rows a period, 50 a batch
    assert np.all(np.diff(np.concatenate(b.batches)[:, 0]) > 0)
    b.loop.accept_command(11.0)                     # clamped, counted, said
    assert b.daq.writes[-1] == 10.0 and b.loop.clamped == 1 and "clamped" in b.said.lines[-1][1]
    b.loop.accept_command(math.nan)                 # rejected: never written
    assert b.daq.writes[-1] == 10.0 and b.loop.rejected == 1
    assert b.loop.stop() and b.daq.writes[-1] == SAFE_V and [len(r) for r in b.batches][-1] == 20   # flushed
    assert b.loop.close() and b.loop.opened is False


def test_the_watchdog_applies_the_safe_voltage_when_commands_stop_and_resumes_on_the_next():
    b = Bench(timeout=0.05)
    b.loop.open()
    b.loop.start()
    b.periods(10, lambda k: 7.0)
    b.periods(49)                                   # 49 ms of silence: not yet
    assert not b.loop.timed_out and b.daq.writes[-1] == 7.0
    b.periods(2)
    assert b.loop.timed_out and b.daq.writes[-1] == SAFE_V and "no valid command" in b.said.lines[-1][1]
    b.periods(1, lambda k: 6.0)
    assert not b.loop.timed_out and b.daq.writes[-1] == 6.0 and b.said.lines[-1] == ("info", "valid command received: resuming")


def test_a_fault_latches_safe_and_only_a_sound_backend_clears_it():
    b = Bench()
    b.loop.open()
    b.loop.start()
    b.periods(10, lambda k: 7.0)
    b.daq.inject("read_raises_once")                # a glitch: retried at once, counted, no fault
    b.periods(1, lambda k: 7.0)
    assert b.loop.fault is None and b.loop.glitches == 1 and "DAQ glitch" in b.said.lines[-1][1]
    b.daq.inject("nan")
    b.periods(1, lambda k: 7.0)
    assert b.loop.fault.kind == "non_finite_sample" and b.faults == [b.loop.fault]
    assert b.daq.writes[-1] == SAFE_V and b.said.lines[-1][0] == "error"
    b.periods(5, lambda k: 7.0)                     # refused while latched, the valve held safe
    assert b.daq.writes[-1] == SAFE_V and b.loop.refused_in_fault == 5 and len(b.faults) == 1
    b.daq.inject("read_raises")
    cleared, why = b.loop.reset()
    assert not cleared and why.startswith("fault non_finite_sample kept: the backend still fails")
    b.daq.inject(None)
    cleared, why = b.loop.reset()
    assert cleared and "cleared" in why and b.loop.fault is None and not b.loop.armed
    b.periods(3, lambda k: 6.5)
    assert b.daq.writes[-1] == 6.5 and b.loop.fault is None


def test_lockstep_runs_a_period_per_command_and_holds_one_while_paused():
    b = Bench("lockstep")
    b.loop.open()
    b.loop.start()
    b.loop.step_budget = 2
    b.loop.accept_command(6.0)                      # y_0 first, then a period at 6 V
    b.loop.accept_command(6.5)
    assert b.loop.periods == 3 and b.loop.step_budget == 0 and len(b.advanced) == 3
    assert b.advanced[-1] == pytest.approx(3 * PERIOD_S, abs=1e-9)   # the valve's time after three periods
    b.loop.accept_command(7.0)                      # paused: held, not written
    assert b.daq.writes[-1] == 6.5 and b.loop.held_command == 7.0 and b.loop.periods == 3
    b.loop.set_step_budget(-1)                      # free-running: the held command goes out
    assert b.daq.writes[-1] == 7.0 and b.loop.periods == 4 and b.loop.held_command is None


def test_the_loop_imports_no_ros():
    out = subprocess.run([sys.executable, "-c", "import sys, piezo_valve_ros.runtime.hardware_loop; "
                          "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'std_msgs')))"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
