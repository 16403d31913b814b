"""Stage ``label``: marker labelling (Alg. 5) in 3D, in the floor frame of the calibration.

Input: ``markers`` (:class:`Markers3D`) of the walking trials, with the ``calibration``
record and the ``model`` (:class:`SubjectModel`) as side inputs. Output: ``labelled``
(:class:`LabelledMarkers`), the 20 named markers, each position taken under the marker's
own Alg. 3 cluster mode (``gaitflow.markers.cluster_mode``).

Per frame (Alg. 5, read in 3D; see docs/readme/labelling.md):

1. every blob is mapped to the floor frame under each cluster mode: a along the walking
   line (toward +u), e horizontal away from the camera, h height above the floor (mm);
2. the shoulder (SHO) is predicted by a constant-velocity Kalman filter (filterpy,
   position + velocity in 3D) and taken as the shoulder-height blob nearest the prediction
   (or a clearly nearer-to-camera one at the same place: the near shoulder); without one
   the prediction stands in for up to ``max_missed`` frames (steps 1-3); missing frames
   count as misses and a track back after 3 restarts. The first shoulder is a
   shoulder-height blob with body markers below it and nearer the camera than they are;
3. the walking direction is the sign of the shoulder's velocity along a (first sight:
   toward the far end of the walkway; then ``flip_frames`` frames against it to change).
   The side facing the camera follows (walking toward +u shows the right side). A change of
   direction resets every track and re-acquires the near shoulder: the return pass shows
   the other side (the L/R swap). While turning (slow along the line, or heading off it)
   only the shoulder is labelled;
4. upper body (steps 5-6): every assignment of the pelvis-band blobs to near PSI, HIP, ASI
   and far ASI, PSI (absorbers, never published) is scored (vectorised) by the tracks or
   the model's standing offsets from the shoulder, sagittal rigid distances, and the hard
   order PSI < HIP < ASI along the walking direction, HIP below both, far ASI deeper;
5. lower body (steps 7-10): every assignment of the low blobs to the near foot (TIB, ANK,
   HEE, TOE) is scored by the foot's sagittal lengths (ANK-HEE, ANK-TOE, HEE-TOE: the
   model's, refined online from walking frames, see ``_learn_foot``), one depth for the
   foot, the wand bounds of TIB (side-independent, ``_interval``), the triangle foot model
   (ANK inside triangle TIB-TOE-HEE) and the tracks, under hard rules (toe half a foot
   ahead of the heel, tibia above ankle, heel and toe not far above the ankle); the best
   ones are completed with the far heel, toe and tibia (the far tibia only absorbs its
   blob; rigid foot, deeper than the near foot; a lone far blob only on last frame's
   track); ambiguity is judged on the joint hypotheses; a lone near foot marker needs a
   fresh track. Then the limb (KNE: thigh and shank lengths to HIP and ANK; THI and TIB
   on their segments, ``_on_segment``; near knee and thigh at the near leg's depth, far
   knee and thigh, deeper, absorb their blobs). Segment lengths more than 25 % off the
   stature-scaled template fall back to it (a static labelling error);
6. a label is left NaN rather than guessed when another blob fits it almost as well
   (``ambiguity``) or it breaks a track gate or a rigid distance: an occluded marker gives a
   gap, not a wrong label. Blobs left over (stray reflectors, far-side leg markers) stay
   unlabelled.

Far-side SHO, HIP, THI, KNE, TIB and ANK face away from the camera in a side view and are
never published; nor, by default, the near ASI and PSI (``publish_asis_psis``).
Conventions: (20, ...) arrays follow ``gaitflow.markers.MARKER_NAMES``; camera space X
right, Y down, Z forward, mm; pixels (u, v); NaN = missing.
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
            5,
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
            "ambiguity",
            float,
            4.0,
            "sigma^2",
            "a label is dropped when another blob scores within this margin of the best",
            0.0,
            100.0,
        ),
        Param(
            "publish_asis_psis",
            bool,
            False,
            "",
            "publish the near ASI and PSI (their depth is poor on the pelvis silhouette)",
        ),
        Param(
            "turn_speed",
            float,
            120.0,
            "mm/s",
            "below this shoulder speed (after walking) the subject is turning: no labels",
            0.0,
        ),
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
# Segments whose measured length is checked against the stature-scaled template, and the
# relative deviation beyond which the template's length is used instead.
SEGMENTS = (("HIP", "KNE"), ("KNE", "ANK"), ("ANK", "HEE"), ("ANK", "TOE"), ("HEE", "TOE"))
PLAUSIBLE = 0.25
PELVIS = (("near", "PSI"), ("near", "HIP"), ("near", "ASI"), ("far", "PSI"), ("far", "ASI"))
MISS_COST = 9.0  # a missing label costs as much as a 3-sigma fit


# --- the subject geometry label uses --------------------------------------------------


@dataclass(frozen=True)
class Geometry:
    """Subject geometry for labelling: standing offsets and segment distances.

    ``offsets`` (2, 10, 3): per side (0 = near, 1 = far) and site, the standing position
    relative to the near shoulder: forward along the walking direction, e (away from the
    camera), height above the floor; mm. Measured in the static pose where seen; otherwise
    the scaled template (far side: the near offset moved back by twice the template's
    lateral offset, at least 60 mm). ``dist`` (10, 10): near-side distances between sites.
    """

    offsets: np.ndarray
    dist: np.ndarray
    sho_h: float

    @classmethod
    def from_model(cls, model: SubjectModel | None) -> Geometry:
        """Geometry of a subject model; the scaled template if there is none."""
        sho_h = TEMPLATE_SHO_HEIGHT
        extra = dict(model.extra) if model is not None else {}
        v = extra.get("sho_height_mm")
        if isinstance(v, int | float) and np.isfinite(v) and v > 0:
            sho_h = float(v)
        tpl = template_layout(sho_h / TEMPLATE_SHO_HEIGHT)
        lay = extra.get("layout", {})
        layout = tpl.copy()
        for j, s in enumerate(SITES):
            v = lay.get(s)
            if v is not None and len(v) == 3 and np.isfinite(v).all():
                layout[j] = v
        s0 = tpl[SITES.index("SHO")]
        offsets = np.zeros((2, 10, 3))
        for j in range(10):
            q = tpl[j]
            offsets[0, j] = (q[0] - s0[0], s0[2] - q[2], q[1])
            offsets[1, j] = offsets[0, j] + (0.0, max(2 * q[2], 60.0), 0.0)
        meas = extra.get("offsets_from_shoulder", {})
        for k, side in enumerate(("near", "far")):
            for j, s in enumerate(SITES):
                v = meas.get(f"{side}_{s}")
                if v is not None and len(v) == 3 and np.isfinite(v).all():
                    offsets[k, j] = v
                    if k == 0 and f"far_{s}" not in meas:
                        back = max(2 * tpl[j, 2], 60.0)
                        offsets[1, j] = np.asarray(v) + np.array([0.0, back, 0.0])
        # Sagittal (forward, height) distances: see _rigid.
        near = offsets[0]
        dist = np.hypot(near[:, None, 0] - near[None, :, 0], near[:, None, 2] - near[None, :, 2])
        # A measured segment far (> PLAUSIBLE) from the stature-scaled template is a static
        # labelling error (a crouched pose, merged blobs), not anatomy: the template's
        # length replaces it.
        t0 = tpl[:, [0, 1]]  # template (forward, height)
        for a, b in SEGMENTS:
            ia, ib = SITES.index(a), SITES.index(b)
            dt = float(np.linalg.norm(t0[ia] - t0[ib]))
            if not abs(dist[ia, ib] / dt - 1.0) <= PLAUSIBLE:
                dist[ia, ib] = dist[ib, ia] = dt
        return cls(offsets, dist, sho_h)

    def d(self, a: str, b: str) -> float:
        return float(self.dist[SITES.index(a), SITES.index(b)])

    def rel_sho(self, side: str, site: str) -> np.ndarray:
        """Standing offset (forward, e, height) of a site from the near shoulder."""
        return self.offsets[0 if side == "near" else 1, SITES.index(site)]


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
    walked: bool = False
    last: np.ndarray | None = None
    vel: np.ndarray | None = None
    seen: np.ndarray | None = None
    frames: int = 0
    labelled: int = 0
    foot: np.ndarray | None = None  # (3,) learned ANK-HEE, ANK-TOE, HEE-TOE, mm
    foot_n: int = 0


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

    qm: np.ndarray  # (N, 3, 3) floor coords (f, e, h) of the blobs per cluster mode
    free: np.ndarray  # (N,) bool, blob not yet assigned
    assign: np.ndarray  # (20,) int blob per marker
    pred: np.ndarray  # (20, 3) prediction (f, e, h)
    sig: np.ndarray  # (20, 3) prediction sigma
    near: str
    tracked: np.ndarray  # (20,) bool, prediction comes from a fresh track
    ambiguity: float
    age: np.ndarray  # (20,) frames since each marker was last labelled
    publish_asis_psis: bool = True

    def pos(self, i: int) -> np.ndarray:
        """(N, 3) blob positions under marker ``i``'s cluster mode."""
        return self.qm[:, MODE_OF[i]]


# Mode each marker is matched under. The output keeps every marker's own cluster mode;
# for matching, ASI and PSI use the normal mode: they sit on the front and back silhouette
# of the pelvis, where the bottom mode's far layer is often the room behind the subject.
MODE_OF = np.array(
    [0 if n[2:] in ("ASI", "PSI") else CLUSTER_MODES.index(cluster_mode(n)) for n in MARKER_NAMES]
)


def _unary(fr: _Frame, idx: int, cand: np.ndarray) -> np.ndarray:
    """Squared-sigma distance of candidate blobs (K,) to marker ``idx``'s prediction."""
    d = (fr.pos(idx)[cand] - fr.pred[idx]) / fr.sig[idx]
    return (d**2).sum(axis=1)


def _rigid(pa: np.ndarray, pb: np.ndarray, d0: float, loose: bool = False) -> np.ndarray:
    """Squared-sigma error of sagittal distances |pa - pb| against the model's d0.

    Points are (M, 3) (f, e, h); only (f, h) count. Depth is the noisy axis of a marker on
    a silhouette (tens of mm, more at the heel and pelvis) while (f, h) come from the
    image, so segment lengths are compared in the sagittal plane (the model's are too).
    """
    sig = (20.0 + 0.2 * d0) if loose else (10.0 + 0.1 * d0)
    d = np.hypot(pa[:, 0] - pb[:, 0], pa[:, 2] - pb[:, 2])
    return ((d - d0) / sig) ** 2


def _interval(pa: np.ndarray, pb: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Squared-sigma cost of sagittal distances |pa - pb| outside [lo, hi] (0 inside).

    For the wand markers (TIB, THI): where along its segment a wand marker sits varies
    between subjects and between the two legs of one subject (by 50-90 mm in the trials),
    so the static pose's one side does not give the other side's distance.
    """
    d = np.hypot(pa[:, 0] - pb[:, 0], pa[:, 2] - pb[:, 2])
    return (np.maximum(lo - d, 0.0) ** 2 + np.maximum(d - hi, 0.0) ** 2) / 15.0**2


def _on_segment(pa: np.ndarray, pw: np.ndarray, pb: np.ndarray, sig: float = 25.0) -> np.ndarray:
    """Squared-sigma cost of wand points pw off the sagittal segment pa-pb (all (M, 3)).

    A wand marker projects (sagittally) onto its segment's line, somewhere between the
    joints: the perpendicular distance and the overshoot past either end count.
    """
    a, w, b = pa[:, [0, 2]], pw[:, [0, 2]], pb[:, [0, 2]]
    e = b - a
    L2 = np.maximum((e**2).sum(axis=1), 1.0)
    t = ((w - a) * e).sum(axis=1) / L2
    perp = np.abs(e[:, 0] * (w[:, 1] - a[:, 1]) - e[:, 1] * (w[:, 0] - a[:, 0])) / np.sqrt(L2)
    over = np.sqrt(L2) * (np.maximum(-t + 0.1, 0.0) + np.maximum(t - 0.9, 0.0))
    return (perp**2 + over**2) / sig**2


def _slots(fr: _Frame, idx: list[int], cand: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(M, r, 3) positions of tuples T (M, r) over ``cand`` (+ missing), per slot's mode."""
    out = np.full((*T.shape, 3), np.nan)
    for k, i in enumerate(idx):
        P = np.vstack([fr.pos(i)[cand], np.full((1, 3), np.nan)])
        out[:, k] = P[T[:, k]]
    return out


def _base_cost(fr: _Frame, idx: list[int], cand: np.ndarray, T: np.ndarray) -> np.ndarray:
    U = np.vstack([np.append(_unary(fr, i, cand), MISS_COST) for i in idx])
    return U[np.arange(len(idx)), T].sum(axis=1)


def _unambiguous(cost: np.ndarray, T: np.ndarray, m: int, K: int, margin: float) -> list[bool]:
    """Per slot of the best tuple ``m``: is every tuple giving the slot another blob clearly
    worse (by ``margin``)? A label that could as well be another blob is left out."""
    keep = []
    for k in range(T.shape[1]):
        if T[m, k] >= K:
            keep.append(False)
            continue
        other = (T[:, k] != T[m, k]) & (T[:, k] < K)
        alt = float(cost[other].min()) if other.any() else np.inf
        keep.append(alt - float(cost[m]) >= margin)
    return keep


# --- the per-frame labelling ---------------------------------------------------------------


def label_frame(
    st: LabelState, pos: np.ndarray, frame_idx: int, ff: FloorFrame, geo: Geometry
) -> tuple[LabelState, np.ndarray]:
    """Alg. 5 on one frame.

    Parameters
    ----------
    st : the label state.
    pos : (N, 3, 3) camera-space blob positions per cluster mode (normal, top, bottom), mm;
        blobs without a normal-mode position are skipped.
    frame_idx : the frame index (gaps = dropped frames).
    ff : the floor frame of the calibration.
    geo : the subject geometry.

    Returns
    -------
    (state, assign) : assign is (20,) int, the blob index per marker, -1 = none.
    """
    p = st.params
    geo = _learned(geo, st)
    H = geo.sho_h
    dt_frames = max(1, frame_idx - st.frame) if st.frame >= 0 else 1
    dt = dt_frames / p["fps"]
    pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3, 3)
    # A mode that found no layer falls back to the normal mode's position.
    pos = np.where(np.isfinite(pos), pos, pos[:, :1, :])
    fm = ff.to_floor(pos) if len(pos) else np.zeros((0, 3, 3))
    floor = fm[:, 0]
    ok = np.isfinite(floor).all(axis=1)
    assign = np.full(20, -1)
    st = replace(st, frame=frame_idx, frames=st.frames + 1)
    top = fm[:, CLUSTER_MODES.index("top")]

    # Steps 1-3: the shoulder (top mode).
    band = ok & (top[:, 2] > 0.85 * H) & (top[:, 2] < 1.15 * H)
    sho_blob = -1
    if st.sho_x is not None and dt_frames > 1:
        # Frames that never arrived (dropped, or nobody in view) count as misses.
        st = replace(st, sho_missed=st.sho_missed + dt_frames - 1)
    if st.sho_x is not None and st.sho_missed > p["max_missed"]:
        st = _reset_tracks(
            replace(st, sho_x=None, sho_cov=None, sho_missed=0, direction=0, walked=False)
        )
    if st.sho_x is not None:
        kf = _kf(st.sho_x, st.sho_cov, dt)
        kf.predict()
        # The gate widens with misses, at most to twice its size: a shoulder that shows up
        # far from a coasting prediction is a new track (e.g. after a turn out of view).
        gate = p["sho_gate_mm"] * min(2.0, 1 + 0.25 * st.sho_missed)
        cand = np.flatnonzero(band)
        if cand.size:
            dist = np.hypot(top[cand, 0] - kf.x[0], top[cand, 1] - kf.x[1])
            j = int(np.argmin(dist))
            if dist[j] < gate:
                sho_blob = int(cand[j])
                # The near shoulder is the one nearest the camera: if the track sits on a
                # far shoulder (seen first), move to a clearly nearer one at the same place.
                nearer = cand[
                    (np.abs(top[cand, 0] - top[sho_blob, 0]) < 0.2 * H)
                    & (top[cand, 1] < top[sho_blob, 1] - 0.07 * H)
                ]
                if nearer.size:
                    sho_blob = int(nearer[np.argmin(top[nearer, 1])])
                    kf.x[:3] = top[sho_blob]
        if sho_blob >= 0 and st.sho_missed >= 3:
            # Back after a gap (out of view, turning): start afresh, the subject may have
            # turned round.
            st = _reset_tracks(
                replace(st, sho_x=None, sho_cov=None, sho_missed=0, direction=0, walked=False)
            )
        elif sho_blob >= 0:
            kf.update(top[sho_blob])
            st = replace(st, sho_x=kf.x.copy(), sho_cov=kf.P.copy(), sho_missed=0)
        elif st.sho_missed < p["max_missed"]:
            st = replace(st, sho_x=kf.x.copy(), sho_cov=kf.P.copy(), sho_missed=st.sho_missed + 1)
        else:
            st = _reset_tracks(
                replace(st, sho_x=None, sho_cov=None, sho_missed=0, direction=0, walked=False)
            )
    if st.sho_x is None:
        sho_blob = _acquire_shoulder(top, ok, band, H)
        if sho_blob < 0:
            return st, assign
        x = np.concatenate([top[sho_blob], np.zeros(3)])
        P = np.diag([20.0**2] * 3 + [1500.0**2] * 3)
        st = _reset_tracks(replace(st, sho_x=x, sho_cov=P, sho_missed=0, direction=0, flip_count=0))

    # Direction (with hysteresis) and near side.
    va = float(st.sho_x[3])
    direction, flips = st.direction, st.flip_count
    if direction == 0:
        # First sight: walking toward the far end of the walkway from where it appears.
        direction = 1 if float(st.sho_x[0]) < 0.5 * ff.length else -1
        if abs(va) > p["dir_speed"]:
            direction = 1 if va > 0 else -1
    elif abs(va) > p["dir_speed"] and np.sign(va) != direction:
        flips += 1
        if flips >= p["flip_frames"]:
            direction, flips = -direction, 0
            st = _reset_tracks(st)
            # The return shows the other side: the shoulder now nearest the camera.
            j = _nearest_shoulder(top, band, st.sho_x, H)
            if j >= 0:
                x = st.sho_x.copy()
                x[:3] = top[j]
                st = replace(st, sho_x=x)
                sho_blob = j
            else:
                sho_blob = -1
    else:
        flips = 0
    walked = st.walked or abs(va) > p["dir_speed"]
    st = replace(st, direction=direction, flip_count=flips, walked=walked)
    near = "R" if direction > 0 else "L"
    if sho_blob >= 0:
        assign[MARKER_INDEX[f"{near}_SHO"]] = sho_blob
    # Turning: slow along the line, backwards, or heading off the line (the near shoulder
    # swings away from the camera as the body turns).
    ve = float(st.sho_x[4])
    turning = walked and (
        abs(va) < p["turn_speed"] or np.sign(va) != direction or abs(ve) > 0.5 * abs(va)
    )
    if not turning:
        qm = fm.copy()
        qm[:, :, 0] *= direction
        sho = np.array([direction * st.sho_x[0], st.sho_x[1], st.sho_x[2]])
        pred, sig, tracked = _predictions(st, geo, sho, near, direction, frame_idx)
        free = ok.copy()
        if sho_blob >= 0:
            free[sho_blob] = False
        age = frame_idx - st.seen
        fr = _Frame(
            qm,
            free,
            assign,
            pred,
            sig,
            near,
            tracked,
            p["ambiguity"],
            age,
            p["publish_asis_psis"],
        )
        _pelvis(fr, geo, sho, H, p["gate"])
        _lower(fr, geo, sho, H, p["gate"])

    # Track update (floor coords under each marker's own mode, un-oriented).
    last, vel, seen = st.last.copy(), st.vel.copy(), st.seen.copy()
    for i in np.flatnonzero(assign >= 0):
        cur = fm[assign[i], MODE_OF[i]]
        age = frame_idx - seen[i]
        if 0 < age <= p["track_age"] + 1 and np.isfinite(last[i]).all():
            vel[i] = (cur - last[i]) / age
        else:
            vel[i] = 0.0
        last[i] = cur
        seen[i] = frame_idx
    st = replace(st, last=last, vel=vel, seen=seen, labelled=st.labelled + int((assign >= 0).sum()))
    if st.direction:
        st = _learn_foot(st, fm, assign, geo, "R" if st.direction > 0 else "L")
    return st, assign


FOOT = (("ANK", "HEE"), ("ANK", "TOE"), ("HEE", "TOE"))
FOOT_PRIOR = 5.0  # weight of the model's foot, in frames
FOOT_RATE = 0.05  # slowest learning rate (exponential forgetting)


def _learned(geo: Geometry, st: LabelState) -> Geometry:
    """The geometry with the foot lengths learned on this trial so far."""
    if st.foot is None:
        return geo
    dist = geo.dist.copy()
    for (a, b), d in zip(FOOT, st.foot, strict=True):
        ia, ib = SITES.index(a), SITES.index(b)
        dist[ia, ib] = dist[ib, ia] = d
    return replace(geo, dist=dist)


def _learn_foot(
    st: LabelState, fm: np.ndarray, assign: np.ndarray, geo: Geometry, near: str
) -> LabelState:
    """Refine the foot triangle from a frame with the near ANK, HEE and TOE all labelled.

    The static pose often gives no foot (heel and ankle merge into one blob there, and the
    template's foot may be 20-30 % off the subject's); walking frames separate them. Only
    labels that passed every gate teach, and an observation far off the current
    length is ignored (40 %), so a wrong frame cannot drag the model far.
    """
    idx = [MARKER_INDEX[f"{near}_{s}"] for s in ("ANK", "HEE", "TOE")]
    if (assign[idx] < 0).any():
        return st
    q = {s: fm[assign[i], MODE_OF[i]] for s, i in zip(("ANK", "HEE", "TOE"), idx, strict=True)}
    cur = np.array([geo.d(a, b) for a, b in FOOT])
    obs = np.array([np.hypot(*(q[a] - q[b])[[0, 2]]) for a, b in FOOT])
    if not (np.isfinite(obs).all() and (np.abs(obs / cur - 1.0) < 0.4).all()):
        return st
    rate = max(FOOT_RATE, 1.0 / (FOOT_PRIOR + st.foot_n + 1))
    return replace(st, foot=cur + rate * (obs - cur), foot_n=st.foot_n + 1)


def _nearest_shoulder(top: np.ndarray, band: np.ndarray, x: np.ndarray, H: float) -> int:
    """The shoulder-height blob nearest the camera within reach of the shoulder track."""
    cand = np.flatnonzero(band & (np.abs(top[:, 0] - x[0]) < 0.3 * H))
    if cand.size == 0:
        return -1
    return int(cand[np.argmin(top[cand, 1])])


def _acquire_shoulder(floor: np.ndarray, ok: np.ndarray, band: np.ndarray, H: float) -> int:
    """The first shoulder: a shoulder-height blob with body markers below it.

    Of the candidates with the most support, the one nearest the camera wins: the far
    shoulder can peek over the near one.
    """
    body = ok & (floor[:, 2] > 0.3 * H) & (floor[:, 2] < 0.8 * H)
    cands = []
    for i in np.flatnonzero(band):
        near = body & (np.abs(floor[:, 0] - floor[i, 0]) < 0.3 * H)
        near &= np.abs(floor[:, 1] - floor[i, 1]) < 0.35 * H
        n = int(near.sum())
        # The near shoulder stands out toward the camera from the hips and thighs (all of
        # them); a far shoulder (seen first as the subject turns into view) lies behind.
        if n >= 3 and floor[i, 1] < np.min(floor[near, 1]) + 0.05 * H:
            cands.append((n, -floor[i, 1], int(i)))
    if not cands:
        return -1
    best = max(c[0] for c in cands)
    return max(c for c in cands if c[0] >= best - 1)[2]


def _predictions(
    st: LabelState, geo: Geometry, sho: np.ndarray, near: str, direction: int, frame_idx: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-marker prediction (f, e, h) and sigma (20, 3): track if fresh, else the model."""
    p = st.params
    H = geo.sho_h
    pred = np.full((20, 3), np.nan)
    sig = np.full((20, 3), np.inf)
    tracked = np.zeros(20, bool)
    for side in ("near", "far"):
        for site in SITES:
            i = MARKER_INDEX[_name(side, site, near)]
            off = geo.rel_sho(side, site)
            pred[i] = (sho[0] + off[0], sho[1] + off[1], off[2])
            if site in ("ASI", "PSI"):
                # The trunk leans while walking (the pelvis shifts along the walk relative
                # to the shoulder); depth on the pelvis silhouette is poor.
                sig[i] = (0.12 * H, 0.25 * H, 0.03 * H)
            elif site in ("HIP", "SHO"):
                sig[i] = (0.12 * H, 0.08 * H, 0.03 * H)
            else:
                # Legs swing: along the walk only the rough reach of a stride is known.
                sig[i] = (0.3 * H, 0.08 * H, 0.1 * H)
            age = frame_idx - st.seen[i]
            if 0 < age <= p["track_age"] + 1 and np.isfinite(st.last[i]).all():
                t = st.last[i] + st.vel[i] * age
                pred[i] = (direction * t[0], t[1], t[2])
                s = 30.0 + 20.0 * age
                se = 0.25 * H if site in ("ASI", "PSI") else s + 20.0
                sig[i] = (s + 0.3 * abs(st.vel[i][0]), se, s)
                tracked[i] = True
    return pred, sig, tracked


def _pelvis(fr: _Frame, geo: Geometry, sho: np.ndarray, H: float, gate: float) -> None:
    """Steps 5-6: the pelvis as a rigid cluster (bottom-mode positions).

    Every assignment of the pelvis-band blobs to near (PSI, HIP, ASI) and far ASI is scored
    by the tracks (or the loose standing offsets from the shoulder: the trunk leans while
    walking), the rigid distances among them, the hard order PSI < HIP < ASI along the
    walking direction with HIP below PSI and ASI, and the far ASI deeper than the near one.
    The far PSI sits ~60 mm behind the near one, closer than the depth error of a marker
    on the silhouette: it is not labelled. Labels another blob would fit about as well
    are left out.
    """
    qb = fr.qm[:, CLUSTER_MODES.index("bottom")]
    cand = np.flatnonzero(
        fr.free
        & (qb[:, 2] > 0.5 * H)
        & (qb[:, 2] < 0.85 * H)
        & (np.abs(qb[:, 0] - sho[0]) < 0.35 * H)
        & (np.abs(qb[:, 1] - sho[1]) < 0.45 * H)
    )
    K = cand.size
    if K == 0:
        return
    near, far = fr.near, ("L" if fr.near == "R" else "R")
    # The far PSI takes part so that, when seen, it absorbs its blob instead of letting
    # another label take it; it is never published (see above).
    names = (("near", "PSI"), ("near", "HIP"), ("near", "ASI"), ("far", "ASI"), ("far", "PSI"))
    idx = [MARKER_INDEX[_name(sd, st, near)] for sd, st in names]
    # Near and far ASI differ mostly in depth, which the silhouette spoils: the far ASI
    # (and PSI) only absorb their blobs, and a near label that could as well be the far
    # one is dropped by the ambiguity test.
    hidden = {MARKER_INDEX[f"{far}_PSI"], MARKER_INDEX[f"{far}_ASI"]}
    publish = set(idx) - hidden
    if not fr.publish_asis_psis:
        publish = {MARKER_INDEX[f"{near}_HIP"]}
    if K > 7:
        # Keep the 7 nearest the expected pelvis height.
        hp = np.mean([geo.rel_sho("near", s)[2] for s in ("PSI", "HIP", "ASI")])
        cand = cand[np.argsort(np.abs(qb[cand, 2] - hp))[:7]]
        K = 7
    T = _tuples(K, 5)
    cost = _base_cost(fr, idx, cand, T)
    pts = _slots(fr, idx, cand, T)
    present = T < K
    off = [geo.rel_sho(sd, st) for sd, st in names]
    fh = [0, 2]  # sagittal (f, h), as in _rigid
    for a, b in ((0, 1), (1, 2), (0, 2), (2, 3), (0, 4), (3, 4)):
        d0 = float(np.linalg.norm(off[a][fh] - off[b][fh]))
        both = present[:, a] & present[:, b]
        cost[both] += _rigid(pts[both, a], pts[both, b], d0)
    for a, b in ((0, 1), (1, 2), (0, 2)):
        both = present[:, a] & present[:, b]
        cost[both & ~(pts[:, a, 0] < pts[:, b, 0])] = np.inf
    for a in (0, 2):
        both = present[:, a] & present[:, 1]
        cost[both & ~(pts[:, 1, 2] < pts[:, a, 2])] = np.inf
    # Near and far ASI both seen: the near one is the nearer (a relative test survives the
    # silhouette's depth bias better than the absolute depth does).
    both = present[:, 2] & present[:, 3]
    cost[both & ~(pts[:, 2, 1] < pts[:, 3, 1])] = np.inf
    both = present[:, 4] & present[:, 3]
    cost[both & ~(pts[:, 4, 0] < pts[:, 3, 0])] = np.inf
    m = int(np.argmin(cost))
    if not np.isfinite(cost[m]):
        return
    keep = _unambiguous(cost, T, m, K, fr.ambiguity)
    for k, i in enumerate(idx):
        if T[m, k] < K and i in hidden:
            fr.free[cand[T[m, k]]] = False
        elif i not in publish:
            if T[m, k] < K:
                fr.free[cand[T[m, k]]] = False
        elif keep[k] and _unary(fr, i, cand[T[m, k] : T[m, k] + 1])[0] <= 3 * gate**2:
            fr.assign[i] = int(cand[T[m, k]])
            fr.free[cand[T[m, k]]] = False


def _lower(fr: _Frame, geo: Geometry, sho: np.ndarray, H: float, gate: float) -> None:
    """Steps 7-10: near foot (triangle model), far heel and toe, then THI and KNE."""
    q = fr.qm[:, 0]
    near, far = fr.near, ("L" if fr.near == "R" else "R")
    hip_i = MARKER_INDEX[f"{near}_HIP"]
    hip = fr.pos(hip_i)[fr.assign[hip_i]] if fr.assign[hip_i] >= 0 else None
    body = (
        fr.free
        & (q[:, 2] > -0.05 * H)
        & (np.abs(q[:, 0] - sho[0]) < 0.65 * H)
        & (q[:, 1] - sho[1] > -0.3 * H)
        & (q[:, 1] - sho[1] < 0.5 * H)
    )
    cand = np.flatnonzero(body & (q[:, 2] < 0.3 * H))
    if cand.size > 9:
        # The foot and shank markers are the lowest on the body.
        cand = cand[np.argsort(q[cand, 2])[:9]]
    K = cand.size
    chosen: dict[int, int] = {}
    tf = None
    if K:
        foot_idx = [MARKER_INDEX[f"{near}_{s}"] for s in NEAR_FOOT]
        T = _tuples(K, 4)
        cost = _base_cost(fr, foot_idx, cand, T)
        pts = _slots(fr, foot_idx, cand, T)
        present = T < K
        pairs = [
            (1, 2, geo.d("ANK", "HEE"), False),
            (1, 3, geo.d("ANK", "TOE"), False),
            (2, 3, geo.d("HEE", "TOE"), False),
        ]
        for a, b, d0, loose in pairs:
            both = present[:, a] & present[:, b]
            cost[both] += _rigid(pts[both, a], pts[both, b], d0, loose)
        # One foot's markers lie at about one depth (silhouette depth errors of tens of mm
        # allowed): the far foot is ~100-200 mm deeper.
        for a, b in ((1, 2), (1, 3), (2, 3), (0, 1)):
            both = present[:, a] & present[:, b]
            cost[both] += ((pts[both, a, 1] - pts[both, b, 1]) / 80.0) ** 2
        # The tibia wand: somewhere on the lower shank, side-independent bounds.
        shank = geo.d("KNE", "ANK")
        both = present[:, 0] & present[:, 1]
        cost[both] += _interval(pts[both, 0], pts[both, 1], 0.12 * shank, 0.8 * shank)
        allp = present.all(axis=1)
        if allp.any():
            sag = pts[allp][:, :, [0, 2]]  # (f, h)
            out = _triangle_outside(sag[:, 0], sag[:, 3], sag[:, 2], sag[:, 1])
            cost[allp] += (out / 15.0) ** 2
        # Hard: the tibia marker above the ankle one.
        # Even pitched 60 deg, the toe stays half a foot length ahead of the heel (a tibia
        # marker, above the ankle, does not).
        reach = 0.5 * geo.d("HEE", "TOE")
        ht = present[:, 2] & present[:, 3]
        cost[ht & ~(pts[:, 3, 0] > pts[:, 2, 0] + reach)] = np.inf
        ta = present[:, 0] & present[:, 1]
        cost[ta & ~(pts[:, 0, 2] > pts[:, 1, 2] - 20.0)] = np.inf
        # The heel and toe markers never rise far above the ankle one (a plantarflexed
        # foot lifts the heel to about the ankle's level).
        for k, margin in ((2, 60.0), (3, 90.0)):
            ak = present[:, 1] & present[:, k]
            cost[ak & ~(pts[:, k, 2] < pts[:, 1, 2] + margin)] = np.inf
        # A shank marker never drops far below its standing height while walking.
        ank_h = geo.rel_sho("near", "ANK")[2]
        cost[present[:, 0] & ~(pts[:, 0, 2] > ank_h + 0.1 * shank)] = np.inf

        # Far heel and toe, completing the best near-foot hypotheses.
        # The far tibia wand (often seen below the near knee) takes part only to absorb its
        # blob: otherwise it passes for a hidden near tibia or heel.
        far_idx = [MARKER_INDEX[f"{far}_{s}"] for s in ("HEE", "TOE", "TIB")]
        T2 = _tuples(K, 3)
        c2 = _base_cost(fr, far_idx, cand, T2)
        p2 = _slots(fr, far_idx, cand, T2)
        pres2 = T2 < K
        both2 = pres2[:, 0] & pres2[:, 1]
        c2[both2] += _rigid(p2[both2, 0], p2[both2, 1], geo.d("HEE", "TOE"))
        c2[both2 & ~(p2[:, 1, 0] > p2[:, 0, 0] + reach)] = np.inf
        for k in (0, 1):
            tk = pres2[:, 2] & pres2[:, k]
            c2[tk & ~(p2[:, 2, 2] > p2[:, k, 2] + 0.1 * shank)] = np.inf
        order = np.argsort(cost)[:30]
        total = np.full((len(order), len(T2)), np.inf)
        for r, m in enumerate(order):
            if not np.isfinite(cost[m]):
                continue
            used = T[m][T[m] < K]
            clash = (np.isin(T2, used) & pres2).any(axis=1)
            cc = c2.copy()
            cc[clash] = np.inf
            # The far foot is deeper than the near one.
            ne = pts[m, present[m], 1]
            if ne.size:
                depth_near = float(np.mean(ne))
                for k in range(2):
                    cc[pres2[:, k] & (p2[:, k, 1] < depth_near + 20.0)] += 9.0
                # An absorber must be clearly far-side: it only ever removes a blob.
                cc[pres2[:, 2] & (p2[:, 2, 1] < depth_near + 50.0)] = np.inf
            total[r] = cost[m] + cc
        if np.isfinite(total).any():
            r, j = np.unravel_index(int(np.argmin(total)), total.shape)
            m = order[r]
            tf, tp = T[m], T2[j]
            # Ambiguity over the joint hypotheses: a near label whose blob could as well be
            # the far foot's is judged with the far foot's completion counted.
            keep = _unambiguous(total.min(axis=1), T[order], int(r), K, fr.ambiguity)
            # A lone foot marker (the other two of ANK, HEE, TOE missing) has no foot
            # geometry behind it: only a fresh track may name it.
            lone_foot = int((tf[1:] < K).sum()) == 1
            for k, i in enumerate(foot_idx):
                if keep[k] and tf[k] < K:
                    if k > 0 and lone_foot and not (fr.tracked[i] and fr.age[i] == 1):
                        continue
                    chosen[i] = int(tf[k])
            keep2 = _unambiguous(total[r], T2, j, K, fr.ambiguity)
            # A lone far-foot blob is heel or toe only if last frame's track says which.
            lone = int((tp[:2] < K).sum()) == 1
            if tp[2] < K:
                fr.free[cand[tp[2]]] = False  # absorbed, never published
            for k, i in enumerate(far_idx[:2]):
                if not (keep2[k] and tp[k] < K):
                    continue
                if lone and not (
                    fr.age[i] == 1 and _unary(fr, i, cand[tp[k] : tp[k] + 1])[0] < 4.0
                ):
                    continue
                chosen[i] = int(tp[k])
    _accept(fr, chosen, cand, geo, hip, gate)

    # Limb: THI and KNE against HIP, TIB and ANK.
    thi_i, kne_i = MARKER_INDEX[f"{near}_THI"], MARKER_INDEX[f"{near}_KNE"]
    lc = np.flatnonzero(fr.free & body & (q[:, 2] > 0.15 * H) & (q[:, 2] < 0.62 * H))
    K2 = lc.size
    if K2 == 0:
        return
    cap = 7 if hip is not None else 6  # the search grows as (K + 1) ** slots
    if cap < K2:
        lc = lc[np.argsort(np.abs(q[lc, 2] - geo.rel_sho("near", "KNE")[2]))[:cap]]
        K2 = cap
    # The far knee and thigh take part only to absorb their blobs when seen (never
    # published): otherwise a far-leg marker would take a hidden near one's label.
    far_leg = [MARKER_INDEX[f"{far}_KNE"], MARKER_INDEX[f"{far}_THI"]]
    slots = [kne_i, thi_i, *far_leg]
    if hip is None:
        # An unlabelled hip blob (left out as ambiguous) must not pass for the thigh one.
        slots.append(hip_i)
    T3 = _tuples(K2, len(slots))
    c3 = _base_cost(fr, slots, lc, T3)
    p3 = _slots(fr, slots, lc, T3)
    pr = T3 < K2
    thigh, shank = geo.d("HIP", "KNE"), geo.d("KNE", "ANK")
    if hip is None:
        both = pr[:, 4] & pr[:, 0]
        c3[both] += _rigid(p3[both, 4], p3[both, 0], thigh)
        both = pr[:, 4] & pr[:, 1]
        c3[both] += _interval(p3[both, 4], p3[both, 1], 0.1 * thigh, 0.9 * thigh)
        for k in (0, 1):
            both = pr[:, 4] & pr[:, k]
            c3[both & ~(p3[:, 4, 2] > p3[:, k, 2])] = np.inf
    anchors = {}
    for site in ("TIB", "ANK"):
        i = MARKER_INDEX[f"{near}_{site}"]
        if fr.assign[i] >= 0:
            anchors[site] = fr.pos(i)[fr.assign[i]]
    k0 = pr[:, 0]
    for a_pos in anchors.values():
        # The knee is above the shank markers.
        c3[k0 & ~(p3[:, 0, 2] > a_pos[2])] = np.inf
    if "ANK" in anchors:
        c3[k0] += _rigid(p3[k0, 0], anchors["ANK"][None], shank)
        if "TIB" in anchors:
            n = int(k0.sum())
            tib, ank = (np.repeat(anchors[k][None], n, 0) for k in ("TIB", "ANK"))
            c3[k0] += _on_segment(p3[k0, 0], tib, ank)
    elif "TIB" in anchors:
        c3[k0] += _interval(p3[k0, 0], anchors["TIB"][None], 0.2 * shank, 0.88 * shank)
    if hip is not None:
        c3[k0] += _rigid(p3[k0, 0], hip[None], thigh)
        k1 = pr[:, 1]
        c3[k1] += _interval(p3[k1, 1], hip[None], 0.1 * thigh, 0.9 * thigh)
    # Near or far leg: depth relative to the near leg's labelled markers (the standing
    # offsets from the shoulder carry the shoulder's depth error and the trunk's rotation).
    ref = [
        fr.pos(MARKER_INDEX[f"{near}_{s}"])[fr.assign[MARKER_INDEX[f"{near}_{s}"]]]
        for s in ("HIP", "TIB", "ANK")
        if fr.assign[MARKER_INDEX[f"{near}_{s}"]] >= 0
    ]
    if ref:
        ref_e = float(np.mean([r[1] for r in ref]))
        for k in (0, 1):
            c3[pr[:, k]] += ((p3[pr[:, k], k, 1] - ref_e) / 60.0) ** 2
        for k in (2, 3):
            c3[pr[:, k] & (p3[:, k, 1] < ref_e + 50.0)] = np.inf
    kne_h = geo.rel_sho("near", "KNE")[2]
    for k in (0, 1):
        c3[pr[:, k] & ~(p3[:, k, 2] > 0.6 * kne_h)] = np.inf
    both = pr.all(axis=1) if hip is None else pr[:, :2].all(axis=1)
    c3[both] += _interval(p3[both, 0], p3[both, 1], 0.1 * thigh, 0.9 * thigh)
    if hip is not None:
        n = int(both.sum())
        c3[both] += _on_segment(np.repeat(hip[None], n, 0), p3[both, 1], p3[both, 0])
    c3[both & ~(p3[:, 1, 2] > p3[:, 0, 2])] = np.inf
    j = int(np.argmin(c3))
    if not np.isfinite(c3[j]):
        return
    keep = _unambiguous(c3, T3, j, K2, fr.ambiguity)
    chosen = {i: int(T3[j, k]) for k, i in enumerate((kne_i, thi_i)) if keep[k]}
    for k in range(2, len(slots)):
        if T3[j, k] < K2:
            fr.free[lc[T3[j, k]]] = False
    _accept(fr, chosen, lc, geo, hip, gate)


RIGID = (
    ("ANK", "HEE", False),
    ("ANK", "TOE", False),
    ("HEE", "TOE", False),
    ("KNE", "ANK", False),
    ("HIP", "KNE", False),
)
# Wand markers: (wand, joint, reference segment, lower, upper fraction of its length).
WAND = (
    ("TIB", "ANK", ("KNE", "ANK"), 0.12, 0.8),
    ("TIB", "KNE", ("KNE", "ANK"), 0.2, 0.88),
    ("THI", "HIP", ("HIP", "KNE"), 0.1, 0.9),
    ("THI", "KNE", ("HIP", "KNE"), 0.1, 0.9),
)


def _accept(
    fr: _Frame,
    chosen: dict[int, int],
    cand: np.ndarray,
    geo: Geometry,
    hip: np.ndarray | None,
    gate: float,
) -> None:
    """Step 10 gate: drop a label that breaks its track or a rigid distance to an accepted
    or co-chosen marker (both ends of a broken distance go: which one is wrong is unknown).
    """
    pos = {MARKER_NAMES[i]: fr.pos(i)[cand[k]] for i, k in chosen.items()}
    for i in np.flatnonzero(fr.assign >= 0):
        pos.setdefault(MARKER_NAMES[i], fr.pos(i)[fr.assign[i]])
    bad: set[int] = set()
    for i, k in chosen.items():
        if _unary(fr, i, np.array([cand[k]]))[0] > 3 * gate**2:
            bad.add(i)
    for side in (fr.near, "L" if fr.near == "R" else "R"):
        for a, b, loose in RIGID:
            na, nb = f"{side}_{a}", f"{side}_{b}"
            if na in pos and nb in pos:
                e = _rigid(pos[na][None], pos[nb][None], geo.d(a, b), loose)[0]
                if e > gate**2:
                    for n in (na, nb):
                        if MARKER_INDEX[n] in chosen:
                            bad.add(MARKER_INDEX[n])
        for w, j, (r0, r1), lo, hi in WAND:
            na, nb = f"{side}_{w}", f"{side}_{j}"
            if na in pos and nb in pos:
                d0 = geo.d(r0, r1)
                e = _interval(pos[na][None], pos[nb][None], lo * d0, hi * d0)[0]
                if e > gate**2:
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
    pos = np.asarray(mk.position, dtype=np.float64).reshape(-1, 3, 3)
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
# Markers the gait stage uses (knee angle HIP-KNE-ANK, heel and toe events, stride).
GAIT_SITES = ("HIP", "KNE", "ANK", "HEE", "TOE")


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
    every such visible marker labelled); ``accuracy_gait`` (share of frames without a
    wrong HIP, KNE, ANK, HEE or TOE label, the markers the gait stage uses);
    ``per_marker_recall`` and ``per_marker_precision``.
    """
    truth = {(t.header.trial, t.header.frame): t for t in truth_msgs}
    frames = ok_frames = labels = correct = visible = hit = complete = ok_gait = 0
    wrong_by = np.zeros(20)
    labels_by = np.zeros(20)
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
        gait_wrong = False
        for i in np.flatnonzero(np.isfinite(px).all(axis=1)):
            labels += 1
            labels_by[i] += 1
            d = np.hypot(*(tp - px[i]).T)
            # The label's own marker must lie within tol_px, and no visible marker may be
            # nearer by more than 1 px: a blob where two markers overlap (near and far ASI
            # seen end-on) is right for either, and a partly hidden marker (flagged
            # occluded, its blob displaced) still counts.
            dv = np.where(vis, d, np.inf)
            j = int(np.argmin(dv))
            own = float(d[i]) if np.isfinite(d[i]) else np.inf
            if own <= tol_px and own <= dv[j] + 1.0:
                good[i] = vis[i]
            else:
                n_wrong += 1
                wrong_by[i] += 1
                gait_wrong |= MARKER_NAMES[i][2:] in GAIT_SITES
                continue
            correct += 1
        ok_frames += n_wrong == 0
        ok_gait += not gait_wrong
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
        "accuracy_gait": ok_gait / frames if frames else nan,
        "per_marker_precision": {
            MARKER_NAMES[i]: float(1 - wrong_by[i] / labels_by[i])
            for i in range(20)
            if labels_by[i]
        },
        "per_marker_recall": {
            MARKER_NAMES[i]: float(per_hit[i] / per_vis[i]) for i in range(20) if per_vis[i]
        },
    }
