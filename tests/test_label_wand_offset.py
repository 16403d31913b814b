"""Label limb search: a wand that stands off its segment's sagittal line by the subject's
standing offset (held-out trials c3dorg_s03_A22_gait, c3dorg_s00_MAC_Walk1).

Literal layouts in the floor frame (forward along the walking direction, e away from the
camera, height; mm). Fails before the fix (``_on_segment`` had no ``off``; the knee of a
subject whose tibia wand stands 60-80 mm behind the shank line was left unlabelled) and
passes after it.
"""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.schemas import SubjectModel
from gaitflow.stages import label
from gaitflow.stages.model import TEMPLATE_SHO_HEIGHT
from test_label_accuracy import _leg_frame

from gaitflow.markers import MARKER_INDEX


def _pt(f: float, h: float) -> np.ndarray:
    return np.array([[f, 0.0, h]])


def test_on_segment_frees_offsets_between_the_line_and_the_standing_offset() -> None:
    kne, ank = _pt(0.0, 500.0), _pt(0.0, 80.0)  # a vertical shank
    # Standing offset 50 mm behind the line: 0..-50 is free, beyond it counts.
    assert label._on_segment(kne, _pt(-30.0, 290.0), ank, off=-50.0)[0] == 0.0
    assert label._on_segment(kne, _pt(0.0, 290.0), ank, off=-50.0)[0] == 0.0
    assert np.isclose(label._on_segment(kne, _pt(-60.0, 290.0), ank, off=-50.0)[0], 0.16)
    # Ahead of the line (opposite side): the full distance counts, as without an offset.
    ahead = label._on_segment(kne, _pt(20.0, 290.0), ank, off=-50.0)[0]
    assert np.isclose(ahead, (20.0 / 25.0) ** 2)
    assert np.isclose(ahead, label._on_segment(kne, _pt(20.0, 290.0), ank)[0])


def _model(tib_back: float) -> SubjectModel:
    """The template subject's static pose with the near TIB wand ``tib_back`` mm behind the
    KNE-ANK line (halfway down the shank)."""
    tpl = label.Geometry.from_model(None)
    offs = {f"near_{s}": [float(v) for v in tpl.rel_sho("near", s)] for s in label.SITES}
    kne, ank = np.array(offs["near_KNE"]), np.array(offs["near_ANK"])
    tib = 0.5 * (kne + ank)
    tib[0] -= tib_back
    tib[1] = offs["near_TIB"][1]
    offs["near_TIB"] = tib.tolist()
    hdr = SubjectModel.make_header("cam0", "static", 0, 0, True)
    return SubjectModel(
        header=hdr,
        reference=np.full((20, 3), np.nan),
        distances=np.full((20, 20), np.nan),
        extra={"sho_height_mm": TEMPLATE_SHO_HEIGHT, "offsets_from_shoulder": offs},
    )


def test_geometry_measures_the_standing_wand_offset() -> None:
    geo = label.Geometry.from_model(_model(60.0))
    assert geo.wand_off["TIB"] == pytest.approx(-60.0, abs=1.0)
    # Clipped to WAND_OFF_MAX of the shank: a static labelling error, not a wand.
    geo = label.Geometry.from_model(_model(400.0))
    lim = label.WAND_OFF_MAX * geo.d("KNE", "ANK")
    assert geo.wand_off["TIB"] == pytest.approx(-lim)


def test_knee_is_labelled_when_the_tibia_wand_stands_behind_the_shank() -> None:
    fr, blob, _, sho = _leg_frame()  # the template subject's near leg, standing offsets
    # Static: TIB 60 mm behind the shank line; walking: 80 mm (the wand's rotation and the
    # knee's flexion change it by 10-20 mm in the trials).
    geo = label.Geometry.from_model(_model(60.0))
    tib = geo.rel_sho("near", "TIB")
    fr.qm[blob["TIB"]] = (sho[0] + tib[0] - 20.0, sho[1] + tib[1], tib[2])
    label._lower(fr, geo, sho, geo.sho_h, 4.0)
    assert fr.assign[MARKER_INDEX["R_TIB"]] == blob["TIB"]
    # Before: the shank-line cost (80 / 25)^2 = 10.2 exceeded a missing knee's 9, the knee
    # was left out and the knee angle gap-filled.
    assert fr.assign[MARKER_INDEX["R_KNE"]] == blob["KNE"]
    assert fr.assign[MARKER_INDEX["R_THI"]] == blob["THI"]
