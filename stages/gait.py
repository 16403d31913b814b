"""Stage ``gait``: per-trial gait analysis (Alg. 6 and the kinematics of section 5).

Input: ``labelled`` (the 20 named markers of a frame) joined per frame, with the
``calibration`` record (floor plane, walking start and end) and the subject ``model`` as
side inputs. Outputs: one ``gait`` message per frame (knee flexion and heel/toe heights of
that frame, plus the gait events confirmed since the previous message), and a ``summary``
(``TrialSummary``) whose ``results`` is the trial results document of
``../shared/spec/results.md``: one with ``scope == "pass"`` as each walking pass ends, and
one with ``scope == "trial"`` at the end of the trial (``header.last``, the start of another
trial, or ``finish``).

Per trial (algorithms.md sections 3.6 and 5, see ``gaitflow.gaitcore``):

0. each heel's runs of labels extended back in time onto the blobs label left unnamed
   (``LabelledMarkers.spare_pixel`` and ``spare_heel``), at most ``heel_extend_frames``
   frames, where one blob alone continues the track (:func:`gaitflow.gaitcore.extend_back`):
   label often names a far heel only once it has landed, and Alg. 6 needs its descent;
1. times from the capture clock (s from the trial's first frame, frame drops stay gaps);
   a heel or toe sample far from its neighbours' median is dropped (``foot_outlier_mm``,
   given for 30 fps and scaled by (30/fps)^2 below: ``gaitcore.outlier_bound``),
   and each marker's depth is smoothed along its viewing ray (``depth_smooth_s``), a depth
   far from its running median taken as a wrong layer (``depth_outlier_mm``; not for heel,
   toe and ankle);
2. every marker gap-filled with cubic Bezier segments (at most ``max_gap_s``), then
   resampled to ``resample_hz`` with Catmull-Rom Bezier segments on the timestamps;
3. heel and toe heights above the calibration's floor plane; positions along the walking
   axis from the start to the end point (``progression="walkway"``) or, per pass, along the
   subject's own line of progression (``"pass"``, :func:`gaitflow.gaitcore.line_of_progression`);
4. the walk split into passes by the direction of progression of the pelvis markers (the
   return pass shows the other side of the body to the camera); a pass whose trunk walks
   out of the image goes on while a foot is still seen (its last stance and toe off,
   ``exit_tail_s``, :func:`gaitflow.gaitcore.extend_to_exit`);
5. per pass and foot, Alg. 6 on the heel and toe heights, events refined inside the flat
   ranges (``refine``), then step and stride length, stance and swing, the eight phases;
6. knee flexion = 180 deg - angle HIP-KNE-ANK from the gap-filled, resampled 3D markers;
   before filling, a frame's hip, knee or ankle sample that makes the thigh or the shank
   (or both: the knee) depart from its median length (``segment_tol``) is dropped
   (:func:`gaitflow.gaitcore.chain_outliers`); then an ankle gap is filled from the knee
   and tibia markers in its frames where they are seen, the ankle held in the shank's frame
   (``segment_fill``, :func:`gaitflow.gaitcore.fill_from_segment`; the Bezier fills the
   rest); after filling, the knee angle is unknown where a length still departs.

Array conventions: marker axis follows ``gaitflow.markers.MARKER_NAMES``; camera mm; NaN =
missing; time axis 0; seconds; degrees. Ground truth is never read here.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from gaitflow.schemas import GaitFrame, Header, LabelledMarkers, Message, TrialSummary
from gaitflow.stages.base import Inputs, StageSpec

from gaitflow import gaitcore as gc
from gaitflow.errors import StageError
from gaitflow.markers import MARKER_INDEX
from gaitflow.params import Param, ParamSet
from gaitflow.results import build_results, empty_results, frame_record, frame_records

PARAMS = ParamSet(
    "gait",
    (
        Param("gamma", float, 0.05, "normalised", "Alg. 6 level resolution (Table I)", 0.005, 0.5),
        Param(
            "xi",
            float,
            0.03,
            "ratio",
            "Alg. 6 left clip rate (Table I 0.03; the text says 0.33)",
            0.001,
            1.0,
        ),
        Param(
            "phi",
            float,
            0.03,
            "ratio",
            "Alg. 6 right clip rate (Table I 0.03; the text says 0.33)",
            0.001,
            1.0,
        ),
        Param("tau", int, 3, "samples", "Alg. 6 minimum range length, resampled samples", 1, 100),
        Param(
            "max_born", float, 0.25, "normalised", "highest level a floor contact may start", 0.05
        ),
        Param("max_gap_s", float, 0.3, "s", "longest gap filled by a cubic Bezier", 0.0, 2.0),
        Param(
            "segment_fill",
            bool,
            True,
            "",
            "an ankle gap is filled first from the knee and tibia markers (the shank's frame)"
            " in its frames where they are seen, the Bezier only where they are not",
        ),
        Param(
            "event_gap_s",
            float,
            0.15,
            "s",
            "a heel strike or toe off inside a gap of its marker longer than this is unknown,"
            " not guessed from the filled curve (0=off)",
            0.0,
            2.0,
        ),
        Param(
            "outlier_mm",
            float,
            25.0,
            "mm",
            "knee markers: one this far from the median of its 4 neighbours is dropped, at "
            "30 fps; x (30/fps)^2 below (0=off)",
            0.0,
        ),
        Param(
            "foot_outlier_mm",
            float,
            100.0,
            "mm",
            "heel and toe markers: one this far from the median of its 4 neighbours is dropped, "
            "at 30 fps; x (30/fps)^2 below (0=off)",
            0.0,
        ),
        Param(
            "segment_tol",
            float,
            0.15,
            "ratio",
            "a thigh or shank length departing this much from its median drops the wrong "
            "marker's sample before gap filling, and the knee angle where it stays",
            0.0,
        ),
        Param(
            "depth_smooth_s",
            float,
            0.3,
            "s",
            "smooth each marker's depth along its ray over this window (0 = off)",
            0.0,
            2.0,
        ),
        Param(
            "depth_outlier_mm",
            float,
            40.0,
            "mm",
            "a depth this far from the marker's running median is a wrong layer: it takes "
            "its neighbours' smoothed depth (heel, toe and ankle excepted; 0 = off)",
            0.0,
        ),
        Param(
            "depth_outlier_s",
            float,
            1.0,
            "s",
            "window of that running median",
            0.15,
            10.0,
        ),
        Param("resample_hz", float, 100.0, "Hz", "resampling rate (the paper: 100)", 10.0, 1000.0),
        Param(
            "refine",
            str,
            "velocity",
            "",
            "event refinement inside Alg. 6 ranges",
            choices=("velocity", "none"),
        ),
        Param("hs_speed_frac", float, 0.1, "ratio", "heel strike: heel speed / swing speed", 0.0),
        Param("to_speed_frac", float, 0.3, "ratio", "toe off: toe speed / swing speed", 0.0),
        Param(
            "swing_floor",
            float,
            1.8,
            "ratio",
            "the swing speed of the event thresholds is at least this times the pass's"
            " walking speed, where the labels leave most of a swing unseen (0 = off)",
            0.0,
        ),
        Param(
            "to_late_s",
            float,
            0.1,
            "s",
            "a toe already that fast for longer than this when its flat range locked had left"
            " the floor: the toe off is where its speed-up began (0 = always at the lock)",
            0.0,
            1.0,
        ),
        Param(
            "progression",
            str,
            "walkway",
            "",
            "lengths and speeds measured along the calibration's walkway axis, or along each "
            "pass's own line of progression (least-squares velocity of the trunk markers)",
            choices=("walkway", "pass"),
        ),
        Param(
            "knee_plane",
            str,
            "3d",
            "",
            "knee flexion from the 3D angle HIP-KNE-ANK (the paper), or from the segments "
            "projected on the sagittal plane (floor normal and walkway axis; departure)",
            choices=("3d", "sagittal"),
        ),
        Param(
            "min_step_mm",
            float,
            60.0,
            "mm",
            "a stance this close to the other foot's overlapping stance is a mislabel (0 = off)",
            0.0,
        ),
        Param(
            "heel_extend_frames",
            int,
            10,
            "frames",
            "a heel's run of labels is extended back onto the blobs label left unnamed for at"
            " most this many frames, so its descent to a heel strike is seen (0 = off)",
            0,
            60,
        ),
        Param(
            "extend_gate_px",
            float,
            6.0,
            "px",
            "heel extension: the blob lies within this (plus half the image speed) of the"
            " heel's predicted pixel",
            0.5,
            50.0,
        ),
        Param(
            "extend_sep_px",
            float,
            8.0,
            "px",
            "heel extension: no other blob or marker prediction within this beyond its distance",
            0.0,
            50.0,
        ),
        Param(
            "extend_depth_mm",
            float,
            60.0,
            "mm",
            "heel extension: the blob's depth lies within this of the heel's last depth",
            1.0,
            500.0,
        ),
        Param("min_pass_s", float, 0.6, "s", "shortest walking pass", 0.1),
        Param("min_speed_mm_s", float, 150.0, "mm/s", "slower than this is not walking", 1.0),
        Param(
            "exit_tail_s",
            float,
            0.25,
            "s",
            "a pass whose trunk leaves the image at most this long after the pass ends goes on"
            " while a foot is seen (its last toe off; 0 = off)",
            0.0,
            1.0,
        ),
        Param("live_every", int, 15, "frames", "live event search period (0 = at the end)", 0),
        Param("live_delay_s", float, 0.5, "s", "live events older than this are confirmed", 0.0),
        Param("live_window_s", float, 20.0, "s", "live event search looks this far back", 2.0),
        Param(
            "max_frames",
            int,
            54000,
            "frames",
            "a trial this long is closed and a new one begun (30 min at 30 fps)",
            100,
        ),
        Param("session", str, "", "", "session name written into the results"),
    ),
)

NOMINAL_PERIOD_S = 1 / 30
CONTACT_PARAMS = (
    "gamma",
    "xi",
    "phi",
    "tau",
    "max_born",
    "refine",
    "hs_speed_frac",
    "to_speed_frac",
    "to_late_s",
    "swing_floor",
)
BODY = [f"{s}_{m}" for s in "LR" for m in ("SHO", "ASI", "PSI", "HIP", "THI")]
# the line of progression: markers that move with the body, not with a leg or an arm
TRUNK = [MARKER_INDEX[f"{s}_{m}"] for s in "LR" for m in ("SHO", "ASI", "PSI", "HIP")]
KNEE_MARKERS = [MARKER_INDEX[f"{s}_{m}"] for s in "LR" for m in ("HIP", "KNE", "ANK")]
FOOT_MARKERS = [MARKER_INDEX[f"{s}_{m}"] for s in "LR" for m in ("HEE", "TOE")]
ANKLE_MARKERS = [MARKER_INDEX[f"{s}_ANK"] for s in "LR"]
# the wrong-layer test on depth (``depth_outlier_mm``) leaves heel, toe and ankle alone:
# heel and toe depths scatter on the shoe's silhouette, and replacing them moved gait
# events (two more heel strikes of 55 missed on the bundled walks) without a gain; the
# ankle swings across under the body and is often unseen, so its running median is thin
# and true depths were flagged (a 4.3 deg knee error on a walk of the unit2 variant)
LAYER_CHECKED = [k for k in range(20) if k not in FOOT_MARKERS and k not in ANKLE_MARKERS]
_HIP, _KNE, _ANK, _HEE, _TOE = (
    [MARKER_INDEX[f"{s}_{m}"] for s in "LR"] for m in ("HIP", "KNE", "ANK", "HEE", "TOE")
)


@dataclass(frozen=True)
class FrameRec:
    """One labelled frame as the stage keeps it."""

    header: Header
    position: np.ndarray  # (20, 3) camera mm
    pixel: np.ndarray  # (20, 2) px
    direction: int
    near_side: str
    # its entry of a results document's ``frames``, made when it came (spreads the cost of
    # a document over the frames), for the time ``record_t`` (checked when used)
    record: Mapping[str, Any] | None = None
    record_t: float = float("nan")
    # the blobs label left unnamed: (M, 2) px and (M, 3) mm where a heel would be published
    spare_pixel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    spare_heel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


# What a clinician does about a calibration that is not Done (results' warnings).
CHECK_SETUP = "check the camera set-up (gaitflow setup --session)"


@dataclass(frozen=True)
class GaitState:
    """The open trial: its frames so far and what was already published."""

    params: Mapping[str, Any]
    frames: tuple[FrameRec, ...] = ()
    plane: np.ndarray | None = None
    start: np.ndarray | None = None
    end: np.ndarray | None = None
    emitted: tuple[tuple[str, str, float], ...] = ()
    summarised_until: float = float("-inf")  # end of the last pass given its own summary
    # the sagittal plane's normal for the live knee angle (``knee_plane`` = sagittal)
    lateral: np.ndarray | None = None
    # the events the live search (``after``) found, published with the next frame's message
    pending: tuple[tuple[str, str, float], ...] = ()
    # results of the recent analyses by a digest of their exact inputs (see ``Memo``)
    memo: tuple[Mapping[bytes, Any], ...] = ()
    # the resampled markers of the last analysis of the whole trial (``analyse(series=)``)
    series: Mapping[str, gc.Resampled] | None = None
    # a calibration record that is not Done, its status and message: warned in every result
    calibration_note: str = ""


@dataclass(frozen=True)
class TrialAnalysis:
    """Everything computed for one trial (or the part of it seen so far)."""

    frame_index: np.ndarray  # (F,)
    t: np.ndarray  # (F,) s
    tq: np.ndarray  # (Q,) s, resampled
    knee: dict[str, np.ndarray]  # side -> (Q,) deg
    passes: list[dict[str, Any]]  # direction, start_s, end_s, near_side
    contacts: list[dict[str, list[gc.Contact]]]  # per pass
    events: list[dict[str, Any]]
    spatiotemporal: dict[str, Any]
    pass_st: list[dict[str, Any]]
    phases: dict[str, list[dict[str, float]]]
    fps: float
    warnings: list[str]
    memo: dict[bytes, Any] = field(default_factory=dict)  # what this analysis looked up
    series: dict[str, gc.Resampled] = field(default_factory=dict)  # see ``analyse``


MEMO_ANALYSES = 3  # a state keeps the memo entries of this many recent analyses


class Memo:
    """Results of pure computations keyed by a digest of their exact inputs.

    The live analysis, the summary of a pass ended and the close of the trial repeat much of
    each other's work on the same samples (the same frames at one step; a finished pass seen
    again). A result is reused only when every input array is bit-for-bit the same, so the
    outputs are exactly those of computing again. ``seen`` holds the entries of the recent
    analyses (read only); ``used`` collects what this analysis looked up or made.
    """

    def __init__(self, seen: Sequence[Mapping[bytes, Any]] = ()) -> None:
        self.seen = seen
        self.used: dict[bytes, Any] = {}

    @staticmethod
    def key(*parts: Any) -> bytes:
        h = hashlib.blake2b(digest_size=16)
        for part in parts:
            if isinstance(part, np.ndarray):
                h.update(repr((part.dtype.str, part.shape)).encode())
                h.update(np.ascontiguousarray(part).view(np.uint8))
            else:
                h.update(repr(part).encode())
            h.update(b"|")
        return h.digest()

    def get(self, key: bytes) -> Any:
        for m in (self.used, *self.seen):
            if key in m:
                self.used[key] = m[key]
                return m[key]
        return None


def init(params: dict[str, Any]) -> GaitState:
    return GaitState(params=dict(params))


def _times(frames: Sequence[FrameRec]) -> tuple[np.ndarray, np.ndarray, float]:
    """Frame indices, seconds from the trial's first frame, and the camera rate."""
    idx = np.array([f.header.frame for f in frames], dtype=np.int64)
    ns = np.array([f.header.capture_ns for f in frames], dtype=np.int64)
    if len(frames) >= 2:
        di = np.diff(idx)
        ok = di > 0
        # nanmedian_last: np.median's values (no NaN here) at a fraction of its cost
        period = float(gc.nanmedian_last(np.diff(ns)[ok] / di[ok])) / 1e9 if ok.any() else 1 / 30
    else:
        period = 1 / 30
    if not period > 0:
        period = 1 / 30
    # frame 0 may not have reached us: its time is extrapolated from the frame index
    t0 = ns[0] - idx[0] * period * 1e9 if len(ns) else 0
    return idx, (ns - t0) / 1e9, 1.0 / period


def _axis(plane: np.ndarray, start: np.ndarray | None, end: np.ndarray | None, pos: np.ndarray):
    """Walking axis and origin: start -> end, else the main horizontal direction of travel."""
    if start is not None and end is not None and np.all(np.isfinite([*start, *end])):
        try:
            return gc.walking_axis(start, end, plane), np.asarray(start, dtype=float)
        except ValueError:
            pass
    body = np.nanmean(pos[:, [MARKER_INDEX[n] for n in BODY]], axis=1)
    body = body[np.all(np.isfinite(body), axis=1)]
    n = plane[:3] / np.linalg.norm(plane[:3])
    if len(body) >= 2:
        d = body - body.mean(axis=0)
        d = d - np.outer(d @ n, n)
        u = np.linalg.svd(d, full_matrices=False)[2][0]
        if u[0] < 0:
            u = -u
        return u, body.mean(axis=0)
    u = np.array([1.0, 0.0, 0.0])
    u = u - (u @ n) * n
    return u / np.linalg.norm(u), np.zeros(3)


def _near_side(frames: Sequence[FrameRec]) -> str:
    """The side facing the camera from geometry, when the labeller did not say: the side
    whose knee and ankle markers are nearer the camera centre (median distance)."""
    dist = {}
    pos = np.stack([f.position for f in frames]) if frames else np.zeros((0, 20, 3))
    for s in "LR":
        idx = [MARKER_INDEX[f"{s}_KNE"], MARKER_INDEX[f"{s}_ANK"]]
        d = np.linalg.norm(pos[:, idx], axis=2).ravel()
        d = d[np.isfinite(d)]
        dist[s] = float(gc.nanmedian_last(d)) if d.size else float("nan")
    if not all(np.isfinite(v) for v in dist.values()):
        return ""
    return "L" if dist["L"] < dist["R"] else "R"


def _nanmedian_rows(x: np.ndarray) -> np.ndarray:
    """Median of each row ignoring NaN; NaN for an all-NaN row (without a warning)."""
    return gc.nanmedian_last(x)


def _body_progression(pq: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Progression of the body (Q,): the pelvis and trunk markers, else any marker seen.

    The legs stay in view longest when the subject walks in or out of the field of view;
    their median still moves with the body over the half-second slope window of
    :func:`gaitflow.gaitcore.split_passes`.
    """
    prog = gc.progression(pq, origin, axis)  # (Q, 20)
    body = _nanmedian_rows(prog[:, [MARKER_INDEX[n] for n in BODY]])
    # rows are independent: the median of all markers only where the body is not seen
    gone = np.flatnonzero(~np.isfinite(body))
    body[gone] = _nanmedian_rows(prog[gone])
    return body


def _fill_resample(
    t: np.ndarray,
    pos: np.ndarray,
    markers: Sequence[int],
    p: Mapping[str, Any],
    prev: gc.Resampled | None,
    keep: bool,
) -> tuple[np.ndarray, gc.Resampled | None]:
    """Step 2: ``markers`` gap-filled and resampled, all at once.

    t : (F,) s; pos : (F, M, 3) mm with M = len(markers). Returns (Q, 20, 3), NaN for the
    markers not asked for and those seen in fewer than two frames, and, with ``keep``, the
    :class:`gaitflow.gaitcore.Resampled` that lets the next analysis of the same growing
    trial compute only what its new frames change (``prev`` is that of the last one).
    """
    res = gc.fill_resample_markers(t, pos, p["max_gap_s"], p["resample_hz"], prev)
    cols = list(markers)
    if cols == list(range(20)):
        pq = res.xq.copy()  # kept in ``res``: the caller may blank markers in its copy
    else:
        pq = np.full((len(res.tq), 20, 3), np.nan)
        pq[:, cols] = res.xq
    few = np.count_nonzero(np.isfinite(pos[:, :, 0]), axis=0) < 2
    pq[:, [k for k, f in zip(cols, few.tolist(), strict=True) if f]] = np.nan
    return pq, (res if keep else None)


def analyse(
    frames: Sequence[FrameRec],
    plane: np.ndarray,
    start: np.ndarray | None,
    end: np.ndarray | None,
    params: Mapping[str, Any],
    live: bool = False,
    memo: Sequence[Mapping[bytes, Any]] = (),
    series: Mapping[str, gc.Resampled] | None = None,
) -> TrialAnalysis:
    """Analyse the frames of one trial (steps 1-6 of the module docstring).

    ``live=True`` skips what live events do not need (knee angles, phases, spatio-temporal
    parameters, the side facing the camera: ``near_side`` is ""). ``memo``: the
    ``memo`` of recent analyses (results reused only for bit-identical inputs). ``series``:
    when given (``{}`` at first), ``frames`` are the whole trial so far and ``series`` the
    resampled markers of its last analyses; every marker is then resampled (live too: the
    next full analysis finds them) and the result kept in ``TrialAnalysis.series``.
    """
    p = params
    cache = Memo(memo)
    keep = series is not None
    prev = series or {}
    idx, t, fps = _times(frames)
    warnings: list[str] = []
    pos = np.stack([f.position for f in frames]) if frames else np.zeros((0, 20, 3))
    if p["heel_extend_frames"] > 0 and len(frames) >= 3:
        _, pos, _ = gc.extend_back(
            idx,
            np.stack([f.pixel for f in frames]),
            pos,
            [f.spare_pixel for f in frames],
            [f.spare_heel for f in frames],
            _HEE,
            np.array([f.direction != 0 for f in frames], dtype=bool),
            p["heel_extend_frames"],
            p["extend_gate_px"],
            p["extend_sep_px"],
            p["extend_depth_mm"],
        )
    # a heel or toe label given for a frame or two to another foot marker (the planted
    # heel of the other foot, say) makes a false contact and a gross step; the bound is
    # far above what a foot's own motion departs from its neighbours' median (heel strike
    # decelerations give a few tens of mm at 30 fps), so real samples stay
    foot_bound = gc.outlier_bound(p["foot_outlier_mm"], fps)
    pos[:, FOOT_MARKERS] = gc.reject_outliers(pos[:, FOOT_MARKERS], foot_bound)
    pos = gc.smooth_depth(
        t, pos, p["depth_smooth_s"], p["depth_outlier_mm"], p["depth_outlier_s"], LAYER_CHECKED
    )
    nq = int(np.floor((t[-1] - t[0]) * p["resample_hz"] + 1e-6)) + 1 if len(t) else 0
    tq = t[0] + np.arange(nq) / p["resample_hz"] if len(t) else np.zeros(0)
    need = list(range(20))
    if live:
        need = [MARKER_INDEX[n] for n in (*BODY, "L_HEE", "R_HEE", "L_TOE", "R_TOE")]
    kept: dict[str, gc.Resampled] = {}
    if keep:
        pq, kept["markers"] = _fill_resample(t, pos, range(20), p, prev.get("markers"), keep)
        # what live events do not use stays missing, as if never computed
        pq[:, [k for k in range(20) if k not in need]] = np.nan
    else:
        pq, _ = _fill_resample(t, pos[:, need], need, p, None, keep)
    if len(pq) != nq:
        raise StageError("gait", f"resampled {len(pq)} samples where {nq} were expected")
    # the walking axis: the passes' progression, the knee's sagittal plane
    axis, origin = _axis(plane, start, end, pos)
    knee = {"L": np.full(nq, np.nan), "R": np.full(nq, np.nan)}
    if live and "knee" in prev:
        kept["knee"] = prev["knee"]  # for the next full analysis, which extends it
    if not live:
        # the knee markers alone go through the outlier filter: a dropped heel sample in a
        # fast swing would cost an event, a dropped knee sample only a filled gap
        kpos = gc.reject_outliers(pos[:, KNEE_MARKERS], gc.outlier_bound(p["outlier_mm"], fps))
        if p["segment_tol"] > 0:
            # a wrong hip, knee or ankle sample is dropped before the gap filler, which
            # would otherwise bend the filled curve through it for the frames around
            # (after filling, only the frames where the length itself departs are caught)
            for leg in (kpos[:, 0:3], kpos[:, 3:6]):
                drop = gc.chain_outliers(leg[:, 0], leg[:, 1], leg[:, 2], p["segment_tol"])
                for k, bad in enumerate(drop):
                    leg[bad, k] = np.nan
        lateral = gc.lateral_axis(plane, axis)  # the sagittal plane's normal
        if p["segment_fill"]:
            for s, leg in zip("LR", (kpos[:, 0:3], kpos[:, 3:6]), strict=True):
                tib = pos[:, MARKER_INDEX[f"{s}_TIB"]].copy()
                if p["segment_tol"] > 0:
                    # a tibia label off the shank (its distance to the knee departs from
                    # the median) would turn the filled ankle with it
                    tib[gc.segment_outliers(leg[:, 1], tib, p["segment_tol"])] = np.nan
                leg[:, 2] = gc.fill_from_segment(
                    t, leg[:, 2], leg[:, 1], tib, lateral, p["max_gap_s"]
                )
        pk, knee_series = _fill_resample(t, kpos, KNEE_MARKERS, p, prev.get("knee"), keep)
        if knee_series is not None:
            kept["knee"] = knee_series
        # knee_plane "sagittal": seen from the side, a marker's position across the walkway
        # comes from its depth, the noisiest coordinate (tens of mm on a silhouette or with
        # a limb in front); the sagittal angle uses only the two coordinates the image
        # gives. In a straight walk the knee moves in about that plane, so the two angles
        # differ by a degree or two.
        lat = lateral if p["knee_plane"] == "sagittal" else None
        for s in "LR":
            hip, kne, ank = (pk[:, MARKER_INDEX[f"{s}_{m}"]] for m in ("HIP", "KNE", "ANK"))
            knee[s] = gc.knee_flexion(hip, kne, ank, lat)
            if p["segment_tol"] > 0:
                # a wrong label that survived makes a thigh or shank change length
                bad = gc.segment_outliers(hip, kne, p["segment_tol"])
                bad |= gc.segment_outliers(kne, ank, p["segment_tol"])
                knee[s][bad] = np.nan
    passes: list[dict[str, Any]] = []
    contacts_all: list[dict[str, list[gc.Contact]]] = []
    pass_st: list[dict[str, Any]] = []
    phases: dict[str, list[dict[str, float]]] = {"L": [], "R": []}
    events: list[dict[str, Any]] = []
    if nq >= 3:
        body = _body_progression(pq, origin, axis)
        found = gc.split_passes(tq, body, p["min_speed_mm_s"], min_duration_s=p["min_pass_s"])
        if p["exit_tail_s"] > 0:
            found = gc.extend_to_exit(
                tq,
                found,
                np.isfinite(pq[:, TRUNK, 0]).any(axis=1),
                np.isfinite(pq[:, FOOT_MARKERS, 0]).any(axis=1),
                p["exit_tail_s"],
            )
        for ps in found:
            sl = slice(ps.start, ps.stop)
            u = float(ps.direction) * axis  # signed: progression grows along the walk
            if p["progression"] == "pass":
                u = gc.line_of_progression(tq[sl], pq[sl][:, TRUNK], plane, u)
            contacts: dict[str, list[gc.Contact]] = {}
            walk_speed = gc.walking_speed(tq[sl], body[sl])
            prog_heel: dict[str, np.ndarray] = {}
            tilt: dict[str, np.ndarray] = {}
            for s in "LR":
                heel = pq[sl, MARKER_INDEX[f"{s}_HEE"]]
                toe = pq[sl, MARKER_INDEX[f"{s}_TOE"]]
                prog_heel[s] = gc.progression(heel, origin, u)
                args = (
                    tq[sl],
                    gc.plane_height(heel, plane),
                    gc.plane_height(toe, plane),
                    prog_heel[s],
                    gc.progression(toe, origin, u),
                    s,
                )
                kw = {k: p[k] for k in CONTACT_PARAMS} | {"walk_speed": walk_speed}
                key = Memo.key("foot_contacts", *args, sorted(kw.items()))
                found_c = cache.get(key)
                if found_c is None:
                    found_c = cache.used[key] = tuple(gc.foot_contacts(*args, **kw))
                contacts[s] = gc.drop_events_in_gaps(
                    found_c,
                    t,
                    np.isfinite(pos[:, MARKER_INDEX[f"{s}_HEE"]]).all(axis=1),
                    np.isfinite(pos[:, MARKER_INDEX[f"{s}_TOE"]]).all(axis=1),
                    p["event_gap_s"],
                )
                if not live:
                    tilt[s] = gc.progression(
                        pq[sl, MARKER_INDEX[f"{s}_KNE"]], origin, u
                    ) - gc.progression(pq[sl, MARKER_INDEX[f"{s}_ANK"]], origin, u)
            contacts = gc.drop_shared_footprints(contacts, p["min_step_mm"], tq[sl], prog_heel)
            near = ""  # live events do not need it
            if not live:
                inside = np.flatnonzero((tq[ps.start] <= t) & (t <= tq[ps.stop - 1])).tolist()
                in_pass = [frames[i] for i in inside]
                sides = [f.near_side for f in in_pass if f.near_side]
                near = max(set(sides), key=sides.count) if sides else _near_side(in_pass)
            passes.append(
                {
                    "direction": int(ps.direction),
                    "start_s": round(float(tq[ps.start]), 4),
                    "end_s": round(float(tq[ps.stop - 1]), 4),
                    "near_side": near,
                }
            )
            contacts_all.append(contacts)
            events.extend(gc.events_from_contacts([c for s in "LR" for c in contacts[s]]))
            if not live:
                pass_st.append(gc.spatiotemporal(contacts, 1.0, tq[sl], prog_heel))
                ph = gc.gait_phases(contacts, tq[sl], prog_heel, tilt)
                for s in "LR":
                    phases[s].extend(ph[s])
    events.sort(key=lambda e: (e["time_s"], e["side"], e["kind"]))
    if not passes and not live:
        seen = np.isfinite(pos[:, :, 0]).any(axis=1).sum() if len(pos) else 0
        warnings.append(
            "no walking pass found: the subject was never seen"
            if seen == 0
            else f"no walking pass found in {seen} frames with markers (standing or turning?)"
        )
    st = {} if live else gc.pool_spatiotemporal(contacts_all, pass_st)
    return TrialAnalysis(
        idx,
        t,
        tq,
        knee,
        passes,
        contacts_all,
        events,
        st,
        pass_st,
        phases,
        fps,
        warnings,
        memo=cache.used,
        series=kept if keep else {},
    )


def _walkway(state: GaitState) -> dict[str, list[float]] | None:
    """The calibration's floor plane and walking line (camera mm), for the results'
    ``walkway`` (exports place the markers in the lab frame with it); None without them."""
    parts = {"floor_plane": state.plane, "start": state.start, "end": state.end}
    if any(v is None or not np.all(np.isfinite(v)) for v in parts.values()):
        return None
    return {k: [round(float(x), 6) for x in v] for k, v in parts.items()}


def _document(
    frames: Sequence[FrameRec],
    a: TrialAnalysis,
    params: Mapping[str, Any],
    pass_index: int | None = None,
    records: Sequence[Mapping[str, Any]] | None = None,
    walkway: Mapping[str, list[float]] | None = None,
) -> dict[str, Any]:
    """The results document of the whole trial, or of one pass of it.

    ``records``: the trial's frame records (``frame_records``), when several documents of
    the trial are made at once. ``walkway``: see :func:`_walkway` (left out when None).
    """
    trial = frames[0].header.trial
    sel = np.ones(len(a.t), dtype=bool)
    selq = np.ones(len(a.tq), dtype=bool)
    events, st, passes, phases = a.events, a.spatiotemporal, a.passes, a.phases
    pass_sts = a.pass_st
    if pass_index is not None:
        ps = a.passes[pass_index]
        sel = (a.t >= ps["start_s"] - 1e-9) & (a.t <= ps["end_s"] + 1e-9)
        selq = (a.tq >= ps["start_s"] - 1e-9) & (a.tq <= ps["end_s"] + 1e-9)
        cs = a.contacts[pass_index]
        events = gc.events_from_contacts([c for s in "LR" for c in cs[s]])
        st = gc.pool_spatiotemporal([cs], [a.pass_st[pass_index]])
        passes = [ps]
        pass_sts = [a.pass_st[pass_index]]
        phases = {
            s: [c for c in a.phases[s] if ps["start_s"] <= c["initial_contact"] <= ps["end_s"]]
            for s in "LR"
        }
    keep = np.flatnonzero(sel).tolist()
    fr = [frames[i] for i in keep]
    pos = np.stack([f.position for f in fr]) if fr else np.zeros((0, 20, 3))
    pix = np.stack([f.pixel for f in fr]) if fr else np.zeros((0, 20, 2))
    warnings = list(a.warnings)
    return build_results(
        session=params.get("session", ""),
        trial=trial,
        camera_fps=a.fps,
        frame_index=a.frame_index[sel].tolist(),
        frame_time_s=a.t[sel],
        positions=pos,
        pixels=pix,
        knee_time_s=a.tq[selq],
        knee_deg={s: a.knee[s][selq] for s in "LR"},
        events=events,
        spatiotemporal=st,
        extra={
            "scope": "trial" if pass_index is None else "pass",
            "passes": passes,
            "phases": phases,
            "cycles": [r for st_p in pass_sts for r in st_p.get("_records", [])],
            "event_uncertainty_s": round(0.5 / a.fps, 4) if a.fps > 0 else 0.0,
            "warnings": warnings,
            "parameters": {k: v for k, v in params.items() if k != "session"},
            **({"walkway": dict(walkway)} if walkway is not None else {}),
        },
        records=None if records is None else [records[i] for i in keep],
    )


def _gait_frame(state: GaitState, rec: FrameRec, events: list) -> GaitFrame:
    pos = rec.position
    # both sides in one call each (rows are independent: the same values as one by one)
    knee = gc.knee_flexion(pos[_HIP], pos[_KNE], pos[_ANK], state.lateral)
    heel = np.full(2, np.nan)
    toe = np.full(2, np.nan)
    if state.plane is not None:
        # gc.plane_height's arithmetic, one point at a time (a (2, 3) product may round
        # differently), with the plane normalised once
        norm = np.linalg.norm(state.plane[:3])
        n, off = state.plane[:3] / norm, state.plane[3] / norm
        heel = np.array([pos[k] @ n + off for k in _HEE])
        toe = np.array([pos[k] @ n + off for k in _TOE])
    # live time: from the trial's first frame at the nominal period (the summary uses the
    # measured one); recomputing it over the whole buffer would cost O(frames) per frame
    first = state.frames[0].header
    t_now = (rec.header.capture_ns - first.capture_ns) / 1e9 + first.frame * NOMINAL_PERIOD_S
    return GaitFrame.follow(
        rec.header,
        knee_flexion=knee,
        heel_height=heel,
        toe_height=toe,
        time_s=float(t_now),
        events=events,
    )


def _reset(state: GaitState) -> GaitState:
    """The state with no open trial (the parameters and calibration stay)."""
    return dataclasses.replace(
        state,
        frames=(),
        emitted=(),
        summarised_until=float("-inf"),
        memo=(),
        series=None,
        pending=(),
    )


def _remember(state: GaitState, a: TrialAnalysis) -> tuple[Mapping[bytes, Any], ...]:
    """The state's memo with the entries of analysis ``a`` first (bounded)."""
    return (a.memo, *state.memo)[:MEMO_ANALYSES]


def _window_frames(state: GaitState) -> int:
    """``live_window_s`` in frames of the open trial, at its camera's rate (from its first
    and last frame's index and capture time; the nominal 30 fps before two frames): a 15 fps
    session's window is as long in seconds as a 30 fps one's."""
    period = NOMINAL_PERIOD_S
    if len(state.frames) >= 2:
        a, b = state.frames[0].header, state.frames[-1].header
        if b.frame > a.frame and b.capture_ns > a.capture_ns:
            period = (b.capture_ns - a.capture_ns) / 1e9 / (b.frame - a.frame)
    return max(1, round(state.params["live_window_s"] / period))


def _series(state: GaitState) -> Mapping[str, gc.Resampled] | None:
    """What an analysis of all the trial's frames may extend: the last one's resampled
    markers; none for a trial longer than the live window (the series would be heavy)."""
    if len(state.frames) > _window_frames(state):
        return None
    return state.series if state.series is not None else {}


def _with_record(rec: FrameRec, first: Header) -> FrameRec:
    """``rec`` with its results record, timed as ``_times`` will most likely time it: from
    the first frame at the nominal rate (exact when the trial starts at frame 0)."""
    t0 = np.int64(first.capture_ns) - first.frame * NOMINAL_PERIOD_S * 1e9
    t = float((np.int64(rec.header.capture_ns) - t0) / 1e9)
    record = frame_record(rec.header.frame, t, rec.position, rec.pixel)
    return dataclasses.replace(rec, record=record, record_t=t)


def _frame_records(frames: Sequence[FrameRec], a: TrialAnalysis) -> list[Mapping[str, Any]]:
    """The results records of all ``frames``: those made as the frames came where their time
    is the analysis' time bit for bit, the others made now."""
    made = np.array([f.record_t for f in frames], dtype=float)
    stale = np.flatnonzero(
        (made.view(np.int64) != a.t.view(np.int64))
        | np.array([f.record is None for f in frames], dtype=bool)
    ).tolist()
    out = [f.record for f in frames]
    if stale:
        fresh = frame_records(
            a.frame_index[stale].tolist(),
            a.t[stale],
            np.stack([frames[i].position for i in stale]),
            np.stack([frames[i].pixel for i in stale]),
        )
        for i, r in zip(stale, fresh, strict=True):
            out[i] = r
    return out  # type: ignore[return-value]


def _analyse_trial(state: GaitState) -> TrialAnalysis:
    """The full analysis of the open trial's frames, with what earlier analyses kept."""
    if state.plane is None:  # the callers check first: a trial without a floor is not analysed
        raise StageError("gait", f"trial {state.frames[0].header.trial!r}: no floor plane")
    a = analyse(
        state.frames,
        state.plane,
        state.start,
        state.end,
        state.params,
        memo=state.memo,
        series=_series(state),
    )
    if state.calibration_note:
        used = ": its floor plane and walking line were used; " + CHECK_SETUP
        a = dataclasses.replace(a, warnings=[*a.warnings, state.calibration_note + used])
    return a


def _close(state: GaitState) -> tuple[GaitState, list[Message], list[list]]:
    """End the open trial: the summaries, and the events not yet published."""
    if not state.frames:
        return state, [], []
    last = state.frames[-1].header
    out: list[Message] = []
    trial = state.frames[0].header.trial
    if state.plane is None:
        note = state.calibration_note
        why = "no floor calibration" + (f": {note}; {CHECK_SETUP}" if note else "")
        doc = empty_results(state.params.get("session", ""), trial, 30.0, why)
        out.append(TrialSummary.follow(last, results=doc, warnings=doc["warnings"]))
        return _reset(state), out, []
    a = _analyse_trial(state)
    records = _frame_records(state.frames, a)
    walkway = _walkway(state)
    doc = _document(state.frames, a, state.params, records=records, walkway=walkway)
    new_events = _new_events(state, a.events, float("inf"))
    for i, ps in enumerate(a.passes):
        if ps["end_s"] > state.summarised_until:
            pdoc = _document(state.frames, a, state.params, i, records, walkway)
            out.append(TrialSummary.follow(last, results=pdoc, warnings=pdoc["warnings"]))
    out.append(TrialSummary.follow(last, results=doc, warnings=list(a.warnings)))
    return _reset(state), out, new_events


def _new_events(state: GaitState, events: list[dict[str, Any]], before: float) -> list[list]:
    """Events older than ``before`` not yet published (nor within 0.1 s of one that was)."""
    out = []
    for e in events:
        if e["time_s"] >= before:
            continue
        dup = any(
            s == e["side"] and k == e["kind"] and abs(t - e["time_s"]) < 0.1
            for s, k, t in state.emitted
        )
        if not dup:
            out.append([e["side"], e["kind"], e["time_s"]])
    return out


def step(state: GaitState, inputs: Inputs) -> tuple[GaitState, list[Message]]:
    """Take one labelled frame; publish its ``gait`` message (and summaries at ends)."""
    msg = inputs["labelled"]
    if not isinstance(msg, LabelledMarkers):
        raise StageError("gait", f"input 'labelled' is a {type(msg).__name__}")
    out: list[Message] = []
    h = msg.header
    if state.frames:
        open_h = state.frames[0].header
        too_long = len(state.frames) >= state.params["max_frames"]
        if (open_h.camera, open_h.trial) != (h.camera, h.trial) or too_long:
            # a new trial, or a live trial too long to keep: close what is open
            state, closed, _ = _close(state)
            out.extend(closed)
    cal = inputs.get("calibration")
    if cal is not None and not state.frames:
        plane = np.asarray(cal.floor_plane, dtype=float)
        ok = plane.shape == (4,) and np.all(np.isfinite(plane)) and np.linalg.norm(plane[:3]) > 0
        # A record that is not Done may still carry a plane (a marker off it, a quad that
        # is not convex): the figures then rest on a floor the operator was told to redo.
        note = ""
        if cal.status != "Done":
            why = f" ({cal.message})" if cal.message else ""
            note = f"the calibration record says {cal.status}{why}"
        state = dataclasses.replace(
            state,
            plane=plane if ok else None,
            start=np.asarray(cal.start, dtype=float),
            end=np.asarray(cal.end, dtype=float),
            calibration_note=note,
        )
        lat = None
        if ok and state.params["knee_plane"] == "sagittal":
            # the walkway axis, as the summary takes it (its fallback needs the trial's
            # markers: without a walking line the live angle stays 3D)
            try:
                lat = gc.lateral_axis(plane, gc.walking_axis(state.start, state.end, plane))
            except ValueError:
                lat = None
        state = dataclasses.replace(state, lateral=lat)
    rec = FrameRec(
        h,
        np.array(msg.position, dtype=float),
        np.array(msg.pixel, dtype=float),
        int(msg.direction),
        str(msg.near_side),
        spare_pixel=np.array(msg.spare_pixel, dtype=float).reshape(-1, 2),
        spare_heel=np.array(msg.spare_heel, dtype=float).reshape(-1, 3),
    )
    rec = _with_record(rec, state.frames[0].header if state.frames else h)
    # live events found after the previous frame go out with this one
    events = [list(e) for e in state.pending]
    state = dataclasses.replace(state, frames=(*state.frames, rec), pending=())
    if h.last:
        closing_state, closed, final_events = _close(state)
        out.insert(0, _gait_frame(state, rec, events + final_events))
        out.extend(closed)
        return closing_state, out
    out.insert(0, _gait_frame(state, rec, events))
    return state, out


def after(state: GaitState) -> tuple[GaitState, list[Message]]:
    """The live event search and pass summaries due after the frame just published.

    Deferred (``StageSpec.after``) so that a frame's ``gait`` message never waits for them:
    the events found here go out with the next frame's message (live events are at least
    ``live_delay_s`` old anyway), a pass summary as its own message now.
    """
    every, n = state.params["live_every"], len(state.frames)
    # due every ``live_every`` frames of an open trial (a closed one has no frames)
    if every <= 0 or n == 0 or n % every or state.plane is None:
        return state, []
    out: list[Message] = []
    h = state.frames[-1].header
    # live events from the recent frames only (times stay on the trial's clock), so the
    # cost per frame does not grow with the trial
    recent = state.frames[-_window_frames(state) :]
    whole = len(recent) == n
    a = analyse(
        recent,
        state.plane,
        state.start,
        state.end,
        state.params,
        live=True,
        memo=state.memo,
        series=_series(state) if whole else None,
    )
    now = float(a.t[-1])
    events = _new_events(state, a.events, now - state.params["live_delay_s"])
    state = dataclasses.replace(
        state,
        emitted=state.emitted + tuple(map(tuple, events)),
        pending=tuple(map(tuple, events)),
        memo=_remember(state, a),
        series=a.series if whole else None,
    )
    # a pass that ended well before now is complete: summarise it (once)
    if any(state.summarised_until < ps["end_s"] < now - 1.0 for ps in a.passes):
        full = _analyse_trial(state)
        state = dataclasses.replace(state, memo=_remember(state, full), series=full.series or None)
        recs, walkway = _frame_records(state.frames, full), _walkway(state)
        for i, ps in enumerate(full.passes):
            if state.summarised_until < ps["end_s"] < now - 1.0:
                pdoc = _document(state.frames, full, state.params, i, recs, walkway)
                out.append(TrialSummary.follow(h, results=pdoc, warnings=pdoc["warnings"]))
                state = dataclasses.replace(state, summarised_until=ps["end_s"])
    return state, out


def finish(state: GaitState) -> tuple[GaitState, list[Message]]:
    """Close a trial whose last frame never came."""
    state, out, _ = _close(state)
    return state, out


SPEC = StageSpec(
    name="gait",
    params=PARAMS,
    init=init,
    step=step,
    finish=finish,
    after=after,
    stateful=True,
    doc=__doc__ or "",
)
