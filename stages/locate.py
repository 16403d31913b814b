"""Stage ``locate``: 3D marker location from the depth ring around each marker (Alg. 3).

Inputs: ``clean`` and ``blobs``, joined per frame. Output: ``markers`` (:class:`Markers3D`),
the blobs in the same order with their depth and camera-space position under each of the
three cluster modes (axis 1 in ``gaitflow.markers.CLUSTER_MODES`` order: normal, top,
bottom). The mode depends on the marker's label, which the label stage assigns after this
one; publishing all three keeps the graph acyclic and label picks the one it needs.

Array conventions: depth images are (row, col), Z in mm, 0 = invalid; pixels (u, v) =
(column, row); camera space X right, Y down, Z forward, mm; NaN = depth not recovered.

Alg. 3 follows the Rec. reading R1-R9 of ``../shared/reference/algorithms.md`` section 3.3,
with these departures, each for the stated reason:

- **Bottom mode reach.** R4 takes the farthest slab. Beside a pelvis or thigh marker seen
  side-on, the window also holds the background (wall, floor) metres behind the body, and
  the farthest slab is then the background, not the body behind the swinging arm. Bottom
  mode therefore takes the farthest significant slab that starts within ``bottom_reach``
  (150 mm: an arm's thickness plus its gap to the trunk) behind the nearest one.
- **Top mode** is the normal mode (Rec. [A-3b]). The optional refinement ``top_half``
  (use only the window rows at and above the centroid, the half away from the floor or the
  arm) was measured worse on the simulator (``gaitflow bench mocap``: median 3D error of
  shoulder and toe markers rose from about 40 and 28 mm to about 110 and 190 mm, because
  the upper half of those windows is mostly background), so it is off by default.
- **Surface fit** (``surface_fit``, on by default). R8 averages
  the ring, which is not the surface under the marker: on a convex limb seen face-on the
  ring lies a few mm deeper than the skin under the marker (the skin curves away), and on a
  surface sloping away towards a silhouette (shoulder, toe, heel) the layer holds only the
  body side, tens of mm nearer. After R2-R4 choose the layer, a least-squares surface ``z =
  a + b du + c dv + k (du^2 + dv^2)`` (a tilted plane plus an isotropic curvature,
  ``fit_curvature``) is fitted to the layer's pixels against their offset (du, dv) from the
  centroid, and its value at the centroid, ``a``, is the depth. R5-R8 remain the fallback
  where the layer has fewer than ``fit_min_px`` pixels or the fitted depth lies more than
  ``fit_max_step`` outside the layer; ``fit_max_se`` (standard error of ``a``) and
  ``fit_prior_mm`` (shrink ``a`` towards the layer mean by its standard error) can make the
  extrapolation more cautious, ``fit_robust`` adds Huber IRLS passes. A wide blob's fit uses
  an even subsample of about ``fit_max_px`` pixels. On the simulator the median 3D error
  fell from 30.5 to 7.85 mm (docs/readme/mocap.md, "3D location"). It was off at first
  because heel and toe depth then jump between frames and the gait events got worse; with
  the gait stage's depth smoothing (``depth_smooth_s`` 0.3 s) and label's leg-layer choice
  it now gives the best gait figures end to end (``gaitflow bench gait``: knee RMSE 3.27 ->
  1.46 deg mean, stride error 1.56 -> 0.90 %), so it is the default.
- **Marker centre.** The ring is the surface the marker sits on; the sphere's centre is one
  radius plus the base height (``marker_base_mm``, 2 mm: the base and tape between the
  skin and the sphere) in front of it, towards the camera (the markers face the camera in
  a side view). The point is moved towards the camera along its viewing ray by that much
  (the diameter from the ``marker_diameter_mm`` parameter, else the session camera.json's,
  else 25 mm) so that the published position is the marker centre, which is what the
  subject model and the gait kinematics assume. ``surface_offset`` = false keeps the
  surface point.
- **Partly hidden markers** (``occlusion_fix``, on by default; :func:`complete_occluded`,
  between R8 and R9). Alg. 2's centroid of a marker that a nearer surface partly hides (a
  far heel or toe behind the near leg, a pelvis marker behind the arm) is the centroid of
  its visible part, up to about half a radius off the centre, away from the occluder. Where
  the window holds a nearer surface beside the blob and the blob is smaller than an
  unhidden marker at the depth behind that surface (at most ``occlusion_peer_mm`` behind
  it; the size of the markers within that depth of the blob's, scaled by 1 / Z^2), the
  centroid is moved towards the occluder by the centroid shift of a disc cut by a
  straight edge with that visible fraction. The published ``centroid`` and the ray of
  R9 are the completed ones. On the simulator (``gaitflow bench mocap --all --frames 0``)
  recall at 0.5 px rose from 91.52 to 93.03 % (the paper's twelve markers 93.26 to
  94.25 %); docs/readme/mocap.md, "Partly hidden markers".
- **D2 in px** ([A-3e]): the distance to (p, q) is measured in the image.
- **Too few pixels** (R1): the margin is widened once by D0; if still fewer than 3 valid
  pixels the depth is NaN (a gap that post-processing fills).

Speed: with ``top_half`` off (the default) all blobs of a frame go through Alg. 3 in one
pass (:func:`_ragged`): their windows' valid pixels are gathered into one flat array and
sorted once by (blob, depth); R2-R4's greedy slab walk is a few pointer jumps per blob on
Python lists (a numpy pass per slab cost more in call overhead), and R5-R8 run for all
blobs and modes at once on contiguous slices of the sorted array. The surface fit of all
jobs is one batched matrix product over their padded pixel runs and one batched 4x4 solve
(:func:`_weighted_lsq`), and R5-R8's histograms run only for the jobs the fit cannot
serve. Results equal the per-blob :func:`locate_depth` (tested); the padded-window path
(:func:`_batch`) remains for ``top_half``.

Compiled kernel (``jit``, on by default): with ``top_half`` off and the surface fit plain
(no ``fit_robust``, ``fit_prior_mm`` or ``fit_max_se``, the defaults), Alg. 3
for all blobs is one numba kernel (``alg_kernels.locate_depths``): per blob it gathers the
window, sorts its depths by counting sort (they are integer mm), walks the slabs and fills
R5-R8's histograms in plain loops, and R9's scaling is a second kernel
(``alg_kernels.marker_points``). Without the surface fit the Alg. 3 depths are
bit-identical to :func:`_ragged` (the R8 mean is summed in numpy's pairwise order) and the
published positions equal the numpy path to 1e-9 mm; with it (the kernel's
``_surface_fit`` sums each job's normal equations pixel by pixel, numpy in one batched
product) they are equal to 1e-6 mm. The completion of partly hidden markers is a third
kernel (``alg_kernels.complete_occluded``, centroids equal to 1e-9 px): in numpy its
per-blob windows cost about 0.2 ms a frame, in the kernel 0.02 ms. ``jit`` = false runs the
numpy path, kept as the reference.

The camera intrinsics come from, in order: the ``camera`` parameter (a camera.json
document, for an explicit override), the ``camera`` field of the clean frame (copied by the
clean stage from the calibration record, i.e. the session's camera.json), or the default
``gaitflow.camera.Camera()``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from gaitflow.schemas import Blobs, CleanFrame, Markers3D
from gaitflow.stages.base import Inputs, StageSpec
from gaitflow.stages.warmup import stage_warmup

from gaitflow.camera import DEFAULT_MARKER_DIAMETER_MM, Camera, marker_diameter
from gaitflow.errors import InputError, StageError
from gaitflow.markers import CLUSTER_MODES
from gaitflow.params import Param, ParamSet

MODE_INDEX = {m: i for i, m in enumerate(CLUSTER_MODES)}

PARAMS = ParamSet(
    "locate",
    (
        Param("W", float, 50.0, "mm", "Alg. 3: Max-Min width of a depth layer (Table I)", low=1.0),
        Param("D0", float, 2.0, "px", "Alg. 3: window margin and pixel count (Table I)", low=0.0),
        Param("D1", float, 5.0, "mm", "Alg. 3: depth histogram bin (Table I)", low=0.1),
        Param("D2", float, 0.5, "px", "Alg. 3: distance histogram bin ([A-3e])", low=0.01),
        Param("min_slab", int, 3, "px", "R3: slabs with fewer pixels are flying pixels", low=1),
        Param(
            "bottom_reach",
            float,
            150.0,
            "mm",
            "bottom mode: farthest slab starting within this of the nearest (departure)",
            low=0.0,
        ),
        Param(
            "top_half",
            bool,
            False,
            "-",
            "top mode uses only the window rows at and above the centroid ([A-3b])",
        ),
        Param("max_depth", float, 8000.0, "mm", "depths above this are invalid", low=1.0),
        Param(
            "surface_offset",
            bool,
            True,
            "-",
            "move the ring surface point back to the marker centre (departure)",
        ),
        Param(
            "marker_diameter_mm",
            float,
            0.0,
            "mm",
            "marker sphere diameter (the surface-to-centre offset is half of it); 0 = the "
            "session camera.json's marker_diameter_mm, else 25 mm",
            low=0.0,
            high=100.0,
        ),
        Param(
            "marker_base_mm",
            float,
            2.0,
            "mm",
            "height of the marker's base and tape between the skin and the sphere (departure)",
            low=0.0,
            high=20.0,
        ),
        Param(
            "surface_fit",
            bool,
            True,
            "-",
            "extrapolate the layer's surface (plane + curvature fit) to the centroid (departure)",
        ),
        Param(
            "fit_curvature",
            bool,
            True,
            "-",
            "the surface fit has an isotropic curvature term (else a tilted plane)",
        ),
        Param("fit_min_px", int, 6, "px", "fewer layer pixels than this: R8 depth, no fit", low=4),
        Param(
            "fit_max_px",
            int,
            128,
            "px",
            "about this many layer pixels per blob at most enter the fit (an even subsample)",
            low=8,
        ),
        Param(
            "fit_max_se",
            float,
            1e9,
            "mm",
            "the fit serves a blob only if the standard error of its depth is at most this",
            low=0.0,
        ),
        Param(
            "fit_prior_mm",
            float,
            0.0,
            "mm",
            "shrink the fitted depth towards the layer mean by tau^2/(tau^2+se^2); 0 = off",
            low=0.0,
        ),
        Param(
            "fit_robust",
            int,
            0,
            "-",
            "IRLS passes of the surface fit (Huber weights at 2 RMS); 0 = plain least squares",
            low=0,
            high=10,
        ),
        Param(
            "fit_max_step",
            float,
            50.0,
            "mm",
            "a fitted depth further than this outside its layer is rejected (R5-R8 used)",
            low=0.0,
        ),
        Param(
            "occlusion_fix",
            bool,
            True,
            "-",
            "complete a marker partly hidden by a nearer surface as a cut disc (departure)",
        ),
        Param(
            "occlusion_gap",
            float,
            20.0,
            "mm",
            "a depth step this deep or deeper between two surfaces of a window separates them",
            low=1.0,
        ),
        Param(
            "occlusion_fraction",
            float,
            0.9,
            "-",
            "a blob beside a nearer surface is completed when it shows less than this "
            "fraction of an unhidden marker's area at the depth behind that surface",
            low=0.5,
            high=1.0,
        ),
        Param(
            "occlusion_peer_mm",
            float,
            500.0,
            "mm",
            "the subject's body depth: blobs whose surface lies within it of a blob's set "
            "the marker size expected there; the surface behind an occluder counts as at "
            "most this far behind it",
            low=0.0,
        ),
        Param(
            "occlusion_min_peers",
            int,
            4,
            "-",
            "a blob with fewer such blobs (itself included) is never completed",
            low=3,
        ),
        Param(
            "jit",
            bool,
            True,
            "-",
            "Alg. 3 and R9 as compiled (numba) kernels (without top_half and the fit's "
            "cautious options); the same outputs, false = the numpy reference",
        ),
        Param(
            "camera",
            dict,
            {},
            "-",
            "intrinsics override: a camera.json document or flat Camera fields; {} = none",
        ),
    ),
)


def _slabs(v: np.ndarray, W: float) -> list[tuple[int, int]]:
    """R2: split sorted depths into W-wide slabs, near to far. Returns (start, stop) index
    pairs into ``v``; each slab is [s, s + W) from the smallest unassigned value s."""
    out: list[tuple[int, int]] = []
    i, n = 0, v.size
    while i < n:
        j = int(np.searchsorted(v, v[i] + W, side="left"))
        j = max(j, i + 1)
        out.append((i, j))
        i = j
    return out


def _layer_depth(
    depth: np.ndarray,
    off: np.ndarray,
    T0: float,
    T1: float,
    r: float,
    d: float,
    nv: int,
    p: Mapping,
) -> float:
    """The layer's depth from the pixels of one window in [T0, T1] (T1 = T0 + W): the
    surface fit (:func:`_surface_fit`), else R5-R8's population-weighted modal-ring depth.
    ``off`` (M,) complex: each pixel's offset from the centroid, du + i dv px."""
    D0, D1, D2 = p["D0"], p["D1"], p["D2"]
    sel = (depth >= T0) & (depth <= T1)
    z, w = depth[sel], off[sel]
    if z.size == 0:
        return float("nan")
    if p["surface_fit"]:
        zf, okf = _surface_fit(np.zeros(z.size, np.intp), w, z, np.array([T0]), p)
        if okf[0]:
            return float(zf[0])
    dd = np.abs(w)
    nb = max(math.ceil((T1 - T0) / D1), 1)
    zb = np.minimum(((z - T0) / D1).astype(np.intp), nb - 1)
    counts = np.bincount(zb, minlength=nb)
    B = int(np.count_nonzero(counts))
    # R6 [A-3c]: |H0| is the number of non-empty bins here; the bound is in effect "fewer
    # than D0 pixels" but is kept in the paper's form.
    bound = min((r + D0) ** 2, d * d / B + D0, D0, nv / B)
    keep = counts >= bound
    keep &= counts > 0
    if not keep.any():
        return float("nan")
    # R7: distance histogram per depth bin; mu(h) = mean depth of its modal distance bin.
    ndist = int(dd.max() / D2) + 1
    db = (dd / D2).astype(np.intp)
    key = zb * ndist + db
    cnt2 = np.bincount(key, minlength=nb * ndist).reshape(nb, ndist)
    sum2 = np.bincount(key, z, minlength=nb * ndist).reshape(nb, ndist)
    mode = np.argmax(cnt2, axis=1)
    rows = np.flatnonzero(keep)
    mu = sum2[rows, mode[rows]] / cnt2[rows, mode[rows]]
    # R8: population-weighted mean over the kept bins ([A-3c]: |H0| = pixel total).
    wts = counts[rows].astype(np.float64)
    return float(np.sum(mu * wts) / np.sum(wts))


def locate_depth(
    depth: np.ndarray,
    centroid: tuple[float, float],
    region_radius: float,
    params: Mapping[str, Any],
) -> tuple[float, float, float]:
    """Alg. 3 (Rec. R1-R8): the marker's surface depth under the three cluster modes.

    Parameters
    ----------
    depth : (H, W) uint16 depth image D_d, mm, 0 = invalid.
    centroid : (p, q) = (u, v) px, from Alg. 2.
    region_radius : r_r px, from Alg. 2.
    params : resolved :data:`PARAMS`.

    Returns
    -------
    (z_normal, z_top, z_bottom) in mm; NaN where no layer is found.
    """
    p = params
    H, Wd = depth.shape
    pu, pq = float(centroid[0]), float(centroid[1])
    if not (np.isfinite(pu) and np.isfinite(pq) and np.isfinite(region_radius)):
        return (math.nan,) * 3
    r = float(region_radius)
    margin = p["D0"]
    for _attempt in range(2):  # R1: widen once by D0 if too few valid pixels
        half = math.ceil(r + margin)
        cu, cq = round(pu), round(pq)
        c0, c1 = max(cu - half, 0), min(cu + half + 1, Wd)
        r0, r1 = max(cq - half, 0), min(cq + half + 1, H)
        if c0 >= c1 or r0 >= r1:  # window outside the image: widen like an empty one
            margin += p["D0"]
            continue
        win = depth[r0:r1, c0:c1]
        ok = (win > 0) & (win <= p["max_depth"])
        if np.count_nonzero(ok) >= 3:
            break
        margin += p["D0"]
    else:
        return (math.nan,) * 3
    rr, cc = np.nonzero(ok)
    z = win[rr, cc].astype(np.float64)
    off = (cc + c0 - pu) + 1j * (rr + r0 - pq)
    upper = rr + r0 <= pq
    d = 2.0 * (r + p["D0"]) + 1.0
    out = []
    for mode in CLUSTER_MODES:
        zz, dd = z, off
        if mode == "top" and p["top_half"] and np.count_nonzero(upper) >= 3:
            zz, dd = z[upper], off[upper]
        order = np.argsort(zz, kind="stable")
        zs = zz[order]
        slabs = [s for s in _slabs(zs, p["W"]) if s[1] - s[0] >= p["min_slab"]]  # R2-R3
        if not slabs:
            out.append(math.nan)
            continue
        if mode == "bottom":
            near = zs[slabs[0][0]]
            reach = [s for s in slabs if zs[s[0]] <= near + p["bottom_reach"]]
            T1 = float(zs[reach[-1][1] - 1])
            T0 = T1 - p["W"]
        else:
            T0 = float(zs[slabs[0][0]])
            T1 = T0 + p["W"]
        out.append(_layer_depth(zz, dd, T0, T1, r, d, zz.size, p))
    return out[0], out[1], out[2]


def _layer_bounds(
    zs: np.ndarray, n: np.ndarray, W: float, min_slab: int, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """R2-R4 for many rows at once, on sorted, inf-padded rows ``zs`` (N, M) holding ``n``
    valid values each.

    One ``searchsorted`` over the flattened rows (offset so that they stay sorted) gives,
    for every value, where the W-slab starting at it ends; the greedy slab walk of each row
    is then a few pointer jumps, done on Python lists because a row has only a handful of
    slabs (a numpy pass per slab cost more in call overhead than the whole walk).

    Returns
    -------
    (near, far): the start of the first slab of >= ``min_slab`` px (T0 of the normal and top
    modes), and the last value of the farthest such slab starting within ``reach`` of it
    (T1 of the bottom mode); NaN where a row has no significant slab.
    """
    N, M = zs.shape
    if N == 0 or M == 0:
        return np.full(N, np.nan), np.full(N, np.nan)
    fin = np.isfinite(zs)
    big = float(np.max(zs, where=fin, initial=0.0)) + 2.0 * W + 1.0
    off = np.arange(N) * (2.0 * big)
    flat = (np.where(fin, zs, big - W * 0.5) + off[:, None]).ravel()
    return _walk(flat, np.arange(N) * M, np.asarray(n), off, W, min_slab, reach)


def _layers_batch(
    z: np.ndarray, off: np.ndarray, T0: np.ndarray, r: np.ndarray, nv: np.ndarray, p: Mapping
) -> np.ndarray:
    """R5-R8 for J jobs at once. z (J, M) with NaN/inf where not a pixel, off (J, M) complex
    offsets du + i dv px from the centroid; T0 (J,)
    (NaN = no layer), r (J,) region radii, nv (J,) valid pixel counts. Returns (J,) mm."""
    W = p["W"]
    J = z.shape[0]
    out = np.full(J, np.nan)
    ok = np.isfinite(T0)
    if not ok.any():
        return out
    T0f = np.where(ok, T0, 0.0)
    sel = ok[:, None] & (z >= T0f[:, None]) & (z <= (T0f + W)[:, None])
    jj, mm = np.nonzero(sel)
    if jj.size == 0:
        return out
    return _layers_core(jj, z[jj, mm], off[jj, mm], T0f, r, nv, p, out)


def _layers_core(
    jj: np.ndarray,
    zz: np.ndarray,
    off: np.ndarray,
    T0f: np.ndarray,
    r: np.ndarray,
    nv: np.ndarray,
    p: Mapping,
    out: np.ndarray,
) -> np.ndarray:
    """R5-R8 on the selected pixels of J jobs: ``jj`` (P,) job of each pixel (a non-empty
    selection), ``zz`` (P,) its depth, all in [T0f, T0f + W] of its job, ``off`` (P,)
    complex, its offset du + i dv px from the centroid. Fills ``out`` (J,) mm where a layer
    survives (:func:`_surface_fit`, else R8); returns it."""
    D0, D1, D2, W = p["D0"], p["D1"], p["D2"], p["W"]
    J = out.shape[0]
    if p["surface_fit"]:
        zf, okf = _surface_fit(jj, off, zz, T0f, p)
        out[okf] = zf[okf]
        rest = ~okf[jj]  # R5-R8 only for the jobs the fit could not serve
        if not rest.any():
            return out
        jj, zz, off = jj[rest], zz[rest], off[rest]
    dd = np.abs(off)
    nb = max(math.ceil(W / D1), 1)
    zb = np.minimum(((zz - T0f[jj]) / D1).astype(np.intp), nb - 1)
    counts = np.bincount(jj * nb + zb, minlength=J * nb).reshape(J, nb)
    B = np.maximum(np.count_nonzero(counts, axis=1), 1)
    d = 2.0 * (r + D0) + 1.0
    bound = np.minimum.reduce([(r + D0) ** 2, d * d / B + D0, np.full(J, D0), nv / B])
    keep = (counts >= bound[:, None]) & (counts > 0)
    ndist = int(dd.max() / D2) + 1
    db = (dd / D2).astype(np.intp)
    key = (jj * nb + zb) * ndist + db
    cnt2 = np.bincount(key, minlength=J * nb * ndist).reshape(J * nb, ndist)
    sum2 = np.bincount(key, zz, minlength=J * nb * ndist).reshape(J * nb, ndist)
    mode = np.argmax(cnt2, axis=1)
    flat = np.arange(J * nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu = (sum2[flat, mode] / cnt2[flat, mode]).reshape(J, nb)
    wts = np.where(keep, counts, 0).astype(np.float64)
    tot = wts.sum(axis=1)
    num = np.where(keep, mu, 0.0) * wts
    good = tot > 0
    out[good] = num.sum(axis=1)[good] / tot[good]
    return out


def _surface_fit(
    jj: np.ndarray, off: np.ndarray, zz: np.ndarray, T0: np.ndarray, p: Mapping
) -> tuple[np.ndarray, np.ndarray]:
    """Depth of each layer's surface extrapolated to the centroid (departure, module doc).

    Least squares over a job's layer pixels of ``z = a + b du + c dv + k (du^2 + dv^2)``: a
    tilted plane plus an isotropic curvature, the skin around the marker (a convex limb or
    trunk seen near-frontally), or the body surface sloping away towards a silhouette. The
    result is ``a``, the surface depth at the centroid. IRLS passes (``fit_robust``) with
    Huber weights at twice the job's RMS residual take the pull of flying pixels and of a
    second surface inside the layer away. A job is not served (``ok`` false; R5-R8 then
    apply) with fewer than ``fit_min_px`` pixels, when ``a`` lies more than
    ``fit_max_step`` outside its layer [T0, T0 + W] (a fit extrapolated beyond its data), or
    when its standard error exceeds ``fit_max_se``; ``fit_prior_mm`` > 0 shrinks ``a``
    towards the layer mean by ``tau^2 / (tau^2 + se^2)``.

    Parameters
    ----------
    jj : (P,) job of each pixel, sorted; off : (P,) complex du + i dv px; zz : (P,) depth
        mm, within its job's layer.
    T0 : (J,) start of each job's layer, mm.

    Returns
    -------
    (J,) depth mm and (J,) bool ok.
    """
    J = T0.size
    half_w = 0.5 * p["W"]
    x, y = off.real, off.imag
    # At most about fit_max_px pixels per job, on every s-th diagonal of the pixel grid
    # (floor of the offsets: the grid's own lattice, whatever the pixel order): a wide
    # non-marker blob (a lamp, a merged pair) must not cost more than a marker.
    nf = np.bincount(jj, minlength=J)
    if nf.max() > p["fit_max_px"]:
        stride = -(-nf // p["fit_max_px"])
        take = (np.floor(x) + np.floor(y)) % stride[jj] == 0
        jj, zz, x, y = jj[take], zz[take], x[take], y[take]
        nf = np.bincount(jj, minlength=J)
    # Depths relative to the layer's middle keep the normal equations well scaled.
    mid = T0 + half_w
    zr = zz - mid[jj]
    start = np.cumsum(nf) - nf
    rows = [np.ones_like(x), x, y] + ([x * x + y * y] if p["fit_curvature"] else []) + [zr]
    B = np.stack(rows)  # (K + 1, P): the design columns and the depths
    tau, max_se = p["fit_prior_mm"], p["fit_max_se"]
    want_se = tau > 0 or max_se < 1e9
    coef, se, mean = _weighted_lsq(start, nf, B, None, want_se)
    if p["fit_robust"]:
        jf = np.repeat(np.arange(J), nf)
    for _ in range(p["fit_robust"]):
        # Huber weights at 2 RMS of the job's residuals (+1 mm, the depth's quantisation).
        res = zr - np.einsum("kp,pk->p", B[:-1], coef[jf])
        rms = np.sqrt(np.bincount(jf, res * res, J) / np.maximum(nf, 1))
        wgt = 1.0 / np.maximum(1.0, np.abs(res) / (2.0 * rms[jf] + 1.0))
        coef, se, mean = _weighted_lsq(start, nf, B, wgt, want_se)
    a = coef[:, 0]
    if tau > 0:
        # Shrink an uncertain extrapolation smoothly towards the layer's mean depth.
        a = mean + (a - mean) * (tau * tau / (tau * tau + se * se))
    ok = (nf >= p["fit_min_px"]) & (np.abs(a) <= half_w + p["fit_max_step"])
    if max_se < 1e9:
        ok &= se <= max_se
    return np.where(ok, mid + a, np.nan), ok


def _weighted_lsq(
    start: np.ndarray,
    n: np.ndarray,
    B: np.ndarray,
    wgt: np.ndarray | None,
    want_se: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Per-job weighted least squares ``A.T c = z`` with ``B = [A; z]`` (K + 1, P) and
    weights wgt (P,) or None; the pixels of job j are the run of ``n[j]`` (possibly none)
    from ``start[j]``.

    Returns (J, K) coefficients, (J,) standard error of the first one (the intercept: the
    depth at the centroid) from the residual variance and (M^-1)_00 (None unless
    ``want_se``), and (J,) weighted mean of z (NaN for a job without pixels). A job with
    fewer than K pixels gets meaningless coefficients (the caller ignores them).
    """
    K = B.shape[0] - 1
    P = B.shape[1]
    # B W B^T of all jobs as one batched matrix product over their pixel runs, padded to
    # the longest with a zero column: the normal matrix, A^T W z and z^T W z.
    lane = np.arange(max(int(n.max()), 1))
    idx = np.where(lane < n[:, None], start[:, None] + lane, P)  # (J, L)
    Bz = np.concatenate([B, np.zeros((K + 1, 1))], axis=1)
    G = Bz[:, idx].transpose(1, 0, 2)  # (J, K + 1, L)
    Gw = G if wgt is None else G * np.append(wgt, 0.0)[idx][:, None, :]
    S = Gw @ G.transpose(0, 2, 1)  # (J, K + 1, K + 1)
    M = S[:, :K, :K]  # a view: S is not used as a whole again
    rhs = S[:, :K, K]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = rhs[:, 0] / M[:, 0, 0]  # the layer's (weighted) mean depth
    # A small ridge keeps degenerate layouts (all pixels on a line, too few pixels)
    # solvable; their wild extrapolations are caught by fit_max_step.
    M += np.eye(K) * (1e-9 * np.trace(M, axis1=1, axis2=2) + 1e-6)[:, None, None]
    if not want_se:
        return np.linalg.solve(M, rhs[:, :, None])[:, :, 0], None, mean
    J = M.shape[0]
    r2 = np.zeros((J, K, 2))
    r2[:, :, 0] = rhs
    r2[:, 0, 1] = 1.0
    sol = np.linalg.solve(M, r2)
    coef = sol[:, :, 0]
    # RSS = z^T W z - c . A^T W z; dof from the pixel count (weights are <= 1).
    rss = np.maximum(S[:, K, K] - np.einsum("jk,jk->j", coef, rhs), 0.0)
    se = np.sqrt(rss / np.maximum(n - K, 1) * np.maximum(sol[:, 0, 1], 0.0))
    return coef, se, mean


def locate_depths(
    depth: np.ndarray,
    centroid: np.ndarray,
    region_radius: np.ndarray,
    params: Mapping[str, Any],
) -> np.ndarray:
    """Alg. 3 (Rec. R1-R8) for every blob at once: surface depth under the three modes.

    Vectorised over blobs (one flat pass, or padded windows per size class with
    ``top_half``), with the same result as calling :func:`locate_depth` per blob. With
    ``jit`` (no ``top_half``, the surface fit plain or off, integer depth: :func:`_jit`) the
    flat pass is the compiled kernel ``alg_kernels.locate_depths``, equal to
    :func:`_ragged` (module docstring).

    Parameters
    ----------
    depth : (H, W) uint16 depth, mm, 0 = invalid.
    centroid : (N, 2) (u, v) px.
    region_radius : (N,) r_r px.

    Returns
    -------
    (N, 3) Z mm under normal, top and bottom; NaN where no layer is found.
    """
    p = params
    if _jit(p, depth):
        from gaitflow.stages import alg_kernels

        return alg_kernels.locate_depths(
            np.ascontiguousarray(depth),
            np.ascontiguousarray(centroid, dtype=np.float64).reshape(-1, 2),
            np.ascontiguousarray(region_radius, dtype=np.float64).reshape(-1),
            float(p["W"]),
            float(p["D0"]),
            float(p["D1"]),
            float(p["D2"]),
            float(p["max_depth"]),
            int(p["min_slab"]),
            float(p["bottom_reach"]),
            bool(p["surface_fit"]),
            int(p["fit_min_px"]),
            int(p["fit_max_px"]),
            float(p["fit_max_step"]),
            bool(p["fit_curvature"]),
        )
    N = centroid.shape[0]
    out = np.full((N, 3), np.nan)
    ok = np.isfinite(centroid).all(axis=1) & np.isfinite(region_radius)
    if not ok.any():
        return out
    if not p["top_half"]:
        idx = np.flatnonzero(ok)
        out[idx] = _widened(_ragged, depth, centroid[idx], region_radius[idx], p)
        return out
    # top_half: padded windows (its own pixel subset per blob).
    # Windows are padded to the largest of a batch, so blobs go in batches of similar size:
    # one wide blob (a lamp, a merged pair) must not make every window wide.
    half = np.ceil(region_radius + p["D0"])
    # Classes: half-size <= 8 px (every marker up close), <= 16, <= 32, ...
    size_class = np.where(ok, np.ceil(np.log2(np.maximum(np.nan_to_num(half) / 8.0, 1.0))), -1)
    for cls in np.unique(size_class[ok]):
        idx = np.flatnonzero(ok & (size_class == cls))
        out[idx] = _widened(_batch, depth, centroid[idx], region_radius[idx], p)
    return out


def _jit(p: Mapping[str, Any], depth: np.ndarray) -> bool:
    """Whether the compiled Alg. 3 kernel serves these parameters and depth image: it
    covers the default path (no ``top_half``; the surface fit by plain least squares, or
    none) on integer depth."""
    plain_fit = not p["fit_robust"] and p["fit_prior_mm"] <= 0 and p["fit_max_se"] >= 1e9
    default_path = not p["top_half"] and (plain_fit or not p["surface_fit"])
    return bool(p["jit"]) and default_path and depth.dtype.kind in "ui"


def _widened(
    locate_blobs: Callable[..., tuple[np.ndarray, np.ndarray]],
    depth: np.ndarray,
    centroid: np.ndarray,
    region_radius: np.ndarray,
    p: Mapping[str, Any],
) -> np.ndarray:
    """(M, 3) ``locate_blobs`` with margin D0, again with 2 D0 where fewer than 3 ring
    pixels were found (R1: widen the margin once by D0)."""
    margin = np.full(len(centroid), p["D0"])
    z, res = locate_blobs(depth, centroid, region_radius, margin, p)
    few = res < 3
    if few.any():
        z[few], _ = locate_blobs(depth, centroid[few], region_radius[few], margin[few] * 2, p)
    return z


def _ragged(
    depth: np.ndarray, cen: np.ndarray, r: np.ndarray, margin: np.ndarray, p: Mapping
) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 3 (normal and bottom modes; top = normal) for n blobs in one pass.

    The windows' valid pixels are gathered into one flat array, sorted by (blob, depth),
    so every blob costs only its own pixels and a frame costs one pass whatever its blob
    sizes (padded windows cost a pass per size class and the padding of the largest).
    Same result as :func:`locate_depth` per blob. Returns ((n, 3) z, (n,) valid px).
    """
    H, Wd = depth.shape
    n = cen.shape[0]
    W, maxd = p["W"], p["max_depth"]
    half = np.ceil(r + margin).astype(np.intp)
    cu = np.rint(cen[:, 0]).astype(np.intp)
    cq = np.rint(cen[:, 1]).astype(np.intp)
    r0 = np.maximum(cq - half, 0)
    c0 = np.maximum(cu - half, 0)
    hgt = np.maximum(np.minimum(cq + half + 1, H) - r0, 0)
    wid = np.maximum(np.minimum(cu + half + 1, Wd) - c0, 0)
    size = hgt * wid
    out = np.full((n, 3), np.nan)
    total = int(size.sum())
    if total == 0:
        return out, np.zeros(n, np.intp)
    job = np.repeat(np.arange(n), size)
    k = np.arange(total) - np.repeat(np.cumsum(size) - size, size)
    rr, cc = np.divmod(k, wid[job])
    rows = r0[job] + rr
    cols = c0[job] + cc
    vals = depth[rows, cols]
    keep = np.flatnonzero((vals > 0) & (vals <= maxd))
    job, rows, cols = job[keep], rows[keep], cols[keep]
    z = vals[keep].astype(np.float64)
    nvalid = np.bincount(job, minlength=n)
    if z.size == 0:
        return out, nvalid
    # One sort for all blobs: blob b's depths are offset by b * 2 * big, so the flat array
    # is sorted by blob, then depth, and a W-window never reaches the next blob's values.
    big = float(z.max()) + 2.0 * W + 1.0
    off = np.arange(n) * (2.0 * big)
    key = z + off[job]
    # Ties need no stable order: depths are integers, so every sum below is exact.
    order = np.argsort(key)
    flat = key[order]
    off_px = ((cols - cen[job, 0]) + 1j * (rows - cen[job, 1]))[order]
    start = np.cumsum(nvalid) - nvalid
    near, far = _walk(flat, start, nvalid, off, W, p["min_slab"], p["bottom_reach"])
    t0_bottom = far - W
    need_bot = ~(t0_bottom == near) & np.isfinite(t0_bottom)
    ib = np.flatnonzero(need_bot)
    jobs = np.concatenate([np.arange(n), ib])
    T0 = np.concatenate([near, t0_bottom[ib]])
    good = np.isfinite(T0)
    T0f = np.where(good, T0, 0.0)
    lo = np.searchsorted(flat, T0f + off[jobs], side="left")
    hi = np.searchsorted(flat, T0f + W + off[jobs], side="right")
    lens = np.where(good, hi - lo, 0)
    J = jobs.size
    zs = np.full(J, np.nan)
    if lens.sum() > 0:
        jj = np.repeat(np.arange(J), lens)
        pos = np.arange(jj.size) - np.repeat(np.cumsum(lens) - lens, lens) + lo[jj]
        zz = flat[pos] - off[jobs[jj]]
        nv = nvalid[jobs].astype(np.float64)
        zs = _layers_core(jj, zz, off_px[pos], T0f, r[jobs], nv, p, zs)
    out[:] = zs[:n, None]
    out[ib, 2] = zs[n:]
    return out, nvalid


def _walk(
    flat: np.ndarray,
    start: np.ndarray,
    count: np.ndarray,
    off: np.ndarray,
    W: float,
    min_slab: int,
    reach: float,
) -> tuple[np.ndarray, np.ndarray]:
    """R2-R4 on the sorted, blob-offset depths of :func:`_ragged` (segment b is
    ``flat[start[b]:start[b] + count[b]]``, offset by ``off[b]``). Same walk and result as
    :func:`_layer_bounds`: (near, far) per blob, NaN where no slab is significant."""
    n = start.size
    near = [math.nan] * n
    far = [math.nan] * n
    ends = np.searchsorted(flat, flat + W, side="left").tolist()
    vals = flat.tolist()
    segs = zip(start.tolist(), count.tolist(), off.tolist(), strict=True)
    for b, (base, cnt, o) in enumerate(segs):
        i = 0
        nr = math.nan
        while i < cnt:
            s = vals[base + i]
            j = min(max(ends[base + i] - base, i + 1), cnt)
            if j - i >= min_slab:
                if nr != nr:  # first significant slab
                    nr = s
                if s <= nr + reach:
                    far[b] = vals[base + j - 1] - o
            i = j
            if nr == nr and i < cnt and vals[base + i] > nr + reach:
                break
        near[b] = nr - o if nr == nr else math.nan
    return np.array(near), np.array(far)


def _batch(
    depth: np.ndarray, cen: np.ndarray, r: np.ndarray, margin: np.ndarray, p: Mapping
) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 3 on windows of half-size ceil(r + margin); returns ((n, 3) z, (n,) valid px)."""
    H, Wd = depth.shape
    n = cen.shape[0]
    half = np.ceil(r + margin).astype(np.intp)
    hm = int(half.max())
    cu = np.rint(cen[:, 0]).astype(np.intp)
    cq = np.rint(cen[:, 1]).astype(np.intp)
    # (n, S, S) windows gathered by one broadcast fancy index; a window is shifted inward
    # at the image border and masked to the blob's own box.
    S = 2 * hm + 1
    if H < S or Wd < S:  # image smaller than a window: pad once, never in practice
        depth = np.pad(depth, ((0, max(S - H, 0)), (0, max(S - Wd, 0))))
    Hp, Wp = depth.shape
    r0 = np.clip(cq - hm, 0, Hp - S)
    c0 = np.clip(cu - hm, 0, Wp - S)
    ar = np.arange(S)
    rows = r0[:, None, None] + ar[None, :, None]  # (n, S, 1)
    cols = c0[:, None, None] + ar[None, None, :]  # (n, 1, S)
    vals = depth[rows, cols]  # (n, S, S)
    hh = half[:, None, None]
    inside = (np.abs(rows - cq[:, None, None]) <= hh) & (np.abs(cols - cu[:, None, None]) <= hh)
    if Hp != H or Wp != Wd:
        inside &= (rows < H) & (cols < Wd)
    valid = inside & (vals > 0) & (vals <= p["max_depth"])
    S2 = S * S
    valid = valid.reshape(n, S2)
    zf = np.where(valid, vals.reshape(n, S2), np.inf)
    # Complex offsets du + i dv from the centroid: one array carries distance and direction.
    dist = ((cols - cen[:, 0, None, None]) + 1j * (rows - cen[:, 1, None, None])).reshape(n, S2)
    nvalid = valid.sum(axis=1)
    if p["top_half"]:
        above = np.broadcast_to(rows <= cen[:, 1, None, None], (n, S, S))
        upper = above.reshape(n, S2) & valid
        use_upper = upper.sum(axis=1) >= 3
        zt = np.where(use_upper[:, None] & ~upper, np.inf, zf)
        nt = np.where(use_upper, upper.sum(axis=1), nvalid)
    else:
        use_upper = np.zeros(n, dtype=bool)
        nt = nvalid
    # Both pixel sets sorted per row; dist follows the depth order.
    # Flat gathers: take_along_axis costs more in call overhead on these small arrays. The
    # sorted rows are cut to the longest valid run (the rest is inf padding).
    oa = np.argsort(zf, axis=1, kind="stable")
    mlen = max(int(nvalid.max()), 1)
    flat_idx = oa[:, :mlen] + (np.arange(n) * S2)[:, None]
    za, da = zf.ravel()[flat_idx], dist.ravel()[flat_idx]
    if p["top_half"]:
        ot = np.argsort(zt, axis=1, kind="stable")
        zt = np.take_along_axis(zt, ot, 1)[:, :mlen]
        dt = np.take_along_axis(dist, ot, 1)[:, :mlen]
    else:
        zt, dt = za, da
    na = nvalid
    W, ms, reach = p["W"], p["min_slab"], p["bottom_reach"]
    t0_normal, t1_bottom = _layer_bounds(za, na, W, ms, reach)
    if p["top_half"]:
        t0_top, _ = _layer_bounds(zt, nt, W, ms, reach)
    else:
        t0_top = t0_normal
    t0_bottom = t1_bottom - W
    # Jobs: normal always; top and bottom only where they differ from it.
    need_top = use_upper  # its own pixel set, whatever its T0
    need_bot = ~(t0_bottom == t0_normal) & np.isfinite(t0_bottom)
    it, ib = np.flatnonzero(need_top), np.flatnonzero(need_bot)
    zj = np.concatenate([za, zt[it], za[ib]])
    dj = np.concatenate([da, dt[it], da[ib]])
    T0 = np.concatenate([t0_normal, t0_top[it], t0_bottom[ib]])
    rj = np.concatenate([r, r[it], r[ib]])
    nvj = np.concatenate([na, nt[it], na[ib]]).astype(np.float64)
    zs = _layers_batch(zj, dj, T0, rj, nvj, p)
    out = np.repeat(zs[:n, None], 3, axis=1)
    out[it, 1] = zs[n : n + it.size]
    out[ib, 2] = zs[n + it.size :]
    return out, nvalid


def locate_all(
    depth: np.ndarray,
    centroid: np.ndarray,
    region_radius: np.ndarray,
    camera: Camera,
    params: Mapping[str, Any],
    diameter: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 3 for every blob, then R9: camera-space positions.

    Parameters
    ----------
    depth : (H, W) uint16 depth, mm.
    centroid : (N, 2) (u, v) px.
    region_radius : (N,) r_r px.
    camera : intrinsics and distortion of the depth sensor.
    diameter : marker diameter in mm (default: the ``marker_diameter_mm`` parameter, or
        25 mm when that is 0).

    Returns
    -------
    depth (N, 3) Z mm of the marker point and position (N, 3, 3) [blob, mode, xyz] mm.
    """
    zs = locate_depths(depth, centroid, region_radius, params)
    return marker_positions(centroid, zs, camera, params, diameter)


def marker_positions(
    centroid: np.ndarray,
    zs: np.ndarray,
    camera: Camera,
    params: Mapping[str, Any],
    diameter: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """R9: the camera-space marker points of pixels ``centroid`` (N, 2) at surface depths
    ``zs`` (N, 3) mm (one per cluster mode), moved from the surface to the marker centre.

    Returns depth (N, 3) Z mm of the marker point and position (N, 3, 3) [blob, mode, xyz].
    """
    n = centroid.shape[0]
    if not n:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    xy = camera.undistort(centroid)  # R9: undistort once per blob, shared by the modes
    if diameter is None:
        diameter = marker_diameter(params["marker_diameter_mm"], None)
    back = surface_offset(params, diameter)
    offset = back > 0
    if params["jit"]:
        from gaitflow.stages import alg_kernels

        pos = alg_kernels.marker_points(xy, zs, offset, back)
    else:
        ray = np.ones((n, 1, 3))
        ray[:, 0, :2] = xy
        pos = ray * zs[:, :, None]  # [blob, mode, xyz]: (x', y', 1) * Z
        if offset:
            # |pos| = Z |ray|: one norm per blob, shared by the modes.
            norm = zs * np.sqrt(np.einsum("nij,nij->ni", ray, ray))
            with np.errstate(invalid="ignore", divide="ignore"):
                pos *= np.clip(1.0 - back / norm, 0.0, None)[:, :, None]
    return pos[:, :, 2].copy(), pos


def _cut_disc_table(n: int = 257) -> tuple[np.ndarray, np.ndarray]:
    """(visible fraction, centroid shift in radii), increasing in the fraction, for a unit
    disc with a circular segment of half-angle 0..pi/2 hidden (see :func:`cut_disc_shift`)."""
    a = np.linspace(0.5 * np.pi, 0.0, n)
    hidden = a - np.sin(a) * np.cos(a)
    return 1.0 - hidden / np.pi, 2.0 * np.sin(a) ** 3 / (3.0 * (np.pi - hidden))


_CUT_DISC = _cut_disc_table()


def cut_disc_shift(fraction: np.ndarray | float) -> np.ndarray:
    """How far the centroid of a disc's visible part lies from the disc's centre when a
    straight edge hides the rest, in disc radii, for the visible area ``fraction`` (clipped
    to [0.5, 1]: below one half the edge passes the centre and the area says too little).

    A circular segment of half-angle a hides ``(a - sin a cos a) / pi`` of the unit disc
    and has its centroid ``2 sin^3 a / (3 (a - sin a cos a))`` beyond the centre, so the
    rest's centroid lies ``2 sin^3 a / (3 (pi - a + sin a cos a))`` on the other side.
    """
    f = np.clip(np.asarray(fraction, dtype=np.float64), 0.5, 1.0)
    return np.interp(f, *_CUT_DISC)


def complete_occluded(
    depth: np.ndarray,
    centroid: np.ndarray,
    region_radius: np.ndarray,
    area: np.ndarray,
    surface_z: np.ndarray,
    params: Mapping[str, Any],
) -> tuple[np.ndarray, np.ndarray]:
    """Departure (before R9): the centre of a marker that a nearer surface partly hides.

    Alg. 2's centroid of such a marker is the centroid of its visible part, up to about
    half a radius away from the centre, on the side away from the occluder (a far heel or
    toe behind the near leg, a pelvis marker behind the swinging arm or the body's own
    curve). Three measurements say so and by how much, all from this frame:

    1. **Size.** A marker's blob area scales as 1 / Z^2, so ``K`` = the median of area x
       Z^2 (Z = the normal-mode surface depth) over the blobs whose Z lies within
       ``occlusion_peer_mm`` of this one's (the subject's body, not reflectors on the
       wall; at least ``occlusion_min_peers`` of them, itself included) is the area of an
       unhidden marker at 1 mm, and K / Z^2 the area expected at depth Z.
    2. **Occluder.** The blob's Alg. 3 window (half-size ceil(r_r + D0)) holds two
       surfaces: its valid depths, sorted, split where consecutive values step by
       ``occlusion_gap`` or more, into groups of at least ``min_slab`` pixels. The nearest
       group is the occluder, the next one the surface the marker is on.
    3. **Visible fraction.** f = area / (K / Z_behind^2), with Z_behind the median depth
       of the second group, but at most ``occlusion_peer_mm`` behind the occluder's (the
       marker is on the body; a farther second surface is the floor or the wall seen past
       the marker's edge). A marker beside a nearer surface that is not hidden (a
       silhouette marker with its own body nearest and the wall behind) has f >= 1 at
       that depth, well behind its own, and is left alone; completion needs
       f < ``occlusion_fraction``.

    The centre then lies ``cut_disc_shift(f)`` expected radii (sqrt(K / Z_behind^2 / pi))
    from the centroid, towards the occluder: the inverse-square-distance weighted mean
    offset of the nearest group's pixels.

    Parameters
    ----------
    depth : (H, W) uint16 depth, mm, 0 = invalid.
    centroid : (N, 2) (u, v) px from Alg. 2.
    region_radius : (N,) r_r px.
    area : (N,) blob pixel counts.
    surface_z : (N,) normal-mode surface depth mm from Alg. 3, NaN where none.

    Returns
    -------
    centroid (N, 2) px, completed where a marker is partly hidden, and completed (N,) bool.
    """
    p = params
    cen = np.array(centroid, dtype=np.float64, order="C").reshape(-1, 2)
    done = np.zeros(cen.shape[0], dtype=bool)
    if not p["occlusion_fix"]:
        return cen, done
    # fresh, C-ordered, writeable copies: the kernel then has one signature per depth
    # image type, which warm-up compiles (a column of Alg. 3's depths is strided, except
    # for one blob or none, and a decoded message's arrays are read-only)
    area = np.array(area, dtype=np.float64, order="C").reshape(-1)
    rr = np.array(region_radius, dtype=np.float64, order="C").reshape(-1)
    sz = np.array(surface_z, dtype=np.float64, order="C").reshape(-1)
    opts = (float(p["D0"]), float(p["max_depth"]), float(p["occlusion_gap"]))
    opts += (int(p["min_slab"]), float(p["occlusion_fraction"]))
    opts += (float(p["occlusion_peer_mm"]), int(p["occlusion_min_peers"]))
    if p["jit"] and depth.dtype.kind in "ui":
        from gaitflow.stages import alg_kernels

        return alg_kernels.complete_occluded(
            np.ascontiguousarray(depth), cen, rr, area, sz, *opts, *_CUT_DISC
        )
    fmax = opts[4]
    size = area * sz**2
    ok = np.isfinite(size) & (size > 0) & np.isfinite(cen).all(axis=1) & np.isfinite(rr)
    for i in np.flatnonzero(ok):
        peers = ok & (np.abs(sz - sz[i]) <= p["occlusion_peer_mm"])
        if np.count_nonzero(peers) < p["occlusion_min_peers"]:
            continue
        K = float(np.median(size[peers]))
        # area x Z_behind^2 >= area x Z^2: a blob at or above fmax K at its own surface
        # cannot fall below it behind an occluder.
        if size[i] >= fmax * K:
            continue
        occluder = _occluder(depth, cen[i], float(rr[i]), p)
        if occluder is None:
            continue
        toward, z_behind = occluder
        expected = K / z_behind**2
        f = float(area[i]) / expected
        if f < fmax:
            cen[i] += float(cut_disc_shift(f)) * math.sqrt(expected / math.pi) * toward
            done[i] = True
    return cen, done


def _occluder(
    depth: np.ndarray, centroid: np.ndarray, region_radius: float, p: Mapping[str, Any]
) -> tuple[np.ndarray, float] | None:
    """Step 2 of :func:`complete_occluded` for one blob: the unit direction (u, v) towards
    the nearest surface of its window and the median depth (mm) of the surface behind
    that, at most ``occlusion_peer_mm`` behind the nearest one's; None where the window
    does not hold two surfaces."""
    H, Wd = depth.shape
    u, v = centroid
    half = math.ceil(region_radius + p["D0"])
    r0, r1 = max(round(v) - half, 0), min(round(v) + half + 1, H)
    c0, c1 = max(round(u) - half, 0), min(round(u) + half + 1, Wd)
    win = depth[r0:r1, c0:c1]
    rr, cc = np.nonzero((win > 0) & (win <= p["max_depth"]))
    z = win[rr, cc].astype(np.float64)
    order = np.argsort(z, kind="stable")
    cuts = np.flatnonzero(np.diff(z[order]) >= p["occlusion_gap"]) + 1
    groups = [g for g in np.split(order, cuts) if g.size >= p["min_slab"]]
    if len(groups) < 2:
        return None
    near = groups[0]
    du = cc[near] + c0 - u
    dv = rr[near] + r0 - v
    w = 1.0 / np.maximum(du * du + dv * dv, 1.0)
    t = np.array([np.sum(w * du), np.sum(w * dv)])
    norm = float(np.hypot(*t))
    if norm == 0.0:
        return None
    # the marker is on the body, within its depth behind the occluder: a farther second
    # surface is the floor or the wall seen past the marker's edge
    behind = min(float(np.median(z[groups[1]])), float(np.median(z[near])) + p["occlusion_peer_mm"])
    return t / norm, behind


def surface_offset(params: Mapping[str, Any], diameter: float) -> float:
    """How far a position moves toward the camera from the surface to the marker centre.

    One radius plus the base height when ``surface_offset`` is on and the diameter is known,
    else 0 mm (see "Marker centre" in the module docstring).
    """
    if not (params["surface_offset"] and diameter > 0):
        return 0.0
    return 0.5 * float(diameter) + float(params["marker_base_mm"])


@dataclass(frozen=True)
class LocateState:
    """The resolved parameters and the intrinsics in use (parsed once, not per frame)."""

    params: Mapping[str, Any]
    camera_doc: Mapping[str, Any]
    camera: Camera
    diameter: float = DEFAULT_MARKER_DIAMETER_MM


def _camera(doc: Mapping[str, Any], where: str) -> Camera:
    """A camera.json document, or a flat mapping of Camera fields, as a Camera."""
    try:
        return Camera.from_doc(doc, source=where)
    except InputError as exc:
        raise StageError("locate", f"bad camera intrinsics from {where}: {exc}") from exc


def _state(params: Mapping[str, Any], doc: Mapping[str, Any], where: str) -> LocateState:
    cam_doc = params.get("camera") or doc
    cam = _camera(cam_doc, "parameter camera" if params.get("camera") else where)
    return LocateState(
        dict(params), dict(doc), cam, marker_diameter(params["marker_diameter_mm"], doc)
    )


def init(params: dict[str, Any]) -> LocateState:
    return _state(params, {}, "defaults")


def step(state: LocateState, inputs: Inputs) -> tuple[LocateState, list]:
    """Locate every blob of one frame in 3D; publish ``markers``."""
    frame, blobs = inputs["clean"], inputs["blobs"]
    if not (isinstance(frame, CleanFrame) and isinstance(blobs, Blobs)):
        raise StageError("locate", "inputs must be a CleanFrame and a Blobs message")
    p = state.params
    doc = frame.camera or {}
    if doc != state.camera_doc:
        state = _state(p, doc, "clean frame camera")
    centroid = np.asarray(blobs.centroid, dtype=np.float64).reshape(-1, 2)
    rr = np.asarray(blobs.region_radius, dtype=np.float64)
    depth = np.asarray(frame.depth)
    zs = locate_depths(depth, centroid, rr, p)
    centroid, _ = complete_occluded(depth, centroid, rr, blobs.area, zs[:, 0], p)
    z, pos = marker_positions(centroid, zs, state.camera, p, state.diameter)
    out = Markers3D.follow(
        blobs.header,
        centroid=centroid,
        marker_radius=np.asarray(blobs.marker_radius, dtype=np.float64),
        region_radius=rr,
        depth=z,
        position=pos,
        threshold=float(blobs.threshold),
        surface_offset_mm=surface_offset(p, state.diameter),
    )
    return state, [out]


SPEC = StageSpec(
    name="locate",
    params=PARAMS,
    init=init,
    step=step,
    stateful=False,
    # loads the compiled kernels before the stage reports ready
    warmup=stage_warmup("locate"),
    doc=__doc__ or "",
)
