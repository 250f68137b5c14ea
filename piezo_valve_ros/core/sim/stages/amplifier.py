"""The amplifier: input clip, gain and offset, current (slew) limit."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .base import Link, StageSwitch


@dataclass(frozen=True)
class AmplifierParams:
    """Noliac NDR6220-like amplifier: input 0..10 V -> -100..+100 V on the control electrode.

    Slew limit = current limit / actuator capacitance.  ``capacitance_f`` = 3 uF is our
    assumption for the CMBR08 control electrode (the paper gives none): 1.5 A / 3 uF = 500 V/ms,
    so an ideal full step is rate limited (0.4 ms for 200 V) while the paper's 2 ms ramps are not.
    """

    enabled: bool = True
    input_min_v: float = 0.0
    input_max_v: float = 10.0
    gain: float = 20.0  # V out per V in
    output_offset_v: float = -100.0
    current_limit_a: float = 1.5
    capacitance_f: float = 3.0e-6

    @property
    def slew_v_per_s(self) -> float:
        return self.current_limit_a / self.capacitance_f


class Amplifier:
    """Input clip, gain and offset, current (slew) limit; out: the input-equivalent voltage [V] the bender sees."""

    def __init__(self, p: AmplifierParams, dt: float, v0: float):
        self.p, self.limit = p, p.slew_v_per_s * dt
        self.electrode_v = p.gain * v0 + p.output_offset_v
        self.last_voltage_v = v0

    def step(self, v: float, k: int) -> float:
        p = self.p
        v = min(max(v, p.input_min_v), p.input_max_v)
        self.last_voltage_v = v
        target = p.gain * v + p.output_offset_v
        if p.enabled:
            self.electrode_v += min(max(target - self.electrode_v, -self.limit), self.limit)
        else:
            self.electrode_v = target
        return (self.electrode_v - p.output_offset_v) / p.gain

    def run(self, v: np.ndarray, k0: int) -> np.ndarray:
        p = self.p
        v = np.clip(v, p.input_min_v, p.input_max_v)
        self.last_voltage_v = float(v[-1])
        target = p.gain * v + p.output_offset_v
        electrode = self._slew_limit(target) if p.enabled else target
        self.electrode_v = float(electrode[-1])
        return (electrode - p.output_offset_v) / p.gain

    def _slew_limit(self, target: np.ndarray) -> np.ndarray:
        """Rate limiter u_k = u_{k-1} + clip(target_k - u_{k-1}, +-S dt), loop only where it binds."""
        limit = self.limit
        out = target.copy()
        prev = self.electrode_v
        k = 0
        n = target.size
        while k < n:
            # follow the target exactly while every step is within the limit
            steps = np.abs(np.diff(np.concatenate(([prev], target[k:]))))
            bad = np.flatnonzero(steps > limit)
            if bad.size == 0:
                return out
            k += int(bad[0])
            prev = float(out[k - 1]) if k > 0 else prev
            # limited stretch: integrate sample by sample until the output meets the target
            while k < n:
                delta = min(max(target[k] - prev, -limit), limit)
                prev += delta
                out[k] = prev
                k += 1
                if prev == target[k - 1]:
                    break
        return out


SWITCH = StageSwitch("slew_limit", "amplifier current limit", lambda c: c.amplifier.enabled,
                     lambda c, on: replace(c, amplifier=replace(c.amplifier, enabled=on)))


def _build(config, v0: float):
    return Amplifier(config.amplifier, config.dt, v0), v0


LINK = Link("amplifier", _build)
