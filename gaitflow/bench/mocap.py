"""``gaitflow bench mocap``: clean, detect and locate on simulated sessions, scored against
the simulator's ground truth and printed beside the paper's Tables II and III.

For each trial, the walk recording is rendered once (its first ``--frames`` frames, so that
the clean stage meets the stray reflectors from the trial's start, as it would live) and
run through the three stage cores twice: with the adaptive threshold (Alg. 1) and with the
static one (the Table II baseline). Ground truth is used here only, to score; no stage sees it.

Scores (per visible truth marker and frame; "visible" = in view and not occluded):

- **detected**: a blob centroid lies within ``--gate`` px (4 px: a marker's own blob; the
  paper does not define it) of the marker's projected centre, matched one-to-one, nearest
  first;
- **recall@beta**: the matched centroid lies within beta px (0.5, 1.5, 2.5);
- **3D error**: distance between the matched blob's position under the marker's own cluster
  mode (``gaitflow.markers.cluster_mode``), as label publishes it (the heels at their
  surface point, ``label.surface_point``), and the true marker centre, mm; also the median
  signed Z error (bias);
- **recall vs mid-exposure truth**: the same against the truth moved to mid-exposure (the
  simulator reports it half a blur sample late, see :func:`truth_lag_frames`);
- **false blobs** per frame: blobs matched to no visible marker;
- **ms/frame** per stage, p50 and p99: CPU time of the one thread running the stages
  (``time.thread_time``; OpenCV threads set to 1), so that time spent waiting for a core
  on a shared machine is not counted; wall time (``time.perf_counter``) of detect, locate,
  detect + locate and all three stages is reported too.
  Single runs; the machine yardstick printed below scales them.

Variants (``--variants``) change the simulator, never the stage parameters: ``base``,
``d20`` / ``d30`` (20 / 30 mm markers), ``near`` / ``far`` (walking line at 2.0 / 3.5 m),
``high`` / ``low`` (camera height and tilt), ``unit2`` (another sensor's intrinsics),
``noisy``, ``slow`` (:mod:`gaitflow.sim.variants`).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import cv2
import numpy as np

from gaitflow.benchutil import add_json_flag, emit, format_table, mean_sd, plus_minus
from gaitflow.errors import ConfigError
from gaitflow.markers import CLUSTER_MODES, MARKER_NAMES, cluster_mode
from gaitflow.params import parse_overrides
from gaitflow.sim.variants import VARIANTS, sim_config, variant_changes
from gaitflow.stages.detect import SPLITTERS, nearest_first_pairs
from gaitflow.stages.label import surface_point

BETAS = (0.5, 1.5, 2.5)
PAPER = {
    "static": {"detected": 91.44, "ms_detect": 0.15},
    "adaptive": {"detected": 98.08, "ms_detect": 1.21},
    "recall_proposed": {0.5: 95.86, 1.5: 97.32, 2.5: 98.04, "ms": 7.72},
    "recall_previous": {0.5: 88.12, 1.5: 90.84, 2.5: 92.10, "ms": 117.53},
}
# Tables II and III give each figure as mean ± SD over the experiments; the SDs.
PAPER_SD = {
    "static": {"detected": 3.52},
    "adaptive": {"detected": 1.08},
    "recall_proposed": {0.5: 1.64, 1.5: 1.75, 2.5: 1.73},
    "recall_previous": {0.5: 2.61, 1.5: 2.67, 2.5: 2.45},
}
SPREAD_KEYS = ("detected", *(f"recall@{b}" for b in BETAS))
# The same figures over the paper's own marker set only (the "12" columns below).
MODEL_KEYS = tuple(f"{k}_12" for k in SPREAD_KEYS)
# Fig. 5's sagittal model, n = 12 (algorithms.md [A-M1]): every site of the side facing the
# camera, and of the far side only the heel and the toe, which show below the near leg.
# The far pelvis markers are its "partially invisible" two, the far leg's lateral markers
# face away.
MODEL_FAR_SITES = ("HEE", "TOE")
NEAR_SIDE_SITES = ("HIP", "THI", "KNE", "TIB", "ANK")
_SIDE = np.array([n.split("_", 1)[0] for n in MARKER_NAMES])
_SITE = np.array([n.split("_", 1)[1] for n in MARKER_NAMES])
_LEG = np.isin(_SITE, NEAR_SIDE_SITES)
GOALS = {"detected": 99.5, "recall@0.5": 97.0, "err_median_mm": 5.0, "ms_detect_locate_p99": 2.0}
MODE_OF = np.array([CLUSTER_MODES.index(cluster_mode(n)) for n in MARKER_NAMES])
HEELS = {MARKER_NAMES.index("L_HEE"), MARKER_NAMES.index("R_HEE")}


@dataclass
class Score:
    """Accumulated figures of one method on one variant."""

    visible: int = 0
    detected: int = 0
    recalled: dict[float, int] = field(default_factory=lambda: dict.fromkeys(BETAS, 0))
    recalled_mid: dict[float, int] = field(default_factory=lambda: dict.fromkeys(BETAS, 0))
    errors: list[float] = field(default_factory=list)
    z_bias: list[float] = field(default_factory=list)
    errors_by_mode: dict[str, list[float]] = field(default_factory=dict)
    errors_by_site: dict[str, list[float]] = field(default_factory=dict)
    false_blobs: int = 0
    missed_merged: int = 0  # missed markers with another visible marker within the gate
    # the same counts over the sagittal model's markers (sagittal_model_markers)
    visible_12: int = 0
    detected_12: int = 0
    recalled_12: dict[float, int] = field(default_factory=lambda: dict.fromkeys(BETAS, 0))
    errors_12: list[float] = field(default_factory=list)
    frames: int = 0
    ms: dict[str, list[float]] = field(default_factory=dict)

    def add_ms(self, stage: str, ms: float) -> None:
        self.ms.setdefault(stage, []).append(ms)


def match(pred: np.ndarray, truth: np.ndarray, gate: float) -> list[tuple[int, int, float]]:
    """One-to-one nearest-first matching of blob centroids (K, 2) to truth pixels (M, 2).

    Returns (blob, truth, distance px) triples with distance <= gate.
    """
    if pred.size == 0 or truth.size == 0:
        return []
    d = np.hypot(pred[:, None, 0] - truth[None, :, 0], pred[:, None, 1] - truth[None, :, 1])
    return [(i, j, float(d[i, j])) for i, j in nearest_first_pairs(d, gate)]


def sagittal_model_markers(position: np.ndarray) -> np.ndarray:
    """The markers of the paper's sagittal model in one frame: (20,) bool from the true
    marker centres (20, 3), camera mm (scoring only).

    The near side is the side whose leg markers (``NEAR_SIDE_SITES``) lie nearer the camera
    (smaller mean Z); its ten sites count, and the far side's ``MODEL_FAR_SITES``. None
    when either side's leg markers are all unknown (no near side to tell).
    """
    z = np.asarray(position, dtype=float).reshape(len(MARKER_NAMES), 3)[:, 2]
    leg_z = {side: z[_LEG & (side == _SIDE)] for side in "LR"}
    leg_z = {side: v[np.isfinite(v)] for side, v in leg_z.items()}
    if not all(v.size for v in leg_z.values()):
        return np.zeros(len(MARKER_NAMES), dtype=bool)
    near = "L" if leg_z["L"].mean() < leg_z["R"].mean() else "R"
    return (near == _SIDE) | np.isin(_SITE, MODEL_FAR_SITES)


def score_frame(
    score: Score, markers: Any, truth: Any, gate: float, mid: np.ndarray | None = None
) -> None:
    """Add one frame's figures (``markers``: Markers3D, ``truth``: GroundTruth; ``mid``:
    (20, 2) truth pixels at mid-exposure, for the second recall figure)."""
    vis = np.asarray(truth.visible) & np.isfinite(truth.pixel).all(axis=1)
    tidx = np.flatnonzero(vis)
    pred = np.asarray(markers.centroid).reshape(-1, 2)
    pairs = match(pred, np.asarray(truth.pixel)[tidx], gate)
    in_model = sagittal_model_markers(truth.position)[tidx]
    score.frames += 1
    score.visible += tidx.size
    score.detected += len(pairs)
    score.visible_12 += int(in_model.sum())
    score.detected_12 += sum(bool(in_model[tj]) for _, tj, _ in pairs)
    score.false_blobs += pred.shape[0] - len(pairs)
    if len(pairs) < tidx.size:
        tp = np.asarray(truth.pixel)[tidx]
        got = {tj for _, tj, _ in pairs}
        for j in range(tidx.size):
            if j not in got:
                d = np.hypot(*(tp - tp[j]).T)
                d[j] = np.inf
                score.missed_merged += int(d.min() <= gate)
    if mid is not None:
        for _, _, dist in match(pred, np.asarray(mid)[tidx], gate):
            for b in BETAS:
                score.recalled_mid[b] += dist <= b
    for bi, tj, dist in pairs:
        for b in BETAS:
            if dist <= b:
                score.recalled[b] += 1
                score.recalled_12[b] += bool(in_model[tj])
        k = int(tidx[tj])
        mode = int(MODE_OF[k])
        p = np.asarray(markers.position)[bi, mode]
        if k in HEELS:
            # as label publishes it (heel_side_on): the heel at its surface point
            p = surface_point(p[None], float(markers.surface_offset_mm))[0]
        if np.isfinite(p).all():
            err = float(np.linalg.norm(p - truth.position[k]))
            score.errors.append(err)
            if in_model[tj]:
                score.errors_12.append(err)
            score.z_bias.append(float(p[2] - truth.position[k, 2]))
            score.errors_by_mode.setdefault(CLUSTER_MODES[mode], []).append(err)
            site = MARKER_NAMES[k].split("_", 1)[1]
            score.errors_by_site.setdefault(site, []).append(err)


def merge_scores(scores: Sequence[Score]) -> Score:
    """One Score holding all of ``scores`` (the trials of one method and variant), field
    by field: counts summed, lists joined in order, dicts of either merged key by key."""

    def join(a: Any, b: Any) -> Any:
        if not isinstance(a, dict):
            return a + b  # counts add, lists concatenate (new lists: the inputs stay as they are)
        merged = dict(a)
        for k, v in b.items():
            merged[k] = join(a[k], v) if k in a else v
        return merged

    out = Score()
    for s in scores:
        for f in fields(Score):
            setattr(out, f.name, join(getattr(out, f.name), getattr(s, f.name)))
    return out


def trial_spread(scores: Sequence[Score]) -> dict[str, float]:
    """Detected % and recall % as Tables II and III give them: mean and sample SD over the
    experiments (here the trials with a visible marker), each trial's own percentage; the
    pooled figures of :func:`summarise` weight each trial by its marker views instead.
    NaN SD with fewer than two trials."""
    per = [summarise(s) for s in scores if s.visible]
    out: dict[str, float] = {}
    for k in SPREAD_KEYS + MODEL_KEYS:
        out[f"{k}_trial_mean"], out[f"{k}_trial_sd"] = mean_sd([r[k] for r in per])
    return out


def _pct(x: Sequence[float], q: float) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def _share(count: int, total: int) -> float:
    """count / total in %, NaN without a total (a trial whose model markers never show)."""
    return 100.0 * count / total if total else float("nan")


def summarise(s: Score) -> dict[str, Any]:
    """The figures of one Score as a flat dict (percentages, mm, ms)."""
    vis = max(s.visible, 1)
    out: dict[str, Any] = {
        "frames": s.frames,
        "visible": s.visible,
        "detected": 100.0 * s.detected / vis,
        **{f"recall@{b}": 100.0 * s.recalled[b] / vis for b in BETAS},
        **{f"recall_mid@{b}": 100.0 * s.recalled_mid[b] / vis for b in BETAS},
        "err_median_mm": _pct(s.errors, 50),
        "err_p95_mm": _pct(s.errors, 95),
        "z_bias_mm": _pct(s.z_bias, 50),
        "located": 100.0 * len(s.errors) / max(s.detected, 1),
        "false_blobs_per_frame": s.false_blobs / max(s.frames, 1),
        "visible_12": s.visible_12,
        "detected_12": _share(s.detected_12, s.visible_12),
        **{f"recall@{b}_12": _share(s.recalled_12[b], s.visible_12) for b in BETAS},
        "err_median_mm_12": _pct(s.errors_12, 50),
        "err_p95_mm_12": _pct(s.errors_12, 95),
        "missed_merged": 100.0 * s.missed_merged / vis,
        "detected_resolvable": 100.0 * s.detected / max(vis - s.missed_merged, 1),
    }
    for m, errs in sorted(s.errors_by_mode.items()):
        out[f"err_median_mm_{m}"] = _pct(errs, 50)
    out["err_median_mm_by_site"] = {k: _pct(v, 50) for k, v in sorted(s.errors_by_site.items())}
    for st, ms in sorted(s.ms.items()):
        out[f"ms_{st}_p50"] = _pct(ms, 50)
        out[f"ms_{st}_p99"] = _pct(ms, 99)
    return out


def render_frames(trial: str, seed: int, variant: str, frames: int, recording: str) -> list:
    """Render the first ``frames`` frames of a recording (all if ``frames`` <= 0).

    Returns (raw, truth, mid-exposure truth pixels, session calibration record) per frame.
    """
    from gaitflow.sim import simulate_session

    cfg = sim_config(variant)
    ses = simulate_session(trial, seed, cfg)
    if recording not in ses.recordings:
        raise ConfigError(f"bench mocap: no recording {recording!r} in trial {trial!r}")
    rec = ses.recordings[recording]
    n = len(rec)
    k = min(frames, n) if frames > 0 else n
    start = 0
    out = [rec.frame(i, last=i == start + k - 1) for i in range(start, start + k)]
    cal = session_record(ses.camera_json)
    lag = truth_lag_frames(cfg)
    mids = mid_exposure_pixels(out, lag)
    return [(raw, truth, mid, cal) for (raw, truth), mid in zip(out, mids, strict=True)]


def session_record(camera_json: dict[str, Any]) -> Any:
    """A calibration record carrying only the session's camera.json, as the pipeline has it.

    The bench does not run the calibrate stage (that is ``gaitflow bench`` of the gait
    application), so w and r_b are absent (NaN) and the stages use their documented
    fallbacks; the camera document gives locate the intrinsics and the marker diameter,
    which a real session folder's camera.json also carries. Nothing here is ground truth.
    """
    from gaitflow.schemas import CalibrationRecord

    return CalibrationRecord(
        header=CalibrationRecord.make_header("cam0", "calibration", 0, 0, last=True),
        floor_pixels=np.zeros((0, 2)),
        floor_points=np.zeros((0, 3)),
        floor_plane=np.full(4, np.nan),
        start=np.full(3, np.nan),
        end=np.full(3, np.nan),
        status="Done",
        camera=dict(camera_json),
    )


def truth_lag_frames(cfg: Any) -> float:
    """How far after mid-exposure the simulator's truth is taken, in frames.

    The simulator samples the exposure at ``blur_samples`` instants centred on the capture
    time and reports the truth at sample ``blur_samples // 2``; for an even count that is
    half a sample interval after mid-exposure (+1.5 ms with the defaults), while a blurred
    blob's centroid is the mid-exposure position. Scoring only; reported separately.
    """
    from gaitflow.sim import truth as sim_truth

    if cfg.blur_samples % 2 or getattr(sim_truth, "TRUTH_AT_MID_EXPOSURE", False):
        # Since the simulator fix, the truth is exactly at mid-exposure: no lag.
        return 0.0
    return 0.5 * cfg.exposure_ms / 1000.0 / cfg.blur_samples * cfg.camera.fps


def mid_exposure_pixels(frames: list, lag: float) -> list[np.ndarray]:
    """Truth pixels moved back by ``lag`` frames along their velocity (central differences
    over neighbouring delivered frames). (20, 2) per frame."""
    pix = np.array([np.asarray(t.pixel) for _, t in frames])
    idx = np.array([r.header.frame for r, _ in frames], dtype=np.float64)
    if len(frames) < 2 or lag == 0.0:
        return list(pix)
    vel = np.gradient(pix, idx, axis=0)
    return list(pix - lag * np.nan_to_num(vel))


# The detect options each ablation row (``adaptive-<name>``) sets over the defaults: the
# sub-pixel refinement on, no splitting of merged blobs, or one splitter alone.
ABLATIONS: dict[str, dict[str, bool]] = {
    "refine": {"refine": True},
    "nosplit": dict.fromkeys(SPLITTERS, False),
    "streak": {"streak_learned": True},
    **{
        name: {s: s == key for s in SPLITTERS}
        for name, key in (
            ("split", "split_merged"),
            ("cores", "split_cores"),
            ("tracked", "split_tracked"),
        )
    },
}


def run_stages(
    frames: list,
    method: str,
    score: Score,
    gate: float,
    ablation: str = "",
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
) -> None:
    """Run clean -> detect -> locate cores on rendered frames and score them.

    ``ablation``: a key of :data:`ABLATIONS` (its detect options over the defaults), or
    empty (the defaults). ``overrides``: per stage, parameter overrides (``--param``); the
    detect keys a row sets (its method and its :data:`ABLATIONS` options) keep the row's
    values.
    """
    from gaitflow.stages import clean, detect, locate

    if ablation and ablation not in ABLATIONS:
        raise ConfigError(f"bench mocap: unknown ablation {ablation!r} (known: {list(ABLATIONS)})")
    ov = dict(overrides or {})
    row = {"method": method, **(ABLATIONS[ablation] if ablation else {})}
    ov["detect"] = {**ov.get("detect", {}), **row}
    state = {k: s.init(s.params.resolve(ov.get(k, {}))) for k, s in _specs().items()}
    clock = time.thread_time  # CPU time of this thread: a shared machine's waits excluded
    wall = time.perf_counter
    for raw, truth, mid, cal in frames:
        w0, t0 = wall(), clock()
        state["clean"], (cf,) = clean.SPEC.step(state["clean"], {"raw": raw, "calibration": cal})
        w1, t1 = wall(), clock()
        state["detect"], (bl,) = detect.SPEC.step(
            state["detect"], {"clean": cf, "calibration": cal}
        )
        w2, t2 = wall(), clock()
        state["locate"], (mk,) = locate.SPEC.step(state["locate"], {"clean": cf, "blobs": bl})
        w3, t3 = wall(), clock()
        score.add_ms("clean", 1e3 * (t1 - t0))
        score.add_ms("detect", 1e3 * (t2 - t1))
        score.add_ms("locate", 1e3 * (t3 - t2))
        score.add_ms("detect+locate", 1e3 * (t3 - t1))
        score.add_ms("wall_detect", 1e3 * (w2 - w1))
        score.add_ms("wall_locate", 1e3 * (w3 - w2))
        score.add_ms("wall_detect+locate", 1e3 * (w3 - w1))
        score.add_ms("wall_all", 1e3 * (w3 - w0))
        score_frame(score, mk, truth, gate, mid)


def bench(
    trials: Sequence[str],
    frames: int,
    seed: int,
    variants: Sequence[str],
    gate: float,
    recording: str = "walk-01",
    refine_ablation: bool = False,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """Render, run and score; returns {variant: {method: figures}}. ``overrides``: per
    stage, parameter overrides for every method row (see :func:`run_stages`)."""
    cv2.setNumThreads(1)  # "on one core"
    methods = ["adaptive", "static"]
    methods += [f"adaptive-{a}" for a in ABLATIONS] if refine_ablation else []
    results: dict[str, Any] = {}
    for var in variants:
        per_trial: dict[str, list[Score]] = {m: [] for m in methods}
        for trial in trials:
            rendered = render_frames(trial, seed, var, frames, recording)
            for m in methods:
                base, _, extra = m.partition("-")
                per_trial[m].append(Score())
                run_stages(rendered, base, per_trial[m][-1], gate, extra, overrides=overrides)
        results[var] = {
            m: summarise(merge_scores(ss)) | trial_spread(ss) for m, ss in per_trial.items()
        }
    return results


def _specs() -> dict[str, Any]:
    """The three stages the bench runs, by name (their ``SPEC``)."""
    from gaitflow.stages import clean, detect, locate

    return {"clean": clean.SPEC, "detect": detect.SPEC, "locate": locate.SPEC}


def _check_overrides(overrides: Mapping[str, Mapping[str, Any]]) -> None:
    """Fail before any rendering on a stage other than clean, detect and locate, or on a
    parameter the stage does not declare (ParameterError names it)."""
    stages = _specs()
    for name, values in overrides.items():
        if name not in stages:
            raise ConfigError(f"bench mocap: --param stage {name!r} is not clean, detect or locate")
        stages[name].params.resolve(values)


def numpy_op_us() -> float:
    """Cost of one tiny numpy operation now, in us: a yardstick for the machine's load.

    Most of the per-frame time of these stages is small-array overhead, so their ms/frame
    scale with it; an idle modern core gives about 0.5-1 us.
    """
    a = np.zeros(10)
    t = time.perf_counter()
    for _ in range(20000):
        a + 1.0
    return 1e6 * (time.perf_counter() - t) / 20000


def _tables(results: dict[str, Any], trials: Sequence[str]) -> list[str]:
    tables = []
    for var, res in results.items():
        rows = []
        for m, r in res.items():
            rows.append(
                [
                    f"ours {m}",
                    r["detected"],
                    r["recall@0.5"],
                    r["recall@1.5"],
                    r["recall@2.5"],
                    r["err_median_mm"],
                    r["err_p95_mm"],
                    r["ms_detect_p50"],
                    r["ms_detect_p99"],
                    r["ms_detect+locate_p99"],
                ]
            )
        pa, ps = PAPER["adaptive"], PAPER["static"]
        rp, rv = PAPER["recall_proposed"], PAPER["recall_previous"]
        rows.append(["paper Alg.1 (II, III)", pa["detected"], rp[0.5], rp[1.5], rp[2.5]])
        rows[-1] += [None, None, pa["ms_detect"], None, rp["ms"]]
        rows.append(["paper static [25] (II)", ps["detected"], None, None, None])
        rows[-1] += [None, None, ps["ms_detect"], None, None]
        rows.append(["paper previous [25] (III)", None, rv[0.5], rv[1.5], rv[2.5]])
        rows[-1] += [None, None, None, None, rv["ms"]]
        rows.append(["goal", GOALS["detected"], GOALS["recall@0.5"], None, None])
        rows[-1] += [GOALS["err_median_mm"], None, None, None, GOALS["ms_detect_locate_p99"]]
        cols = [
            "method",
            "detected %",
            "recall@0.5 %",
            "@1.5 %",
            "@2.5 %",
            "3D med mm",
            "3D p95 mm",
            "detect p50 ms",
            "detect p99 ms",
            "det+loc p99 ms",
        ]
        tables.append(format_table(f"mocap, variant {var}, trials {', '.join(trials)}", cols, rows))
        rows2 = []
        for m, r in res.items():
            rows2.append(
                [
                    f"ours {m}",
                    r["frames"],
                    r["visible"],
                    r["false_blobs_per_frame"],
                    r["missed_merged"],
                    r["detected_resolvable"],
                    r["recall_mid@0.5"],
                    r["recall_mid@1.5"],
                    r["located"],
                    r["z_bias_mm"],
                    r.get("err_median_mm_normal"),
                    r.get("err_median_mm_top"),
                    r.get("err_median_mm_bottom"),
                    r["ms_clean_p50"],
                    r["ms_locate_p50"],
                    r["ms_locate_p99"],
                    r["ms_detect+locate_p50"],
                    r["ms_wall_detect_p50"],
                    r["ms_wall_detect_p99"],
                    r["ms_wall_locate_p50"],
                    r["ms_wall_locate_p99"],
                    r["ms_wall_detect+locate_p99"],
                    r["ms_wall_all_p50"],
                    r["ms_wall_all_p99"],
                ]
            )
        cols2 = [
            "method",
            "frames",
            "visible",
            "false/frame",
            "missed merged %",
            "detected resolvable %",
            "recall@0.5 mid-exp %",
            "@1.5 mid-exp %",
            "located %",
            "Z bias mm",
            "med normal",
            "med top",
            "med bottom",
            "clean p50 ms",
            "locate p50 ms",
            "locate p99 ms",
            "det+loc p50 ms",
            "wall detect p50",
            "wall detect p99",
            "wall locate p50",
            "wall locate p99",
            "wall det+loc p99",
            "wall 3 stages p50",
            "wall p99",
        ]
        tables.append(format_table(f"details, variant {var}", cols2, rows2))

        rows_sd = [
            [f"ours {m}"]
            + [plus_minus(r[f"{k}_trial_mean"], r[f"{k}_trial_sd"]) for k in SPREAD_KEYS]
            for m, r in res.items()
            if m in ("adaptive", "static")
        ]
        for label, det, rec in (
            ("paper Alg.1 (II, III)", "adaptive", "recall_proposed"),
            ("paper static [25] (II)", "static", None),
            ("paper previous [25] (III)", None, "recall_previous"),
        ):
            row = [
                label,
                plus_minus(PAPER[det]["detected"], PAPER_SD[det]["detected"]) if det else "-",
            ]
            row += [plus_minus(PAPER[rec][b], PAPER_SD[rec][b]) if rec else "-" for b in BETAS]
            rows_sd.append(row)
        cols_sd = ["method", "detected %", *(f"recall@{b} %" for b in BETAS)]
        tables.append(
            format_table(
                f"as Tables II and III give them: mean ± SD over trials, variant {var}",
                cols_sd,
                rows_sd,
            )
        )
        tables.append(_model_table(var, res))
        sites = list(dict.fromkeys(n.split("_", 1)[1] for n in MARKER_NAMES))
        rows3 = [
            [f"ours {m}"] + [r["err_median_mm_by_site"].get(s) for s in sites]
            for m, r in res.items()
        ]
        cols3 = ["3D median mm by site", *(f"{s} ({cluster_mode('L_' + s)})" for s in sites)]
        tables.append(format_table(f"3D error by marker site, variant {var}", cols3, rows3))
    return tables


def _model_table(var: str, res: dict[str, Any]) -> str:
    """Detected and recall over the paper's own marker set (:func:`sagittal_model_markers`),
    pooled and as mean ± SD over trials, beside Tables II and III and the goals."""
    rows: list[list[Any]] = []
    for m, r in res.items():
        rows.append([f"ours {m}", r["visible_12"], r["detected_12"]])
        rows[-1] += [r[f"recall@{b}_12"] for b in BETAS]
        rows[-1] += [r["err_median_mm_12"], r["err_p95_mm_12"]]
        rows[-1] += [plus_minus(r[f"{k}_trial_mean"], r[f"{k}_trial_sd"]) for k in MODEL_KEYS]
    pa, rp = PAPER["adaptive"], PAPER["recall_proposed"]
    sa, sp = PAPER_SD["adaptive"], PAPER_SD["recall_proposed"]
    rows.append(["paper Alg.1 (II, III)", None, pa["detected"], *(rp[b] for b in BETAS)])
    rows[-1] += ["-", "-", plus_minus(pa["detected"], sa["detected"])]
    rows[-1] += [plus_minus(rp[b], sp[b]) for b in BETAS]
    rows.append(["goal", None, GOALS["detected"], GOALS["recall@0.5"], None, None])
    rows[-1] += [GOALS["err_median_mm"], "-", *["-"] * len(MODEL_KEYS)]
    cols = ["method", "views", "detected %", *(f"recall@{b} %" for b in BETAS)]
    cols += ["3D med mm", "3D p95 mm"]
    cols += ["detected, trials", *(f"@{b}, trials" for b in BETAS)]
    title = (
        f"the paper's marker set (Fig. 5, n = 12: the near side's ten, the far heel and toe), "
        f"variant {var}"
    )
    return format_table(title, cols, rows)


def _run(args: argparse.Namespace) -> int:
    from gaitflow.sim import list_trials

    available = list_trials()
    trials = available if args.all else (args.trials or available[:1])
    for t in trials:
        if t not in available:
            raise ConfigError(f"bench mocap: unknown trial {t!r} (bundled: {available})")
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    for v in variants:
        variant_changes(v)  # names it if unknown, before any trial runs
    overrides = parse_overrides(args.param)
    _check_overrides(overrides)
    t0 = time.perf_counter()
    op_us = numpy_op_us()
    results = bench(
        trials,
        args.frames,
        args.seed,
        variants,
        args.gate,
        refine_ablation=args.ablation,
        overrides=overrides,
    )
    figures = {
        "trials": list(trials),
        "frames_per_trial": args.frames,
        "seed": args.seed,
        "params": overrides,
        "results": results,
        "paper": {k: {str(a): b for a, b in v.items()} for k, v in PAPER.items()},
        "paper_sd": {k: {str(a): b for a, b in v.items()} for k, v in PAPER_SD.items()},
        "goals": GOALS,
        "wall_s": time.perf_counter() - t0,
        "numpy_op_us": op_us,
    }
    tables = _tables(results, trials)
    tables.append(f"machine yardstick: one tiny numpy op = {op_us:.2f} us (idle core: ~0.5-1)")
    emit(args, figures, tables)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "mocap",
        help="clean/detect/locate accuracy and speed vs the paper's Tables II-III",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  gaitflow bench mocap\n  gaitflow bench mocap --all --frames 0\n"
        "  gaitflow bench mocap --variants base,d20,d30,near,far --json",
    )
    p.add_argument("--trials", nargs="+", help="bundled trial ids (default: the first one)")
    p.add_argument("--all", action="store_true", help="every bundled trial")
    p.add_argument("--frames", type=int, default=90, help="first frames of each walk (0 = all)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument(
        "--variants",
        default="base",
        help=f"comma list of {list(VARIANTS)}; join names with + to combine set-ups",
    )
    p.add_argument("--gate", type=float, default=4.0, help="matching gate, px")
    p.add_argument(
        "--ablation",
        action="store_true",
        help="also run adaptive with the sub-pixel refinement, without splitting merged blobs, "
        "and with each way of splitting them alone (split_merged, split_cores, split_tracked)",
    )
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="STAGE.NAME=VALUE",
        help="a clean, detect or locate parameter override for every method row, e.g. "
        "detect.step6_saturated_only=true (a row's own method and ablation keys win)",
    )
    add_json_flag(p)
    p.set_defaults(func=_run)
