"""Stage ``clean``: invalid pixels and interfering reflectors (paper section III-A).

Input: ``raw`` frames; side input ``calibration`` (for static and walk trials). Output:
``clean`` (:class:`CleanFrame`): IR with interference zeroed, depth with invalid pixels set
to 0, the mask (1 = masked interferer) and the session's camera intrinsics copied from the
calibration record (so that locate, which has no calibration input, can use them).

Array conventions: images (row, col); pixels (u, v) = (column, row); depth mm, 0 = invalid;
IR 0..65535.

The paper leaves the interference model unspecified [A-0]. Our reading (Rec. of
``../shared/reference/algorithms.md`` section 3.0, with departures explained):

- **Invalid pixels.** Depth outside ``[min_depth, max_depth]`` becomes 0. IR is kept
  everywhere: a marker's IR is valid exactly where its depth is not.
- **What counts as interference.** A bright component (IR above the anchor threshold ``w``
  of the calibration record, or a value derived from the first frame) whose centroid stays
  within ``still_tol`` px for ``still_frames`` frames (gaps of up to ``still_gap`` frames
  allowed, for someone walking past it). Stillness is the only cue that tells a stray
  reflector from a body marker without labels. Body markers of a walking subject move: a
  foot in stance rolls over heel and toe, so its markers drift by more than ``still_tol``
  (0.2 px, against the hundredths of a pixel of noise jitter of a fixed reflector) well
  within ``still_frames`` (1 s). A *standing* subject's markers do not, so new interferers are
  not learned in static trials (``learn_static``), only in calibration frames (the empty
  walkway, when the graph feeds them to this stage; nothing is published for them) and walk
  trials. Tracks persist across trials of a camera: the scene does not change between
  them. The calibration record's floor markers are seeded as interferers
  (``mask_floor_markers``): they are known, still and not body markers, and would otherwise
  count against Alg. 1's n.
- **Tracking.** A constant-position Kalman filter (filterpy) on each region's box
  (centre u, v and size w, h, px). A frame's measurement is a component near the predicted
  centre of similar size; a track with no measurement for ``miss_frames`` frames is
  dropped (the reflector was removed); until then its prediction stays masked (the subject
  walking in front of it).
- **Levels.** Calibration frames come before the calibration record, so interferers are
  learned there at the first frame's level and the later trials run at the record's w.
  A thin highlight (a chrome pole) breaks into other pieces at another level, so each
  track keeps the level it was learned at and, finding no component at the trial's level,
  is matched at that one. A component at the trial's level that shares pixels only with
  components so matched (components above two levels nest) and reaches no further than
  their boxes is that interferer: it lifts nothing and is masked with them.
- **Masking and lifting.** Each kept track's box, dilated by ``box_margin``, is zeroed in
  IR and set to 1 in ``mask``. A bright component that overlaps a box but is not that
  track's measurement (a moving marker passing over the reflector) lifts the box for this
  frame, so that the marker is not cut; the paper lifts on the tracked marker's prediction,
  which this stage, upstream of labelling, does not have. A component inside the box of a
  bar (a long thin reflector: one side at least three times the other) is a piece of it,
  left when the passing body hides the rest, and lifts nothing.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update
from gaitflow.schemas import CalibrationRecord, CleanFrame, RawFrame
from gaitflow.stages.base import Inputs, StageSpec
from gaitflow.stages.detect import E_MAX, block_max, compact_roi, components, initial_w
from gaitflow.stages.warmup import stage_warmup

from gaitflow.errors import ParameterError, StageError
from gaitflow.markers import trial_kind
from gaitflow.params import Param, ParamSet

PARAMS = ParamSet(
    "clean",
    (
        Param("min_depth", float, 300.0, "mm", "depths below this are invalid", low=0.0),
        Param("max_depth", float, 8000.0, "mm", "depths above this are invalid", low=1.0),
        Param(
            "bright_threshold",
            float,
            0.0,
            "IR",
            "bright-component level; 0 = the calibration w, else derived from the first frame",
            low=0.0,
            high=E_MAX,
        ),
        Param("min_area", int, 2, "px", "smallest bright component considered", low=1),
        Param(
            "still_frames",
            int,
            30,
            "frames",
            "a component still this long becomes an interferer",
            low=2,
        ),
        Param("still_tol", float, 0.2, "px", "centroid motion that still counts as still", low=0),
        Param(
            "still_gap",
            int,
            5,
            "frames",
            "a still candidate survives this many frames unseen (someone walks past it)",
            low=0,
        ),
        Param("miss_frames", int, 45, "frames", "drop a track unseen this long", low=1),
        Param("box_margin", int, 2, "px", "dilation of a masked box", low=0),
        Param("kf_q", float, 0.01, "px^2", "KF process noise per frame (constant position)"),
        Param("kf_r", float, 0.25, "px^2", "KF measurement noise of a box coordinate"),
        Param("learn_static", bool, False, "-", "learn new interferers in static trials"),
        Param("mask_floor_markers", bool, True, "-", "mask the calibration floor markers"),
        Param("floor_marker_radius", float, 4.0, "px", "box half-size of a seeded floor marker"),
        Param("max_tracks", int, 32, "tracks", "most interferers tracked at once", low=0),
        Param("max_candidates", int, 256, "-", "most still-candidates followed at once", low=1),
    ),
)


@dataclass(frozen=True)
class Candidate:
    """A bright component seen still at ``anchor`` (u, v) px for ``count`` frames."""

    anchor: tuple[float, float]
    count: int
    radius: float
    unseen: int = 0


@dataclass(frozen=True)
class Track:
    """An interferer: constant-position KF state x = (u, v, w, h) px and covariance P."""

    x: np.ndarray = field(repr=False)  # (4,)
    P: np.ndarray = field(repr=False)  # (4, 4)
    misses: int = 0
    source: str = "still"  # still | floor
    # The bright level it was learned at (0 = none: a seeded floor marker). A long
    # reflector breaks into other pieces at another level, so a track that finds no
    # component at the trial's level is matched at this one.
    level: float = 0.0

    @property
    def centre(self) -> np.ndarray:
        return self.x[:2]


@dataclass(frozen=True)
class CameraClean:
    """Clean state of one camera; tracks persist across trials."""

    trial: str = ""
    level: float = 0.0  # bright threshold in use
    candidates: tuple[Candidate, ...] = ()
    tracks: tuple[Track, ...] = ()
    seeded: int = -1  # capture_ns of the calibration record whose floor markers were seeded


@dataclass(frozen=True)
class CleanState:
    params: Mapping[str, Any]
    cameras: Mapping[str, CameraClean] = field(default_factory=dict)
    learned: int = 0  # interferers promoted so far (all cameras)


@dataclass(frozen=True)
class CleanResult:
    ir: np.ndarray  # (H, W) uint16
    depth: np.ndarray  # (H, W) uint16
    mask: np.ndarray  # (H, W) uint8
    state: CameraClean
    lifted: int
    promoted: int


def _box(u: float, v: float, r: float) -> np.ndarray:
    s = 2.0 * r + 1.0
    return np.array([u, v, s, s])


def _new_track(box: np.ndarray, p: Mapping[str, Any], source: str, level: float = 0.0) -> Track:
    return Track(box.astype(np.float64), np.eye(4) * p["kf_r"], 0, source, level)


def _boxes(comps: Any) -> tuple[np.ndarray, np.ndarray]:
    """(inclusive u0, v0, u1, v1 boxes; centre u, v and size w, h boxes) of components."""
    bb = comps.box if comps.box is not None else np.zeros((0, 4))
    centre = (bb[:, :2] + bb[:, 2:]) / 2
    return bb, np.concatenate([centre, bb[:, 2:] - bb[:, :2] + 1], axis=1)


def _is_bar(box: np.ndarray) -> bool:
    """A centre/size box one side of which is at least three times the other."""
    return bool(max(box[2], box[3]) >= 3.0 * min(box[2], box[3]))


def _inside_any(bb: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(K,) bool: inclusive pixel box ``bb`` (K, 4) lies within one of the centre/size
    ``boxes`` (M, 4), with half a pixel's slack (a box's pixels reach its edges)."""
    lo, hi = boxes[:, :2] - boxes[:, 2:] / 2, boxes[:, :2] + boxes[:, 2:] / 2
    within = (bb[:, None, :2] >= lo[None]) & (bb[:, None, 2:] <= hi[None])
    return within.all(axis=2).any(axis=1)


def clean_frame(
    ir: np.ndarray,
    depth: np.ndarray,
    cs: CameraClean,
    learn: bool,
    p: Mapping[str, Any],
) -> CleanResult:
    """Clean one frame (pure).

    Parameters
    ----------
    ir, depth : (H, W) uint16 raw IR and depth.
    cs : this camera's state, with ``cs.level`` set.
    learn : may still components be promoted to interferers in this frame.
    p : resolved :data:`PARAMS`.
    """
    d = depth.copy()
    d[(d < p["min_depth"]) | (d > p["max_depth"])] = 0
    # Tracks learned at another level (the empty walkway's, before the calibration record
    # gave w) that find no component here are matched with the components at that level.
    levels = {t.level for t in cs.tracks if t.level and t.level != cs.level}
    roi = compact_roi(ir, min(levels | {cs.level}), 8)
    comps = components(roi, cs.level, p["min_area"], 8, extent=True)
    cen = comps.centroid
    rad = comps.region_radius
    # Boxes (centre u, v, size w, h) of the components: a thin bar gets a thin box.
    bb, boxes = _boxes(comps)
    Fm, Hm = np.eye(4), np.eye(4)
    Q, R = np.eye(4) * p["kf_q"], np.eye(4) * p["kf_r"]
    used = np.zeros(comps.count, dtype=bool)
    # Per other level, made when first needed: components, their boxes, taken, matched.
    other: dict[float, tuple[Any, np.ndarray, np.ndarray, list[int]]] = {}
    tracks: list[Track] = []

    def nearest(x: np.ndarray, t_boxes: np.ndarray, t_used: np.ndarray) -> int:
        if not len(t_boxes):
            return -1
        dist = np.hypot(t_boxes[:, 0] - x[0], t_boxes[:, 1] - x[1])
        similar = (t_boxes[:, 2] <= 2.0 * x[2] + 2.0) & (t_boxes[:, 3] <= 2.0 * x[3] + 2.0)
        ok = (dist <= max(2.0 * p["still_tol"], 1.0)) & similar & ~t_used
        return int(np.argmin(np.where(ok, dist, np.inf))) if ok.any() else -1

    # Tracks first: predict, then take the nearest still component of similar size, at this
    # level or else at the level the track was learned at.
    for t in cs.tracks:
        x, P = kf_predict(t.x, t.P, Fm, Q)
        t_boxes, t_used = boxes, used
        match = nearest(x, t_boxes, t_used)
        if match < 0 and t.level in levels:
            if t.level not in other:
                oc = components(roi, t.level, p["min_area"], 8, extent=True)
                ob = _boxes(oc)[1]
                other[t.level] = (oc, ob, np.zeros(len(ob), dtype=bool), [])
            _, t_boxes, t_used, matched = other[t.level]
            match = nearest(x, t_boxes, t_used)
            if match >= 0:
                matched.append(match)
        if match >= 0:
            t_used[match] = True
            x, P = kf_update(x, P, t_boxes[match], R, Hm)
            tracks.append(Track(np.asarray(x, dtype=np.float64), P, 0, t.source, t.level))
        elif t.misses + 1 < p["miss_frames"]:
            tracks.append(
                Track(np.asarray(x, dtype=np.float64), P, t.misses + 1, t.source, t.level)
            )
    # A component at this level is an interferer when it shares pixels with components
    # matched at another level, with no other component there, and reaches no further than
    # their boxes (components above two levels nest: the higher one's lie inside the lower
    # one's). So a pole's pieces joined into one, or a reflector's smaller core, lift no
    # box. A marker that touches the reflector at this level still does: at the track's
    # level it is a component of its own (or has changed the reflector's, which then
    # matches no track), or, too dim to show there, it sticks out of the boxes.
    # There as here, a component inside a bar's box is a piece of the bar.
    bars = np.array([t.x for t in tracks if _is_bar(t.x)]).reshape(-1, 4)
    holds_other = np.zeros(comps.count, dtype=bool)
    reach = np.tile([np.inf, np.inf, -np.inf, -np.inf], (comps.count, 1))  # held boxes' hull
    for oc, _, _, idx in other.values():
        if comps.count and idx:
            hit = np.zeros(len(oc.ids), dtype=bool)
            hit[idx] = True
            hit |= _inside_any(oc.box, bars)
            holds_other |= np.isin(comps.ids, comps.labels[np.isin(oc.labels, oc.ids[~hit])])
            for j in np.flatnonzero(hit):
                held = np.isin(comps.ids, comps.labels[oc.labels == oc.ids[j]])
                reach[held, :2] = np.minimum(reach[held, :2], oc.box[j, :2])
                reach[held, 2:] = np.maximum(reach[held, 2:], oc.box[j, 2:])
    m = p["box_margin"]
    explained = ~holds_other & (bb[:, :2] >= reach[:, :2] - m).all(1)
    explained &= (bb[:, 2:] <= reach[:, 2:] + m).all(1)
    used |= explained
    # Still candidates: components not explained by a track.
    cands: list[Candidate] = []
    promoted = 0
    prev = cs.candidates
    prev_anchor = np.array([c.anchor for c in prev]).reshape(-1, 2)
    taken = np.zeros(len(prev), dtype=bool)
    for i in np.flatnonzero(~used):
        count, anchor = 1, (float(cen[i, 0]), float(cen[i, 1]))
        if len(prev):
            dist = np.hypot(prev_anchor[:, 0] - cen[i, 0], prev_anchor[:, 1] - cen[i, 1])
            dist[taken] = np.inf
            j = int(np.argmin(dist))
            if dist[j] <= p["still_tol"]:
                taken[j] = True
                count, anchor = prev[j].count + 1, prev[j].anchor
        if learn and count >= p["still_frames"] and len(tracks) < p["max_tracks"]:
            tracks.append(_new_track(boxes[i], p, "still", cs.level))
            used[i] = True
            promoted += 1
        elif len(cands) < p["max_candidates"]:
            cands.append(Candidate(anchor, count, float(rad[i])))
    for j in np.flatnonzero(~taken):  # unseen this frame: keep through a short gap
        c = prev[j]
        if c.unseen < p["still_gap"] and len(cands) < p["max_candidates"]:
            cands.append(Candidate(c.anchor, c.count, c.radius, c.unseen + 1))
    # Mask every track's box unless a moving (unexplained) component overlaps it.
    out_ir = ir.copy()
    mask = np.zeros(ir.shape, dtype=np.uint8)
    H, W = ir.shape
    moving = bb[~used]
    lifted = 0
    # The components explained at another level are masked too: the joined stretches of a
    # pole lie between its pieces' boxes.
    for k, box in enumerate([t.x for t in tracks] + list(boxes[explained])):
        u, v, bw, bh = box
        c0, c1 = int(np.floor(u - bw / 2 - m)), int(np.ceil(u + bw / 2 + m)) + 1
        r0, r1 = int(np.floor(v - bh / 2 - m)), int(np.ceil(v + bh / 2 + m)) + 1
        hit = (moving[:, 2] >= c0) & (moving[:, 0] < c1) & (moving[:, 3] >= r0)
        hit &= moving[:, 1] < r1
        # A component inside a bar's box is a piece of the bar: a long thin reflector (a
        # chrome pole's highlight) half hidden by the passing body shows as short pieces
        # that match no track, and they lifted the whole box, to be taken for markers. Not
        # for a compact box, where a marker passing in front may lie inside it.
        if _is_bar(box):
            hit &= ~_inside_any(moving, box[None])
        if hit.any():
            lifted += k < len(tracks)
            continue
        c0, c1, r0, r1 = max(c0, 0), min(c1, W), max(r0, 0), min(r1, H)
        if c0 < c1 and r0 < r1:
            out_ir[r0:r1, c0:c1] = 0
            mask[r0:r1, c0:c1] = 1
    new = replace(cs, candidates=tuple(cands), tracks=tuple(tracks))
    return CleanResult(out_ir, d, mask, new, lifted, promoted)


def _seed_floor(cs: CameraClean, cal: CalibrationRecord, p: Mapping[str, Any]) -> CameraClean:
    """Add the calibration record's floor markers as interferer tracks (once per record)."""
    px = np.asarray(cal.floor_pixels, dtype=np.float64).reshape(-1, 2)
    tracks = [t for t in cs.tracks if t.source != "floor"]
    for u, v in px:
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        near = [t for t in tracks if np.hypot(*(t.centre - (u, v))) < p["floor_marker_radius"]]
        if not near and len(tracks) < p["max_tracks"]:
            tracks.append(_new_track(_box(u, v, p["floor_marker_radius"]), p, "floor"))
    return replace(cs, tracks=tuple(tracks), seeded=cal.header.capture_ns)


def init(params: dict[str, Any]) -> CleanState:
    if params["min_depth"] >= params["max_depth"]:
        raise ParameterError(
            "clean",
            "min_depth",
            params["min_depth"],
            f"must be below max_depth={params['max_depth']}",
        )
    return CleanState(dict(params))


def step(state: CleanState, inputs: Inputs) -> tuple[CleanState, list]:
    """Clean one raw frame; publish ``clean`` (nothing for calibration frames)."""
    raw = inputs["raw"]
    if not isinstance(raw, RawFrame):
        raise StageError("clean", f"input raw is a {type(raw).__name__}, not a RawFrame")
    cal = inputs.get("calibration")
    cal = cal if isinstance(cal, CalibrationRecord) else None
    p = state.params
    h = raw.header
    kind = trial_kind(h.trial)
    ir, depth = np.asarray(raw.ir), np.asarray(raw.depth)
    cs = state.cameras.get(h.camera, CameraClean())
    if cs.trial != h.trial:
        level = p["bright_threshold"]
        if not level and cal is not None and np.isfinite(cal.w) and cal.w > 0:
            level = float(cal.w)
        if not level:
            level = cs.level or initial_w(block_max(ir, 8))
        # Candidates restart with the trial: frames of different trials are not contiguous.
        cs = replace(cs, trial=h.trial, level=float(level), candidates=())
    if cal is not None and p["mask_floor_markers"] and cs.seeded != cal.header.capture_ns:
        cs = _seed_floor(cs, cal, p)
    learn = kind != "static" or p["learn_static"]
    res = clean_frame(ir, depth, cs, learn, p)
    cams = dict(state.cameras)
    cams[h.camera] = res.state
    new = CleanState(p, cams, state.learned + res.promoted)
    if kind == "calibration":
        return new, []
    doc = dict(cal.camera) if cal is not None and cal.camera else {}
    out = CleanFrame.follow(
        h,
        ir=res.ir,
        depth=res.depth,
        mask=res.mask,
        interferers=len(res.state.tracks) - res.lifted,
        camera=doc,
    )
    return new, [out]


SPEC = StageSpec(
    name="clean",
    params=PARAMS,
    init=init,
    step=step,
    stateful=True,
    # loads the compiled kernels before the stage reports ready
    warmup=stage_warmup("clean"),
    doc=__doc__ or "",
)
