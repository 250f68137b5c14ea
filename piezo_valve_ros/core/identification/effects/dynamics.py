"""Dynamics beyond the baseline's second-order G_v: extra poles (a lag, a delay or a resonance a second
order cannot represent) and rate-dependent hysteresis (the loop widens with the input rate).

Structure, nonlinear in its parameters (fitted by Gauss-Newton with the rest of the model):
* G(s) gets a second unity-DC-gain pole pair, fourth order in all;
* the operators' thresholds grow with the input rate, ``r_j + sum_k c_k rho / (rho + rate_k)``: the
  rate-dependent Prandtl-Ishlinskii model of Al Janaideh and Krejci (thresholds as functions of the
  rate) with a widening that is linear at low rates and levels off, at the scales
  ``RATE_SCALES_V_S``; ``rho`` is |dv/dt| through each lag of ``RATE_FILTERS_S`` (cycling rates over
  two memories, not the slope inside a 2 ms ramp).
For the subset search (one linear solve from the baseline) the extra poles are represented to first
order by fast lags of H (``lag_tau[H] - H`` is ``-tau s H`` for small tau) and the rate terms by their
exact sensitivities.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...model.dynamics import lag_bank
from ...model.rate_dependence import MAX_WIDENING_V, RATE_FILTERS_S, RATE_SCALES_V_S, TERM_COUNT
from .base import Effect

__all__ = ["Dynamics", "FAST_LAGS_S", "MAX_WIDENING_V", "EXTRA_START"]

FAST_LAGS_S = (3e-4, 1e-3, 3e-3)   # first-order proxies of extra poles, for the subset search
FORMS = ("poles", "rate", "both")
EXTRA_START = 3.0   # the extra pole pair starts this factor above G_v's natural frequency (well damped)


@dataclass(frozen=True)
class Dynamics(Effect):
    name = "dynamics"
    signature = ("lag or ringing after fast moves beyond the second-order G_v, or a loop that widens with the "
                 "input rate: the residual follows fast lags (0.3-3 ms) of the model output, or the operators' "
                 "sensitivity to thresholds that grow with the input rate")
    form: str = "both"   # "poles", "rate" or "both": the structures switched on

    def forms(self) -> list["Dynamics"]:
        """Each structure alone and both together: fitted jointly from scratch the two trade against each
        other and end in a poor optimum, so each form is fitted and the best on training data kept."""
        return [replace(self, form=f) for f in FORMS]

    def switch_on(self, model):
        if self.form in ("rate", "both") and not model.rate_widening_v:
            model = replace(model, rate_widening_v=(0.0,) * TERM_COUNT)
        if self.form in ("poles", "both") and len(model.sections) == 1:
            w, _ = model.sections[0]
            model = replace(model, sections=model.sections + ((EXTRA_START * w, 1.1),))
        return model

    def carry(self, source, target):
        if source.term(self.name) is None:
            return target
        if self.form in ("rate", "both") and source.rate_widening_v:
            target = replace(target, rate_widening_v=source.rate_widening_v)
        if self.form in ("poles", "both") and len(source.sections) > 1:
            target = replace(target, sections=source.sections)
        return target

    def sensitivities(self, ctx) -> np.ndarray:
        if self.form == "poles":
            return np.zeros((len(ctx.record), 0))
        terms = ctx.rate_terms
        return np.column_stack([ctx.bound_sensitivity(-terms[:, k], terms[:, k]) for k in range(terms.shape[1])])

    def step(self, model, delta):
        if self.form == "poles":
            return model
        c = np.clip(np.asarray(model.rate_widening_v) + np.asarray(delta, float), -MAX_WIDENING_V, MAX_WIDENING_V)
        return replace(model, rate_widening_v=tuple(float(x) for x in c))

    def search_columns(self, ctx) -> np.ndarray:
        taus = [t for t in FAST_LAGS_S if t >= ctx.dt / 4]
        H = ctx.H
        return np.column_stack((lag_bank(H, taus, ctx.dt) - H[:, None], replace(self, form="both").sensitivities(ctx)))

    def describe(self, model, coefs) -> dict:
        extra = model.sections[1:]
        return {"form": self.form, "extra_poles": [{"omega_rad_s": round(w, 3), "zeta": round(z, 4)} for w, z in extra],
                "rate_widening_v": [float(x) for x in model.rate_widening_v], "rate_scales_v_s": list(RATE_SCALES_V_S),
                "rate_filters_s": list(RATE_FILTERS_S)}

    def plot_axis(self, ctx):
        return np.gradient(ctx.H, ctx.record.time_s), "model output rate [um/s]", False

    def compensation(self, model, coefs) -> dict:
        """Extra poles: G_v becomes the fitted higher-order G (the identification writes all of G's sections),
        which the dynamic feedforward inverts and ff_pid_g shapes with.  Rate-dependent thresholds: the
        controller's inverse widens its thresholds the same way (``rate_dependence``)."""
        if any(c != 0.0 for c in model.rate_widening_v):
            return {"gpim.rate_widening_v": [float(c) for c in model.rate_widening_v]}
        return {}
