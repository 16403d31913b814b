"""Session set-up shared by every test module."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from gaitflow.schemas import CalibrationRecord


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile (or load) the numba kernels of clean, detect and locate once, first.

    On a fresh checkout the compile takes tens of seconds and lands in numba's disk cache;
    done here, the stage processes that bus tests start load it in about a second instead
    of each compiling it at once inside a test's time limits.
    """
    from gaitflow.stages import locate

    locate.SPEC.warmup(locate.PARAMS.resolve({}))


@pytest.fixture
def flat_record() -> Callable[..., CalibrationRecord]:
    """Factory of a calibration record for a level floor 800 mm below the camera:
    ``flat_record(w, r_b=2.5, floor_pixels=None, frame=0, capture_ns=0, **fields)``."""

    def make(
        w: float,
        r_b: float = 2.5,
        floor_pixels: np.ndarray | None = None,
        frame: int = 0,
        capture_ns: int = 0,
        **fields: Any,
    ) -> CalibrationRecord:
        px = np.zeros((0, 2)) if floor_pixels is None else np.asarray(floor_pixels, float)
        hdr = CalibrationRecord.make_header("cam0", "calibration", frame, capture_ns, last=True)
        return CalibrationRecord(
            header=hdr,
            floor_pixels=px,
            floor_points=np.zeros((len(px), 3)),
            floor_plane=np.array([0.0, -1.0, 0.0, 800.0]),
            start=np.zeros(3),
            end=np.zeros(3),
            status="Done",
            w=w,
            r_b=r_b,
            **fields,
        )

    return make
