"""The ROS-free core: models, inverse, simulator, strategies, identification, residual analysis and metrics, usable
from a notebook.  Each part exports its everyday names (``from piezo_valve_ros.core.identification import analyse,
Record``), imported on first use, so importing a part costs nothing until a name is used."""
from __future__ import annotations

from importlib import import_module
from typing import Callable


def lazy_exports(package: str, exports: dict[str, str]) -> tuple[list[str], Callable[[str], object]]:
    """(``__all__``, module ``__getattr__``) for ``package`` whose public ``exports`` map a name to the submodule
    (relative to the package) that defines it: a name is imported on first use (PEP 562) and kept."""
    def __getattr__(name: str) -> object:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(f"{package}.{exports[name]}"), name)
        import sys
        setattr(sys.modules[package], name, value)
        return value
    return sorted(exports), __getattr__


# the core's own modules' everyday names (metrics, runs, validation, blas, errors); ``lazy_exports`` stays a
# module attribute for the parts' faces
__all__, __getattr__ = lazy_exports(__name__, {
    "ErrorFigures": "metrics",
    "POSITIVE": "validation",
    "ParameterSpec": "validation",
    "PiezoValveError": "errors",
    "StepMetrics": "metrics",
    "THREAD_VARIABLES": "blas",
    "TimeWindow": "runs",
    "align_jumps": "runs",
    "bandwidth_metrics": "metrics",
    "error_figures": "metrics",
    "field_problems": "validation",
    "find_steps": "runs",
    "one_blas_thread_for_process": "blas",
    "receive_to_sample_time": "runs",
    "reference_on_samples": "runs",
    "rms": "metrics",
    "ruled": "validation",
    "same_period": "validation",
    "step_metrics": "metrics",
    "whole_periods": "validation",
})
