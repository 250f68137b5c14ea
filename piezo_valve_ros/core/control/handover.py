"""What the valve went through while another node drove it: the applied voltages' turning points, so the controller
that takes over again resumes with its inverses' operators in the valve's state, not a synchronised one at the
last voltage (after an identification's wide swings the two differ by up to the loop's width: under OL HC, with no
feedback to take it away, the whole of it stays as a tracking error).  Nothing here imports ROS."""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..model.hysteresis import GPIM, dominant_turning_points

__all__ = ["AppliedPath", "KEEP_RAW"]

KEEP_RAW = 4096   # applied voltages kept as they came before they are reduced to their dominant turning points


class AppliedPath:
    """The voltages applied [V] since the operators were last in a known state (``start_state``, the forward model's
    operator states then; None: the synchronised state at the first voltage), reduced to the turning points that
    still set the operators (``dominant_turning_points``: exact, and bounded for a valve in operation)."""

    def __init__(self, start_v: float, start_state: Optional[np.ndarray] = None):
        self.start_state = None if start_state is None else np.array(start_state, dtype=float)
        self._points: list[float] = [float(start_v)]
        self._raw: list[float] = []

    def extend(self, voltages_v) -> None:
        """Voltages applied after the last ones, in order [V]; non-finite ones are not what the valve got (the
        hardware rejects them) and are skipped."""
        self._raw.extend(float(v) for v in np.asarray(voltages_v, float).reshape(-1) if np.isfinite(v))
        if len(self._raw) >= KEEP_RAW:
            self._reduce()

    def _reduce(self) -> None:
        self._points = list(dominant_turning_points(self._points + self._raw))
        self._raw = []

    @property
    def last_v(self) -> float:
        return self._raw[-1] if self._raw else self._points[-1]

    def points(self) -> tuple[float, ...]:
        """The path's first voltage and the turning points that still set the operators, ending with the last."""
        self._reduce()
        return tuple(self._points)

    def state(self, model: GPIM) -> np.ndarray:
        """``model``'s operator states at the path's end, from ``start_state`` (or the synchronised state at the
        path's first voltage) through every voltage applied since."""
        path = np.asarray(self.points(), float)
        start = model.virgin_state(float(path[0])) if self.start_state is None else self.start_state
        if self.start_state is not None and self.start_state.shape != (model.n,):
            start = model.virgin_state(float(path[0]))   # a model of another size came in meanwhile
        _, final = model.run(path, start)
        return final
