"""Hardware backends of the ``valve_hardware`` node (ROS-free).

A backend owns the valve: it applies voltage commands and samples the spool position.
To add real DAQ hardware, subclass :class:`ValveBackend`, implement the four methods and
register it::

    @register_backend("my_daq")
    class MyDaqBackend(ValveBackend):
        def open(self): ...                  # connect, start acquisition
        def write_voltage(self, v): ...      # applied from the next sample on [V]
        def read_samples(self): ...          # new rows (time [s], command [V], position [m]) since last call
        def close(self): ...                 # stop acquisition (the node has applied safe_voltage before)

then run ``valve_hardware --ros-args -p backend:=my_daq``.  ``read_position`` has a default
built on ``read_samples``.  Backends that can advance time on demand (simulators) also
implement ``advance(n)``, which is what the node's ``lockstep`` clock uses.
"""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import Callable, Dict, Type

import numpy as np

from .core.simulator import SimulatedValve, ValveSimConfig

__all__ = ["ValveBackend", "SimBackend", "register_backend", "make_backend", "BACKENDS"]

BACKENDS: Dict[str, Type["ValveBackend"]] = {}


def register_backend(name: str) -> Callable[[Type["ValveBackend"]], Type["ValveBackend"]]:
    def deco(cls):
        BACKENDS[name] = cls
        return cls
    return deco


def make_backend(name: str, **options) -> "ValveBackend":
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; registered: {', '.join(sorted(BACKENDS))}")
    return BACKENDS[name](**options)


class ValveBackend(ABC):
    """Interface between the hardware node and a valve."""

    sample_period_s: float = 1e-4
    supports_lockstep: bool = False

    @abstractmethod
    def open(self) -> None:
        ...

    @abstractmethod
    def write_voltage(self, voltage_v: float) -> None:
        ...

    @abstractmethod
    def read_samples(self) -> np.ndarray:
        """Rows (time [s], command [V], position [m]) acquired since the last call, shape (k, 3)."""

    @abstractmethod
    def close(self) -> None:
        ...

    _last_position_m: float = float("nan")

    def read_position(self) -> float:
        """Latest measured position [m]."""
        rows = self.read_samples()
        if rows.shape[0]:
            self._last_position_m = float(rows[-1, 2])
        return self._last_position_m

    def read_position_cached(self) -> float:
        """Latest position [m] already read, without sampling again."""
        return self._last_position_m

    def advance(self, n_samples: int) -> np.ndarray:  # pragma: no cover - only lockstep backends
        raise NotImplementedError(f"{type(self).__name__} cannot advance time on demand (no lockstep)")


@register_backend("sim")
class SimBackend(ValveBackend):
    """The simulated valve (``core.simulator``).  In real time it samples on the wall clock."""

    supports_lockstep = True
    per_sample_below = 14  # advance() steps sample by sample up to this many (batch path: ~70 us fixed cost)

    def __init__(self, config: ValveSimConfig = ValveSimConfig(), clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.sample_period_s = config.dt
        self._clock = clock
        self.valve = SimulatedValve(config)
        self._voltage = config.initial_voltage_v
        self._pending = np.zeros((0, 3))
        self._t0 = None
        self._done = 0
        self._phased = False
        self.is_open = False

    def open(self) -> None:
        self.valve.reset()
        self._t0 = self._clock()
        self._done = 0
        self._phased = False
        self.is_open = True

    def write_voltage(self, voltage_v: float) -> None:
        self._voltage = float(voltage_v)

    @property
    def voltage_v(self) -> float:
        """The command [V] applied from the next sample on."""
        return self._voltage

    def advance(self, n_samples: int) -> np.ndarray:
        """Run ``n_samples`` at the present command; returns their rows."""
        k0 = self.valve.sample_index
        dt = self.sample_period_s
        if n_samples <= self.per_sample_below:  # the batch path's fixed numpy cost dominates short runs
            rows = np.empty((n_samples, 3))
            step, v = self.valve.step, self._voltage
            for i in range(n_samples):
                y = step(v)
                rows[i, 0] = (k0 + i) * dt
                rows[i, 2] = y
            rows[:, 1] = self.valve.last_voltage_v
        else:
            y = self.valve.run(np.full(n_samples, self._voltage))
            rows = np.column_stack(((k0 + np.arange(n_samples)) * dt, np.full(n_samples, self.valve.last_voltage_v), y))
        self._done += n_samples
        self._last_position_m = float(rows[-1, 2])
        return rows

    def read_samples(self) -> np.ndarray:
        """Real-time use: everything due on the wall clock since the last call.

        The simulated sample clock locks its phase to the reader: each call nudges it by at most
        2.5 % of a sample so that the reader's instants sit mid-sample, where timer jitter of up to
        half a sample either way still returns exactly one control period of samples.  A reader
        later than that gets the samples it missed (the simulated valve never waits)."""
        now = self._clock()
        dt = self.sample_period_s
        if not self._phased:
            self._t0 = now - 0.5 * dt
            self._phased = True
        x = (now - self._t0) / dt
        due = int(x) - self._done
        self._t0 += (x - int(x) - 0.5) * dt * 0.05
        if due <= 0:
            return np.zeros((0, 3))
        return self.advance(due)

    def close(self) -> None:
        self.is_open = False
