"""Stream ``raw``: one IR and depth frame as the sensor delivered it (grab's output).

Arrays are (row, col) = (424, 512) for a Kinect v2; other sensors keep their own size.
IR is amplitude 0..65535 with 65535 = saturated; depth is Z in mm with 0 = invalid.
``camera`` carries the source's camera.json document with the frames, so that a pipeline
started from any source (``gaitflow run``, a grab stage on an edge box) measures with that
camera's intrinsics and marker size, not the factory defaults: calibrate puts it in the
calibration record, which every later stage reads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class RawFrame(Message):
    """A raw IR amplitude and depth frame pair from one time-of-flight sensor."""

    STREAM = "raw"
    VERSION = 1

    ir: np.ndarray = array_field("uint16", (None, None), "IR amplitude, 65535 = saturated")
    depth: np.ndarray = array_field("uint16", (None, None), "depth along Z in mm, 0 = invalid")
    camera: dict = value_field(
        dict,
        {},
        "the source's camera.json document (intrinsics, marker_diameter_mm, fps, ...) as grab"
        " read it; calibrate adopts it when its camera parameter is empty; {} = unknown",
    )
