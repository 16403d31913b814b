"""The simulated subject: markers from a real trial, derived markers, and a capsule body.

Arrays: time axis 0; marker axis follows :data:`gaitflow.markers.MARKER_NAMES`; positions
in mm in the trial's *standard frame* (x = walking direction, y = left, z = up, floor at
z = 0), obtained with the trial's ``R_lab_to_std``. NaN = missing.

Rules for markers a source trial lacks (all documented in docs/readme/simulator.md):

- **Hip joint centre** (HJC): Harrington et al. (2007) regression from pelvis width PW
  (ASIS to ASIS) and depth PD (mid-ASIS to mid-PSIS), in the pelvis frame (origin mid-ASIS,
  x anterior, y up, z lateral): x = -0.24 PD - 9.9, y = -0.30 PW - 10.9, z = 0.33 PW + 7.3.
- **HIP** (greater-trochanter marker): HJC + 85 mm lateral (femoral-neck offset ~60 mm plus
  ~25 mm soft tissue) + marker radius, 15 mm down the thigh axis.
- **PSI** from SACR: SACR -/+ 0.18 PW along the pelvis lateral axis (inter-PSIS distance
  about 0.36 PW); **SACR** from PSI: their midpoint.
- **HEE** from ANK and TOE: 0.27 |TOE - ANK| behind the ankle along the ankle-toe axis,
  43 mm below it and 48 mm medial (medians over the 48 feet with heel markers in
  ../shared/gaitdata; median 6-37 mm from the real heel marker on the bundled trials).
- **SHO** from C7: C7 -/+ 0.13 H lateral and 0.02 H lower; without C7 from the pelvis
  centre: 0.27 H up (Winter 2009 segment proportions; H = stature estimated as ASIS
  height / 0.55).

Markers are moved outwards along their segment's normal by the difference between the
simulated and the source marker radius. Every marker is taped to the skin, so a **skin
patch** (a short capsule of the segment's material, about 70 mm across, its axis along the
segment and tangent to the marker's base) is added under each marker: the body surface then
passes ``marker radius + base`` behind the marker centre along its normal, wherever the
nominal capsule (a smooth, round limb) is thinner or thicker than the real segment there.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow.errors import ConfigError, InputError
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES
from gaitflow.sim.config import WAND_MOUNTS

SIDES = ("L", "R")
REQUIRED = ("ASI", "THI", "KNE", "TIB", "ANK", "TOE")

# Capsule segments of the body and their surface material for the IR albedo: a gait-lab
# subject in a T-shirt and shorts, legs and feet bare (Plug-in Gait markers go on the skin).
# The markers listed must stay outside the segment (see :func:`build_body`).
SEGMENTS: tuple[tuple[str, float, str, tuple[str, ...]], ...] = (
    # name, nominal radius mm, material, markers that must stay outside
    ("pelvis", 95.0, "shorts", ("L_ASI", "R_ASI", "L_HIP", "R_HIP", "L_PSI", "R_PSI")),
    ("sacrum", 60.0, "shorts", ("L_PSI", "R_PSI", "L_ASI", "R_ASI")),
    ("trunk", 125.0, "shirt", ("L_SHO", "R_SHO", "L_PSI", "R_PSI", "L_ASI", "R_ASI")),
    ("shoulders", 55.0, "shirt", ("L_SHO", "R_SHO")),
    ("neck", 50.0, "skin", ("L_SHO", "R_SHO")),
    ("head", 95.0, "skin", ()),
    ("L_thigh", 80.0, "shorts", ("L_THI", "L_HIP")),
    ("R_thigh", 80.0, "shorts", ("R_THI", "R_HIP")),
    ("L_thigh_lo", 58.0, "skin", ("L_THI", "L_KNE")),
    ("R_thigh_lo", 58.0, "skin", ("R_THI", "R_KNE")),
    ("L_shank", 55.0, "skin", ("L_TIB", "L_KNE")),
    ("R_shank", 55.0, "skin", ("R_TIB", "R_KNE")),
    ("L_shank_lo", 38.0, "skin", ("L_TIB", "L_ANK")),
    ("R_shank_lo", 38.0, "skin", ("R_TIB", "R_ANK")),
    ("L_foot", 26.0, "skin", ("L_HEE", "L_TOE")),
    ("R_foot", 26.0, "skin", ("R_HEE", "R_TOE")),
    ("L_upperarm", 45.0, "shirt", ("L_SHO",)),
    ("R_upperarm", 45.0, "shirt", ("R_SHO",)),
    ("L_forearm", 38.0, "skin", ()),
    ("R_forearm", 38.0, "skin", ()),
)
SEGMENT_NAMES = tuple(s[0] for s in SEGMENTS)
# Plug-in Gait's thigh and tibia markers are often mounted on wands: a thin stick whose
# base is taped to the skin, the sphere 40-100 mm off the limb (see ``build_body``).
WAND_SITES = {"THI": ("thigh", "thigh_lo"), "TIB": ("shank", "shank_lo")}
WAND_RADIUS_MM = 3.0
SEGMENT_INDEX = {n: i for i, n in enumerate(SEGMENT_NAMES)}


@dataclass(frozen=True)
class Trial:
    """One source trial in the standard frame, gaps filled, trimmed to complete frames.

    Attributes
    ----------
    name : trial id.
    t : (F,) s from the first kept frame.
    markers : canonical name -> (F, 3) mm, standard frame.
    knee_ref : (F, 2) source Plug-in Gait knee flexion (L, R) deg, NaN where absent.
    events : list of (time_s, side, kind) with kind 'FS' or 'FO', inside [0, t[-1]].
    meta : the source's metadata (source, licence, ...).
    """

    name: str
    t: np.ndarray
    markers: dict[str, np.ndarray]
    knee_ref: np.ndarray
    events: list[tuple[float, str, str]]
    rate_hz: float
    meta: dict[str, Any] = field(default_factory=dict)


def trials_dir() -> Path:
    """Folder of the bundled trials (gaitflow/data/trials)."""
    return Path(str(resources.files("gaitflow") / "data" / "trials"))


def list_trials() -> list[str]:
    """Ids of the bundled trials, from the bundled index.csv."""
    path = trials_dir() / "index.csv"
    with path.open(newline="") as fh:
        return [row["trial_id"] for row in csv.DictReader(fh)]


def _fill_gaps(x: np.ndarray) -> np.ndarray:
    """Linear interpolation over interior NaN gaps of a (F, 3) trajectory; ends stay NaN."""
    x = x.copy()
    ok = np.isfinite(x).all(axis=1)
    if ok.sum() < 2:
        return x
    idx = np.arange(len(x))
    first, last = np.flatnonzero(ok)[[0, -1]]
    inner = (~ok) & (idx > first) & (idx < last)
    for k in range(3):
        x[inner, k] = np.interp(idx[inner], idx[ok], x[ok, k])
    return x


def load_trial(name: str, folder: Path | None = None) -> Trial:
    """Load a bundled trial (or one from ``folder``) into the standard frame.

    ``name`` is a bundled trial id, or the path of a ``.npz`` trial in the gaitdata format
    (``../shared/gaitdata/README.md``): a researcher's own trial, or one held out of the
    bundle to check that the pipeline is not tuned to the bundled five.

    Raises InputError naming the file when the trial lacks a required lower-limb marker.
    """
    as_path = Path(name)
    path = as_path if as_path.suffix == ".npz" else (folder or trials_dir()) / f"{name}.npz"
    if not path.exists():
        raise InputError(path, f"no such trial; bundled trials: {', '.join(list_trials())}")
    d = np.load(path, allow_pickle=True)
    R = np.asarray(d["R_lab_to_std"], dtype=np.float64)
    raw = np.asarray(d["markers"], dtype=np.float64) @ R.T
    canon = [str(c) for c in d["canonical"]]
    rate = float(d["rate_hz"])
    markers = {c: _fill_gaps(raw[:, i]) for i, c in enumerate(canon) if c}
    for side in SIDES:
        for site in REQUIRED:
            if f"{side}_{site}" not in markers:
                raise InputError(path, f"trial lacks marker {side}_{site}")
    if not any(k in markers for k in ("SACR", "L_PSI")):
        raise InputError(path, "trial has neither SACR nor PSI markers")
    # Keep the longest run of frames in which every marker the body needs is present.
    need = [f"{s}_{m}" for s in SIDES for m in REQUIRED]
    need += ["L_PSI", "R_PSI"] if "L_PSI" in markers else ["SACR"]
    ok = np.all([np.isfinite(markers[n]).all(axis=1) for n in need], axis=0)
    runs = np.flatnonzero(np.diff(np.r_[0, ok.astype(int), 0]))
    starts, ends = runs[::2], runs[1::2]
    if len(starts) == 0:
        raise InputError(path, "no frame has every required marker")
    j = int(np.argmax(ends - starts))
    a, b = int(starts[j]), int(ends[j])
    markers = {k: v[a:b] for k, v in markers.items()}
    t = np.arange(b - a) / rate
    knee = np.full((b - a, 2), np.nan)
    if "ref_angle_names" in d.files:
        names = [str(n) for n in d["ref_angle_names"]]
        for k, side in enumerate(SIDES):
            for cand in (f"{side}KneeAngles", f"{side}KneeAnglesV"):
                if cand in names:
                    knee[:, k] = np.asarray(d["ref_angles"], dtype=np.float64)[
                        a:b, names.index(cand), 0
                    ]
                    break
    events = []
    for tt, side, kind in zip(d["event_times"], d["event_sides"], d["event_kinds"], strict=True):
        tt = float(tt) - a / rate
        if str(kind) in ("FS", "FO") and str(side) in SIDES and 0.0 <= tt <= t[-1]:
            events.append((tt, str(side), str(kind)))
    events.sort()
    meta = json.loads(str(d["metadata"])) if "metadata" in d.files else {}
    return Trial(name, t, markers, knee, events, rate, meta)


def scale_trial(trial: Trial, k: float) -> Trial:
    """The trial's subject at ``k`` times the size (a child for k < 1), walking the same
    gait with dynamic similarity: lengths times k (about the floor point below the origin,
    so the feet stay on the floor), times times sqrt(k) (equal Froude number: speed grows
    with the square root of leg length), joint angles unchanged. ``k`` = 1 returns the trial.
    """
    if k == 1.0:
        return trial
    f = float(np.sqrt(k))
    return replace(
        trial,
        t=trial.t * f,
        markers={n: v * k for n, v in trial.markers.items()},
        events=[(tt * f, side, kind) for tt, side, kind in trial.events],
        rate_hz=trial.rate_hz / f,
    )


# Half the knee and ankle widths of Plug-in Gait (100 and 70 mm): the joint centres lie this
# much plus the marker radius medial of the lateral markers.
KNEE_HALF_WIDTH, ANKLE_HALF_WIDTH = 50.0, 35.0
UPPER_BODY = ("C7", "SACR", "L_ASI", "R_ASI", "L_PSI", "R_PSI", "L_SHO", "R_SHO")


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations taking directions a (F, 3) onto b (F, 3), about a x b."""
    a, b = _unit(a), _unit(b)
    v = np.cross(a, b)
    c = (a * b).sum(axis=1)
    vx = np.zeros((len(a), 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx = vx - vx.transpose(0, 2, 1)
    return np.eye(3) + vx + (vx @ vx) / (1.0 + c)[:, None, None]


def crouch_trial(trial: Trial, drop_mm: float, marker_radius: float = 12.5) -> Trial:
    """The trial walked in crouch: pelvis and trunk ``drop_mm`` lower, feet where they were.

    Each leg keeps its thigh and shank lengths (hip, knee and ankle joint centres), so the
    knee flexes further: the knee is placed where the two lengths meet, bent toward the
    pelvis's anterior axis (joint centres as :func:`derive_markers` places them for
    ``marker_radius``); the thigh and tibia markers turn with their segments, the knee marker
    moves with its joint centre, ankle, heel and toe markers stay. Ground contact and the
    gait's timing are the source's. The source's Plug-in Gait knee angle no longer applies
    (``knee_ref`` NaN). ``drop_mm`` = 0 returns the trial.
    """
    if drop_mm == 0.0:
        return trial
    m = {k: v.copy() for k, v in trial.markers.items()}
    pf = pelvis_frame(m)
    down = np.array([0.0, 0.0, drop_mm])
    z = np.array([0.0, 0.0, 1.0])
    fwd = _unit(pf.anterior - (pf.anterior @ z)[:, None] * z)
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        lat = sgn * pf.left
        h0 = pf.hjc[side]
        h1 = h0 - down
        k0 = m[f"{side}_KNE"] - (KNEE_HALF_WIDTH + marker_radius) * lat
        ank = m[f"{side}_ANK"] - (ANKLE_HALF_WIDTH + marker_radius) * lat
        thigh = np.linalg.norm(k0 - h0, axis=1)
        shank = np.linalg.norm(k0 - ank, axis=1)
        d = np.linalg.norm(ank - h1, axis=1)
        u = (ank - h1) / d[:, None]
        a = (thigh**2 - shank**2 + d**2) / (2.0 * d)
        h = np.sqrt(np.maximum(thigh**2 - a**2, 0.0))
        w = _unit(fwd - (fwd * u).sum(axis=1, keepdims=True) * u)
        k1 = h1 + a[:, None] * u + h[:, None] * w
        rt = _rotation_between(k0 - h0, k1 - h1)
        rs = _rotation_between(k0 - ank, k1 - ank)
        m[f"{side}_KNE"] = m[f"{side}_KNE"] + (k1 - k0)
        for name, rot, pivot0, pivot1 in (("THI", rt, h0, h1), ("TIB", rs, ank, ank)):
            key = f"{side}_{name}"
            if key in m:
                m[key] = pivot1 + np.einsum("fij,fj->fi", rot, m[key] - pivot0)
    for name in UPPER_BODY:
        if name in m:
            m[name] = m[name] - down
    return replace(trial, markers=m, knee_ref=np.full_like(trial.knee_ref, np.nan))


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


@dataclass(frozen=True)
class PelvisFrame:
    """Per-frame pelvis axes (F, 3) and the Harrington hip joint centres."""

    origin: np.ndarray
    anterior: np.ndarray
    left: np.ndarray
    up: np.ndarray
    hjc: dict[str, np.ndarray]
    width: float
    depth: float


def pelvis_frame(m: dict[str, np.ndarray]) -> PelvisFrame:
    """Pelvis axes and hip joint centres (Harrington et al. 2007) from ASI and PSI/SACR."""
    origin = 0.5 * (m["L_ASI"] + m["R_ASI"])
    back = 0.5 * (m["L_PSI"] + m["R_PSI"]) if "L_PSI" in m else m["SACR"]
    left = _unit(m["L_ASI"] - m["R_ASI"])
    ant = origin - back
    ant = _unit(ant - (ant * left).sum(axis=1, keepdims=True) * left)
    up = np.cross(ant, left)
    pw = float(np.nanmedian(np.linalg.norm(m["L_ASI"] - m["R_ASI"], axis=1)))
    pd = float(np.nanmedian(np.linalg.norm(origin - back, axis=1)))
    hjc = {}
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        hjc[side] = (
            origin
            + (-0.24 * pd - 9.9) * ant
            + (-0.30 * pw - 10.9) * up
            + sgn * (0.33 * pw + 7.3) * left
        )
    return PelvisFrame(origin, ant, left, up, hjc, pw, pd)


def derive_markers(trial: Trial, marker_radius: float) -> dict[str, np.ndarray]:
    """All 20 markers (plus SACR, C7 and joint centres as ``*_HJC``...) for every frame.

    Returns name -> (F, 3). See the module docstring for the rules.
    """
    m = dict(trial.markers)
    if "L_PSI" not in m or "R_PSI" not in m:
        pf0 = pelvis_frame({k: m[k] for k in ("L_ASI", "R_ASI", "SACR")})
        for side, sgn in (("L", 1.0), ("R", -1.0)):
            m[f"{side}_PSI"] = m["SACR"] + sgn * 0.18 * pf0.width * pf0.left
    if "SACR" not in m:
        m["SACR"] = 0.5 * (m["L_PSI"] + m["R_PSI"])
    pf = pelvis_frame(m)
    stature = float(np.nanmedian(m["L_ASI"][:, 2] + m["R_ASI"][:, 2]) / 2 / 0.55)
    for side, sgn in (("L", 1.0), ("R", -1.0)):
        lat = sgn * pf.left  # outward for this side
        # Heel from the foot axis when the source has none: the median heel position in
        # the ankle-toe frame over the 48 feet of ../shared/gaitdata that carry heels.
        if f"{side}_HEE" not in m:
            ank, toe = m[f"{side}_ANK"], m[f"{side}_TOE"]
            ax = toe - ank
            length = np.linalg.norm(ax, axis=1, keepdims=True)
            fwd = _unit(ax)
            out = _unit(lat - (lat * fwd).sum(axis=1, keepdims=True) * fwd)
            up = sgn * np.cross(fwd, out)
            m[f"{side}_HEE"] = ank - 0.27 * length * fwd - 43.0 * up - 48.0 * out
        hjc = pf.hjc[side]
        # Joint centres medial of the lateral markers by half the joint width plus the
        # marker radius, as in Plug-in Gait (knee width 100 mm, ankle width 70 mm).
        kjc = m[f"{side}_KNE"] - (KNEE_HALF_WIDTH + marker_radius) * lat
        thigh_ax = _unit(kjc - hjc)
        m[f"{side}_HJC"] = hjc
        m[f"{side}_KJC"] = kjc
        m[f"{side}_AJC"] = m[f"{side}_ANK"] - (ANKLE_HALF_WIDTH + marker_radius) * lat
        m[f"{side}_HIP"] = hjc + (85.0 + marker_radius) * lat + 15.0 * thigh_ax
        if f"{side}_SHO" not in m:
            if "C7" in m and np.isfinite(m["C7"]).all():
                m[f"{side}_SHO"] = m["C7"] + 0.13 * stature * lat - 0.02 * stature * pf.up
            else:
                centre = 0.25 * (m["L_ASI"] + m["R_ASI"] + m["L_PSI"] + m["R_PSI"])
                m[f"{side}_SHO"] = (
                    centre + 0.27 * stature * np.array([0, 0, 1.0]) + 0.13 * stature * lat
                )
    if "C7" not in m or not np.isfinite(m["C7"]).all():
        m["C7"] = 0.5 * (m["L_SHO"] + m["R_SHO"]) + 0.02 * stature * pf.up - 40.0 * pf.anterior
    m["_stature"] = np.full((len(trial.t), 3), stature)
    m["_pelvis_left"] = pf.left
    m["_pelvis_ant"] = pf.anterior
    return m


def _thigh_angle(hjc: np.ndarray, kjc: np.ndarray, fwd: np.ndarray) -> np.ndarray:
    """Sagittal thigh angle (rad), positive when the knee is ahead of the hip."""
    v = kjc - hjc
    return np.arctan2((v * fwd).sum(axis=1), -v[:, 2])


@dataclass(frozen=True)
class Body:
    """A posed body for every source frame, standard frame, mm.

    Attributes
    ----------
    t : (F,) s.
    markers : (F, 20, 3) marker centres (MARKER_NAMES order).
    cap_a, cap_b : (F, S, 3) capsule end points (SEGMENT_NAMES order).
    radius : (S,) capsule radii.
    material : (S,) str, surface material per capsule ("skin", "shirt", "shorts").
    stature : estimated stature H in mm (ASIS height / 0.55).
    normal : (F, 20, 3) unit outward skin normal under each marker.

    The capsules are the 20 segments of :data:`SEGMENTS` followed by one skin patch per
    marker (MARKER_NAMES order), so S = 40.
    """

    t: np.ndarray
    markers: np.ndarray
    cap_a: np.ndarray
    cap_b: np.ndarray
    radius: np.ndarray
    material: np.ndarray
    stature: float
    normal: np.ndarray | None = None

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Markers (K, 20, 3) and capsule ends (K, S, 3) x2 at times t (K,), linear."""
        t = np.clip(np.asarray(t, dtype=np.float64), self.t[0], self.t[-1])
        if len(self.t) == 1:
            k = len(t)
            return (
                np.repeat(self.markers, k, 0),
                np.repeat(self.cap_a, k, 0),
                np.repeat(self.cap_b, k, 0),
            )
        i = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 2)
        w = ((t - self.t[i]) / (self.t[i + 1] - self.t[i]))[:, None, None]

        def lerp(x: np.ndarray) -> np.ndarray:
            return x[i] * (1 - w) + x[i + 1] * w

        return lerp(self.markers), lerp(self.cap_a), lerp(self.cap_b)


def _segment_ends(
    m: dict[str, np.ndarray], swing_gain: float, static: bool, marker_radius: float
) -> dict:
    """Capsule end points (F, 3) per segment, with swinging arms."""
    left, ant = m["_pelvis_left"], m["_pelvis_ant"]
    stature = float(m["_stature"][0, 0])
    z = np.array([0.0, 0.0, 1.0])
    fwd = _unit(ant - (ant @ z)[:, None] * z)
    ends: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    hjc_mid = 0.5 * (m["L_HJC"] + m["R_HJC"])
    psi_mid = 0.5 * (m["L_PSI"] + m["R_PSI"])
    sho_mid = 0.5 * (m["L_SHO"] + m["R_SHO"])
    ends["pelvis"] = (m["L_HJC"] + 10 * left, m["R_HJC"] - 10 * left)
    sac = psi_mid - 75.0 * fwd - 15.0 * z
    ends["sacrum"] = (sac + 35 * left, sac - 35 * left)
    trunk_lo = hjc_mid + 170.0 * z - 15.0 * fwd
    trunk_hi = sho_mid - 70.0 * z - 20.0 * fwd
    ends["trunk"] = (trunk_lo, trunk_hi)
    sjc = {s: m[f"{s}_SHO"] - 55.0 * z for s in SIDES}
    ends["shoulders"] = (sjc["L"] - 40 * left, sjc["R"] + 40 * left)
    neck_lo = sho_mid - 20.0 * fwd
    head_c = sho_mid + 0.13 * stature * z + 15.0 * fwd
    ends["neck"] = (neck_lo, head_c - 60.0 * z)
    ends["head"] = (head_c - 20.0 * z, head_c + 20.0 * z)
    for s in SIDES:
        # Thigh and shank taper: two capsules each (proximal thick, distal thin).
        hjc, kjc, ajc = m[f"{s}_HJC"], m[f"{s}_KJC"], m[f"{s}_AJC"]
        ends[f"{s}_thigh"] = (hjc, hjc + 0.6 * (kjc - hjc))
        ends[f"{s}_thigh_lo"] = (hjc + 0.45 * (kjc - hjc), kjc)
        ends[f"{s}_shank"] = (kjc, kjc + 0.5 * (ajc - kjc))
        ends[f"{s}_shank_lo"] = (kjc + 0.4 * (ajc - kjc), ajc)
        hee, toe = m[f"{s}_HEE"], m[f"{s}_TOE"]
        ax = _unit(toe - hee)
        up = _unit(np.cross(ax, left))  # foot's dorsal direction
        inset = 26.0 + marker_radius + 2.0
        ends[f"{s}_foot"] = (hee + inset * ax, toe - inset * up - 10.0 * ax)
    # Arms: pendulums in the sagittal plane driven by the contralateral thigh, so the
    # left arm swings forward with the right leg (counter to the legs).
    up_len, fore_len = 0.186 * stature, 0.146 * stature + 0.08 * stature
    for s, other, sgn in (("L", "R", 1.0), ("R", "L", -1.0)):
        lat = sgn * left
        if static:
            # Arms folded across the chest so that every pelvis and thigh marker is visible
            # in the static pose.
            shoulder_ang = np.full(len(fwd), np.radians(40.0))
            elbow = np.full(len(fwd), np.radians(100.0))
            abduct = np.radians(10.0)
        else:
            th = _thigh_angle(m[f"{other}_HJC"], m[f"{other}_KJC"], fwd)
            shoulder_ang = swing_gain * (th - np.median(th))
            elbow = np.radians(15.0) + 0.6 * np.clip(shoulder_ang, 0, None)
            abduct = np.radians(9.0)
        zz = np.broadcast_to(z, fwd.shape)
        upper = _unit(
            np.sin(shoulder_ang)[:, None] * fwd
            - (np.cos(shoulder_ang) * np.cos(abduct))[:, None] * zz
            + np.sin(abduct) * lat
        )
        elbow_p = sjc[s] + up_len * upper
        fa = shoulder_ang + elbow
        fore_dir = _unit(np.sin(fa)[:, None] * fwd - np.cos(fa)[:, None] * zz + 0.05 * lat)
        if static:
            # Forearm towards the body midline, across the chest.
            fore_dir = _unit(0.45 * fwd - 0.85 * lat + 0.25 * zz)
        ends[f"{s}_upperarm"] = (sjc[s], elbow_p)
        ends[f"{s}_forearm"] = (elbow_p, elbow_p + fore_len * fore_dir)
    return ends


def _dist_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (F,) from points p (F, 3) to segments a-b (F, 3)."""
    ab = b - a
    w = np.clip(((p - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-9), 0, 1)
    return np.linalg.norm(p - (a + w[:, None] * ab), axis=1)


def _wands(
    markers: np.ndarray,
    normals: np.ndarray,
    cap_a: np.ndarray,
    cap_b: np.ndarray,
    radii: np.ndarray,
    base_mm: float,
    wand_mm: float,
) -> dict[int, np.ndarray]:
    """The wand markers: marker index -> (F,) distance (mm) of the centre off its limb's
    surface, for THI and TIB markers whose base (``base_mm`` behind the centre) stands
    more than ``wand_mm`` off it in the median frame."""
    out = {}
    for name in MARKER_NAMES:
        side, site = name.split("_")
        if site not in WAND_SITES:
            continue
        i = MARKER_INDEX[name]
        # Off the limb's surface: the nearer of the segment's two tapering capsules.
        stand = np.min(
            [
                _dist_to_segment(markers[:, i], cap_a[:, k], cap_b[:, k]) - radii[k]
                for k in (SEGMENT_INDEX[f"{side}_{seg}"] for seg in WAND_SITES[site])
            ],
            axis=0,
        )
        if float(np.median(stand)) - base_mm > wand_mm:
            out[i] = stand
    return out


def build_body(
    trial: Trial,
    marker_radius: float,
    source_marker_radius: float = 7.0,
    swing_gain: float = 0.7,
    static: bool = False,
    marker_base_mm: float = 2.0,
    patch_mm: float = 70.0,
    wand_mount: str = "skin",
    wand_mm: float = 25.0,
) -> Body:
    """Markers, capsules and radii for every frame of ``trial``.

    A segment's radius is its nominal radius, reduced where needed so that every marker it
    must not swallow stays outside it by the marker radius plus 2 mm (1st percentile over
    the trial). Then each marker gets a skin patch (:func:`skin_patches`) whose surface
    passes ``marker_radius + marker_base_mm`` behind the marker centre along its normal.

    ``wand_mount`` says what carries a thigh or tibia marker whose base stands more than
    ``wand_mm`` off its limb's surface (median over the trial; the source lab put it on a
    wand): ``"patch"`` a skin patch like every marker (a surface floating beside the limb),
    ``"stick"`` a stick (:data:`WAND_RADIUS_MM`) from the sphere into the limb, so that the
    ring around its depth hole is whatever lies behind it, as on a real wand, or ``"skin"``
    none: the marker is taped to the limb, moved in along its normal until its base
    touches the limb's surface (the paper's protocol: every marker on the skin).
    """
    if wand_mount not in WAND_MOUNTS:
        raise ConfigError(f"wand_mount={wand_mount!r} is not one of {', '.join(WAND_MOUNTS)}")
    m = derive_markers(trial, marker_radius)
    ends = _segment_ends(m, swing_gain, static, marker_radius)
    # Push markers outwards by the change of marker radius, along the normal of the closest
    # point on their own segment's axis.
    grow = marker_radius - source_marker_radius
    own = {
        "ASI": "pelvis",
        "PSI": "sacrum",
        "HIP": "pelvis",
        "SHO": "shoulders",
        "THI": "thigh",
        "KNE": "thigh_lo",
        "TIB": "shank",
        "ANK": "shank_lo",
        "HEE": "foot",
        "TOE": "foot",
    }
    markers = np.empty((len(trial.t), len(MARKER_NAMES), 3))
    normals = np.empty_like(markers)
    axes = np.empty_like(markers)
    for name in MARKER_NAMES:
        side, site = name.split("_")
        seg = own[site] if site in ("ASI", "PSI", "HIP", "SHO") else f"{side}_{own[site]}"
        a, b = ends[seg]
        p = m[name]
        ab = b - a
        w = ((p - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-9)
        if site not in ("THI", "KNE", "TIB", "ANK"):
            # Markers beyond a segment's end (trochanter, acromion, heel, toe, ASIS) point
            # away from that end; limb markers point straight out of the limb.
            w = np.clip(w, 0, 1)
        normal = _unit(p - (a + w[:, None] * ab))
        if site in ("HEE", "TOE"):
            # The heel faces backwards and the toe marker up-forwards in the sagittal plane;
            # the heel-toe line's medial slant (the heel rule puts HEE 48 mm medial) is
            # not the skin's orientation.
            lat = m["_pelvis_left"]
            normal = _unit(normal - (normal * lat).sum(axis=1, keepdims=True) * lat)
        markers[:, MARKER_INDEX[name]] = p + (0.0 if site == "HIP" else grow) * normal
        normals[:, MARKER_INDEX[name]] = normal
        axes[:, MARKER_INDEX[name]] = _unit(ab)
    radii = np.empty(len(SEGMENTS))
    for k, (name, nominal, _material, keep_out) in enumerate(SEGMENTS):
        a, b = ends[name]
        r = nominal
        for mk in keep_out:
            d = _dist_to_segment(markers[:, MARKER_INDEX[mk]], a, b)
            r = min(r, float(np.percentile(d, 1)) - marker_radius - 2.0)
        radii[k] = max(r, 25.0)
    cap_a = np.stack([ends[n][0] for n in SEGMENT_NAMES], axis=1)
    cap_b = np.stack([ends[n][1] for n in SEGMENT_NAMES], axis=1)
    # A patch is curved like its segment (a real thigh or knee is flatter than a 35 mm
    # cylinder), within [patch_mm / 2, 60 mm].
    nominal = {s[0]: s[1] for s in SEGMENTS}
    rho0 = np.empty(len(MARKER_NAMES))
    for name in MARKER_NAMES:
        side, site = name.split("_")
        seg = own[site] if site in ("ASI", "PSI", "HIP", "SHO") else f"{side}_{own[site]}"
        rho0[MARKER_INDEX[name]] = float(np.clip(nominal[seg], 0.5 * patch_mm, 60.0))
    base = marker_radius + marker_base_mm
    wands = (
        {}
        if wand_mount == "patch"
        else _wands(markers, normals, cap_a, cap_b, radii, base, wand_mm)
    )
    if wand_mount == "skin":
        # Taped to the skin instead: the marker moves in along its normal onto the limb,
        # and gets its patch there like any other.
        for i, stand in wands.items():
            markers[:, i] -= (stand - base)[:, None] * normals[:, i]
    pa, pb, pr = skin_patches(
        markers, normals, axes, marker_radius, marker_base_mm, patch_mm, rho0, m["_pelvis_left"]
    )
    if wand_mount == "stick":
        for i, stand in wands.items():
            # The stick reaches 5 mm into the limb so that no gap opens as it moves.
            pa[:, i] = markers[:, i] - marker_radius * normals[:, i]
            pb[:, i] = markers[:, i] - (stand + 5.0)[:, None] * normals[:, i]
            pr[i] = WAND_RADIUS_MM
    cap_a = np.concatenate([cap_a, pa], axis=1)
    cap_b = np.concatenate([cap_b, pb], axis=1)
    radii = np.r_[radii, pr]
    # A marker sphere cannot sink into the floor: lift the subject when the source's floor
    # level (lab calibration, smaller markers) would put one below it.
    lift = max(0.0, marker_radius + 1.0 - float(np.nanmin(markers[..., 2])))
    if lift > 0:
        markers[..., 2] += lift
        cap_a[..., 2] += lift
        cap_b[..., 2] += lift
    seg_mat = {s[0]: s[2] for s in SEGMENTS}
    patch_mat = []
    for name in MARKER_NAMES:
        side, site = name.split("_")
        seg = own[site] if site in ("ASI", "PSI", "HIP", "SHO") else f"{side}_{own[site]}"
        patch_mat.append(seg_mat[seg])
    material = np.array([s[2] for s in SEGMENTS] + patch_mat)
    stature = float(m["_stature"][0, 0])
    return Body(trial.t.copy(), markers, cap_a, cap_b, radii, material, stature, normals)


def skin_patches(
    markers: np.ndarray,
    normals: np.ndarray,
    axes: np.ndarray,
    marker_radius: float,
    base_mm: float,
    patch_mm: float,
    rho0: np.ndarray | None = None,
    lateral: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One capsule of skin under every marker: the surface the marker is taped to.

    The capsule's axis runs along the segment (its component across the marker normal),
    with half-length 0.3 ``patch_mm``, at depth ``rho`` below the marker's base, where
    ``rho`` is its radius: its surface touches the plane of the base at the base point
    ``c - (marker_radius + base_mm) n``, curved like a limb across the segment and flat
    along it. ``rho`` is ``rho0`` (default ``patch_mm / 2``), reduced where needed (1st
    percentile over the frames) so that no other marker sinks into the patch and, for
    markers of the same side of the body, none is covered by it in a side view (distances
    measured in the sagittal plane when ``lateral`` is given).

    Parameters
    ----------
    markers, normals, axes : (F, N, 3) marker centres (mm), unit outward normals, unit
        directions of the marker's segment axis.
    rho0 : (N,) wanted patch radii (curvature across the segment), mm.
    lateral : (F, 3) unit lateral (pelvis left) axis, or None.

    Returns
    -------
    a, b : (F, N, 3) capsule end points; rho : (N,) radii, mm.
    """
    n_m = markers.shape[1]
    base = markers - (marker_radius + base_mm) * normals
    tang = axes - (axes * normals).sum(-1, keepdims=True) * normals  # |tang| = sin(angle)
    half = 0.3 * patch_mm
    rho = np.full(n_m, 0.5 * patch_mm) if rho0 is None else np.asarray(rho0, float).copy()
    for i in range(n_m):
        for j in range(n_m):
            if i == j:
                continue
            # Another marker's centre must stay rho + r + 2 mm from this patch's axis; the
            # axis moves with rho, so shrink by a few fixed-point steps.
            pj = markers[:, j]
            flat = lateral is not None and MARKER_NAMES[i][0] == MARKER_NAMES[j][0]
            for _ in range(4):
                c0 = base[:, i] - rho[i] * normals[:, i]
                a, b = c0 - half * tang[:, i], c0 + half * tang[:, i]
                if flat:
                    # Same side: clearance in the sagittal plane, so the patch cannot
                    # cover the marker in a side view.
                    a, b, q = (
                        x - (x * lateral).sum(axis=1, keepdims=True) * lateral for x in (a, b, pj)
                    )
                else:
                    q = pj
                d = _dist_to_segment(q, a, b)
                rho[i] = max(8.0, min(rho[i], float(np.percentile(d, 1)) - marker_radius - 2.0))
    centre = base - rho[None, :, None] * normals
    a = centre - half * tang
    b = centre + half * tang
    return a, b, rho


def knee_flexion(markers: np.ndarray) -> np.ndarray:
    """Knee flexion (..., 2) deg (L, R) = 180 - angle HIP-KNE-ANK from markers (..., 20, 3)."""
    out = []
    for s in SIDES:
        hip = markers[..., MARKER_INDEX[f"{s}_HIP"], :]
        kne = markers[..., MARKER_INDEX[f"{s}_KNE"], :]
        ank = markers[..., MARKER_INDEX[f"{s}_ANK"], :]
        u, v = hip - kne, ank - kne
        c = (u * v).sum(-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
        out.append(180.0 - np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    return np.stack(out, axis=-1)
