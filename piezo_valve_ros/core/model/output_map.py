"""A static output map and its inverse: ``S = H + sum_i c_i f_i(h)`` of the hysteresis output H [um], the
square and cube of the normalised output and squared hinges at its ends (loop ends flattened by friction or
an end stop).  Identification fits it as the ``saturation`` effect; the controller inverts it where it rises.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ["OutputMap", "terms", "term_rows", "KNOTS", "TERM_COUNT", "MIN_MAP_SLOPE", "MAP_CHECK_MARGIN"]

KNOTS = (0.4, 0.6, 0.8)
TERM_COUNT = 2 + 2 * len(KNOTS)
MIN_MAP_SLOPE = 0.1       # the compensated map must rise at least this steeply [um/um] to be inverted ...
MAP_CHECK_MARGIN = 0.1    # ... over the drive's output range widened by this share on each side
MAP_CHECK_POINTS = 801
INVERSE_TOL_UM = 1e-12    # Newton's method stops at steps this small (relative to 1 + |H|) ...
INVERSE_ITERATIONS = 50   # ... or after this many


def terms(h: np.ndarray) -> np.ndarray:
    """(N, TERM_COUNT) terms of the normalised output ``h``: h^2, h^3, then max(+-h - k, 0)^2 per knot.  The cube is
    h^2 times h (numpy's ``power`` for a cube calls the C library's pow, ~100x the cost of a product)."""
    h = np.asarray(h, float)
    square = h * h
    return np.column_stack([square, square * h] + [np.maximum(s * h - k, 0.0) ** 2 for s in (1.0, -1.0) for k in KNOTS])


def term_rows(h: np.ndarray) -> np.ndarray:
    """:func:`terms` as rows (TERM_COUNT, N), bit for bit, each written in place (no temporaries, no strided
    column writes): what a fit's design takes."""
    h = np.asarray(h, float).reshape(-1)
    out = np.empty((TERM_COUNT, h.size))
    np.multiply(h, h, out=out[0])
    np.multiply(out[0], h, out=out[1])
    row = 2
    for s in (1.0, -1.0):
        for k in KNOTS:
            r = out[row]
            np.multiply(s, h, out=r)
            np.subtract(r, k, out=r)
            np.maximum(r, 0.0, out=r)
            np.multiply(r, r, out=r)
            row += 1
    return out


@dataclass(frozen=True)
class OutputMap:
    """The saturation compensator: the static map ``S = H + sum_i c_i f_i(h)``, ``h = (H - centre) / half``,
    of the hysteresis output H [um] (f_i: :func:`terms`).  No coefficients: the identity.

    ``value`` and ``slope`` are scalar and allocation-free (the controller calls them every period)."""

    centre_um: float = 0.0
    half_range_um: float = 1.0
    coefficients_um: tuple[float, ...] = ()

    @property
    def active(self) -> bool:
        return any(c != 0.0 for c in self.coefficients_um)

    def problems(self, lo_um: Optional[float] = None, hi_um: Optional[float] = None, floor: float = 0.0) -> list[str]:
        """Reasons the map cannot be used; with an output range [lo_um, hi_um] also where ``slope - floor``
        falls below MIN_MAP_SLOPE on it (widened by MAP_CHECK_MARGIN): there it has no inverse."""
        c = self.coefficients_um
        if len(c) not in (0, TERM_COUNT):
            return [f"saturation.coefficients_um needs {TERM_COUNT} values (or none), got {len(c)}"]
        if not all(math.isfinite(x) for x in (self.centre_um, self.half_range_um) + tuple(c)):
            return ["saturation: non-finite value"]
        if self.half_range_um <= 0:
            return [f"saturation.half_range_um must be > 0, got {self.half_range_um}"]
        if not self.active or lo_um is None or hi_um is None:
            return []
        pad = MAP_CHECK_MARGIN * (hi_um - lo_um)
        H = np.linspace(lo_um - pad, hi_um + pad, MAP_CHECK_POINTS)
        slope = self.slopes(H) - floor
        if np.any(slope < MIN_MAP_SLOPE):
            bad = H[slope < MIN_MAP_SLOPE]
            return [f"saturation: the output map flattens (slope {slope.min() + floor:.3g} um/um) between "
                    f"{bad[0]:.4g} and {bad[-1]:.4g} um: no inverse there"]
        return []

    def values(self, H: np.ndarray) -> np.ndarray:
        """S for an array of H [um]."""
        H = np.asarray(H, float)
        if not self.active:
            return H.copy()
        return H + terms((H - self.centre_um) / self.half_range_um) @ np.asarray(self.coefficients_um)

    def slopes(self, H: np.ndarray) -> np.ndarray:
        """dS/dH for an array of H [um]."""
        H = np.asarray(H, float)
        if not self.active:
            return np.ones_like(H)
        h = (H - self.centre_um) / self.half_range_um
        c = np.asarray(self.coefficients_um)
        d = 2.0 * c[0] * h + 3.0 * c[1] * h * h
        for i, k in enumerate(KNOTS):
            d = d + 2.0 * c[2 + i] * np.maximum(h - k, 0.0) - 2.0 * c[2 + len(KNOTS) + i] * np.maximum(-h - k, 0.0)
        return 1.0 + d / self.half_range_um

    def value(self, H: float) -> float:
        """S [um] for one H [um]."""
        c = self.coefficients_um
        if not c:
            return H
        h = (H - self.centre_um) / self.half_range_um
        s = H + c[0] * h * h + c[1] * h * h * h
        n = len(KNOTS)
        for i, k in enumerate(KNOTS):
            up, down = h - k, -h - k
            if up > 0.0:
                s += c[2 + i] * up * up
            if down > 0.0:
                s += c[2 + n + i] * down * down
        return s

    def solve(self, rhs: float, h_start: float, g: float = 0.0, lo: float = -math.inf, hi: float = math.inf
              ) -> float:
        """The H [um] in [lo, hi] with ``value(H) - g H = rhs``, exact to INVERSE_TOL_UM where the map minus
        g H rises on [lo, hi] (as ``problems`` checks on the output range); ``lo``/``hi`` when the solution lies
        beyond them.  Newton's method from ``h_start``, kept inside the bracket by bisection: a demand far
        outside the range (a dynamic feedforward's peak, say) cannot send it where the cubic terms run away."""
        if lo > -math.inf and self.value(lo) - g * lo - rhs >= 0.0:
            return lo
        if hi < math.inf and self.value(hi) - g * hi - rhs <= 0.0:
            return hi
        a, b = lo, hi                       # f(a) < 0 < f(b): the root is between
        h = min(max(h_start, lo), hi)
        for _ in range(INVERSE_ITERATIONS):
            f = self.value(h) - g * h - rhs
            if f > 0.0:
                b = h
            else:
                a = h
            d = self.slope(h) - g
            new = h - (f / d if d > MIN_MAP_SLOPE else f / MIN_MAP_SLOPE)
            if not a <= new <= b:           # Newton left the bracket: bisect (both ends finite by then)
                new = 0.5 * (a + b) if a > -math.inf and b < math.inf else min(max(new, a), b)
            done = abs(new - h) <= INVERSE_TOL_UM * (1.0 + abs(new))
            h = new
            if done:
                break
        return h

    def slope(self, H: float) -> float:
        """dS/dH [um/um] at one H [um]."""
        c = self.coefficients_um
        if not c:
            return 1.0
        h = (H - self.centre_um) / self.half_range_um
        d = 2.0 * c[0] * h + 3.0 * c[1] * h * h
        n = len(KNOTS)
        for i, k in enumerate(KNOTS):
            up, down = h - k, -h - k
            if up > 0.0:
                d += 2.0 * c[2 + i] * up
            if down > 0.0:
                d -= 2.0 * c[2 + n + i] * down
        return 1.0 + d / self.half_range_um
