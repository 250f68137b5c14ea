"""Checking parameter values (ROS-free): each function returns the value in its Python type or raises
ValueError naming the parameter and what was wrong."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Optional

__all__ = ["as_float", "as_int", "as_float_list", "as_bool", "PERIOD_TOLERANCE", "whole_periods", "same_period",
           "ParameterSpec", "POSITIVE", "NON_NEGATIVE", "ruled", "field_problems", "Settings", "from_parameter"]

PERIOD_TOLERANCE = 1e-6   # times [s] closer than this share of the longer one are equal (rounding, not a choice)


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


def whole_periods(span_s: float, period_s: float) -> int | None:
    """``span_s / period_s`` [s / s] when it is a whole number (to PERIOD_TOLERANCE), else None (also for a
    ratio that is not finite)."""
    ratio = span_s / period_s
    if not math.isfinite(ratio):
        return None
    k = round(ratio)
    return int(k) if abs(k * period_s - span_s) <= PERIOD_TOLERANCE * max(abs(span_s), period_s) else None


POSITIVE = "positive"          # a field's rule (``ruled``): a finite number > 0
NON_NEGATIVE = "non-negative"  # ... a finite number >= 0


def ruled(default: Any, rule: str) -> Any:
    """A dataclass field with ``default`` and its rule (POSITIVE or NON_NEGATIVE), declared once beside it:
    ``field_problems`` checks every such field, so a settings class lists its cross-field checks alone."""
    if rule not in (POSITIVE, NON_NEGATIVE):
        raise ValueError(f"unknown rule {rule!r}")
    return field(default=default, metadata={"rule": rule})


def field_problems(settings: Any) -> list[str]:
    """One line for each field of the dataclass ``settings`` declared with a rule (``ruled``) that its value breaks,
    in the order of the fields."""
    out = []
    for f in fields(settings):
        rule, x = f.metadata.get("rule"), getattr(settings, f.name)
        if rule is None:
            continue
        number = isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
        if rule == POSITIVE and not (number and x > 0):
            out.append(f"{f.name} must be > 0, got {x!r}")
        elif rule == NON_NEGATIVE and not (number and x >= 0):
            out.append(f"{f.name} must be a finite number >= 0, got {x!r}")
    return out


def same_period(a_s: float, b_s: float) -> bool:
    """Whether two periods [s] are the same (to PERIOD_TOLERANCE)."""
    return abs(a_s - b_s) <= PERIOD_TOLERANCE * max(abs(a_s), abs(b_s))


@dataclass(frozen=True)
class ParameterSpec:
    """One node (or backend) parameter, declared once: the node declares it from here (typed descriptor, range,
    read-only), ``--help`` lists it, and the handbook's parameter tables are written from it
    (``scripts/parameter_tables.py``).  ``low``/``high``: the admissible range of a number, where it has one;
    ``choices``: the admissible values of a string.  :meth:`checked` applies them.  ROS-free: backends declare
    theirs with it too."""

    name: str
    default: Any
    description: str
    read_only: bool = False
    low: Optional[float] = None
    high: Optional[float] = None
    choices: tuple[str, ...] = ()

    def checked(self, value: Any) -> Any:
        """``value`` as this parameter's type (a number as int or float like the default, a bool, a string, a list
        of numbers) within its range or choices; ValueError with a one-line reason naming the parameter."""
        d = self.default
        if isinstance(d, bool):
            out: Any = as_bool(self.name, value)
        elif isinstance(d, str):
            if not isinstance(value, str):
                raise ValueError(f"{self.name} must be a string, got {value!r}")
            out = value
        elif isinstance(d, int):
            out = as_int(self.name, value)
        elif isinstance(d, (list, tuple)):
            return as_float_list(self.name, value)
        else:
            out = as_float(self.name, value)
        if self.choices and out not in self.choices:
            raise ValueError(f"{self.name} must be one of {', '.join(self.choices)}, got {out!r}")
        if self.low is not None and self.high is not None and not self.low <= out <= self.high:
            raise ValueError(f"{self.name} must lie in [{self.low:g}, {self.high:g}], got {out!r}")
        if self.low is not None and out < self.low:
            raise ValueError(f"{self.name} must be >= {self.low:g}, got {out!r}")
        if self.high is not None and out > self.high:
            raise ValueError(f"{self.name} must be <= {self.high:g}, got {out!r}")
        return out

    @property
    def type_name(self) -> str:
        d = self.default
        if isinstance(d, bool):
            return "bool"
        if isinstance(d, str):
            return "string"
        if isinstance(d, int):
            return "integer"
        if isinstance(d, (list, tuple)):
            return "double array"
        return "double"

    def range_text(self) -> str:
        if self.choices:
            return " or ".join(self.choices)
        if self.low is None and self.high is None:
            return ""
        return f"{'' if self.low is None else format(self.low, 'g')}..{'' if self.high is None else format(self.high, 'g')}"

    def help_line(self) -> str:
        extras = [self.type_name, f"default {self.default!r}"]
        if self.choices:
            extras.append(f"one of {', '.join(self.choices)}")
        elif self.range_text():
            extras.append(f"range {self.range_text()}")
        if self.read_only:
            extras.append("read-only")
        return f"  {self.name} ({', '.join(extras)})\n      {self.description}"

    def under(self, prefix: str, read_only: Optional[bool] = None) -> "ParameterSpec":
        """This parameter named ``prefix`` + its name (a backend's under ``<backend>.``, a composed process's node's
        under ``<node>:``)."""
        return replace(self, name=prefix + self.name, read_only=self.read_only if read_only is None else read_only)


def from_parameter(name: str) -> Any:
    """A field of a :class:`Settings` dataclass read from the parameter ``name`` (default: the field's own name;
    e.g. ``max_speed: float = from_parameter("lockstep.max_speed")``)."""
    return field(metadata={"parameter": name})


class Settings:
    """A node's (or backend's) start-up settings as one frozen dataclass, read from its ``ParameterSpec`` s: each
    field the checked value of the parameter of its name (or ``from_parameter``'s), the cross-field checks in
    ``problems``.  A subclass is a frozen dataclass; ``from_specs`` builds it or raises one ValueError with every
    reason."""

    @classmethod
    def from_specs(cls, specs: Any, values: Any):
        """The settings from parameter ``values`` (name -> value) checked by ``specs`` (name -> ParameterSpec)."""
        kwargs, problems = {}, []
        for f in fields(cls):
            name = f.metadata.get("parameter", f.name)
            try:
                kwargs[f.name] = specs[name].checked(values[name])
            except ValueError as exc:
                problems.append(str(exc))
        if problems:
            raise ValueError("; ".join(problems))
        out = cls(**kwargs)
        problems = out.problems()
        if problems:
            raise ValueError("; ".join(problems))
        return out

    def problems(self) -> list[str]:
        """Cross-field checks: one line for each rule the values break together (empty: fine)."""
        return []
