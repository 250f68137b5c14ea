"""Dynamics beyond the baseline's second-order G_v: a transport delay, extra poles (a lag or a resonance a second
order cannot represent) and rate-dependent hysteresis (the loop widens with the input rate).

Structure, nonlinear in its parameters (fitted by Gauss-Newton with the rest of the model):
* a transport delay between drive and sensor, in whole and fractional samples at any sample rate (``delay_s``:
  the Hammerstein structure's dead time; a DAQ pipeline, a conditioning filter, a sensor's own lag);
* G(s) gets a second unity-DC-gain pole pair, fourth order in all (a first-order lag: one pole, its partner far);
* the operators' thresholds grow with the input rate, ``r_j + sum_k c_k rho / (rho + rate_k)``: the
  rate-dependent Prandtl-Ishlinskii model of Al Janaideh and Krejci (thresholds as functions of the
  rate) with a widening that is linear at low rates and levels off, at the scales
  ``RATE_SCALES_V_S``; ``rho`` is |dv/dt| through each lag of ``RATE_FILTERS_S`` (cycling rates over
  three memories, the shortest 5 ms, not the slope inside a 2 ms ramp);
* the loading curve's slope grows with the input rate (Ang, Khosla and Riviere's modified PI model):
  ``(H - H_c) / H_h * rho / (rho + rate_k)`` for the same rate terms, linear in their coefficients [um].
For the subset search (one linear solve from the baseline) the extra poles are represented to first
order by fast lags of H (``lag_tau[H] - H`` is ``-tau s H`` for small tau) and the rate terms by their
exact sensitivities.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from ...model.dynamics import lag_bank
from ...model.rate_dependence import MAX_WIDENING_V, RATE_FILTERS_S, RATE_SCALES_V_S, TERM_COUNT
from ..records import Record
from .base import Effect, NotCompensable, normalised

__all__ = ["Dynamics", "FAST_LAGS_S", "MAX_WIDENING_V", "EXTRA_START", "MAX_DELAY_S"]

FAST_LAGS_S = (3e-4, 1e-3, 3e-3)   # first-order proxies of extra poles, for the subset search
# see Dynamics.has; the costliest fits first (they run side by side on a pool, the longest started first),
# "all" last (it starts from the best of those it contains)
FORMS = ("rates", "poles", "rate", "slope", "delay", "all")
STRUCTURES = ("delay", "poles", "rate", "slope")
MAX_DELAY_S = 0.05                          # a transport delay of at most this long [s]
SEARCH_DELAY_SAMPLES = (1, 2, 4)            # the subset search's delay proxies: H this many samples late
EXTRA_START = 3.0   # the extra pole pair starts this factor above G_v's natural frequency (well damped)


@dataclass(frozen=True)
class Dynamics(Effect):
    name = "dynamics"
    simulated_by = ("dynamics", "rate_dependence")
    compensated_by = ("rate_widening_v",)
    costly_refit = True   # six forms, each a Gauss-Newton fit (the poles' placed from several starts)
    telling_experiment = ("the same loop at several rates (0.1 to 10 Hz) and fast steps: a delay or a lag shows in "
                          "the first milliseconds after a step, rate-dependent hysteresis in a loop that widens with "
                          "the rate; a play or a static effect looks the same at every rate")
    signature = ("lag or ringing after fast moves beyond the second-order G_v, or a loop that widens with the "
                 "input rate: the residual follows fast lags (0.3-3 ms) of the model output, or the operators' "
                 "sensitivity to thresholds that grow with the input rate")
    form: str = "all"   # "delay", "poles", "rate", "slope", "rates", "all" or structures joined by "+" (see has)
    centre_um: float = 0.0   # H's centre and half span over the training record [um]: the slope terms' scale
    half_um: float = 1.0
    delay_held: bool = False   # the delay held where a refit starts it (chosen on held-out data), not fitted

    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> "Dynamics":
        lo, hi = float(np.min(H)), float(np.max(H))
        return cls(centre_um=0.5 * (lo + hi), half_um=max(0.5 * (hi - lo), 1e-9))

    def forms(self) -> list["Dynamics"]:
        """Each structure alone, both rate structures together (thresholds in proportion to the rate are a
        widening and a steeper slope at once) and all but the slope together, from the best of those it contains:
        fitted jointly from scratch they trade against each other and end in a poor optimum, so each form is fitted
        and the best on training data kept."""
        return [replace(self, form=f) for f in FORMS]

    def has(self, structure: str) -> bool:
        """Whether this form has ``structure``: its own, or every one but the rate-dependent slope for "all" (a
        slope that follows the rate terms fits a lag or a delay's share of the training record too, and loses it
        on held-out data; it stands alone against the others)."""
        if self.form == "rates":   # both rate structures: thresholds in proportion to the rate are both
            return structure in ("rate", "slope")
        if "+" in self.form:       # structures named one by one (``with_delay``)
            return structure in self.form.split("+")
        return self.form == structure or (self.form == "all" and structure != "slope")

    def with_delay(self) -> "Dynamics":
        """This form with a transport delay besides its own structures ("poles" -> "delay+poles")."""
        if self.has("delay"):
            return self
        return replace(self, form="+".join(["delay"] + [s for s in STRUCTURES if self.has(s)]))

    def contains(self, other: "Dynamics") -> bool:
        return all(self.has(s) for s in STRUCTURES if other.has(s))

    def switch_on(self, model):
        if self.has("rate") and not model.rate_widening_v:
            model = replace(model, rate_widening_v=(0.0,) * TERM_COUNT)
        if self.has("poles") and len(model.sections) == 1:
            w, _ = model.sections[0]
            model = replace(model, sections=model.sections + ((EXTRA_START * w, 1.1),))
        return model

    def carry(self, source, target):
        if source.term(self.name) is None:
            return target
        if self.has("rate") and source.rate_widening_v:
            target = replace(target, rate_widening_v=source.rate_widening_v)
        if self.has("poles") and len(source.sections) > 1:
            target = replace(target, sections=source.sections)
        if self.has("delay"):
            target = replace(target, delay_s=source.delay_s)
        return target

    def columns(self, ctx) -> np.ndarray:
        """The rate-dependent slope terms (rate form): the normalised output times each rate term."""
        if not self.has("slope"):
            return np.zeros((len(ctx.record), 0))
        return normalised(ctx.H, self.centre_um, self.half_um)[:, None] * ctx.rate_terms

    @property
    def nonlinear(self) -> bool:
        """A delay that is fitted, or rate-dependent thresholds (the slope form and a held delay are linear)."""
        return (self.has("delay") and not self.delay_held) or self.has("rate")

    def sensitivities(self, ctx) -> np.ndarray:
        columns = []
        if self.has("delay") and not self.delay_held:   # y(t - d): dy/dd = -dy/dt: G applied to -dS/dt
            columns.append(-np.gradient(ctx.H, ctx.dt)[:, None])
        if self.has("rate"):
            terms = ctx.rate_terms
            columns.append(ctx.widening_sensitivity(terms))
        return np.column_stack(columns) if columns else np.zeros((len(ctx.record), 0))

    def step(self, model, delta):
        delta = np.asarray(delta, float)
        if self.has("delay") and not self.delay_held:
            model = replace(model, delay_s=float(np.clip(model.delay_s + delta[0], 0.0, MAX_DELAY_S)))
            delta = delta[1:]
        if self.has("rate"):
            c = np.clip(np.asarray(model.rate_widening_v) + delta, -MAX_WIDENING_V, MAX_WIDENING_V)
            model = replace(model, rate_widening_v=tuple(float(x) for x in c))
        return model

    def search_columns(self, ctx) -> np.ndarray:
        """Fast lags of H (extra poles), H a few whole samples late (a delay, which a derivative represents only
        well below a sample), and the rate terms' exact sensitivities."""
        taus = [t for t in FAST_LAGS_S if t >= ctx.dt / 4]
        H = ctx.H
        shifts = [m for m in SEARCH_DELAY_SAMPLES if m * ctx.dt <= MAX_DELAY_S and m < H.size]
        late = [np.concatenate((np.full(m, H[0]), H[:-m])) - H for m in shifts]
        return np.column_stack([lag_bank(H, taus, ctx.dt) - H[:, None]] + late
                               + [replace(self, form="slope").columns(ctx), replace(self, form="rate").sensitivities(ctx)])

    def describe(self, model, coefs) -> dict:
        extra = model.sections[1:]
        return {"form": self.form, "extra_poles": [{"omega_rad_s": round(w, 3), "zeta": round(z, 4)} for w, z in extra],
                "delay_s": model.delay_s, "rate_widening_v": [float(x) for x in model.rate_widening_v],
                "rate_slope_um": [float(x) for x in np.asarray(coefs, float).reshape(-1)],
                "rate_scales_v_s": list(RATE_SCALES_V_S), "rate_filters_s": list(RATE_FILTERS_S)}

    def plot_axis(self, ctx):
        return np.gradient(ctx.H, ctx.record.time_s), "model output rate [um/s]", False

    def compensation(self, model, coefs) -> dict:
        """Extra poles: G_v becomes the fitted higher-order G (the identification writes all of G's sections),
        which the dynamic feedforward inverts and ff_pid_g shapes with.  Rate-dependent thresholds: the
        controller's inverse widens its thresholds the same way (``rate_dependence``).  Rate-dependent slopes
        are not in the controller's inverse: NotCompensable (the rest of the model is refitted without them)."""
        if np.any(np.asarray(coefs, float) != 0.0):
            raise NotCompensable("dynamics: the controller's inverse has no rate-dependent slope (the loading "
                                 "curve steepening with the input rate); left to the feedback")
        if any(c != 0.0 for c in model.rate_widening_v):
            return {"rate_widening_v": tuple(float(c) for c in model.rate_widening_v)}
        return {}

    def compensable(self) -> Optional["Dynamics"]:
        """This form without the rate-dependent slope (``rates``: the thresholds' widening alone); None where the
        slope is all it has."""
        kept = [s for s in STRUCTURES if self.has(s) and s != "slope"]
        if not kept:
            return None
        return replace(self, form=kept[0] if len(kept) == 1 else "+".join(kept))
