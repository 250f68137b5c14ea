"""Checking parameter values (ROS-free): each function returns the value in its Python type or raises
ValueError naming the parameter and what was wrong."""
from __future__ import annotations

import math
from typing import Any

__all__ = ["as_float", "as_int", "as_float_list", "as_bool"]


def as_float(name: str, value: Any) -> float:
    """A finite number (ints accepted, bools refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def as_int(name: str, value: Any) -> int:
    """An integer (a float with no fraction accepted, bools refused)."""
    if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
            or float(value) != int(value)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(value)


def as_float_list(name: str, value: Any) -> list[float]:
    """A list of finite numbers (a string is not one, though it iterates)."""
    if isinstance(value, (str, bytes)):
        raise ValueError(f"{name} must be a list of numbers, got {value!r}")
    try:
        return [as_float(name, x) for x in list(value)]
    except TypeError:
        raise ValueError(f"{name} must be a list of numbers, got {value!r}") from None


def as_bool(name: str, value: Any) -> bool:
    """A boolean (not a string such as 'false')."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be true or false, got {value!r}")
    return value
