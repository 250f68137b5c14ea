"""What an effect of the catalogue is: one small class per module (see ``effects/__init__.py``).

An effect knows
* its **signature** (what it looks like in a residual, in words) and the axis to plot that residual on;
* its **columns**: terms linear in their coefficients that it adds to the static part of the model
  (before G), computed from the hysteresis output H, the input and time;
* its **nonlinear structure**, if any (a descending envelope, thresholds that widen with the rate,
  extra poles of G): ``switch_on`` puts it into a model, ``sensitivities`` are its exact first-order
  columns and ``step`` applies a Gauss-Newton step to it;
* its **search columns**: what the subset search uses to judge it from the baseline in one linear
  solve (its columns and sensitivities, plus any first-order proxy of its structure);
* or, for an effect on the spool's path after G (``after_dynamics``: backlash), an **output map** of G's output
  that is linear in it and in its coefficients for a given structure (``output_linear``);
* its **description** for the report and its **compensation** (the ``CompensationModel`` fields it fills, typed
  values: no parameter names, which belong to the controller's and the files' edge), or the reason the controller
  cannot use it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Optional

import numpy as np

from ..records import Record

if TYPE_CHECKING:
    from ..valve_model import Context, ValveModel

__all__ = ["Effect", "NotCompensable", "EFFECT_RIDGE", "normalised"]

# Ridge on an effect's standardised columns, as a share of the record length: collinear columns (lags a
# factor 3 apart, polynomial powers) then share a coefficient instead of cancelling each other with
# large alternating ones, and a column that explains less than this share of its own variance is ignored.
EFFECT_RIDGE = 1e-5


class NotCompensable(Exception):
    """The controller cannot use this effect (the message says why)."""


def normalised(H: np.ndarray, centre: float, half: float) -> np.ndarray:
    """(H - centre) / half: the model output on [-1, 1] over the training range."""
    return (H - centre) / half


@dataclass(frozen=True)
class Effect:
    """Base class: an effect with no terms.  Subclasses set the class variables and override what they use."""

    name: ClassVar[str] = ""
    signature: ClassVar[str] = ""
    telling_experiment: ClassVar[str] = ""   # the excitation that shows this effect and not its look-alikes
    ridge: ClassVar[float] = EFFECT_RIDGE
    after_dynamics: ClassVar[int] = 0        # coefficients of an output map after G (0: the effect acts before G)
    coefficient_floor: ClassVar[float] = -np.inf   # the lower bound of its coefficients in a fit
    costly_refit: ClassVar[bool] = False     # an exact refit costs seconds (several forms, each a nonlinear fit):
                                             # checked after the others (``_EffectChoice.exact_addition``)
    # its other two homes: the simulated valve's stages that make it (StageSwitch names), and the CompensationModel
    # fields its ``compensation`` fills (a control term's, or the GPIM's; none: it raises NotCompensable, the
    # feedback's to absorb); ``to_controller`` refuses a compensation that fills another field
    simulated_by: ClassVar[tuple[str, ...]] = ()
    compensated_by: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def prepare(cls, train: Record, H: np.ndarray) -> Optional["Effect"]:
        """The effect with settings fitted to the training record (time constants, scales); None when the
        record cannot show it (e.g. too short for its time constants)."""
        return cls()

    # -- linear terms of the final model
    def columns(self, ctx: "Context") -> np.ndarray:
        """(N, k) terms added before G; k = 0 when the effect is purely structural."""
        return np.zeros((len(ctx.record), 0))

    def design_rows(self, ctx: "Context") -> np.ndarray:
        """``columns`` as rows (k, N), the layout a fit's design takes; an effect may write them so directly
        (the same values)."""
        return self.columns(ctx).T

    def rest_columns(self, ctx: "Context", columns: np.ndarray) -> np.ndarray:
        """(k,) values of ``columns`` (this effect's ``columns`` or ``search_columns`` on ``ctx``) while the
        valve rested before the record, where it rested at another voltage (``Context.rest_states``): what G
        had settled to.  Default: the first row (the terms taken as continuous across the first move)."""
        return columns[0]

    # -- nonlinear structure
    def switch_on(self, model: "ValveModel") -> "ValveModel":
        """The model with this effect's structure in place (at its neutral value)."""
        return model

    def carry(self, source: "ValveModel", target: "ValveModel") -> "ValveModel":
        """``target`` with this effect's nonlinear structure as fitted in ``source`` (a warm start for a refit
        of a related subset); ``target`` unchanged when ``source`` lacks the effect or it has no structure."""
        return target

    def sensitivities(self, ctx: "Context") -> np.ndarray:
        """(N, m) first-order columns of the nonlinear parameters (before G); m = 0 without any."""
        return np.zeros((len(ctx.record), 0))

    @property
    def nonlinear(self) -> bool:
        """Whether this effect, in its form, has nonlinear parameters (``sensitivities`` with columns) for a
        Gauss-Newton step to move: a subclass that has some overrides ``sensitivities``."""
        return type(self).sensitivities is not Effect.sensitivities

    def step(self, model: "ValveModel", delta: np.ndarray) -> "ValveModel":
        """Apply a Gauss-Newton step (coefficients of ``sensitivities``) to the nonlinear parameters."""
        return model

    def forms(self) -> list["Effect"]:
        """Alternative structures of this effect; a refit tries each and keeps the best on training data.  The
        last form combines others and is fitted starting from the best of those it ``contains``."""
        return [self]

    def held_out_forms(self) -> list["Effect"]:
        """Nested structures of this effect, the simplest first and this one last: each richer one fits the training
        record at least as well, so training error cannot choose among them and a refit chooses on held-out data
        (``[self]``: one structure)."""
        return [self]

    def contains(self, other: "Effect") -> bool:
        """Whether this form has every structure of ``other`` (a form of the same effect): the combined last form
        starts from the best of the forms it contains."""
        return True

    # -- an output map after G (``after_dynamics`` coefficients)
    def output(self, x: np.ndarray, coefs: np.ndarray) -> np.ndarray:
        """The position [um] (N,) for G's output ``x`` [um] (N,)."""
        return x

    def output_linear(self, x: np.ndarray, coefs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The output map at its structure for ``x`` and ``coefs`` (empty: at its neutral value) as ``(index (N,),
        columns (N, after_dynamics))``: position = ``x[index] + columns @ coefs``, exact for that structure."""
        return np.arange(x.size), np.zeros((x.size, 0))

    def frees_poles(self, coefs: np.ndarray) -> bool:
        """Whether an output map, settled at ``coefs``, is large enough that G_v's own poles are refitted with it
        (the baseline fitted them with its structure absorbed)."""
        return False

    def output_search_columns(self, x: np.ndarray) -> np.ndarray:
        """What the subset search fits for an output map, from the baseline's G output ``x`` (N,): (N, k) columns
        added to the position.  Default: its linear form at its neutral value."""
        return self.output_linear(x, np.zeros(0))[1]

    def search_columns(self, ctx: "Context") -> np.ndarray:
        """What the subset search fits for this effect (from the baseline, one linear solve)."""
        return np.column_stack((self.columns(ctx), self.sensitivities(ctx)))

    # -- reporting and use
    def describe(self, model: "ValveModel", coefs: np.ndarray) -> dict:
        return {}

    def plot_axis(self, ctx: "Context") -> tuple[np.ndarray, str, bool]:
        """(values, label, log scale?) to plot this effect's residual against."""
        return ctx.H, "model output [um]", False

    def controller_fields(self, model: "ValveModel", coefs: np.ndarray) -> dict:
        """``compensation``, held to the fields the effect declares as its home in the controller
        (``compensated_by``): TypeError naming the effect where it fills another (a catalogue effect written
        wrong); NotCompensable as ``compensation`` raises it."""
        fields = self.compensation(model, coefs)
        stray = set(fields) - set(self.compensated_by)
        if stray:
            raise TypeError(f"the {self.name} effect's compensation fills {', '.join(sorted(stray))}, which it does "
                            f"not declare (compensated_by: {', '.join(self.compensated_by) or 'none'})")
        return fields

    def compensation(self, model: "ValveModel", coefs: np.ndarray) -> dict:
        """What compensates this effect: ``CompensationModel`` field -> typed value (a ``CreepModel``, an ``OutputMap``,
        ...); raises NotCompensable with the reason."""
        raise NotCompensable(f"{self.name}: the controller has no compensation for it")

    def compensable(self) -> Optional["Effect"]:
        """This effect without the structures its ``compensation`` refuses, for a model refitted with what the
        controller can compensate (``to_controller``); None where nothing of it is left."""
        return None
