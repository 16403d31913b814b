"""Stream ``truth``: simulator ground truth, for evaluation only. No stage may read it.

Axis 0 follows ``gaitflow.markers.MARKER_NAMES``. Camera-space mm and pixels (u, v);
NaN = marker absent from the source trial. Knee flexion (L, R) in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class GroundTruth(Message):
    """What the simulator rendered in one frame."""

    STREAM = "truth"
    VERSION = 1

    position: np.ndarray = array_field("float64", (20, 3), "marker centres, camera mm")
    pixel: np.ndarray = array_field("float64", (20, 2), "projected centres (u, v) px")
    visible: np.ndarray = array_field("bool", (20,), "in view and not occluded")
    occluded: np.ndarray = array_field("bool", (20,), "in view but hidden (e.g. by an arm)")
    knee_flexion: np.ndarray = array_field("float64", (2,), "(L, R) deg")
    time_s: float = value_field(float, 0.0, "seconds since the trial's first frame")
    events: list = value_field(list, [], "[side, kind, time_s] events in this frame")
    knee_flexion_ref: list = value_field(
        list, [], "(L, R) source Plug-in Gait knee flexion deg, NaN where absent"
    )
    pass_name: str = value_field(str, "", "walk part: out, turn, back; '' for other trials")
    visible_fraction: list = value_field(
        list, [], "per marker, fraction of its image footprint not hidden (0..1)"
    )
    merged: list = value_field(
        list,
        [],
        "per marker, visible but its image disc (over the exposure, + 1 px) touches another"
        " visible marker's: the two cannot be resolved as separate blobs",
    )
