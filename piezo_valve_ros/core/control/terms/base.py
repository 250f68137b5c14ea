"""What a compensator term is: a part of ``CompensationModel`` with its own ``valve_controller`` parameters."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

Getter = Callable[[str, Callable[[str, Any], Any]], Optional[Any]]   # (name, conversion) -> value, None if refused


@dataclass(frozen=True)
class Term:
    """One term of the compensation model besides the GPIM, declared in its own module: the ``CompensationModel``
    field it fills, its ``valve_controller`` parameters (name -> (default, description)), how its value is
    written to them (``write``: value -> {name: value}, every parameter, so applying them replaces an older
    value) and read from them (``read``: a getter -> value, None where a parameter was refused; the getter
    collects the reasons)."""

    field: str
    parameters: dict[str, tuple[Any, str]]
    write: Callable[[Any], dict[str, Any]]
    read: Callable[[Getter], Optional[Any]]


def floats(values) -> list[float]:
    return [float(x) for x in values]
