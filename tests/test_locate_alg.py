"""Alg. 3 (3D marker location) on small literal depth frames."""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.schemas import Blobs, CleanFrame, Markers3D
from gaitflow.stages import locate

from gaitflow.camera import Camera
from gaitflow.errors import StageError


def params(**kw):
    return locate.PARAMS.resolve(kw)


def plane_with_hole(
    z0: float = 2500.0, seed: int = 0, shape=(60, 80), centre=(40.3, 30.6), hole=3.0
) -> np.ndarray:
    """A noisy plane at z0 mm with a marker hole and a few flying / invalid pixels."""
    rng = np.random.default_rng(seed)
    d = rng.normal(z0, 3.0, shape)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    r = np.hypot(cc - centre[0], rr - centre[1])
    d[r <= hole] = 0
    ring = np.flatnonzero((r > hole) & (r <= hole + 3))
    fly = rng.choice(ring, 4, replace=False)
    d.ravel()[fly[:2]] = z0 - rng.uniform(200, 900, 2)  # flying pixels in front
    d.ravel()[fly[2:]] = z0 + rng.uniform(300, 1500, 2)  # and behind
    d.ravel()[rng.choice(ring, 3, replace=False)] = 0  # edge dropouts
    return np.clip(d, 0, 65535).astype(np.uint16)


@pytest.mark.parametrize("seed", range(5))
def test_depth_on_plane_within_2mm_despite_hole_and_flying_pixels(seed: int) -> None:
    d = plane_with_hole(seed=seed)
    z = locate.locate_depth(d, (40.3, 30.6), 3.4, params())
    assert abs(z[0] - 2500.0) < 2.0, z
    zb = locate.locate_depths(d, np.array([[40.3, 30.6]]), np.array([3.4]), params())
    assert abs(zb[0, 0] - 2500.0) < 2.0


def test_bottom_mode_picks_far_layer_behind_an_arm() -> None:
    d = plane_with_hole(z0=2500.0, seed=7)
    # An arm 110 mm in front covers the left part of the window, beside the marker.
    arm = np.random.default_rng(1).normal(2390.0, 3.0, (60, 16))
    d[:, 26:42] = np.where(d[:, 26:42] > 0, arm, 0).astype(np.uint16)
    z_normal, z_top, z_bottom = locate.locate_depth(d, (40.3, 30.6), 3.4, params())
    assert abs(z_bottom - 2500.0) < 2.0
    assert abs(z_normal - 2390.0) < 5.0
    assert z_top == z_normal  # Rec. [A-3b]: top shares normal's layer unless top_half
    # Background metres behind is out of bottom's reach: it stays on the body.
    d2 = d.copy()
    d2[:, 50:] = 4200
    assert abs(locate.locate_depth(d2, (40.3, 30.6), 3.4, params())[2] - 2500.0) < 2.0


def test_too_few_valid_pixels_gives_nan() -> None:
    d = np.zeros((30, 30), np.uint16)
    d[0, 0] = 2000
    z = locate.locate_depth(d, (15.0, 15.0), 2.0, params())
    assert np.isnan(z).all()
    zb = locate.locate_depths(
        d, np.array([[15.0, 15.0], [np.nan, 3.0]]), np.array([2.0, 2.0]), params()
    )
    assert np.isnan(zb).all()


@pytest.mark.parametrize("top_half", [False, True])
def test_batched_equals_per_blob(top_half: bool) -> None:
    rng = np.random.default_rng(11)
    p = params(top_half=top_half)
    for _ in range(40):
        h, w = 50, 70
        d = rng.normal(2700, 20, (h, w))
        d[:, : rng.integers(0, w)] = rng.choice([2560.0, 2620.0, 4000.0])
        d[rng.random((h, w)) < 0.1] = 0
        d[rng.random((h, w)) < 0.05] = rng.uniform(500, 5000)
        d = np.clip(d, 0, 65535).astype(np.uint16)
        cen = np.stack([rng.uniform(-3, w + 3, 6), rng.uniform(-3, h + 3, 6)], 1)
        rr = rng.uniform(0.5, 9.0, 6)
        batch = locate.locate_depths(d, cen, rr, p)
        single = np.array([locate.locate_depth(d, c, r, p) for c, r in zip(cen, rr, strict=True)])
        np.testing.assert_allclose(batch, single, atol=1e-6)


def test_positions_backproject_and_marker_centre_offset() -> None:
    cam = Camera()
    d = np.full((424, 512), 2500, np.uint16)
    cen = np.array([[100.4, 80.2], [400.7, 350.1]])
    d[78:83, 98:103] = 0
    d[348:353, 398:403] = 0
    rr = np.array([2.0, 2.0])
    z0, pos0 = locate.locate_all(d, cen, rr, cam, params(surface_offset=False))
    np.testing.assert_allclose(z0, 2500.0, atol=1e-9)
    ref = cam.backproject(cen, np.full(2, 2500.0))
    np.testing.assert_allclose(pos0[:, 0], ref, atol=1e-9)
    np.testing.assert_allclose(pos0[:, 2], ref, atol=1e-9)
    z1, pos1 = locate.locate_all(d, cen, rr, cam, params(marker_diameter_mm=25.0))
    # The centre is one radius plus the base height (2 mm) nearer along the same ray.
    shrink = np.linalg.norm(pos0, axis=2) - np.linalg.norm(pos1, axis=2)
    np.testing.assert_allclose(shrink, 12.5 + 2.0, atol=1e-9)
    assert (z1 < 2500.0).all()


def locate_inputs(
    depth: np.ndarray,
    centroid: np.ndarray,
    region_radius: np.ndarray,
    area: np.ndarray,
    camera: dict | None = None,
) -> tuple[CleanFrame, Blobs]:
    """locate's inputs for one frame: a clean frame of ``depth`` (IR and mask blank) and
    blobs at ``centroid`` (K, 2) with ``region_radius`` and ``area`` (K,)."""
    h = CleanFrame.make_header("cam0", "walk-01", 3, 0)
    cf = CleanFrame(
        header=h,
        ir=np.zeros(depth.shape, np.uint16),
        depth=depth,
        mask=np.zeros(depth.shape, np.uint8),
        camera=camera or {},
    )
    k = len(centroid)
    bl = Blobs.follow(
        h,
        centroid=np.asarray(centroid, dtype=np.float64).reshape(-1, 2),
        marker_radius=np.full(k, 2.0),
        region_radius=np.asarray(region_radius, dtype=np.float64),
        mean_ir=np.full(k, 60000.0),
        area=np.asarray(area).astype(np.int32),
        threshold=30000.0,
    )
    return cf, bl


def _msgs(camera: dict | None = None) -> tuple[CleanFrame, Blobs]:
    d = plane_with_hole(shape=(424, 512), centre=(200.3, 150.6))
    return locate_inputs(d, np.array([[200.3, 150.6]]), np.array([3.4]), np.array([30]), camera)


def test_step_uses_camera_from_clean_frame_and_param_override() -> None:
    cf, bl = _msgs()
    st = locate.init(params(surface_offset=False))
    st, (out,) = locate.step(st, {"clean": cf, "blobs": bl})
    assert isinstance(out, Markers3D)
    assert out.position.shape == (1, 3, 3) and out.depth.shape == (1, 3)
    x_default = out.position[0, 0, 0]
    other = Camera(fx=500.0, fy=500.0, cx=250.0, cy=200.0).to_json()
    cf2, _ = _msgs(camera=other)
    st, (out2,) = locate.step(st, {"clean": cf2, "blobs": bl})
    assert out2.position[0, 0, 0] != pytest.approx(x_default)
    expect = Camera.from_json(other).backproject(bl.centroid, out2.depth[:, 0])
    np.testing.assert_allclose(out2.position[:, 0], expect, atol=1e-6)
    # An explicit parameter wins over the frame's camera.
    st3 = locate.init(params(surface_offset=False, camera=Camera().to_json()))
    _, (out3,) = locate.step(st3, {"clean": cf2, "blobs": bl})
    assert out3.position[0, 0, 0] == pytest.approx(x_default)


def test_bad_camera_document_is_a_stage_error() -> None:
    with pytest.raises(StageError, match="camera"):
        locate.init(params(camera={"model": "x", "depth_intrinsics": {}}))
    with pytest.raises(StageError, match="unknown camera key"):
        locate.init(params(camera={"focal": 3.0}))


def test_marker_diameter_from_session_camera_json_unless_set() -> None:
    cam_doc = {**Camera().to_json(), "marker_diameter_mm": 30}
    cf, bl = _msgs(camera=cam_doc)
    _, (raw_pt,) = locate.step(
        locate.init(params(surface_offset=False)), {"clean": cf, "blobs": bl}
    )
    _, (out,) = locate.step(locate.init(params()), {"clean": cf, "blobs": bl})
    shrink = np.linalg.norm(raw_pt.position[0, 0]) - np.linalg.norm(out.position[0, 0])
    assert shrink == pytest.approx(15.0 + 2.0)
    _, (out2,) = locate.step(
        locate.init(params(marker_diameter_mm=20.0)), {"clean": cf, "blobs": bl}
    )
    shrink2 = np.linalg.norm(raw_pt.position[0, 0]) - np.linalg.norm(out2.position[0, 0])
    assert shrink2 == pytest.approx(10.0 + 2.0)
    # The message says how far it moved the points, so that label can undo it per site.
    assert raw_pt.surface_offset_mm == 0.0
    assert out.surface_offset_mm == pytest.approx(shrink)
    assert out2.surface_offset_mm == pytest.approx(shrink2)
    # A flat mapping of Camera fields is accepted as the intrinsics override too.
    st = locate.init(params(camera={"fx": 500.0, "fy": 500.0}))
    assert st.camera.fx == 500.0


def test_one_pass_equals_per_blob_with_one_wide_blob() -> None:
    # The flat one-pass Alg. 3 (no padding) against the per-blob reference, when a wide
    # blob (a lamp, a streak) shares the frame with marker-sized ones.
    rng = np.random.default_rng(5)
    p = params()
    h, w = 120, 160
    d = rng.normal(2600, 15, (h, w))
    d[:, 90:] = 3900.0
    d[rng.random((h, w)) < 0.08] = 0
    d = np.clip(d, 0, 65535).astype(np.uint16)
    cen = np.array([[20.2, 30.7], [85.5, 60.1], [140.3, 10.9], [60.0, 100.4], [150.0, 115.0]])
    rr = np.array([2.1, 28.5, 3.3, 1.2, 4.0])
    batch = locate.locate_depths(d, cen, rr, p)
    single = np.array([locate.locate_depth(d, c, r, p) for c, r in zip(cen, rr, strict=True)])
    np.testing.assert_allclose(batch, single, atol=1e-6)
    assert np.isfinite(batch).all()
