"""Subject model from a synthetic static pose (literal 3D layout, strays included)."""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.schemas import SubjectModel
from gaitflow.stages import model
from gaitflow.stages.model import FloorFrame

from gaitflow.evaluate_label import calibration_record, synthetic_walk
from gaitflow.markers import MARKER_INDEX


def _build(facing: int) -> tuple[SubjectModel, list, np.ndarray]:
    cal = calibration_record()
    walk = synthetic_walk(seed=3, frames_per_pass=12, static=True, trial="static", facing=facing)
    st = model.SPEC.init(model.PARAMS.resolve({}))
    out = []
    for f in walk.frames:
        st, msgs = model.SPEC.step(st, {"markers": f, "calibration": cal})
        out.extend(msgs)
    # Truth of the first frame, for checking only (the stage never sees it).
    f0, ids0 = walk.frames[0], walk.truth[0]
    truth = np.full((20, 3), np.nan)
    for b, i in enumerate(ids0):
        if i >= 0:
            truth[i] = f0.position[b, 0]
    return out, walk, truth


@pytest.mark.parametrize("facing, near", [(1, "R"), (-1, "L")])
def test_model_from_static_pose(facing: int, near: str) -> None:
    out, _, truth = _build(facing)
    assert len(out) == 1 and isinstance(out[0], SubjectModel)
    m = out[0]
    assert m.near_side == near
    assert m.extra["facing"] == facing
    far = "L" if near == "R" else "R"
    # Every near-side marker is found, within the 2 mm noise of the layout.
    for site in ("SHO", "ASI", "PSI", "HIP", "THI", "KNE", "TIB", "ANK", "HEE", "TOE"):
        i = MARKER_INDEX[f"{near}_{site}"]
        assert np.linalg.norm(m.reference[i] - truth[i]) < 8.0, site
    # Far heel and toe are seen; far leg markers are not invented.
    for site in ("HEE", "TOE"):
        i = MARKER_INDEX[f"{far}_{site}"]
        assert np.linalg.norm(m.reference[i] - truth[i]) < 8.0, site
    for site in ("SHO", "HIP", "THI", "KNE", "TIB", "ANK"):
        assert np.isnan(m.reference[MARKER_INDEX[f"{far}_{site}"]]).all(), site
    ff = FloorFrame.from_record(calibration_record(), 800.0)
    heights = ff.to_floor(m.reference)[:, 2]
    assert m.extra["sho_height_mm"] == pytest.approx(heights[MARKER_INDEX[f"{near}_SHO"]])
    # Segment lengths: thigh (HIP-KNE) of the synthetic chain is 430 mm.
    assert m.extra["thigh_mm"] == pytest.approx(430.0, abs=10.0)
    assert np.isfinite(m.distances[MARKER_INDEX[f"{near}_HIP"], MARKER_INDEX[f"{near}_KNE"]])


def test_model_published_at_finish_without_last_frame() -> None:
    walk = synthetic_walk(seed=4, frames_per_pass=5, static=True, trial="static")
    st = model.SPEC.init(model.PARAMS.resolve({}))
    for f in walk.frames[:-1]:  # the 'last' frame never arrives
        st, msgs = model.SPEC.step(st, {"markers": f, "calibration": calibration_record()})
        assert msgs == []
    st, msgs = model.SPEC.finish(st)
    assert len(msgs) == 1 and msgs[0].near_side == "R"
    st, again = model.SPEC.finish(st)
    assert again == []
