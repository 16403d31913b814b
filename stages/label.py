"""Stage ``label``: marker labelling (Alg. 5) in 3D, in the floor frame of the calibration.

Input: ``markers`` (:class:`Markers3D`) of the walking trials, with the ``calibration``
record and the ``model`` (:class:`SubjectModel`) as side inputs. Output: ``labelled``
(:class:`LabelledMarkers`), the 20 named markers, each position taken under the marker's
own Alg. 3 cluster mode (``gaitflow.markers.cluster_mode``).

Per frame (Alg. 5, read in 3D; see docs/readme/labelling.md):

1. every blob is mapped to the floor frame: a along the walking line (toward +u), e
   horizontal away from the camera, h height above the floor plane (mm);
2. the shoulder (SHO) is predicted by a constant-velocity Kalman filter (filterpy,
   position + velocity in 3D) and taken as the blob in the shoulder height band nearest the
   prediction; without one the prediction stands in for up to ``max_missed`` frames (steps
   1-3). The first shoulder is the shoulder-height blob with the most body markers below it;
3. the walking direction is the sign of the shoulder's velocity along a (hysteresis:
   ``flip_frames`` consecutive frames against the current direction); the side facing the
   camera follows from it (walking toward +u shows the right side). On a change of
   direction every track is reset: the return pass shows the other side (the L/R swap);
4. upper body (steps 5-6): near PSI, HIP, ASI and far PSI, ASI are assigned jointly
   (Hungarian, scipy) to the pelvis-band blobs, each against its track prediction or, when
   untracked, the subject model's layout placed at the shoulder; then the order
   PSI < HIP < ASI (near) and PSI < ASI (far) along the walking direction is enforced (a
   label that breaks it is dropped, never swapped);
5. lower body (steps 7-10): every assignment of the blobs below the hip to the near foot
   (TIB, ANK, HEE, TOE) is scored exhaustively (vectorised) by the model's rigid distances
   (TIB-ANK, ANK-HEE, ANK-TOE, HEE-TOE; TIB-HEE and TIB-TOE loosely), the triangle foot
   model (ANK inside triangle TIB-TOE-HEE in the sagittal plane) and the tracks; the best
   ones are completed with the far heel and toe (rigid HEE-TOE, deeper than the near foot)
   and then with the limb (THI, KNE: distances to HIP, TIB, ANK);
6. a label whose blob breaks its gates (track, rigid distances) is left NaN rather than
   guessed: an occluded marker gives a gap, not a wrong label. Blobs left over (stray
   reflectors, far-side leg markers) stay unlabelled.

Far-side SHO, HIP, THI, KNE, TIB and ANK face away from the camera in a side view and are
never assigned. Conventions: (20, ...) arrays follow ``gaitflow.markers.MARKER_NAMES``;
camera space X right, Y down, Z forward, mm; pixels (u, v); NaN = missing.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np
from filterpy.kalman import KalmanFilter
from gaitflow.schemas import CalibrationRecord, LabelledMarkers, Markers3D, Message, SubjectModel
from gaitflow.stages.base import StageSpec
from gaitflow.stages.model import (
    TEMPLATE_SHO_HEIGHT,
    FloorFrame,
    template_layout,
)
from scipy.optimize import linear_sum_assignment

from gaitflow.errors import StageError
from gaitflow.markers import CLUSTER_MODES, MARKER_INDEX, MARKER_NAMES, SITES, cluster_mode
from gaitflow.params import Param, ParamSet

NAME = "label"

PARAMS = ParamSet(
    NAME,
    (
        Param("fps", float, 30.0, "Hz", "nominal frame rate (frame index -> time)", 1.0, 1000.0),
        Param(
            "max_missed",
            int,
            10,
            "frames",
            "frames the shoulder may be predicted without a detection before the track ends",
            0,
            1000,
        ),
        Param("sho_gate_mm", float, 150.0, "mm", "shoulder gate around the prediction", 10.0),
        Param(
            "dir_speed",
            float,
            250.0,
            "mm/s",
            "shoulder speed along the walking line that decides the direction",
            0.0,
        ),
        Param("flip_frames", int, 3, "frames", "frames against the direction before it flips", 1),
        Param("track_age", int, 3, "frames", "frames a marker track predicts after a miss", 0),
        Param("gate", float, 4.0, "sigma", "per-label acceptance gate", 1.0, 100.0),
        Param(
            "camera_height_mm",
            float,
            800.0,
            "mm",
            "camera height assumed when the calibration has no floor plane",
            100.0,
            5000.0,
        ),
    ),
)

NEAR_FOOT = ("TIB", "ANK", "HEE", "TOE")
PELVIS = (("near", "PSI"), ("near", "HIP"), ("near", "ASI"), ("far", "PSI"), ("far", "ASI"))
MISS_COST = 9.0  # a missing label costs as much as a 3-sigma fit


# --- the subject geometry label uses --------------------------------------------------


@dataclass(frozen=True)
class Geometry:
    """Site layout and distances from the subject model (template where unmeasured)."""

    layout: np.ndarray  # (10, 3) [forward from pelvis centre, height, lateral], mm
    dist: np.ndarray  # (10, 10) near-side distances between sites, mm
    sho_h: float

    @classmethod
    def from_model(cls, model: SubjectModel | None) -> Geometry:
        """Geometry of a subject model; the scaled template if there is none."""
        layout = template_layout()
        sho_h = TEMPLATE_SHO_HEIGHT
        extra = dict(model.extra) if model is not None else {}
        if "sho_height_mm" in extra and np.isfinite(extra["sho_height_mm"]):
            sho_h = float(extra["sho_height_mm"])
            layout = template_layout(sho_h / TEMPLATE_SHO_HEIGHT)
        lay = extra.get("layout", {})
        for j, s in enumerate(SITES):
            v = lay.get(s)
            if v is not None and len(v) == 3 and np.isfinite(v).all():
                layout[j] = v
        dist = np.linalg.norm(layout[:, None, :] - layout[None, :, :], axis=2)
        sd = extra.get("site_distances")
        if sd is not None:
            sd = np.asarray(sd, dtype=np.float64)
            if sd.shape == (10, 10):
                dist = np.where(np.isfinite(sd) & (sd > 0), sd, dist)
        return cls(layout, dist, sho_h)

    def d(self, a: str, b: str) -> float:
        return float(self.dist[SITES.index(a), SITES.index(b)])

    def rel_sho(self, side: str, site: str) -> np.ndarray:
        """Standing offset (forward, e, h) of a site from the near shoulder.

        ``side`` is "near" or "far"; e grows away from the camera.
        """
        s = self.layout[SITES.index("SHO")]
        q = self.layout[SITES.index(site)]
        lat = -q[2] if side == "near" else q[2]
        return np.array([q[0] - s[0], s[2] + lat, q[1]])


# --- the shoulder Kalman filter ----------------------------------------------------------


def _kf(x: np.ndarray, P: np.ndarray, dt: float) -> KalmanFilter:
    """Constant-velocity KF over (a, e, h, va, ve, vh), mm and mm/s."""
    kf = KalmanFilter(dim_x=6, dim_z=3)
    kf.F = np.eye(6)
    kf.F[:3, 3:] = dt * np.eye(3)
    kf.H = np.hstack([np.eye(3), np.zeros((3, 3))])
    kf.R = np.eye(3) * 10.0**2
    q = 4000.0**2  # white acceleration (mm/s^2)^2: gait sways the trunk ~ 1-4 m/s^2
    g = np.array([0.5 * dt * dt, dt])
    Q1 = np.outer(g, g) * q
    kf.Q = np.zeros((6, 6))
    for i in range(3):
        kf.Q[np.ix_([i, i + 3], [i, i + 3])] = Q1
    kf.x = x.copy()
    kf.P = P.copy()
    return kf


# --- state -------------------------------------------------------------------------------


@dataclass(frozen=True)
class LabelState:
    """Explicit state of the label stage (one camera, one trial at a time).

    ``last``/``vel``/``seen`` are per-marker tracks in floor coordinates (20, 3) mm, mm per
    frame, and the frame index each marker was last labelled (-10**9 = never).
    """

    params: dict[str, Any]
    trial: str = ""
    frame: int = -1
    sho_x: np.ndarray | None = None  # (6,) KF state, None = no track
    sho_cov: np.ndarray | None = None
    sho_missed: int = 0
    direction: int = 0
    flip_count: int = 0
    last: np.ndarray | None = None
    vel: np.ndarray | None = None
    seen: np.ndarray | None = None
    frames: int = 0
    labelled: int = 0


def init(params: dict[str, Any]) -> LabelState:
    """Initial state; ``params`` are resolved by :data:`PARAMS`."""
    return _reset_tracks(LabelState(params=dict(params)))


def _reset_tracks(st: LabelState) -> LabelState:
    return replace(
        st,
        last=np.full((20, 3), np.nan),
        vel=np.zeros((20, 3)),
        seen=np.full(20, -(10**9), dtype=np.int64),
    )


# --- assignment helpers --------------------------------------------------------------------


def _name(side: str, site: str, near: str) -> str:
    far = "L" if near == "R" else "R"
    return f"{near if side == 'near' else far}_{site}"


@lru_cache(maxsize=32)
def _tuples(k: int, r: int) -> np.ndarray:
    """All r-tuples over k candidates plus 'missing' (index k), distinct when present."""
    rows = [
        t
        for t in itertools.product(range(k + 1), repeat=r)
        if len({i for i in t if i < k}) == sum(1 for i in t if i < k)
    ]
    return np.array(rows, dtype=np.int64).reshape(-1, r)


def _triangle_outside(a: np.ndarray, b: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance (mm, 0 inside) of 2D points p outside triangles (a, b, c); arrays (M, 2)."""

    def side(p1: np.ndarray, p2: np.ndarray, q: np.ndarray) -> np.ndarray:
        e = p2 - p1
        n = np.linalg.norm(e, axis=1) + 1e-9
        return (e[:, 0] * (q[:, 1] - p1[:, 1]) - e[:, 1] * (q[:, 0] - p1[:, 0])) / n

    s1, s2, s3 = side(a, b, p), side(b, c, p), side(c, a, p)
    orient = np.sign(side(a, b, c))
    d = np.minimum(np.minimum(s1 * orient, s2 * orient), s3 * orient)
    return np.maximum(-d, 0.0)


@dataclass
class _Frame:
    """Working data of one frame (not state)."""

    q: np.ndarray  # (N, 3) floor coords of the blobs, forward-oriented: (f, e, h)
    free: np.ndarray  # (N,) bool, blob not yet assigned
    assign: np.ndarray  # (20,) int blob per marker
    pred: np.ndarray  # (20, 3) prediction (f, e, h)
    sig: np.ndarray  # (20, 3) prediction sigma
    near: str


def _unary(fr: _Frame, idx: int, cand: np.ndarray) -> np.ndarray:
    """Squared-sigma distance of candidate blobs (K,) to marker ``idx``'s prediction."""
    d = (fr.q[cand] - fr.pred[idx]) / fr.sig[idx]
    return (d**2).sum(axis=1)


def _rigid(pa: np.ndarray, pb: np.ndarray, d0: float, loose: bool = False) -> np.ndarray:
    """Squared-sigma error of distances |pa - pb| (M, 3) against the model distance d0."""
    sig = (20.0 + 0.2 * d0) if loose else (10.0 + 0.1 * d0)
    return ((np.linalg.norm(pa - pb, axis=1) - d0) / sig) ** 2


# --- the per-frame labelling ---------------------------------------------------------------


def label_frame(
    st: LabelState, pos: np.ndarray, frame_idx: int, ff: FloorFrame, geo: Geometry
) -> tuple[LabelState, np.ndarray]:
    """Alg. 5 on one frame.

    Parameters
    ----------
    st : the label state.
    pos : (N, 3) camera-space blob positions (normal mode), mm; NaN rows are skipped.
    frame_idx : the frame index (gaps = dropped frames).
    ff : the floor frame of the calibration.
    geo : the subject geometry.

    Returns
    -------
    (state, assign) : assign is (20,) int, the blob index per marker, -1 = none.
    """
    p = st.params
    H = geo.sho_h
    dt_frames = max(1, frame_idx - st.frame) if st.frame >= 0 else 1
    dt = dt_frames / p["fps"]
    floor = ff.to_floor(pos) if len(pos) else np.zeros((0, 3))
    ok = np.isfinite(floor).all(axis=1)
    assign = np.full(20, -1)
    st = replace(st, frame=frame_idx, frames=st.frames + 1)

    # Steps 1-3: the shoulder.
    band = ok & (floor[:, 2] > 0.85 * H) & (floor[:, 2] < 1.15 * H)
    sho_blob = -1
    if st.sho_x is not None:
        kf = _kf(st.sho_x, st.sho_cov, dt)
        kf.predict()
        gate = p["sho_gate_mm"] * (1 + 0.5 * st.sho_missed)
        cand = np.flatnonzero(band)
        if cand.size:
            dist = np.hypot(floor[cand, 0] - kf.x[0], floor[cand, 1] - kf.x[1])
            j = int(np.argmin(dist))
            if dist[j] < gate:
                sho_blob = int(cand[j])
        if sho_blob >= 0:
            kf.update(floor[sho_blob])
            st = replace(st, sho_x=kf.x.copy(), sho_cov=kf.P.copy(), sho_missed=0)
        elif st.sho_missed < p["max_missed"]:
            st = replace(st, sho_x=kf.x.copy(), sho_cov=kf.P.copy(), sho_missed=st.sho_missed + 1)
        else:
            st = _reset_tracks(replace(st, sho_x=None, sho_cov=None, sho_missed=0, direction=0))
    if st.sho_x is None:
        sho_blob = _acquire_shoulder(floor, ok, band, H)
        if sho_blob < 0:
            return st, assign
        x = np.concatenate([floor[sho_blob], np.zeros(3)])
        P = np.diag([20.0**2] * 3 + [1500.0**2] * 3)
        st = _reset_tracks(replace(st, sho_x=x, sho_cov=P, sho_missed=0, direction=0, flip_count=0))

    # Direction (with hysteresis) and near side.
    va = float(st.sho_x[3])
    sho_a = float(st.sho_x[0])
    direction, flips = st.direction, st.flip_count
    if direction == 0:
        # First sight: walking toward the far end of the walkway from where it appears.
        half = 0.5 * ff.length
        direction = 1 if sho_a < half else -1
        if abs(va) > p["dir_speed"]:
            direction = 1 if va > 0 else -1
    elif abs(va) > p["dir_speed"] and np.sign(va) != direction:
        flips += 1
        if flips >= p["flip_frames"]:
            direction, flips = -direction, 0
            st = _reset_tracks(st)
    else:
        flips = 0
    st = replace(st, direction=direction, flip_count=flips)
    near = "R" if direction > 0 else "L"

    # Forward-oriented floor coords relative to nothing: f = direction * a.
    q = floor.copy()
    q[:, 0] *= direction
    sho = np.array([direction * st.sho_x[0], st.sho_x[1], st.sho_x[2]])
    if sho_blob >= 0:
        assign[MARKER_INDEX[f"{near}_SHO"]] = sho_blob
    pred, sig = _predictions(st, geo, sho, near, direction, frame_idx)
    free = ok.copy()
    if sho_blob >= 0:
        free[sho_blob] = False
    fr = _Frame(q, free, assign, pred, sig, near)

    _pelvis(fr, geo, sho, H, p["gate"])
    _lower(fr, geo, sho, H, p["gate"])

    # Track update (floor coords, un-oriented).
    last, vel, seen = st.last.copy(), st.vel.copy(), st.seen.copy()
    for i in np.flatnonzero(assign >= 0):
        cur = floor[assign[i]]
        age = frame_idx - seen[i]
        if 0 < age <= p["track_age"] + 1 and np.isfinite(last[i]).all():
            vel[i] = (cur - last[i]) / age
        else:
            vel[i] = 0.0
        last[i] = cur
        seen[i] = frame_idx
    st = replace(st, last=last, vel=vel, seen=seen, labelled=st.labelled + int((assign >= 0).sum()))
    return st, assign


def _acquire_shoulder(floor: np.ndarray, ok: np.ndarray, band: np.ndarray, H: float) -> int:
    """The first shoulder: a shoulder-height blob with the most body markers below it."""
    best, best_score = -1, 0.0
    body = ok & (floor[:, 2] > 0.3 * H) & (floor[:, 2] < 0.8 * H)
    for i in np.flatnonzero(band):
        near = body & (np.abs(floor[:, 0] - floor[i, 0]) < 0.3 * H)
        near &= np.abs(floor[:, 1] - floor[i, 1]) < 0.35 * H
        n = int(near.sum())
        score = n + floor[i, 2] / (10 * H)
        if n >= 2 and score > best_score:
            best, best_score = int(i), score
    return best


def _predictions(
    st: LabelState, geo: Geometry, sho: np.ndarray, near: str, direction: int, frame_idx: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-marker prediction (f, e, h) and sigma (20, 3): track if fresh, else the model."""
    p = st.params
    H = geo.sho_h
    pred = np.full((20, 3), np.nan)
    sig = np.full((20, 3), np.inf)
    for side in ("near", "far"):
        for site in SITES:
            i = MARKER_INDEX[_name(side, site, near)]
            off = geo.rel_sho(side, site)
            pred[i] = sho + off * np.array([1.0, 1.0, 0.0]) + np.array([0.0, 0.0, off[2]])
            if site in ("ASI", "PSI", "HIP", "SHO"):
                sig[i] = (0.06 * H, 0.06 * H, 0.04 * H)
            else:
                # Legs swing: along the walk only the rough reach of a stride is known.
                sig[i] = (0.3 * H, 0.07 * H, 0.1 * H)
            age = frame_idx - st.seen[i]
            if 0 < age <= p["track_age"] + 1 and np.isfinite(st.last[i]).all():
                t = st.last[i] + st.vel[i] * age
                pred[i] = (direction * t[0], t[1], t[2])
                s = 30.0 + 20.0 * age
                sig[i] = (s + 0.3 * abs(st.vel[i][0]), s, s)
    return pred, sig


def _pelvis(fr: _Frame, geo: Geometry, sho: np.ndarray, H: float, gate: float) -> None:
    """Steps 5-6: near PSI/HIP/ASI and far PSI/ASI, Hungarian then the order test."""
    q = fr.q
    cand = np.flatnonzero(
        fr.free
        & (q[:, 2] > 0.5 * H)
        & (q[:, 2] < 0.8 * H)
        & (np.abs(q[:, 0] - sho[0]) < 0.35 * H)
        & (np.abs(q[:, 1] - sho[1]) < 0.4 * H)
    )
    if cand.size == 0:
        return
    idx = [MARKER_INDEX[_name(s, m, fr.near)] for s, m in PELVIS]
    cost = np.stack([_unary(fr, i, cand) for i in idx])
    big = 1e6
    rows, cols = linear_sum_assignment(np.where(cost <= gate**2, cost, big))
    got: dict[int, tuple[int, float]] = {}
    for r, c in zip(rows, cols, strict=True):
        if cost[r, c] <= gate**2:
            got[idx[r]] = (int(cand[c]), float(cost[r, c]))

    def f(name: str) -> float | None:
        i = MARKER_INDEX[_name(*name.split(":"), fr.near)] if ":" in name else MARKER_INDEX[name]
        return q[got[i][0], 0] if i in got else None

    def drop_worse(a: int, b: int) -> None:
        worst = a if got[a][1] >= got[b][1] else b
        del got[worst]

    order = [
        (MARKER_INDEX[_name("near", "PSI", fr.near)], MARKER_INDEX[_name("near", "HIP", fr.near)]),
        (MARKER_INDEX[_name("near", "HIP", fr.near)], MARKER_INDEX[_name("near", "ASI", fr.near)]),
        (MARKER_INDEX[_name("near", "PSI", fr.near)], MARKER_INDEX[_name("near", "ASI", fr.near)]),
        (MARKER_INDEX[_name("far", "PSI", fr.near)], MARKER_INDEX[_name("far", "ASI", fr.near)]),
    ]
    del f
    for a, b in order:
        if a in got and b in got and q[got[a][0], 0] >= q[got[b][0], 0]:
            drop_worse(a, b)
    for i, (blob, _) in got.items():
        fr.assign[i] = blob
        fr.free[blob] = False


def _lower(fr: _Frame, geo: Geometry, sho: np.ndarray, H: float, gate: float) -> None:
    """Steps 7-10: near foot (triangle model), far heel and toe, then THI and KNE."""
    q = fr.q
    near, far = fr.near, ("L" if fr.near == "R" else "R")
    hip_i = MARKER_INDEX[f"{near}_HIP"]
    hip = q[fr.assign[hip_i]] if fr.assign[hip_i] >= 0 else None
    cand = np.flatnonzero(
        fr.free
        & (q[:, 2] < 0.56 * H)
        & (q[:, 2] > -0.05 * H)
        & (np.abs(q[:, 0] - sho[0]) < 0.65 * H)
        & (q[:, 1] - sho[1] > -0.3 * H)
        & (q[:, 1] - sho[1] < 0.5 * H)
    )
    K = cand.size
    if K == 0:
        return
    if K > 12:
        # Keep the lowest 12: the foot and shank markers are the lowest on the body.
        cand = cand[np.argsort(q[cand, 2])[:12]]
        K = 12
    P = np.vstack([q[cand], np.full((1, 3), np.nan)])  # row K = missing
    foot_idx = [MARKER_INDEX[f"{near}_{s}"] for s in NEAR_FOOT]
    U = np.vstack([np.append(_unary(fr, i, cand), MISS_COST) for i in foot_idx])  # (4, K+1)
    T = _tuples(K, 4)
    cost = U[np.arange(4), T].sum(axis=1)
    pts = P[T]  # (M, 4, 3)
    present = T < K
    pairs = [
        (0, 1, geo.d("TIB", "ANK"), False),
        (1, 2, geo.d("ANK", "HEE"), False),
        (1, 3, geo.d("ANK", "TOE"), False),
        (2, 3, geo.d("HEE", "TOE"), False),
        (0, 2, geo.d("TIB", "HEE"), True),
        (0, 3, geo.d("TIB", "TOE"), True),
    ]
    for a, b, d0, loose in pairs:
        both = present[:, a] & present[:, b]
        e = np.zeros(len(T))
        e[both] = _rigid(pts[both, a], pts[both, b], d0, loose)
        cost += e
    allp = present.all(axis=1)
    if allp.any():
        sag = pts[allp][:, :, [0, 2]]  # (f, h)
        out = _triangle_outside(sag[:, 0], sag[:, 3], sag[:, 2], sag[:, 1])
        cost[allp] += (out / 15.0) ** 2
    # The toe is ahead of the heel; the tibia above the ankle.
    ht = present[:, 2] & present[:, 3]
    cost[ht] += 4.0 * (pts[ht, 3, 0] < pts[ht, 2, 0])
    ta = present[:, 0] & present[:, 1]
    cost[ta] += 4.0 * (pts[ta, 0, 2] < pts[ta, 1, 2])

    # Far heel and toe for the best near-foot hypotheses.
    far_idx = [MARKER_INDEX[f"{far}_HEE"], MARKER_INDEX[f"{far}_TOE"]]
    UF = np.vstack([np.append(_unary(fr, i, cand), MISS_COST) for i in far_idx])
    T2 = _tuples(K, 2)
    c2 = UF[np.arange(2), T2].sum(axis=1)
    both2 = (T2 < K).all(axis=1)
    p2 = P[T2]
    c2[both2] += _rigid(p2[both2, 0], p2[both2, 1], geo.d("HEE", "TOE"))
    c2[both2] += 4.0 * (p2[both2, 1, 0] < p2[both2, 0, 0])
    best = (np.inf, None, None)
    for m in np.argsort(cost)[:40]:
        used = set(T[m][T[m] < K].tolist())
        clash = np.array([bool(used & set(t[t < K].tolist())) for t in T2])
        cc = c2.copy()
        cc[clash] = np.inf
        # The far foot is deeper than the near one (its lateral markers face away).
        ne = pts[m, present[m], 1]
        if ne.size:
            depth_near = float(np.mean(ne))
            for k in range(2):
                pk = T2[:, k] < K
                cc[pk] += 4.0 * (P[T2[pk, k], 1] < depth_near + 20.0)
        j = int(np.argmin(cc))
        if cost[m] + cc[j] < best[0]:
            best = (cost[m] + cc[j], T[m], T2[j])
    _, tf, tp = best
    if tf is None:
        return
    chosen = {}
    for k, i in enumerate(foot_idx):
        if tf[k] < K:
            chosen[i] = int(tf[k])
    for k, i in enumerate(far_idx):
        if tp[k] < K:
            chosen[i] = int(tp[k])

    # Limb: THI and KNE against HIP, TIB and ANK.
    used = set(chosen.values())
    rest = [k for k in range(K) if k not in used]
    thi_i, kne_i = MARKER_INDEX[f"{near}_THI"], MARKER_INDEX[f"{near}_KNE"]
    if rest:
        R = np.array([*rest, K])
        uk = np.append(_unary(fr, kne_i, cand[rest]), MISS_COST)
        ut = np.append(_unary(fr, thi_i, cand[rest]), MISS_COST)
        tib = P[tf[0]] if tf[0] < K else None
        ank = P[tf[1]] if tf[1] < K else None
        best2 = (np.inf, K, K)
        for a, ka in enumerate(R):
            for b, kb in enumerate(R):
                if ka == kb and ka < K:
                    continue
                c = uk[a] + ut[b]
                pk, pt = P[ka], P[kb]
                if ka < K:
                    for other, d0 in ((tib, geo.d("KNE", "TIB")), (ank, geo.d("KNE", "ANK"))):
                        if other is not None:
                            c += _rigid(pk[None], other[None], d0)[0]
                    if hip is not None:
                        c += _rigid(pk[None], hip[None], geo.d("HIP", "KNE"))[0]
                if kb < K:
                    if hip is not None:
                        c += _rigid(pt[None], hip[None], geo.d("HIP", "THI"))[0]
                    if ka < K:
                        c += _rigid(pt[None], pk[None], geo.d("THI", "KNE"))[0]
                        c += 4.0 * (pt[2] < pk[2])
                if c < best2[0]:
                    best2 = (c, ka, kb)
        if best2[1] < K:
            chosen[kne_i] = int(best2[1])
        if best2[2] < K:
            chosen[thi_i] = int(best2[2])

    _accept(fr, chosen, cand, geo, hip, gate)


RIGID = (
    ("TIB", "ANK", False),
    ("ANK", "HEE", False),
    ("ANK", "TOE", False),
    ("HEE", "TOE", False),
    ("TIB", "HEE", True),
    ("TIB", "TOE", True),
    ("KNE", "TIB", False),
    ("KNE", "ANK", False),
    ("HIP", "KNE", False),
    ("HIP", "THI", False),
    ("THI", "KNE", False),
)


def _accept(
    fr: _Frame,
    chosen: dict[int, int],
    cand: np.ndarray,
    geo: Geometry,
    hip: np.ndarray | None,
    gate: float,
) -> None:
    """Step 10 gate: drop a label whose track or rigid distances it breaks; keep the rest."""
    q = fr.q
    pos = {MARKER_NAMES[i]: q[cand[k]] for i, k in chosen.items()}
    if hip is not None:
        pos.setdefault(f"{fr.near}_HIP", hip)
    bad: set[int] = set()
    for i, k in chosen.items():
        u = _unary(fr, i, np.array([cand[k]]))[0]
        if u > gate**2 * 3:
            bad.add(i)
    for side in (fr.near, "L" if fr.near == "R" else "R"):
        for a, b, loose in RIGID:
            na, nb = f"{side}_{a}", f"{side}_{b}"
            if na in pos and nb in pos:
                e = _rigid(pos[na][None], pos[nb][None], geo.d(a, b), loose)[0]
                if e > gate**2:
                    # Blame the one without another good partner: drop both unless one is the
                    # already accepted hip.
                    for n in (na, nb):
                        if MARKER_INDEX[n] in chosen:
                            bad.add(MARKER_INDEX[n])
    for i, k in chosen.items():
        if i not in bad:
            fr.assign[i] = int(cand[k])
            fr.free[cand[k]] = False


# --- the stage core ------------------------------------------------------------------------


def _output(mk: Markers3D, assign: np.ndarray, direction: int, near: str) -> LabelledMarkers:
    pos = np.asarray(mk.position, dtype=np.float64).reshape(-1, 3, 3)
    cen = np.asarray(mk.centroid, dtype=np.float64).reshape(-1, 2)
    position = np.full((20, 3), np.nan)
    pixel = np.full((20, 2), np.nan)
    for i in np.flatnonzero(assign >= 0):
        b = assign[i]
        m = CLUSTER_MODES.index(cluster_mode(MARKER_NAMES[i]))
        xyz = pos[b, m]
        if not np.isfinite(xyz).all():
            xyz = pos[b, 0]  # the label's own mode found no layer: normal mode
        position[i] = xyz
        pixel[i] = cen[b]
    return LabelledMarkers.follow(
        mk.header,
        position=position,
        pixel=pixel,
        blob=assign.astype(np.int32),
        direction=int(direction),
        near_side=near,
    )


def step(state: LabelState, inputs: Mapping[str, Message]) -> tuple[LabelState, list[Message]]:
    """Label one frame of a walking trial.

    Parameters
    ----------
    inputs : ``{"markers": Markers3D, "calibration": CalibrationRecord, "model":
        SubjectModel}`` (the side inputs may be absent: level camera and template subject).

    Returns
    -------
    (state, [LabelledMarkers])
    """
    mk = inputs["markers"]
    if not isinstance(mk, Markers3D):
        raise StageError(NAME, f"input 'markers' is a {type(mk).__name__}, not Markers3D")
    cal = inputs.get("calibration")
    model = inputs.get("model")
    p = state.params
    ff = FloorFrame.from_record(
        cal if isinstance(cal, CalibrationRecord) else None, p["camera_height_mm"]
    )
    geo = Geometry.from_model(model if isinstance(model, SubjectModel) else None)
    st = state
    if mk.header.trial != st.trial or mk.header.frame <= st.frame:
        st = init(p)
        st = replace(st, trial=mk.header.trial)
    pos = np.asarray(mk.position, dtype=np.float64).reshape(-1, 3, 3)[:, 0, :]
    st, assign = label_frame(st, pos, mk.header.frame, ff, geo)
    near = "" if st.direction == 0 else ("R" if st.direction > 0 else "L")
    if st.sho_x is None:
        near = ""
    return st, [_output(mk, assign, st.direction if st.sho_x is not None else 0, near)]


SPEC = StageSpec(
    name=NAME,
    params=PARAMS,
    init=init,
    step=step,
    stateful=True,
    doc=__doc__ or "",
)


# --- scoring (evaluation only: ground truth never reaches the stage) ------------------------

FAR_SEEN = ("ASI", "PSI", "HEE", "TOE")


def score_labelling(
    labelled_msgs: list[LabelledMarkers], truth_msgs: list[Any], tol_px: float = 4.0
) -> dict[str, Any]:
    """Labelling accuracy of ``labelled`` messages against simulator ground truth.

    A label is correct when the truth pixel of that marker is the nearest visible truth
    marker to the labelled pixel and lies within ``tol_px``. A frame is correct when it has
    no wrong label (a missing label is a gap for the gap filler, not an error).

    Parameters
    ----------
    labelled_msgs : LabelledMarkers of the walking trials.
    truth_msgs : GroundTruth messages (matched by trial and frame).
    tol_px : pixel tolerance.

    Returns
    -------
    dict: ``frames``; ``accuracy`` (share of frames without a wrong label); ``labels``,
    ``wrong`` and ``precision`` (correct labels / labels); ``recall`` (visible markers
    labelled correctly / visible, over the markers a side view shows: the near side plus the
    far ASI, PSI, HEE and TOE); ``complete`` (share of frames without a wrong label and with
    every such visible marker labelled); ``per_marker_recall``.
    """
    truth = {(t.header.trial, t.header.frame): t for t in truth_msgs}
    frames = ok_frames = labels = correct = visible = hit = complete = 0
    per_vis = np.zeros(20)
    per_hit = np.zeros(20)
    for m in labelled_msgs:
        t = truth.get((m.header.trial, m.header.frame))
        if t is None:
            continue
        frames += 1
        tp = np.asarray(t.pixel, dtype=np.float64)
        vis = np.asarray(t.visible, dtype=bool) & np.isfinite(tp).all(axis=1)
        px = np.asarray(m.pixel, dtype=np.float64)
        good = np.zeros(20, bool)
        n_wrong = 0
        for i in np.flatnonzero(np.isfinite(px).all(axis=1)):
            labels += 1
            d = np.where(vis, np.hypot(*(tp - px[i]).T), np.inf)
            j = int(np.argmin(d))
            if j == i and d[j] <= tol_px:
                good[i] = True
            else:
                n_wrong += 1
        correct += int(good.sum())
        ok_frames += n_wrong == 0
        near = m.near_side or ("R" if m.direction >= 0 else "L")
        expect = vis & np.array([n[0] == near or n.split("_")[1] in FAR_SEEN for n in MARKER_NAMES])
        visible += int(expect.sum())
        hit += int((good & expect).sum())
        per_vis += expect
        per_hit += good & expect
        complete += int(n_wrong == 0 and bool((good | ~expect).all()))
    nan = float("nan")
    return {
        "frames": frames,
        "accuracy": ok_frames / frames if frames else nan,
        "labels": labels,
        "wrong": labels - correct,
        "precision": correct / labels if labels else nan,
        "recall": hit / visible if visible else nan,
        "complete": complete / frames if frames else nan,
        "per_marker_recall": {
            MARKER_NAMES[i]: float(per_hit[i] / per_vis[i]) for i in range(20) if per_vis[i]
        },
    }
