"""The effect catalogue: one effect per module, each a small class (see ``base.Effect``).

A new effect is one module with one class, added to ``CATALOGUE`` below.
"""
from __future__ import annotations

from .asymmetry import Asymmetry
from .backlash import Backlash
from .base import EFFECT_RIDGE, Effect, NotCompensable
from .creep import Creep
from .drift import Drift
from .dynamics import Dynamics
from .saturation import Saturation

__all__ = ["CATALOGUE", "Effect", "NotCompensable", "EFFECT_RIDGE", "effect_class"]

CATALOGUE: tuple[type[Effect], ...] = (Creep, Dynamics, Asymmetry, Drift, Saturation, Backlash)


def effect_class(name: str) -> type[Effect]:
    for cls in CATALOGUE:
        if cls.name == name:
            return cls
    raise KeyError(f"unknown effect {name!r}; known: {', '.join(c.name for c in CATALOGUE)}")
