"""Streams ``calibration`` (the scene calibration record, Alg. 4) and ``calstatus``.

``calstatus`` is published on every calibration frame with the live operator status.
``calibration`` is published once, when the calibration trial ends: stages that need the
record hold their frames until it is there, so it must only ever carry a finished record
(``status`` is ``Done``, or ``Replace Markers`` when calibration failed).
C floor markers on axis 0. Camera-space mm, pixels (u, v).
``floor_plane`` is (nx, ny, nz, d) with unit normal pointing up (away from the floor) and
n . p + d = height above the floor in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field

STATUSES = (
    "Uninitialized",
    "Move Left",
    "Move Right",
    "Tilt Down",
    "Tilt Up",
    "Pan Left",
    "Pan Right",
    "Replace Markers",
    "Done",
)


@register
@dataclass(frozen=True, eq=False)
class CalibrationRecord(Message):
    """The walking-scene calibration: floor markers, plane, w, r_b, start/end and L."""

    STREAM = "calibration"
    VERSION = 1

    floor_pixels: np.ndarray = array_field("float64", (None, 2), "floor-marker centroids (u, v) px")
    floor_points: np.ndarray = array_field("float64", (None, 3), "floor markers, camera mm")
    floor_plane: np.ndarray = array_field("float64", (4,), "(nx, ny, nz, d), normal up")
    start: np.ndarray = array_field("float64", (3,), "walking start point on the floor, mm")
    end: np.ndarray = array_field("float64", (3,), "walking end point on the floor, mm")
    status: str = value_field(str, "Uninitialized", "operator status, one of STATUSES")
    markers_found: int = value_field(int, 0, "floor markers found so far")
    w: float = value_field(float, float("nan"), "initial IR threshold w")
    r_b: float = value_field(float, float("nan"), "blob base radius r_b, px")
    length_mm: float = value_field(float, float("nan"), "walking line length L, mm")
    camera: dict = value_field(dict, {}, "depth intrinsics used (camera.json form)")
    tilt_deg: float = value_field(float, float("nan"), "optical axis elevation above floor, deg")
    pan_deg: float = value_field(float, float("nan"), "walking line angle off image X, deg")
    offset_mm: float = value_field(float, float("nan"), "quad centre offset from optical axis")
    plane_rms_mm: float = value_field(float, float("nan"), "floor markers' rms plane residual")
    message: str = value_field(str, "", "a human-readable note on the outcome")


@register
@dataclass(frozen=True, eq=False)
class CalibrationStatus(Message):
    """Live calibration status for the operator adjusting the camera."""

    STREAM = "calstatus"
    VERSION = 1

    floor_pixels: np.ndarray = array_field("float64", (None, 2), "floor markers found so far, px")
    status: str = value_field(str, "Uninitialized", "operator status, one of STATUSES")
    markers_found: int = value_field(int, 0, "floor markers found so far")
    message: str = value_field(str, "", "a human-readable hint for the operator")
