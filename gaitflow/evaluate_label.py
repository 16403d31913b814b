"""Labelling evaluation: the score, and a small kinematic walker for tests.

:func:`score_labelling` (re-exported from ``gaitflow.stages.label``) scores ``labelled``
messages against simulator ground truth. :func:`synthetic_walk` builds a side-on walk
(out and back) of the 20 markers from simple sagittal kinematics, as ``Markers3D``
messages with the truth beside them, so that label and model can be tested on literal
layouts without rendering frames. Ground truth never enters a stage: the tests compare the
stage's blob indices with the generator's.

Conventions: floor frame (a along the walking line toward +u, e away from the camera,
h up), mm; the camera looks along +e from 2700 mm, 800 mm above the floor, level; camera
space X right, Y down, Z forward.
"""

from __future__ import annotations

import argparse
import pickle
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from gaitflow.camera import Camera
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES, SITES
from gaitflow.schemas import CalibrationRecord, Markers3D
from gaitflow.stages.label import score_labelling

__all__ = ["Walk", "calibration_record", "score_labelling", "synthetic_walk", "to_camera"]

CAM_HEIGHT = 800.0
LINE_DEPTH = 2700.0
HALF_LENGTH = 2000.0

# Lateral offsets of each site from the body's mid-plane, mm.
LATERAL = {
    "SHO": 170.0,
    "ASI": 110.0,
    "PSI": 50.0,
    "HIP": 150.0,
    "THI": 100.0,
    "KNE": 80.0,
    "TIB": 65.0,
    "ANK": 60.0,
    "HEE": 40.0,
    "TOE": 45.0,
}
# Far-side markers a side view shows.
FAR_SEEN = ("ASI", "HEE", "TOE")


def to_camera(q: np.ndarray) -> np.ndarray:
    """Floor coords (..., 3) (a, e, h) -> camera space (..., 3) mm."""
    q = np.asarray(q, dtype=np.float64)
    return np.stack([q[..., 0] - HALF_LENGTH, CAM_HEIGHT - q[..., 2], LINE_DEPTH + q[..., 1]], -1)


def calibration_record(camera: str = "cam0") -> CalibrationRecord:
    """The record of the synthetic scene: level camera, walking line 2.7 m away."""
    hdr = CalibrationRecord.make_header(camera, "calibration", 0, 0, True)
    start = to_camera(np.array([0.0, 0.0, 0.0]))
    end = to_camera(np.array([2 * HALF_LENGTH, 0.0, 0.0]))
    return CalibrationRecord(
        header=hdr,
        floor_pixels=np.zeros((0, 2)),
        floor_points=np.zeros((0, 3)),
        floor_plane=np.array([0.0, -1.0, 0.0, CAM_HEIGHT]),
        start=start,
        end=end,
        status="Done",
        markers_found=4,
        length_mm=2 * HALF_LENGTH,
    )


def _rot(v: np.ndarray, ang: float) -> np.ndarray:
    """Rotate sagittal vectors (..., 2) = (forward, up) by ``ang`` rad (forward -> up)."""
    c, s = np.cos(ang), np.sin(ang)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def pose(t: float, x0: float, speed: float, standing: bool = False) -> np.ndarray:
    """Body-frame marker positions (20, 3): (forward, lateral toward the right, height).

    Sagittal chain per leg: thigh 430 mm, shank 420 mm, the ankle 75 mm above the sole;
    a 1 Hz stride; the pelvis lowered so the lowest sole point touches the floor.
    """
    out = np.zeros((20, 3))
    thigh, shank = 430.0, 420.0
    hip_h = 0.0
    legs = {}
    for side, ph in (("R", 0.0), ("L", np.pi)):
        phase = 2 * np.pi * 1.0 * t + ph
        if standing:
            a_th, flex, foot = 0.0, 0.0, 0.0
        else:
            a_th = np.radians(22.0) * np.sin(phase)
            flex = np.radians(5.0 + 30.0 * max(0.0, np.sin(phase + 0.6)))
            foot = np.radians(10.0) * np.sin(phase - 0.8)
        down = np.array([0.0, -1.0])
        knee = _rot(down * thigh, a_th)
        ank = knee + _rot(down * shank, a_th - flex)
        hee = ank + _rot(np.array([-55.0, -60.0]), foot)
        toe = ank + _rot(np.array([140.0, -62.0]), foot)
        legs[side] = dict(
            HIP=np.array([0.0, 0.0]),
            THI=0.55 * knee,
            KNE=knee,
            TIB=knee + 0.55 * (ank - knee),
            ANK=ank,
            HEE=hee,
            TOE=toe,
        )
        hip_h = max(hip_h, -min(hee[1], toe[1]) + 12.0)
    trunk = {"SHO": (-20.0, 520.0), "ASI": (95.0, 85.0), "PSI": (-105.0, 110.0)}
    for side in ("R", "L"):
        sign = 1.0 if side == "R" else -1.0
        for site in SITES:
            fw, up = trunk[site] if site in trunk else legs[side][site]
            out[MARKER_INDEX[f"{side}_{site}"]] = (x0 + speed * t + fw, sign * LATERAL[site], up)
    out[:, 2] += hip_h
    return out


@dataclass
class Walk:
    """A synthetic walk: per frame the Markers3D and the marker index of each blob."""

    frames: list[Markers3D]
    truth: list[np.ndarray]  # per frame (N,) marker index of each blob, -1 = stray
    near: list[str]


def synthetic_walk(
    seed: int = 0,
    frames_per_pass: int = 80,
    gap: int = 10,
    noise_mm: float = 2.0,
    occlude: dict[int, list[str]] | None = None,
    trial: str = "walk-01",
    static: bool = False,
    facing: int = 1,
) -> Walk:
    """Out (right side to the camera) and back (left side), with two static strays.

    Parameters
    ----------
    seed : noise seed.
    frames_per_pass : frames per pass at 30 fps.
    gap : frames between the passes with nobody in view (the turn, out of view).
    noise_mm : position noise per axis.
    occlude : frame index -> marker names hidden in that frame (e.g. an arm over R_HIP).
    trial : trial name of the messages.
    static : a standing pose (the static trial) instead of a walk.
    facing : for ``static``, the way the subject faces (+1: toward +a, right side near).
    """
    rng = np.random.default_rng(seed)
    cam = Camera()
    occlude = occlude or {}
    strays = np.array([[500.0, 1500.0, 1300.0], [3500.0, 900.0, 300.0]])
    frames, truth, nears = [], [], []
    one = [("R", 1)] if facing > 0 else [("L", -1)]
    passes = one if static else [("R", 1), ("L", -1)]
    k = 0
    speed = 0.0 if static else 1200.0
    for pi, (near, direction) in enumerate(passes):
        if pi:
            k += gap
        for j in range(frames_per_pass):
            t = j / 30.0
            body = pose(t, 300.0 if direction > 0 else -300.0, speed, standing=static)
            q = np.empty((20, 3))
            # Body frame -> floor: forward = direction * a; the right side faces the camera
            # walking toward +a (e = -lateral).
            start_a = 400.0 if direction > 0 else 2 * HALF_LENGTH - 400.0
            q[:, 0] = start_a + direction * body[:, 0]
            q[:, 1] = -direction * body[:, 1]
            q[:, 2] = body[:, 2]
            seen = [
                i
                for i, n in enumerate(MARKER_NAMES)
                if (n[0] == near or n[2:] in FAR_SEEN) and n not in occlude.get(k, [])
            ]
            pts = np.vstack([q[seen], strays])
            ids = np.array([*seen, -1, -1])
            order = rng.permutation(len(pts))
            pts, ids = pts[order], ids[order]
            cam_pts = to_camera(pts) + rng.normal(0.0, noise_mm, pts.shape)
            pix = cam.project(cam_pts)
            pos = np.repeat(cam_pts[:, None, :], 3, axis=1)
            n = len(pts)
            hdr = Markers3D.make_header(
                "cam0",
                trial,
                k,
                int(k * 1e9 / 30),
                last=(pi == len(passes) - 1) and j == frames_per_pass - 1,
            )
            frames.append(
                Markers3D(
                    header=hdr,
                    centroid=pix,
                    marker_radius=np.full(n, 2.0),
                    region_radius=np.full(n, 3.0),
                    depth=pos[:, :, 2],
                    position=pos,
                    threshold=60000.0,
                )
            )
            truth.append(ids)
            nears.append(near)
            k += 1
    return Walk(frames, truth, nears)


# --- evaluation on simulated sessions ---------------------------------------------------

DEFAULT_TRIALS = (
    ("bz_HC002D_straight_HC002D06", 1),
    ("c3dorg_s00_vicon_CGM24", 2),
    ("btk_PiG_Motion-FlatFoot-Full", 2),
    ("btk_PiG_Motion3_FF", 2),
    ("btk_c3dorg_sample04_Matt", 2),
)
UPSTREAM = ("calibrate", "clean", "detect", "locate")


def upstream_messages(trial: str, seed: int, jobs: int = 2) -> tuple[list[Any], list[Any]]:
    """Simulate a quick session and run it through calibrate .. locate inline.

    Returns ``(messages, truths)``: the calibration record and every ``markers`` message in
    protocol order (what model and label read), and the GroundTruth of the walking frames
    (for scoring only; it never enters a stage).
    """
    from gaitflow.commands.demo import rendered_frames
    from gaitflow.markers import trial_kind
    from gaitflow.stages.graph import load
    from gaitflow.stages.inline import InlinePipeline

    msgs: list[Any] = []
    truths: list[Any] = []

    def sink(stream: str, msg: Any) -> None:
        if stream in ("calibration", "markers"):
            msgs.append(msg)

    pipe = InlinePipeline(load(), stages=UPSTREAM, sink=sink)
    _, frames = rendered_frames(trial, seed, True, jobs, with_truth=True)
    for raw, truth in frames:
        if trial_kind(raw.header.trial) == "walk":
            truths.append(truth)
        pipe.push(raw)
    pipe.finish()
    return msgs, truths


def label_session(
    msgs: list[Any], params: Mapping[str, Any] | None = None
) -> tuple[list[Any], float]:
    """Run model and label on cached upstream messages; (labelled messages, s per frame)."""
    from gaitflow.stages.graph import load
    from gaitflow.stages.inline import InlinePipeline

    out: list[Any] = []
    pipe = InlinePipeline(
        load(),
        stages=("model", "label"),
        params={"label": dict(params or {})},
        sink=lambda s, m: out.append(m) if s == "labelled" else None,
    )
    t0 = time.perf_counter()
    for m in msgs:
        pipe.push(m)
    pipe.finish()
    return out, (time.perf_counter() - t0) / max(1, len(out))


def _cached(trial: str, seed: int, cache: str | None, jobs: int) -> tuple[list[Any], list[Any]]:
    if not cache:
        return upstream_messages(trial, seed, jobs)
    path = Path(cache) / f"{trial}_{seed}.pkl"
    if path.exists():
        with path.open("rb") as f:
            return pickle.load(f)
    res = upstream_messages(trial, seed, jobs)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump(res, f)
    return res


def main(argv: list[str] | None = None) -> int:
    """``python -m gaitflow.evaluate_label``: labelling accuracy/recall per simulated trial."""
    p = argparse.ArgumentParser(prog="python -m gaitflow.evaluate_label", description=main.__doc__)
    p.add_argument(
        "--trials",
        nargs="*",
        default=[f"{t}:{s}" for t, s in DEFAULT_TRIALS],
        help="trial[:seed] of gaitflow.sim (default: five bundled trials)",
    )
    p.add_argument("--jobs", type=int, default=2, help="render worker processes")
    p.add_argument(
        "--cache",
        default=None,
        help="directory caching the upstream (calibrate..locate) output per trial and seed",
    )
    p.add_argument("--param", action="append", default=[], help="label parameter NAME=VALUE")
    p.add_argument("--markers", action="store_true", help="print per-marker recall/precision")
    args = p.parse_args(argv)
    params: dict[str, Any] = {}
    for kv in args.param:
        k, _, v = kv.partition("=")
        params[k] = yaml.safe_load(v)  # typed as in pipeline.yaml
    rows = []
    for spec in args.trials:
        trial, _, seed = spec.partition(":")
        msgs, truths = _cached(trial, int(seed or 1), args.cache, args.jobs)
        labelled, dt = label_session(msgs, params)
        r = score_labelling(labelled, truths)
        rows.append((f"{trial}:{seed or 1}", r, dt))
        if args.markers:
            for name in MARKER_NAMES:
                if name in r["per_marker_recall"] or name in r["per_marker_precision"]:
                    print(
                        f"  {name:6s} recall {r['per_marker_recall'].get(name, np.nan):5.2f}"
                        f"  precision {r['per_marker_precision'].get(name, np.nan):5.2f}"
                    )
    hdr = f"{'trial':38s} {'frames':>6s} {'acc':>6s} {'acc_gait':>8s} {'prec':>6s} {'recall':>6s}"
    print(hdr + f" {'gait_rec':>8s} {'ms/frame':>8s}")
    for name, r, dt in rows:
        print(
            f"{name:38s} {r['frames']:6d} {r['accuracy']:6.3f} {r['accuracy_gait']:8.3f} "
            f"{r['precision']:6.3f} {r['recall']:6.3f} {gait_recall(r):8.3f} {1e3 * dt:8.1f}"
        )
    return 0


def gait_recall(r: Mapping[str, Any]) -> float:
    """Mean recall over the near HIP, KNE, ANK, HEE, TOE and far HEE, TOE (what gait uses)."""
    vals = [
        v
        for k, v in r["per_marker_recall"].items()
        if k[2:] in ("HEE", "TOE") or k[2:] in ("HIP", "KNE", "ANK")
    ]
    return float(np.mean(vals)) if vals else float("nan")


if __name__ == "__main__":
    raise SystemExit(main())
