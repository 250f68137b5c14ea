"""Hardware backends of the ``valve_hardware`` node (ROS-free).

A backend owns the valve: it applies voltage commands and samples the spool position.  Backends are
found by name: the ``sim`` backend here, and any class another installed package lists under the entry-point
group ``piezo_valve_ros.backends`` (so a DAQ needs no change to this package)::

    # my_daq/backend.py
    from .base import BackendParameter, ValveBackend

    class MyDaqBackend(ValveBackend):
        PARAMETERS = (BackendParameter("device", "/dev/daq0", "DAQ device"),)   # -> my_daq.device

        @classmethod
        def from_parameters(cls, values, safe_voltage_v):   # validated values by name; ValueError if bad
            return cls(values["device"])

        def open(self): ...                  # connect, start acquisition
        def write_voltage(self, v): ...      # applied from the next sample on [V]
        def read_samples(self): ...          # new rows (time [s], command [V], position [m]) since last call
        def close(self): ...                 # stop acquisition (the node has applied safe_voltage before)

    # its setup.py:  entry_points={"piezo_valve_ros.backends": ["my_daq = my_daq.backend:MyDaqBackend"]}

then ``valve_hardware --ros-args -p backend:=my_daq -p my_daq.device:=/dev/daq1``.  The node declares each
backend parameter as ``<backend>.<name>`` (read-only, refused with the backend's reason when invalid).
Backends that can advance time on demand (simulators) also implement ``advance(n)``, which is what the
node's ``lockstep`` clock uses.
"""
from __future__ import annotations

import copy
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, Optional, Type

import numpy as np

from ..core.sim.simulator import STAGE_SWITCHES, SimulatedValve, ValveSimConfig
from ..core.sim.stages import STAGE_PARAMETERS
from ..core.validation import ParameterSpec, Settings
from ..core.model.drive import CENTRE_VOLTAGE_V

__all__ = ["ValveBackend", "SimBackend", "BackendParameter", "backend_parameters", "register_backend", "backend_class",
           "available_backends", "sim_config_from_parameters", "ENTRY_POINT_GROUP"]

ENTRY_POINT_GROUP = "piezo_valve_ros.backends"
_REGISTERED: Dict[str, Type["ValveBackend"]] = {}


def BackendParameter(name: str, default: Any, description: str, low: Optional[float] = None,
                     high: Optional[float] = None) -> ParameterSpec:
    """One parameter of a backend (the nodes' own spec type): declared by the node as ``<backend>.<name>``,
    read-only (``backend_parameters``)."""
    return ParameterSpec(name, default, description, read_only=True, low=low, high=high)


def backend_parameters(name: str, backend_type: Optional[Type["ValveBackend"]] = None) -> tuple[ParameterSpec, ...]:
    """The parameters of backend ``name`` (of ``backend_type``, else the registered class) as the hardware node
    declares them: under ``<name>.``, read-only, described as that backend's."""
    cls = backend_class(name) if backend_type is None else backend_type
    return tuple(replace(p.under(f"{name}.", read_only=True), description=f"{name} backend: {p.description}")
                 for p in cls.PARAMETERS)


def register_backend(name: str) -> Callable[[Type["ValveBackend"]], Type["ValveBackend"]]:
    """Register a backend class in this process (for backends defined in a test or a notebook; installed
    packages use the entry-point group instead)."""
    def deco(cls):
        _REGISTERED[name] = cls
        return cls
    return deco


def _entry_points():
    from importlib.metadata import entry_points
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def available_backends() -> list[str]:
    """Names of every backend this process can make."""
    return sorted(set(_REGISTERED) | set(_entry_points()))


def backend_class(name: str) -> Type["ValveBackend"]:
    """The backend class called ``name``; ValueError with the names available otherwise."""
    if name in _REGISTERED:
        return _REGISTERED[name]
    ep = _entry_points().get(name)
    if ep is None:
        raise ValueError(f"unknown backend {name!r}; available: {', '.join(available_backends())}")
    try:
        cls = ep.load()
    except Exception as exc:
        raise ValueError(f"backend {name!r} ({ep.value}) cannot be loaded: {type(exc).__name__}: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, ValveBackend)):
        raise ValueError(f"backend {name!r} ({ep.value}) is not a ValveBackend subclass")
    _REGISTERED[name] = cls
    return cls


class ValveBackend(ABC):
    """Interface between the hardware node and a valve."""

    sample_period_s: float = 1e-4
    supports_lockstep: bool = False
    PARAMETERS: tuple = ()   # ParameterSpec (BackendParameter), ...: declared by the node as "<backend name>.<name>"

    @classmethod
    def from_parameters(cls, values: dict, safe_voltage_v: float) -> "ValveBackend":
        """A backend from its parameters' values (by name, without the prefix) and the node's safe voltage
        [V] (applied at start-up); ValueError with the reason for a bad value."""
        return cls()

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

    def advance(self, n_samples: int) -> np.ndarray:  # pragma: no cover - only lockstep backends
        raise NotImplementedError(f"{type(self).__name__} cannot advance time on demand (no lockstep)")

    def prepare_realtime(self) -> None:
        """Called once after ``open``, before a real-time loop starts reading: do here whatever a first call of a
        per-period path would otherwise do inside a tick (imports, first-use allocations).  Optional."""


@dataclass(frozen=True)
class SimSettings(Settings):
    """The ``sim`` backend's own settings (the valve's sampling and noise seed); each stage's are its own
    (``stages.STAGE_PARAMETERS``), its switch its ``StageSwitch``."""

    seed: int
    sample_period_s: float        # [s]

    def problems(self) -> list[str]:
        return [] if self.sample_period_s > 0 else [f"sim.sample_period_s must be > 0, got {self.sample_period_s}"]


def sim_config_from_parameters(values: dict, initial_voltage_v: float = CENTRE_VOLTAGE_V) -> ValveSimConfig:
    """The simulated valve from the ``sim`` backend's parameter values (names without ``sim.``; missing ones
    take their defaults; effects switchable one by one); ValueError with every reason."""
    specs = {prm.name: prm.under("sim.") for prm in SimBackend.PARAMETERS}   # keyed by name, said as sim.<name>
    v = {name: spec.default for name, spec in specs.items()}
    v.update(values)
    problems = []
    config = replace(ValveSimConfig(), initial_voltage_v=float(initial_voltage_v))
    try:
        own = SimSettings.from_specs(specs, v)
        config = replace(config, dt=own.sample_period_s, seed=own.seed)
    except ValueError as exc:   # the stages still checked (against the default period): every reason in one refusal
        problems.append(str(exc))
    for stage in STAGE_PARAMETERS:   # each stage's settings, from its one declaration
        try:
            config = stage.settings.from_specs(specs, v).apply(config, config.dt)
        except ValueError as exc:
            problems.append(str(exc))
    for switch in STAGE_SWITCHES:    # each stage's switch, from its one declaration
        try:
            config = switch.set(config, specs[switch.name].checked(v[switch.name]))
        except ValueError as exc:
            problems.append(str(exc))
    if problems:
        raise ValueError("; ".join(problems))
    return config


def _sim_parameters() -> tuple:
    return (BackendParameter("seed", 0, "noise seed"),
            BackendParameter("sample_period_s", ValveSimConfig().dt, "sampling period [s]"),
            *(BackendParameter(s.name, s.is_on(ValveSimConfig()), s.description) for s in STAGE_SWITCHES),
            *(spec for stage in STAGE_PARAMETERS for spec in stage.specs))


@register_backend("sim")
class SimBackend(ValveBackend):
    """The simulated valve (``core.simulator``).  In real time it samples on the wall clock."""

    PARAMETERS = _sim_parameters()
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

    @classmethod
    def from_parameters(cls, values: dict, safe_voltage_v: float) -> "SimBackend":
        return cls(sim_config_from_parameters(values, safe_voltage_v))

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

    def prepare_realtime(self) -> None:
        """Run the batch path once on a scratch copy of the valve: a real-time reader that falls behind catches
        up through it, and its first run imported scipy.signal (0.5-0.9 s, a stall inside the very tick that
        catches up).  Lockstep never takes it at a cost to anyone, so its nodes keep the import lazy."""
        copy.deepcopy(self.valve).run(np.full(self.per_sample_below + 1, self._voltage))

    def close(self) -> None:
        self.is_open = False
