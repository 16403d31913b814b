"""Label stage: the thigh wand above the knee (limb search) and the walking direction of a
shoulder track that restarts mid-walkway.

Literal layouts in the floor frame (forward along the walking direction, e away from the
camera, height; mm) around the stature-scaled template subject (no static model).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from gaitflow.stages import label
from gaitflow.stages.model import FloorFrame
from test_label_accuracy import _leg_frame

from gaitflow.evaluate_label import calibration_record, to_camera
from gaitflow.markers import MARKER_INDEX


def _low_thigh_frame() -> tuple[label._Frame, dict[str, int], label.Geometry, np.ndarray]:
    """Near leg R at the template's standing offsets, hip hidden (``_leg_frame``), and the
    thigh wand only 60 mm above the knee marker (10 mm behind, 20 mm nearer the camera: a
    wand on the lower thigh); the thigh's stale track (2 frames old) predicts it at the
    knee blob."""
    fr, blob, geo, sho = _leg_frame()
    thi, kne = blob["THI"], blob["KNE"]
    fr.qm[thi] = fr.qm[kne] + (-10.0, -20.0, 60.0)
    i = MARKER_INDEX["R_THI"]
    fr.pred[i], fr.sig[i] = fr.qm[kne, 0], (70.0, 90.0, 70.0)
    fr.tracked[i], fr.age[i] = True, 2
    return fr, blob, geo, sho


def test_thigh_wand_low_on_the_thigh_is_not_swapped_with_the_knee() -> None:
    fr, blob, geo, sho = _low_thigh_frame()
    label._lower(fr, geo, sho, geo.sho_h, 4.0)
    thi, kne = blob["THI"], blob["KNE"]
    # Without a hip label the thigh-above-knee order used to count only with every slot of
    # the limb search filled: both labels were left out (or swapped on other frames).
    assert fr.assign[MARKER_INDEX["R_KNE"]] == kne
    assert fr.assign[MARKER_INDEX["R_THI"]] == thi


def test_a_thigh_label_below_the_knee_label_is_never_chosen() -> None:
    fr, blob, geo, sho = _low_thigh_frame()
    # The thigh wand blob 60 mm below the knee blob: never thigh below knee in the labels.
    thi, kne = blob["THI"], blob["KNE"]
    fr.qm[thi, :, 2] = fr.qm[kne, 0, 2] - 60.0
    label._lower(fr, geo, sho, geo.sho_h, 4.0)
    a_t, a_k = fr.assign[MARKER_INDEX["R_THI"]], fr.assign[MARKER_INDEX["R_KNE"]]
    assert not (a_t >= 0 and a_k >= 0 and fr.qm[a_t, 0, 2] < fr.qm[a_k, 0, 2])


def test_a_thigh_wand_whose_far_layer_is_the_wall_is_still_the_thigh() -> None:
    # A wand's ring holds no surface of its own: its farthest layer (bottom mode) is
    # whatever lies behind the stick, here the wall 1 m behind the subject. The thigh wand
    # is matched on its nearest layer (the stick, or the near side of the limb).
    fr, blob, geo, sho = _leg_frame()
    thi = blob["THI"]
    fr.qm[thi, label.BOTTOM, 1] += 1000.0
    label._lower(fr, geo, sho, geo.sho_h, 4.0)
    assert fr.assign[MARKER_INDEX["R_THI"]] == thi
    assert fr.assign[MARKER_INDEX["R_KNE"]] == blob["KNE"]


# --- the direction of a restarted shoulder track ---------------------------------------


def test_shoulder_move_matches_in_3d_and_ignores_the_far_shoulder() -> None:
    prev = np.array([[1000.0, 250.0, 1400.0], [985.0, 0.0, 1402.0]])  # far, near shoulder
    # The far shoulder is nearer along the line and in height, but 250 mm deeper.
    assert label._shoulder_move(np.array([1012.0, 2.0, 1400.0]), prev, 140.0) == 27.0
    assert label._shoulder_move(np.array([1012.0, 2.0, 1400.0]), None, 140.0) == 0.0
    assert label._shoulder_move(np.array([1400.0, 2.0, 1400.0]), prev, 140.0) == 0.0


def _restart(move: float | None, lost: bool = True, at: float = 0.8, heading: int = 1) -> int:
    """Direction after one frame in which the shoulder shows at ``at`` of the walkway (80 %:
    its far half, so "toward the far end" says -1), with a hip, thigh and knee below it.

    ``heading``: the walking direction before. ``lost``: a shoulder track coasted 5 frames
    (``max_missed``) far from it and ends in this frame; else there was no track (a pass's
    first sight). ``move``: how far along the line the blobs moved since the last frame, mm
    (None: no last frame).
    """
    geo = label.Geometry.from_model(None)
    H = geo.sho_h
    ff = FloorFrame.from_record(calibration_record(), 800.0)
    a = at * ff.length
    body = [(a, 0.0, H)] + [(a - 30.0, 60.0, h * H) for h in (0.7, 0.5, 0.35)]
    st = label.init(label.PARAMS.resolve({}))
    st = replace(st, trial="walk-01", frame=20, direction=heading, walked=True)
    if lost:
        x = np.array([a - 900.0, -600.0, H, 900.0, -900.0, 0.0])  # drifted far off
        st = replace(st, sho_x=x, sho_cov=np.eye(6) * 100.0**2, sho_missed=5)
    if move is not None:
        prev = np.array(body, float)
        prev[:, 0] -= move
        st = replace(st, prev_q=prev)
    pos = np.repeat(to_camera(np.array(body))[:, None, :], 3, axis=1)
    st, _ = label.label_frame(st, pos, 21, ff, geo)
    return st.direction


def test_a_lost_track_restarts_in_the_direction_the_shoulder_moves() -> None:
    # The shoulder moved +35 mm since the last frame: walking toward +a although in the
    # walkway's far half (the first-sight guess said -1 and named the wrong side).
    assert _restart(move=35.0) == 1
    assert _restart(move=-35.0) == -1
    # Too little move (under dir_speed, 250 mm/s): the far-end guess stands.
    assert _restart(move=5.0) == -1


def test_a_track_lost_the_frame_before_restarts_in_the_direction_of_the_move() -> None:
    geo = label.Geometry.from_model(None)
    H = geo.sho_h
    ff = FloorFrame.from_record(calibration_record(), 800.0)
    a = 0.8 * ff.length
    body = np.array([(a, 0.0, H)] + [(a - 30.0, 60.0, h * H) for h in (0.7, 0.5, 0.35)])
    st = label.init(label.PARAMS.resolve({}))
    prev = body.copy()
    prev[:, 0] -= 35.0
    st = replace(st, trial="walk-01", frame=20, sho_lost=20, prev_q=prev)
    pos = np.repeat(to_camera(body)[:, None, :], 3, axis=1)
    assert label.label_frame(st, pos, 21, ff, geo)[0].direction == 1
    # Longer ago than max_missed frames: a new pass, the far-end guess.
    st = replace(st, sho_lost=10)
    assert label.label_frame(st, pos, 21, ff, geo)[0].direction == -1


def test_a_track_lost_mid_walkway_with_its_blob_restarts_in_the_lost_direction() -> None:
    # The shoulder blob was missed in the last frame too (no move to measure): in the
    # middle of the walkway the lost track's direction (+1) stands, where the far-end guess
    # (-1 from the walkway's middle on) named the wrong side (a child's walk, 7 frames).
    assert _restart(move=None, at=0.55) == 1
    assert _restart(move=None, at=0.3, heading=-1) == -1
    # Near an end the subject may have turned: the far-end guess.
    assert _restart(move=None, at=0.8) == -1


def test_a_pass_first_sight_keeps_the_far_end_guess() -> None:
    # No track before: a blob entering the image moves with its visible part, so its move
    # is not trusted.
    assert _restart(move=35.0, lost=False) == -1


def recorded_frame(name: str) -> tuple[label._Frame, label.Geometry, np.ndarray, float, float]:
    """A label stage working frame recorded from a simulated walk (``tests/data``)."""
    import json
    from pathlib import Path

    doc = json.loads((Path(__file__).parent / "data" / name).read_text())
    f, g = doc["frame"], doc["geometry"]
    fr = label._Frame(
        qm=np.array(f["qm"]),
        free=np.array(f["free"]),
        assign=np.array(f["assign"]),
        pred=np.array(f["pred"]),
        sig=np.array(f["sig"]),
        near=f["near"],
        tracked=np.array(f["tracked"]),
        ambiguity=f["ambiguity"],
        age=np.array(f["age"]),
        publish_asis_psis=f["publish_asis_psis"],
        outside=np.array(f["outside"]),
        cam=np.array(f["cam"]),
        still=None if f.get("still") is None else np.array(f["still"]),
    )
    geo = label.Geometry(
        offsets=np.array(g["offsets"]),
        dist=np.array(g["dist"]),
        sho_h=g["sho_h"],
        pelvis_d0={(a, b): v for a, b, v in g["pelvis_d0"]},
        wand_off=g["wand_off"],
    )
    return fr, geo, np.array(doc["sho"]), doc["H"], doc["gate"]


def test_the_thigh_wand_does_not_take_a_blob_far_above_its_standing_height(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The first frame of a walk back (the `mirror` set-up): the near leg walks in with the
    # thigh and knee low (late stance) and nothing tracked yet. Against the standing pose
    # the leg shifted up by one marker fitted better: the thigh label took the near ASI's
    # blob (735 mm high, the wand stands at 550), the knee the thigh's and the tibia the
    # knee's, and the tracks held the shift for 17 frames.
    asi, thi = 8, 3  # blobs, from the simulator's truth
    fr, geo, sho, H, gate = recorded_frame("label_mirror_first_frame.json")
    label._lower(fr, geo, sho, H, gate)
    assert fr.assign[MARKER_INDEX["R_THI"]] != asi
    assert fr.assign[MARKER_INDEX["R_THI"]] in (-1, thi)
    # Without the rule (a rise allowed up to twice the thigh), the shift comes back.
    monkeypatch.setattr(label, "THI_RISE", 2.0)
    fr, geo, sho, H, gate = recorded_frame("label_mirror_first_frame.json")
    label._lower(fr, geo, sho, H, gate)
    assert fr.assign[MARKER_INDEX["R_THI"]] == asi
    assert fr.assign[MARKER_INDEX["R_KNE"]] == thi


def test_an_untracked_hip_far_below_the_shoulders_bob_is_dropped_for_the_leg(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The first labelled frame of a walk back (``far+d30+noisy+strays_late+paretic``, the
    # crouched walker): the near hip is hidden, nothing is tracked, and the shoulder stands
    # 83 mm above its standing height (the gait's bob). The pelvis search gave the hip label
    # to the thigh wand's blob, 31 mm below the hip's standing height above the floor but
    # 114 mm below its standing drop from the shoulder; the limb search then kept it, put
    # the thigh label on the knee's blob and left the knee out.
    thi, kne = 2, 1  # blobs, from the simulator's truth
    fr, geo, sho, H, gate = recorded_frame("label_bobbing_hidden_hip.json")
    hip_i = MARKER_INDEX["L_HIP"]
    assert fr.assign[hip_i] == thi  # the pelvis search's choice, before the limb
    label._lower(fr, geo, sho, H, gate)
    assert fr.assign[hip_i] == -1
    assert fr.assign[MARKER_INDEX["L_THI"]] == thi
    assert fr.assign[MARKER_INDEX["L_KNE"]] == kne
    # Without the shoulder's height (any drop allowed), the shifted leg comes back.
    monkeypatch.setattr(label, "HIP_BELOW_SHO_SIG", 1e6)
    fr, geo, sho, H, gate = recorded_frame("label_bobbing_hidden_hip.json")
    label._lower(fr, geo, sho, H, gate)
    assert fr.assign[hip_i] == thi
    assert fr.assign[MARKER_INDEX["L_THI"]] == kne
    assert fr.assign[MARKER_INDEX["L_KNE"]] == -1
