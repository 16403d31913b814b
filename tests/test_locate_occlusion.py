"""locate's completion of partly hidden markers (``complete_occluded``) on literal frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gaitflow.stages import locate
from test_locate_alg import locate_inputs

SURFACE_MM = 2000.0
OCCLUDER_MM = 1850.0
RADIUS_PX = 2.2
# Marker centres (u, v) px; the last is the one the tests hide.
CENTRES = np.array([[10.3, 20.4], [25.6, 19.7], [40.2, 20.2], [55.7, 20.6], [72.4, 20.3]])


def params(**kw):
    return locate.PARAMS.resolve(kw)


def disc(shape: tuple[int, int], centre: np.ndarray) -> np.ndarray:
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    return np.hypot(cc - centre[0], rr - centre[1]) <= RADIUS_PX


def scene(
    occluder_from: int | None = 73,
    shape: tuple[int, int] = (40, 90),
    peers: int = 4,
    wall_mm: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Depth (H, W) of a flat body at SURFACE_MM with marker holes, a nearer occluder (an
    arm, OCCLUDER_MM) over columns >= ``occluder_from`` (None: no occluder), and the blobs
    Alg. 2 would give: centroids of the visible marker pixels (K, 2), areas (K,) and
    region radii (K,). ``peers``: how many unhidden markers share the frame. ``wall_mm``:
    the last marker's left side shows a wall that far away instead of the body (its own
    surface out of sight, as a far heel's behind the near leg can be)."""
    rng = np.random.default_rng(0)
    depth = SURFACE_MM + rng.normal(0.0, 1.5, shape)
    if wall_mm is not None:
        depth[:, 64:] = wall_mm + rng.normal(0.0, 1.5, (shape[0], shape[1] - 64))
    cols = np.arange(shape[1])[None, :].repeat(shape[0], axis=0)
    arm = np.zeros(shape, dtype=bool) if occluder_from is None else cols >= occluder_from
    depth[arm] = OCCLUDER_MM + rng.normal(0.0, 1.5, int(arm.sum()))
    centres = np.concatenate([CENTRES[:peers], CENTRES[-1:]])
    cen, area = [], []
    for c in centres:
        seen = disc(shape, c) & ~arm
        depth[seen] = 0  # the saturated marker: no depth
        rr, cc = np.nonzero(seen)
        cen.append([cc.mean(), rr.mean()])
        area.append(seen.sum())
    rr_px = np.full(len(centres), RADIUS_PX + 0.5)
    return depth.astype(np.uint16), np.array(cen), np.array(area, float), rr_px


def complete(depth, cen, area, rr, **kw):
    p = params(**kw)
    zs = locate.locate_depths(depth, cen, rr, p)
    return locate.complete_occluded(depth, cen, rr, area, zs[:, 0], p)


@pytest.mark.parametrize("fraction", [0.55, 0.65, 0.75, 0.85, 0.95, 1.0])
def test_cut_disc_shift_matches_a_finely_rasterised_disc(fraction: float) -> None:
    g = np.linspace(-1.0, 1.0, 1601)
    x, y = np.meshgrid(g, g)
    inside = x * x + y * y <= 1.0
    # the straight edge at x = h hides the part beyond it; find h for this fraction
    hs = np.linspace(-0.05, 1.0, 2101)
    frac = np.array([np.mean(x[inside] <= h) for h in hs[::50]])
    h = np.interp(fraction, frac, hs[::50])
    seen = inside & (x <= h)
    measured = -x[seen].mean()
    assert locate.cut_disc_shift(seen.sum() / inside.sum()) == pytest.approx(measured, abs=5e-3)


def test_cut_disc_shift_limits() -> None:
    assert locate.cut_disc_shift(1.0) == 0.0
    assert locate.cut_disc_shift(0.5) == pytest.approx(4.0 / (3.0 * math.pi))
    assert locate.cut_disc_shift(0.2) == locate.cut_disc_shift(0.5)  # clipped


@pytest.mark.parametrize(("occluder_from", "off_by"), [(73, 0.8), (74, 0.3)])
def test_partly_hidden_marker_is_completed_towards_the_occluder(
    occluder_from: int, off_by: float
) -> None:
    # The arm hides half (7 of 14 px) or a fifth (11 of 14 px) of the last marker.
    depth, cen, area, rr = scene(occluder_from)
    truth = CENTRES[-1]
    before = float(np.hypot(*(cen[-1] - truth)))
    assert before > off_by  # Alg. 2 alone: the visible part's centroid, away from the arm
    out, done = complete(depth, cen, area, rr)
    assert done.tolist() == [False] * 4 + [True]
    assert np.hypot(*(out[-1] - truth)) < 0.15
    assert out[-1, 0] > cen[-1, 0]  # towards the arm, on the right
    np.testing.assert_array_equal(out[:-1], cen[:-1])  # the whole ones stay


def test_a_wall_far_behind_stands_for_the_body_within_its_depth() -> None:
    # The second surface past the arm is a wall 1.5 m behind the body: at the wall's
    # depth the hidden marker would look whole (f = 1.5); the marker is on the body,
    # so the depth behind the arm counts as at most occlusion_peer_mm (500 mm) behind it.
    depth, cen, area, rr = scene(wall_mm=3500.0)
    truth = CENTRES[-1]
    out, done = complete(depth, cen, area, rr)
    assert done.tolist() == [False] * 4 + [True]
    assert out[-1, 0] > cen[-1, 0]
    assert np.hypot(*(out[-1] - truth)) < 0.6 * np.hypot(*(cen[-1] - truth))
    # Allowed the whole 1.5 m, it would not be completed.
    _, far = complete(depth, cen, area, rr, occlusion_peer_mm=2000.0)
    assert not far[-1]


def test_whole_marker_beside_a_nearer_surface_stays() -> None:
    # The arm starts just past the last marker's disc: two surfaces in its window, but
    # its whole area.
    depth, cen, area, rr = scene(occluder_from=75)
    assert area[-1] == area[0]
    out, done = complete(depth, cen, area, rr)
    assert not done.any()
    np.testing.assert_array_equal(out, cen)


def test_small_blob_with_one_surface_stays() -> None:
    # A blob smaller than its peers with nothing nearer beside it (a smaller marker, a
    # dim one) is not taken for a hidden one.
    depth, cen, area, rr = scene(occluder_from=None)
    area[-1] = 0.6 * area[0]
    out, done = complete(depth, cen, area, rr)
    assert not done.any()
    np.testing.assert_array_equal(out, cen)


def test_too_few_peers_at_that_depth_leave_the_blob_as_it_is() -> None:
    # Two unhidden markers and the hidden one: three blobs, under the four that set a
    # reliable expected size (reflectors on the wall behind would not count: too far).
    depth, cen, area, rr = scene(peers=2)
    _, done = complete(depth, cen, area, rr)
    assert not done.any()
    _, done4 = complete(depth, cen, area, rr, occlusion_min_peers=3)
    assert done4[-1]
    # Peers further than occlusion_peer_mm from the blob's surface do not count.
    _, done_near = complete(depth, cen, area, rr, occlusion_min_peers=3, occlusion_peer_mm=100)
    assert not done_near.any()


def test_switched_off_or_no_blobs() -> None:
    depth, cen, area, rr = scene()
    out, done = complete(depth, cen, area, rr, occlusion_fix=False)
    assert not done.any()
    np.testing.assert_array_equal(out, cen)
    empty, none = complete(depth, np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    assert empty.shape == (0, 2) and none.shape == (0,)


@pytest.mark.parametrize(
    ("occluder_from", "wall_mm"), [(None, None), (73, None), (74, None), (75, None), (73, 3500.0)]
)
def test_compiled_kernel_equals_the_reference(
    occluder_from: int | None, wall_mm: float | None
) -> None:
    depth, cen, area, rr = scene(occluder_from, wall_mm=wall_mm)
    a, da = complete(depth, cen, area, rr)
    b, db = complete(depth, cen, area, rr, jit=False)
    np.testing.assert_array_equal(da, db)
    np.testing.assert_allclose(a, b, atol=1e-9, rtol=0)


def test_step_publishes_the_completed_centroid_and_its_ray() -> None:
    depth, cen, area, rr = scene()
    cf, bl = locate_inputs(depth, cen, rr, area)
    st = locate.init(params(surface_offset=False))
    _, (out,) = locate.step(st, {"clean": cf, "blobs": bl})
    assert np.hypot(*(out.centroid[-1] - CENTRES[-1])) < 0.15
    expect = st.camera.backproject(out.centroid, out.depth[:, 0])
    np.testing.assert_allclose(out.position[:, 0], expect, atol=1e-6)
    _, (off,) = locate.step(
        locate.init(params(surface_offset=False, occlusion_fix=False)), {"clean": cf, "blobs": bl}
    )
    np.testing.assert_array_equal(off.centroid, cen)
