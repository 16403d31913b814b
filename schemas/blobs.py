"""Stream ``blobs``: 2D marker candidates from Alg. 1 (threshold) and Alg. 2 (blobs).

N blobs, axis 0. ``centroid`` is (u, v) = (column, row) in pixels, intensity-weighted;
radii are in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class Blobs(Message):
    """Connected IR components above the frame's threshold."""

    STREAM = "blobs"
    VERSION = 1

    centroid: np.ndarray = array_field("float64", (None, 2), "(u, v) px, intensity-weighted")
    marker_radius: np.ndarray = array_field("float64", (None,), "r_m: weighted mean radius, px")
    region_radius: np.ndarray = array_field("float64", (None,), "r_r: blob extent, px")
    mean_ir: np.ndarray = array_field("float64", (None,), "k: mean IR of the blob")
    area: np.ndarray = array_field("int32", (None,), "pixel count of the blob")
    threshold: float = value_field(float, meaning="e_d: IR threshold used for this frame")
    iterations: int = value_field(int, 0, "Alg. 1 iterations until convergence")
    method: str = value_field(str, "adaptive", "adaptive (Alg. 1) or static threshold")
    status: str = value_field(
        str, "ok", "ok, empty (no blob) or too-many (more than max_blobs candidates)"
    )
    rejected: int = value_field(int, 0, "components rejected as too wide to be a marker")
