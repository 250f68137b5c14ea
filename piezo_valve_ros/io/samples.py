"""The contract's ``samples`` matrix (Float64MultiArray): its columns and its row-major layout.  ROS-free:
the nodes (std_msgs messages) and the bag reader (rosbags messages) decode it with the same function."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..core.errors import PiezoValveError

__all__ = ["SAMPLES_COLUMNS", "SAMPLES_LABEL", "SamplesLayoutError", "decode_samples"]

SAMPLES_COLUMNS = ("time", "voltage_command", "spool_position")   # [s], [V], [m]
SAMPLES_LABEL = ",".join(SAMPLES_COLUMNS)                         # the label of the column dimension


class SamplesLayoutError(PiezoValveError, ValueError):
    """A samples message whose layout or size is not the contract's (one-line reason)."""


def decode_samples(dims: Sequence, data, name: str = "samples message") -> np.ndarray:
    """(N, 3) rows of time [s], voltage [V], position [m] from a message's ``layout.dim`` (two dimensions,
    the second labelled with the comma-separated column names, which may be in any order or include
    others) and its ``data``; SamplesLayoutError naming ``name`` otherwise."""
    if len(dims) != 2:
        raise SamplesLayoutError(f"{name}: {len(dims)} layout dimensions, expected 2")
    labels = dims[1].label.split(",")
    missing = [c for c in SAMPLES_COLUMNS if c not in labels]
    if missing:
        raise SamplesLayoutError(f"{name}: columns {dims[1].label!r} lack {', '.join(missing)}")
    n, k = dims[0].size, dims[1].size
    values = np.asarray(data, dtype=float)
    if values.size != n * k:
        raise SamplesLayoutError(f"{name}: {values.size} values, its layout says {n}x{k}")
    return values.reshape(n, k)[:, [labels.index(c) for c in SAMPLES_COLUMNS]]
