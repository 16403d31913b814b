"""Stage ``detect``: the adaptive IR threshold (Alg. 1) and 2D marker detection (Alg. 2).

Input: ``clean`` (cleaned IR, depth, mask) joined per frame, and the ``calibration`` record as
a side input (its ``w`` and ``r_b`` seed Alg. 1). Output: ``blobs``.

Array conventions: images are (row, col) = (v, u); a pixel's centre is at integer (u, v);
centroids are (u, v) = (column, row) in pixels; radii in pixels; IR amplitude 0..65535 with
65535 = saturated. N blobs along axis 0.

Implementation notes (see ``../shared/reference/algorithms.md`` sections 3.1 and 3.2):

- **Region of interest.** Every threshold Alg. 1 tries is at least ``min(w, e_j in H)``:
  step 5 averages blob means (each above the current threshold) and step 6 averages blob
  means and ``w``. All components of every threshold it tries therefore lie inside the
  pixels above a floor level. :func:`compact_roi` finds the 8x8-pixel blocks holding such
  pixels from a block-maximum image, merges the bounding boxes of their 8-connected groups
  where they overlap, and gathers the boxes into one small mosaic with a zero line between
  neighbours, so that no two components merge. Connected components of the mosaic are
  exactly those of the frame, at any threshold above the floor; Alg. 1 iterates on it at
  a fraction of the full-frame cost.
- **Alg. 1** follows the Rec. reading: blob means for [A-1a] with normalised weights, stop
  when f is unchanged or f = n [A-1b] with an iteration cap, ``w`` stays the anchor [A-1c],
  8-connectivity, at least ``min_area`` pixels, strict ``S_d > e``. With an empty history
  the h1/h2 term drops out (it has no data), as the h0 term does when f = 0.
- **Alg. 1 cycles (departure).** Steps 4-10 can alternate between two blob sets (f above
  n, then below) until the cap. A blob set seen before in the frame (same count and areas:
  thresholds are nested, so equal areas mean equal components) ends the loop, keeping the
  visited state whose count is closest to n (ties: the most recent), as step 1 does with
  the history. On the simulated walks this changes no detection figure beyond 0.03 points
  and removes the slowest frames.
- **Threshold cap (departure, ``max_threshold`` = 3/4 of full scale).** For saturated,
  flat-topped markers, step 5 drives e_d to the mean IR of the largest blobs, i.e. to
  65535: only fully saturated pixels remain, and a small or distant marker with fewer than
  ``min_area`` saturated pixels drops out although its rim is plainly there. Capping e_d at
  three quarters of full scale keeps every pixel at least 3/4 covered by a marker. On the
  simulator this raised detection from 91.8 to 95.7 % with markers 3.5 m away and from 96.1
  to 97.1 % on a second trial at 2.75 m, and changed nothing where e_d stayed below it.
- **Step 6 over unsaturated blobs (departure, ``step6_saturated_only``, on by default
  since the twenty-fifth session).** With fewer blobs than n, step 6 moves e_d to a
  weighted mean of w, the blobs' mean IR and the history's largest blob's. For saturated
  markers that mean lies near full scale and a higher e_d loses none of them (their cores
  stay above any e_d up to ``max_threshold``). For markers that do not saturate (worn or
  dim ones, the simulator's ``dim`` and ``faint``) it lies above the dimmer markers' peaks,
  so step 6 *raised* e_d while blobs were missing and lost more of them. With the option,
  step 6 raises e_d only when every blob holds a saturated pixel, and otherwise keeps it
  (the loop ends there), **until the camera's markers are seen to saturate**: a frame whose
  blobs include ``saturating_markers`` (4) saturated ones sets ``CameraState
  .markers_saturate``, kept for the camera's later frames and trials (the static pose,
  every marker in view, usually sets it), and from then on step 6 is the printed one.
  Without that flag the option kept e_d low at a pass's first frames, where half-hidden
  markers do not saturate, and their rims misled the label stage (twenty-fourth session,
  when the option was off by default). With it, every simulated set-up whose markers
  saturate gives the printed rule's output, and ``dim`` and ``faint`` label 99.6 %
  (README, gait section, "Markers that do not saturate").
- **Alg. 2** uses the weight ``P - e_d`` [A-2a] and ``r_r = max l`` [A-2b].
- **Speed.** The ROI's float image and each mosaic pixel's frame (u, v) are made once per
  frame (:class:`Roi`), so Alg. 1's iterations only threshold, label and ``bincount``;
  step 1 compares the history thresholds' blob counts from component areas alone
  (:func:`count_components`) and computes full statistics only for the one it picks;
  ``r_r`` (a per-component maximum) comes from one sort instead of ``np.maximum.at``, and
  the ``max_region_radius`` test runs on the kept components only. Results are identical
  to the straightforward version (checked on every third frame of two simulated walks at
  several thresholds, and by the unit tests against full-frame labelling).
- **Compiled kernels (``jit``, on by default).** What was left after that was numpy's
  per-call overhead on small arrays, so the block maxima, the mosaic (box merging, shelf
  packing, the flat copies), the labelling and Alg. 2's statistics run as numba kernels
  (``stages/alg_kernels.py``): a few loops over the pixels, summing in the order
  ``np.bincount`` does, so blobs, thresholds and iterations are bit-identical to the numpy
  path above, which ``jit`` = false keeps as the reference (``tests/test_mocap_jit.py``).
  The kernel's union-find labelling numbers components as OpenCV's block-based labelling
  does (by their first 2x2 block; 4-way: by their first pixel), so blob order is kept
  too; it replaced OpenCV in the Alg. 1 loop because OpenCV's call, with its mask and
  statistics, cost about three times as much on these small mosaics. Kernels compile on
  first use, not at import, and are cached on disk.
- **Merged markers: three splitters, on by default since the thirtieth session.** Heel
  and ankle, the two PSI or ASI seen side-on, crossing feet: markers whose images touch or
  overlap form one component and one centroid between them. They run in the order
  tracked, cores, merged; a part one of them made has no pixels of its own (``ids`` -1)
  and the next leaves it alone. Each uses the detector's own frames only (no label, no
  truth). On all five bundled walks the three together detected 98.93 % of the visible
  markers (96.33 % without them) and 99.60 % of the paper's twelve, and recalled 91.52 %
  within 0.5 px (87.93 %; 99.42 %, 99.71 % and 93.50 % with the thirty-second session's
  optional learned streak ratio, below, and locate's completion of partly hidden markers)
  (``gaitflow bench mocap --ablation``: ``adaptive-nosplit`` and
  one row per splitter alone). They were off until then because end to end the label
  stage did no better with the extra blobs; replayed over the 41 rows of the gait
  variation table (README, mocap section) they now find more gait events (heel strikes
  missed 38.9 -> 34.6 %) and measure 10 % more steps, for 0.1 point of labelling, which
  label's foot rule of the same session wins back (99.40 % either way).

  - ``split_tracked`` (:func:`split_tracked`): a blob that took in two blobs of the
    previous frame lying close together, and grew, is split by a 2-means seeded with their
    offset. A blob that is one marker in both frames is never split.
  - ``split_cores`` (:func:`split_cores`): a blob that holds two or more separate *cores*,
    regions of its pixels near its peak level (``core_depth``; an intensity valley
    separates them), or of those inside the blob eroded by the 4-neighbourhood or the 3x3
    square (which cut the neck of two touching saturated discs, whose flat top has no
    valley). A single marker, however blurred, is a convex spot with one core and is never
    split; lines (tape, a pole's highlight) are excluded by their low fill ratio
    (``split_min_fill``).
  - ``split_merged`` (:func:`split_merged`): a blob whose area is 1.5-3x the frame's median
    and whose weighted covariance is elongated (eigenvalue ratio >= 2) is split by a
    weighted 2-means along its principal axis, when the halves lie 2-5 median marker radii
    apart (two touching discs lie about 3 apart; a 23 px streak beside a hidden hip, 6.7
    apart, took the hip label). A blob that moved along its elongation, since the frame
    before, by at least the streak it shows is left whole (a marker's blur streak is never
    longer than its motion per frame): without that test a knee marker in swing was split
    in two in 63 frames of one walk and the label stage dropped the knee. Option
    ``streak_learned`` (thirty-second session, off by default) makes the bound the
    camera's own: its streaks are at most a share of its motion (the exposure's share of
    the frame interval), learned as the 0.9 quantile of streak / motion over its isolated
    moving blobs (:func:`streak_ratios`, ``streak_quantile``, ``streak_min_samples`` 30,
    one sample a frame, ``streak_window`` 300 kept per camera from trial to trial), 1 until
    enough are in. With the simulator's exposure (12 of 33 ms) it settles near 0.3, and the
    two PSI seen side-on, 3 px apart and moving 6 px a frame along their own axis, are
    split instead of being read as one streak: detected 98.93 -> 99.42 %, recall at 0.5 px
    93.03 -> 93.50 % (``gaitflow bench mocap --all --frames 0 --ablation``, row
    ``adaptive-streak``). It is off because end to end it is a trade: a fast foot marker
    in swing can streak beyond the learned share of its motion and is split, a shoe's reflector
    is parted from the heel it touches, and the label stage names the extra blobs (README,
    mocap section).
- **Sub-pixel refinement (optional, ``refine``, off by default).** Saturated markers are
  flat-topped: with e_d near 65535 every pixel above it weighs the same and Alg. 2's
  centroid is quantised; the sub-pixel information is in the partly covered rim below e_d.
  ``refine`` grows each blob by one pixel and recomputes its centroid over the grown
  pixels above a lower level ``e_low``, weighted by ``P - e_low`` (blob set, radii and e_d
  unchanged). On literal discs it cuts the mean error from 0.065 to 0.018 px, and on the
  simulator it halves the median error (0.12 -> 0.06 px), but it *lowers* recall at 0.5 px
  by 1.5-3 points on walking trials: for moving and partly hidden markers the rim also
  holds motion-blur tails and occlusion edges. With the threshold cap above, Alg. 2 already
  uses rim pixels at least 3/4 covered, so the pipeline keeps Alg. 2's centroid by default
  and the bench reports both (``gaitflow bench mocap --ablation``).
- **Bad input** never raises: an all-zero frame gives no blobs (status ``empty``); blobs
  wider than ``max_region_radius`` (a saturated frame, a lamp) are rejected and counted;
  more than ``max_blobs`` candidates keep the ``max_blobs`` largest (status ``too-many``).
  Work per frame is bounded by the iteration cap and by the frame size.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from gaitflow.schemas import Blobs, CalibrationRecord, CleanFrame
from gaitflow.stages.base import Inputs, StageSpec
from gaitflow.stages.warmup import stage_warmup

from gaitflow.errors import StageError
from gaitflow.params import Param, ParamSet

SATURATED = 65535
_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
_SQUARE = np.ones((3, 3), np.uint8)
# Alg. 1 thresholds are compared with uint16 pixels by ``S > e``; 65534 still keeps
# saturated pixels, so the threshold never rises past it.
E_MAX = float(SATURATED - 1)

# The three ways of splitting a blob of merged markers, in the order they run.
SPLITTERS = ("split_tracked", "split_cores", "split_merged")

PARAMS = ParamSet(
    "detect",
    (
        Param(
            "method",
            str,
            "adaptive",
            "-",
            "adaptive (Alg. 1) or static (fixed threshold, the Table II baseline)",
            choices=("adaptive", "static"),
        ),
        Param("n", int, 12, "markers", "Alg. 1: number of markers expected (Table I)", low=1),
        Param("b", int, 3, "frames", "Alg. 1: scan-window (history) length (Table I)", low=1),
        Param("max_iterations", int, 10, "-", "Alg. 1: iteration cap [A-1b]", low=1, high=100),
        Param("connectivity", int, 8, "-", "pixel connectivity of components", choices=(4, 8)),
        Param("min_area", int, 3, "px", "smallest component counted as a blob", low=1),
        Param(
            "static_threshold",
            float,
            0.0,
            "IR",
            "threshold of method=static; 0 = the calibration w (or its image fallback)",
            low=0.0,
            high=E_MAX,
        ),
        Param(
            "default_w",
            float,
            0.0,
            "IR",
            "w when no calibration record carries one; 0 = derive from the trial's first "
            "frame: a quarter of the way from its background level to saturation",
            low=0.0,
            high=E_MAX,
        ),
        Param(
            "default_r_b",
            float,
            0.0,
            "px",
            "r_b when no calibration record carries one; 0 = the median r_r of the blobs "
            "at w in the trial's first frame with blobs (2 px if none)",
            low=0.0,
        ),
        Param("refine", bool, False, "-", "sub-pixel centroid refinement below e_d (optional)"),
        Param(
            "refine_fraction",
            float,
            0.2,
            "-",
            "e_low = background + refine_fraction * (e_floor - background)",
            low=0.0,
            high=1.0,
        ),
        Param(
            "max_threshold",
            float,
            49151.0,
            "IR",
            "highest e_d Alg. 1 may reach: 3/4 of full scale (departure, see the module doc)",
            low=1.0,
            high=E_MAX,
        ),
        Param(
            "step6_saturated_only",
            bool,
            True,
            "-",
            "Alg. 1 step 6 raises e_d only when every blob is saturated, until the markers are"
            " seen saturating (departure for markers that do not, see the module doc);"
            " false = as printed",
        ),
        Param(
            "saturating_markers",
            int,
            4,
            "blobs",
            "with step6_saturated_only: a frame with this many saturated blobs shows that the"
            " camera's markers saturate, and step 6 is the printed one from then on",
            low=1,
        ),
        Param("max_blobs", int, 64, "blobs", "keep at most this many (largest) blobs", low=1),
        Param(
            "max_region_radius",
            float,
            40.0,
            "px",
            "reject components wider than this (not a marker: saturated area, lamp)",
            low=1.0,
        ),
        Param("block", int, 8, "px", "block size of the region-of-interest search", low=2),
        Param(
            "jit",
            bool,
            True,
            "-",
            "compiled (numba) kernels for the region of interest, labelling and Alg. 2 "
            "statistics; identical outputs, false = the numpy reference",
        ),
        Param(
            "split_merged",
            bool,
            True,
            "-",
            "split a blob shaped like two merged markers in two (departure)",
        ),
        Param(
            "split_tracked",
            bool,
            True,
            "-",
            "split a blob into two markers the previous frame saw apart (departure)",
        ),
        Param(
            "split_cores",
            bool,
            True,
            "-",
            "split a blob holding two or more separate bright cores (departure)",
        ),
        Param(
            "core_depth",
            float,
            0.25,
            "-",
            "split_cores: core level below a blob's peak, as a fraction of its height above e_d",
            low=0.0,
            high=1.0,
        ),
        Param("min_core_area", int, 2, "px", "split_cores: smallest core", low=1),
        Param(
            "streak_learned",
            bool,
            False,
            "-",
            "split_merged: bound a single marker's blur streak by the share of its motion"
            " learned from the camera's isolated moving blobs, not by its whole motion"
            " (off: end to end a trade, README mocap section)",
        ),
        Param(
            "streak_quantile",
            float,
            0.9,
            "-",
            "split_merged: a single marker's blur streak is taken to be at most this quantile"
            " of the streak / motion ratios of the camera's isolated moving blobs",
            low=0.0,
            high=1.0,
        ),
        Param(
            "streak_min_samples",
            int,
            30,
            "blobs",
            "split_merged: ratios needed before the learned one replaces 1 (an exposure as"
            " long as the frame interval)",
            low=1,
        ),
        Param(
            "streak_every",
            int,
            1,
            "frames",
            "split_merged: sample the streak / motion ratio on one frame in this many (a"
            " pixel pass of about 0.1 ms)",
            low=1,
        ),
        Param(
            "streak_window",
            int,
            300,
            "blobs",
            "split_merged: ratios sampled per camera (one a frame at most; none once this"
            " many are kept, the exposure being the camera's)",
            low=1,
        ),
        Param(
            "split_min_fill",
            float,
            0.25,
            "-",
            "split_cores: least area / (pi r_r^2) of a blob split (compact groups, not lines)",
            low=0.0,
            high=1.0,
        ),
    ),
)


# --------------------------------------------------------------------------------------
# Region of interest


@dataclass(frozen=True)
class Roi:
    """A small mosaic image gathering the parts of a frame above a level.

    ``image`` (h, w) uint16 holds the gathered pixels, 0 elsewhere; ``tile`` (h, w) int32
    says which crop each mosaic pixel came from (-1 = none), and crop t's pixel at mosaic
    (r, c) is frame pixel (row, col) = (r + dv[t], c + du[t]).
    """

    image: np.ndarray
    tile: np.ndarray
    du: np.ndarray
    dv: np.ndarray
    level: float
    # Flat (h*w,) float64 copies of the image and of each mosaic pixel's frame (u, v),
    # made once per frame so that Alg. 1's iterations do no conversions.
    flat_ir: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    flat_u: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    flat_v: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.flat_ir is None:
            h, w = self.image.shape
            t = self.tile.ravel()
            tt = np.maximum(t, 0)
            rr, cc = np.divmod(np.arange(h * w), max(w, 1))
            object.__setattr__(self, "flat_ir", self.image.ravel().astype(np.float64))
            object.__setattr__(self, "flat_u", (cc + self.du[tt]).astype(np.float64))
            object.__setattr__(self, "flat_v", (rr + self.dv[tt]).astype(np.float64))

    def frame_uv(self, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frame (u, v) of mosaic pixels (r, c)."""
        t = self.tile[r, c]
        return c + self.du[t], r + self.dv[t]


def block_max(ir: np.ndarray, block: int, jit: bool = True) -> np.ndarray:
    """Maximum over each ``block`` x ``block`` tile. (H, W) -> (ceil(H/b), ceil(W/b)).

    ``jit`` uses the compiled kernel for unsigned images (the same values: padding with
    zeros never changes their maxima); otherwise numpy.
    """
    if jit and ir.dtype.kind == "u" and ir.ndim == 2:
        from gaitflow.stages import alg_kernels

        # Contiguous input: one compiled specialisation serves every caller.
        return alg_kernels.block_max(np.ascontiguousarray(ir), int(block))
    h, w = ir.shape
    hb, wb = -(-h // block), -(-w // block)
    if hb * block != h or wb * block != w:
        ir = np.pad(ir, ((0, hb * block - h), (0, wb * block - w)))
    rm = np.maximum.reduce(ir.reshape(hb, block, wb * block), axis=1)
    # Strided maxima over the block columns: much cheaper than a reduce over a short axis.
    bm = rm[:, 0::block].copy()
    for k in range(1, block):
        np.maximum(bm, rm[:, k::block], out=bm)
    return bm


def _empty_roi(dtype: np.dtype, level: float) -> Roi:
    z = np.zeros(0, dtype=np.intp)
    return Roi(np.zeros((0, 0), dtype), np.zeros((0, 0), np.int32), z, z, float(level))


def _merge_boxes(boxes: list[list[int]]) -> list[list[int]]:
    """Union of overlapping [x0, y0, x1, y1) boxes, repeated until none overlap."""
    out = [list(b) for b in boxes]
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    out[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out


def compact_roi(
    ir: np.ndarray,
    level: float,
    block: int = 8,
    bmax: np.ndarray | None = None,
    mosaic_width: int = 128,
    jit: bool = True,
) -> Roi:
    """Gather the groups of ``block`` x ``block`` tiles holding pixels above ``level``.

    Tiles holding a pixel above ``level`` are grouped by 8-connectivity; the groups'
    bounding boxes are merged where they overlap, and the boxes are cropped and
    shelf-packed into one mosaic with one zero line between neighbours.

    Parameters
    ----------
    ir : (H, W) uint16 IR frame.
    level : only pixels ``> level`` matter to the caller.
    block : tile size in px.
    bmax : the frame's :func:`block_max`, if already computed.
    mosaic_width : shelf width of the mosaic in px (wider crops get their own shelf).
    jit : compiled :func:`block_max`, tile labelling and mosaic (``alg_kernels.roi_mosaic``;
        identical result) for uint16 frames.

    Returns
    -------
    Roi
        Components of ``image > e`` for any ``e >= level`` are exactly the components of
        ``ir > e``: every such component lies inside one tile group, every group inside
        exactly one (merged) box, and boxes are separated by zeros in the mosaic.
    """
    bm = block_max(ir, block, jit) if bmax is None else bmax
    if jit and ir.dtype == np.uint16:
        from gaitflow.stages import alg_kernels

        img, tile, du, dv, flat_ir, fu, fv = alg_kernels.roi_mosaic(
            np.ascontiguousarray(ir), np.ascontiguousarray(bm), float(level), int(block),
            int(mosaic_width),
        )  # fmt: skip
        if du.size == 0:
            return _empty_roi(ir.dtype, level)
        return Roi(img, tile, du, dv, float(level), flat_ir, fu, fv)
    act = bm > level
    H, W = ir.shape
    ng, _, stats, _ = cv2.connectedComponentsWithStats(act.view(np.uint8), connectivity=8)
    if ng <= 1:
        return _empty_roi(ir.dtype, level)
    boxes = [
        [bx * block, by * block, min((bx + bw) * block, W), min((by + bh) * block, H)]
        for bx, by, bw, bh, _ in stats[1:].tolist()
    ]
    if len(boxes) > 1:
        boxes = _merge_boxes(boxes)
    # Shelf packing, tallest first so shelves waste little height.
    boxes.sort(key=lambda b: b[1] - b[3])
    place = []  # (mosaic row, mosaic col) of each box
    x = y = shelf_h = width = 0
    for c0, r0, c1, r1 in boxes:
        ch, cw = r1 - r0, c1 - c0
        if x > 0 and x + cw > mosaic_width:
            y += shelf_h + 1
            x = shelf_h = 0
        place.append((y, x))
        x += cw + 1
        shelf_h = max(shelf_h, ch)
        width = max(width, x - 1)
    height = y + shelf_h
    img = np.zeros((height, width), dtype=ir.dtype)
    tile = np.full((height, width), -1, dtype=np.int32)
    for g, ((c0, r0, c1, r1), (my, mx)) in enumerate(zip(boxes, place, strict=True)):
        img[my : my + r1 - r0, mx : mx + c1 - c0] = ir[r0:r1, c0:c1]
        tile[my : my + r1 - r0, mx : mx + c1 - c0] = g
    du = np.array([b[0] - p[1] for b, p in zip(boxes, place, strict=True)], dtype=np.intp)
    dv = np.array([b[1] - p[0] for b, p in zip(boxes, place, strict=True)], dtype=np.intp)
    # Frame (u, v) of every mosaic pixel (pixels outside the crops are 0 in ``img`` and
    # never foreground, so their offsets do not matter).
    fu = (np.arange(width, dtype=np.float64)[None, :] + du[tile]).ravel()
    fv = (np.arange(height, dtype=np.float64)[:, None] + dv[tile]).ravel()
    return Roi(img, tile, du, dv, float(level), img.ravel().astype(np.float64), fu, fv)


# --------------------------------------------------------------------------------------
# Alg. 2: components and their statistics


@dataclass(frozen=True)
class Components:
    """Alg. 2 statistics of the connected components above one threshold.

    K components along axis 0, frame coordinates. ``labels`` (h, w) int32 labels the ROI
    image (0 = background, component i has label ``ids[i]``).
    """

    threshold: float
    centroid: np.ndarray  # (K, 2) (u, v) px, weights P - e
    marker_radius: np.ndarray  # (K,) r_m: weighted mean distance to the centroid, px
    region_radius: np.ndarray  # (K,) r_r: max distance to the centroid, px
    mean_ir: np.ndarray  # (K,) k: mean IR
    area: np.ndarray  # (K,) pixel count
    ids: np.ndarray  # (K,) label of each component in ``labels``
    labels: np.ndarray = field(repr=False)
    rejected: int = 0  # components dropped as too wide (max_region_radius)
    box: np.ndarray | None = None  # (K, 4) u0, v0, u1, v1 px (inclusive), if asked for

    @property
    def count(self) -> int:
        return int(self.area.size)


def components(
    roi: Roi,
    e: float,
    min_area: int = 3,
    connectivity: int = 8,
    max_region_radius: float = np.inf,
    extent: bool = False,
    jit: bool = True,
) -> Components:
    """Alg. 2: connected components of ``roi.image > e`` with weighted centroid and radii.

    Parameters
    ----------
    roi : compact image of the frame, ``roi.level <= e``.
    e : threshold e_d; strict ``P > e``.
    min_area : components with fewer pixels are not blobs.
    connectivity : 4 or 8.
    max_region_radius : components with ``r_r`` above it are rejected (counted).
    extent : also return each component's bounding box (``box``).
    jit : labelling and statistics by the compiled kernel ``alg_kernels.components_at``
        (a few loops over the pixels instead of OpenCV and about 25 numpy calls; identical
        labels and figures); false = the numpy reference below.

    Returns
    -------
    Components
        Weight ``omega = (P - e) / v`` (Rec. [A-2a]); centroid ``sum omega * (u, v)``;
        ``r_m = sum omega * l`` (Alg. 2 step 7); ``r_r = max l`` ([A-2b]).
    """
    img = roi.image
    if img.size == 0:
        return _no_components(e)
    if jit:
        _check_connectivity(connectivity)
        return _components_jit(roi, e, connectivity, min_area, max_region_radius, extent)
    mask = (img > e).view(np.uint8)
    nlab, labels, stats, _ = cv2.connectedComponentsWithStats(
        mask, connectivity=connectivity, ltype=cv2.CV_32S
    )
    if nlab == 1:  # nothing above e: skip the statistics
        return _no_components(e, labels)
    area = stats[:, cv2.CC_STAT_AREA]
    ok = area >= min_area
    ok[0] = False
    ids = np.flatnonzero(ok).astype(np.int32)
    # Statistics over the foreground pixels only, from the per-frame float copies.
    idx = np.flatnonzero(mask)
    lab = labels.ravel()[idx]
    val = roi.flat_ir[idx]
    u = roi.flat_u[idx]
    v = roi.flat_v[idx]
    wt = val - e
    sw = np.bincount(lab, wt, minlength=nlab)
    sw[0] = 1.0
    pu = np.bincount(lab, wt * u, minlength=nlab) / sw
    pv = np.bincount(lab, wt * v, minlength=nlab) / sw
    dist = np.hypot(u - pu[lab], v - pv[lab])
    rm = np.bincount(lab, wt * dist, minlength=nlab) / sw
    # r_r = max l per component: sort by distance once, the last write per label wins.
    rr = np.zeros(nlab)
    order = np.argsort(dist, kind="stable")
    rr[lab[order]] = dist[order]
    k = np.bincount(lab, val, minlength=nlab) / np.maximum(area, 1)
    rejected = 0
    if np.isfinite(max_region_radius):
        wide = rr[ids] > max_region_radius
        if wide.any():
            rejected = int(wide.sum())
            ids = ids[~wide]
    box = None
    if extent:
        x0, y0 = stats[ids, cv2.CC_STAT_LEFT], stats[ids, cv2.CC_STAT_TOP]
        # Mosaic boxes to frame boxes: every pixel of a component lies in one crop.
        pix = np.argmax(lab[:, None] == ids[None, :], axis=0)
        t = roi.tile.ravel()[idx[pix]]
        x0 = x0 + roi.du[t]
        y0 = y0 + roi.dv[t]
        x1 = x0 + stats[ids, cv2.CC_STAT_WIDTH] - 1
        y1 = y0 + stats[ids, cv2.CC_STAT_HEIGHT] - 1
        box = np.stack([x0, y0, x1, y1], axis=1).astype(np.float64)
    return Components(
        threshold=float(e),
        centroid=np.stack([pu[ids], pv[ids]], axis=1),
        marker_radius=rm[ids],
        region_radius=rr[ids],
        mean_ir=k[ids],
        area=area[ids].astype(np.int32),
        ids=ids,
        labels=labels,
        rejected=rejected,
        box=box,
    )


def _check_connectivity(connectivity: int) -> None:
    """The kernels label 4- or 8-connected components only (as OpenCV)."""
    if connectivity not in (4, 8):
        raise StageError("detect", f"connectivity {connectivity!r} is not 4 or 8")


def _components_jit(
    roi: Roi,
    e: float,
    connectivity: int,
    min_area: int,
    max_region_radius: float,
    extent: bool,
) -> Components:
    """:func:`components` by the compiled kernel (same labels and figures)."""
    from gaitflow.stages import alg_kernels

    nlab, labels, ids, cen, rm, rr, k, area, mbox, first, rejected = alg_kernels.components_at(
        roi.image,
        roi.flat_ir,
        roi.flat_u,
        roi.flat_v,
        float(e),
        int(connectivity),
        int(min_area),
        float(max_region_radius),
    )
    if nlab == 1:  # nothing above e
        return _no_components(e, labels)
    box = None
    if extent:
        # Mosaic boxes to frame boxes through the crop of each blob's first pixel.
        t = roi.tile.ravel()[first]
        du, dv = roi.du[t], roi.dv[t]
        box = np.stack(
            [mbox[:, 0] + du, mbox[:, 1] + dv, mbox[:, 2] + du, mbox[:, 3] + dv], axis=1
        ).astype(np.float64)
    return Components(
        threshold=float(e),
        centroid=cen,
        marker_radius=rm,
        region_radius=rr,
        mean_ir=k,
        area=area,
        ids=ids,
        labels=labels,
        rejected=int(rejected),
        box=box,
    )


def _no_components(e: float, labels: np.ndarray | None = None) -> Components:
    z = np.zeros(0)
    lab = np.zeros((0, 0), np.int32) if labels is None else labels
    return Components(
        float(e), np.zeros((0, 2)), z, z, z, np.zeros(0, np.int32), np.zeros(0, np.int32), lab
    )


def count_components(
    roi: Roi,
    e: float,
    min_area: int = 3,
    connectivity: int = 8,
    max_region_radius: float = np.inf,
    jit: bool = True,
) -> int | None:
    """Number of blobs :func:`components` would return at ``e``, from areas alone.

    Returns None when a component's bounding box is wide enough that its ``r_r`` might
    exceed ``max_region_radius`` (then only the full statistics can tell). ``r_r`` is at
    most the box diagonal between pixel centres, so below that bound areas decide. Alg. 1
    step 1 needs only the blob count at each history threshold. ``jit`` labels with the
    compiled ``alg_kernels.count_at`` (the same count).
    """
    img = roi.image
    if img.size == 0:
        return 0
    if jit:
        from gaitflow.stages import alg_kernels

        _check_connectivity(connectivity)
        c = alg_kernels.count_at(
            img, float(e), int(connectivity), int(min_area), float(max_region_radius)
        )
        return None if c < 0 else c
    mask = (img > e).view(np.uint8)
    _, _, stats, _ = cv2.connectedComponentsWithStats(
        mask, connectivity=connectivity, ltype=cv2.CV_32S
    )
    st = stats[1:]
    big = st[:, cv2.CC_STAT_AREA] >= min_area
    if np.isfinite(max_region_radius):
        diag = np.hypot(st[:, cv2.CC_STAT_WIDTH] - 1, st[:, cv2.CC_STAT_HEIGHT] - 1)
        if np.any(big & (diag > max_region_radius)):
            return None
    return int(np.count_nonzero(big))


def refine_centroids(
    roi: Roi, comps: Components, e_low: float, connectivity: int = 8, ring: int = 1
) -> np.ndarray:
    """Sub-pixel centroids from the partly covered edge pixels (departure, see module doc).

    Each blob at e_d is grown by ``ring`` px (a 3x3 dilation per pixel of ring); the grown
    region's pixels above ``e_low`` are weighted by ``P - e_low``. The ring is where a
    marker's partly covered pixels are; growing no further keeps out blur tails, skin and
    neighbouring highlights that a plain lower threshold would take in.

    Parameters
    ----------
    roi : compact image, ``roi.level <= e_low``.
    comps : the blobs at e_d (``e_low < e_d``).
    e_low : the lower level; weights ``P - e_low``.
    connectivity : unused (the growth is 8-connected); kept for a stable signature.
    ring : growth in px.

    Returns
    -------
    (K, 2) centroids (u, v); a blob whose grown region touches another blob's keeps its
    Alg. 2 centroid.
    """
    del connectivity
    out = comps.centroid.copy()
    if comps.count == 0 or e_low >= comps.threshold or ring < 1:
        return out
    lab = comps.labels.astype(np.float32)  # labels < 2**24 are exact in float32
    kernel = np.ones((2 * ring + 1, 2 * ring + 1), np.uint8)
    grown_hi = cv2.dilate(lab, kernel)
    # Where two blobs' rings meet, max and min of the grown labels differ: contested.
    big = np.float32(comps.labels.max() + 1)
    grown_lo = -cv2.dilate(np.where(lab > 0, -lab, -big).astype(np.float32), kernel)
    sel = (grown_hi > 0) & (roi.image > e_low)
    r, c = np.nonzero(sel)
    g = grown_hi[r, c].astype(np.intp)
    contested = np.zeros(int(big) + 1, dtype=bool)
    clash = grown_lo[r, c] != grown_hi[r, c]
    contested[g[clash]] = True
    wt = roi.image[r, c].astype(np.float64) - e_low
    fu, fv = roi.frame_uv(r, c)
    n = int(big)
    sw = np.bincount(g, wt, minlength=n)
    su = np.bincount(g, wt * fu, minlength=n)
    sv = np.bincount(g, wt * fv, minlength=n)
    ok = (sw[comps.ids] > 0) & ~contested[comps.ids]
    ids = comps.ids[ok]
    out[ok, 0] = su[ids] / sw[ids]
    out[ok, 1] = sv[ids] / sw[ids]
    return out


def _with_parts(
    comps: Components, first: tuple, extra: list[tuple], split: list[int]
) -> Components:
    """``comps`` with split blobs' first parts in place and the further parts appended.

    ``first`` = (centroid, r_m, r_r, k, area) arrays for the K original blobs (split ones
    overwritten); ``extra`` = one (centroid, r_m, r_r, k, area) tuple per appended part;
    ``split`` = the indices of the blobs split. Every part's ``ids`` is -1: its pixels are
    not a label of its own in ``labels`` (a further splitter leaves it alone).
    """
    cen, rm, rr, k, area = first
    ids = comps.ids.copy()
    ids[split] = -1
    return Components(
        threshold=comps.threshold,
        centroid=np.vstack([cen, [x[0] for x in extra]]),
        marker_radius=np.concatenate([rm, [x[1] for x in extra]]),
        region_radius=np.concatenate([rr, [x[2] for x in extra]]),
        mean_ir=np.concatenate([k, [x[3] for x in extra]]),
        area=np.concatenate([area, [x[4] for x in extra]]).astype(np.int32),
        ids=np.concatenate([ids, np.full(len(extra), -1, np.int32)]),
        labels=comps.labels,
        rejected=comps.rejected,
    )


def _statistics(comps: Components) -> tuple:
    """Copies of the (centroid, r_m, r_r, k, area) arrays of ``comps``, for a splitter to
    overwrite split blobs' entries in."""
    return (comps.centroid.copy(), comps.marker_radius.copy(), comps.region_radius.copy(),
            comps.mean_ir.copy(), comps.area.copy())  # fmt: skip


def _blob_pixels(roi: Roi, comps: Components, i: int) -> tuple[np.ndarray, ...]:
    """Frame (u, v) (n, 2), IR (n,) and Alg. 2 weights ``P - e_d`` (n,) of blob ``i``'s
    pixels (a blob with its own label in ``labels``)."""
    idx = np.flatnonzero(comps.labels.ravel() == comps.ids[i])
    val = roi.flat_ir[idx]
    return np.stack([roi.flat_u[idx], roi.flat_v[idx]], axis=1), val, val - comps.threshold


def _centroid(X: np.ndarray, wt: np.ndarray) -> np.ndarray:
    """Weighted centroid (2,) of pixels ``X`` (n, 2) with weights ``wt`` (n,)."""
    return (wt[:, None] * X).sum(axis=0) / wt.sum()


def _part_stats(X: np.ndarray, val: np.ndarray, wt: np.ndarray) -> tuple:
    """Alg. 2 statistics (centroid, r_m, r_r, k, area) of one part of a blob: pixels ``X``
    (n, 2) frame (u, v), IR ``val`` and weights ``wt`` (n,)."""
    ch = _centroid(X, wt)
    dist = np.hypot(*(X - ch).T)
    return (ch, float(np.sum(wt * dist) / wt.sum()), float(dist.max()), float(val.mean()),
            int(X.shape[0]))  # fmt: skip


def _principal(X: np.ndarray, wt: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, ...]:
    """Weighted principal axes of pixels ``X`` (n, 2) about ``centre`` (2,): eigenvalues (2,)
    ascending, eigenvectors (2, 2) as columns, and each pixel's coordinate along the major
    (t) and the minor (n) axis, (n,) each."""
    d = X - centre
    ev, evec = np.linalg.eigh((d * wt[:, None]).T @ d / wt.sum())
    return ev, evec, d @ evec[:, 1], d @ evec[:, 0]


# Columns of the per-blob record detect keeps from one frame to the next (split_tracked,
# split_merged).
TRACK_U, TRACK_V, TRACK_AREA, TRACK_GROUP, TRACK_RR = range(5)
# Largest image motion of a blob between two frames for the splitters' matching, px.
TRACK_GATE_PX = 30.0


def match_previous(
    previous: np.ndarray, centroid: np.ndarray, gate: float
) -> tuple[np.ndarray, np.ndarray]:
    """This frame's blobs matched to the frame before's, one to one, nearest first within
    ``gate`` px.

    Parameters
    ----------
    previous : (P, 5) :func:`blob_record` of the frame before.
    centroid : (K, 2) this frame's blob centroids (u, v) px.

    Returns
    -------
    (owner, dist): for each blob the previous blob matched to it, -1 for none, (K,) int;
    and the distances (P, K) px.
    """
    pu = previous[:, TRACK_U : TRACK_V + 1]
    dist = np.hypot(*(pu[:, None, :] - centroid[None, :, :]).transpose(2, 0, 1))
    owner = np.full(len(centroid), -1)
    for j, b in nearest_first_pairs(dist, gate):
        owner[b] = j
    return owner, dist


def split_merged(
    roi: Roi,
    comps: Components,
    area_ratio: float = 1.5,
    area_max: float = 3.0,
    elongation: float = 2.0,
    separation: float = 2.0,
    iterations: int = 5,
    previous: np.ndarray | None = None,
    gate: float = TRACK_GATE_PX,
    separation_max: float = 5.0,
    streak_ratio: float = 1.0,
) -> Components:
    """Split blobs shaped like two merged markers (departure, ``split_merged``).

    Two markers closer than their diameters in the image (left and right PSI seen side-on)
    give one component and one centroid between them. A blob is split when, against the
    frame's other blobs, its area is ``area_ratio``-``area_max`` times the median, its
    weighted covariance has an eigenvalue ratio of at least ``elongation``, and a weighted
    2-means along its principal axis gives two halves of at least ``min_area`` pixels whose
    centroids are ``separation`` to ``separation_max`` median marker radii apart (two touching
    discs of radius R lie 2 R apart, about three marker radii r_m, as r_m is about two thirds
    of R; halves further apart make a line, a glint or a seam, not a pair). Each half gets its own
    Alg. 2 statistics (weights ``P - e_d``). Needs at least 3 blobs for the medians.

    Motion blur: with ``previous`` (the frame before's :func:`blob_record`), a blob matched
    one to one, nearest first within ``gate`` px, to a blob of the frame before is left
    whole when its elongation is a streak its own motion can draw. A marker moving d px per
    frame draws a streak at most d px long (the exposure is no longer than the frame
    interval), and a streak of length L, or two discs L apart, reach L further along the
    principal axis than across it. So the blob is left whole when its extent along the axis
    less its extent across is at most ``streak_ratio`` times its motion along the axis. With
    1 (an exposure as long as the frame interval) a blurred single marker is never split,
    whatever the exposure, but a pair moving along its own axis by more than its separation
    per frame is left whole too (the two PSI seen side-on, 3 px apart, moving 6 px a frame).
    With ``streak_learned`` the detect stage passes the camera's own ratio, learned from its
    isolated moving blobs (:func:`streak_ratios`, :func:`learned_streak_ratio`). A blob left
    unmatched while a blob of the frame before lies within ``gate`` px of it is left whole
    too: its motion is unknown, not zero. Its previous blob went to a nearer blob of this
    frame, which is what happens to a fast marker (a toe in swing, 13-21 px a frame on the
    simulated walks) whose neighbour has moved to where it was, and a fast marker draws the
    longest streak. A blob with no blob of the frame before within ``gate`` (it has just
    come into view) is tested as in a trial's first frame.

    Returns
    -------
    Components with the split blobs' first halves in place and second halves appended
    (their ``ids`` are -1: they have no label of their own in ``labels``).
    """
    if comps.count < 3:
        return comps
    med_a = float(np.median(comps.area))
    med_r = float(np.median(comps.marker_radius))
    cand = np.flatnonzero((comps.area >= area_ratio * med_a) & (comps.area <= area_max * med_a))
    cand = cand[comps.ids[cand] >= 0]  # parts another splitter made
    if cand.size == 0:
        return comps
    cen, rm, rr, k, area = _statistics(comps)
    motion = np.full((comps.count, 2), np.nan)  # displacement since the frame before, px
    outmatched = np.zeros(comps.count, bool)  # unmatched, with a previous blob within the gate
    if previous is not None and previous.shape[0]:
        owner, dist = match_previous(previous, cen, gate)
        seen = owner >= 0
        motion[seen] = cen[seen] - previous[owner[seen], TRACK_U : TRACK_V + 1]
        outmatched = ~seen & (dist.min(axis=0) <= gate)
    extra: list[tuple] = []
    split: list[int] = []
    for i in cand.tolist():
        X, val, wt = _blob_pixels(roi, comps, i)
        ev, evec, t, n = _principal(X, wt, cen[i])
        if ev[1] < elongation * max(ev[0], 1e-9) or outmatched[i]:
            continue
        if np.ptp(t) - np.ptp(n) <= streak_ratio * abs(float(motion[i] @ evec[:, 1])):
            continue  # one blur streak (a NaN motion compares False: no blob before near it)
        c = np.array([-math.sqrt(ev[1]), math.sqrt(ev[1])])
        for _ in range(iterations):  # weighted 2-means on the principal-axis coordinate
            g = np.abs(t[:, None] - c[None]).argmin(axis=1)
            if g.min() == g.max():
                break
            c = np.array([np.sum(wt[g == h] * t[g == h]) / np.sum(wt[g == h]) for h in (0, 1)])
        g = np.abs(t[:, None] - c[None]).argmin(axis=1)
        halves = [g == 0, g == 1]
        if min(int(h.sum()) for h in halves) < 3:
            continue
        stats = [_part_stats(X[h], val[h], wt[h]) for h in halves]
        apart = np.hypot(*(stats[0][0] - stats[1][0]))
        if not separation * med_r <= apart <= separation_max * med_r:
            continue
        cen[i], rm[i], rr[i], k[i], area[i] = stats[0]
        extra.append(stats[1])
        split.append(i)
    if not extra:
        return comps
    return _with_parts(comps, (cen, rm, rr, k, area), extra, split)


def streak_ratios(
    roi: Roi,
    comps: Components,
    previous: np.ndarray,
    owner: np.ndarray,
    min_motion: float = 4.0,
    isolation: float = 4.0,
    area_band: tuple[float, float] = (0.6, 1.5),
) -> np.ndarray:
    """How long a single marker's blur streak is against its motion, sampled on this
    frame's fastest isolated moving blob (for the blur test of :func:`split_merged`).

    A blob qualifies when it is one of Alg. 1's own (not a part a splitter made), is matched
    to a blob of the frame before (``owner``, from :func:`match_previous`), moved at least
    ``min_motion`` px, has an area within ``area_band`` times the frame's median (one
    marker, not a merged pair) and no other blob within ``isolation`` times its r_r
    (nothing merged into it). The fastest one that qualifies (the ratio is best resolved
    there) gives the sample that test compares: its extent along its principal axis less
    its extent across, over its motion along that axis, when that motion is at least
    ``min_motion`` px. That is the exposure's share of the frame interval as the
    threshold e_d sees the streak (a streak's dim ends fall below e_d). One pixel pass
    per frame. Needs at least 3 blobs for the median area.

    Returns
    -------
    (S,) ratios, S <= 1.
    """
    none = np.zeros(0)
    if comps.count < 3 or previous.shape[0] == 0:
        return none
    cen = comps.centroid
    motion = cen - previous[owner, TRACK_U : TRACK_V + 1]  # owner -1: masked below
    speed2 = np.einsum("ij,ij->i", motion, motion)
    ok = (owner >= 0) & (comps.ids >= 0) & (speed2 >= min_motion * min_motion)
    if not ok.any():
        return none
    med_a = float(np.median(comps.area))
    ok &= (comps.area >= area_band[0] * med_a) & (comps.area <= area_band[1] * med_a)
    for i in np.flatnonzero(ok)[np.argsort(-speed2[ok], kind="stable")].tolist():
        gap = np.hypot(*(cen - cen[i]).T)
        gap[i] = np.inf
        if gap.min() <= isolation * comps.region_radius[i]:
            continue
        X, _, wt = _blob_pixels(roi, comps, i)
        _, evec, t, n = _principal(X, wt, cen[i])
        along = abs(float(motion[i] @ evec[:, 1]))
        if along < min_motion:
            return none
        return np.array([(np.ptp(t) - np.ptp(n)) / along])
    return none


def learned_streak_ratio(samples: np.ndarray, quantile: float, min_samples: int) -> float:
    """The ``streak_ratio`` for :func:`split_merged`: the ``quantile`` of a camera's
    :func:`streak_ratios` samples, at most 1 (an exposure is no longer than the frame
    interval); 1 until there are ``min_samples`` of them."""
    if samples.size < min_samples:
        return 1.0
    return min(1.0, float(np.quantile(samples, quantile)))


def split_cores(
    roi: Roi,
    comps: Components,
    core_depth: float = 0.25,
    min_core_area: int = 2,
    min_fill: float = 0.25,
    erode: bool = True,
) -> Components:
    """Split blobs holding two or more separate bright cores (departure, ``split_cores``).

    A marker's image is one compact bright spot: a flat saturated plateau, or one intensity
    peak. Two markers whose images touch (heel and ankle, the two PSI seen side-on, feet
    crossing) form one component at e_d, but each keeps its own core: the pixels near the
    blob's peak level separate into two 4-connected regions, joined at e_d only through a
    neck of partly covered pixels (an intensity valley) or a diagonal touch. The core level
    of blob i is ``max_i - core_depth * (max_i - e_d)``; a blob with at least two cores of
    at least ``min_core_area`` pixels is split, every pixel going to the nearest core
    (pixels equidistant from several cores are shared equally), and each part gets its own
    Alg. 2 statistics (weights ``P - e_d`` times the share). A single marker, even motion
    blurred (a convex streak) or saturated, has one core, so it is never split; read noise
    (tens of counts) cannot open a valley ``core_depth`` of the blob's height deep.

    Parameters
    ----------
    roi : compact image the components were labelled on.
    comps : Alg. 2 components at e_d.
    core_depth : depth of the core level below the blob's peak, as a fraction of the
        peak's height above e_d.
    min_core_area : smallest core, px.
    min_fill : least ``area / (pi r_r^2)`` of a blob that is split.
    erode : also separate lobes of a flat (saturated) top by shape.

    Returns
    -------
    Components with split blobs' first parts in place and further parts appended (their
    ``ids`` are -1: they have no label of their own in ``labels``). Unchanged (the same
    object) when nothing is split.
    """
    if comps.count == 0:
        return comps
    e = comps.threshold
    labels = comps.labels
    lab_flat = labels.ravel()
    idx = np.flatnonzero(lab_flat)
    lab = lab_flat[idx]
    val = roi.flat_ir[idx]
    nlab = int(lab.max()) + 1
    peak = np.zeros(nlab)
    np.maximum.at(peak, lab, val)
    level = peak - core_depth * (peak - e)
    near_peak = np.zeros(labels.shape, np.uint8)
    near_peak.ravel()[idx[val >= level[lab]]] = 1
    pos = {int(b): i for i, b in enumerate(comps.ids.tolist()) if b >= 0}
    # Only compact groups: a few touching markers fill at least ``min_fill`` of the disc of
    # radius r_r about their centroid (two touching discs: 1/2, three in a row: 1/3); a line
    # (reflective tape, a pole's highlight) fills far less and is not split.
    fill = comps.area / (np.pi * np.maximum(comps.region_radius, 0.5) ** 2)
    fg = (labels > 0).view(np.uint8)
    # Cores at increasing scales: the near-peak pixels themselves (8-connected: split only
    # by an intensity valley), then
    # inside the blob eroded by the 4-neighbourhood (4-connected cores: cuts necks up to
    # 2 px wide), then by the 3x3 square (8-connected cores: cuts wider diagonal necks).
    # Erosion keeps a convex spot (one marker, however blurred) in one piece at every
    # scale, so a blob split at one scale is two spots joined by a neck.
    scales = [(None, 8)] + ([(_CROSS, 4), (_SQUARE, 8)] if erode else [])
    plan: dict[int, tuple[np.ndarray, list[int]]] = {}  # blob label -> (core labels, cores)
    for kernel, conn in scales:
        core = near_peak
        if kernel is not None:
            core = near_peak & cv2.erode(fg, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        ncore, clab, cstats, _ = cv2.connectedComponentsWithStats(core, connectivity=conn)
        if ncore <= 2:
            continue
        big = np.flatnonzero(cstats[1:, cv2.CC_STAT_AREA] >= min_core_area) + 1
        # The blob each core lies in (all of a core's pixels share the blob's label).
        first = np.zeros(ncore, np.intp)
        cl = clab.ravel()[idx]
        first[cl] = lab
        parent = first[big]
        for b in np.flatnonzero(np.bincount(parent, minlength=nlab) >= 2).tolist():
            if b not in plan and b in pos and fill[pos[b]] >= min_fill:
                plan[b] = (cl, big[parent == b].tolist())
    if not plan:
        return comps
    cen, rm, rr, k, area = _statistics(comps)
    extra: list[tuple] = []
    for b, (cl, cores) in plan.items():
        sel = lab == b
        X = np.stack([roi.flat_u[idx[sel]], roi.flat_v[idx[sel]]], axis=1)
        v = val[sel]
        c_of = cl[sel]
        # Distance from every pixel of the blob to the nearest pixel of each core.
        d = np.stack(
            [
                np.hypot(*(X[:, None, :] - X[c_of == c][None, :, :]).transpose(2, 0, 1)).min(axis=1)
                for c in cores
            ],
            axis=1,
        )
        share = (d <= d.min(axis=1, keepdims=True) + 1e-9).astype(np.float64)
        share /= share.sum(axis=1, keepdims=True)
        parts = []
        for j in range(len(cores)):
            wt = (v - e) * share[:, j]
            on = share[:, j] > 0
            sw = wt.sum()
            ch = _centroid(X, wt)
            dist = np.hypot(*(X[on] - ch).T)
            parts.append((ch, float(np.sum(wt[on] * dist) / sw), float(dist.max()),
                          float(np.sum(v * share[:, j]) / share[:, j].sum()),
                          round(float(share[:, j].sum()))))  # fmt: skip
        i = pos[b]
        cen[i], rm[i], rr[i], k[i], area[i] = parts[0]
        extra.extend(parts[1:])
    return _with_parts(comps, (cen, rm, rr, k, area), extra, [pos[b] for b in plan])


def blob_record(centroid: np.ndarray, comps: Components, group_area: np.ndarray) -> np.ndarray:
    """(K, 5) record of a frame's final blobs for the next frame's :func:`split_tracked`:
    u, v px (``centroid`` (K, 2), the published ones), area px, the area of the component
    the blob came from (its own area unless it is a part of a split one) and r_r px."""
    return np.column_stack(
        [centroid.reshape(-1, 2), comps.area, group_area, comps.region_radius]
    ).astype(np.float64)


def split_tracked(
    roi: Roi,
    comps: Components,
    previous: np.ndarray,
    gate: float = TRACK_GATE_PX,
    area_gain: float = 1.2,
    keep_area: float = 0.8,
    iterations: int = 4,
    match: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[Components, np.ndarray]:
    """Split a blob into the two markers the previous frame saw separately (departure,
    ``split_tracked``).

    Two markers whose images come to touch or overlap (heel and ankle, crossing feet,
    the two PSI) form one component and one centroid between them. In a single frame such
    a blob can look like one blurred marker (``split_cores`` cannot tell them apart), but
    the frame before usually held the two markers as two blobs close together. The
    previous frame's blobs are matched one to one, nearest first within ``gate`` px, to
    this frame's. A previous blob j left unmatched whose nearest blob B of this frame is
    matched to a previous blob i near j (``|p_i - p_j| <= 2 (r_r,i + r_r,j)``) has merged
    into B when B also grew: its area is at least ``area_gain`` times the larger of the
    two and at least ``keep_area`` times that of the component i came from (so a pair
    split in the frame before stays split only while its blob stays as large; a marker
    hidden beside another does not split the other). B's pixels are then split by a
    weighted 2-means seeded with the pair's offset in the previous frame, centred on B's
    centroid (the pair moves as a whole much more than its markers move apart), and each
    part gets its own Alg. 2 statistics (weights ``P - e_d``). The split is kept when both
    parts hold at least 3 pixels and their centroids lie at least half the previous
    offset apart (the two halves of one disc lie 0.85 of its radius apart).

    Parameters
    ----------
    roi : compact image the components were labelled on.
    comps : Alg. 2 components at e_d.
    previous : (P, 5) record of the previous frame's final blobs (:func:`blob_record`).
    gate : largest image motion of a blob between two frames, px.
    area_gain, keep_area : growth tests above.
    iterations : 2-means iterations.
    match : :func:`match_previous` of ``previous`` and these blobs within ``gate``, if made.

    Returns
    -------
    (Components, group_area): split blobs' first parts in place and second parts appended
    (``ids`` -1), and for each final blob the area of the component it came from.
    """
    group = comps.area.astype(np.float64)
    if comps.count == 0 or previous.shape[0] < 2:
        return comps, group
    pu = previous[:, TRACK_U : TRACK_V + 1]
    pa, pg, pr = previous[:, TRACK_AREA], previous[:, TRACK_GROUP], previous[:, TRACK_RR]
    owner, d = match if match is not None else match_previous(previous, comps.centroid, gate)
    plan: dict[int, tuple[int, int]] = {}  # blob -> (previous blob matched, previous merged)
    for j in np.setdiff1d(np.arange(previous.shape[0]), owner).tolist():
        b = int(np.argmin(d[j]))
        i = int(owner[b])
        if i < 0 or d[j, b] > gate or b in plan:
            continue
        near = np.hypot(*(pu[i] - pu[j])) <= 2.0 * (pr[i] + pr[j])
        grew = comps.area[b] >= max(area_gain * max(pa[i], pa[j]), keep_area * pg[i])
        if near and grew:
            plan[b] = (i, j)
    if not plan:
        return comps, group
    cen, rm, rr, k, area = _statistics(comps)
    extra: list[tuple] = []
    split: list[int] = []
    for b, (i, j) in plan.items():
        X, val, wt = _blob_pixels(roi, comps, b)  # Alg. 1's own blob: it has its label
        offset = pu[i] - pu[j]
        share = pa[i] / (pa[i] + pa[j])
        seeds = np.stack([cen[b] + (1.0 - share) * offset, cen[b] - share * offset])
        for _ in range(iterations):
            g = _nearest_seed(X, seeds)
            if g.min() == g.max():
                break
            seeds = np.stack([_centroid(X[g == h], wt[g == h]) for h in (0, 1)])
        g = _nearest_seed(X, seeds)
        if min(np.count_nonzero(g == 0), np.count_nonzero(g == 1)) < 3:
            continue
        stats = [_part_stats(X[g == h], val[g == h], wt[g == h]) for h in (0, 1)]
        if np.hypot(*(stats[0][0] - stats[1][0])) < 0.5 * np.hypot(*offset):
            continue
        group = np.append(group, comps.area[b])
        cen[b], rm[b], rr[b], k[b], area[b] = stats[0]
        extra.append(stats[1])
        split.append(b)
    if not extra:
        return comps, group
    return _with_parts(comps, (cen, rm, rr, k, area), extra, split), group


def _nearest_seed(X: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Index of the nearest of ``seeds`` (S, 2) for each point of ``X`` (n, 2)."""
    return np.hypot(*(X[:, None, :] - seeds[None, :, :]).transpose(2, 0, 1)).argmin(axis=1)


def nearest_first_pairs(d: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """One-to-one matching, nearest pair first, of the rows and columns of a distance
    matrix ``d`` (P, K); pairs farther than ``gate`` are never matched. Returns (row, col)
    pairs in the order matched."""
    rows, cols = np.nonzero(d <= gate)
    order = np.argsort(d[rows, cols], kind="stable")
    used_r: set[int] = set()
    used_c: set[int] = set()
    out = []
    for r, c in zip(rows[order].tolist(), cols[order].tolist(), strict=True):
        if r not in used_r and c not in used_c:
            used_r.add(r)
            used_c.add(c)
            out.append((r, c))
    return out


# --------------------------------------------------------------------------------------
# Alg. 1: adaptive threshold


@dataclass(frozen=True)
class HistoryEntry:
    """One scan-window entry: the frame's threshold e_j, and mean IR k1_j and region
    radius u1_j of its largest blob (NaN when it had none)."""

    e: float
    k1: float
    u1: float


def saturated(roi: Roi, comps: Components) -> np.ndarray:
    """(K,) bool: which components hold at least one saturated pixel (IR = 65535).

    ``comps`` are components of ``roi`` (their ``labels`` index its image).
    """
    if comps.count == 0:
        return np.zeros(0, bool)
    return np.isin(comps.ids, comps.labels[roi.image >= SATURATED])


def _largest(comps: Components) -> tuple[float, float]:
    if comps.count == 0:
        return float("nan"), float("nan")
    i = int(np.argmax(comps.marker_radius))
    return float(comps.mean_ir[i]), float(comps.region_radius[i])


def _wmean(x: np.ndarray, w: np.ndarray) -> float:
    ok = np.isfinite(x) & np.isfinite(w) & (w > 0)
    if not ok.any():
        return float("nan")
    return float(np.sum(x[ok] * w[ok]) / np.sum(w[ok]))


def _wmean_list(x: list[float], w: list[float]) -> float:
    """:func:`_wmean` of a few Python floats (the scan window) without numpy overhead."""
    num = den = 0.0
    for xi, wi in zip(x, w, strict=True):
        if math.isfinite(xi) and math.isfinite(wi) and wi > 0:
            num += xi * wi
            den += wi
    return num / den if den > 0 else float("nan")


def adaptive_threshold(
    roi: Roi,
    w: float,
    r_b: float,
    n: int,
    history: tuple[HistoryEntry, ...],
    max_iterations: int = 10,
    min_area: int = 3,
    connectivity: int = 8,
    max_region_radius: float = np.inf,
    e_cap: float = E_MAX,
    jit: bool = True,
    saturated_only: bool = False,
) -> tuple[Components, int]:
    """Alg. 1: the frame's threshold e_d, iterated until the blob count settles.

    Parameters
    ----------
    roi : compact image of S_d with ``roi.level <= min(w, e_j)``.
    w, r_b : calibration anchor threshold and blob base radius (px).
    n : expected number of markers.
    history : the last b entries H, oldest first.
    max_iterations : cap on the loop of steps 3-10.
    e_cap : highest threshold tried (departure, see ``max_threshold``).
    jit : compiled statistics in :func:`components` (identical result).
    saturated_only : step 6 raises e_d only when every blob is saturated (departure, see
        ``step6_saturated_only`` in the module doc).

    Returns
    -------
    (components at e_d, iterations): ``components.threshold`` is e_d. The loop stops at
    step 7 or 9, at the cap, or when a blob set repeats (a cycle, see the module doc).
    """
    cache: dict[float, Components] = {}

    def at(e: float) -> Components:
        e = float(min(max(e, roi.level), e_cap))
        if e not in cache:
            cache[e] = components(roi, e, min_area, connectivity, max_region_radius, jit=jit)
        return cache[e]

    counts: dict[float, int] = {}

    def count_at(e: float) -> int:
        # Step 1 compares blob counts only: areas suffice unless a blob may be too wide.
        e = float(min(max(e, roi.level), e_cap))
        if e not in counts:
            c = count_components(roi, e, min_area, connectivity, max_region_radius, jit)
            counts[e] = at(e).count if c is None else c
        return counts[e]

    # Step 1: the history threshold whose blob count is closest to n (ties: most recent).
    if history and len({h.e for h in history}) == 1:
        cur = at(history[-1].e)  # one candidate: no count to compare
    elif history:
        best_e, best_f = 0.0, -1
        for h in reversed(history):
            f = count_at(h.e)
            if best_f < 0 or abs(n - f) < abs(n - best_f):
                best_e, best_f = h.e, f
        cur = at(best_e)
    else:
        cur = at(w)
    h1 = _wmean_list([h.k1 for h in history], [h.e / w for h in history])
    h2 = _wmean_list([h.u1 for h in history], [h.e / w for h in history])
    it = 0
    visited = [(cur.count, cur.area.tobytes())]  # blob sets seen, as (count, areas)
    states = [cur]
    while it < max_iterations:
        f = cur.count
        if f == n:
            break
        it += 1
        order = np.argsort(-cur.marker_radius, kind="stable")
        if f > n:  # Step 5: raise e_d to the radius-weighted mean IR of the n largest
            top = order[:n]
            lq = cur.marker_radius[top]
            kq = cur.mean_ir[top]
            e = float(np.sum(lq * kq) / np.sum(lq)) if np.sum(lq) > 0 else float(np.mean(kq))
        else:  # Step 6: pull e_d towards the blob, history and calibration intensities
            num, den = w, 1.0
            if f > 0:
                h0 = _wmean(cur.mean_ir, cur.marker_radius / r_b)
                if np.isfinite(h0):
                    num += h0 * f / n
                    den += f / n
            if np.isfinite(h1) and np.isfinite(h2):
                num += h1 * h2 / r_b
                den += h2 / r_b
            e = num / den
            if saturated_only and e > cur.threshold and not saturated(roi, cur).all():
                e = cur.threshold  # a higher e_d would lose unsaturated markers
        nxt = at(e)
        if nxt.threshold == cur.threshold:
            break
        sig = (nxt.count, nxt.area.tobytes())
        if sig in visited:
            # The blob set of a state seen before: thresholds are nested, so equal areas
            # mean equal components, and steps 5-6 lead back to the same alternation,
            # which would run to the cap. Take the cycle's blob count closest to n, as
            # step 1 does (ties: the most recent).
            cycle = states[visited.index(sig) :]
            cur = min(reversed(cycle), key=lambda c: abs(n - c.count))
            break
        visited.append(sig)
        states.append(nxt)
        f_new = nxt.count
        cur = nxt
        if f_new in (f, n):  # Step 9
            break
    return cur, it


def initial_w(bmax: np.ndarray, fraction: float = 0.25) -> float:
    """Fallback anchor w from one frame: ``fraction`` of the way from background to saturation.

    The background level is the median of the 8x8 block maxima, which ignores the few
    blocks holding markers. The result does not depend on what bright things the frame
    holds, so an empty first frame (the subject not yet in view) or a stray lamp cannot set
    it; retro-reflective markers reach or approach saturation at clinical distances, and
    Alg. 1 raises the threshold from there as the blob count requires.
    """
    bg = float(np.median(bmax)) if bmax.size else 0.0
    return float(min(max(bg + fraction * (SATURATED - bg), 1.0), E_MAX))


# --------------------------------------------------------------------------------------
# Stage state and step


@dataclass(frozen=True)
class CameraState:
    """Alg. 1 state of one camera within one trial."""

    trial: str
    w: float
    r_b: float
    history: tuple[HistoryEntry, ...] = ()
    # The camera's markers were seen saturating (``saturating_markers``); kept from trial
    # to trial of the camera: the static pose, all markers in view, usually tells.
    markers_saturate: bool = False
    # The previous frame's final blobs (blob_record), for split_tracked and split_merged
    # (an array: left out of the dataclass's equality).
    previous: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)), compare=False)
    # The last ``streak_window`` streak_ratios samples: the camera's exposure, kept from
    # trial to trial like markers_saturate.
    streaks: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False)


@dataclass(frozen=True)
class DetectState:
    """Per-camera Alg. 1 state (``cameras`` is never mutated, only replaced)."""

    params: Mapping[str, Any]
    cameras: Mapping[str, CameraState] = field(default_factory=dict)
    frames: int = 0


@dataclass(frozen=True)
class Detection:
    """Result of :func:`detect_frame` for one frame."""

    blobs: Components
    centroid: np.ndarray  # (K, 2) final (possibly refined) centroids
    threshold: float
    iterations: int
    status: str
    history_entry: HistoryEntry
    candidates: int  # blobs before the max_blobs cut
    saturated_blobs: int = 0  # blobs holding a saturated pixel (counted only when needed)
    record: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))  # blob_record
    streaks: np.ndarray = field(default_factory=lambda: np.zeros(0))  # streak_ratios samples


def detect_frame(
    ir: np.ndarray,
    w: float,
    r_b: float,
    history: tuple[HistoryEntry, ...],
    params: Mapping[str, Any],
    markers_saturate: bool = False,
    previous: np.ndarray | None = None,
    streak_ratio: float = 1.0,
    sample_streaks: bool = False,
) -> Detection:
    """Alg. 1 + Alg. 2 on one IR frame (pure).

    Parameters
    ----------
    ir : (H, W) uint16 cleaned IR frame S_d.
    w, r_b : anchor threshold and blob base radius.
    history : Alg. 1 scan window, oldest first.
    params : resolved :data:`PARAMS`.
    markers_saturate : the camera's markers were seen saturating: step 6 is the printed one
        even with ``step6_saturated_only``.
    previous : (P, 5) :func:`blob_record` of the camera's previous frame (``split_tracked``).
    streak_ratio : ``split_merged``'s blur test (:func:`learned_streak_ratio`).
    sample_streaks : measure :func:`streak_ratios` on Alg. 1's blobs (``Detection.streaks``).
    """
    previous = np.zeros((0, 5)) if previous is None else previous
    p = params
    jit = p["jit"]
    bm = block_max(ir, p["block"], jit)
    if p["method"] == "static":
        e_static = p["static_threshold"] or w
        floor = e_static
    else:
        floor = min([w, *(h.e for h in history)])
    e_low, level = floor, floor
    if p["refine"]:
        bg = float(np.median(bm)) if bm.size else 0.0
        e_low = bg + p["refine_fraction"] * max(floor - bg, 0.0)
        level = min(e_low, floor)
    roi = compact_roi(ir, level, p["block"], bm, jit=jit)
    saturated_only = p["step6_saturated_only"] and not markers_saturate
    if p["method"] == "static":
        comps = components(
            roi, e_static, p["min_area"], p["connectivity"], p["max_region_radius"], jit=jit
        )
        iterations = 0
    else:
        comps, iterations = adaptive_threshold(
            roi,
            w,
            r_b,
            p["n"],
            history,
            p["max_iterations"],
            p["min_area"],
            p["connectivity"],
            p["max_region_radius"],
            max(p["max_threshold"], roi.level),
            jit,
            saturated_only,
        )
    # Alg. 1's history entry is of the blobs it settled on, before any split.
    k1, u1 = _largest(comps)
    n_saturated = int(saturated(roi, comps).sum()) if saturated_only else 0
    centroid = comps.centroid
    if p["refine"] and comps.count:
        centroid = refine_centroids(roi, comps, e_low, p["connectivity"])
    group = comps.area.astype(np.float64)
    # Alg. 1's blobs matched to the frame before's, shared by split_tracked and the streaks.
    match = None
    if previous.shape[0] and (p["split_tracked"] or sample_streaks):
        match = match_previous(previous, comps.centroid, TRACK_GATE_PX)
    streaks = np.zeros(0)
    if sample_streaks and match is not None:
        streaks = streak_ratios(roi, comps, previous, match[0])
    splitters = []
    if p["split_tracked"]:

        def tracked(c: Components) -> Components:
            nonlocal group
            c, group = split_tracked(roi, c, previous, match=match)
            return c

        splitters.append(tracked)
    if p["split_cores"]:
        splitters.append(
            lambda c: split_cores(roi, c, p["core_depth"], p["min_core_area"], p["split_min_fill"])
        )
    if p["split_merged"]:
        splitters.append(
            lambda c: split_merged(roi, c, previous=previous, streak_ratio=streak_ratio)
        )
    for split_fn in splitters:
        if not comps.count:
            break
        n0, before = comps.count, comps.centroid
        comps = split_fn(comps)
        split = (comps.centroid[:n0] != before).any(axis=1)  # first parts of split blobs
        # Split blobs take their parts' centroids; the others keep the (refined) ones.
        centroid = np.vstack([np.where(split[:, None], comps.centroid[:n0], centroid),
                              comps.centroid[n0:]])  # fmt: skip
    entry = HistoryEntry(comps.threshold, k1, u1)
    status = "ok"
    if roi.image.size == 0 or comps.count == 0:
        status = "empty"
    if comps.count > p["max_blobs"]:
        status = "too-many"
    record = np.zeros((0, 5))
    if p["split_tracked"] or p["split_merged"]:  # the next frame's splits need it
        # Parts a later splitter made count as components of their own.
        group = np.concatenate([group, comps.area[group.size :]])
        record = blob_record(centroid, comps, group)
    return Detection(
        comps,
        centroid,
        comps.threshold,
        iterations,
        status,
        entry,
        comps.count,
        n_saturated,
        record,
        streaks,
    )


def _anchor(ir: np.ndarray, cal: CalibrationRecord | None, p: Mapping[str, Any]) -> tuple:
    """(w, r_b) from the calibration record, the declared defaults, or the image."""
    w = cal.w if cal is not None and np.isfinite(cal.w) and cal.w > 0 else p["default_w"]
    if not w:
        w = initial_w(block_max(ir, p["block"], p["jit"]))
    r_b = cal.r_b if cal is not None and np.isfinite(cal.r_b) and cal.r_b > 0 else p["default_r_b"]
    if not r_b:
        roi = compact_roi(ir, w, p["block"], jit=p["jit"])
        c = components(
            roi, w, p["min_area"], p["connectivity"], p["max_region_radius"], jit=p["jit"]
        )
        r_b = float(np.median(c.region_radius)) if c.count else 0.0
    return float(min(w, E_MAX)), float(r_b)


def init(params: dict[str, Any]) -> DetectState:
    return DetectState(params=dict(params))


def step(state: DetectState, inputs: Inputs) -> tuple[DetectState, list]:
    """Detect blobs in one ``clean`` frame; publish ``blobs``."""
    frame = inputs["clean"]
    if not isinstance(frame, CleanFrame):
        raise StageError("detect", f"input clean is a {type(frame).__name__}, not a CleanFrame")
    cal = inputs.get("calibration")
    cal = cal if isinstance(cal, CalibrationRecord) else None
    p = state.params
    cam, trial = frame.header.camera, frame.header.trial
    cs = state.cameras.get(cam)
    ir = np.asarray(frame.ir)
    if cs is None or cs.trial != trial:
        w, r_b = _anchor(ir, cal, p)
        cs = CameraState(
            trial,
            w,
            r_b,
            markers_saturate=cs is not None and cs.markers_saturate,
            streaks=cs.streaks if cs is not None else np.zeros(0),
        )
    elif cs.r_b <= 0:  # no blob seen yet to derive r_b from
        cs = replace(cs, r_b=_anchor(ir, cal, p)[1])
    learn = p["streak_learned"] and p["split_merged"]
    ratio = 1.0
    if learn:
        ratio = learned_streak_ratio(cs.streaks, p["streak_quantile"], p["streak_min_samples"])
    det = detect_frame(
        ir,
        cs.w,
        cs.r_b if cs.r_b > 0 else 2.0,
        cs.history,
        p,
        cs.markers_saturate,
        cs.previous,
        ratio,
        learn and cs.streaks.size < p["streak_window"] and state.frames % p["streak_every"] == 0,
    )
    history = (*cs.history, det.history_entry)[-p["b"] :]
    cams = dict(state.cameras)
    seen = cs.markers_saturate or det.saturated_blobs >= p["saturating_markers"]
    streaks = cs.streaks
    if det.streaks.size:
        streaks = np.concatenate([streaks, det.streaks])[-p["streak_window"] :]
    cams[cam] = replace(
        cs, history=history, markers_saturate=seen, previous=det.record, streaks=streaks
    )
    c = det.blobs
    keep = np.argsort(-c.area, kind="stable")[: p["max_blobs"]]
    keep.sort()
    out = Blobs.follow(
        frame.header,
        centroid=det.centroid[keep],
        marker_radius=c.marker_radius[keep],
        region_radius=c.region_radius[keep],
        mean_ir=c.mean_ir[keep],
        area=c.area[keep],
        threshold=det.threshold,
        iterations=det.iterations,
        method=p["method"],
        status=det.status,
        rejected=c.rejected,
    )
    return DetectState(p, cams, state.frames + 1), [out]


SPEC = StageSpec(
    name="detect",
    params=PARAMS,
    init=init,
    step=step,
    stateful=True,
    # loads the compiled kernels before the stage reports ready
    warmup=stage_warmup("detect"),
    doc=__doc__ or "",
)
