"""Stage ``model``: the person-centric subject model from the static recording (Sec. IV-B).

The subject stands still, side-on, on the walking line. At the end of the static trial
every frame is labelled by layout rules (height above the floor plane, order along the
walking axis, near/far by twins: :func:`label_pose`) and the pose is the per-marker
consensus of the frames (:func:`consensus_pose`), so that no single frame, with an extra
blob (a split far toe, a hand) or a missing one, decides the model. The model:

- ``reference``: the standing pose, camera mm (20, 3), NaN = not seen;
- ``distances``: the inter-marker distances (20, 20), mm;
- ``near_side``: the side that faced the camera (``L`` or ``R``);
- ``extra["layout"]``: per site (SHO, ASI, ..., TOE) the body-frame position
  [forward, height, lateral] in mm: forward along the facing direction from the pelvis
  centre (mean of ASI and PSI), height above the floor, lateral outward from the body's
  mid-plane. Measured on the near side (far ASI/PSI also when seen), the rest from a
  default adult template scaled to the subject's shoulder height;
- ``extra["site_distances"]``: near-side distances between sites (10, 10) mm, the rigid
  segment lengths the label stage checks (thigh, shank, foot triangle);
- ``extra`` also holds the H*/W* style measurements: heights above the floor per site,
  thigh (HIP-KNE), shank (KNE-ANK), foot (HEE-TOE) lengths, and the facing direction.

The paper's H0*, H7*, W3*-W9* and virtual lines L12-L16 exist only in its Fig. 5 [A-M2];
this model keeps their intent (heights and distances among markers, per side) in 3D.

Conventions: floor frame from the calibration record: a = along the walking line (toward
+u), e = horizontal away from the camera, h = height above the floor; mm; NaN = missing.
Handedness: a subject facing +a has the right side toward the camera (camera X right,
Y down, Z forward, right-handed).
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from gaitflow.schemas import CalibrationRecord, Markers3D, Message, SubjectModel
from gaitflow.stages.base import StageSpec

from gaitflow.camera import marker_diameter
from gaitflow.errors import StageError
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES, SITES
from gaitflow.params import Param, ParamSet

NAME = "model"

# Default adult template, body frame [forward, height, lateral] mm, shoulder 1450 mm high.
# Forward is from the pelvis centre; lateral is outward from the mid-plane. Typical values
# for the marker placements of the Plug-in Gait / CGM lower-body set (HIP = greater
# trochanter); used to label the static pose and for sites it could not measure.
TEMPLATE_SHO_HEIGHT = 1450.0
TEMPLATE: dict[str, tuple[float, float, float]] = {
    "SHO": (-20.0, 1450.0, 170.0),
    "ASI": (110.0, 985.0, 110.0),
    "PSI": (-110.0, 1015.0, 60.0),
    "HIP": (0.0, 915.0, 150.0),
    "THI": (30.0, 650.0, 100.0),
    "KNE": (0.0, 505.0, 70.0),
    "TIB": (20.0, 230.0, 55.0),
    "ANK": (0.0, 75.0, 45.0),
    "HEE": (-60.0, 42.0, 35.0),
    "TOE": (135.0, 45.0, 35.0),
}


def body_cluster(P: np.ndarray, radius: float) -> np.ndarray:
    """Boolean mask of the blobs that belong to the subject, (N, 3) floor coords.

    The subject's markers crowd within a body radius of each other horizontally; stray
    reflectors (on walls, furniture, the floor) stand apart. The seed is the blob with the
    most horizontal neighbours within ``radius``; members lie within ``radius`` of the
    seed's neighbourhood median.
    """
    if len(P) == 0:
        return np.zeros(0, bool)
    dh = np.hypot(P[:, None, 0] - P[None, :, 0], P[:, None, 1] - P[None, :, 1])
    counts = (dh < radius).sum(axis=1)
    seed = int(np.argmax(counts))
    nb = P[dh[seed] < radius]
    c = np.median(nb[:, :2], axis=0)
    return np.hypot(P[:, 0] - c[0], P[:, 1] - c[1]) < radius


# Neighbours along the body chain, nearest first: an unmeasured site is placed from them.
CHAIN: dict[str, tuple[str, ...]] = {
    "ANK": ("HEE", "TOE", "TIB"),
    "HEE": ("ANK", "TOE"),
    "TOE": ("HEE", "ANK"),
    "TIB": ("ANK", "KNE"),
    "KNE": ("TIB", "THI"),
    "THI": ("KNE", "HIP"),
    "HIP": ("THI", "ASI", "PSI"),
    "ASI": ("PSI", "HIP"),
    "PSI": ("ASI", "HIP"),
}

# Layout rules of :func:`label_pose`, as fractions of the shoulder height H (about 1450 mm):
# twins (near and far marker of a site) differ by under TWIN_TOL_FRAC * H in forward
# position and height (the adult heel is 0.04 H behind the ankle); a pelvis-band blob
# further than STRAY_PELVIS_FRAC * H beyond the template's pelvis span (PSI..ASI) from the
# shoulder, or any blob beyond the whole body's span (PSI..TOE) by STRAY_BODY_FRAC * H, is
# a stray (the bundled crouched subject's knee is 0.27 H ahead of the shoulder, a stray hand
# 0.41 H); an untwinned foot blob further than FAR_FOOT_FRAC * H in depth beyond the near
# foot is the far foot.
TWIN_TOL_FRAC = 0.025
# Static frames agree on a marker when their labelled positions lie within this many marker
# diameters (forward, height) of the median over the frames.
CONSENSUS_DIAMETERS = 2.0
# ASI and PSI of a standing subject differ in height by under PELVIS_LEVEL_FRAC * H (a
# 15 degree pelvic tilt moves them by about 0.04 H).
PELVIS_LEVEL_FRAC = 0.08
STRAY_PELVIS_FRAC = 0.12
STRAY_BODY_FRAC = 0.25
FAR_FOOT_FRAC = 0.08
# The hip marker (greater trochanter) sits a little below the pelvis markers' level: the
# template's drop is 0.06 H, 0.05-0.09 H on the trials. A pelvis-band blob more than
# HIP_DROP_FACTOR times the template's drop below the other pelvis blobs is a thigh wand
# placed high (0.13-0.15 H below them on opensim_rajagopal_walk), not the hip.
HIP_DROP_FACTOR = 2.0
# Ankle, heel and toe markers of a standing subject sit below this fraction of H (the
# ankle at 0.04-0.07 H on the trials), a tibia wand above it (0.10-0.28 H).
FOOT_BAND_FRAC = 0.085
# One foot's heel, ankle and toe markers lie within FOOT_SPAN_FRAC * H of each other along
# the walking axis: heel to toe is 0.11-0.17 H on the bundled trials (and the child and
# crouch set-ups), 0.13 H in the template; the margin takes the heel's silhouette depth
# error and larger shoes. A reflector lying on the walkway ahead of a toe (0.26 H from the
# heel on `far+strays_late`) is beyond it.
FOOT_SPAN_FRAC = 0.24
# A subject's heel-to-toe length over the subject-scaled template's: 0.82-1.27 on the
# bundled trials (0.11-0.17 H against 0.13 H).
FOOT_LENGTH_RANGE = (0.75, 1.35)
# Weight of a foot marker's height misfit against its forward one (heights of foot markers
# carry the silhouette's depth error: a heel measured 37 mm too high on Motion3).
FOOT_HEIGHT_WEIGHT = 0.5
# Two foot markers within this height (mm) of each other are equally "the highest", the
# ankle's mark in facing_from_feet.
FOOT_HEIGHT_TIE = 15.0
# The near foot's markers in a side view, rearmost first (the far foot shows heel and toe).
FOOT_SITES = ("HEE", "ANK", "TOE")
# A foot marker less than this far (mm, along the walking axis) from the ankle lies on
# neither side of it (facing_from_feet).
FOOT_SIDE_MM = 20.0

# The floor frame's fallback (FloorFrame.from_record), declared once for every stage that
# builds one.
CAMERA_HEIGHT = Param(
    "camera_height_mm",
    float,
    800.0,
    "mm",
    "camera height assumed when the calibration has no floor plane",
    100.0,
    5000.0,
)

PARAMS = ParamSet(
    NAME,
    (
        Param("subject", str, "", "", "pseudonymous subject id written into the model"),
        Param(
            "marker_diameter_mm",
            float,
            0.0,
            "mm",
            "marker diameter; 0 = the session camera.json's (carried by the calibration"
            " record), else 25 mm",
            0.0,
            100.0,
        ),
        Param(
            "gate_sigma",
            float,
            4.0,
            "sigma",
            "a blob further than this from the scaled template is left unlabelled",
            1.0,
            100.0,
        ),
        Param(
            "body_radius_mm",
            float,
            700.0,
            "mm",
            "blobs further than this horizontally from the body axis are strays",
            100.0,
            3000.0,
        ),
        CAMERA_HEIGHT,
    ),
)


# --- the floor frame ----------------------------------------------------------------------


@dataclass(frozen=True)
class FloorFrame:
    """Camera space <-> floor frame (a, e, h): rows of ``rot`` are the floor axes."""

    rot: np.ndarray  # (3, 3): e1 (walking axis, +u), e2 (away from camera), e3 (up)
    origin: np.ndarray  # (3,) camera mm, the walking start point on the floor
    length: float = 0.0  # walking line length L (end at a = L); 0 without a calibration

    def to_floor(self, p: np.ndarray) -> np.ndarray:
        """Camera points (..., 3) mm -> floor coordinates (..., 3) = (a, e, h)."""
        return (np.asarray(p, dtype=np.float64) - self.origin) @ self.rot.T

    def to_camera(self, q: np.ndarray) -> np.ndarray:
        """Floor coordinates (..., 3) -> camera points (..., 3) mm."""
        return np.asarray(q, dtype=np.float64) @ self.rot + self.origin

    @classmethod
    def from_record(cls, rec: CalibrationRecord | None, camera_height_mm: float) -> FloorFrame:
        """The floor frame of a calibration record.

        Without a usable plane (no record, or NaN) the camera is assumed level at
        ``camera_height_mm``: a = X, e = Z, h = camera height - Y.
        """
        if rec is not None:
            ff = cls.from_walkway(rec.floor_plane, rec.start, rec.end)
            if ff is not None:
                return ff
        rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
        return cls(rot, np.array([0.0, camera_height_mm, 0.0]))

    @classmethod
    def from_walkway(cls, plane: Any, start: Any, end: Any) -> FloorFrame | None:
        """The floor frame of a floor plane (4,) and walking line start, end (3,) in camera
        mm; None if any is not finite or the line is vertical."""
        plane, start, end = (np.asarray(v, dtype=np.float64) for v in (plane, start, end))
        if not (np.isfinite(plane).all() and np.isfinite(start).all() and np.isfinite(end).all()):
            return None
        n = plane[:3] / np.linalg.norm(plane[:3])
        e1 = end - start
        e1 = e1 - (e1 @ n) * n
        norm = np.linalg.norm(e1)
        if not norm > 0:
            return None
        e1 = e1 / norm
        if e1[0] < 0:
            e1 = -e1
        e2 = np.cross(n, e1)
        # Origin on the floor plane: height 0 there.
        origin = start - (n @ start + plane[3] / np.linalg.norm(plane[:3])) * n
        return cls(np.stack([e1, e2, n]), origin, float(np.linalg.norm(end - start)))


# --- labelling a standing pose --------------------------------------------------------


def template_layout(scale: float = 1.0) -> np.ndarray:
    """The default template as a (10, 3) array [forward, height, lateral] in SITES order."""
    return np.array([TEMPLATE[s] for s in SITES]) * scale


def site_index(name: str) -> int:
    """Index of a marker's site (e.g. ``R_KNE`` -> SITES.index("KNE"))."""
    return SITES.index(name.split("_", 1)[1])


def body_to_floor(layout: np.ndarray, centre: np.ndarray, facing: int) -> np.ndarray:
    """Template layout (10, 3) -> floor positions (20, 3) in MARKER_NAMES order.

    ``centre`` is the floor position (a, e, h-ignored) of the pelvis centre; ``facing`` the
    walking direction (+1: toward +a). The near side (R when facing +1) is at smaller e.
    """
    out = np.full((20, 3), np.nan)
    near = "R" if facing > 0 else "L"
    for i, name in enumerate(MARKER_NAMES):
        f, h, lat = layout[site_index(name)]
        sign = -1.0 if name[0] == near else 1.0
        out[i] = (centre[0] + facing * f, centre[1] + sign * lat, h)
    return out


def facing_from_feet(pts: np.ndarray, sho_height: float) -> int:
    """Facing direction of a standing subject from the foot markers (floor coords, (N, 3)).

    The toe marker lies far in front of the ankle, the heel a little behind it. Among the
    low markers (below ``FOOT_BAND_FRAC`` of the shoulder height) the ankle is the highest;
    the marker of the same foot furthest from it along the walking axis is the toe, and its
    side is the facing direction. With the two highest within ``FOOT_HEIGHT_TIE`` of each
    other, both are read as the ankle and must agree, or only one reading may have the
    ankle between its foot's other markers (an ankle lies between heel and toe). Returns
    +1 or -1, or 0 when undecidable.
    """
    # The foot band of label_pose: a tibia wand low on the shank (0.10-0.13 H on two of
    # the trials) is no ankle.
    low = pts[pts[:, 2] < FOOT_BAND_FRAC * sho_height]
    if len(low) < 2:
        return 0
    order = np.argsort(-low[:, 2])
    vote = _toe_side(low, int(order[0]), sho_height)
    if low[order[0], 2] - low[order[1], 2] < FOOT_HEIGHT_TIE:
        # A toe marker as high as the ankle's (btk_c3dorg_sample04_Matt's left foot: 68
        # and 67 mm): either may be the ankle, and the feet vote only if both readings
        # agree (the toe taken for the ankle points the foot backwards), or if only one
        # has the ankle between its foot's other markers, as an ankle lies between heel
        # and toe (the toe taken for the ankle has them all on one side).
        other = _toe_side(low, int(order[1]), sho_height)
        if other != vote:
            between = [_between(low, int(k), sho_height) for k in order[:2]]
            if between[0] == between[1]:
                return 0
            return vote if between[0] else other
    return vote


def _foot_of(low: np.ndarray, ank: int, sho_height: float) -> np.ndarray:
    """Forward offsets (M,) from the ankle ``ank`` of the other low markers (N, 3) within a
    foot's length of it horizontally (its own foot, and a far marker beside it)."""
    a = low[ank]
    rest = np.delete(low, ank, axis=0)
    near = rest[np.hypot(rest[:, 0] - a[0], rest[:, 1] - a[1]) < 0.2 * sho_height]
    return near[:, 0] - a[0]


def _between(low: np.ndarray, ank: int, sho_height: float) -> bool:
    """Does the ankle ``ank`` have foot markers both behind and ahead of it (by at least
    ``FOOT_SIDE_MM``)?"""
    da = _foot_of(low, ank, sho_height)
    return bool((da < -FOOT_SIDE_MM).any() and (da > FOOT_SIDE_MM).any())


def _toe_side(low: np.ndarray, ank: int, sho_height: float) -> int:
    """The side (+1 / -1, 0 = undecidable) on which the foot marker farthest from the
    ankle ``ank`` along the walking axis lies, among the low markers (N, 3) of its foot."""
    # Only the ankle's own foot: markers within a foot length horizontally.
    da = _foot_of(low, ank, sho_height)
    if len(da) == 0:
        return 0
    s = float(da[np.argmax(np.abs(da))])
    return 0 if abs(s) < FOOT_SIDE_MM else int(np.sign(s))


def _facing_from_mass(pts: np.ndarray, sho_h: float) -> int:
    """Facing from where the feet lie: the toes reach forward of the pelvis, the heels
    only a little behind it, so the low markers' mean lies ahead of the pelvis markers'."""
    if len(pts) == 0:
        return 0
    pts = pts[body_cluster(pts, 0.4 * sho_h)]
    low = pts[pts[:, 2] < 0.1 * sho_h]
    pel = pts[(pts[:, 2] > 0.55 * sho_h) & (pts[:, 2] < 0.8 * sho_h)]
    if len(low) == 0 or len(pel) == 0:
        return 0
    # A hand or a stray at pelvis height lies beyond the pelvis's own length (the
    # template's PSI-ASI span) from the pelvis blobs' median: btk_PiG_Motion-FlatFoot-Full's
    # stray 0.3 H ahead moved the pelvis centre forward and turned every frame's vote.
    tpl = template_layout(sho_h / TEMPLATE_SHO_HEIGHT)
    span = float(tpl[SITES.index("ASI"), 0] - tpl[SITES.index("PSI"), 0])
    pel = pel[np.abs(pel[:, 0] - np.median(pel[:, 0])) <= span]
    d = float(low[:, 0].mean() - 0.5 * (pel[:, 0].min() + pel[:, 0].max()))
    return 0 if abs(d) < 15.0 else int(np.sign(d))


def label_pose(
    pts: np.ndarray, facing: int, layout: np.ndarray, gate_sigma: float = 4.0
) -> np.ndarray:
    """Label the blobs of one standing pose by layout rules.

    Parameters
    ----------
    pts : (N, 3) floor coordinates (a, e, h) of the blobs (NaN rows ignored).
    facing : +1 / -1, the walking direction the subject faces.
    layout : (10, 3) body-frame [forward, height, lateral] per site; only the heights
        (as fractions of the shoulder height) are used, to cut the body into bands.
    gate_sigma : unused by the rules; kept for the template-based interface.

    Used by :func:`consensus_pose` on every static frame.

    Returns
    -------
    (20,) int: blob index per marker, -1 = not seen.

    Rules (side view, subject standing; H = shoulder height): the shoulder is the top
    body blob nearest the camera. Blobs beyond the template's forward span from the
    shoulder (pelvis band: PSI..ASI + STRAY_PELVIS_FRAC * H; any: PSI..TOE +
    STRAY_BODY_FRAC * H) are strays. Near or far: a blob is far only behind a near twin
    (same forward position and height within TWIN_TOL_FRAC * H; depth alone is too noisy),
    or, on the floor, more than FAR_FOOT_FRAC * H beyond the near foot. Pelvis band: a near
    blob more than HIP_DROP_FACTOR times the template's hip drop below the other pelvis
    blobs is a thigh wand (it joins the leg band); the near HIP is the lowest near blob
    (when clearly lower), PSI the rearmost and ASI the foremost within PELVIS_LEVEL_FRAC * H
    of the PSI's height; far PSI/ASI likewise. Leg band: KNE is the blob nearest the
    template's knee height, THI the highest above it; blobs below it join the shank band.
    Shank/foot band: TIB is the highest near blob above the ankle band; of the low near
    blobs TOE is the foremost, ANK and HEE the rest by the template's forward and height
    gaps (a far twin of the near foot's middle blob that fits the ankle's place better is
    the near ankle behind a shoe's reflector: the far foot shows no ankle marker); the far
    heel and toe are the rearmost and foremost low far blobs. Each foot's
    blobs are the largest group within FOOT_SPAN_FRAC * H along the walking axis (the near
    foot's nearest the tibia marker, the far foot's nearest the near foot); low blobs
    outside it are reflectors on the floor.
    """
    del gate_sigma
    out = np.full(20, -1)
    ok = np.flatnonzero(np.isfinite(pts).all(axis=1))
    if ok.size == 0:
        return out
    P = pts[ok]
    H0 = layout[SITES.index("SHO"), 1]
    member = body_cluster(P, 0.4 * H0)
    ok, P = ok[member], P[member]
    if len(P) < 3:
        return out
    near = "R" if facing > 0 else "L"
    far = "L" if near == "R" else "R"
    f = facing * P[:, 0]
    h = P[:, 2]
    e = P[:, 1]
    # The shoulder: of the blobs near the top, the one nearest the camera (the far
    # shoulder can peek over the near one, a little higher).
    top = np.flatnonzero(h > 0.92 * h.max())
    sho = int(top[np.argmin(e[top])])
    H = float(h[sho])
    out[MARKER_INDEX[f"{near}_SHO"]] = ok[sho]
    frac = {s: layout[SITES.index(s), 1] / H0 for s in SITES}
    # Closer to the thigh than to the hip: a crouching subject's hip sits low.
    lo_pel = (0.3 * frac["HIP"] + 0.7 * frac["THI"]) * H
    hi_pel = 0.5 * (1.0 + max(frac["ASI"], frac["PSI"])) * H
    lo_leg = 0.5 * (frac["TIB"] + frac["KNE"]) * H
    # Ankle, heel and toe sit below ~7% of shoulder height, a tibia marker above ~10%.
    lo_shank = FOOT_BAND_FRAC * H
    # A standing subject's markers lie within the template's forward span around the
    # shoulder (PSI rearmost, TOE foremost) plus a margin for posture and proportions;
    # a blob beyond it at body height is a stray (a hand, a reflector) within the cluster.
    rel_f = facing * (layout[:, 0] - layout[SITES.index("SHO"), 0]) * H / H0
    pel_f = rel_f[[SITES.index(x) for x in ("ASI", "PSI", "HIP")]]
    df = f - f[sho]
    # Knees and feet reach further forward in a crouched stance than the pelvis can.
    inside = (df > rel_f.min() - STRAY_BODY_FRAC * H) & (df < rel_f.max() + STRAY_BODY_FRAC * H)
    in_pel = (df > pel_f.min() - STRAY_PELVIS_FRAC * H) & (df < pel_f.max() + STRAY_PELVIS_FRAC * H)
    pel = np.flatnonzero((h > lo_pel) & (h < hi_pel) & in_pel)
    # Near or far: in a side view a far marker sits behind its near twin (same forward
    # position and height, further in depth); a blob without such a twin is on the near
    # side, whatever its depth (a marker's depth is noisy, often by 50-100 mm).
    is_near = np.ones(len(P), bool)
    tol = TWIN_TOL_FRAC * H

    def twins(cand: np.ndarray) -> None:
        for i in cand:
            for j in cand:
                if (
                    i != j
                    and e[j] > e[i]
                    and abs(f[i] - f[j]) < tol
                    and abs(h[i] - h[j]) < tol
                    and is_near[i]
                ):
                    is_near[j] = False

    twins(pel)

    def put(name: str, i: int) -> None:
        out[MARKER_INDEX[name]] = ok[i]

    hip_drop = HIP_DROP_FACTOR * (0.5 * (frac["ASI"] + frac["PSI"]) - frac["HIP"]) * H
    wand = []  # near pelvis-band blobs too low for the hip: the thigh wand's candidates
    for side, sel in ((near, is_near), (far, ~is_near)):
        c = [i for i in pel if sel[i]]
        while side == near and len(c) >= 2:
            low = min(c, key=lambda i: h[i])
            if h[low] > float(np.median([h[i] for i in c if i != low])) - hip_drop:
                break
            wand.append(low)
            c.remove(low)
        if side == near and len(c) >= 2:
            low = min(c, key=lambda i: h[i])
            others = [i for i in c if i != low]
            if len(c) >= 3 or h[low] < min(h[i] for i in others) - 0.03 * H:
                put(f"{side}_HIP", low)
                c = others
        if len(c) >= 2:
            c = sorted(c, key=lambda i: f[i])
            put(f"{side}_PSI", c[0])
            # The pelvis stands about level (tilt moves ASI and PSI by a few cm): a blob
            # far above or below the PSI is a hand or a stray, not the ASI.
            level = [i for i in c[1:] if abs(h[i] - h[c[0]]) < PELVIS_LEVEL_FRAC * H]
            if level:
                put(f"{side}_ASI", level[-1])
        elif len(c) == 1:
            # One pelvis blob: front or back of the pelvis, judged against the shoulder.
            put(f"{side}_ASI" if f[c[0]] > f[sho] else f"{side}_PSI", c[0])
    leg = [i for i in np.flatnonzero((h > lo_leg) & (h <= lo_pel) & inside) if is_near[i]]
    leg = sorted(leg + wand, key=lambda i: -h[i])
    below_knee: list[int] = []
    th, kn = frac["THI"] * H, frac["KNE"] * H
    if len(leg) >= 2:
        # The knee is the blob nearest the template's knee height (0.32-0.37 H on every
        # trial), not the lowest: a tibia wand placed high on the shank (0.28 H, 0.07 H
        # below the knee, on opensim_rajagopal_walk) enters this band. The thigh wand is
        # the highest blob above the knee; blobs below it belong to the shank.
        knee = min(leg, key=lambda i: abs(h[i] - kn))
        above = [i for i in leg if h[i] > h[knee]]
        below_knee = [i for i in leg if h[i] < h[knee]]
        put(f"{near}_KNE", knee)
        if above:
            put(f"{near}_THI", above[0])
    elif len(leg) == 1:
        put(f"{near}_THI" if abs(h[leg[0]] - th) < abs(h[leg[0]] - kn) else f"{near}_KNE", leg[0])
    shank = [i for i in np.flatnonzero((h > lo_shank) & (h <= lo_leg) & inside) if is_near[i]]
    shank += below_knee
    if shank:
        put(f"{near}_TIB", max(shank, key=lambda i: h[i]))
    # Feet: twins as for the pelvis (the far heel or toe behind the near one); a low blob
    # without a twin is near unless it lies clearly beyond the near foot in depth.
    low_all = np.flatnonzero((h <= lo_shank) & inside)
    twins(low_all)
    if is_near[low_all].sum() >= 2:
        e_foot = float(np.median(e[low_all[is_near[low_all]]]))
        for i in low_all:
            if is_near[i] and e[i] > e_foot + FAR_FOOT_FRAC * H:
                is_near[i] = False
    # Each foot is one group within a foot's length; a low blob outside its side's group
    # is a reflector on the floor, not a marker (the group nearest the shank above it).
    shank_f = f[max(shank, key=lambda i: h[i])] if shank else None
    near_low = _one_foot([i for i in low_all if is_near[i]], f, FOOT_SPAN_FRAC * H, shank_f)
    scaled = layout * (H / H0)
    near_low = _fit_foot(near_low, f, h, scaled, FOOT_SITES)
    if len(near_low) == 3:
        # The far foot shows only its heel and toe, so a far twin of the near foot's middle
        # blob that fits the ankle's place better is no far marker but the near ankle, with
        # a shoe's reflector just in front of it (on `shoes`: 15 mm behind the ankle, 18 mm
        # below it, 39 mm nearer the camera). The blob in front is left a reflector.
        mid = near_low[1]
        for j in low_all:
            if is_near[j] or e[j] <= e[mid] or max(abs(f[j] - f[mid]), abs(h[j] - h[mid])) >= tol:
                continue
            swapped = (near_low[0], int(j), near_low[2])
            if _foot_misfit(swapped, f, h, scaled, FOOT_SITES) < _foot_misfit(
                tuple(near_low), f, h, scaled, FOOT_SITES
            ):
                near_low = sorted(swapped, key=lambda i: f[i])
                is_near[j] = True
    near_mid = 0.5 * (f[near_low[0]] + f[near_low[-1]]) if near_low else shank_f
    far_low = _one_foot([i for i in low_all if not is_near[i]], f, FOOT_SPAN_FRAC * H, near_mid)
    far_low = _fit_foot(far_low, f, h, scaled, ("HEE", "TOE"))
    if near_low:
        put(f"{near}_TOE", near_low[-1])
        rest = near_low[:-1]
        if len(rest) >= 2:
            # Ankle and heel: the ankle is ahead of and above the heel; weigh both gaps by
            # the template's (forward 60 mm, height 33 mm for an adult), as heights of foot
            # markers are noisy.
            gap_f = (layout[SITES.index("ANK"), 0] - layout[SITES.index("HEE"), 0]) * H / H0
            gap_h = (layout[SITES.index("ANK"), 1] - layout[SITES.index("HEE"), 1]) * H / H0
            a, b = rest[-1], rest[-2]
            if (f[a] - f[b]) / gap_f + (h[a] - h[b]) / gap_h < 0:
                a, b = b, a
            put(f"{near}_ANK", a)
            put(f"{near}_HEE", min((i for i in rest if i != a), key=lambda i: f[i]))
        # One blob between heel and ankle is likely the two merged: neither is measured.
    if len(far_low) >= 2:
        put(f"{far}_HEE", far_low[0])
        put(f"{far}_TOE", far_low[-1])
    elif len(far_low) == 1:
        # One far foot blob: heel or toe, whichever near one it lines up with.
        nt, nh = out[MARKER_INDEX[f"{near}_TOE"]], out[MARKER_INDEX[f"{near}_HEE"]]
        ref_t = f[list(ok).index(nt)] if nt >= 0 else None
        ref_h = f[list(ok).index(nh)] if nh >= 0 else None
        i = far_low[0]
        if ref_t is not None and (ref_h is None or abs(f[i] - ref_t) < abs(f[i] - ref_h)):
            put(f"{far}_TOE", i)
        elif ref_h is not None:
            put(f"{far}_HEE", i)
    return out


def _one_foot(idx: list[int], f: np.ndarray, span: float, centre: float | None) -> list[int]:
    """The largest group of blobs ``idx`` within ``span`` of each other in forward position
    ``f``, sorted by it; of equal groups the one whose middle is nearest ``centre`` (the
    rearmost without one)."""
    order = sorted(idx, key=lambda i: f[i])
    best: list[int] = []
    best_d = np.inf
    for a in range(len(order)):
        b = a
        while b + 1 < len(order) and f[order[b + 1]] - f[order[a]] <= span:
            b += 1
        group = order[a : b + 1]
        d = 0.0 if centre is None else abs(0.5 * (f[group[0]] + f[group[-1]]) - centre)
        if len(group) > len(best) or (len(group) == len(best) and d < best_d):
            best, best_d = group, d
    return best


def _fit_foot(
    idx: list[int], f: np.ndarray, h: np.ndarray, layout: np.ndarray, sites: tuple[str, ...]
) -> list[int]:
    """Of more blobs of one foot than its visible ``sites`` (rearmost first, the toe last),
    the ones whose forward distances to the foremost best fit the template's (``layout``
    scaled to the subject), sorted by forward position ``f``; the others are reflectors on
    the floor or the other foot's markers.

    With three sites the template is also scaled to the candidates' own heel-to-toe length
    (within ``FOOT_LENGTH_RANGE``): feet differ in length more than in shape, and fitted at
    the template's length a short foot's heel and toe (0.11 H) misfit as much as a far heel
    seen beside its ankle. The middle site's height above the rearmost counts too, at
    ``FOOT_HEIGHT_WEIGHT``: a shoe's reflector can sit where the ankle marker would be along
    the foot, but not as high. With two sites the length is all there is to fit.
    """
    if len(idx) <= len(sites):
        return idx
    return list(
        min(
            itertools.combinations(idx, len(sites)),
            key=lambda t: _foot_misfit(t, f, h, layout, sites),
        )
    )


def _foot_misfit(
    t: tuple[int, ...], f: np.ndarray, h: np.ndarray, layout: np.ndarray, sites: tuple[str, ...]
) -> float:
    """How far blobs ``t`` (one per site of ``sites``, rearmost first) lie from the
    template's foot (``layout`` scaled to the subject), mm: :func:`_fit_foot`'s measure."""
    tpl = [float(layout[SITES.index(s), 0]) for s in sites]
    tpl_h = [float(layout[SITES.index(s), 1]) for s in sites]
    length = tpl[-1] - tpl[0]
    scale = 1.0
    if len(t) > 2 and length > 0:
        scale = float(np.clip((f[t[-1]] - f[t[0]]) / length, *FOOT_LENGTH_RANGE))
    along = sum(abs(f[t[-1]] - f[t[k]] - scale * (tpl[-1] - tpl[k])) for k in range(len(t) - 1))
    up = sum(abs(h[t[k]] - h[t[0]] - scale * (tpl_h[k] - tpl_h[0])) for k in range(1, len(t) - 1))
    return along + FOOT_HEIGHT_WEIGHT * up


def consensus_pose(
    floors: list[np.ndarray],
    facing: int,
    layout: np.ndarray,
    marker_diameter_mm: float = 25.0,
    gate_sigma: float = 4.0,
) -> np.ndarray:
    """Standing pose labelled by the consensus of the static frames (Sec. IV-B, departure).

    Parameters
    ----------
    floors : per frame, (N, 3) floor coordinates (a, e, h) of the blobs, mm.
    facing, layout, gate_sigma : as for :func:`label_pose`.
    marker_diameter_mm : two markers closer than this (forward, height) are one blob.

    Returns
    -------
    (20, 3) floor positions in MARKER_NAMES order, NaN = not labelled.

    Every frame is labelled by :func:`label_pose`. Per marker, the labelled positions
    within ``CONSENSUS_DIAMETERS`` marker diameters (forward and height; depth is noisy) of
    their median agree; a frame whose labels mostly disagree is dropped and the medians
    recomputed. A marker is kept if at least a third of the kept frames agree on it (a
    hand, a glint or a split that comes and goes is outvoted); two markers on one position
    keep the one more frames agree on. The position is the median of the agreeing labels.
    """
    out = np.full((20, 3), np.nan)
    labs = []
    for P in floors:
        idx = label_pose(P, facing, layout, gate_sigma) if len(P) else np.full(20, -1)
        q = np.full((20, 3), np.nan)
        q[idx >= 0] = P[idx[idx >= 0]]
        labs.append(q)
    if not labs:
        return out
    L = np.stack(labs)  # (F, 20, 3)
    tol = CONSENSUS_DIAMETERS * marker_diameter_mm
    keep = np.ones(len(L), bool)
    for _ in range(2):
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN markers: never seen
            med = np.nanmedian(L[keep], axis=0)
        dev = np.hypot(L[..., 0] - med[None, :, 0], L[..., 2] - med[None, :, 2])
        seen = np.isfinite(dev)
        agree = seen & (dev < tol)
        # A frame agreeing on under half of its labels is an outlier frame.
        frac = agree.sum(axis=1) / np.maximum(seen.sum(axis=1), 1)
        new_keep = frac >= 0.5
        if not new_keep.any() or (new_keep == keep).all():
            break
        keep = new_keep
    agree &= keep[:, None]
    votes = agree.sum(axis=0)
    for i in np.flatnonzero(votes >= max(keep.sum() / 3.0, 1.0)):
        out[i] = np.median(L[agree[:, i], i], axis=0)
    # One position, two labels in different frames (near in some, far in others): most
    # votes win. Twins (near and far heel side by side) are both labelled in the same
    # frames, on two blobs, and both stay.
    order = np.argsort(-votes)
    for x, i in enumerate(order):
        if not np.isfinite(out[i]).all():
            continue
        for j in order[x + 1 :]:
            if not np.isfinite(out[j]).all():
                continue
            close = np.hypot(*(out[i] - out[j])[[0, 2]]) < marker_diameter_mm
            both = int((agree[:, i] & agree[:, j]).sum())
            if close and both < 0.5 * min(votes[i], votes[j]):
                out[j] = np.nan
    return out


# --- the stage core ---------------------------------------------------------------------


@dataclass(frozen=True)
class ModelState:
    """Positions accumulated over the static trial."""

    params: dict[str, Any]
    frames: tuple[np.ndarray, ...] = ()  # each (N, 3) camera mm, normal mode
    last_header: Any = None
    calibration: CalibrationRecord | None = None
    published: bool = False


def init(params: dict[str, Any]) -> ModelState:
    """Initial state; ``params`` are resolved by :data:`PARAMS`."""
    return ModelState(params=dict(params))


def build_model(
    frames: tuple[np.ndarray, ...] | list[np.ndarray],
    frame: FloorFrame,
    marker_diameter_mm: float = 25.0,
    gate_sigma: float = 4.0,
) -> dict[str, Any]:
    """Build the subject model from the static frames.

    Parameters
    ----------
    frames : per frame, (N, 3) camera-space blob positions (normal mode), mm.
    frame : the floor frame.

    Returns
    -------
    dict with ``reference`` (20, 3), ``distances`` (20, 20), ``near_side`` and ``extra``.
    """
    floors = [frame.to_floor(f.reshape(-1, 3)) for f in frames if len(f)]
    # The shoulder: the highest blob near the body, per frame (median over frames).
    tops = []
    for f in floors:
        g = f[np.isfinite(f).all(axis=1)]
        if len(g):
            # A first guess of the body size only serves to find the body cluster.
            g = g[body_cluster(g, 0.4 * TEMPLATE_SHO_HEIGHT)]
            tops.append(float(g[:, 2].max()))
    sho_h = float(np.median(tops)) if tops else TEMPLATE_SHO_HEIGHT
    if not 0.5 * TEMPLATE_SHO_HEIGHT < sho_h < 1.5 * TEMPLATE_SHO_HEIGHT:
        sho_h = TEMPLATE_SHO_HEIGHT
    layout = template_layout(sho_h / TEMPLATE_SHO_HEIGHT)
    votes = [facing_from_feet(f[np.isfinite(f).all(axis=1)], sho_h) for f in floors]
    votes += [_facing_from_mass(f[np.isfinite(f).all(axis=1)], sho_h) for f in floors]
    facing = 1 if sum(votes) >= 0 else -1
    near = "R" if facing > 0 else "L"
    # The subject stands still: label every frame on its own and keep, per marker, the
    # consensus of the frames (see consensus_pose), so that one frame with an extra or a
    # missing blob cannot mislabel the model.
    valid = [f[np.isfinite(f).all(axis=1)] for f in floors]
    floor_ref = consensus_pose(valid, facing, layout, marker_diameter_mm, gate_sigma)
    reference = frame.to_camera(floor_ref)
    diff = reference[:, None, :] - reference[None, :, :]
    distances = np.linalg.norm(diff, axis=2)
    # Body-frame layout of the sites, measured on the near side.
    pel = [MARKER_INDEX[f"{s}_{m}"] for s in "LR" for m in ("ASI", "PSI")]
    centre = np.nanmean(floor_ref[pel], axis=0) if np.isfinite(floor_ref[pel]).any() else None
    measured = layout.copy()
    seen: dict[str, bool] = {}
    if centre is not None:
        near_e = [floor_ref[MARKER_INDEX[f"{near}_{s}"], 1] for s in SITES]
        far = "L" if near == "R" else "R"
        far_e = [floor_ref[MARKER_INDEX[f"{far}_{s}"], 1] for s in ("ASI", "PSI")]
        both = [e for e in (*near_e[1:3], *far_e) if np.isfinite(e)]
        mid_e = float(np.mean(both)) if len(both) == 4 else centre[1]
        for j, s in enumerate(SITES):
            q = floor_ref[MARKER_INDEX[f"{near}_{s}"]]
            if np.isfinite(q).all():
                measured[j] = (facing * (q[0] - centre[0]), q[2], mid_e - q[1])
                seen[s] = True
            else:
                seen[s] = False
    # Unmeasured sites: the template's offset from the nearest measured site of the same
    # chain, so that foot and leg distances stay consistent with what was measured.
    for j, s in enumerate(SITES):
        if seen.get(s):
            continue
        for k in CHAIN.get(s, ()):
            if seen.get(k):
                jk = SITES.index(k)
                measured[j, [0, 2]] = measured[jk, [0, 2]] + (layout[j] - layout[jk])[[0, 2]]
                break
    site_d = np.linalg.norm(measured[:, None, :] - measured[None, :, :], axis=2)
    near_ref = floor_ref[[MARKER_INDEX[f"{near}_{s}"] for s in SITES]]
    with np.errstate(invalid="ignore"):
        nd = np.linalg.norm(near_ref[:, None, :] - near_ref[None, :, :], axis=2)
    site_d = np.where(np.isfinite(nd), nd, site_d)

    def seg(a: str, b: str) -> float:
        return float(site_d[SITES.index(a), SITES.index(b)])

    # Standing offsets from the near shoulder: forward (along the facing direction), e
    # (away from the camera), height. Near side: every site (measured, or anchored as
    # above); far side: the markers seen. Label predicts from these.
    sho_q = floor_ref[MARKER_INDEX[f"{near}_SHO"]]
    offsets: dict[str, list[float]] = {}
    s0 = measured[SITES.index("SHO")]
    for j, s in enumerate(SITES):
        offsets[f"near_{s}"] = [
            float(measured[j, 0] - s0[0]),
            float(s0[2] - measured[j, 2]),
            float(measured[j, 1]),
        ]
    if np.isfinite(sho_q).all():
        far = "L" if near == "R" else "R"
        for s in SITES:
            q = floor_ref[MARKER_INDEX[f"{far}_{s}"]]
            if np.isfinite(q).all():
                offsets[f"far_{s}"] = [
                    float(facing * (q[0] - sho_q[0])),
                    float(q[1] - sho_q[1]),
                    float(q[2]),
                ]
    extra = {
        "facing": facing,
        "offsets_from_shoulder": offsets,
        "frames_used": len(floors),
        "sho_height_mm": sho_h,
        "layout": {s: [float(x) for x in measured[j]] for j, s in enumerate(SITES)},
        "measured": seen,
        "site_distances": site_d.tolist(),
        "heights_mm": {s: float(measured[j, 1]) for j, s in enumerate(SITES)},
        "thigh_mm": seg("HIP", "KNE"),
        "shank_mm": seg("KNE", "ANK"),
        "foot_mm": seg("HEE", "TOE"),
    }
    return {
        "reference": reference,
        "distances": distances,
        "near_side": near,
        "marker_diameter_mm": marker_diameter_mm,
        "extra": extra,
    }


def _publish(state: ModelState, hdr: Any) -> SubjectModel:
    p = state.params
    ff = FloorFrame.from_record(state.calibration, p["camera_height_mm"])
    cal = state.calibration
    diameter = marker_diameter(p["marker_diameter_mm"], cal.camera if cal is not None else None)
    m = build_model(state.frames, ff, diameter, p["gate_sigma"])
    return SubjectModel.follow(hdr, subject=p["subject"], **m)


def step(state: ModelState, inputs: Mapping[str, Message]) -> tuple[ModelState, list[Message]]:
    """Accumulate one static frame; publish the SubjectModel on the trial's last frame.

    Parameters
    ----------
    inputs : ``{"markers": Markers3D, "calibration": CalibrationRecord}``.
    """
    mk = inputs["markers"]
    if not isinstance(mk, Markers3D):
        raise StageError(NAME, f"input 'markers' is a {type(mk).__name__}, not Markers3D")
    cal = inputs.get("calibration")
    pos = np.asarray(mk.position, dtype=np.float64).reshape(-1, 3, 3)[:, 0, :]
    st = replace(
        state,
        frames=(*state.frames, pos.copy()),
        last_header=mk.header,
        calibration=cal if isinstance(cal, CalibrationRecord) else state.calibration,
        published=False,
    )
    if mk.header.last:
        return replace(st, frames=(), published=True), [_publish(st, mk.header)]
    return st, []


def finish(state: ModelState) -> tuple[ModelState, list[Message]]:
    """Publish the model if the static trial ended without a ``last`` frame."""
    if state.published or state.last_header is None or not state.frames:
        return state, []
    return replace(state, frames=(), published=True), [_publish(state, state.last_header)]


SPEC = StageSpec(
    name=NAME,
    params=PARAMS,
    init=init,
    step=step,
    finish=finish,
    stateful=True,
    doc=__doc__ or "",
)
