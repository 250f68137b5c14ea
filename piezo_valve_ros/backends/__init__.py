"""Hardware backends of ``valve_hardware``: the interface a DAQ implements and the simulated valve (``base``), the
faults a DAQ can show and the checks that find them (``faults``), and a contract test kit with a fault-injecting
wrapper (``kit``).  A backend installed by another package registers under the entry-point group
``piezo_valve_ros.backends``.  No ROS import."""
from __future__ import annotations

from .base import (ENTRY_POINT_GROUP, BackendParameter, SimBackend, ValveBackend, available_backends,
                   backend_class, backend_parameters, register_backend, sim_config_from_parameters)
from .faults import Fault, FaultLimits, SampleCheck
from .kit import FaultInjectingBackend, check_backend

__all__ = ["ValveBackend", "SimBackend", "BackendParameter", "backend_parameters", "register_backend",
           "backend_class", "available_backends", "sim_config_from_parameters", "ENTRY_POINT_GROUP", "Fault",
           "FaultLimits", "SampleCheck", "FaultInjectingBackend", "check_backend"]
