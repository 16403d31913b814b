"""The compiled (numba) kernels of detect and locate against their numpy references.

Blobs, thresholds and Alg. 3 depths must be bit-identical; the published positions and
depths to 1e-9 mm (their |ray| is summed in a fixed order, numpy's einsum in one that
depends on its SIMD build; on the development machine they are identical too).
"""

from __future__ import annotations

import importlib
import sys

import cv2
import numpy as np
import pytest
from gaitflow.schemas import Blobs, Markers3D
from gaitflow.stages import clean, detect, locate

from gaitflow.bench import mocap
from gaitflow.camera import Camera
from gaitflow.errors import ConfigError, StageError

H, W = 212, 256
BLOB_FIELDS = ("centroid", "marker_radius", "region_radius", "mean_ir", "area")


def disc_frame(seed: int, n: int = 14) -> np.ndarray:
    """A noisy IR frame with ``n`` blurred, partly saturated discs, some touching."""
    rng = np.random.default_rng(seed)
    ir = rng.normal(1200.0, 60.0, (H, W))
    rr, cc = np.mgrid[0:H, 0:W]
    for _ in range(n):
        u, v = rng.uniform(5, W - 5), rng.uniform(5, H - 5)
        rad = rng.uniform(1.0, 6.0)
        peak = rng.uniform(15000.0, 90000.0)
        ir += peak * np.clip(rad + 0.5 - np.hypot(cc - u, rr - v), 0.0, 1.0)
    ir[rng.integers(0, H), :] = 30000.0  # a line: one wide, thin component
    return np.clip(ir, 0, 65535).astype(np.uint16)


def depth_frame(seed: int) -> np.ndarray:
    """Depth with a tilted body plane, a nearer arm, a far wall, holes and flying pixels."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0:H, 0:W]
    z = 2500.0 + 0.8 * (cc - W / 2) + rng.normal(0.0, 4.0, (H, W))
    z[:, : W // 4] = 4200.0 + rng.normal(0.0, 6.0, (H, W // 4))  # wall
    z[60:90, 60:200] -= 120.0  # an arm in front of the body
    fly = rng.random((H, W)) < 0.03
    z[fly] = rng.uniform(300.0, 6000.0, fly.sum())
    z[rng.random((H, W)) < 0.05] = 0.0  # invalid pixels
    for _ in range(12):  # marker holes
        u, v, rad = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(1.0, 4.0)
        z[np.hypot(cc - u, rr - v) <= rad] = 0.0
    return np.clip(z, 0, 9000).astype(np.uint16)


def assert_components_equal(a: detect.Components, b: detect.Components) -> None:
    for f in (*BLOB_FIELDS, "ids", "labels"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and np.array_equal(x, y), f
    assert a.threshold == b.threshold and a.rejected == b.rejected
    assert (a.box is None) == (b.box is None)
    if a.box is not None:
        assert np.array_equal(a.box, b.box)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_block_max_and_roi_equal_the_reference(seed: int) -> None:
    ir = disc_frame(seed)[:203, :250]  # not a multiple of the block size
    for block in (8, 5):
        assert np.array_equal(detect.block_max(ir, block), detect.block_max(ir, block, False))
    for level in (1500.0, 20000.0, 60000.0):
        for width in (128, 24):  # narrow shelves: many shelves and merges
            a = detect.compact_roi(ir, level, 8, mosaic_width=width)
            b = detect.compact_roi(ir, level, 8, mosaic_width=width, jit=False)
            for f in ("image", "tile", "du", "dv", "flat_ir", "flat_u", "flat_v"):
                x, y = getattr(a, f), getattr(b, f)
                assert x.dtype == y.dtype and np.array_equal(x, y), (level, width, f)


@pytest.mark.parametrize("seed", [0, 3])
def test_components_equal_the_reference(seed: int) -> None:
    ir = disc_frame(seed, n=20)
    roi = detect.compact_roi(ir, 1500.0)
    seen = 0
    for e in (1500.0, 2500.0, 18000.0, 40000.5, 65534.0):
        for conn, min_area, radius, extent in ((8, 3, np.inf, False), (4, 1, 6.0, True)):
            a = detect.components(roi, e, min_area, conn, radius, extent=extent)
            b = detect.components(roi, e, min_area, conn, radius, extent=extent, jit=False)
            assert_components_equal(a, b)
            seen += a.count + a.rejected
    assert seen > 50  # the cases hold blobs and rejections, not just empty frames


@pytest.mark.parametrize("conn", [8, 4])
def test_labels_and_counts_equal_opencv_on_noise(conn: int) -> None:
    # Dense noise: branching, ring-shaped and diagonally touching components, so the
    # kernel's labelling must number them in OpenCV's order, not just find them.
    rng = np.random.default_rng(conn)
    for h, w in ((1, 40), (37, 53), (64, 64)):
        img = (rng.random((h, w)) * 65535).astype(np.uint16)
        roi = detect.Roi(img, np.zeros((h, w), np.int32), np.zeros(1, np.intp),
                         np.zeros(1, np.intp), 0.0)  # fmt: skip
        for e in (20000.0, 40000.0, 60000.0):
            for radius in (np.inf, 2.0):
                a = detect.components(roi, e, 1, conn, radius, extent=True)
                b = detect.components(roi, e, 1, conn, radius, extent=True, jit=False)
                assert_components_equal(a, b)
                for min_area in (1, 3):
                    ca = detect.count_components(roi, e, min_area, conn, radius)
                    cb = detect.count_components(roi, e, min_area, conn, radius, jit=False)
                    assert ca == cb
        with pytest.raises(StageError, match="connectivity 6"):
            detect.components(roi, 20000.0, 1, 6)
        n, *_ = cv2.connectedComponentsWithStats(
            (img > 40000.0).view(np.uint8), connectivity=conn, ltype=cv2.CV_32S
        )
        assert n > (2 if h == 1 else 20)  # many components in these cases


def test_detect_frame_equals_the_reference_with_every_option() -> None:
    ir = disc_frame(4, n=16)
    hist = (detect.HistoryEntry(30000.0, 50000.0, 4.0), detect.HistoryEntry(20000.0, 45000.0, 3.0))
    for over in ({}, {"refine": True, "split_cores": True, "split_merged": True}, {"n": 30}):
        pj = detect.PARAMS.resolve({"n": 12, **over})
        pr = detect.PARAMS.resolve({"n": 12, **over, "jit": False})
        a = detect.detect_frame(ir, 20000.0, 2.5, hist, pj)
        b = detect.detect_frame(ir, 20000.0, 2.5, hist, pr)
        assert a.threshold == b.threshold and a.iterations == b.iterations
        assert np.array_equal(a.centroid, b.centroid)
        assert_components_equal(a.blobs, b.blobs)


def _blob_set(seed: int, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    cen = np.stack([rng.uniform(-4, W + 4, n), rng.uniform(-4, H + 4, n)], axis=1)
    rr = rng.uniform(0.5, 12.0, n)
    cen[3] = np.nan  # not a blob position
    rr[5] = np.inf
    cen[7] = [W - 0.5, H - 0.5]  # window cut by the image corner
    cen[8] = [-30.0, 50.0]  # window outside the image
    return cen, rr


# With the surface fit (locate's default) the kernel sums the fit's normal equations in
# another order than numpy's batched product: equal to rounding, 1e-6 mm against depths
# quantised to 1 mm (the plane-only fit of a steep window is the worst conditioned, about
# 2e-7 mm apart). Without the fit the kernel is bit-identical.
FIT_TOL_MM = 1e-6


@pytest.mark.parametrize(
    ("over", "least"),
    [
        ({}, 100),
        ({"surface_fit": False}, 100),
        ({"fit_curvature": False, "fit_max_px": 16, "fit_min_px": 12}, 100),
        # Single flying pixels now form the nearest slab, whose layer R6 rejects.
        ({"min_slab": 1, "bottom_reach": 400.0}, 15),
        ({"W": 37.5, "D0": 1.0, "D1": 0.25, "D2": 0.3}, 100),  # 150 depth bins: pairwise split
        ({"max_depth": 3000.0, "min_slab": 6}, 80),
    ],
)
def test_locate_depths_equal_the_reference(over: dict, least: int) -> None:
    pj = locate.PARAMS.resolve(over)
    pr = locate.PARAMS.resolve({**over, "jit": False})
    found = 0
    for seed in range(3):
        depth = depth_frame(seed)
        cen, rr = _blob_set(seed)
        a = locate.locate_depths(depth, cen, rr, pj)
        b = locate.locate_depths(depth, cen, rr, pr)
        if pj["surface_fit"]:
            assert np.array_equal(np.isnan(a), np.isnan(b)), seed
            assert np.nanmax(np.abs(a - b), initial=0.0) <= FIT_TOL_MM, seed
        else:
            assert np.array_equal(a, b, equal_nan=True), (seed, np.nanmax(np.abs(a - b)))
        found += int(np.isfinite(a[:, 0]).sum())
        assert np.isnan(a[[3, 5]]).all()
    assert found >= least  # blobs with a normal-mode depth
    # No blobs, and all-invalid depth.
    assert locate.locate_depths(depth_frame(0), np.zeros((0, 2)), np.zeros(0), pj).shape == (0, 3)
    z0 = locate.locate_depths(np.zeros((H, W), np.uint16), cen, rr, pj)
    assert np.isnan(z0).all()


def test_locate_all_positions_match_the_reference() -> None:
    cam = Camera()
    depth = depth_frame(5)
    cen, rr = _blob_set(5)
    for over in ({}, {"surface_offset": False}, {"marker_diameter_mm": 14.0}):
        pj = locate.PARAMS.resolve(over)
        pr = locate.PARAMS.resolve({**over, "jit": False})
        za, pa = locate.locate_all(depth, cen, rr, cam, pj)
        zb, pb = locate.locate_all(depth, cen, rr, cam, pr)
        assert np.array_equal(np.isnan(pa), np.isnan(pb))
        tol = FIT_TOL_MM if pj["surface_fit"] else 1e-9
        assert np.nanmax(np.abs(pa - pb)) <= tol and np.nanmax(np.abs(za - zb)) <= tol
        assert np.isfinite(pa).sum() > 60


def _run(frames: list, jit: bool) -> list[tuple[Blobs, Markers3D]]:
    sc = clean.SPEC.init(clean.SPEC.params.resolve({}))
    sd = detect.SPEC.init(detect.SPEC.params.resolve({"jit": jit}))
    sl = locate.SPEC.init(locate.SPEC.params.resolve({"jit": jit}))
    out = []
    for raw, _truth, _mid, cal in frames:
        sc, (cf,) = clean.SPEC.step(sc, {"raw": raw, "calibration": cal})
        sd, (bl,) = detect.SPEC.step(sd, {"clean": cf, "calibration": cal})
        sl, (mk,) = locate.SPEC.step(sl, {"clean": cf, "blobs": bl})
        out.append((bl, mk))
    return out


def test_stages_on_a_simulated_walk_equal_the_reference() -> None:
    from gaitflow.sim import SimConfig, list_trials, simulate_session

    cfg = SimConfig.quick()
    ses = simulate_session(list_trials()[0], 0, cfg)
    rec = ses.recordings["walk-01"]
    cal = mocap.session_record(ses.camera_json)
    # Frames 18-47: the subject walks into view, so Alg. 1 iterates and blobs vary.
    frames = [(*rec.frame(i), None, cal) for i in range(18, 48)]
    cv2.setNumThreads(1)
    fast, ref = _run(frames, True), _run(frames, False)
    blobs = 0
    for (ba, ma), (bb, mb) in zip(fast, ref, strict=True):
        for f in (*BLOB_FIELDS, "threshold", "iterations", "status", "rejected"):
            x, y = np.asarray(getattr(ba, f)), np.asarray(getattr(bb, f))
            assert x.dtype == y.dtype and np.array_equal(x, y), (ba.header.frame, f)
        assert np.array_equal(np.isnan(ma.position), np.isnan(mb.position))
        if ma.position.size:
            assert np.nanmax(np.abs(ma.position - mb.position), initial=0.0) <= FIT_TOL_MM
            assert np.nanmax(np.abs(ma.depth - mb.depth), initial=0.0) <= FIT_TOL_MM
        blobs += len(ba.centroid)
    assert blobs > 150


def test_missing_numba_is_a_config_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba -> ImportError
    monkeypatch.delitem(sys.modules, "gaitflow.stages.alg_kernels", raising=False)
    with pytest.raises(ConfigError, match="numba"):
        importlib.import_module("gaitflow.stages.alg_kernels")
