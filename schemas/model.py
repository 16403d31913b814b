"""Stream ``model``: the person-centric subject model built from the static recording.

Axis 0 (and 1 of ``distances``) follows ``gaitflow.markers.MARKER_NAMES``. Positions are
camera-space mm of the standing pose; NaN = marker not seen in the static pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class SubjectModel(Message):
    """Reference layout and inter-marker distances of one subject."""

    STREAM = "model"
    VERSION = 1

    reference: np.ndarray = array_field("float64", (20, 3), "standing pose, camera mm")
    distances: np.ndarray = array_field("float64", (20, 20), "inter-marker distances, mm")
    subject: str = value_field(str, "", "pseudonymous subject id")
    near_side: str = value_field(str, "", "side that faced the camera in the static pose")
    marker_diameter_mm: float = value_field(float, 25.0, "marker diameter, mm")
    extra: dict = value_field(dict, {}, "further model measurements (H*, W*), mm")
