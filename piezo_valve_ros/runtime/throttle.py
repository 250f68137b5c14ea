"""A repeated log line's throttle.  No ROS import."""
from __future__ import annotations

import math
import time
from typing import Callable

__all__ = ["Throttle"]


class Throttle:
    """Whether a repeated log line is due: the first time, then at most once per ``period_s`` [s].  Asked before
    the logger is called: rclpy's logger looks up its caller's source file on every call, throttled or not
    (about a millisecond), so a throttled warning on a per-command path stalled the 10 kHz loop at every call,
    and a stall that made commands late made the next ones late through their warnings."""

    __slots__ = ("period_s", "_next", "_clock")

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic):
        self.period_s, self._next, self._clock = float(period_s), -math.inf, clock

    def due(self) -> bool:
        now = self._clock()
        if now < self._next:
            return False
        self._next = now + self.period_s
        return True
