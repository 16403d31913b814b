"""Label accuracy rules on literal layouts (phase 2 of the label speed/accuracy work)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from gaitflow.stages import label
from gaitflow.stages.model import FloorFrame

from gaitflow.errors import ParameterError
from gaitflow.evaluate_label import calibration_record, to_camera
from gaitflow.markers import MARKER_INDEX

WALK_V = 1350.0  # mm/s along the walk


def _walking_track(
    params: dict, depth_speed: float = 0.0
) -> tuple[label.LabelState, label.Geometry, FloorFrame, np.ndarray]:
    """(state, geometry, floor frame, shoulder track (6,)) in frame 10 of a subject walking
    toward +a at WALK_V past a = 3000 mm, the track on the near shoulder at depth 0;
    ``depth_speed`` is the track's velocity in depth, mm/s."""
    geo = label.Geometry.from_model(None)
    ff = FloorFrame.from_record(calibration_record(), 800.0)
    x = np.array([3000.0, 0.0, geo.sho_h, WALK_V, depth_speed, 0.0])
    st = replace(
        label.init(label.PARAMS.resolve(params)),
        trial="walk-01",
        frame=10,
        sho_x=x,
        sho_cov=np.diag([15.0**2] * 3 + [300.0**2] * 3),
        direction=1,
        walked=True,
    )
    return st, geo, ff, x


def _shoulder_frame(
    far_sho_mm: float, depth_speed: float = 0.0, depth_mm: float = 100.0
) -> tuple[label.LabelState, np.ndarray]:
    """One frame after a walking shoulder track whose near shoulder has left the view: the
    only shoulder-height blob is the far shoulder, 60 mm behind the prediction along the
    walk and ``depth_mm`` deeper than the track's last depth (inside the 150 mm gate).
    ``depth_speed`` is the track's velocity in depth, mm/s."""
    st, geo, ff, x = _walking_track({"far_sho_mm": far_sho_mm}, depth_speed)
    H = geo.sho_h
    ahead = x[0] + WALK_V / 30.0
    blob = to_camera(np.array([ahead - 60.0, depth_mm, H]))
    pos = np.repeat(blob[None, None, :], 3, axis=1)  # (1 blob, 3 modes, 3)
    st, assign = label.label_frame(st, pos, 11, ff, geo)
    return st, assign


def test_far_shoulder_does_not_continue_the_near_shoulder_track() -> None:
    st, assign = _shoulder_frame(80.0)
    assert assign[MARKER_INDEX["R_SHO"]] == -1
    assert st.sho_missed == 1  # the track coasts on its prediction


def test_far_shoulder_rule_is_what_rejects_it() -> None:
    # Without the rule (any depth accepted) the same blob continues the track. (Not
    # published: a 100 mm step away from the camera reads as heading off the line, a turn.)
    st, _ = _shoulder_frame(1000.0)
    assert st.sho_missed == 0


def test_a_depth_drift_of_the_track_does_not_make_its_shoulder_the_far_one() -> None:
    # Depth noise gives the track a velocity toward the camera (-900 mm/s: its prediction
    # 30 mm nearer than its last depth). The shoulder blob, 55 mm deeper than the last
    # depth and so 85 mm behind the prediction, is still the track's own shoulder: the
    # far-shoulder test measures from the deeper of the two.
    st, _ = _shoulder_frame(80.0, depth_speed=-900.0, depth_mm=55.0)
    assert st.sho_missed == 0
    # A blob 100 mm behind the last depth stays the far shoulder whatever the drift.
    st, _ = _shoulder_frame(80.0, depth_speed=-900.0, depth_mm=100.0)
    assert st.sho_missed == 1


def test_a_shoulder_blob_whose_depth_jumps_does_not_drag_the_track_off_its_shoulder() -> None:
    # A low camera 3.5 m away (``low+far+k4a``, FlatFoot frame 257): the shoulder blob's
    # depth, taken from an arm in front, jumped 134 mm toward the camera for one frame. The
    # track took it, its depth velocity became -1 m/s, the real shoulder the next frame
    # was "clearly deeper" than the track (the far shoulder's rule) and the track was lost:
    # seven frames without any label (a 20 deg knee error in the gap's Bezier).
    st, geo, ff, x = _walking_track({})
    for k, depth in ((1, -134.0), (2, 30.0)):
        blob = to_camera(np.array([x[0] + k * WALK_V / 30.0, depth, geo.sho_h]))
        st, _ = label.label_frame(st, np.repeat(blob[None, None, :], 3, axis=1), 10 + k, ff, geo)
        assert st.sho_missed == 0, k  # the shoulder's blob continues the track both times
        if k == 1:  # the track kept its depth and depth velocity
            assert abs(st.sho_x[1]) < 5.0 and abs(st.sho_x[4]) < 100.0
    assert 0.0 < st.sho_x[1] < 30.0


def test_far_sho_mm_is_declared_non_negative() -> None:
    with pytest.raises(ParameterError, match="far_sho_mm"):
        label.PARAMS.resolve({"far_sho_mm": -1.0})


def walking_frame(q: np.ndarray, sho: np.ndarray, geo: label.Geometry) -> label._Frame:
    """An untracked walking frame (near side R, walking toward +a) of blobs q (N, 3)
    (a, e, h) mm, every cluster mode at the same place."""
    st = label.init(label.PARAMS.resolve({}))
    pred, sig, tracked = label._predictions(st, geo, sho, "R", 1, 100)
    return label._Frame(
        qm=np.repeat(np.asarray(q, float)[:, None, :], 3, axis=1),
        free=np.ones(len(q), bool),
        assign=np.full(20, -1),
        pred=pred,
        sig=sig,
        near="R",
        tracked=tracked,
        ambiguity=4.0,
        age=np.full(20, 10**9),
    )


def _leg_frame() -> tuple[label._Frame, dict[str, int], label.Geometry, np.ndarray]:
    """A walking frame of the template subject (near side R, walking toward +a): blobs at the
    standing offsets of the near leg's THI, KNE, TIB, ANK, HEE and TOE; the hip is hidden."""
    geo = label.Geometry.from_model(None)
    sho = np.array([2000.0, 0.0, geo.sho_h])
    sites = ("THI", "KNE", "TIB", "ANK", "HEE", "TOE")
    offs = [geo.rel_sho("near", s) for s in sites]
    q = np.array([[sho[0] + o[0], sho[1] + o[1], o[2]] for o in offs])
    return walking_frame(q, sho, geo), {s: k for k, s in enumerate(sites)}, geo, sho


def test_hip_label_on_the_thigh_wand_is_dropped_by_the_limb_search() -> None:
    fr, blob, geo, sho = _leg_frame()
    # The pelvis search took the thigh wand for the hidden hip.
    fr.assign[MARKER_INDEX["R_HIP"]] = blob["THI"]
    fr.free[blob["THI"]] = False
    label._lower(fr, geo, sho, geo.sho_h, 4.0)
    assert fr.assign[MARKER_INDEX["R_HIP"]] == -1
    # Without a thigh track, "hip or thigh wand" stays open for that blob: no label (a
    # gap), never the wrong one; the knee and ankle below are named.
    assert fr.assign[MARKER_INDEX["R_THI"]] in (-1, blob["THI"])
    assert fr.assign[MARKER_INDEX["R_KNE"]] == blob["KNE"]
    assert fr.assign[MARKER_INDEX["R_ANK"]] == blob["ANK"]


def test_a_right_hip_label_is_kept_by_the_limb_search() -> None:
    fr, blob, geo, sho = _leg_frame()
    o = geo.rel_sho("near", "HIP")
    hip = np.array([sho[0] + o[0], sho[1] + o[1], o[2]])
    fr.qm = np.concatenate([fr.qm, np.repeat(hip[None, None, :], 3, axis=1)])
    fr.free = np.append(fr.free, False)
    fr.assign[MARKER_INDEX["R_HIP"]] = len(fr.qm) - 1
    label._lower(fr, geo, sho, geo.sho_h, 4.0)
    assert fr.assign[MARKER_INDEX["R_HIP"]] == len(fr.qm) - 1
    assert fr.assign[MARKER_INDEX["R_THI"]] == blob["THI"]
    assert fr.assign[MARKER_INDEX["R_KNE"]] == blob["KNE"]


def test_a_tibia_wand_near_the_knee_track_stays_in_the_foot_search() -> None:
    # A child's (or any short shank's) tibia wand lies within 2 sigma of the knee track's
    # prediction. The knee's own blob, above the foot band, is the track's best blob: the
    # tibia wand is not the knee's and stays a candidate of the foot search (it was kept
    # out as the best *low* blob on the knee's track, and the tibia label took the heel).
    fr, blob, geo, sho = _leg_frame()
    H = geo.sho_h
    k, t = blob["KNE"], blob["TIB"]
    i = MARKER_INDEX["R_KNE"]
    fr.pred[i] = fr.qm[k, 0]
    fr.sig[i] = (66.0, 70.0, 50.0)
    fr.tracked[i], fr.age[i] = True, 1
    band = max(0.3 * H, geo.rel_sho("near", "TIB")[2] + 0.05 * H)
    assert fr.qm[k, 0, 2] > band  # the knee is above the foot band
    fr.qm[t] = fr.qm[k] + (-60.0, 10.0, -80.0)  # u = 3.4 < 4 from the knee's prediction
    assert fr.qm[t, 0, 2] < band
    label._lower(fr, geo, sho, H, 4.0)
    assert fr.assign[MARKER_INDEX["R_TIB"]] == t
    assert fr.assign[i] == k


def test_a_crouched_knee_on_its_track_is_not_taken_for_the_tibia() -> None:
    fr, blob, geo, sho = _leg_frame()
    H = geo.sho_h
    # Feet out of view; the knee, crouched to a quarter of shoulder height (inside the foot
    # search's band), was labelled last frame and its track predicts it.
    k = blob["KNE"]
    fr.qm[k, :, 2] = 0.25 * H
    for s in ("TIB", "ANK", "HEE", "TOE"):
        fr.free[blob[s]] = False
        fr.qm[blob[s]] = np.nan
    i = MARKER_INDEX["R_KNE"]
    fr.pred[i] = fr.qm[k, 0]
    fr.sig[i] = (50.0, 70.0, 50.0)
    fr.tracked[i], fr.age[i] = True, 1
    label._lower(fr, geo, sho, H, 4.0)
    assert fr.assign[MARKER_INDEX["R_TIB"]] == -1
    assert fr.assign[i] == k
