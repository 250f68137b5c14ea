"""A contract test kit for hardware backends, for a DAQ vendor's own tests, and a fault-injecting wrapper.

    from piezo_valve_ros.backends.kit import check_backend

    def test_my_daq_keeps_the_backend_contract():
        assert check_backend(lambda: MyDaqBackend.from_parameters(defaults, 5.0)) == []

:func:`check_backend` opens a fresh backend, writes voltages and reads on the wall clock for a while, and returns
every way it breaks the contract ``valve_hardware`` relies on (``backends.ValveBackend``): rows of (time [s],
command [V], position [m]) as a (k, 3) float array, finite, in time order without gaps or repeats at
``sample_period_s``, the command written showing in the rows, ``close`` working after ``open`` and after a
failure.  :class:`FaultInjectingBackend` wraps any backend and makes it fail the ways a real DAQ does (a read or
write that raises, NaN samples, a frozen sensor, silence): what ``valve_hardware`` must turn into a latched
fault (``faults``), as ``test/test_faults.py`` checks.  No ROS import.
"""
from __future__ import annotations

import math
import time
from typing import Callable, Optional

import numpy as np

from ..core.defaults import CONTROL_PERIOD_S
from .base import ValveBackend

__all__ = ["check_backend", "FaultInjectingBackend", "INJECTABLE_FAULTS"]

INJECTABLE_FAULTS = ("read_raises", "read_raises_once", "nan", "write_raises", "write_raises_once", "stuck", "silent")
TIME_TOLERANCE = 0.01   # sample instants within 1 % of a sample period of the grid


def check_backend(make: Callable[[], ValveBackend], seconds: float = 0.3, period_s: float = CONTROL_PERIOD_S,
                  voltages: tuple[float, ...] = (5.0, 6.0, 4.0)) -> list[str]:
    """Every way the backend ``make()`` returns breaks the contract (empty: it keeps it).  It is opened, each of
    ``voltages`` [V] is written in turn for a share of ``seconds`` while ``read_samples`` is called every
    ``period_s``, and it is closed (twice: the node closes a failed backend once more at shutdown)."""
    problems: list[str] = []
    backend = make()
    dt = float(getattr(backend, "sample_period_s", math.nan))
    if not (math.isfinite(dt) and dt > 0):
        return [f"sample_period_s must be a number > 0, got {dt!r}"]
    rows: list[np.ndarray] = []
    written: list[tuple[int, float]] = []   # (rows read before the write, voltage)
    try:
        backend.open()
    except Exception as exc:
        return [f"open raised {exc!r}"]
    try:
        for v in voltages:
            backend.write_voltage(v)
            written.append((sum(len(r) for r in rows), v))
            deadline = time.monotonic() + seconds / len(voltages)
            while time.monotonic() < deadline:
                time.sleep(period_s)
                got = backend.read_samples()
                problem = _shape_problem(got)
                if problem:
                    problems.append(problem)
                    break
                rows.append(np.asarray(got, float))
    except Exception as exc:
        problems.append(f"raised while running: {exc!r}")
    finally:
        for attempt in ("close", "a second close"):
            try:
                backend.close()
            except Exception as exc:
                problems.append(f"{attempt} raised {exc!r}")
    if problems:
        return problems
    data = np.concatenate(rows) if rows else np.zeros((0, 3))
    expected = seconds / dt
    if data.shape[0] < 0.5 * expected:
        problems.append(f"{data.shape[0]} samples in {seconds:g} s at a sample period of {dt:g} s (expected about "
                        f"{expected:.0f}): samples are lost or the sample period is wrong")
    if data.shape[0] and not np.isfinite(data).all():
        problems.append("non-finite values in the rows")
    if data.shape[0] > 1:
        steps = np.diff(data[:, 0])
        if not np.all(np.abs(steps - dt) <= TIME_TOLERANCE * dt):
            bad = steps[np.abs(steps - dt) > TIME_TOLERANCE * dt][0]
            problems.append(f"sample times must step by sample_period_s ({dt:g} s) from read to read, without gaps "
                            f"or repeats; one step is {bad:g} s")
    for (start, v), (end, _) in zip(written, written[1:] + [(data.shape[0], math.nan)]):
        # the command column shows what was written, from a sample or two after the write on
        shown = data[min(start + 2, end):end, 1]
        if shown.size and not np.allclose(shown, v, atol=1e-9):
            problems.append(f"the command column does not show the {v:g} V written (it shows {shown[0]:g} V)")
    return problems


def _shape_problem(rows) -> Optional[str]:
    if not isinstance(rows, np.ndarray):
        return f"read_samples must return a numpy array, got {type(rows).__name__}"
    if rows.ndim != 2 or rows.shape[1] != 3:
        return f"read_samples must return an array of shape (k, 3), got {rows.shape}"
    if not np.issubdtype(rows.dtype, np.floating):
        return f"read_samples must return floats, got {rows.dtype}"
    return None


class FaultInjectingBackend(ValveBackend):
    """``inner`` with the faults of INJECTABLE_FAULTS switched on by ``inject(kind)`` (None: healthy):
    ``read_raises`` (every read raises OSError), ``read_raises_once`` (the next read only), ``nan`` (positions
    NaN), ``write_raises``, ``write_raises_once`` (the next write only), ``stuck`` (the position frozen at its last
    value), ``silent`` (no samples).  Every
    voltage written is kept in ``writes``."""

    def __init__(self, inner: ValveBackend):
        self.inner = inner
        self.sample_period_s = inner.sample_period_s
        self.supports_lockstep = inner.supports_lockstep
        self.fault: Optional[str] = None
        self.writes: list[float] = []
        self._frozen: Optional[float] = None

    def inject(self, kind: Optional[str]) -> None:
        if kind is not None and kind not in INJECTABLE_FAULTS:
            raise ValueError(f"fault must be one of {', '.join(INJECTABLE_FAULTS)} or None, got {kind!r}")
        self.fault, self._frozen = kind, None

    def open(self) -> None:
        self.inner.open()

    def write_voltage(self, voltage_v: float) -> None:
        if self.fault == "write_raises":
            raise OSError("injected: DAQ write timed out")
        if self.fault == "write_raises_once":
            self.fault = None
            raise OSError("injected: DAQ write glitch")
        self.writes.append(float(voltage_v))
        self.inner.write_voltage(voltage_v)

    def _faulty(self, rows: np.ndarray) -> np.ndarray:
        if self.fault == "nan":
            rows = rows.copy()
            rows[:, 2] = np.nan
        elif self.fault == "stuck" and rows.shape[0]:
            rows = rows.copy()
            if self._frozen is None:
                self._frozen = float(rows[0, 2])
            rows[:, 2] = self._frozen
        elif self.fault == "silent":
            return np.zeros((0, 3))
        return rows

    def read_samples(self) -> np.ndarray:
        if self.fault == "read_raises":
            raise OSError("injected: DAQ disconnected")
        if self.fault == "read_raises_once":
            self.fault = None
            raise OSError("injected: DAQ glitch")
        return self._faulty(self.inner.read_samples())

    def advance(self, n_samples: int) -> np.ndarray:
        if self.fault in ("read_raises", "read_raises_once"):
            if self.fault == "read_raises_once":
                self.fault = None
            raise OSError("injected: DAQ disconnected")
        return self._faulty(self.inner.advance(n_samples))

    def close(self) -> None:
        self.inner.close()
