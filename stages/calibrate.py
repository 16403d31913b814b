"""Stage ``calibrate``: walking-scene calibration (Alg. 4) on the calibration recording.

The operator places C floor markers one at a time on an empty walkway. Per frame:

1. a frame-difference motion test (Alg. 4 lines 3-5);
2. on a motion-free frame, the difference against the background (the previous motion-free
   frame) finds a newly appeared bright blob (lines 6-8); Alg. 2 runs on it with
   e_d = min IR inside the blob, giving the c-th floor marker (p, q)_c and r_c;
3. once the C markers are down: w (line 9), their 3D points (line 10, a small Alg. 3 normal
   mode: nearest significant depth layer of the ring around the depth hole), the floor plane,
   the diagonal test (line 11) and the operator status (lines 12-14).

A ``CalibrationStatus`` goes out on every frame; the ``CalibrationRecord`` goes out once,
when the trial's last frame arrives (``header.last``) or at ``finish``.

Conventions: images are (row, col) arrays, pixels are (u, v) = (col, row); camera space is
X right, Y down, Z forward, mm; NaN = missing. The floor plane is (nx, ny, nz, d) with the
unit normal pointing up and n . p + d = height above the floor (mm).

Departures from the paper (see docs/readme/labelling.md):

- the walking line is derived from the marker quad (through its centre, along its long
  axis, length L = ``length_mm``, ends projected on the floor plane) instead of an operator
  guideline tool [A-4];
- the floor plane is fitted through the markers, then refined with the valid floor depth
  pixels inside the marker quad (a least-squares plane through thousands of pixels is far
  less noisy than one through four markers);
- a marker whose ring has no depth (the far floor at a grazing angle) is placed where its
  ray meets the floor seen from the quad down to the image's edge, when at least two
  markers have depth and agree with that floor (``_markers_on_walkway``); Alg. 4 would
  ask for the markers to be replaced;
- a new blob within the ring of a marker already found is that marker seen again, not the
  next one;
- the status tests (Move, Tilt, Pan) use the 3D floor frame with declared tolerances
  [A-4b]; the final record's status is ``Done`` whenever the calibration is geometrically
  usable (C markers, diagonals cross, plane fits), the residual camera pose is recorded in
  ``tilt_deg``, ``pan_deg`` and ``offset_mm``: a recording cannot move its camera, and the
  3D labelling does not need an exactly sagittal view;
- w (line 9) is the modal IR of the partly covered pixels on the edge of the marker's pixels
  brighter than ``bright_ratio`` times the background's p99, the level that makes a new
  marker pixel: dimmer pixels around a marker are stray light (lens glare) or the scene,
  and a w read there (640-896 against 8 832-16 000 on the simulator's ``glare`` set-up) let
  ``clean`` and detect's Alg. 1 anchor take the body for bright components.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from gaitflow.schemas import CalibrationRecord, CalibrationStatus, Message, RawFrame
from gaitflow.stages.base import StageSpec

from gaitflow.camera import Camera
from gaitflow.errors import InputError, ParameterError, StageError
from gaitflow.params import Param, ParamSet

NAME = "calibrate"

PARAMS = ParamSet(
    NAME,
    (
        Param("C", int, 4, "markers", "number of floor calibration markers (Table I)", 3, 16),
        Param("W", float, 50.0, "mm", "Alg. 3 Max-Min depth-layer width (Table I)", 1.0, 1000.0),
        Param("D0", float, 2.0, "px", "Alg. 3 ring margin around the blob (Table I)", 0.0, 20.0),
        Param(
            "marker_diameter_mm",
            float,
            25.0,
            "mm",
            "floor marker diameter (spheres; 0 = flat floor marks)",
            0.0,
            100.0,
        ),
        Param("length_mm", float, 4000.0, "mm", "walking line length L", 500.0, 20000.0),
        Param(
            "motion_frac",
            float,
            0.002,
            "fraction",
            "share of changed pixels above which a frame counts as moving",
            0.0,
            1.0,
        ),
        Param(
            "motion_sigma",
            float,
            6.0,
            "sigma",
            "a pixel changed when |frame difference| exceeds this many noise sigmas",
            1.0,
            100.0,
        ),
        Param(
            "bright_ratio",
            float,
            3.0,
            "ratio",
            "a new marker pixel is this many times brighter than the background p99",
            1.0,
            1000.0,
        ),
        Param("min_area", int, 3, "px", "smallest new blob accepted as a marker", 1, 1000),
        Param("max_area", int, 2500, "px", "largest new blob accepted as a marker", 4, 100000),
        Param("hist_bin", float, 256.0, "IR", "edge-pixel IR histogram bin for w", 1.0, 65535.0),
        Param("move_tol_mm", float, 200.0, "mm", "Move: lateral offset of quad centre", 0.0),
        Param("tilt_tol_deg", float, 5.0, "deg", "Tilt: optical axis vs floor plane", 0.0, 90.0),
        Param("pan_tol_deg", float, 5.0, "deg", "Pan: walking line vs image X axis", 0.0, 90.0),
        Param(
            "plane_tol_mm",
            float,
            25.0,
            "mm",
            "a marker further than this from the fitted floor plane means Replace Markers",
            0.0,
        ),
        Param(
            "camera",
            dict,
            {},
            "",
            "depth intrinsics (camera.json document or its depth_intrinsics); {} = Kinect v2",
        ),
    ),
)


def camera_from_param(value: Mapping[str, Any], stage: str = NAME) -> Camera:
    """The :class:`Camera` a ``camera`` parameter describes.

    Accepts {} (Kinect v2 defaults), a whole camera.json document, or a flat mapping of
    Camera fields (fx, fy, cx, cy, k1, ..., width, height).
    """
    if not value:
        return Camera()
    if "depth_intrinsics" in value:
        return Camera.from_json(value, source=f"stage {stage!r} parameter camera")
    fields = set(Camera.__dataclass_fields__)
    unknown = sorted(set(value) - fields)
    if unknown:
        raise ParameterError(stage, "camera", dict(value), f"unknown key {unknown[0]!r}")
    return Camera(**dict(value))


@dataclass(frozen=True)
class FloorMarker:
    """One calibration marker found by Alg. 4 lines 7-8."""

    u: float
    v: float
    r_m: float
    r_r: float
    w_edge: float


@dataclass(frozen=True)
class CalibrateState:
    """Explicit state of the calibrate stage (one calibration trial per camera)."""

    params: dict[str, Any]
    camera: Camera
    # The camera.json document in use: the ``camera`` parameter's when it is a whole
    # document, else the one the raw frames carry (adopted when the parameter is empty).
    camera_doc: dict[str, Any] = field(default_factory=dict)
    prev_ir: np.ndarray | None = None
    background_ir: np.ndarray | None = None
    background_depth: np.ndarray | None = None
    markers: tuple[FloorMarker, ...] = ()
    # Pixels bright in any earlier motion-free frame: a stray reflector hidden by the
    # operator in one background frame must not come back as a "new" marker.
    seen_bright: np.ndarray | None = None
    published: bool = False
    last_header: Any = None
    moving_frames: int = 0
    rejected_blobs: int = 0


def init(params: dict[str, Any]) -> CalibrateState:
    """Initial state; ``params`` are resolved by :data:`PARAMS`."""
    cam = params["camera"]
    doc = dict(cam) if "depth_intrinsics" in cam else {}
    return CalibrateState(params=dict(params), camera=camera_from_param(cam), camera_doc=doc)


def adopt_camera(state: CalibrateState, doc: Mapping[str, Any]) -> CalibrateState:
    """The state measuring with the camera.json document ``doc`` that came with the frames.

    Only when the ``camera`` parameter is empty (an explicit camera wins), and only once
    per document. As ``gaitflow analyze`` does with a session's camera.json, the document
    sets the intrinsics, C (``calibration_markers``) and the marker diameter. A document
    that does not parse is a StageError naming the bad key.
    """
    if state.params["camera"] or not doc or doc == state.camera_doc:
        return state
    try:
        cam = Camera.from_json(doc, source="the raw frame's camera document")
    except InputError as exc:
        raise StageError(NAME, str(exc)) from exc
    p = dict(state.params)
    if "calibration_markers" in doc:
        p["C"] = doc["calibration_markers"]
    if "marker_diameter_mm" in doc:
        p["marker_diameter_mm"] = doc["marker_diameter_mm"]
    # ParameterError naming the value when the document's are out of range
    return replace(state, params=PARAMS.resolve(p), camera=cam, camera_doc=dict(doc))


# --- Alg. 2 and a small Alg. 3 (normal mode) -------------------------------------------


def blob_stats(ir: np.ndarray, mask: np.ndarray, e_d: float) -> tuple[float, float, float, float]:
    """Alg. 2 on one component: intensity-weighted centroid and radii.

    Parameters
    ----------
    ir : (H, W) float IR image.
    mask : (H, W) bool, the pixels of the component.
    e_d : the threshold; weights are (P - e_d) / v with v = sum(P - e_d) [A-2a].

    Returns
    -------
    (u, v, r_m, r_r) : centroid px, weighted mean radius r_m and extent r_r = max l [A-2b].
    """
    rows, cols = np.nonzero(mask)
    vals = ir[rows, cols].astype(np.float64) - e_d
    total = vals.sum()
    if total <= 0:
        # Flat blob (every pixel at the threshold): uniform weights.
        vals = np.ones_like(vals)
        total = vals.sum()
    om = vals / total
    u = float((om * cols).sum())
    v = float((om * rows).sum())
    dist = np.hypot(cols - u, rows - v)
    return u, v, float((om * dist).sum()), float(dist.max())


def ring_depth(
    depth: np.ndarray, u: float, v: float, r_r: float, W: float = 50.0, D0: float = 2.0
) -> float:
    """Alg. 3 normal mode, reduced: depth (mm) of the nearest significant layer around a hole.

    Takes valid depths in the square [u +- (r_r + D0 + 1)] x [v +- ...], splits them into
    W-wide layers from near to far, drops layers of <= 2 px (flying pixels), and returns the
    median of the nearest remaining layer. NaN when nothing valid remains.
    """
    sel = _ring(depth, u, v, r_r, D0)
    vals = np.sort(sel[2])
    i = 0
    while i < vals.size:
        j = int(np.searchsorted(vals, vals[i] + W, side="left"))
        if j - i > 2:
            return float(np.median(vals[i:j]))
        i = j
    return float("nan")


def _ring(
    depth: np.ndarray, u: float, v: float, r_r: float, D0: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cols, rows, depths) of the valid pixels in the Alg. 3 window around (u, v)."""
    h, w = depth.shape
    rad = int(np.ceil(r_r + D0 + 1))
    r0, r1 = max(0, round(v) - rad), min(h, round(v) + rad + 1)
    c0, c1 = max(0, round(u) - rad), min(w, round(u) + rad + 1)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    vals = depth[r0:r1, c0:c1].astype(np.float64)
    ok = vals > 0
    return cols[ok].astype(np.float64), rows[ok].astype(np.float64), vals[ok]


def floor_point(
    depth: np.ndarray,
    camera: Camera,
    u: float,
    v: float,
    r_r: float,
    W: float = 50.0,
    D0: float = 2.0,
    radius: float = 0.0,
) -> np.ndarray:
    """Camera-space floor point (3,) mm under a floor marker at pixel (u, v).

    A floor seen at a grazing angle changes depth by ~20 mm per pixel row, so the nearest
    layer of the ring (Alg. 3 normal mode) is biased toward the camera. The ring pixels of
    that layer's neighbourhood (within W of its median) are mapped to 3D, a local plane is
    fitted through them, and the marker's ray is intersected with it. Falls back to the
    Alg. 3 depth when the ring is too small for a plane. NaN when no depth is available.
    A spherical marker of ``radius`` mm has its centre (the blob centroid's ray) that far
    above the floor: the ray is cut with the plane lifted by ``radius`` and the point is
    dropped back onto the floor, giving the foot point under the marker.
    """
    z0 = ring_depth(depth, u, v, r_r, W, D0)
    if not np.isfinite(z0):
        return np.full(3, np.nan)
    cols, rows, vals = _ring(depth, u, v, r_r + 2.0, D0)
    if vals.size >= 8:
        # Trimmed: flying pixels and objects standing in the ring are dropped.
        plane = robust_plane(camera.backproject(np.stack([cols, rows], axis=1), vals), 8)
        if plane is not None:
            point, t = marker_on_plane(camera, u, v, plane, radius)
            if vals.min() - W <= t <= vals.max() + W:
                return point
    return camera.backproject(np.array([[u, v]]), np.array([z0]))[0]


def robust_plane(points: np.ndarray, min_points: int, passes: int = 3) -> np.ndarray | None:
    """A plane through (N, 3) points, refitted ``passes`` times without the outliers.

    A point is an outlier beyond 3 robust sigmas of the residuals (at least 5 mm). None when
    fewer than ``min_points`` points are left.
    """
    keep = np.ones(len(points), bool)
    plane = None
    for _ in range(passes):
        if keep.sum() < min_points:
            return None
        plane = fit_plane(points[keep])
        res = np.abs(points @ plane[:3] + plane[3])
        keep = res < max(3.0 * 1.4826 * float(np.median(res[keep])), 5.0)
    return plane if keep.sum() >= min_points else None


def marker_on_plane(
    camera: Camera, u: float, v: float, plane: np.ndarray, radius: float
) -> tuple[np.ndarray, float]:
    """(foot point (3,), depth along the ray) of a marker of ``radius`` resting on ``plane``.

    The centroid's ray is cut with the plane lifted by the radius (the sphere's centre) and
    the point is dropped back onto the plane. NaN where the ray runs parallel to it.
    """
    xy = camera.undistort(np.array([[u, v]], dtype=np.float64))[0]
    ray = np.array([xy[0], xy[1], 1.0])
    denom = float(plane[:3] @ ray)
    if abs(denom) <= 1e-6:
        return np.full(3, np.nan), float("nan")
    t = -(plane[3] - radius) / denom
    return ray * t - radius * plane[:3], t


def fit_plane(points: np.ndarray) -> np.ndarray:
    """Least-squares plane (nx, ny, nz, d) through (N, 3) points, normal toward the camera.

    The camera looks down on the floor from above, so the origin has positive height:
    the sign is chosen so that d > 0 (the normal points up, away from the floor).
    """
    pts = points[np.isfinite(points).all(axis=1)]
    c = pts.mean(axis=0)
    q = pts - c
    _, vecs = np.linalg.eigh(q.T @ q)
    n = vecs[:, 0]  # eigenvector of the smallest eigenvalue
    d = -float(n @ c)
    if d < 0:
        n, d = -n, -d
    return np.array([*n, d])


def _segments_cross(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> bool:
    """True when the 2D segments p1-p2 and q1-q2 properly intersect."""

    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    return (orient(p1, p2, q1) * orient(p1, p2, q2) < 0) and (
        orient(q1, q2, p1) * orient(q1, q2, p2) < 0
    )


def cyclic_order(pixels: np.ndarray) -> np.ndarray:
    """Indices ordering (C, 2) image points by angle around their mean (Alg. 4 line 11)."""
    c = pixels.mean(axis=0)
    return np.argsort(np.arctan2(pixels[:, 1] - c[1], pixels[:, 0] - c[0]))


def diagonals_cross(pixels: np.ndarray) -> bool:
    """Alg. 4 line 11: with the markers in cyclic order, do diagonals 1-3 and 2-4 cross?

    Only meaningful for C = 4; for other C the polygon must be convex, which is tested the
    same way on every pair of 'opposite' diagonals.
    """
    p = pixels[cyclic_order(pixels)]
    n = len(p)
    if n < 4:
        return n == 3 and abs(_cross2(p[1] - p[0], p[2] - p[0])) > 1.0
    half = n // 2
    return all(
        _segments_cross(p[i], p[(i + half) % n], p[(i + 1) % n], p[(i + 1 + half) % n])
        for i in range(n)
    )


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def floor_frame(plane: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Rotation rows (e1, e2, e3) of the floor frame.

    e1 = walking axis (start -> end, toward +u), e3 = floor normal (up), e2 = e3 x e1
    (away from the camera). Floor coordinates of p: R @ (p - start).
    """
    n = plane[:3] / np.linalg.norm(plane[:3])
    e1 = end - start
    e1 = e1 - (e1 @ n) * n
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return np.stack([e1, e2, n])


# --- the stage core ---------------------------------------------------------------------


def _noise_sigma(diff: np.ndarray) -> float:
    # Robust: the median absolute difference ignores the few pixels that really changed;
    # a quarter of the pixels estimate it well enough at a quarter of the cost.
    return 1.4826 * float(np.median(np.abs(diff[::2, ::2]))) + 1.0


def _is_moving(ir: np.ndarray, prev: np.ndarray, p: dict[str, Any]) -> bool:
    diff = ir - prev
    sig = _noise_sigma(diff)
    changed = np.count_nonzero(np.abs(diff) > p["motion_sigma"] * sig)
    return changed > p["motion_frac"] * ir.size


def _bright_level(bg: np.ndarray, p: dict[str, Any]) -> float:
    # p99 of a subsample: the scene level, unaffected by the few marker or stray pixels.
    level = max(float(np.percentile(bg[::4, ::4], 99)), 1.0)
    return min(p["bright_ratio"] * level, 0.5 * 65535.0)


def _new_blobs(
    ir: np.ndarray, bg: np.ndarray, seen: np.ndarray | None, p: dict[str, Any]
) -> tuple[list[tuple[float, float, float, float, float]], int]:
    """Alg. 4 lines 6-8: new bright blobs against the background, each through Alg. 2.

    ``seen`` masks pixels that were bright in an earlier motion-free frame (strays).
    Returns ([(u, v, r_m, r_r, w_edge)], number of rejected components).
    """
    t_bright = _bright_level(bg, p)
    mask = (ir > t_bright) & (ir - bg > 0.5 * t_bright)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    found = []
    rejected = 0
    for k in range(1, n):
        area = int(stats[k, cv2.CC_STAT_AREA])
        if not p["min_area"] <= area <= p["max_area"]:
            rejected += 1
            continue
        comp = lab == k
        if seen is not None and np.count_nonzero(seen & comp) > 0.5 * area:
            rejected += 1
            continue
        # Alg. 4 line 7: e_d = the minimum IR inside the blob. The blob (and its partial
        # edge pixels) is the component of IR >= e_d around the seed, grown by 1 px.
        x0, y0 = stats[k, cv2.CC_STAT_LEFT], stats[k, cv2.CC_STAT_TOP]
        x1, y1 = x0 + stats[k, cv2.CC_STAT_WIDTH], y0 + stats[k, cv2.CC_STAT_HEIGHT]
        r0, r1 = max(0, y0 - 2), min(ir.shape[0], y1 + 2)
        c0, c1 = max(0, x0 - 2), min(ir.shape[1], x1 + 2)
        sub = ir[r0:r1, c0:c1]
        seed = comp[r0:r1, c0:c1]
        grown = cv2.dilate(seed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        # Partial-pixel edges: grown pixels clearly above the background belong to the blob.
        sub_bg = bg[r0:r1, c0:c1]
        blob = grown & ((sub - sub_bg) > 0.1 * t_bright)
        e_d = float(sub[blob].min())
        u, v, r_m, r_r = blob_stats(sub, blob, e_d)
        # w is read on the edge of the blob's pixels brighter than a new marker pixel must
        # be (t_bright): under lens glare the ring around a marker holds its stray light, a
        # few hundred counts, and w read there fell to the level of the scene itself (clean
        # then took the whole body for bright components).
        bright = (blob & (sub > t_bright)).astype(np.uint8)
        edge = (bright > 0) & ~cv2.erode(bright, np.ones((3, 3), np.uint8)).astype(bool)
        # Saturated edge pixels say nothing about where the marker fades into the floor;
        # the partly covered ones do.
        partial = edge & (sub < 0.98 * float(sub[blob].max()))
        vals = sub[partial] if partial.any() else sub[edge]
        found.append((u + c0, v + r0, r_m, r_r, _modal(vals, p["hist_bin"])))
    return found, rejected


def _modal(values: np.ndarray, bin_width: float) -> float:
    """Centre of the most populated histogram bin of ``values`` (Alg. 4 line 9)."""
    if values.size == 0:
        return float("nan")
    idx = np.floor(values / bin_width).astype(np.int64)
    uniq, counts = np.unique(idx, return_counts=True)
    return float((uniq[np.argmax(counts)] + 0.5) * bin_width)


@dataclass(frozen=True)
class Solution:
    """The geometric result of Alg. 4 lines 9-17 for the markers found so far."""

    status: str
    message: str
    pixels: np.ndarray
    points: np.ndarray
    plane: np.ndarray
    start: np.ndarray
    end: np.ndarray
    w: float
    r_b: float
    tilt_deg: float
    pan_deg: float
    offset_mm: float
    plane_rms_mm: float


def solve(
    markers: tuple[FloorMarker, ...],
    depth: np.ndarray | None,
    camera: Camera,
    p: dict[str, Any],
) -> Solution:
    """Alg. 4 lines 9-17 on the markers found so far.

    Parameters
    ----------
    markers : the floor markers, in order of placement.
    depth : (H, W) uint16 depth of the latest motion-free frame (the background).
    camera : intrinsics used to map pixels to camera space.
    p : resolved parameters.

    Returns
    -------
    Solution : status one of Uninitialized (fewer than C markers), Replace Markers (a
        marker without depth, diagonals not crossing, or a marker off the fitted plane),
        Move Left/Right, Tilt Down/Up, Pan Left/Right, Done.
    """
    C = p["C"]
    nan3 = np.full(3, np.nan)
    pixels = np.array([[m.u, m.v] for m in markers], dtype=np.float64).reshape(-1, 2)
    w = float(min((m.w_edge for m in markers), default=np.nan))
    r_b = float(np.mean([m.r_m for m in markers])) if markers else float("nan")
    empty = Solution(
        "Uninitialized",
        f"place floor marker {len(markers) + 1} of {C}",
        pixels,
        np.full((len(markers), 3), np.nan),
        np.full(4, np.nan),
        nan3,
        nan3,
        w,
        r_b,
        np.nan,
        np.nan,
        np.nan,
        np.nan,
    )
    if len(markers) < C or depth is None:
        return empty
    points = np.array(
        [
            floor_point(
                depth, camera, m.u, m.v, m.r_r, p["W"], p["D0"], 0.5 * p["marker_diameter_mm"]
            )
            for m in markers
        ]
    )
    sol = replace(empty, points=points)
    if not diagonals_cross(pixels):
        return replace(
            sol,
            status="Replace Markers",
            message="the marker quad is not convex: its diagonals do not cross",
        )
    order = cyclic_order(pixels)
    missing = [i + 1 for i in range(len(points)) if not np.isfinite(points[i]).all()]
    if missing:
        found = _markers_on_walkway(points, pixels, pixels[order], depth, camera, p)
        if found is None:
            return replace(
                sol, status="Replace Markers", message=f"no floor depth at marker(s) {missing}"
            )
        filled, floor = found
        sol = _pose(replace(sol, points=filled), floor, p)
        note = f"; marker(s) {missing} placed on the floor seen nearer (no depth there)"
        return replace(sol, message=sol.message + note)
    return _pose(sol, _quad_points(depth, camera, pixels[order]), p)


def _markers_on_walkway(
    points: np.ndarray,
    pixels: np.ndarray,
    quad: np.ndarray,
    depth: np.ndarray,
    camera: Camera,
    p: dict[str, Any],
) -> tuple[np.ndarray, np.ndarray] | None:
    """Floor points (C, 3) with the markers that have no floor depth placed on the floor.

    ``points`` (C, 3) mm and ``pixels`` (C, 2) px are in placement order, ``quad`` (C, 2)
    px in cyclic order.

    A camera low and far from the walkway sees the far floor at a grazing angle, where a
    time-of-flight sensor returns no depth: the far markers' rings are empty. The floor is
    then the plane through the valid depth pixels of the empty floor from the quad down to
    the image's bottom edge (the quad's columns), kept only when at least two markers have
    depth and lie within ``plane_tol_mm`` of it; each marker without depth is placed where
    its ray meets it (:func:`marker_on_plane`). Returns (points, the strip's floor pixels
    (N, 3) mm, through which the plane is refined), or None when that cannot be done.

    The quad alone is not enough there: it spans a few hundred mm of depth, all of it near
    the grazing limit, whose last valid pixels lie about 10 mm below the floor, and a plane
    through it tilted by 1.4 deg (the simulator's ``low+far``; the strip down to the image's
    edge, 1 to 3.5 m away: 0.001 deg).
    """
    have = np.isfinite(points).all(axis=1)
    if have.sum() < 2:
        return None
    below = np.stack([quad[:, 0], np.full(len(quad), depth.shape[0] - 1.0)], axis=1)
    strip = cv2.convexHull(np.concatenate([quad, below]).astype(np.float32))[:, 0]
    floor = _quad_points(depth, camera, strip)
    plane = robust_plane(floor, 500)
    if plane is None or np.max(np.abs(points[have] @ plane[:3] + plane[3])) > p["plane_tol_mm"]:
        return None
    out = points.copy()
    for i in np.flatnonzero(~have):
        out[i], t = marker_on_plane(camera, *pixels[i], plane, 0.5 * p["marker_diameter_mm"])
        if not t > 0:
            return None
    return out, floor


def _pose(sol: Solution, floor: np.ndarray, p: dict[str, Any]) -> Solution:
    """Alg. 4 lines 11-17 on a convex quad whose markers all have floor points.

    The floor plane is refined through ``floor`` (N, 3) mm, valid floor pixels in camera
    space (:func:`_quad_points`).
    """
    points = sol.points
    plane = _refine_plane(fit_plane(points), floor)
    resid = points @ plane[:3] + plane[3]
    if np.max(np.abs(resid)) > p["plane_tol_mm"]:
        return replace(
            sol,
            plane=plane,
            status="Replace Markers",
            message=f"marker {int(np.argmax(np.abs(resid))) + 1} is "
            f"{np.max(np.abs(resid)):.0f} mm off the floor plane",
        )
    n = plane[:3]
    centre = points.mean(axis=0)
    centre = centre - (n @ centre + plane[3]) * n
    # The walking line follows the quad's long axis in the floor plane.
    flat = points - np.outer(points @ n + plane[3], n)
    _, _, vt = np.linalg.svd(flat - flat.mean(axis=0), full_matrices=False)
    axis = vt[0] - (vt[0] @ n) * n
    axis = axis / np.linalg.norm(axis)
    if axis[0] < 0:
        axis = -axis
    half = 0.5 * p["length_mm"] * axis
    start, end = centre - half, centre + half
    # Tilt: elevation of the optical axis above the floor plane (+ = looking up).
    tilt = float(np.degrees(np.arcsin(np.clip(n[2], -1, 1))))
    # Pan: how far the walking line recedes toward +X (+ = its +u end is farther).
    pan = float(np.degrees(np.arctan2(axis[2], axis[0])))
    offset = float(centre @ axis)  # lateral offset of the quad centre from the optical axis
    sol = replace(
        sol,
        plane=plane,
        start=start,
        end=end,
        tilt_deg=tilt,
        pan_deg=pan,
        offset_mm=offset,
        plane_rms_mm=float(np.sqrt(np.mean(resid**2))),
    )
    if abs(offset) > p["move_tol_mm"]:
        side = "Right" if offset > 0 else "Left"
        return replace(
            sol,
            status=f"Move {side}",
            message=f"quad centre is {offset:+.0f} mm off the optical axis; move the camera "
            f"{side.lower()}",
        )
    if abs(tilt) > p["tilt_tol_deg"]:
        # Optical axis above the horizontal (tilt > 0): tilt the camera down.
        way = "Down" if tilt > 0 else "Up"
        return replace(
            sol,
            status=f"Tilt {way}",
            message=f"optical axis is {tilt:+.1f} deg from the floor; tilt {way.lower()}",
        )
    if abs(pan) > p["pan_tol_deg"]:
        # The +u end is farther: turn the camera toward -u (left) to face the line squarely.
        way = "Left" if pan > 0 else "Right"
        return replace(
            sol,
            status=f"Pan {way}",
            message=f"walking line is {pan:+.1f} deg off square; pan {way.lower()}",
        )
    return replace(sol, status="Done", message="calibration done")


def _refine_plane(plane: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Refit the plane through floor pixels ``pts`` (N, 3) mm (those of the marker quad).

    Pixels more than 30 mm from the marker plane (objects, flying pixels) are left out.
    """
    if len(pts) < 50:
        return plane
    near = np.abs(pts @ plane[:3] + plane[3]) < 30.0
    if near.sum() < 50:
        return plane
    return fit_plane(pts[near])


def _quad_points(depth: np.ndarray, camera: Camera, quad: np.ndarray) -> np.ndarray:
    """Camera points (N, 3) of the valid depth pixels inside a convex polygon (cyclic).

    At most about 5000, evenly subsampled.
    """
    h, w = depth.shape
    poly = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(poly, np.round(quad).astype(np.int32), 1)
    rows, cols = np.nonzero((poly > 0) & (depth > 0))
    step = max(1, rows.size // 5000)
    rows, cols = rows[::step], cols[::step]
    return camera.backproject(np.stack([cols, rows], axis=1).astype(np.float64), depth[rows, cols])


def _status_msg(hdr: Any, sol: Solution, n_found: int) -> CalibrationStatus:
    return CalibrationStatus.follow(
        hdr,
        floor_pixels=sol.pixels.reshape(-1, 2),
        status=sol.status,
        markers_found=n_found,
        message=sol.message,
    )


def _record(state: CalibrateState, hdr: Any) -> CalibrationRecord:
    p = state.params
    sol = solve(state.markers, state.background_depth, state.camera, p)
    status = sol.status
    if status.startswith(("Move", "Tilt", "Pan")):
        # Usable geometry; the residual pose is recorded in tilt/pan/offset.
        status = "Done"
    elif status == "Uninitialized":
        status = "Replace Markers"
    cam = state.camera
    return CalibrationRecord.follow(
        hdr,
        floor_pixels=sol.pixels.reshape(-1, 2),
        floor_points=sol.points.reshape(-1, 3),
        floor_plane=sol.plane,
        start=sol.start,
        end=sol.end,
        status=status,
        markers_found=len(state.markers),
        w=sol.w,
        r_b=sol.r_b,
        length_mm=float(np.linalg.norm(sol.end - sol.start)),
        # the document's other keys (marker_diameter_mm, fps) go on to model, locate, label
        camera={**{k: v for k, v in state.camera_doc.items() if k != "subject"}, **cam.to_json()},
        tilt_deg=sol.tilt_deg,
        pan_deg=sol.pan_deg,
        offset_mm=sol.offset_mm,
        plane_rms_mm=sol.plane_rms_mm,
        message=sol.message,
    )


def step(
    state: CalibrateState, inputs: Mapping[str, Message]
) -> tuple[CalibrateState, list[Message]]:
    """One calibration frame: motion test, new-marker search, status; record on last frame.

    Parameters
    ----------
    state : the calibrate state.
    inputs : ``{"raw": RawFrame}`` of the calibration trial.

    Returns
    -------
    (state, [CalibrationStatus] or [CalibrationStatus, CalibrationRecord])
    """
    raw = inputs["raw"]
    if not isinstance(raw, RawFrame):
        raise StageError(NAME, f"input 'raw' is a {type(raw).__name__}, not a RawFrame")
    state = adopt_camera(state, raw.camera)
    p = state.params
    hdr = raw.header
    ir = raw.ir.astype(np.float32)
    moving = state.prev_ir is not None and _is_moving(ir, state.prev_ir, p)
    st = replace(state, prev_ir=ir, last_header=hdr)
    if moving:
        st = replace(st, moving_frames=st.moving_frames + 1)
    elif st.background_ir is None:
        bright = ir > _bright_level(ir, p)
        st = replace(st, background_ir=ir, background_depth=np.array(raw.depth), seen_bright=bright)
    else:
        markers = st.markers
        rejected = st.rejected_blobs
        seen = st.seen_bright
        if len(markers) < p["C"]:
            found, rej = _new_blobs(ir, st.background_ir, seen, p)
            rejected += rej
            for u, v, r_m, r_r, w_edge in sorted(found):
                # A blob on a marker already found is that marker, more of it showing (an
                # operator who stood still beside it, hiding part of it, has walked away):
                # floor markers lie far apart, never within each other's ring.
                if any(np.hypot(u - m.u, v - m.v) < m.r_r + r_r + p["D0"] for m in markers):
                    rejected += 1
                elif len(markers) < p["C"]:
                    markers = (*markers, FloorMarker(u, v, r_m, r_r, w_edge))
        bright = ir > _bright_level(ir, p)
        if seen is not None:
            # Markers just found are not strays: only pixels away from them join the mask.
            for m in markers[len(st.markers) :]:
                r = int(np.ceil(m.r_r + 2))
                bright[
                    max(0, int(m.v) - r) : int(m.v) + r + 2, max(0, int(m.u) - r) : int(m.u) + r + 2
                ] = False
            bright |= seen
        # Alg. 4 line 6: the background is the previous motion-free frame.
        st = replace(
            st,
            seen_bright=bright,
            background_ir=ir,
            background_depth=np.array(raw.depth),
            markers=markers,
            rejected_blobs=rejected,
        )
    sol = solve(st.markers, st.background_depth, st.camera, p)
    out: list[Message] = [_status_msg(hdr, sol, len(st.markers))]
    if hdr.last and not st.published:
        out.append(_record(st, hdr))
        st = replace(st, published=True)
    return st, out


def finish(state: CalibrateState) -> tuple[CalibrateState, list[Message]]:
    """Publish the record if the trial ended without a ``last`` frame."""
    if state.published or state.last_header is None:
        return state, []
    return replace(state, published=True), [_record(state, state.last_header)]


SPEC = StageSpec(
    name=NAME,
    params=PARAMS,
    init=init,
    step=step,
    finish=finish,
    stateful=True,
    doc=__doc__ or "",
)
