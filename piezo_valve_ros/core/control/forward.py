"""The controller's model run forwards: what the valve would do under a voltage if the model were right.

:class:`ModelValve` steps it once per sample (the tuner's and the evaluation's valve) or runs it over a block
(the health monitor's prediction); both share one state.  Nothing here imports ROS.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..model.dynamics import first_order_lag
from ..model.hysteresis import PlayOperatorBank
from ..model.rate_dependence import hysteresis_stream
from . import terms as _terms
from .compensation import CompensationModel

__all__ = ["ModelValve"]


class ModelValve:
    """The identified model run forwards, ``step(v) -> position [m]`` once per ``dt`` (the same timing as
    ``simulator.SimulatedValve``) or ``run(v) -> positions [m]`` over a block: the (rate-dependent) GPIM's
    H, then ``S = M(H) + sum g_i (lag_i[H] - H)`` (saturation map and creep, as ``compensation`` inverts
    them), then G_v, then the terms on the spool's path (``Term.forward``: the backlash's play), folded in the
    order of ``terms.TERMS``.  No noise, no amplifier.  The operators start virgin at ``initial_voltage_v`` or in
    ``state`` (e.g. ``GPIM.state_after`` a voltage history); creep and G_v at rest at that output."""

    def __init__(self, model: CompensationModel, dt: float, initial_voltage_v: float,
                 state: Optional[np.ndarray] = None):
        self.model, self.dt, self.initial_voltage_v = model, float(dt), float(initial_voltage_v)
        self.initial_state = None if state is None else np.array(state, float)
        self.reset()

    def reset(self) -> None:
        m = self.model
        self._gpim = hysteresis_stream(m.gpim, m.rate_widening_v, self.dt, self.initial_voltage_v)
        if self.initial_state is not None:
            self._gpim.bank = PlayOperatorBank(m.gpim.thresholds, self.initial_state)
        y0 = m.gpim.output_from_state(self._gpim.state)
        self._creep = [(g, first_order_lag(tau, self.dt)) for tau, g in zip(m.creep.time_constants_s, m.creep.gains)
                       if g]
        for _, lag in self._creep:
            lag.reset(y0)
        self._map = m.output_map
        self._gv = m.valve_model.discretise(self.dt)
        self._gv.reset(self._map.value(y0))
        x0 = self._map.value(y0)
        self._outputs = [step for term in _terms.TERMS if term.place == "output"
                         for step in [term.forward(m.terms[term.field], x0)] if step is not None]

    def step(self, voltage_v: float) -> float:
        h = self._gpim.step(voltage_v)
        y = self._map.value(h)
        for g, lag in self._creep:
            y += g * (lag.step(h) - h)
        x = self._gv.step(y)
        for output in self._outputs:
            x = output.step(x)
        return x * 1e-6

    def run(self, voltage_v: np.ndarray) -> np.ndarray:
        """Positions [m] for a block of voltages [V], one per ``dt``; the state carries on as with ``step``."""
        v = np.asarray(voltage_v, float)
        if hasattr(self._gpim, "run"):
            h = self._gpim.run(v)
        else:   # the rate-dependent GPIM runs per sample
            h = np.fromiter((self._gpim.step(float(x)) for x in v), float, v.size)
        y = self._map.values(h)
        for g, lag in self._creep:
            y += g * (lag.run(h) - h)
        x = self._gv.run(y)
        for output in self._outputs:
            x = output.run(x)
        return x * 1e-6
