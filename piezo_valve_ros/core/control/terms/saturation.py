"""The saturation map (``output_map.OutputMap``): the loop ends flattened, inverted on the feedforward path."""
from __future__ import annotations

from ...model.output_map import TERM_COUNT, OutputMap
from ...validation import as_float, as_float_list
from .base import Term, floats


def _write(m: OutputMap) -> dict:
    return {"saturation.centre_um": float(m.centre_um), "saturation.half_range_um": float(m.half_range_um),
            # zeros rather than []: an empty list has no element type for a ROS parameter
            "saturation.coefficients_um": floats(m.coefficients_um) or [0.0] * TERM_COUNT}


def _read(get):
    centre, half = get("saturation.centre_um", as_float), get("saturation.half_range_um", as_float)
    coefs = get("saturation.coefficients_um", as_float_list)
    return None if None in (centre, half, coefs) else OutputMap(centre, half, tuple(coefs))


TERM = Term(
    field="output_map",
    default=OutputMap(),
    place="static",
    parameters={
        "saturation.centre_um": (0.0, "saturation map: centre of the normalised output [um]"),
        "saturation.half_range_um": (1.0, "saturation map: half range of the normalised output [um]"),
        "saturation.coefficients_um": ([], f"saturation map: {TERM_COUNT} coefficients [um] of h^2, h^3 and the end "
                                           "hinges (empty or all 0: none)")},
    write=_write,
    read=_read,
)
