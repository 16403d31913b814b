"""Stream ``clean``: a frame after data cleaning (paper section III-A, clean stage).

Arrays are (row, col). Masked (interference) and invalid pixels are zero in ``ir``;
``mask`` is 1 where a tracked interfering reflector was masked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class CleanFrame(Message):
    """Cleaned IR and depth with the interference mask."""

    STREAM = "clean"
    VERSION = 1

    ir: np.ndarray = array_field("uint16", (None, None), "IR with interference zeroed")
    depth: np.ndarray = array_field("uint16", (None, None), "depth in mm, 0 = invalid")
    mask: np.ndarray = array_field("uint8", (None, None), "1 = masked interfering reflector")
    interferers: int = value_field(int, 0, "number of tracked interfering reflectors")
    camera: dict = value_field(
        dict, {}, "depth intrinsics (camera.json form) from the calibration record; {} = none"
    )
