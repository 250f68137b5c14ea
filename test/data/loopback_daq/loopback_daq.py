"""An out-of-tree valve backend, as a DAQ vendor's package would ship it (used by test_tools.py).

A loopback "DAQ": the position it measures is ``gain_m_per_v * (command - centre_v)`` after a first-order
lag of ``time_constant_s``, sampled every ``sample_period_s``.  It knows nothing of piezo_valve_ros's
internals: only the public ``ValveBackend`` interface and the entry-point group in its dist-info.
"""
import math
import time

import numpy as np

from piezo_valve_ros.backends import BackendParameter, ValveBackend


class LoopbackBackend(ValveBackend):
    PARAMETERS = (BackendParameter("gain_m_per_v", 10e-6, "position per volt [m/V]"),
                  BackendParameter("centre_v", 5.0, "command at zero position [V]"),
                  BackendParameter("time_constant_s", 2e-3, "first-order lag [s]"),
                  BackendParameter("sample_period_s", 1e-4, "sampling period [s]"))
    supports_lockstep = True

    def __init__(self, gain_m_per_v, centre_v, time_constant_s, sample_period_s, initial_voltage_v):
        self.gain, self.centre, self.sample_period_s = gain_m_per_v, centre_v, sample_period_s
        self.alpha = 1.0 - math.exp(-sample_period_s / time_constant_s)
        self.voltage = initial_voltage_v
        self.position = gain_m_per_v * (initial_voltage_v - centre_v)
        self.index = 0
        self.t0 = None

    @classmethod
    def from_parameters(cls, values, safe_voltage_v):
        for name in ("gain_m_per_v", "time_constant_s", "sample_period_s"):
            value = values[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"loopback.{name} must be a number > 0, got {value!r}")
        return cls(float(values["gain_m_per_v"]), float(values["centre_v"]), float(values["time_constant_s"]),
                   float(values["sample_period_s"]), safe_voltage_v)

    def open(self):
        self.t0 = time.monotonic()

    def write_voltage(self, voltage_v):
        self.voltage = float(voltage_v)

    def advance(self, n_samples):
        rows = np.empty((n_samples, 3))
        target = self.gain * (self.voltage - self.centre)
        for i in range(n_samples):
            self.position += self.alpha * (target - self.position)
            rows[i] = (self.index * self.sample_period_s, self.voltage, self.position)
            self.index += 1
        return rows

    def read_samples(self):
        due = int((time.monotonic() - self.t0) / self.sample_period_s) - self.index
        return self.advance(due) if due > 0 else np.zeros((0, 3))

    def close(self):
        pass
