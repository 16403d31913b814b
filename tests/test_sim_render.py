"""Simulator rendering: camera round trip, marker blobs, depth noise, occlusion."""

from __future__ import annotations

import numpy as np
import pytest

from gaitflow.errors import ConfigError
from gaitflow.sim.config import SimConfig
from gaitflow.sim.render import SAT, FramePose, Renderer, axial_sigma_mm
from gaitflow.sim.truth import merged_flags, visibility

# Fronto-parallel wall at Z = 2.5 m: the camera looks straight at it.
FLAT_SCENE = dict(
    tilt_deg=0.0,
    pan_deg=0.0,
    roll_deg=0.0,
    walk_distance_mm=1000.0,
    back_wall_mm=1500.0,
    stray_reflectors=False,
)


@pytest.fixture(scope="module")
def flat_renderer() -> Renderer:
    return Renderer(SimConfig(**FLAT_SCENE))


def _pose(centre_world: np.ndarray, blur: int = 1) -> FramePose:
    sph = np.repeat(np.asarray(centre_world, float)[None, None], blur, axis=0)
    e = np.zeros((0, 3))
    return FramePose(sph, e, e, np.zeros(0), np.zeros(0))


def test_projection_round_trip_within_0_01_px(flat_renderer: Renderer) -> None:
    r = Renderer(SimConfig())  # default pose: tilted, panned, rolled
    cam = r.cam
    rng = np.random.default_rng(3)
    world = np.c_[
        rng.uniform(-1800, 1800, 200), rng.uniform(1500, 4000, 200), rng.uniform(0, 2000, 200)
    ]
    pc = r.to_cam(world)
    uv = cam.project(pc)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= 511) & (uv[:, 1] >= 0) & (uv[:, 1] <= 423)
    assert inside.sum() > 100
    xy = cam.undistort(uv[inside])
    back = np.c_[cam.fx * xy[:, 0] + cam.cx, cam.fy * xy[:, 1] + cam.cy]
    want = np.c_[
        cam.fx * pc[inside, 0] / pc[inside, 2] + cam.cx,
        cam.fy * pc[inside, 1] / pc[inside, 2] + cam.cy,
    ]
    assert np.abs(back - want).max() < 0.01
    # The renderer's per-pixel rays land back on their own pixel centres, corners included.
    for v, u in [(0, 0), (0, 511), (423, 0), (423, 511), (212, 256), (100, 400)]:
        p = 2500.0 * np.array([r.rx[v, u], r.ry[v, u], 1.0])
        assert np.abs(cam.project(p[None])[0] - [u, v]).max() < 0.01


def test_marker_is_saturated_blob_over_depth_hole(flat_renderer: Renderer) -> None:
    r = flat_renderer
    cfg = r.cfg
    # Sphere centre 2.5 m in front of the camera, slightly off a pixel centre.
    c_cam = np.array([31.0, -17.0, 2500.0])
    c_world = c_cam @ r.R + r.C
    out = r.render(_pose(c_world), np.random.default_rng(0))
    sat = out.ir == SAT
    hole = out.depth == 0
    expected_d = r.cam.fx * cfg.marker_diameter_mm / 2500.0  # 3.66 px
    d_sat = 2 * np.sqrt(sat.sum() / np.pi)
    assert abs(d_sat - expected_d) < 0.75, (d_sat, expected_d)
    # The depth hole has the same footprint as the saturated blob.
    inter = (sat & hole).sum()
    union = (sat | hole).sum()
    assert inter / union >= 0.8
    # Partial-pixel edges: pixels next to the blob are brighter than the wall but not
    # saturated.
    uv = r.cam.project(c_cam[None])[0]
    v, u = round(uv[1]), round(uv[0])
    ring = out.ir[v - 4 : v + 5, u - 4 : u + 5].astype(float)
    wall = np.median(out.ir[v - 30 : v - 20, u - 30 : u - 20])
    partial = (ring > wall + 8 * cfg.ir_read_noise) & (ring < SAT)
    assert partial.sum() >= 3
    assert out.in_view[0] and out.seen[0] == pytest.approx(1.0)


def test_motion_blur_streaks_fast_marker(flat_renderer: Renderer) -> None:
    r = flat_renderer
    c0 = np.array([0.0, 0.0, 2500.0])
    # 4 m/s across the image during a 12 ms exposure = 48 mm = ~7 px of travel.
    path = np.stack([c0 + np.array([dx, 0.0, 0.0]) for dx in np.linspace(-24, 24, 8)])
    still = r.render(_pose(c0 @ r.R + r.C), np.random.default_rng(1))
    sph = (path @ r.R + r.C)[:, None, :]
    e = np.zeros((0, 3))
    moving = r.render(FramePose(sph, e, e, np.zeros(0), np.zeros(0)), np.random.default_rng(1))
    bright_still = (still.ir > 20000).sum()
    bright_moving = (moving.ir > 20000).sum()
    assert bright_moving > 1.5 * bright_still

    # The streak runs along the motion (image x): about 7 px longer than the still blob.
    def extent(img: np.ndarray, axis: int) -> int:
        idx = np.flatnonzero((img > 20000).any(axis=axis))
        return int(idx[-1] - idx[0]) + 1

    assert extent(moving.ir, 0) - extent(still.ir, 0) >= 5
    assert extent(moving.ir, 1) - extent(still.ir, 1) <= 1


def test_depth_noise_matches_fankhauser_within_20_percent(flat_renderer: Renderer) -> None:
    r = flat_renderer
    rng = np.random.default_rng(5)
    frames = np.stack([r.render(None, rng).depth for _ in range(40)]).astype(float)
    v, u = int(r.cam.cy), int(r.cam.cx)
    patch = frames[:, v - 15 : v + 15, u - 15 : u + 15]
    assert (patch > 0).all()
    assert abs(patch.mean() - 2500.0) < 2.0
    measured = patch.std(axis=0, ddof=1).mean()
    model = float(axial_sigma_mm(2500.0, 0.0))
    assert model == pytest.approx(2.125, abs=1e-9)
    assert abs(measured / model - 1) < 0.2, (measured, model)
    # Grazing floor: noise grows with incidence as the model says.
    theta = np.arccos(np.clip(r.bg_cos, 0, 1))
    z = r.bg_z
    sel = (np.abs(np.degrees(theta) - 70) < 1.5) & (z < 2200) & (z > 1200)
    sel &= (frames > 0).all(axis=0)
    assert sel.sum() > 200
    meas = frames[:, sel].std(axis=0, ddof=1)
    pred = axial_sigma_mm(z[sel], theta[sel])
    ratio = np.sqrt(np.mean(meas**2) / np.mean(pred**2 + 1 / 12))
    assert abs(ratio - 1) < 0.2, ratio
    assert np.mean(pred) > 1.5 * model


def test_marker_behind_arm_is_dark_and_flagged_occluded(flat_renderer: Renderer) -> None:
    r = flat_renderer
    c_cam = np.array([0.0, 0.0, 2300.0])
    # An arm (capsule, radius 45 mm) hanging 150 mm in front of the marker.
    a_cam = np.array([0.0, -300.0, 2150.0])
    b_cam = np.array([0.0, 300.0, 2150.0])
    sph = (c_cam @ r.R + r.C)[None, None]
    pose = FramePose(
        sph,
        (a_cam @ r.R + r.C)[None],
        (b_cam @ r.R + r.C)[None],
        np.array([45.0]),
        np.array([0.4]),
    )
    out = r.render(pose, np.random.default_rng(2))
    uv = r.cam.project(c_cam[None])[0]
    v, u = round(uv[1]), round(uv[0])
    assert out.ir[v - 6 : v + 7, u - 6 : u + 7].max() < 20000
    # The arm itself is there in depth.
    assert abs(float(np.median(out.depth[v - 3 : v + 4, u - 3 : u + 4])) - 2105) < 20
    visible, occluded = visibility(out.seen, out.in_view)
    assert occluded[0] and not visible[0]
    # Control: without the arm the same marker is visible and saturated.
    free = r.render(_pose(c_cam @ r.R + r.C), np.random.default_rng(2))
    visible, occluded = visibility(free.seen, free.in_view)
    assert visible[0] and not occluded[0]
    assert free.ir[v - 6 : v + 7, u - 6 : u + 7].max() == SAT


def test_marker_behind_marker_is_z_buffered_and_flagged(flat_renderer: Renderer) -> None:
    """A sphere half behind another: hidden where the nearer covers it, not added."""
    r = flat_renderer
    front = np.array([0.0, 0.0, 2300.0])
    px_mm = 2300.0 / r.cam.fx
    # 6 mm to the side (half a radius) and 60 mm behind: mostly hidden.
    behind = front + np.array([6.0, 0.0, 60.0])
    sph = np.stack([front, behind]) @ r.R + r.C
    pose = FramePose(sph[None], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    out = r.render(pose, np.random.default_rng(4))
    visible, occluded = visibility(out.seen, out.in_view)
    assert visible[0] and out.seen[0] == 1.0
    assert occluded[1] and not visible[1] and 0.0 < out.seen[1] < 0.5
    # Control: the rear sphere alone is fully seen, and further aside both are visible.
    alone = r.render(_pose(behind @ r.R + r.C), np.random.default_rng(4))
    assert alone.seen[0] == 1.0
    aside = front + np.array([20.0, 0.0, 60.0])
    sph2 = np.stack([front, aside]) @ r.R + r.C
    pose2 = FramePose(sph2[None], np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    out2 = r.render(pose2, np.random.default_rng(4))
    assert visible_both(out2) and 0.5 < out2.seen[1] < 1.0
    # Their image discs overlap (centres 20 mm ~ 3 px apart, radii ~ 2 px): merged.
    streak = r.cam.project(np.stack([front, aside]))[None]
    rad = r.cam.fx * r.cfg.marker_radius_mm / np.array([[front[2], aside[2]]])
    assert merged_flags(streak, rad, np.array([True, True])).all()
    # Far apart: not merged; an invisible neighbour never merges.
    far = streak.copy()
    far[0, 1, 0] += 60.0 / px_mm
    assert not merged_flags(far, rad, np.array([True, True])).any()
    assert not merged_flags(streak, rad, np.array([True, False])).any()


def visible_both(out) -> bool:
    visible, _ = visibility(out.seen, out.in_view)
    return bool(visible.all())


def test_static_reflector_saturates_in_an_empty_scene_and_hides_behind_the_body() -> None:
    """A marker-like sphere fixed in the room: a saturated blob over a depth hole in every
    frame, with or without a subject; the subject's arm in front of it hides it; never in
    the truth arrays (``seen``)."""
    base = dict(tilt_deg=0.0, pan_deg=0.0, roll_deg=0.0, walk_distance_mm=1000.0,
                back_wall_mm=1500.0, stray_reflectors=False)  # fmt: skip
    plain = Renderer(SimConfig(**base))
    r = Renderer(SimConfig(**base, static_reflectors=((0.0, 2300.0, 700.0),)))  # 100 mm up
    c_cam = r.to_cam(np.array([0.0, 2300.0, 700.0]))
    uv = r.cam.project(c_cam[None])[0]
    v, u = round(uv[1]), round(uv[0])
    win = (slice(v - 6, v + 7), slice(u - 6, u + 7))
    empty = r.render(None, np.random.default_rng(5))
    assert empty.ir[win].max() == SAT and (empty.depth[win] == 0).sum() >= 4
    assert plain.render(None, np.random.default_rng(5)).ir[win].max() < 20000
    # a subject's marker elsewhere in the image: the reflector is still there, not in seen
    marker = _pose(r.to_cam(np.array([600.0, 2300.0, 700.0])) @ r.R + r.C)
    out = r.render(marker, np.random.default_rng(5))
    assert out.ir[win].max() == SAT and out.seen.shape == (1,)
    # ... and the same with a body box around it: the box starts from the scene without
    # the reflector and puts it back (no double radiance, the same hole)
    arm_far = FramePose(
        marker.spheres,
        (np.array([-120.0, 2200.0, 400.0]))[None],
        (np.array([-120.0, 2200.0, 1000.0]))[None],
        np.array([45.0]),
        np.array([0.4]),
    )
    near_box = r.render(arm_far, np.random.default_rng(5))
    assert near_box.ir[win].max() == SAT
    np.testing.assert_array_equal(near_box.depth[win] == 0, empty.depth[win] == 0)
    # an arm 100 mm in front of it hides it
    arm = FramePose(
        marker.spheres,
        (np.array([0.0, 2200.0, 400.0]))[None],
        (np.array([0.0, 2200.0, 1000.0]))[None],
        np.array([45.0]),
        np.array([0.4]),
    )
    hid = r.render(arm, np.random.default_rng(5))
    assert hid.ir[win].max() < 20000 and (hid.depth[win] == 0).sum() == 0


def test_lens_glare_widens_the_depth_hole_and_pulls_the_ring_towards_the_marker(
    flat_renderer: Renderer,
) -> None:
    plain, glared = flat_renderer, Renderer(SimConfig(glare_fraction=0.03, **FLAT_SCENE))
    c_cam = np.array([31.0, -17.0, 2000.0])  # half a metre before the wall
    outs = [r.render(_pose(c_cam @ r.R + r.C), np.random.default_rng(0)) for r in (plain, glared)]
    uv = plain.cam.project(c_cam[None])[0]
    v, u = round(uv[1]), round(uv[0])
    near = (slice(v - 5, v + 6), slice(u - 5, u + 6))
    sat = [(o.ir[near] == SAT).sum() for o in outs]
    hole = [(o.depth[near] == 0).sum() for o in outs]
    assert sat[1] == sat[0]  # the marker's image is the same
    # A 4.6 px disc's hole grown by about a pixel all round: at least 1.8 times the area.
    assert hole[1] >= 1.8 * hole[0], hole
    # Where depth is still valid next to the hole, the stray light pulls it nearer (the
    # sphere's front is about 0.5 m nearer than the wall behind it).
    both = (outs[0].depth[near] > 0) & (outs[1].depth[near] > 0)
    pull = outs[1].depth[near][both].astype(float) - outs[0].depth[near][both]
    assert pull.min() < -20.0 and np.median(pull) <= 0.0
    # Stray light brightens the IR around the marker, and nothing far from it changes.
    ring = outs[1].ir[near].astype(float) - outs[0].ir[near]
    assert (ring[outs[0].ir[near] < SAT] > 0).sum() >= 20
    far = (slice(v - 40, v - 20), slice(u - 40, u - 20))
    assert np.array_equal(outs[1].ir[far], outs[0].ir[far])
    assert np.array_equal(outs[1].depth[far], outs[0].depth[far])


def test_lens_glare_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match=r"glare_fraction=0\.6"):
        SimConfig(glare_fraction=0.6)
    with pytest.raises(ConfigError, match="glare_sigma_px=0"):
        SimConfig(glare_fraction=0.03, glare_sigma_px=0.0)
