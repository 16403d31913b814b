"""Stream ``labelled``: named markers from Alg. 5 (label's output).

Axis 0 follows ``gaitflow.markers.MARKER_NAMES`` (20 markers). NaN = not seen this frame.
Positions are camera-space mm taken under each marker's own cluster mode. ``spare_pixel``
and ``spare_heel`` (M, ...) are the blobs no marker was named on, M varying per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class LabelledMarkers(Message):
    """The 20 named markers of one frame."""

    STREAM = "labelled"
    VERSION = 1

    position: np.ndarray = array_field("float64", (20, 3), "camera-space mm, NaN = missing")
    pixel: np.ndarray = array_field("float64", (20, 2), "(u, v) px, NaN = missing")
    blob: np.ndarray = array_field("int32", (20,), "index into the frame's blobs, -1 = none")
    direction: int = value_field(int, 0, "+1 walking toward +u, -1 toward -u, 0 unknown")
    near_side: str = value_field(str, "", "side facing the camera: L, R or empty")
    # The frame's blobs no marker was named on, for the gait stage's heel extension. Added
    # after version 1 was published: messages without them read as empty.
    spare_pixel: np.ndarray = array_field(
        "float64", (None, 2), "(u, v) px of the blobs left unnamed", optional=True
    )
    spare_heel: np.ndarray = array_field(
        "float64",
        (None, 3),
        "camera-space mm of those blobs as label would publish a heel there (the heel's"
        " cluster mode, at the surface point with heel_side_on); NaN = no layer",
        optional=True,
    )
