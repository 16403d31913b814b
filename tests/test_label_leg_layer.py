"""Label output: a knee's depth layer chosen by continuity when something passes in front,
or against a marker of the same segment; the heel published at its surface point."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gaitflow.schemas import Markers3D
from gaitflow.stages import label
from gaitflow.stages.model import FloorFrame

from gaitflow.markers import MARKER_INDEX

KNE = MARKER_INDEX["L_KNE"]
HIP = MARKER_INDEX["L_HIP"]
HEE = MARKER_INDEX["L_HEE"]


def _markers(frame: int, knee_normal_z: float, knee_bottom_z: float) -> Markers3D:
    """Two blobs: 0 = a hip (all modes 2600 mm), 1 = a knee with its normal (and top) and
    bottom layers at the given depths."""
    pos = np.zeros((2, 3, 3))
    pos[0, :, :] = [100.0, 0.0, 2600.0]
    pos[1, :2, :] = [120.0, 400.0, knee_normal_z]
    pos[1, 2, :] = [120.0, 400.0, knee_bottom_z]
    return Markers3D(
        header=Markers3D.make_header("c", "walk-01", frame, frame),
        centroid=np.array([[300.0, 200.0], [305.0, 260.0]]),
        marker_radius=np.full(2, 2.0),
        region_radius=np.full(2, 4.0),
        depth=pos[:, :, 2].copy(),
        position=pos,
    )


def _assign() -> np.ndarray:
    a = np.full(20, -1)
    a[HIP], a[KNE] = 0, 1
    return a


def test_a_hand_in_front_of_the_knee_gives_way_to_the_layer_that_continues_it() -> None:
    prev = (np.full(20, np.nan), np.full(20, -(10**9)))
    # frame 0: one layer only; frame 1: a hand 90 mm in front of the knee for a frame
    out, prev = label._output(_markers(0, 2610.0, 2610.0), _assign(), 1, "L", prev)
    assert out.position[KNE, 2] == 2610.0
    out, prev = label._output(_markers(1, 2520.0, 2612.0), _assign(), 1, "L", prev)
    assert out.position[KNE, 2] == 2612.0
    assert out.position[HIP, 2] == 2600.0  # one layer: its own mode


def _hip(frame: int, normal_z: float, bottom_z: float) -> Markers3D:
    """Blob 0 a hip with its normal (and top) and bottom layers at the given depths."""
    mk = _markers(frame, 2610.0, 2610.0)
    pos = mk.position.copy()
    pos[0, :2, 2] = normal_z
    pos[0, 2, 2] = bottom_z
    return dataclasses.replace(mk, position=pos, depth=pos[:, :, 2].copy())


def test_a_hip_takes_the_normal_layer_where_its_bottom_one_is_the_body_behind_it() -> None:
    # The hip's own mode is the bottom one, for the arm that swings in front of it. With no
    # arm there, the bottom layer can be the far leg 125 mm behind: the normal layer
    # continues the hip's depth and is published (a frame later, the arm: bottom again).
    prev = (np.full(20, np.nan), np.full(20, -(10**9)))
    out, prev = label._output(_hip(0, 2600.0, 2600.0), _assign(), 1, "L", prev)
    assert out.position[HIP, 2] == 2600.0
    out, prev = label._output(_hip(1, 2603.0, 2728.0), _assign(), 1, "L", prev)
    assert out.position[HIP, 2] == 2603.0
    out, prev = label._output(_hip(2, 2540.0, 2604.0), _assign(), 1, "L", prev)
    assert out.position[HIP, 2] == 2604.0
    # without a recent depth of its own the bottom mode stands
    out, _ = label._output(_hip(2, 2603.0, 2728.0), _assign(), 1, "L", None)
    assert out.position[HIP, 2] == 2728.0


def test_a_hip_back_from_a_gap_is_judged_against_the_shoulder_in_the_floor_frame() -> None:
    # The hip, hidden for a while, reappears at the body's rear edge: its bottom layer is
    # the far leg 150 mm behind. Without a last depth of its own the near shoulder (blob 1,
    # 40 mm nearer the camera in the static pose) is the reference, and by floor depth: the
    # camera, tilted 10 deg down, sees the shoulder 500 mm above the hip.
    SHO = MARKER_INDEX["L_SHO"]
    tilt = np.radians(10.0)
    # floor axes in camera coordinates: along X; away from the camera and up, tilted
    rot = np.array(
        [[1.0, 0.0, 0.0], [0.0, np.sin(tilt), np.cos(tilt)], [0.0, -np.cos(tilt), np.sin(tilt)]]
    )
    ff = FloorFrame(rot=rot, origin=np.array([0.0, 800.0, 0.0]))
    hip_floor = np.array([1000.0, 2600.0, 900.0])
    sho_floor = hip_floor + np.array([0.0, -40.0, 500.0])
    ray = ff.to_camera(hip_floor)
    sho = ff.to_camera(sho_floor)

    def along(mm: float) -> np.ndarray:  # the point ``mm`` behind the hip on its ray
        return ray * (1.0 + mm / np.linalg.norm(ray))

    def frame(normal: np.ndarray, bottom: np.ndarray, shoulder: np.ndarray) -> Markers3D:
        pos = np.zeros((2, 3, 3))
        pos[0, :2], pos[0, 2], pos[1, :] = normal, bottom, shoulder
        return Markers3D(
            header=Markers3D.make_header("c", "walk-01", 9, 9),
            centroid=np.array([[300.0, 200.0], [300.0, 120.0]]),
            marker_radius=np.full(2, 2.0),
            region_radius=np.full(2, 4.0),
            depth=pos[:, :, 2].copy(),
            position=pos,
        )

    a = np.full(20, -1)
    a[HIP], a[SHO] = 0, 1
    ref, off = np.full(20, -1), np.zeros(20)
    ref[HIP], off[HIP] = SHO, 40.0
    unseen = (np.full(20, np.nan), np.full(20, -(10**9)))
    leg = frame(ray, along(150.0), sho)
    out, _ = label._output(leg, a, 1, "L", unseen, None, (ref, off), ff)
    np.testing.assert_allclose(out.position[HIP], ray)
    # not without the floor frame, nor without the shoulder in the frame
    out, _ = label._output(leg, a, 1, "L", unseen, None, (ref, off))
    np.testing.assert_allclose(out.position[HIP], along(150.0))
    no_sho = a.copy()
    no_sho[SHO] = -1
    out, _ = label._output(leg, no_sho, 1, "L", unseen, None, (ref, off), ff)
    np.testing.assert_allclose(out.position[HIP], along(150.0))
    # a layer 80 mm behind is within the shoulder's spread: the own (bottom) mode stands
    out, _ = label._output(frame(ray, along(80.0), sho), a, 1, "L", unseen, None, (ref, off), ff)
    np.testing.assert_allclose(out.position[HIP], along(80.0))
    # an arm 90 mm in front (the normal layer) never takes over, even with the shoulder
    # 80 mm nearer than its offset says
    arm = frame(along(-90.0), ray, ff.to_camera(sho_floor - np.array([0.0, 80.0, 0.0])))
    out, _ = label._output(arm, a, 1, "L", unseen, None, (ref, off), ff)
    np.testing.assert_allclose(out.position[HIP], ray)
    # a last depth of its own comes first: here it says the far layer
    own = (np.full(20, along(150.0)[2]), np.full(20, 8))
    out, _ = label._output(leg, a, 1, "L", own, None, (ref, off), ff)
    np.testing.assert_allclose(out.position[HIP], along(150.0))


def test_without_a_recent_depth_the_own_mode_stands() -> None:
    # no previous depth (None), or one too old: the knee keeps its own (normal) mode
    out, _ = label._output(_markers(1, 2520.0, 2612.0), _assign(), 1, "L", None)
    assert out.position[KNE, 2] == 2520.0
    stale = (np.full(20, 2610.0), np.full(20, -10))
    out, _ = label._output(_markers(1, 2520.0, 2612.0), _assign(), 1, "L", stale)
    assert out.position[KNE, 2] == 2520.0
    # a small difference is no reason to leave the own mode
    near = (np.full(20, 2610.0), np.zeros(20, int))
    out, _ = label._output(_markers(1, 2600.0, 2612.0), _assign(), 1, "L", near)
    assert out.position[KNE, 2] == 2600.0


def test_a_segment_reference_overrules_a_knee_depth_that_started_on_the_wrong_layer() -> None:
    # The mechanism, on a knee with a reference given (LAYER_REF pairs the ankle with the
    # tibia wand only). The thigh wand (blob 0, here in the hip's place) stands 50 mm
    # nearer the camera than the knee (the static pose's offset). The knee's track started
    # on the arm in front of it (2520) and continuity alone keeps it there; measured against
    # the wand on the same segment (2560 + 50 = 2610) the bottom layer (2612) is the knee's.
    thi = MARKER_INDEX["L_THI"]
    a = np.full(20, -1)
    a[thi], a[KNE] = 0, 1
    on_arm = (np.full(20, 2522.0), np.zeros(20, int))
    mk = _markers(1, 2520.0, 2612.0)
    pos = mk.position.copy()
    pos[0, :, 2] = 2560.0
    mk = dataclasses.replace(mk, position=pos)
    out, _ = label._output(mk, a, 1, "L", on_arm)
    assert out.position[KNE, 2] == 2520.0
    ref, off = np.full(20, -1), np.zeros(20)
    ref[KNE], off[KNE] = thi, 50.0
    out, _ = label._output(mk, a, 1, "L", on_arm, None, (ref, off))
    assert out.position[KNE, 2] == 2612.0
    # without the wand in the frame, continuity decides as before
    a[thi] = -1
    out, _ = label._output(mk, a, 1, "L", on_arm, None, (ref, off))
    assert out.position[KNE, 2] == 2520.0


def test_layer_references_pair_each_side_within_its_segment() -> None:
    geo = label.Geometry.from_model(None)
    ref, off = label.layer_reference(geo)
    for side in "LR":
        for site, r_site in label.LAYER_REF.items():
            k = MARKER_INDEX[f"{side}_{site}"]
            assert ref[k] == MARKER_INDEX[f"{side}_{r_site}"]
            want = geo.rel_sho("near", site)[1] - geo.rel_sho("near", r_site)[1]
            assert off[k] == pytest.approx(want)
    for side in "LR":
        k = MARKER_INDEX[f"{side}_HIP"]
        assert ref[k] == MARKER_INDEX[f"{side}_SHO"]
        want = geo.rel_sho("near", "HIP")[1] - geo.rel_sho("near", "SHO")[1]
        assert off[k] == pytest.approx(want)
    assert (ref >= 0).sum() == 2 * len(label.LAYER_REF | label.LAYER_FALLBACK)
    # The knee has none: the thigh wand's depth is the limb, the other leg or the wall
    # behind the stick, not a depth the knee's layer can be judged against.
    assert ref[MARKER_INDEX["L_KNE"]] == ref[MARKER_INDEX["R_KNE"]] == -1


def test_the_heel_is_published_at_its_surface_point() -> None:
    mk = dataclasses.replace(_markers(0, 2610.0, 2610.0), surface_offset_mm=14.5)
    a = np.full(20, -1)
    a[HEE], a[KNE] = 0, 1
    out, _ = label._output(mk, a, 1, "L", None, label.HEELS)
    before = mk.position[0, 2]
    # moved back along its own viewing ray by locate's offset; the knee is left alone
    moved = out.position[HEE] - before
    assert np.linalg.norm(moved) == pytest.approx(14.5)
    np.testing.assert_allclose(np.cross(moved, before), 0.0, atol=1e-6)
    assert np.linalg.norm(out.position[HEE]) > np.linalg.norm(before)
    np.testing.assert_array_equal(out.position[KNE], mk.position[1, 0])
    # off (no mask), or points locate left at the surface: as located
    out, _ = label._output(mk, a, 1, "L", None, None)
    np.testing.assert_array_equal(out.position[HEE], before)
    out, _ = label._output(_markers(0, 2610.0, 2610.0), a, 1, "L", None, label.HEELS)
    np.testing.assert_array_equal(out.position[HEE], before)
