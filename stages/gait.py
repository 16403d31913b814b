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

1. times from the capture clock (s from the trial's first frame, frame drops stay gaps);
2. every marker gap-filled with cubic Bezier segments (at most ``max_gap_s``), then
   resampled to ``resample_hz`` with Catmull-Rom Bezier segments on the timestamps;
3. heel and toe heights above the calibration's floor plane; positions along the walking
   axis from the start to the end point;
4. the walk split into passes by the direction of progression of the pelvis markers (the
   return pass shows the other side of the body to the camera);
5. per pass and foot, Alg. 6 on the heel and toe heights, events refined inside the flat
   ranges (``refine``), then step and stride length, stance and swing, the eight phases;
6. knee flexion = 180 deg - angle HIP-KNE-ANK from the gap-filled, resampled 3D markers.

Array conventions: marker axis follows ``gaitflow.markers.MARKER_NAMES``; camera mm; NaN =
missing; time axis 0; seconds; degrees. Ground truth is never read here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from gaitflow.schemas import GaitFrame, Header, LabelledMarkers, Message, TrialSummary
from gaitflow.stages.base import Inputs, StageSpec

from gaitflow import gaitcore as gc
from gaitflow.errors import StageError
from gaitflow.markers import MARKER_INDEX
from gaitflow.params import Param, ParamSet
from gaitflow.results import build_results, empty_results

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
            "outlier_mm",
            float,
            25.0,
            "mm",
            "knee markers: one this far from the median of its 4 neighbours is dropped (0=off)",
            0.0,
        ),
        Param(
            "segment_tol",
            float,
            0.15,
            "ratio",
            "knee angle unknown where thigh or shank length departs this much from its median",
            0.0,
        ),
        Param(
            "depth_smooth_s",
            float,
            0.0,
            "s",
            "smooth each marker's depth along its ray over this window (0 = off)",
            0.0,
            2.0,
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
        Param("min_pass_s", float, 0.6, "s", "shortest walking pass", 0.1),
        Param("min_speed_mm_s", float, 150.0, "mm/s", "slower than this is not walking", 1.0),
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
BODY = [f"{s}_{m}" for s in "LR" for m in ("SHO", "ASI", "PSI", "HIP", "THI")]


@dataclass(frozen=True)
class FrameRec:
    """One labelled frame as the stage keeps it."""

    header: Header
    position: np.ndarray  # (20, 3) camera mm
    pixel: np.ndarray  # (20, 2) px
    direction: int
    near_side: str


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


def init(params: dict[str, Any]) -> GaitState:
    return GaitState(params=dict(params))


def _times(frames: Sequence[FrameRec]) -> tuple[np.ndarray, np.ndarray, float]:
    """Frame indices, seconds from the trial's first frame, and the camera rate."""
    idx = np.array([f.header.frame for f in frames], dtype=np.int64)
    ns = np.array([f.header.capture_ns for f in frames], dtype=np.int64)
    if len(frames) >= 2:
        di = np.diff(idx)
        ok = di > 0
        period = float(np.median(np.diff(ns)[ok] / di[ok])) / 1e9 if ok.any() else 1 / 30
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
    for s in "LR":
        idx = [MARKER_INDEX[f"{s}_KNE"], MARKER_INDEX[f"{s}_ANK"]]
        d = np.array([np.linalg.norm(f.position[idx], axis=1) for f in frames]).ravel()
        d = d[np.isfinite(d)]
        dist[s] = float(np.median(d)) if d.size else float("nan")
    if not all(np.isfinite(v) for v in dist.values()):
        return ""
    return "L" if dist["L"] < dist["R"] else "R"


def _nanmedian_rows(x: np.ndarray) -> np.ndarray:
    """Median of each row ignoring NaN; NaN for an all-NaN row (without a warning)."""
    out = np.full(x.shape[0], np.nan)
    ok = np.isfinite(x).any(axis=1)
    if ok.any():
        out[ok] = np.nanmedian(x[ok], axis=1)
    return out


def _body_progression(pq: np.ndarray, origin: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Progression of the body (Q,): the pelvis and trunk markers, else any marker seen.

    The legs stay in view longest when the subject walks in or out of the field of view;
    their median still moves with the body over the half-second slope window of
    :func:`gaitflow.gaitcore.split_passes`.
    """
    prog = gc.progression(pq, origin, axis)  # (Q, 20)
    body = _nanmedian_rows(prog[:, [MARKER_INDEX[n] for n in BODY]])
    anym = _nanmedian_rows(prog)
    return np.where(np.isfinite(body), body, anym)


def analyse(
    frames: Sequence[FrameRec],
    plane: np.ndarray,
    start: np.ndarray | None,
    end: np.ndarray | None,
    params: Mapping[str, Any],
    live: bool = False,
) -> TrialAnalysis:
    """Analyse the frames of one trial (steps 1-6 of the module docstring).

    ``live=True`` skips what live events do not need (knee angles, phases).
    """
    p = params
    idx, t, fps = _times(frames)
    warnings: list[str] = []
    pos = np.stack([f.position for f in frames]) if frames else np.zeros((0, 20, 3))
    pos = gc.smooth_depth(t, pos, p["depth_smooth_s"])
    nq = int(np.floor((t[-1] - t[0]) * p["resample_hz"] + 1e-6)) + 1 if len(t) else 0
    tq = t[0] + np.arange(nq) / p["resample_hz"] if len(t) else np.zeros(0)
    pq = np.full((nq, 20, 3), np.nan)
    need = range(20)
    if live:
        need = [MARKER_INDEX[n] for n in (*BODY, "L_HEE", "R_HEE", "L_TOE", "R_TOE")]
    for k in need:
        if np.isfinite(pos[:, k, 0]).sum() < 2:
            continue
        filled, _ = gc.fill_gaps(t, pos[:, k], p["max_gap_s"])
        _, pq[:, k] = gc.resample(t, filled, p["resample_hz"])
    knee = {"L": np.full(nq, np.nan), "R": np.full(nq, np.nan)}
    if not live:
        # the knee markers alone go through the outlier filter: a dropped heel sample in a
        # fast swing would cost an event, a dropped knee sample only a filled gap
        kidx = [MARKER_INDEX[f"{s}_{m}"] for s in "LR" for m in ("HIP", "KNE", "ANK")]
        kpos = gc.reject_outliers(pos[:, kidx], p["outlier_mm"])
        pk = np.full((nq, 20, 3), np.nan)
        for j, k in enumerate(kidx):
            if np.isfinite(kpos[:, j, 0]).sum() >= 2:
                filled, _ = gc.fill_gaps(t, kpos[:, j], p["max_gap_s"])
                _, pk[:, k] = gc.resample(t, filled, p["resample_hz"])
        for s in "LR":
            hip, kne, ank = (pk[:, MARKER_INDEX[f"{s}_{m}"]] for m in ("HIP", "KNE", "ANK"))
            knee[s] = gc.knee_flexion(hip, kne, ank)
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
        axis, origin = _axis(plane, start, end, pos)
        body = _body_progression(pq, origin, axis)
        found = gc.split_passes(tq, body, p["min_speed_mm_s"], min_duration_s=p["min_pass_s"])
        for ps in found:
            sl = slice(ps.start, ps.stop)
            d = float(ps.direction)
            contacts: dict[str, list[gc.Contact]] = {}
            prog_heel: dict[str, np.ndarray] = {}
            tilt: dict[str, np.ndarray] = {}
            for s in "LR":
                heel = pq[sl, MARKER_INDEX[f"{s}_HEE"]]
                toe = pq[sl, MARKER_INDEX[f"{s}_TOE"]]
                prog_heel[s] = d * gc.progression(heel, origin, axis)
                contacts[s] = gc.foot_contacts(
                    tq[sl],
                    gc.plane_height(heel, plane),
                    gc.plane_height(toe, plane),
                    prog_heel[s],
                    d * gc.progression(toe, origin, axis),
                    s,
                    gamma=p["gamma"],
                    xi=p["xi"],
                    phi=p["phi"],
                    tau=p["tau"],
                    max_born=p["max_born"],
                    refine=p["refine"],
                    hs_speed_frac=p["hs_speed_frac"],
                    to_speed_frac=p["to_speed_frac"],
                )
                tilt[s] = d * (
                    gc.progression(pq[sl, MARKER_INDEX[f"{s}_KNE"]], origin, axis)
                    - gc.progression(pq[sl, MARKER_INDEX[f"{s}_ANK"]], origin, axis)
                )
            in_pass = [
                f for f, tt in zip(frames, t, strict=True) if tq[ps.start] <= tt <= tq[ps.stop - 1]
            ]
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
            pass_st.append(gc.spatiotemporal(contacts, 1.0, tq[sl], prog_heel))
            if not live:
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
    st = gc.pool_spatiotemporal(contacts_all, pass_st)
    return TrialAnalysis(
        idx, t, tq, knee, passes, contacts_all, events, st, pass_st, phases, fps, warnings
    )


def _document(
    frames: Sequence[FrameRec],
    a: TrialAnalysis,
    params: Mapping[str, Any],
    pass_index: int | None = None,
) -> dict[str, Any]:
    """The results document of the whole trial, or of one pass of it."""
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
    fr = [f for f, k in zip(frames, sel, strict=True) if k]
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
        },
    )


def _gait_frame(state: GaitState, rec: FrameRec, events: list) -> GaitFrame:
    pos = rec.position
    knee = np.array(
        [
            gc.knee_flexion(
                pos[MARKER_INDEX[f"{s}_HIP"]],
                pos[MARKER_INDEX[f"{s}_KNE"]],
                pos[MARKER_INDEX[f"{s}_ANK"]],
            )
            for s in "LR"
        ],
        dtype=float,
    )
    heel = np.full(2, np.nan)
    toe = np.full(2, np.nan)
    if state.plane is not None:
        heel = np.array([gc.plane_height(pos[MARKER_INDEX[f"{s}_HEE"]], state.plane) for s in "LR"])
        toe = np.array([gc.plane_height(pos[MARKER_INDEX[f"{s}_TOE"]], state.plane) for s in "LR"])
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
    return dataclasses.replace(state, frames=(), emitted=(), summarised_until=float("-inf"))


def _close(state: GaitState) -> tuple[GaitState, list[Message], list[list]]:
    """End the open trial: the summaries, and the events not yet published."""
    if not state.frames:
        return state, [], []
    last = state.frames[-1].header
    out: list[Message] = []
    trial = state.frames[0].header.trial
    if state.plane is None:
        doc = empty_results(state.params.get("session", ""), trial, 30.0, "no floor calibration")
        out.append(TrialSummary.follow(last, results=doc, warnings=doc["warnings"]))
        return (
            dataclasses.replace(state, frames=(), emitted=(), summarised_until=float("-inf")),
            out,
            [],
        )
    a = analyse(state.frames, state.plane, state.start, state.end, state.params)
    doc = _document(state.frames, a, state.params)
    new_events = _new_events(state, a.events, float("inf"))
    for i, ps in enumerate(a.passes):
        if ps["end_s"] > state.summarised_until:
            pdoc = _document(state.frames, a, state.params, i)
            out.append(TrialSummary.follow(last, results=pdoc, warnings=pdoc["warnings"]))
    out.append(TrialSummary.follow(last, results=doc, warnings=list(a.warnings)))
    return (
        dataclasses.replace(state, frames=(), emitted=(), summarised_until=float("-inf")),
        out,
        new_events,
    )


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
        state = dataclasses.replace(
            state,
            plane=plane if ok else None,
            start=np.asarray(cal.start, dtype=float),
            end=np.asarray(cal.end, dtype=float),
        )
    rec = FrameRec(
        h,
        np.array(msg.position, dtype=float),
        np.array(msg.pixel, dtype=float),
        int(msg.direction),
        str(msg.near_side),
    )
    state = dataclasses.replace(state, frames=(*state.frames, rec))
    events: list = []
    every = state.params["live_every"]
    n = len(state.frames)
    if every > 0 and n % every == 0 and state.plane is not None and not h.last:
        # live events from the recent frames only (times stay on the trial's clock), so the
        # cost per frame does not grow with the trial
        recent = state.frames[-int(state.params["live_window_s"] * 30) :]
        a = analyse(recent, state.plane, state.start, state.end, state.params, live=True)
        now = float(a.t[-1])
        events = _new_events(state, a.events, now - state.params["live_delay_s"])
        state = dataclasses.replace(state, emitted=state.emitted + tuple(map(tuple, events)))
        # a pass that ended well before now is complete: summarise it (once)
        if any(state.summarised_until < ps["end_s"] < now - 1.0 for ps in a.passes):
            full = analyse(state.frames, state.plane, state.start, state.end, state.params)
            for i, ps in enumerate(full.passes):
                if state.summarised_until < ps["end_s"] < now - 1.0:
                    pdoc = _document(state.frames, full, state.params, i)
                    out.append(TrialSummary.follow(h, results=pdoc, warnings=pdoc["warnings"]))
                    state = dataclasses.replace(state, summarised_until=ps["end_s"])
    if h.last:
        closing_state, closed, final_events = _close(state)
        out.insert(0, _gait_frame(state, rec, events + final_events))
        out.extend(closed)
        return closing_state, out
    out.insert(0, _gait_frame(state, rec, events))
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
    stateful=True,
    doc=__doc__ or "",
)
