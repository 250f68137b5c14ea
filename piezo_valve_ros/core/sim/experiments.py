"""In-process experiments: the simulated valve in the loop with a controller.

Timing convention (the same as the ROS lockstep rig): the valve first applies its initial
voltage for one sample and reports ``y_0``; then for every period k the controller turns
(reference_k, y_k) into ``v_k`` and the valve applies ``v_k`` for one sample, giving ``y_{k+1}``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Optional

import numpy as np

from ..metrics import BandwidthMetrics, StepMetrics, bandwidth_metrics, fundamental, step_metrics
from .signals import PAPER_STEPS_UM, step_reference_m, stepped_sine_reference_m
from .simulator import SimulatedValve, ValveSimConfig
from ..control.strategies import ControllerConfig, ValveController

__all__ = ["ClosedLoopRecord", "run_closed_loop", "responses", "step_test", "paper_step_tests", "frequency_response",
           "DEFAULT_SWEEP_HZ", "simulate_rows"]

DEFAULT_SWEEP_HZ = np.geomspace(2.0, 250.0, 22)


@dataclass
class ClosedLoopRecord:
    reference_m: np.ndarray
    command_v: np.ndarray
    position_m: np.ndarray  # position measured when the command was computed (y_k)


def run_closed_loop(valve: SimulatedValve, controller: ValveController, reference_m: np.ndarray,
                    first_position_m: Optional[float] = None) -> ClosedLoopRecord:
    """Run ``reference_m`` through controller and valve, one sample per period."""
    ref = np.asarray(reference_m, float)
    n = ref.size
    commands = np.empty(n)
    positions = np.empty(n)
    y = valve.step(valve.config.initial_voltage_v) if first_position_m is None else first_position_m
    ctl_step = controller.step
    valve_step = valve.step
    for k in range(n):
        positions[k] = y
        v = ctl_step(ref[k], y)
        commands[k] = v
        y = valve_step(v)
    return ClosedLoopRecord(ref, commands, positions)


def responses(valve: SimulatedValve, record: ClosedLoopRecord) -> np.ndarray:
    """Position [m] answering each command of ``record``: the response to command k appears at k + 1, so the
    last one is measured by applying the last command for one more sample."""
    return np.append(record.position_m[1:], valve.step(record.command_v[-1]))


def run_delayed_loop(valve: SimulatedValve, controller: ValveController, reference_m: np.ndarray,
                     delay_periods: Callable[[int], int], samples_per_period: int = 1) -> ClosedLoopRecord:
    """A loop whose measurements reach the controller late (two processes on a busy computer).

    Every control period the valve runs ``samples_per_period`` samples at the last command and is measured;
    the measurement of period k reaches the controller once ``delay_periods(now)`` periods have passed
    (0: at once), and the controller answers it with the reference of period k.  ``position_m`` holds the
    position at the start of each period, ``command_v`` the command in force during it.
    """
    from collections import deque
    ref = np.asarray(reference_m, float)
    n = ref.size
    commands, positions = np.empty(n), np.empty(n)
    queue: deque = deque()
    v = valve.config.initial_voltage_v
    step = controller.step
    for k in range(n):
        for _ in range(samples_per_period):
            y = valve.step(v)
        positions[k], commands[k] = y, v
        queue.append((k, y))
        lag = delay_periods(k)
        while queue and k - queue[0][0] >= lag:
            kk, yy = queue.popleft()
            v = step(ref[kk], yy)
    return ClosedLoopRecord(ref, commands, positions)


def _fresh(sim_config: ValveSimConfig, ctl_config: ControllerConfig, controller_kwargs: dict):
    valve = SimulatedValve(sim_config)
    controller = ValveController(replace(ctl_config, dt=sim_config.dt), **controller_kwargs)
    controller.reset(sim_config.initial_voltage_v)
    return valve, controller


def step_test(ctl_config: ControllerConfig, start_um: float, end_um: float,
              sim_config: ValveSimConfig = ValveSimConfig(), hold_before_s: float = 0.1, hold_after_s: float = 0.1,
              **controller_kwargs) -> tuple[StepMetrics, ClosedLoopRecord, int]:
    """One of the paper's step tests (2 ms ramp) on a fresh valve; returns (metrics, record, ramp index)."""
    valve, controller = _fresh(sim_config, ctl_config, controller_kwargs)
    ref, start = step_reference_m(sim_config.dt, start_um, end_um, hold_before_s, hold_after_s)
    rec = run_closed_loop(valve, controller, ref)
    y = responses(valve, rec)
    return step_metrics(y, start, start_um, end_um, sim_config.dt), rec, start


def paper_step_tests(ctl_config: ControllerConfig, sim_config: ValveSimConfig = ValveSimConfig(),
                     **controller_kwargs) -> list[StepMetrics]:
    return [step_test(ctl_config, a, b, sim_config, **controller_kwargs)[0] for a, b in PAPER_STEPS_UM]


def frequency_response(ctl_config: ControllerConfig, amplitude_um: float,
                       sim_config: ValveSimConfig = ValveSimConfig(), freqs_hz=DEFAULT_SWEEP_HZ,
                       periods: int = 4, **controller_kwargs) -> tuple[np.ndarray, np.ndarray, BandwidthMetrics]:
    """Stepped-sine response (position / demand) about 0 um; returns (freqs, complex H, metrics)."""
    dt = sim_config.dt
    h = np.empty(len(freqs_hz), complex)
    for i, f in enumerate(freqs_hz):
        valve, controller = _fresh(sim_config, ctl_config, controller_kwargs)
        ref, k0 = stepped_sine_reference_m(dt, f, amplitude_um, periods=periods)
        rec = run_closed_loop(valve, controller, ref)
        y = responses(valve, rec)
        h[i] = fundamental(y[k0:], f, dt) / fundamental(ref[k0:], f, dt)
    return np.asarray(freqs_hz, float), h, bandwidth_metrics(freqs_hz, h)


def simulate_rows(voltage_v: np.ndarray, sim_config: ValveSimConfig = ValveSimConfig()) -> np.ndarray:
    """Open-loop run of a fresh simulated valve as ``samples`` rows: time [s], applied voltage [V], position [m]."""
    valve = SimulatedValve(sim_config)
    v = np.clip(np.asarray(voltage_v, float), sim_config.amplifier.input_min_v, sim_config.amplifier.input_max_v)
    y = valve.run(v)
    return np.column_stack((np.arange(v.size) * sim_config.dt, v, y))
