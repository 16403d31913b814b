"""Stage ``label``: marker labelling (Alg. 5) in 3D, in the floor frame of the calibration.

Input: ``markers`` (:class:`Markers3D`) of the walking trials, with the ``calibration``
record and the ``model`` (:class:`SubjectModel`) as side inputs. Output: ``labelled``
(:class:`LabelledMarkers`), the 20 named markers, each position taken under the marker's
own Alg. 3 cluster mode (``gaitflow.markers.cluster_mode``), and the blobs left unnamed
(``spare_pixel``, and ``spare_heel``: where a heel on each would be published), which the
gait stage's heel extension may take.

Per frame (Alg. 5, read in 3D; see docs/readme/labelling.md):

1. every blob is mapped to the floor frame under each cluster mode: a along the walking
   line (toward +u), e horizontal away from the camera, h height above the floor (mm); a
   blob over ``HUGE_BLOB`` times the frame's median radius is no marker (``_huge``);
2. the shoulder (SHO) is predicted by a constant-velocity Kalman filter (filterpy's equations,
   position + velocity in 3D) and taken as the shoulder-height blob nearest the prediction
   (or a clearly nearer-to-camera one at the same place: the near shoulder); without one
   the prediction stands in for up to ``max_missed`` frames (steps 1-3); missing frames
   count as misses and a track back after 3 restarts; a blob ``far_sho_mm`` deeper than the
   track (the deeper of its last and predicted depth; the far shoulder) never continues
   it. The first shoulder is a shoulder-height blob with body markers below it and nearer
   the camera than they are;
3. the walking direction is the sign of the shoulder's velocity along a (first sight:
   toward the far end of the walkway, or, when a track that ended for misses restarts
   within ``restart_frames`` frames, the shoulder blob's move since the last frame
   (``_shoulder_move``), or in mid-walkway the lost track's direction; near an end without
   a move, labels wait until the new track walks along the line); then ``flip_frames``
   frames against it to change).
   The side facing the camera follows (walking toward +u shows the right side). A change of
   direction resets every track and re-acquires the near shoulder: the return pass shows
   the other side (the L/R swap). While turning (slow along the line, or heading off it)
   nothing is labelled, the shoulder included (its track may move to the other shoulder as
   it comes nearer, and the side follows the direction only once the turn is done);
4. upper body (steps 5-6): every assignment of the pelvis-band blobs to near PSI, HIP, ASI
   and far ASI, PSI (absorbers, never published) is scored (vectorised) by the tracks or
   the model's standing offsets from the shoulder, sagittal rigid distances, and the hard
   order PSI < HIP < ASI along the walking direction, HIP below every ASI and PSI by
   ``HIP_DROP`` of its standing drop, far ASI deeper; blobs that stood still while the
   shoulder walked are no candidates (``_still``);
5. lower body (steps 7-10): every assignment of the low blobs to the near foot (TIB, ANK,
   HEE, TOE) is scored by the foot's sagittal lengths (ANK-HEE, ANK-TOE, HEE-TOE: the
   model's, refined online from walking frames, see ``_learn_foot``), one depth for the
   foot, the wand bounds of TIB (side-independent, ``_interval``), the triangle foot model
   (ANK inside triangle TIB-TOE-HEE) and the tracks, under hard rules (toe half a foot
   ahead of the heel, or below it in a steeply pitched foot, ``toe_ahead``; tibia above
   ankle, heel and toe not far above the ankle, heel and toe within the tibia wand's
   reach: its highest place on the shank plus the ankle's distance to them); the best
   ones are completed with the far heel, toe and tibia (the far tibia only absorbs its
   blob; rigid foot, deeper than the near foot, by ``FAR_NEW_DEPTH`` without a fresh
   track; a lone far blob only on last frame's track, and not when the other site's
   live track lies nearer it, in (forward, height) or across its viewing ray); ambiguity
   is judged on the joint hypotheses, for the near labels and the far ones alike (a foot
   label is ambiguous too when the other foot, or for a near label another near foot
   marker, could as well take its blob, its own slot left empty: ``_clear_of_other_markers``);
   a lone near foot marker, or an ankle whose heel and toe that test left out, needs a
   fresh track. Foot tracks widen with the time unseen
   (``FOOT_SPEED_SIG``: swing onset); an untracked far heel (toe) pays for a blob the near
   heel's (toe's) fresh track claims, and a tracked thigh wand for one the knee's fresh
   track claims (judged across the blob's viewing ray, along which a layer in front moves
   it); without a fresh knee track, a blob at the thigh's length from the hip is left to the
   limb search (``KNEE_RING``). Then the limb (KNE: thigh and shank lengths to HIP and
   ANK; THI and TIB on their segments, ``_on_segment``, up to the subject's standing
   offset off the segment's line; the thigh wand above the knee marker, always, and never
   more than ``THI_RISE`` of the thigh above its standing height; near knee
   and thigh at the near leg's depth, far knee and thigh, deeper, absorb their blobs; the
   pelvis's hip label is a slot too, and dropped when the leg below contradicts it (an
   untracked hip alone in the pelvis also pays for its height off the labelled shoulder's,
   ``HIP_BELOW_SHO_SIG``); the
   blob on the knee's fresh track is kept from the foot search).
   Segment lengths more than 25 % off the stature-scaled template fall back to it (a
   static labelling error);
6. a label is left NaN rather than guessed when another blob fits it almost as well
   (``ambiguity``) or it breaks a track gate or a rigid distance: an occluded marker gives a
   gap, not a wrong label. Blobs left over (stray reflectors, far-side leg markers) stay
   unlabelled. A marker whose prediction projects outside the image (``view_gate``: the
   subject entering or leaving the view) takes no blob: otherwise the search, which pays
   for every label it leaves out, shifted the chain (the tibia label on the ankle, the
   ankle's on the heel) as a leg left the field of view.

Published positions: each marker's own cluster mode (a knee, tibia or ankle may take the
bottom mode's layer when that one fits better the depth of a marker on the same segment,
or without one continues its own depth, ``leg_layer``; a hip, whose own mode is the bottom
one, may likewise take the normal mode's layer when that one continues its depth). The
heels are
published at their surface point (``heel_side_on``, departure): locate puts every marker
one radius plus base in front of the surface it sits on (``surface_offset_mm``), right
for a marker facing the camera; a heel marker sits on the back of the heel and is seen
side-on, so the surface beside it lies at its centre's depth. Measured on the simulator
(heels in stance, 5 trials): depth 15 mm too near with the offset, which shortened every
step and stride by 0.6 %. A near heel named on a blob where it merged with the ankle is
moved to the heel by the subject model (``merged_heel_ratio``, :func:`merged_heel`).

Far-side SHO, HIP, THI, KNE, TIB and ANK face away from the camera in a side view and are
never published; nor, by default, the near ASI and PSI (``publish_asis_psis``).
Conventions: (20, ...) arrays follow ``gaitflow.markers.MARKER_NAMES``; camera space X
right, Y down, Z forward, mm; pixels (u, v); NaN = missing.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any

import numpy as np
from gaitflow.schemas import CalibrationRecord, LabelledMarkers, Markers3D, Message, SubjectModel
from gaitflow.stages.base import StageSpec
from gaitflow.stages.model import (
    CAMERA_HEIGHT,
    TEMPLATE_SHO_HEIGHT,
    FloorFrame,
    template_layout,
)

from gaitflow.camera import Camera, doc_number
from gaitflow.errors import InputError, StageError
from gaitflow.markers import CLUSTER_MODES, MARKER_INDEX, MARKER_NAMES, SITES, cluster_mode
from gaitflow.params import Param, ParamSet

NAME = "label"

PARAMS = ParamSet(
    NAME,
    (
        Param(
            "fps",
            float,
            0.0,
            "Hz",
            "nominal frame rate (frame index -> time); 0 = the session camera.json's (carried"
            " by the calibration record), else 30",
            0.0,
            1000.0,
        ),
        Param(
            "leg_layer",
            str,
            "track",
            "",
            "knee, tibia, ankle (hip): own cluster mode, or the bottom (normal) mode's layer "
            "where it fits a wand on the same segment, or continues the last depth "
            "(departure)",
            choices=("own", "track"),
        ),
        Param(
            "max_missed",
            int,
            5,
            "frames",
            "frames the shoulder may be predicted without a detection before the track ends",
            0,
            1000,
        ),
        Param(
            "restart_frames",
            int,
            10,
            "frames",
            "a shoulder track that starts within this many frames of the last one's end takes"
            " the walking direction from the shoulder blob's move (a track lost mid-walkway"
            " for a few frames, not a new pass)",
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
        Param(
            "sho_reach",
            float,
            0.1,
            "x shoulder height",
            "a restarted shoulder track's blob is last frame's blob within this reach (3D) when"
            " its move decides the direction (a walking shoulder moves 10-50 mm per frame)",
            0.01,
            1.0,
        ),
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
            "view_gate",
            bool,
            True,
            "",
            "a marker whose prediction projects outside the image (the calibration record's"
            " camera) takes no blob",
        ),
        Param(
            "heel_side_on",
            bool,
            True,
            "",
            "publish the heel markers at the surface point, without locate's offset toward"
            " the camera: a heel marker is seen side-on, with no surface behind it",
        ),
        Param(
            "merged_heel_ratio",
            float,
            1.4,
            "x median r_m",
            "a near heel whose blob's marker radius is at least this many times the frame's"
            " median, with the ankle unlabelled, is heel and ankle merged into one blob: the"
            " heel is published half the model's ankle-to-heel vector behind it; 0 = off",
            0.0,
            10.0,
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
            "far_sho_mm",
            float,
            80.0,
            "mm",
            "a shoulder-height blob this much deeper than the shoulder track is the far"
            " shoulder, never the track's",
            0.0,
        ),
        CAMERA_HEIGHT,
    ),
)

DEFAULT_FPS = 30.0  # Kinect v2, when neither the parameter nor the session says
NEAR_FOOT = ("TIB", "ANK", "HEE", "TOE")
HEELS = np.isin(np.arange(20), [MARKER_INDEX["L_HEE"], MARKER_INDEX["R_HEE"]])
# Segments whose measured length is checked against the stature-scaled template, and the
# relative deviation beyond which the template's length is used instead.
SEGMENTS = (("HIP", "KNE"), ("KNE", "ANK"), ("ANK", "HEE"), ("ANK", "TOE"), ("HEE", "TOE"))
PLAUSIBLE = 0.25
# The foot triangle (ANK-HEE, ANK-TOE, HEE-TOE) and the range of a measured foot length
# against the template's within which it is kept (Geometry; other segments: PLAUSIBLE).
FOOT = (("ANK", "HEE"), ("ANK", "TOE"), ("HEE", "TOE"))
FOOT_SCALE = (0.5, 2.0)
# The pelvis search's slots (_pelvis).
PELVIS = (("near", "PSI"), ("near", "HIP"), ("near", "ASI"), ("far", "ASI"), ("far", "PSI"))
MISS_COST = 9.0  # a missing label costs as much as a 3-sigma fit
# A blob whose radius exceeds this many times the frame's median is no marker (_huge).
HUGE_BLOB = 3.0
# Share of its standing drop below the ASI and PSI that the hip keeps while walking (0.25
# until the twenty-sixth session; README labelling section, "The hip kept 0.4 of its
# drop below the spines").
HIP_DROP = 0.4
# The middle of the walkway (fractions of its length L): a shoulder track restarting here
# within restart_frames of the last one's end, with no move to measure, keeps its direction
# (nobody turns round mid-walkway in a third of a second; near the ends they may have).
MID_WALKWAY = (0.25, 0.75)
# Foot tracks (ANK, HEE, TOE): the forward speed's uncertainty, mm/s; the forward sigma grows
# by it times the time since last seen (see _predictions).
FOOT_SITES = [SITES.index(s) for s in ("ANK", "HEE", "TOE")]
FOOT_SPEED_SIG = 2400.0
# Track claims (squared sigma; see _lower): a far heel or toe without a fresh track pays a
# miss for a blob that the same site's fresh near track predicts within CLAIM_SIG2, and the
# thigh wand for a blob that the knee's fresh track predicts so (across its viewing ray).
CLAIM_SIG2 = 4.0
# A far heel or toe without a fresh track pays a miss unless it lies this much (mm) deeper
# than the near foot's mean depth (20 mm with a fresh track; see _lower).
FAR_NEW_DEPTH = 40.0
# How much deeper than its standing depth from the shoulder track a near tibia wand may
# lie, mm. Measured on four cached set-ups (base, near, slow, the held-out seven), from
# that reference: the near tibia wand at most 49 mm deeper (99th percentile, 4170 views),
# the far heel 53 / 81 / 138 mm (1st, 5th percentile, median), the far tibia wand 159 mm
# and the far ankle 249 mm at their 1st percentile.
NEAR_TIB_DEEP = 80.0
# The same for the near hip, mm: at most 96-143 mm deeper (99th percentile per set-up, 5425
# views over seven cached set-ups, eleven checked), the far thigh 193-241 mm at the median.
NEAR_HIP_DEEP = 160.0
# Half-width (in _rigid sigmas) of the ring at the thigh's length from the hip whose blobs
# the foot search leaves to the limb search when the knee has no fresh track (see _lower).
KNEE_RING = 0.5
# Sigma of the hip's height below the shoulder while walking, as a share of the shoulder's
# standing height (2 % is about 25 mm): the pelvis and shoulder bob together, the hip's drop
# below the shoulder marker varying by 1-12 mm (standard deviation per walk and side, five
# walks, the simulator's truth) against 10-40 mm for its height above the floor.
HIP_BELOW_SHO_SIG = 0.02
# Highest rise of the thigh wand above its standing height, as a share of the thigh's
# length: hip flexion of 60 degrees lifts a wand at mid-thigh by a quarter of it.
THI_RISE = 0.5
# The largest standing wand offset off its segment's line taken from a static pose, as a
# share of the segment's length (the 12 trials: up to 0.25, MAC_Walk1's thigh); see _on_segment.
WAND_OFF_MAX = 0.35


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
    # Sagittal distances between the pelvis search's slots (near PSI, HIP, ASI, far ASI,
    # PSI), by slot pair: see _pelvis.
    pelvis_d0: Mapping[tuple[int, int], float] = field(default_factory=dict)
    # Standing signed offset (mm, + = forward) of the THI and TIB wands off their segments'
    # sagittal lines (HIP-KNE, KNE-ANK): see _on_segment.
    wand_off: Mapping[str, float] = field(default_factory=dict)
    # The side ("L" or "R") whose ankle, heel and toe the static pose measured at plausible
    # lengths (FOOT_SCALE), or "" when it did not: that foot's triangle is the subject's.
    foot_side: str = ""
    # Those measured lengths (FOOT order, mm; empty without foot_side): kept apart from
    # ``dist``, which the walk's learned foot replaces (_learned).
    foot_lengths: tuple[float, ...] = ()

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
        implausible: set[tuple[str, str]] = set()
        for a, b in SEGMENTS:
            ia, ib = SITES.index(a), SITES.index(b)
            dt = float(np.linalg.norm(t0[ia] - t0[ib]))
            ratio = dist[ia, ib] / dt
            # Foot markers sit where the lab puts them (a toe marker on the metatarsal
            # head or on the toe's tip, a heel marker high or low on the shoe): the
            # measured foot lengths of the trials are 0.75-1.6 times the template's, so
            # only a foot length outside FOOT_SCALE is a static labelling error (a toe
            # taken for a blob beside the ankle).
            lo, hi = FOOT_SCALE if (a, b) in FOOT else (1.0 - PLAUSIBLE, 1.0 + PLAUSIBLE)
            if not lo <= ratio <= hi:
                dist[ia, ib] = dist[ib, ia] = dt
                implausible.add((a, b))
        fh = [0, 2]  # sagittal (f, h), as in _rigid
        off = [offsets[0 if sd == "near" else 1, SITES.index(s)] for sd, s in PELVIS]
        pelvis_d0 = {
            (a, b): float(np.linalg.norm(off[a][fh] - off[b][fh]))
            for a, b in ((0, 1), (1, 2), (0, 2), (2, 3), (0, 4), (3, 4))
        }
        wand_off = {}
        for w, a, b in (("THI", "HIP", "KNE"), ("TIB", "KNE", "ANK")):
            pa, pw, pb = (near[None, SITES.index(s)] for s in (a, w, b))
            off = float(_wand_offset(pa, pw, pb)[0])
            # A wand far off its segment is a static labelling error, not a wand: at most
            # WAND_OFF_MAX of the segment's length.
            lim = WAND_OFF_MAX * float(dist[SITES.index(a), SITES.index(b)])
            wand_off[w] = float(np.clip(off, -lim, lim)) if np.isfinite(off) else 0.0
        seen = extra.get("measured", {})
        foot_side = ""
        if model is not None and all(seen.get(k) is True for k in ("ANK", "HEE", "TOE")):
            foot_side = "" if implausible & set(FOOT) else model.near_side
        lengths = tuple(float(dist[SITES.index(a), SITES.index(b)]) for a, b in FOOT)
        return cls(
            offsets, dist, sho_h, pelvis_d0, wand_off, foot_side, lengths if foot_side else ()
        )

    def d(self, a: str, b: str) -> float:
        return float(self.dist[SITES.index(a), SITES.index(b)])

    def rel_sho(self, side: str, site: str) -> np.ndarray:
        """Standing offset (forward, e, height) of a site from the near shoulder."""
        return self.offsets[0 if side == "near" else 1, SITES.index(site)]


# --- the shoulder Kalman filter ----------------------------------------------------------


@lru_cache(maxsize=16)
def _kf_model(dt: float) -> tuple[np.ndarray, ...]:
    """Constant-velocity model over (a, e, h, va, ve, vh), mm and mm/s, for a step of dt s.

    Returns read-only (F, Q, H, R, I): transition, white-acceleration process noise,
    measurement (position), measurement noise, identity.
    """
    F = np.eye(6)
    F[:3, 3:] = dt * np.eye(3)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    R = np.eye(3) * 10.0**2
    q = 4000.0**2  # white acceleration (mm/s^2)^2: gait sways the trunk ~ 1-4 m/s^2
    g = np.array([0.5 * dt * dt, dt])
    Q1 = np.outer(g, g) * q
    Q = np.zeros((6, 6))
    for i in range(3):
        Q[np.ix_([i, i + 3], [i, i + 3])] = Q1
    mats = (F, Q, H, R, np.eye(6))
    for m in mats:
        m.flags.writeable = False
    return mats


def _kf_predict(x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Kalman prediction (6,), (6, 6): filterpy's ``KalmanFilter.predict``, same arithmetic."""
    F, Q, _, _, _ = _kf_model(dt)
    return np.dot(F, x), np.dot(np.dot(F, P), F.T) + Q


def _kf_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with a position z (3,): filterpy's ``KalmanFilter.update`` (Joseph
    form), same arithmetic, without building a filter object per frame."""
    _, _, H, R, eye = _kf_model(dt)
    y = z - np.dot(H, x)
    PHT = np.dot(P, H.T)
    S = np.dot(H, PHT) + R
    K = np.dot(PHT, np.linalg.inv(S))
    x = x + np.dot(K, y)
    I_KH = eye - np.dot(K, H)
    return x, np.dot(np.dot(I_KH, P), I_KH.T) + np.dot(np.dot(K, R), K.T)


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
    fps: float = DEFAULT_FPS  # the ``fps`` parameter, else the calibration record's camera fps
    sho_x: np.ndarray | None = None  # (6,) KF state, None = no track
    sho_cov: np.ndarray | None = None
    sho_missed: int = 0
    sho_lost: int = -(10**9)  # frame in which the last shoulder track ended for misses
    sho_lost_direction: int = 0  # that track's walking direction (0: none yet)
    direction: int = 0
    flip_count: int = 0
    walked: bool = False
    last: np.ndarray | None = None
    vel: np.ndarray | None = None
    seen: np.ndarray | None = None
    frames: int = 0
    # (N, 3) last frame's blobs (a, e, h), normal mode, mm: which blobs stood still
    # (_still), and a restarted shoulder track's first move (_shoulder_move).
    prev_q: np.ndarray | None = None
    labelled: int = 0
    foot: np.ndarray | None = None  # (3,) learned ANK-HEE, ANK-TOE, HEE-TOE, mm
    foot_n: int = 0
    # (calibration, model, FloorFrame, Geometry, Camera or None, layer_reference): the side
    # inputs, and what is derived from them once per side input, not per frame (the
    # camera: the record's, for ``view_gate``).
    sides: (
        tuple[Any, Any, FloorFrame, Geometry, Camera | None, tuple[np.ndarray, np.ndarray]] | None
    ) = None
    # ((20,) camera Z mm, (20,) frame) of each marker's last published position
    leg_depth: tuple[np.ndarray, np.ndarray] | None = None


def init(params: dict[str, Any]) -> LabelState:
    """Initial state; ``params`` are resolved by :data:`PARAMS`."""
    return _reset_tracks(LabelState(params=dict(params), fps=params["fps"] or DEFAULT_FPS))


def _end_shoulder(st: LabelState, frame_idx: int) -> LabelState:
    """The shoulder track ended for misses in frame ``frame_idx``: no track, no direction,
    every marker track reset (see ``sho_lost``)."""
    return _reset_tracks(
        replace(
            st,
            sho_x=None,
            sho_cov=None,
            sho_missed=0,
            direction=0,
            walked=False,
            sho_lost=frame_idx,
            sho_lost_direction=st.direction,
        )
    )


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


@lru_cache(maxsize=64)
def _tuples(k: int, r: int) -> np.ndarray:
    """All r-tuples over k candidates plus 'missing' (index k), distinct when present.

    Rows in lexicographic order (as ``itertools.product``); (M, r) int64, read-only.
    """
    # np.indices enumerates the product in lexicographic order; a pair of slots may share
    # only the 'missing' index.
    T = np.indices((k + 1,) * r).reshape(r, -1).T
    ok = np.ones(len(T), bool)
    for a, b in itertools.combinations(range(r), 2):
        ok &= (T[:, a] != T[:, b]) | (T[:, a] == k)
    out = np.ascontiguousarray(T[ok], dtype=np.int64)
    out.flags.writeable = False
    return out


def _side(p1: np.ndarray, p2: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Signed sagittal distance (mm) of points q from the lines p1 -> p2; arrays (M, 3)."""
    p1, p2, q = p1[:, [0, 2]], p2[:, [0, 2]], q[:, [0, 2]]
    e = p2 - p1
    n = np.linalg.norm(e, axis=1) + 1e-9
    return (e[:, 0] * (q[:, 1] - p1[:, 1]) - e[:, 1] * (q[:, 0] - p1[:, 0])) / n


def _outside(s1: np.ndarray, s2: np.ndarray, s3: np.ndarray, so: np.ndarray) -> np.ndarray:
    """Distance (mm, 0 inside) of a point outside a triangle (a, b, c), from its signed
    distances to the edges a-b, b-c, c-a (s1, s2, s3) and that of c to a-b (so)."""
    orient = np.sign(so)
    d = np.minimum(np.minimum(s1 * orient, s2 * orient), s3 * orient)
    return np.maximum(-d, 0.0)


def _triangle_outside(a: np.ndarray, b: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Sagittal distance (mm, 0 inside) of points p outside triangles (a, b, c); (M, 3)."""
    return _outside(_side(a, b, p), _side(b, c, p), _side(c, a, p), _side(a, b, c))


@dataclass
class _Frame:
    """Working data of one frame (not state)."""

    qm: np.ndarray  # (N, 3, 3) floor coords (f, e, h) of the blobs per cluster mode
    free: np.ndarray  # (N,) bool, blob not yet assigned
    assign: np.ndarray  # (20,) int blob per marker
    pred: np.ndarray  # (20, 3) prediction (f, e, h)
    sig: np.ndarray  # (20, 3) prediction sigma
    near: str
    tracked: np.ndarray  # (20,) bool, prediction from a live track (<= track_age missed)
    ambiguity: float
    age: np.ndarray  # (20,) frames since each marker was last labelled
    publish_asis_psis: bool = True
    still: np.ndarray | None = None  # (N,) bool, blob stood still while the subject walked
    outside: np.ndarray | None = None  # (20,) bool, predicted outside the image: no blob
    # (3,) the camera's centre in these coordinates; None: viewing rays along the e axis
    cam: np.ndarray | None = None

    def pos(self, i: int) -> np.ndarray:
        """(N, 3) blob positions under marker ``i``'s cluster mode."""
        return self.qm[:, MODE_OF[i]]


# Mode each marker is matched under. The output keeps every marker's own cluster mode;
# for matching, ASI and PSI use the normal mode: they sit on the front and back silhouette
# of the pelvis, where the bottom mode's far layer is often the room behind the subject.
# So does the thigh marker: on a wand its ring holds no surface of its own, and the
# farthest layer behind the stick is the other leg or the wall (the nearest is the stick
# or the limb's near side, 30-100 mm off; the farthest 140-1100 mm).
MODE_OF = np.array(
    [
        0 if n[2:] in ("ASI", "PSI", "THI") else CLUSTER_MODES.index(cluster_mode(n))
        for n in MARKER_NAMES
    ]
)


# Each marker's own cluster mode (the output's).
OWN_MODE = np.array([CLUSTER_MODES.index(cluster_mode(n)) for n in MARKER_NAMES])
HEEL_MODE = int(OWN_MODE[MARKER_INDEX["L_HEE"]])  # both heels share it


def _fresh(fr: _Frame, idx: int) -> bool:
    """Marker ``idx`` has a track labelled within the last two frames."""
    return bool(fr.tracked[idx] and fr.age[idx] <= 2)


def _unary(fr: _Frame, idx: int, cand: np.ndarray) -> np.ndarray:
    """Squared-sigma distance of candidate blobs (K,) to marker ``idx``'s prediction."""
    d = (fr.pos(idx)[cand] - fr.pred[idx]) / fr.sig[idx]
    return (d**2).sum(axis=1)


def _across_ray(fr: _Frame, idx: int, cand: np.ndarray) -> np.ndarray:
    """Offset (K, 3) of marker ``idx``'s prediction from the viewing rays of candidate blobs
    (K,), its part along each ray removed.

    A blob's depth may be a layer in front of its marker (an arm, a wand's stick), which
    moves the blob along its viewing ray only. Dropping the e axis (the sagittal plane)
    assumes level rays; from a camera above or below the marker the layer also moves the
    blob in height (a camera 1.2 m high, a child's knee 0.33 m high, 2.75 m away: the arm
    127 mm in front of it read 34 mm high).
    """
    q = fr.pos(idx)[cand]
    if fr.cam is None:
        ray = np.broadcast_to(np.array([0.0, 1.0, 0.0]), q.shape)
    else:
        ray = q - fr.cam
        ray = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    d = fr.pred[idx] - q
    return d - (d * ray).sum(axis=1, keepdims=True) * ray


def _off_ray(fr: _Frame, idx: int, cand: np.ndarray) -> np.ndarray:
    """Squared-sigma distance (K,) of marker ``idx``'s prediction to the viewing rays of
    candidate blobs (K,) (:func:`_across_ray`)."""
    return ((_across_ray(fr, idx, cand) / fr.sig[idx]) ** 2).sum(axis=1)


def _nearer(fr: _Frame, o: int, i: int, cand: np.ndarray) -> bool:
    """Marker ``o``'s prediction lies nearer one candidate blob (1,) than marker ``i``'s, in
    forward and height (depth left out) or across the blob's viewing ray
    (:func:`_across_ray`): either suffices, as the two differ only where depths are unsure
    (from a camera above the foot a blob's depth error also moves it in height; the tracks'
    own depth errors leak into the offset across a descending ray)."""
    sag = [float(np.hypot(*(fr.pos(m)[cand] - fr.pred[m])[0, [0, 2]])) for m in (o, i)]
    ray = [float(np.linalg.norm(_across_ray(fr, m, cand)[0])) for m in (o, i)]
    return sag[0] < sag[1] or ray[0] < ray[1]


def _rigid(pa: np.ndarray, pb: np.ndarray, d0: float, loose: bool = False) -> np.ndarray:
    """Squared-sigma error of sagittal distances |pa - pb| against the model's d0.

    Points are (M, 3) (f, e, h); only (f, h) count. Depth is the noisy axis of a marker on
    a silhouette (tens of mm, more at the heel and pelvis) while (f, h) come from the
    image, so segment lengths are compared in the sagittal plane (the model's are too).
    """
    sig = (20.0 + 0.2 * d0) if loose else (10.0 + 0.1 * d0)
    d = np.hypot(pa[:, 0] - pb[:, 0], pa[:, 2] - pb[:, 2])
    return ((d - d0) / sig) ** 2


# The toe-ahead rule of the foot search (toe_ahead): the toe at least TOE_AHEAD of the
# foot length ahead of the heel (any foot pitched less than TOE_STEEP_DEG), or, in a foot
# pitched toe down by TOE_STEEP_DEG to TOE_PITCH_MAX_DEG, at least TOE_STEEP_LENGTH of it
# from the heel.
TOE_AHEAD = 0.5
TOE_STEEP_DEG = 60.0
TOE_PITCH_MAX_DEG = 80.0
TOE_STEEP_LENGTH = 0.75


def toe_ahead(ph: np.ndarray, pt: np.ndarray, foot: float) -> np.ndarray:
    """Whether toe points can belong to a foot with these heel points (a hard rule of the
    foot search, steps 7-9).

    The toe lies ``TOE_AHEAD`` of the foot length ahead of the heel, which any foot
    pitched less than ``TOE_STEEP_DEG`` (60 deg) satisfies and a tibia marker, above the
    ankle, does not. In early swing the foot pitches further, toe down (up to 83 deg on the
    true markers of the twelve walks; btk_PiG_Motion3_FF on the base set-up, frame 114:
    the heel 200 mm above the toe and 70 mm behind it, and the near foot's four markers
    went unlabelled for three frames):
    there the toe may lie less far ahead if it lies below the heel, pitched at most
    ``TOE_PITCH_MAX_DEG``, and at least ``TOE_STEEP_LENGTH`` of the foot length from it
    (a blob nearer the heel is no toe at any pitch).

    Parameters
    ----------
    ph, pt : (M, 3) heel and toe positions (forward, e, height), mm, oriented floor frame.
    foot : the heel-to-toe sagittal length, mm.

    Returns
    -------
    (M,) bool.
    """
    ahead = pt[:, 0] - ph[:, 0]
    down = ph[:, 2] - pt[:, 2]
    pitch = np.degrees(np.arctan2(down, ahead))
    steep = (pitch >= TOE_STEEP_DEG) & (pitch <= TOE_PITCH_MAX_DEG)
    return (ahead > TOE_AHEAD * foot) | (steep & (np.hypot(ahead, down) > TOE_STEEP_LENGTH * foot))


def _interval(pa: np.ndarray, pb: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Squared-sigma cost of sagittal distances |pa - pb| outside [lo, hi] (0 inside).

    For the wand markers (TIB, THI): where along its segment a wand marker sits varies
    between subjects and between the two legs of one subject (by 50-90 mm in the trials),
    so the static pose's one side does not give the other side's distance.
    """
    d = np.hypot(pa[:, 0] - pb[:, 0], pa[:, 2] - pb[:, 2])
    return (np.maximum(lo - d, 0.0) ** 2 + np.maximum(d - hi, 0.0) ** 2) / 15.0**2


def _wand_offset(pa: np.ndarray, pw: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Signed sagittal distance (mm) of wand points pw off the line pa-pb (all (M, 3)).

    Positive ahead of a segment that points down (pa above pb), in the direction of
    increasing f (forward).
    """
    a, w, b = pa[:, [0, 2]], pw[:, [0, 2]], pb[:, [0, 2]]
    e = b - a
    L = np.sqrt(np.maximum((e**2).sum(axis=1), 1.0))
    return (e[:, 0] * (w[:, 1] - a[:, 1]) - e[:, 1] * (w[:, 0] - a[:, 0])) / L


def _on_segment(
    pa: np.ndarray, pw: np.ndarray, pb: np.ndarray, sig: float = 25.0, off: float = 0.0
) -> np.ndarray:
    """Squared-sigma cost of wand points pw off the sagittal segment pa-pb (all (M, 3)).

    A wand marker projects (sagittally) onto its segment's line, somewhere between the
    joints: the perpendicular distance and the overshoot past either end count. ``off``
    (mm, signed as :func:`_wand_offset`) is the subject's standing offset of the wand off
    the line: a wand pointing partly forward or back projects ahead of or behind the line
    (by up to 120 mm in the trials), and how much differs between the legs (the wand's
    rotation about the segment), so any offset between 0 and ``off`` is free.
    """
    a, w, b = pa[:, [0, 2]], pw[:, [0, 2]], pb[:, [0, 2]]
    e = b - a
    L2 = np.maximum((e**2).sum(axis=1), 1.0)
    t = ((w - a) * e).sum(axis=1) / L2
    s = _wand_offset(pa, pw, pb)
    perp = np.maximum(s - max(off, 0.0), 0.0) + np.maximum(min(off, 0.0) - s, 0.0)
    over = np.sqrt(L2) * (np.maximum(-t + 0.1, 0.0) + np.maximum(t - 0.9, 0.0))
    return (perp**2 + over**2) / sig**2


def _base_cost(U: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(M,) summed unary cost of tuples T (M, r), from U (r, K + 1) (last column: missing)."""
    return U[np.arange(U.shape[0]), T].sum(axis=1)


def _unambiguous(cost: np.ndarray, T: np.ndarray, m: int, K: int, margin: float) -> list[bool]:
    """Per slot of the best tuple ``m``: is every tuple giving the slot another blob clearly
    worse (by ``margin``)? A label that could as well be another blob is left out."""
    other = (T[m] != T) & (T < K)  # (M, r): the slot holds another blob
    alt = np.where(other, cost[:, None], np.inf).min(axis=0)
    return ((T[m] < K) & (alt - cost[m] >= margin)).tolist()


def _clear_of_other_markers(
    total: np.ndarray, leaves: np.ndarray, takes: np.ndarray, margin: float
) -> bool:
    """Is a foot label's blob clearly not another marker's? Every joint hypothesis in which
    the label's slot leaves the blob (``leaves``) while another slot takes it (``takes``:
    the other foot's heel or toe, or for a near label another near foot slot) must cost at
    least ``margin`` more than the best one.

    ``total`` (R, A2): near hypothesis by far completion; ``leaves`` and ``takes`` broadcast
    to it ((R, 1) for the near foot's slots, (1, A2) for the far foot's). The ambiguity
    tests (:func:`_unambiguous`, :func:`_far_unambiguous`) count only hypotheses giving the
    slot another blob: one leaving it empty, its blob going to another marker, never made a
    label ambiguous, however close.
    """
    alt = total[np.broadcast_to(leaves & takes, total.shape)]
    return not alt.size or float(alt.min()) - float(total.min()) >= margin


def _far_unambiguous(
    total: np.ndarray, T2: np.ndarray, j: int, K: int, margin: float
) -> list[bool]:
    """Per slot of the best far completion ``j``: is every joint hypothesis giving the slot
    another blob clearly worse (by ``margin``)?

    ``total`` (R, A2): near hypothesis by far completion. Each far completion counts at its
    best near hypothesis, not only at the chosen one: where the near labels are in doubt,
    a far completion of a near hypothesis about as good can give the far heel or toe
    another blob (the near heel's, when the chosen near hypothesis left it missing or gave
    it to the ankle), and such a far label is as ambiguous as a near one.
    """
    return _unambiguous(total.min(axis=0), T2, j, K, margin)


class _Hyp:
    """Joint hypotheses of one exhaustive search (steps 5-10).

    Every assignment ``T`` (M, r) of the candidate blobs ``cand`` (K,) to the markers ``idx``
    (index K = missing; ``_tuples``). The hard rules come first (:meth:`forbid`); only the
    hypotheses they leave alive, ``rows`` (A,), are scored (:meth:`add`; cost ``c`` (A,),
    from the summed unary cost on). A forbidden hypothesis would cost inf whatever else is
    added, so this is the same as scoring all and setting inf. A term over some slots is
    evaluated on every hypothesis at once (positions ``Q`` (M, r, 3), 0 where a slot is
    missing) and counts (added, or forbids) only where all its slots hold a blob.
    """

    def __init__(self, fr: _Frame, idx: list[int], cand: np.ndarray) -> None:
        self.K, self.r = len(cand), len(idx)
        self.T = _tuples(self.K, self.r)
        self.present = self.T < self.K
        X = fr.qm[cand[:, None], MODE_OF[idx]]  # (K, r, 3) under each slot's mode
        d = (X - fr.pred[idx]) / fr.sig[idx]
        # (r, K + 1) unary cost (as _unary), last column: missing.
        self.U = np.hstack([(d**2).sum(axis=2).T, np.full((self.r, 1), MISS_COST)])
        if fr.outside is not None:
            self.U[fr.outside[idx], : self.K] = np.inf  # only "missing" is left to them
        X0 = np.concatenate([X, np.zeros((1, self.r, 3))])
        self.Q = X0[self.T, np.arange(self.r)]  # (M, r, 3)
        self._bad = np.zeros(len(self.T), bool)
        self._rows: np.ndarray | None = None
        self._c = np.zeros(0)
        self._masks: dict[tuple[int, ...], np.ndarray] = {}

    def _mask(self, slots: tuple[int, ...], present: np.ndarray) -> np.ndarray:
        m = present[:, slots[0]]
        for s in slots[1:]:
            m = m & present[:, s]
        return m

    def forbid(self, slots: tuple[int, ...], ok: Any, where: np.ndarray | None = None) -> None:
        """Hard rule: drop the hypotheses where every slot (and ``where`` (M,)) holds a blob
        and ``ok(positions (M, 3) per slot)`` is False. Before any :meth:`add`."""
        if self._rows is not None:
            raise StageError(NAME, "a hard rule after a cost term (internal)")
        m = self._mask(slots, self.present)
        if where is not None:
            m = m & where
        self._bad |= m & ~ok(*(self.Q[:, s] for s in slots))

    @property
    def rows(self) -> np.ndarray:
        """(A,) the hypotheses the hard rules left."""
        if self._rows is None:
            self._rows = np.flatnonzero(~self._bad)
            self.Qa, self.pa = self.Q[self._rows], self.present[self._rows]
            self._c = _base_cost(self.U, self.T[self._rows])
        return self._rows

    @property
    def c(self) -> np.ndarray:
        """(A,) cost of the hypotheses alive (``rows``)."""
        _ = self.rows
        return self._c

    def add(self, slots: tuple[int, ...], fn: Any, where: np.ndarray | None = None) -> None:
        """c += fn(positions (A, 3) per slot) where every slot (and ``where`` (M,)) holds
        a blob."""
        rows = self.rows
        if slots not in self._masks:
            self._masks[slots] = self._mask(slots, self.pa)
        m = self._masks[slots]
        if where is not None:
            m = m & where[rows]
        self._c += np.where(m, fn(*(self.Qa[:, s] for s in slots)), 0.0)

    @property
    def cost(self) -> np.ndarray:
        """(M,) cost of every hypothesis (inf = forbidden)."""
        full = np.full(len(self.T), np.inf)
        full[self.rows] = self.c
        return full


# --- the per-frame labelling ---------------------------------------------------------------


def label_frame(
    st: LabelState,
    pos: np.ndarray,
    frame_idx: int,
    ff: FloorFrame,
    geo: Geometry,
    radius: np.ndarray | None = None,
    view: Camera | None = None,
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
    radius : (N,) locate's blob radius r_m, px (optional): blobs far larger than the frame's
        median (``_huge``) are no candidates for any label.

    Returns
    -------
    (state, assign) : assign is (20,) int, the blob index per marker, -1 = none.
    """
    p = st.params
    geo = _learned(geo, st)
    H = geo.sho_h
    dt_frames = max(1, frame_idx - st.frame) if st.frame >= 0 else 1
    dt = dt_frames / st.fps
    pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3, 3)
    whole = np.isfinite(pos[:, 0]).all(axis=1)  # the normal mode found a layer
    pos = fill_modes(pos)
    fm = ff.to_floor(pos) if len(pos) else np.zeros((0, 3, 3))
    floor = fm[:, 0]
    ok = np.isfinite(floor).all(axis=1) & ~_huge(radius, len(floor))
    assign = np.full(20, -1)
    # (st.frame and st.frames are updated on the way out.)
    top = fm[:, CLUSTER_MODES.index("top")]
    ah = floor[:, [0, 2]]
    prev_q = st.prev_q if dt_frames == 1 else None

    # Steps 1-3: the shoulder (top mode).
    band = ok & (top[:, 2] > 0.85 * H) & (top[:, 2] < 1.15 * H)
    sho_blob = -1
    if st.sho_x is not None and dt_frames > 1:
        # Frames that never arrived (dropped, or nobody in view) count as misses.
        st = replace(st, sho_missed=st.sho_missed + dt_frames - 1)
    if st.sho_x is not None and st.sho_missed > p["max_missed"]:
        st = _end_shoulder(st, frame_idx)
    if st.sho_x is not None:
        kx, kP = _kf_predict(st.sho_x, st.sho_cov, dt)
        # The gate widens with misses, at most to twice its size: a shoulder that shows up
        # far from a coasting prediction is a new track (e.g. after a turn out of view).
        gate = p["sho_gate_mm"] * min(2.0, 1 + 0.25 * st.sho_missed)
        # Not a blob clearly deeper than the track: the far shoulder, which stays in view
        # a few frames longer when the near one leaves the image at the end of a pass.
        # Measured from the deeper of the last depth and the predicted one: depth noise
        # gives the track a depth velocity toward the camera (±700 mm/s at twice the
        # Kinect's noise), and measured from that prediction alone the true shoulder was
        # refused until the track was lost.
        cand = np.flatnonzero(band & (top[:, 1] < max(kx[1], st.sho_x[1]) + p["far_sho_mm"]))
        if cand.size:
            dist = np.hypot(top[cand, 0] - kx[0], top[cand, 1] - kx[1])
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
                    kx[:3] = top[sho_blob]
        if sho_blob >= 0 and st.sho_missed >= 3:
            # Back after a gap (out of view, turning): start afresh, the subject may have
            # turned round.
            st = _end_shoulder(st, frame_idx)
        elif sho_blob >= 0:
            z = top[sho_blob]
            if z[1] < kx[1] - p["far_sho_mm"]:
                # The blob is the shoulder but its depth is not: a layer taken from an arm
                # in front (134 mm nearer, a low camera 3.5 m away). Taken into the track,
                # it gave it a depth velocity of 1 m/s toward the camera, the shoulder was
                # then "clearly deeper" than the track (the far shoulder's rule above), and
                # the track was lost: seven frames without any label. The trunk cannot
                # come that much nearer within a frame: the track keeps its own depth. (Not
                # the other way: a blob that deep is the track's own shoulder after a drift
                # toward the camera, which the update must undo; deeper still, the far one.)
                z = np.array([z[0], kx[1], z[2]])
            kx, kP = _kf_update(kx, kP, z, dt)
            st = replace(st, sho_x=kx, sho_cov=kP, sho_missed=0)
        elif st.sho_missed < p["max_missed"]:
            st = replace(st, sho_x=kx, sho_cov=kP, sho_missed=st.sho_missed + 1)
        else:
            st = _end_shoulder(st, frame_idx)
    if st.sho_x is None:
        # A pass's first shoulder, and the body blobs below it, only from blobs whose normal
        # mode found a layer: one without is at best half seen (at the image's edge, behind
        # an arm), and with such blobs as support the far shoulder peeking over the near
        # one was taken a few frames before the near one appeared.
        sho_blob = _acquire_shoulder(top, ok & whole, band & whole, H)
        if sho_blob < 0:
            return replace(st, frame=frame_idx, frames=st.frames + 1, prev_q=floor), assign
        x = np.concatenate([top[sho_blob], np.zeros(3)])
        P = np.diag([20.0**2] * 3 + [1500.0**2] * 3)
        st = _reset_tracks(replace(st, sho_x=x, sho_cov=P, sho_missed=0, direction=0, flip_count=0))

    # Direction (with hysteresis) and near side.
    va = float(st.sho_x[3])
    direction, flips = st.direction, st.flip_count
    guessed = False
    if direction == 0:
        # First sight: walking toward the far end of the walkway from where it appears.
        direction = 1 if float(st.sho_x[0]) < 0.5 * ff.length else -1
        if abs(va) > p["dir_speed"]:
            direction = 1 if va > 0 else -1
        elif sho_blob >= 0 and frame_idx - st.sho_lost <= p["restart_frames"]:
            # A track that ended for misses (within restart_frames frames) restarts
            # mid-walkway, where "toward the far end" is a guess: it named the wrong side
            # for the frames the new track needs to gain a velocity. The shoulder blob's
            # move since the last frame tells (a depth glitch of the shoulder can end the
            # track and leave it unacquired for 6 frames, one more than max_missed, the
            # window before). Not at a pass's first sight: a blob entering
            # the image at its edge moves with its visible part.
            da = _shoulder_move(floor[sho_blob], prev_q, p["sho_reach"] * H)
            # Without a walkway (no usable calibration: length 0) nobody is known to be in
            # its middle.
            a_frac = float(st.sho_x[0]) / ff.length if ff.length > 0 else float("nan")
            if abs(da) > p["dir_speed"] * dt:
                direction = 1 if da > 0 else -1
            elif st.sho_lost_direction and MID_WALKWAY[0] < a_frac < MID_WALKWAY[1]:
                # The blob was not in the last frame (missed with the track): in the
                # middle of the walkway nobody turns round within restart_frames, so the
                # lost track's direction stands (a child's shoulder missed three frames
                # running restarted facing the wrong way for 7 frames).
                direction = st.sho_lost_direction
            else:
                # Near an end of the walkway, where people turn round, "toward the far end"
                # is a guess: the track is taken as having walked, so that the turn test
                # holds the labels until its velocity runs along the line (turning in view,
                # the track lost mid-turn restarted on the wrong side).
                guessed = True
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
    walked = st.walked or abs(va) > p["dir_speed"] or guessed
    near = "R" if direction > 0 else "L"
    # Turning: slow along the line, backwards, or heading off the line (the near shoulder
    # swings away from the camera as the body turns).
    ve = float(st.sho_x[4])
    turning = walked and (
        abs(va) < p["turn_speed"] or np.sign(va) != direction or abs(ve) > 0.5 * abs(va)
    )
    if sho_blob >= 0 and not turning:
        # While turning the track may move to the other shoulder as it comes nearer, and
        # which side it is follows the walking direction only once the turn is done.
        assign[MARKER_INDEX[f"{near}_SHO"]] = sho_blob
    if not turning:
        qm = fm.copy()
        qm[:, :, 0] *= direction
        sho = np.array([direction * st.sho_x[0], st.sho_x[1], st.sho_x[2]])
        pred, sig, tracked = _predictions(st, geo, sho, near, direction, frame_idx)
        outside = None if view is None else beyond_image(pred, direction, ff, view)
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
            _still(ah, None if prev_q is None else prev_q[:, [0, 2]], abs(va) * dt),
            outside,
            ff.to_floor(np.zeros(3)) * np.array([direction, 1.0, 1.0]),
        )
        _pelvis(fr, geo, sho, H, p["gate"])
        _lower(fr, geo, sho, H, p["gate"])

    # Track update (floor coords under each marker's own mode, un-oriented).
    last, vel, seen = st.last.copy(), st.vel.copy(), st.seen.copy()
    ii = np.flatnonzero(assign >= 0)
    if ii.size:
        cur = fm[assign[ii], MODE_OF[ii]]
        age = frame_idx - seen[ii]
        fresh = (age > 0) & (age <= p["track_age"] + 1) & np.isfinite(last[ii]).all(axis=1)
        # A knee, tibia or ankle track continues on the bottom mode's layer where that one
        # continues its depth (as _output publishes it): a hand or the other leg passing in
        # front puts the own mode's layer 100+ mm too near for a frame, and the track's
        # depth velocity then sent its next predictions off by that much per frame.
        bot = fm[assign[ii], BOTTOM]
        better = _layer_continues(cur[:, 1], bot[:, 1], last[ii, 1])
        cur = np.where((np.isin(ii, LEG) & fresh & better)[:, None], bot, cur)
        vel[ii] = np.where(fresh[:, None], (cur - last[ii]) / age[:, None], 0.0)
        last[ii] = cur
        seen[ii] = frame_idx
    st = replace(
        st,
        frame=frame_idx,
        frames=st.frames + 1,
        direction=direction,
        flip_count=flips,
        walked=walked,
        last=last,
        vel=vel,
        seen=seen,
        labelled=st.labelled + int((assign >= 0).sum()),
        prev_q=floor,
    )
    if st.direction:
        near = "R" if st.direction > 0 else "L"
        static = np.asarray(geo.foot_lengths) if near == geo.foot_side else None
        st = _learn_foot(st, fm, assign, geo, near, static)
    return st, assign


FOOT_PRIOR = 5.0  # weight of the model's foot, in frames
FOOT_RATE = 0.05  # slowest learning rate (exponential forgetting)
# Largest relative difference of a walking frame's foot lengths from the static pose's
# (same foot) that teaches the foot triangle (_learn_foot).
FOOT_STATIC_GATE = 0.25


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
    st: LabelState,
    fm: np.ndarray,
    assign: np.ndarray,
    geo: Geometry,
    near: str,
    static: np.ndarray | None = None,
) -> LabelState:
    """Refine the foot triangle from a frame with the near ANK, HEE and TOE all labelled.

    The static pose often gives no foot (heel and ankle merge into one blob there, and the
    template's foot may be 20-30 % off the subject's); walking frames separate them. Only
    labels that passed every gate teach, and an observation far off the current
    length is ignored (40 %), so a wrong frame cannot drag the model far. ``static``: the
    static pose's own lengths of this foot, when it measured them (``Geometry.foot_side``);
    an observation more than ``FOOT_STATIC_GATE`` off them is ignored too. Markers on one
    shoe keep their sagittal distances but for the foot's turn out of the sagittal plane
    and the heel's silhouette depth; step by step within 40 % of the last length, wrong
    frames had walked the learned heel from 58 to 36 mm behind the ankle on `shoes` (a
    reflector under the ankle taken for the heel). The other foot's markers may be placed
    otherwise (btk_c3dorg_sample04_Matt), so it learns as before.
    """
    idx = [MARKER_INDEX[f"{near}_{s}"] for s in ("ANK", "HEE", "TOE")]
    if (assign[idx] < 0).any():
        return st
    q = {s: fm[assign[i], MODE_OF[i]] for s, i in zip(("ANK", "HEE", "TOE"), idx, strict=True)}
    cur = np.array([geo.d(a, b) for a, b in FOOT])
    obs = np.array([np.hypot(*(q[a] - q[b])[[0, 2]]) for a, b in FOOT])
    if not (np.isfinite(obs).all() and (np.abs(obs / cur - 1.0) < 0.4).all()):
        return st
    if static is not None and not (np.abs(obs / static - 1.0) < FOOT_STATIC_GATE).all():
        return st
    rate = max(FOOT_RATE, 1.0 / (FOOT_PRIOR + st.foot_n + 1))
    return replace(st, foot=cur + rate * (obs - cur), foot_n=st.foot_n + 1)


def _size_ratio(radius: np.ndarray, min_blobs: int) -> np.ndarray | None:
    """(N,) each blob's marker radius r_m over the frame's median (of the finite ones; NaN
    stays NaN), or None with fewer than ``min_blobs`` blobs or no positive median.

    Markers of one session share a size and a distance to the camera, so the median blob is
    a marker: two markers merged into one blob measure 1.2-2.4 times it, a hand or a
    reflective patch more (the bundled walks' stray hand: 3-4.7). Serves :func:`_huge` and
    :func:`_merged`.
    """
    r = np.asarray(radius, dtype=np.float64)
    fin = np.isfinite(r)
    if len(r) < min_blobs or not fin.any():
        return None
    med = float(np.median(r[fin]))
    return r / med if med > 0 else None


def _huge(radius: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) blobs far larger than a marker: radius over ``HUGE_BLOB`` times the frame's median
    (:func:`_size_ratio`; needs 5 blobs for a median).

    ``radius`` (n,) is locate's r_m per blob (px; None or another length: nothing is huge).
    """
    ratio = None if radius is None or len(radius) != n else _size_ratio(radius, 5)
    if ratio is None:
        return np.zeros(n, bool)
    return ratio > HUGE_BLOB  # NaN compares False: a blob without r_m is not huge


STILL_MOVE_MM = 20.0  # the shoulder's move per frame below which nothing is judged still
STILL_FRAC = 0.25  # a blob moved less than this share of the shoulder's move stood still


def _still(ah: np.ndarray, prev: np.ndarray | None, moved: float) -> np.ndarray | None:
    """Blobs that stood still since the last frame while the shoulder moved ``moved`` mm.

    Parameters
    ----------
    ah : (N, 2) this frame's blobs (along the line, height), mm (NaN = no position).
    prev : (P, 2) the last frame's, or None (no last frame, or frames were dropped).
    moved : the shoulder's move along the line since the last frame, mm.

    Returns
    -------
    (N,) bool: a blob within ``STILL_FRAC * moved`` of a blob of the last frame (in the
    sagittal plane); None when the subject hardly moved (nothing can be told apart).
    The pelvis moves with the trunk at walking speed: a pelvis-band blob that stays put
    is a stray (a reflector, a hand held still), whatever its fit to the model.
    """
    if prev is None or len(prev) == 0 or len(ah) == 0 or moved < STILL_MOVE_MM:
        return None
    d = np.hypot(ah[:, None, 0] - prev[None, :, 0], ah[:, None, 1] - prev[None, :, 1])
    return np.nan_to_num(d, nan=np.inf).min(axis=1) < STILL_FRAC * moved


def _shoulder_move(cur: np.ndarray, prev: np.ndarray | None, reach: float) -> float:
    """The move (mm) along the walking line of the blob at ``cur`` (3,) since the last frame.

    ``cur`` is (a, e, h), mm; ``prev`` (P, 3) the last frame's blobs (None: no last frame).
    The blob's last position is the nearest of ``prev`` within ``reach`` mm, in 3D: the far
    shoulder lies as high and about as far along, but ~250 mm deeper. 0.0 without one.
    """
    if prev is None or len(prev) == 0 or not np.isfinite(cur).all():
        return 0.0
    d = np.nan_to_num(np.linalg.norm(prev - cur, axis=1), nan=np.inf)
    j = int(np.argmin(d))
    return float(cur[0] - prev[j, 0]) if d[j] < reach else 0.0


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


def _side_sites(near: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per marker (20,): its side (0 = near, 1 = far) and site index, and a sigma class."""
    side = np.zeros(20, np.int64)
    site = np.zeros(20, np.int64)
    for k, sd in enumerate(("near", "far")):
        for j, s in enumerate(SITES):
            i = MARKER_INDEX[_name(sd, s, near)]
            side[i], site[i] = k, j
    names = np.array(SITES)[site]
    cls = np.where(np.isin(names, ("ASI", "PSI")), 0, 2)
    cls[np.isin(names, ("HIP", "SHO"))] = 1
    return side, site, cls


SIDE_SITES = {near: _side_sites(near) for near in ("R", "L")}
# Model sigma (f, e, h) per class, as fractions of the shoulder height: ASI and PSI (the
# trunk leans while walking, so the pelvis shifts along the walk relative to the shoulder;
# depth on the pelvis silhouette is poor), HIP and SHO, the legs (they swing: along the
# walk only the rough reach of a stride is known).
MODEL_SIG = np.array([[0.12, 0.25, 0.03], [0.12, 0.08, 0.03], [0.3, 0.08, 0.1]])


def _predictions(
    st: LabelState, geo: Geometry, sho: np.ndarray, near: str, direction: int, frame_idx: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-marker prediction (f, e, h) and sigma (20, 3): track if fresh, else the model."""
    p = st.params
    H = geo.sho_h
    side, site, cls = SIDE_SITES[near]
    off = geo.offsets[side, site]
    pred = np.stack([sho[0] + off[:, 0], sho[1] + off[:, 1], off[:, 2]], axis=1)
    sig = np.array([[f * H for f in row] for row in MODEL_SIG])[cls]
    age = frame_idx - st.seen
    tracked = (age > 0) & (age <= p["track_age"] + 1) & np.isfinite(st.last).all(axis=1)
    if tracked.any():
        a = age[tracked]
        t = st.last[tracked] + st.vel[tracked] * a[:, None]
        pred[tracked] = np.stack([direction * t[:, 0], t[:, 1], t[:, 2]], axis=1)
        s = 30.0 + 20.0 * a
        se = np.where(cls[tracked] == 0, 0.25 * H, s + 20.0)
        # The feet accelerate hard at toe-off and heel strike: a swing foot goes from
        # standing to 3-4 m/s within two frames, so a foot track's last velocity says little
        # about the next frames. Its forward sigma also grows with the time unseen (at 30 fps
        # 80 mm per frame). Otherwise the far toe's track, still at the stance speed, took the
        # far heel's blob at toe-off, the heel's the near toe's, and the shift held.
        foot = np.isin(site[tracked], FOOT_SITES)
        sf = s + 0.3 * np.abs(st.vel[tracked][:, 0])
        sf = sf + np.where(foot, FOOT_SPEED_SIG * a / st.fps, 0.0)
        sig[tracked] = np.stack([sf, se, s], axis=1)
    return pred, sig, tracked


def beyond_image(pred: np.ndarray, direction: int, ff: FloorFrame, view: Camera) -> np.ndarray:
    """Which predicted markers project outside the image (``view_gate``).

    pred : (M, 3) predictions (f, e, h) mm in the oriented floor frame (f along the walking
    direction ``direction``); ff : the floor frame; view : the camera (intrinsics, image
    size). Returns (M,) bool; a prediction behind the camera or NaN counts as outside.
    The point estimate decides, not its uncertainty: a leg leaving the view is predicted
    from its last frames, a few px from the edge it crossed.
    """
    q = np.array(pred, dtype=np.float64)
    q[:, 0] *= direction
    uv = view.project(ff.to_camera(q))
    with np.errstate(invalid="ignore"):
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 0] <= view.width - 1)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] <= view.height - 1)
        )
    return ~inside


def _bob(sho: np.ndarray, H: float) -> float:
    """The shoulder track's height ``sho`` (f, e, h) above its standing height ``H``, mm:
    the gait's bob, which carries the pelvis and the thighs with it (a standing height
    plus this is where a trunk or thigh marker is expected now)."""
    return float(sho[2] - H)


def _pelvis(fr: _Frame, geo: Geometry, sho: np.ndarray, H: float, gate: float) -> None:
    """Steps 5-6: the pelvis as a rigid cluster (bottom-mode positions).

    Every assignment of the pelvis-band blobs to near (PSI, HIP, ASI) and far ASI is scored
    by the tracks (or the loose standing offsets from the shoulder: the trunk leans while
    walking), the rigid distances among them, the hard order PSI < HIP < ASI along the
    walking direction with HIP below PSI and ASI (those labelled, and where the shoulder
    track puts them), and the far ASI deeper than the near one.
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
    if fr.still is not None:
        cand = cand[~fr.still[cand]]
    K = cand.size
    if K == 0:
        return
    near, far = fr.near, ("L" if fr.near == "R" else "R")
    # The far PSI takes part so that, when seen, it absorbs its blob instead of letting
    # another label take it; it is never published (see above).
    names = PELVIS
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
    hy = _Hyp(fr, idx, cand)
    for a, b in ((0, 1), (1, 2), (0, 2)):
        hy.forbid((a, b), lambda pa, pb: pa[:, 0] < pb[:, 0])
    # The hip (greater trochanter) lies well below the iliac spines of both sides: at least
    # HIP_DROP of its standing drop below each ASI and PSI, near or far (pelvic obliquity and
    # tilt while walking change the drop by a few cm). Without the far ones, a hidden hip's
    # label took the near ASI whenever the near ASI slot stayed empty.
    spines = float(np.mean([geo.rel_sho("near", s)[2] for s in ("ASI", "PSI")]))
    drop = HIP_DROP * max(spines - geo.rel_sho("near", "HIP")[2], 0.0)
    for a in (0, 2, 3, 4):
        hy.forbid((a, 1), lambda pa, ph: ph[:, 2] < pa[:, 2] - drop)
    # The same against where the spines are expected, for when none is labelled: their
    # standing height, moved with the shoulder track's (which carries the gait's bob). The
    # hip's height below the shoulder varies little while walking (5th-95th percentile
    # spread 4-41 mm over twelve walks) against its 57-169 mm below the spines; without
    # this, a hip hidden behind the arm took the near ASI's half-hidden blob, the commonest
    # wrong label left.
    top = spines + _bob(sho, H) - drop
    hy.forbid((1,), lambda ph: ph[:, 2] <= top)
    # Nor does it lie far deeper than its standing depth from the shoulder track (as the
    # near tibia wand, NEAR_HIP_DEEP): a hip track that had slipped onto the far thigh held
    # it 330 mm behind the shoulder.
    hip_e = sho[1] + geo.rel_sho("near", "HIP")[1] + NEAR_HIP_DEEP
    hy.forbid((1,), lambda ph: ph[:, 1] < hip_e)
    # Near and far ASI both seen: the near one is the nearer (a relative test survives the
    # silhouette's depth bias better than the absolute depth does).
    hy.forbid((2, 3), lambda pn, pf: pn[:, 1] < pf[:, 1])
    hy.forbid((4, 3), lambda pp, pa: pp[:, 0] < pa[:, 0])
    for a, b in ((0, 1), (1, 2), (0, 2), (2, 3), (0, 4), (3, 4)):
        hy.add((a, b), lambda pa, pb, d0=geo.pelvis_d0[(a, b)]: _rigid(pa, pb, d0))
    if hy.rows.size == 0:
        return
    T, cost = hy.T[hy.rows], hy.c
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
    # The foot and shank markers: below 0.3 H, or up to 0.05 H above where the static
    # pose measured the tibia wand (a wand placed just below the knee, 0.27 H, rises past
    # 0.3 H in swing).
    low = body & (q[:, 2] < max(0.3 * H, geo.rel_sho("near", "TIB")[2] + 0.05 * H))
    kne_i = MARKER_INDEX[f"{near}_KNE"]
    if fr.tracked[kne_i] and fr.age[kne_i] == 1:
        # The blob on the near knee's fresh track is kept for the limb search: a crouched
        # knee sits as low as a tibia wand (the foot search comes first).
        u = (((fr.pos(kne_i) - fr.pred[kne_i]) / fr.sig[kne_i]) ** 2).sum(axis=1)
        # Only the track's best blob, and only when that one is low: a tibia wand placed
        # just below the knee (80 mm) also lies within 2 sigma of the knee's prediction
        # (a child's, 100 mm below and ahead of it, too), and with it kept out the tibia
        # label took the heel in swing.
        u = np.where(body, u, np.inf)
        best = int(np.argmin(u)) if u.size else -1
        if best >= 0 and u[best] < 4.0:
            low[best] = False
    elif hip is not None:
        # Without a fresh knee track (a pass's first frames), a blob at the thigh's length
        # from the labelled hip (within half a sigma of _rigid) is kept for the limb search
        # too: the crouched subject's knee, as low as a tibia wand, took the tibia label
        # when the ankle and heel were hidden, the tibia wand the ankle's, and the tracks
        # held the shift for 8 frames.
        thigh = geo.d("HIP", "KNE")
        d_hip = np.hypot(q[:, 0] - hip[0], q[:, 2] - hip[2])
        low &= ~(np.abs(d_hip - thigh) < KNEE_RING * (10.0 + 0.1 * thigh))
    cand = np.flatnonzero(low)
    if cand.size > 9:
        # The foot and shank markers are the lowest on the body.
        cand = cand[np.argsort(q[cand, 2])[:9]]
    K = cand.size
    chosen: dict[int, int] = {}
    tf = None
    if K:
        foot_idx = [MARKER_INDEX[f"{near}_{s}"] for s in NEAR_FOOT]
        hy = _Hyp(fr, foot_idx, cand)
        shank = geo.d("KNE", "ANK")
        # Hard: the tibia marker above the ankle one; the toe ahead of the heel, or below
        # it in a steeply pitched foot (toe_ahead).
        foot = geo.d("HEE", "TOE")
        hy.forbid((2, 3), lambda ph, pt: toe_ahead(ph, pt, foot))
        hy.forbid((0, 1), lambda pt, pa: pt[:, 2] > pa[:, 2] - 20.0)
        # The heel and toe markers never rise far above the ankle one (a plantarflexed
        # foot lifts the heel to about the ankle's level).
        for k, margin in ((2, 60.0), (3, 90.0)):
            hy.forbid((1, k), lambda pa, pk, margin=margin: pk[:, 2] < pa[:, 2] + margin)
        # A shank marker never drops far below its standing height while walking.
        ank_h = geo.rel_sho("near", "ANK")[2]
        hy.forbid((0,), lambda pt: pt[:, 2] > ank_h + 0.1 * shank)
        # Nor lies far deeper than its standing depth from the shoulder track: a hidden near
        # tibia wand took the far ankle's, tibia wand's or heel's blob (the far leg, deeper).
        tib_e = sho[1] + geo.rel_sho("near", "TIB")[1] + NEAR_TIB_DEEP
        hy.forbid((0,), lambda pt: pt[:, 1] < tib_e)
        # With the ankle hidden, the heel and toe still lie within reach of the tibia wand:
        # at most its highest place on the shank (as _interval below) plus the ankle's
        # distance to them (triangle inequality). Otherwise a blob far behind a near heel
        # passed for the tibia wand.
        for k, site in ((2, "HEE"), (3, "TOE")):
            r = 0.8 * shank + geo.d("ANK", site)
            hy.forbid((0, k), lambda pt, pk, r=r: np.hypot(*(pt - pk)[:, [0, 2]].T) < r)
        # The foot's sagittal lengths.
        for a, b, d0 in ((1, 2, geo.d("ANK", "HEE")), (1, 3, geo.d("ANK", "TOE"))):
            hy.add((a, b), lambda pa, pb, d0=d0: _rigid(pa, pb, d0, False))
        hy.add((2, 3), lambda pa, pb: _rigid(pa, pb, foot, False))
        # One foot's markers lie at about one depth (silhouette depth errors of tens of mm
        # allowed): the far foot is ~100-200 mm deeper.
        for a, b in ((1, 2), (1, 3), (2, 3), (0, 1)):
            hy.add((a, b), lambda pa, pb: ((pa[:, 1] - pb[:, 1]) / 80.0) ** 2)
        # The tibia wand: somewhere on the lower shank, side-independent bounds.
        hy.add((0, 1), lambda pt, pa: _interval(pt, pa, 0.12 * shank, 0.8 * shank))
        allp = hy.pa.all(axis=1)
        if allp.any():
            # The triangle foot model: ANK inside TIB-TOE-HEE (sagittal), from the signed
            # distances of _triangle_outside, one table per triple of slots.
            tib, ank, hee, toe = (hy.Qa[allp, k] for k in range(4))
            sides = [
                _side(*s)
                for s in ((tib, toe, ank), (toe, hee, ank), (hee, tib, ank), (tib, toe, hee))
            ]
            out = _outside(*sides)
            hy.c[allp] += (out / 15.0) ** 2
        T, present = hy.T, hy.present

        # Far heel and toe, completing the best near-foot hypotheses.
        # The far tibia wand (often seen below the near knee) takes part only to absorb its
        # blob: otherwise it passes for a hidden near tibia or heel.
        far_idx = [MARKER_INDEX[f"{far}_{s}"] for s in ("HEE", "TOE", "TIB")]
        h2 = _Hyp(fr, far_idx, cand)
        # Track claims: a far heel (toe) without a fresh track of its own pays a miss for a
        # blob that the near heel's (toe's) fresh track predicts within 2 sigma. The model's
        # loose standing offsets let an untracked far heel take the near heel's blob (and
        # then the far toe's track the far heel's) when the feet pass each other, where depth
        # cannot tell near from far.
        for k, i in enumerate(far_idx[:2]):
            ni = foot_idx[2 + k]
            if _fresh(fr, ni) and not _fresh(fr, i):
                h2.U[k, :K] += np.where(hy.U[2 + k, :K] < CLAIM_SIG2, MISS_COST, 0.0)
        # The absorber leaves its slot empty at the cost of a blob 2 sigma from its prediction
        # (CLAIM_SIG2), not a miss: at MISS_COST it took any blob its loose prediction fitted
        # better than 3 sigma, a far heel's in swing (above the shank rule's bound) among
        # them, and the far heel went unnamed (btk_PiG_Motion-FlatFoot-Full, base, frame 66).
        h2.U[2, K] = CLAIM_SIG2
        h2.forbid((0, 1), lambda ph, pt: toe_ahead(ph, pt, foot))
        for k in (0, 1):
            h2.forbid((2, k), lambda pw, pk: pw[:, 2] > pk[:, 2] + 0.1 * shank)
        # The absorber is a shank marker too, never far below its standing height (as the
        # near tibia wand): absorbing a blob at foot height, it took the far toe's (or heel's)
        # blob while the far foot's labels, without tracks of their own, went to the other
        # foot marker or none, and the far foot went unlabelled through whole swings and
        # heel strikes (btk_c3dorg_sample04_Matt, base, frames 110-121).
        far_ank_h = geo.rel_sho("far", "ANK")[2]
        h2.forbid((2,), lambda pw: pw[:, 2] > far_ank_h + 0.1 * shank)
        h2.add((0, 1), lambda ph, pt: _rigid(ph, pt, foot))
        # Forbidden far completions (inf) can be neither the best nor an alternative.
        T2, c2, pres2 = h2.T[h2.rows], h2.c, h2.present[h2.rows]
        p2 = h2.Qa  # (0 where missing: every use below is masked by pres2)
        best = np.argsort(hy.c)[:30]
        order = hy.rows[best]
        # Each near hypothesis against every far completion at once: the far blobs must
        # not reuse a near one ('used' (R, K + 1), the missing column never counts).
        Tn = T[order]
        used = np.zeros((len(order), K + 1), bool)
        used[np.arange(len(order))[:, None], Tn] = True
        used[:, K] = False
        clash = used[:, T2].any(axis=2)
        # The far foot is deeper than the near one (mean depth of the near foot's blobs,
        # summed slot by slot as np.mean would).
        pn = present[order]
        n_near = pn.sum(axis=1)
        ne = np.where(pn, hy.Q[order, :, 1], 0.0)
        depth_near = (((ne[:, 0] + ne[:, 1]) + ne[:, 2]) + ne[:, 3]) / np.maximum(n_near, 1)
        has = (n_near > 0)[:, None]
        cc = c2
        for k in range(2):
            # Without a fresh track of its own, a far heel or toe has only the loose
            # standing offsets behind it: at a pass's first frames the far foot's labels
            # took the near heel and toe, 0-20 mm deeper than the near foot's mean (pulled
            # toward the camera by the tibia wand).
            margin = 20.0 if _fresh(fr, far_idx[k]) else FAR_NEW_DEPTH
            deep = pres2[:, k] & (p2[:, k, 1] < depth_near[:, None] + margin)
            cc = cc + np.where(has & deep, 9.0, 0.0)  # (R, A2)
        cc = np.where(clash, np.inf, cc)
        # An absorber must be clearly far-side: it only ever removes a blob.
        absorb = pres2[:, 2] & (p2[:, 2, 1] < depth_near[:, None] + 50.0)
        cc = np.where(has & absorb, np.inf, cc)
        cn = hy.c[best]
        total = np.where(np.isfinite(cn)[:, None], cn[:, None] + cc, np.inf)
        if np.isfinite(total).any():
            r, j = np.unravel_index(int(np.argmin(total)), total.shape)
            m = order[r]
            tf, tp = T[m], T2[j]
            # Ambiguity over the joint hypotheses: a near label whose blob could as well be
            # the far foot's is judged with the far foot's completion counted.
            keep = _unambiguous(total.min(axis=1), T[order], int(r), K, fr.ambiguity)
            # ... and so is a foot label whose blob could as well be the far heel's or toe's,
            # or another marker's of the near foot, with its own slot left empty: with the
            # near foot beyond the image's edge at a pass's first frames, the far foot took
            # all three near foot labels; with the heel hidden, the ankle's blob took the
            # heel label, the ankle left empty, at 2.3 less than the reading the other way.
            keep = [
                kept
                and (
                    k == 0
                    or _clear_of_other_markers(
                        total,
                        (Tn[:, k] != tf[k])[:, None],
                        (T2[:, :2] == tf[k]).any(axis=1)[None, :]
                        | (np.delete(Tn, k, axis=1) == tf[k]).any(axis=1)[:, None],
                        fr.ambiguity,
                    )
                )
                for k, kept in enumerate(keep)
            ]
            # A lone foot marker (the other two of ANK, HEE, TOE missing) has no foot
            # geometry behind it: only a fresh track may name it. Nor has an ankle whose heel
            # and toe the ambiguity test left out (a near toe at the image's edge, its ankle
            # beyond it, took the ankle label). A heel or toe left alone so keeps its label
            # (dropped too, they cost 5 % of the toe offs on the bundled walks).
            lone_foot = int((tf[1:] < K).sum()) == 1
            lone_ankle = int((tf[1:] < K).sum()) > 1 and sum(keep[1:]) == 1
            for k, i in enumerate(foot_idx):
                if keep[k] and tf[k] < K:
                    alone = lone_foot or (lone_ankle and k == 1)
                    if k > 0 and alone and not (fr.tracked[i] and fr.age[i] == 1):
                        continue
                    chosen[i] = int(tf[k])
            keep2 = _far_unambiguous(total, T2, j, K, fr.ambiguity)
            # ... and a far heel or toe whose blob the near foot could as well take, the far
            # slot left empty (the far labels took the near heel's and toe's blobs while
            # the near foot went unnamed).
            keep2 = [
                kept
                and (
                    k == 2
                    or _clear_of_other_markers(
                        total,
                        (T2[:, k] != tp[k])[None, :],
                        (Tn[:, 1:] == tp[k]).any(axis=1)[:, None],
                        fr.ambiguity,
                    )
                )
                for k, kept in enumerate(keep2)
            ]
            # A lone far-foot blob is heel or toe only if last frame's track says which.
            lone = int((tp[:2] < K).sum()) == 1
            if tp[2] < K:
                fr.free[cand[tp[2]]] = False  # absorbed, never published
            for k, i in enumerate(far_idx[:2]):
                if not (keep2[k] and tp[k] < K):
                    continue
                b = cand[tp[k] : tp[k] + 1]
                if lone and not (fr.age[i] == 1 and _unary(fr, i, b)[0] < 4.0):
                    continue
                # ... and the other site's track does not lie nearer it (``_nearer``): a
                # half-hidden far foot's depth jumps, so the depth may favour the wrong
                # track. Any live track counts, not only last frame's: as the near foot
                # swings past the planted far one it hides the far heel, then the toe, and
                # the heel's blob, back after a frame or two unseen, took the toe's label
                # from the toe's last-frame track.
                o = far_idx[1 - k]
                if lone and fr.tracked[o] and _nearer(fr, o, i, b):
                    continue
                chosen[i] = int(tp[k])
    _accept(fr, chosen, cand, geo, hip, gate)

    # Limb: THI and KNE against HIP, TIB and ANK, with the pelvis's hip label on trial.
    thi_i, kne_i = MARKER_INDEX[f"{near}_THI"], MARKER_INDEX[f"{near}_KNE"]
    lc = np.flatnonzero(fr.free & body & (q[:, 2] > 0.15 * H) & (q[:, 2] < 0.62 * H))
    cap = 7 if fr.assign[hip_i] >= 0 else 6  # the search grows as (K + 1) ** slots
    if cap < lc.size:
        lc = lc[np.argsort(np.abs(q[lc, 2] - geo.rel_sho("near", "KNE")[2]))[:cap]]
    hip_blob = int(fr.assign[hip_i])
    if hip_blob >= 0:
        # The hip slot may keep the pelvis's hip blob or leave it: a hip label that the leg
        # below contradicts is dropped, and its blob may then be the thigh's or the knee's
        # (a hidden hip otherwise takes the thigh wand, the thigh label the knee, and the
        # tracks keep the shifted chain).
        lc = np.append(lc, hip_blob)
    K2 = lc.size
    if K2 == 0:
        return
    # The far knee and thigh take part only to absorb their blobs when seen (never
    # published): otherwise a far-leg marker would take a hidden near one's label. Without
    # a pelvis hip, the hip slot absorbs an unlabelled hip blob (left out as ambiguous),
    # which must not pass for the thigh one.
    far_leg = [MARKER_INDEX[f"{far}_KNE"], MARKER_INDEX[f"{far}_THI"]]
    slots = [kne_i, thi_i, *far_leg, hip_i]
    h3 = _Hyp(fr, slots, lc)
    if hip_blob >= 0:
        # The pelvis search has judged the hip's own fit: here only the leg may overrule it.
        h3.U[4, K2 - 1] = 0.0
        sho_i = MARKER_INDEX[f"{near}_SHO"]
        near_spines = [fr.assign[MARKER_INDEX[f"{near}_{s}"]] >= 0 for s in ("ASI", "PSI")]
        if not (_fresh(fr, hip_i) or any(near_spines)) and fr.assign[sho_i] >= 0:
            # ... unless the hip stands alone, with no track of its own and no near spine
            # labelled with it: then its height below the shoulder track (updated by a
            # shoulder labelled in this frame) counts too. The pelvis search judged it
            # against its standing height above the floor, which a bobbing gait leaves (by
            # 96 mm in the frame of the test): a hidden hip took the thigh wand's blob, the
            # thigh label the knee's, and the knee was left out, for a dozen frames at a
            # pass's start.
            drop = q[hip_blob, 2] - (geo.rel_sho("near", "HIP")[2] + _bob(sho, H))
            h3.U[4, K2 - 1] = (drop / (HIP_BELOW_SHO_SIG * H)) ** 2
    if _fresh(fr, kne_i) and fr.tracked[thi_i]:
        # Track claim: the thigh wand pays a miss for a blob that the knee's fresh track
        # predicts within 2 sigma of its viewing ray, and better than the thigh's does.
        # A thigh wand 50-70 mm above the knee, hidden behind the swinging arm, otherwise
        # took the knee's blob whenever the knee's depth there was the arm's (100+ mm too
        # near: the knee's shank length and depth then cost more than the thigh's miss).
        # The thigh's track need only be live: the arm hides the wand for several frames.
        # Without one (a thigh prediction from the standing pose only), a knee track
        # already on the thigh's blob claimed it and held the leg shifted by one marker
        # (the crouch gait). One way only: a thigh track on the knee's blob would claim it
        # back and hold the swap (seen on the ``high`` set-up).
        u_kne, u_thi = (_off_ray(fr, i, lc) for i in (kne_i, thi_i))
        h3.U[1, :K2] += np.where((u_kne < CLAIM_SIG2) & (u_kne < u_thi), MISS_COST, 0.0)
    pr = h3.present
    thigh, shank = geo.d("HIP", "KNE"), geo.d("KNE", "ANK")
    anchors = {}
    for site in ("TIB", "ANK"):
        i = MARKER_INDEX[f"{near}_{site}"]
        if fr.assign[i] >= 0:
            anchors[site] = fr.pos(i)[fr.assign[i]]
    # Near or far leg: depth relative to the near leg's labelled markers (the standing
    # offsets from the shoulder carry the shoulder's depth error and the trunk's rotation).
    ref = [
        fr.pos(MARKER_INDEX[f"{near}_{s}"])[fr.assign[MARKER_INDEX[f"{near}_{s}"]]]
        for s in ("HIP", "TIB", "ANK")
        if fr.assign[MARKER_INDEX[f"{near}_{s}"]] >= 0
    ]
    ref_e = float(np.mean([r[1] for r in ref])) if ref else np.nan
    # Without a pelvis hip the knee-thigh spacing counts only with all five slots filled
    # (as before the hip check; the absorbed hip blob is not a confirmed hip); the order
    # (thigh above knee) always counts.
    both = pr[:, :2].all(axis=1) if hip_blob >= 0 else pr.all(axis=1)
    chain = both & pr[:, 4] & (hip_blob >= 0)
    kne_h = geo.rel_sho("near", "KNE")[2]
    # Hard rules: the pelvis's hip blob or none in the hip slot; the hip above knee and
    # thigh; the knee above the shank markers; far knee and thigh deeper than the near leg;
    # knee and thigh well above the floor; the thigh above the knee.
    if hip_blob >= 0:
        h3.forbid((4,), lambda ph: np.zeros(len(ph), bool), where=h3.T[:, 4] != K2 - 1)
        if not 0.15 * H < q[hip_blob, 2] < 0.62 * H:
            # Above the limb band: a hip blob that is no knee or thigh candidate itself.
            for k in range(4):
                h3.forbid((k,), lambda p: np.zeros(len(p), bool), where=h3.T[:, k] == K2 - 1)
    for k in (0, 1):
        h3.forbid((4, k), lambda ph, pk: ph[:, 2] > pk[:, 2])
    for a_pos in anchors.values():
        h3.forbid((0,), lambda pk, a_pos=a_pos: pk[:, 2] > a_pos[2])
    if ref:
        for k in (2, 3):
            h3.forbid((k,), lambda p: ~(p[:, 1] < ref_e + 50.0))
    for k in (0, 1):
        h3.forbid((k,), lambda p: p[:, 2] > 0.6 * kne_h)
    # Nor does the thigh wand rise far above where the static pose measured it (moved with
    # the shoulder track's bob): hip flexion lifts it by a share of its distance from the
    # hip, THI_RISE of the thigh's length even in a high-stepping gait. Without this, at a
    # pass's first frames the thigh label took the hip's blob and the knee label the
    # thigh's, and the tracks held the leg shifted by one marker for half a second.
    thi_top = geo.rel_sho("near", "THI")[2] + _bob(sho, H) + THI_RISE * thigh
    h3.forbid((1,), lambda p: p[:, 2] < thi_top)
    # The thigh wand sits on the thigh, above the knee marker, whatever else is seen. It
    # may sit only 50-70 mm above the knee; when this counted only with all five slots
    # filled, a frame without a hip label let the two swap.
    h3.forbid((0, 1), lambda pk, pt: pt[:, 2] > pk[:, 2])
    # Costs: thigh and shank lengths, the wands on their segments, the near leg's depth.
    h3.add((4, 0), lambda ph, pk: _rigid(ph, pk, thigh))
    h3.add((4, 1), lambda ph, pt: _interval(ph, pt, 0.1 * thigh, 0.9 * thigh))
    if "ANK" in anchors:
        h3.add((0,), lambda pk: _rigid(pk, anchors["ANK"][None], shank))
        if "TIB" in anchors:

            def on_shank(pk: np.ndarray) -> np.ndarray:
                tib, ank = (np.repeat(anchors[k][None], len(pk), 0) for k in ("TIB", "ANK"))
                return _on_segment(pk, tib, ank, off=geo.wand_off.get("TIB", 0.0))

            h3.add((0,), on_shank)
    elif "TIB" in anchors:
        h3.add((0,), lambda pk: _interval(pk, anchors["TIB"][None], 0.2 * shank, 0.88 * shank))
    if ref:
        for k in (0, 1):
            h3.add((k,), lambda p: ((p[:, 1] - ref_e) / 60.0) ** 2)
    h3.add((0, 1), lambda pk, pt: _interval(pk, pt, 0.1 * thigh, 0.9 * thigh), where=both)
    thi_off = geo.wand_off.get("THI", 0.0)
    h3.add((4, 1, 0), lambda ph, pt, pk: _on_segment(ph, pt, pk, off=thi_off), where=chain)
    if h3.rows.size == 0:
        return
    T3, c3 = h3.T[h3.rows], h3.c
    j = int(np.argmin(c3))
    if not np.isfinite(c3[j]):
        return
    if hip_blob >= 0 and T3[j, 4] >= K2:
        fr.assign[hip_i] = -1
        fr.free[hip_blob] = True
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


def _checks(near: str) -> tuple[np.ndarray, ...]:
    """The step-10 distance checks of ``_accept`` for a near side, as index arrays.

    Returns (kind (C,) 0 = rigid, 1 = loose rigid, 2 = wand interval; marker indices ia, ib;
    site indices ra, rb of the reference segment; lo, hi fractions of its length).
    """
    rows = []
    for side in (near, "L" if near == "R" else "R"):
        for a, b, loose in RIGID:
            ia, ib = MARKER_INDEX[f"{side}_{a}"], MARKER_INDEX[f"{side}_{b}"]
            rows.append((int(loose), ia, ib, SITES.index(a), SITES.index(b), 0.0, 0.0))
        for w, j, (r0, r1), lo, hi in WAND:
            ia, ib = MARKER_INDEX[f"{side}_{w}"], MARKER_INDEX[f"{side}_{j}"]
            rows.append((2, ia, ib, SITES.index(r0), SITES.index(r1), lo, hi))
    cols = list(zip(*rows, strict=True))
    return (*(np.array(c, dtype=np.int64) for c in cols[:5]), *(np.array(c) for c in cols[5:]))


CHECKS = {near: _checks(near) for near in ("R", "L")}


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
    if not chosen:
        return
    ci = np.fromiter(chosen.keys(), np.int64, len(chosen))
    cb = cand[np.fromiter(chosen.values(), np.int64, len(chosen))]
    have = fr.assign >= 0
    P = np.full((20, 3), np.nan)
    P[have] = fr.qm[fr.assign[have], MODE_OF[have]]
    P[ci] = fr.qm[cb, MODE_OF[ci]]  # a co-chosen label stands for an accepted one
    have[ci] = True
    is_chosen = np.zeros(20, bool)
    is_chosen[ci] = True
    bad = np.zeros(20, bool)
    d = (P[ci] - fr.pred[ci]) / fr.sig[ci]
    bad[ci] = (d**2).sum(axis=1) > 3 * gate**2
    kind, ia, ib, ra, rb, lo, hi = CHECKS[fr.near]
    live = have[ia] & have[ib]
    for k in (0, 1, 2):
        m = live & (kind == k)
        if not m.any():
            continue
        d0 = geo.dist[ra[m], rb[m]]
        if k == 2:
            e = _interval(P[ia[m]], P[ib[m]], lo[m] * d0, hi[m] * d0)
        else:
            e = _rigid(P[ia[m]], P[ib[m]], d0, bool(k))
        broken = e > gate**2
        bad[ia[m][broken]] = True
        bad[ib[m][broken]] = True
    bad &= is_chosen
    for i, k in chosen.items():
        if not bad[i]:
            fr.assign[i] = int(cand[k])
            fr.free[cand[k]] = False


# --- the stage core ------------------------------------------------------------------------


# Leg markers whose layer is chosen by depth continuity (``leg_layer="track"``, _output).
LEG = np.array([MARKER_INDEX[f"{side}_{m}"] for side in "LR" for m in ("KNE", "TIB", "ANK")])
BOTTOM = CLUSTER_MODES.index("bottom")
NORMAL = CLUSTER_MODES.index("normal")
# The hip's own mode is the bottom one (the swinging arm in front of it), whose far layer,
# with no arm there, can be the far leg or pelvis 70-130 mm behind the hip: its layer is
# chosen too, between the bottom and the normal mode.
HIPS = np.array([MARKER_INDEX[f"{side}_HIP"] for side in "LR"])
LAYERED = np.concatenate([LEG, HIPS])
# The other layer each of them may take instead of its own mode's.
ALT_MODE = np.where(np.isin(np.arange(20), HIPS), NORMAL, BOTTOM)
# A leg marker's depth (its lateral position in a side view) moves a few mm per frame; a
# layer this much closer to the reference depth (see LAYER_REF) than the own mode's wins.
LAYER_GAIN_MM = 20.0
LAYER_MAX_AGE = 3  # frames: an older last depth is not trusted
# A leg marker's layer is judged against a marker of the same segment seen in the frame
# (the ankle against the tibia wand on the shank) at the standing depth offset between
# them; without one, against its own last depth. Not the knee against the thigh wand: the
# thigh wand's depth (its bottom mode, the output's) is often a layer behind it, and with
# the wand matched on its nearest layer such frames are labelled (the knee then followed
# the wrong reference: seed 0 knee 1.37 / 1.92 deg against 1.26 / 2.09 without it, on
# the simulator's old patch mount).
LAYER_REF = {"ANK": "TIB"}
# A hip without a last depth of its own (hidden behind the swinging arm for more than
# LAYER_MAX_AGE frames) has its layer judged against the near shoulder's instead, in the
# floor frame (a tilted camera makes the shoulder-to-hip drop a depth difference), at the
# static pose's depth offset between them. The shoulder is a poorer reference than the
# hip's own last depth: on three cached set-ups (base, ``high``, ``veryslow``; 3354 views)
# the hip's true depth lay from it 15 mm at the median but 85 mm at the 90th percentile.
# So the other layer must be nearer the reference by LAYER_FALLBACK_GAIN_MM, more than that
# spread: a far leg or pelvis layer well behind still gives way (on base and ``far``, seven
# hips published 90-175 mm too deep after such a gap moved to within 5 mm of the truth; no
# other set-up changed), and an arm less than that gain in front of the hip can never take
# over, whatever the reference's error.
LAYER_FALLBACK = {"HIP": "SHO"}
LAYER_FALLBACK_GAIN_MM = 100.0
FALLBACK_LAYERED = np.array(
    [MARKER_INDEX[f"{side}_{site}"] for side in "LR" for site in LAYER_FALLBACK]
)


def layer_reference(geo: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """(20,) reference marker per marker for the leg layer (-1 = none) and (20,) its
    expected depth offset (mm): the static pose's depth of the marker minus its reference's
    (near-side offsets, used for whichever side faces the camera). ``LAYER_REF`` and
    ``LAYER_FALLBACK`` pairs both."""
    ref = np.full(20, -1)
    off = np.zeros(20)
    for side in "LR":
        for site, r_site in (LAYER_REF | LAYER_FALLBACK).items():
            k = MARKER_INDEX[f"{side}_{site}"]
            ref[k] = MARKER_INDEX[f"{side}_{r_site}"]
            off[k] = geo.rel_sho("near", site)[1] - geo.rel_sho("near", r_site)[1]
    return ref, off


def _layer_continues(
    own: np.ndarray, alt: np.ndarray, last: np.ndarray, gain: float = LAYER_GAIN_MM
) -> np.ndarray:
    """Where another mode's depth (``alt``) continues the last one better than the own
    mode's by ``gain`` (same-shape arrays of depths, mm; NaN anywhere = no)."""
    with np.errstate(invalid="ignore"):
        return np.abs(alt - last) + gain < np.abs(own - last)


def merged_heel(
    position: np.ndarray,
    assign: np.ndarray,
    radius: np.ndarray,
    near: str,
    direction: int,
    rot: np.ndarray,
    geo: Geometry,
    ratio: float,
) -> np.ndarray:
    """Published positions with a near heel on a merged heel-ankle blob moved to the heel.

    In stance the heel and ankle markers of the near foot are 3-4 px apart at 2.7 m and
    often one blob; the search gives a blob one label, so the blob is named heel with the
    ankle left out. Its centroid (and 3D position) lies between the two markers, 30-50 mm
    ahead of the heel, which shortened the step that foot's stance measures by as much (a
    step 8.6 % short on btk_PiG_Motion3_FF). Such a blob is larger than a single marker's
    (marker radius r_m 1.2-1.9 times the frame's median, against 1.0-1.2 for a single
    ankle), so a near heel whose blob's r_m is at least ``ratio`` times the median, with its
    ankle unlabelled, is moved by half the subject model's standing ankle-to-heel vector:
    the midpoint, the two markers' relative brightness being unknown. The pixel stays the
    blob's centroid. The ankle on such a blob is left where it is: with the heel mostly
    hidden it lies near the ankle (11-15 mm), and half the vector made it worse. Part of
    Alg. 5 step 11 (the published 3D positions); a departure.

    Parameters
    ----------
    position : (20, 3) camera mm, as published (NaN = missing).
    assign : (20,) blob per marker, -1 = none.
    radius : (N,) marker radius r_m of the frame's blobs, px.
    near : "L" or "R", the side facing the camera.
    direction : +1 / -1, walking toward +/- the floor frame's first axis.
    rot : (3, 3) the floor frame's axes as rows (:class:`FloorFrame`).
    geo : the subject geometry (standing offsets of the near heel and ankle).
    ratio : the merged-blob ratio; 0 = no change.

    Returns
    -------
    (20, 3) new array.
    """
    out = np.array(position, dtype=np.float64)
    big = _merged(radius, ratio)
    if big is None or near not in ("L", "R") or direction == 0:
        return out
    heel, ankle = MARKER_INDEX[f"{near}_HEE"], MARKER_INDEX[f"{near}_ANK"]
    b = int(assign[heel])
    if b < 0 or assign[ankle] >= 0 or not big[b]:
        return out
    fwd, e, h = geo.rel_sho("near", "HEE") - geo.rel_sho("near", "ANK")
    out[heel] += 0.5 * (np.array([direction * fwd, e, h]) @ np.asarray(rot))
    return out


def merged_ankle(assign: np.ndarray, radius: np.ndarray, near: str, ratio: float) -> bool:
    """Whether the near ankle is on a merged heel-ankle blob with the heel unlabelled: its
    label is then kept for tracking but not published (departure, Alg. 5 step 11).

    The foot search gives a blob one label. Where the near heel and ankle are one blob
    (marker radius r_m at least ``ratio`` times the frame's median, as for
    :func:`merged_heel`) and the search named it ankle, its centroid lies between the two
    markers, 10-30 mm behind and below the ankle, mostly in swing, where blur merges them:
    the knee angle's ankle then pulls the shank back. Left out, the gait stage fills the
    ankle from the shank (``segment_fill``): knee RMSE 0.91 -> 0.80 deg on the bundled
    walks (seed 0), lower in 19 of 21 simulated set-ups; every other label, event and step
    as before.

    assign : (20,) blob per marker, -1 = none; radius : (N,) r_m of the frame's blobs, px;
    near : "L" or "R"; ratio : ``merged_heel_ratio`` (0 = off).
    """
    big = _merged(radius, ratio)
    if big is None or near not in ("L", "R"):
        return False
    heel, ankle = MARKER_INDEX[f"{near}_HEE"], MARKER_INDEX[f"{near}_ANK"]
    return bool(assign[ankle] >= 0 and assign[heel] < 0 and big[assign[ankle]])


def _merged(radius: np.ndarray, ratio: float) -> np.ndarray | None:
    """(N,) blobs whose marker radius r_m is at least ``ratio`` times the frame's median
    (:func:`_size_ratio`): two markers merged. None with ``ratio`` <= 0 or fewer than 3
    blobs (no median to speak of)."""
    size = _size_ratio(radius, 3) if ratio > 0 else None
    if size is None:
        return None
    return size >= ratio


def fill_modes(pos: np.ndarray) -> np.ndarray:
    """Each blob's position under every cluster mode, a mode without a layer filled in.

    A mode that found no layer takes the normal mode's position; where the normal mode
    found none either, the first mode (in ``CLUSTER_MODES`` order) that did. An arm in
    front of the pelvis can leave the normal mode without a layer while the bottom mode
    has the hip's: such a blob was left out of the search, and its label went to another
    blob. A blob without any layer stays NaN.

    pos : (N, 3, 3) [blob, mode, xyz]. Returns a new (N, 3, 3) array.
    """
    pos = np.asarray(pos, dtype=np.float64)
    if not len(pos):
        return pos.copy()
    found = np.isfinite(pos).all(axis=2)
    first = pos[np.arange(len(pos)), np.argmax(found, axis=1)]
    return np.where(found[:, :, None], pos, first[:, None, :])


def surface_point(position: np.ndarray, surface_offset_mm: float) -> np.ndarray:
    """Marker centres moved back along their viewing rays to the surface they sit on.

    Locate puts every marker ``surface_offset_mm`` (one radius plus base) in front of the
    surface it sits on, which is right for a marker facing the camera. A heel marker sits
    on the back of the heel and is seen side-on: the surface beside it lies at its centre's
    depth, so label publishes the heels at the surface point (``heel_side_on``).

    position : (K, 3) camera mm (the camera at the origin). Returns a new (K, 3) array.
    """
    position = np.asarray(position, dtype=np.float64)
    if surface_offset_mm <= 0 or not len(position):
        return position.copy()
    dist = np.linalg.norm(position, axis=1, keepdims=True)
    return position * (1.0 + surface_offset_mm / dist)


def _output(
    mk: Markers3D,
    assign: np.ndarray,
    direction: int,
    near: str,
    prev: tuple[np.ndarray, np.ndarray] | None = None,
    side_on: np.ndarray | None = None,
    ref: tuple[np.ndarray, np.ndarray] | None = None,
    ff: FloorFrame | None = None,
    merged: tuple[Geometry, float] | None = None,
) -> tuple[LabelledMarkers, tuple[np.ndarray, np.ndarray]]:
    """The labelled frame, and the (20,) depth and frame of each marker's last position.

    ``side_on`` (20,) bool: markers published at their surface point (locate's
    ``surface_offset_mm`` undone along the viewing ray); see the ``heel_side_on`` parameter.
    ``merged`` (the subject geometry and ``merged_heel_ratio``; needs ``ff``): a near heel
    on a merged heel-ankle blob is published at the heel (:func:`merged_heel`).

    ``prev`` (the previous call's second output, or None) enables the leg layer choice: a
    knee, tibia or ankle marker whose own-mode layer is the nearest surface in its window
    takes the bottom mode's layer instead when that one continues its last depth (within
    ``LAYER_MAX_AGE`` frames) better by ``LAYER_GAIN_MM``: a hand or the other leg passing
    in front makes the nearest layer tens of mm too near for a few frames (departure). A
    hip (own mode bottom) takes the normal mode's layer by the same rule: with no arm in
    front, its bottom layer can be the far leg or pelvis 70-130 mm behind it.

    ``ref`` (:func:`layer_reference`) makes the choice against a marker of the same segment
    seen in the frame instead (``LAYER_REF``: the ankle against the tibia wand, at the
    static pose's depth offset), and against the last depth only without one:
    a track that starts on the layer in front (a tibia wand, an arm) would otherwise keep
    it for whole strides. A hip's pair (``LAYER_FALLBACK``, the near shoulder) is used only
    without a last depth of its own, in the floor frame ``ff`` (needed for it) and by
    ``LAYER_FALLBACK_GAIN_MM``.
    """
    pos = fill_modes(np.asarray(mk.position, dtype=np.float64).reshape(-1, 3, 3))
    cen = np.asarray(mk.centroid, dtype=np.float64).reshape(-1, 2)
    position = np.full((20, 3), np.nan)
    pixel = np.full((20, 2), np.nan)
    ii = np.flatnonzero(assign >= 0)
    b = assign[ii]
    mode = OWN_MODE.copy()
    frame = mk.header.frame
    if prev is not None:
        zp, seen = prev
        for k in LAYERED:
            bk = assign[k]
            if bk < 0:
                continue
            own, alt = OWN_MODE[k], ALT_MODE[k]
            r = -1 if ref is None else int(ref[0][k])
            r_seen = r >= 0 and assign[r] >= 0
            fallback = k in FALLBACK_LAYERED
            if r_seen and not fallback:
                last = pos[assign[r], OWN_MODE[r], 2] + ref[1][k]
            elif np.isfinite(zp[k]) and frame - seen[k] <= LAYER_MAX_AGE:
                last = zp[k]
            elif r_seen and ff is not None:
                e = ff.to_floor(pos[bk, [own, alt]])[:, 1]
                e_ref = ff.to_floor(pos[assign[r], OWN_MODE[r]])[1] + ref[1][k]
                if _layer_continues(e[0], e[1], e_ref, LAYER_FALLBACK_GAIN_MM):
                    mode[k] = alt
                continue
            else:
                continue
            if _layer_continues(pos[bk, own, 2], pos[bk, alt, 2], last):
                mode[k] = alt
    position[ii] = pos[b, mode[ii]]
    if side_on is not None:
        k = np.flatnonzero(side_on & (assign >= 0))
        position[k] = surface_point(position[k], mk.surface_offset_mm)
    pixel[ii] = cen[b]
    published = assign
    if merged is not None and ff is not None and near:
        radius = np.asarray(mk.marker_radius, dtype=np.float64)
        position = merged_heel(position, assign, radius, near, direction, ff.rot, *merged)
        if merged_ankle(assign, radius, near, merged[1]):
            # (its depth is not kept for the next frame's layer choice either, as for any
            # marker not published)
            ank = MARKER_INDEX[f"{near}_ANK"]
            position[ank] = pixel[ank] = np.nan
            published = assign.copy()
            published[ank] = -1
    zs = np.full(20, np.nan) if prev is None else prev[0].copy()
    seen = np.full(20, -(10**9)) if prev is None else prev[1].copy()
    zs[ii] = position[ii, 2]
    seen[ii] = frame
    # the blobs left unnamed (a merged ankle not published still names its blob), with
    # where a heel on each would be published: the gait stage may extend a heel's track
    # back onto them (its heel extension)
    spare = np.setdiff1d(np.arange(len(cen)), b)
    spare_heel = pos[spare, HEEL_MODE]
    if side_on is not None and side_on[HEELS].any():
        spare_heel = surface_point(spare_heel, mk.surface_offset_mm)
    msg = LabelledMarkers.follow(
        mk.header,
        position=position,
        pixel=pixel,
        blob=published.astype(np.int32),
        direction=int(direction),
        near_side=near,
        spare_pixel=cen[spare],
        spare_heel=spare_heel,
    )
    return msg, (zs, seen)


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
    cal = cal if isinstance(cal, CalibrationRecord) else None
    model = model if isinstance(model, SubjectModel) else None
    st = state
    if mk.header.trial != st.trial or mk.header.frame <= st.frame:
        st = init(p)
        st = replace(st, trial=mk.header.trial)
    # The floor frame and geometry are rebuilt only when a side input changes (the driver
    # hands the same message objects every frame; the state holds them, so the identity
    # test cannot be fooled by a recycled id).
    if st.sides is None or st.sides[0] is not cal or st.sides[1] is not model:
        ff = FloorFrame.from_record(cal, p["camera_height_mm"])
        fps = p["fps"] or doc_number(cal.camera if cal is not None else None, "fps", 1.0, 1000.0)
        view = None
        if p["view_gate"] and cal is not None and cal.camera:
            try:
                view = Camera.from_doc(cal.camera, source="calibration record camera")
            except InputError as exc:
                raise StageError(NAME, f"bad camera in the calibration record: {exc}") from exc
        geo = Geometry.from_model(model)
        sides = (cal, model, ff, geo, view, layer_reference(geo))
        st = replace(st, sides=sides, fps=fps or DEFAULT_FPS)
    _, _, ff, geo, view, layer_ref = st.sides
    pos = np.asarray(mk.position, dtype=np.float64).reshape(-1, 3, 3)
    radius = np.asarray(mk.marker_radius, dtype=np.float64)
    st, assign = label_frame(st, pos, mk.header.frame, ff, geo, radius, view)
    near = "" if st.direction == 0 else ("R" if st.direction > 0 else "L")
    if st.sho_x is None:
        near = ""
    direction = st.direction if st.sho_x is not None else 0
    track = p["leg_layer"] == "track"
    side_on = HEELS if p["heel_side_on"] else None
    merged = (geo, p["merged_heel_ratio"]) if p["merged_heel_ratio"] > 0 else None
    out, leg_depth = _output(
        mk, assign, direction, near, st.leg_depth if track else None, side_on, layer_ref, ff, merged
    )
    return replace(st, leg_depth=leg_depth if track else None), [out]


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
