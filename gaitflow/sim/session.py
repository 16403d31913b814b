"""Simulate a whole clinical session: calibration, static pose and walking trials.

``simulate_session(trial, seed, config)`` returns a :class:`SimSession` whose recordings
yield ``(RawFrame, GroundTruth)`` per frame, lazily. Each frame is rendered with its own
random generator seeded by (seed, recording, frame index), so output is deterministic for
a seed and any recording can be iterated more than once.

Timing: frames are nominally 1/30 s apart; the capture time has a small Gaussian jitter,
and frames are dropped now and then (never the first or last one), leaving gaps in the
frame index. Ground truth is the marker positions at the middle of each frame's exposure
(the actual capture time), exactly.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gaitflow.camera import Camera
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES
from gaitflow.schemas.raw import RawFrame
from gaitflow.schemas.truth import GroundTruth
from gaitflow.sim.body import build_body, crouch_trial, knee_flexion, load_trial, scale_trial
from gaitflow.sim.config import RECORDING_KINDS, SimConfig
from gaitflow.sim.render import Renderer
from gaitflow.sim.truth import merged_flags, spatiotemporal, visibility
from gaitflow.sim.walk import CalibrationMotion, StaticMotion, WalkMotion

CAMERA_ID = "cam0"
EPOCH_NS = 1_700_000_000_000_000_000
RECORDING_GAP_NS = 60_000_000_000  # a minute between recordings


@dataclass(frozen=True)
class FrameTime:
    """Frames actually delivered: index (K,), capture time (K,) s from the first frame."""

    index: np.ndarray
    time_s: np.ndarray


def frame_times(duration_s: float, fps: float, cfg: SimConfig, seed: int, rec: int) -> FrameTime:
    """Frame indices and capture times of a recording, with jitter and drops."""
    n = int(np.floor(duration_s * fps)) + 1
    rng = np.random.default_rng([seed, rec, 1_000_003])
    jitter = np.clip(rng.normal(0.0, cfg.jitter_ms / 1000.0, n), -0.004, 0.004)
    jitter[0] = 0.0
    t = np.arange(n) / fps + jitter
    keep = rng.random(n) >= cfg.drop_prob
    keep[0] = keep[-1] = True
    idx = np.flatnonzero(keep)
    return FrameTime(idx, t[idx])


class Recording:
    """One simulated recording: iterate it for ``(RawFrame, GroundTruth)`` pairs."""

    def __init__(self, session: SimSession, name: str, motion: Any, rec: int, kind: str) -> None:
        self.session, self.name, self.motion, self.rec, self.kind = (
            session,
            name,
            motion,
            rec,
            kind,
        )
        cfg = session.config
        self.times = frame_times(motion.duration_s, cfg.camera.fps, cfg, session.seed, rec)
        self.t0_ns = EPOCH_NS + rec * RECORDING_GAP_NS

    def __len__(self) -> int:
        return len(self.times.index)

    def __iter__(self) -> Iterator[tuple[RawFrame, GroundTruth]]:
        n = len(self)
        for k in range(n):
            yield self.frame(k, last=k == n - 1)

    def __call__(self) -> Iterator[tuple[RawFrame, GroundTruth]]:
        return iter(self)

    def frame(self, k: int, last: bool = False) -> tuple[RawFrame, GroundTruth]:
        """The k-th delivered frame (not the k-th index: dropped frames are skipped)."""
        ses = self.session
        cfg = ses.config
        index = int(self.times.index[k])
        t = float(self.times.time_s[k])
        rng = np.random.default_rng([ses.seed, self.rec, index])
        pose = self.motion.pose(t, cfg.exposure_ms / 1000.0, cfg.blur_samples)
        out = ses.renderer_for(self.kind).render(pose, rng)
        capture_ns = self.t0_ns + round(t * 1e9)
        raw = RawFrame(
            header=RawFrame.make_header(CAMERA_ID, self.name, index, capture_ns, last=last),
            ir=out.ir,
            depth=out.depth,
            camera=ses.camera_json,
        )
        truth = self._truth(raw, pose, out, t)
        return raw, truth

    def _truth(self, raw: RawFrame, pose: Any, out: Any, t: float) -> GroundTruth:
        ses = self.session
        cfg = ses.config
        # The truth is the marker position at mid-exposure, t itself (the blur samples
        # straddle it and an even count has no sample there).
        pos_w = None if self.kind == "calibration" else pose.markers
        n = len(MARKER_NAMES)
        position = np.full((n, 3), np.nan)
        pixel = np.full((n, 2), np.nan)
        visible = np.zeros(n, dtype=bool)
        occluded = np.zeros(n, dtype=bool)
        knee = np.full(2, np.nan)
        knee_ref = [float("nan"), float("nan")]
        pass_name = ""
        fraction = [0.0] * n
        merged = [False] * n
        if self.kind in ("walk", "static"):
            # the markers are the first n spheres (the shoes' reflectors follow, no truth)
            fraction = [float(v) for v in out.seen[:n]]
            position = ses.renderer.to_cam(pos_w)
            pixel = ses.camera.project(position)
            visible, occluded = visibility(out.seen[:n], out.in_view[:n])
            streak = ses.renderer.to_cam(pose.spheres[:, :n])  # (B, 20, 3) over the exposure
            with np.errstate(invalid="ignore"):
                streak_px = ses.camera.project(streak.reshape(-1, 3)).reshape(-1, n, 2)
                radius_px = ses.camera.fx * cfg.marker_radius_mm / streak[..., 2]
            merged = [bool(v) for v in merged_flags(streak_px, radius_px, visible)]
            knee = knee_flexion(pos_w[None])[0]
            knee_ref = [float(v) for v in self.motion.knee_ref(np.array([t]))[0]]
            if self.kind == "walk":
                wm = self.motion
                pass_name = (
                    "out" if t <= wm.pass_dur else ("turn" if t < wm.passes[1].t0 else "back")
                )
        half = 0.5 / cfg.camera.fps
        events = [
            [side, kind, float(te)]
            for te, side, kind, _p in self.motion.events()
            if t - half <= te < t + half
        ]
        return GroundTruth.follow(
            raw.header,
            position=position,
            pixel=pixel,
            visible=visible,
            occluded=occluded,
            knee_flexion=knee,
            time_s=t,
            events=events,
            knee_flexion_ref=knee_ref,
            pass_name=pass_name,
            visible_fraction=fraction,
            merged=merged,
        )

    def frames(self) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
        """``(index, timestamp_ns, ir, depth)`` tuples, the SessionWriter's input."""
        for raw, _truth in self:
            yield raw.header.frame, raw.header.capture_ns, raw.ir, raw.depth


@dataclass
class SimSession:
    """A simulated session.

    Attributes
    ----------
    camera : the intrinsics.
    camera_json : the session folder's camera.json document.
    recordings : name -> :class:`Recording` ("calibration", "static", "walk-01", ...).
    """

    trial: str
    seed: int
    config: SimConfig
    camera: Camera
    renderer: Renderer
    camera_json: dict[str, Any]
    recordings: dict[str, Recording] = field(default_factory=dict)
    _bare: Renderer | None = field(default=None, repr=False)

    def renderer_for(self, kind: str) -> Renderer:
        """The renderer of a recording kind: without the static reflectors before the
        recording they were put down in (``SimConfig.reflectors_from``)."""
        cfg = self.config
        if not cfg.static_reflectors or RECORDING_KINDS.index(kind) >= RECORDING_KINDS.index(
            cfg.reflectors_from
        ):
            return self.renderer
        if self._bare is None:
            self._bare = Renderer(cfg.with_(static_reflectors=()), bank_seed=self.seed)
        return self._bare

    def truth_summary(self, name: str) -> dict[str, Any]:
        """Trial-level ground truth of one recording (JSON-ready)."""
        rec = self.recordings[name]
        cfg = self.config
        r = self.renderer
        doc: dict[str, Any] = {
            "recording": name,
            "kind": rec.kind,
            "source_trial": self.trial,
            "seed": self.seed,
            "fps": cfg.camera.fps,
            "n_frames": len(rec),
            "frame_index": [int(i) for i in rec.times.index],
            "dropped": int(rec.times.index[-1] + 1 - len(rec)),
            "duration_s": float(rec.motion.duration_s),
            "first_timestamp_ns": int(rec.t0_ns),
            "marker_names": list(MARKER_NAMES),
            "marker_diameter_mm": cfg.marker_diameter_mm,
            "floor_plane_cam": [float(v) for v in r.floor_plane_cam()],
            "camera_pose": {
                "R_world_to_cam": r.R.tolist(),
                "centre_world_mm": r.C.tolist(),
                "world": "x along the walkway, y away from the camera, z up, floor z=0",
            },
        }
        if rec.kind == "calibration":
            m = rec.motion
            cam_pts = r.to_cam(m.markers)
            doc["calibration_markers_cam"] = cam_pts.tolist()
            doc["calibration_markers_px"] = self.camera.project(cam_pts).tolist()
            doc["calibration_markers_world"] = m.markers.tolist()
            doc["placed_at_s"] = [float(v) for v in m.t_drop]
        if rec.kind == "walk":
            wm = rec.motion
            events = wm.events()
            doc["events"] = wm.events_detail()
            doc["passes"] = [
                {
                    "name": p.name,
                    "start_s": float(p.t0),
                    "end_s": float(p.t0 + wm.pass_dur),
                    "source_start_s": float(wm.time_at(p, 0.0)),
                    "source_end_s": float(wm.time_at(p, wm.src_dur)),
                    "direction_world": p.direction.tolist(),
                    "side_facing_camera": "R" if p.direction[0] > 0 else "L",
                }
                for p in wm.passes
            ]
            directions = {p.name: p.direction for p in wm.passes}
            hee = [MARKER_INDEX["L_HEE"], MARKER_INDEX["R_HEE"]]

            def heel_at(t: np.ndarray) -> np.ndarray:
                return wm.markers_caps(t)[0][:, hee]

            doc["spatiotemporal"] = spatiotemporal(events, heel_at, directions)
            doc["source"] = {
                k: wm.trial.meta.get(k) for k in ("source", "licence", "subject", "condition")
            }
        if rec.kind == "static":
            m = rec.motion
            doc["standing_at_world"] = np.asarray(m.T, dtype=float).tolist()
        return doc

    def walks(self) -> list[str]:
        return [n for n in self.recordings if n.startswith("walk-")]


def simulate_session(trial: str, seed: int = 0, config: SimConfig | None = None) -> SimSession:
    """Build a simulated session from a bundled trial (nothing is rendered yet).

    Parameters
    ----------
    trial : a bundled trial id (:func:`gaitflow.sim.list_trials`).
    seed : random seed; the same seed gives byte-identical frames.
    config : simulator knobs; default :class:`SimConfig`.
    """
    cfg = config or SimConfig()
    src = scale_trial(load_trial(trial), cfg.body_scale)
    src = crouch_trial(src, cfg.crouch_mm, cfg.marker_radius_mm)
    body = build_body(
        src,
        cfg.marker_radius_mm,
        cfg.source_marker_diameter_mm / 2,
        cfg.arm_swing_gain,
        marker_base_mm=cfg.marker_base_mm,
        patch_mm=cfg.skin_patch_mm,
        wand_mount=cfg.wand_mount,
        wand_mm=cfg.wand_mm,
    )
    renderer = Renderer(cfg, bank_seed=seed)
    cam = cfg.camera
    camera_json = cam.to_json(
        marker_diameter_mm=cfg.marker_diameter_mm,
        calibration_markers=cfg.calibration_markers,
        subject={"id": cfg.subject_id},
    )
    ses = SimSession(trial, seed, cfg, cam, renderer, camera_json)
    # World x of the left and right image edges on the walking line.
    D = cfg.walk_distance_mm
    row = round(cam.cy)
    x_lo = float(renderer.rx[row, 0] * D + D * np.tan(np.radians(cfg.pan_deg)))
    x_hi = float(renderer.rx[row, -1] * D + D * np.tan(np.radians(cfg.pan_deg)))
    walk = WalkMotion(src, body, cfg, view_x=(x_lo, x_hi), margin_mm=cfg.walk_margin_mm)
    ses.recordings["calibration"] = Recording(
        ses, "calibration", CalibrationMotion(cfg, seed), 0, "calibration"
    )
    # The static pose is taken on the walking line in the middle of the view, side-on:
    # clinics stand the subject where the camera sees every near-side marker square-on
    # (towards the image edge the view is up to 25 degrees oblique, and the heel marker
    # hides behind the ankle).
    start = walk.start_point()
    start[0] = 0.5 * (x_lo + x_hi)
    ses.recordings["static"] = Recording(
        ses, "static", StaticMotion(src, cfg, start, seed, walk.passes[0].R), 1, "static"
    )
    vary = np.random.default_rng([seed, 99])
    for k in range(cfg.n_walks):
        name = f"walk-{k + 1:02d}"
        motion = walk
        if k > 0:
            # Repeated trials differ a little: the subject walks a few cm off the line and a
            # few % faster or slower (same gait pattern, played at another speed).
            cfg_k = cfg.with_(
                walk_distance_mm=cfg.walk_distance_mm + float(vary.normal(0.0, 80.0)),
                speed_factor=cfg.speed_factor * float(1.0 + vary.normal(0.0, 0.04)),
            )
            motion = WalkMotion(src, body, cfg_k, view_x=(x_lo, x_hi), margin_mm=cfg.walk_margin_mm)
        ses.recordings[name] = Recording(ses, name, motion, 2 + k, "walk")
    return ses
