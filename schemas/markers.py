"""Stream ``markers``: 3D marker candidates from Alg. 3 (locate's output).

N blobs, axis 0, in the same order as the ``blobs`` message of the same frame. Because the
cluster mode depends on the label, which only the label stage knows, locate publishes the
depth under each of the three modes (axis 1, order ``gaitflow.markers.CLUSTER_MODES``:
normal, top, bottom) and label picks the one for the label it assigns. Camera space:
X right, Y down, Z forward, mm; NaN = depth could not be recovered.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class Markers3D(Message):
    """Blobs with their camera-space position under each cluster mode."""

    STREAM = "markers"
    VERSION = 1

    centroid: np.ndarray = array_field(
        "float64", (None, 2), "(u, v) px from Alg. 2; completed where a nearer surface hides part"
    )
    marker_radius: np.ndarray = array_field("float64", (None,), "r_m, px")
    region_radius: np.ndarray = array_field("float64", (None,), "r_r, px")
    depth: np.ndarray = array_field("float64", (None, 3), "Z mm under modes normal/top/bottom")
    position: np.ndarray = array_field(
        "float64", (None, 3, 3), "[blob, mode, xyz] camera-space mm under each cluster mode"
    )
    threshold: float = value_field(float, 0.0, "e_d carried from detect")
    surface_offset_mm: float = value_field(
        float,
        0.0,
        "how far locate moved each position toward the camera along its viewing ray, from"
        " the surface the marker sits on to the sphere's centre, mm (0 = surface points)",
    )
