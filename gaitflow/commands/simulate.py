"""``gaitflow simulate TRIAL --out SESSION_DIR``: write a simulated session folder.

The session folder follows ../shared/spec/session-folder.md (camera.json, calibration/,
static/, walk-NN/). Ground truth goes BESIDE the recordings, in ``SESSION_DIR/truth/``:

- ``<recording>.json``: the trial-level summary (:meth:`SimSession.truth_summary`);
- ``<recording>.npz``: per-frame arrays, axis 0 = delivered frames in frames.csv order:
  ``index`` (K,), ``timestamp_ns`` (K,), ``time_s`` (K,), ``position`` (K, 20, 3) camera mm,
  ``pixel`` (K, 20, 2), ``visible`` / ``occluded`` (K, 20) bool, ``knee_flexion`` and
  ``knee_flexion_ref`` (K, 2) deg (L, R), ``marker_names`` (20,).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow.errors import InputError
from gaitflow.sim.variants import variants_help

PREVIEW_PATH = Path("docs/img/sim-preview.png")


def _stretch_ir(ir: np.ndarray) -> np.ndarray:
    """IR to 8 bit: square root, then 1st..99.5th percentile stretch (markers saturate)."""
    x = np.sqrt(ir.astype(np.float64))
    lo, hi = np.percentile(x, [1.0, 99.5])
    return np.clip((x - lo) / max(hi - lo, 1e-6) * 255.0, 0, 255).astype(np.uint8)


def _colour_depth(depth: np.ndarray, lo: float = 500.0, hi: float = 4500.0) -> np.ndarray:
    import cv2

    x = np.clip((depth.astype(np.float64) - lo) / (hi - lo), 0, 1)
    img = cv2.applyColorMap((255 * (1 - x)).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[depth == 0] = 0
    return img


def preview_strip(
    tiles: list[tuple[str, np.ndarray, np.ndarray]], scale: float = 0.6
) -> np.ndarray:
    """A BGR image: one column per (label, ir, depth), IR above depth, scaled by ``scale``."""
    import cv2

    cols = []
    for label, ir, depth in tiles:
        top = cv2.cvtColor(_stretch_ir(ir), cv2.COLOR_GRAY2BGR)
        bot = _colour_depth(depth)
        col = np.vstack([top, bot])
        if scale != 1.0:
            col = cv2.resize(col, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.putText(col, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1)
        cols.append(col)
        cols.append(np.full((col.shape[0], 4, 3), 255, np.uint8))
    return np.hstack(cols[:-1])


def write_session(
    ses: Any,
    out: Path,
    preview: Path | None = None,
    log: Any = print,
    max_frames: int | None = None,
) -> dict:
    """Write every recording with the session writer, the truth files, and a preview.

    ``max_frames`` keeps only the first frames of each recording (quick looks, tests).
    """
    from gaitflow.session import SessionWriter

    writer = SessionWriter(out, ses.camera_json)
    truth_dir = out / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    tiles: list[tuple[str, np.ndarray, np.ndarray]] = []
    stats = {}
    for name, rec in ses.recordings.items():
        rows: dict[str, list] = {
            k: []
            for k in (
                "index",
                "timestamp_ns",
                "time_s",
                "position",
                "pixel",
                "visible",
                "occluded",
                "knee_flexion",
                "knee_flexion_ref",
            )
        }
        n_total = len(rec) if max_frames is None else min(len(rec), max_frames)
        picks = _preview_picks(name, rec, max_frames) if preview is not None else set()

        def frames(
            rec: Any = rec,
            rows: dict = rows,
            picks: set = picks,
            name: str = name,
            n_total: int = n_total,
        ):
            for k in range(n_total):
                raw, gt = rec.frame(k, last=k == len(rec) - 1)
                rows["index"].append(raw.header.frame)
                rows["timestamp_ns"].append(raw.header.capture_ns)
                rows["time_s"].append(gt.time_s)
                for key in ("position", "pixel", "visible", "occluded", "knee_flexion"):
                    rows[key].append(np.asarray(getattr(gt, key)))
                rows["knee_flexion_ref"].append(np.asarray(gt.knee_flexion_ref, dtype=float))
                if k in picks:
                    tiles.append((f"{name} t={gt.time_s:.1f}s", raw.ir, raw.depth))
                yield raw.header.frame, raw.header.capture_ns, raw.ir, raw.depth

        t0 = time.perf_counter()
        n = writer.write_recording(name, frames())
        dt = time.perf_counter() - t0
        np.savez_compressed(
            truth_dir / f"{name}.npz",
            marker_names=np.array(ses.truth_summary(name)["marker_names"]),
            **{k: np.array(v) for k, v in rows.items()},
        )
        (truth_dir / f"{name}.json").write_text(
            json.dumps(ses.truth_summary(name), indent=1, default=float) + "\n"
        )
        stats[name] = {"frames": n, "seconds": dt}
        log(f"{name}: {n}/{n_total} frames in {dt:.1f} s")
    if preview is not None and tiles:
        import cv2

        preview.parent.mkdir(parents=True, exist_ok=True)
        strip = preview_strip(tiles)
        if not cv2.imwrite(str(preview), strip, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
            raise InputError(preview, "could not write the preview PNG")
        log(f"preview: {preview}")
    return stats


def _preview_picks(name: str, rec: Any, max_frames: int | None) -> set[int]:
    """Frames worth showing: the last calibration frame, mid static, walk passes."""
    n = len(rec) if max_frames is None else min(len(rec), max_frames)
    if name == "calibration":
        return {n - 1}
    if name == "static":
        return {n // 2}
    if name != "walk-01":
        return set()
    m = rec.motion
    times = []
    for p, fracs in zip(m.passes, ((0.3, 0.7), (0.5,)), strict=True):
        for f in fracs:
            times.append(m.time_at(p, f * m.src_dur))
    idx = {int(np.argmin(np.abs(rec.times.time_s - t))) for t in times}
    return {k for k in idx if k < n}


def run(args: argparse.Namespace) -> int:
    from gaitflow.sim.session import simulate_session
    from gaitflow.sim.variants import sim_config

    # the benches' named set-ups (camera, distance, markers, subject), as session folders
    cfg = sim_config(args.variant, quick=args.quick).with_(n_walks=args.walks)
    ses = simulate_session(args.trial, seed=args.seed, config=cfg)
    preview = None
    if args.preview:
        preview = Path(args.preview_path) if args.preview_path else args.out / "preview.png"
    write_session(ses, args.out, preview, max_frames=args.max_frames)
    if args.preview and not args.preview_path:
        print(f"(copy it to {PREVIEW_PATH} for the README)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a Kinect v2 session folder from a bundled real walking trial",
        description="Render a calibration sequence, a static pose and walking trials from a "
        "real motion-capture trial, and write them as a session folder "
        "(camera.json, calibration/, static/, walk-NN/) with ground truth in truth/.",
        epilog="Example: gaitflow simulate btk_PiG_Motion-FlatFoot-Full --out out/S01 --preview\n"
        "         gaitflow simulate btk_PiG_Motion3_FF --out out/C01 --variant child",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("trial", help="bundled trial id (see: gaitflow simulate --list)")
    p.add_argument("--out", type=Path, required=True, help="session folder to write")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--walks", type=int, default=1, help="number of walking trials")
    p.add_argument("--quick", action="store_true", help="short calibration and static parts")
    p.add_argument(
        "--variant",
        default="base",
        metavar="NAME[+NAME...]",
        help="a named set-up of `gaitflow bench gait --variant` (default base; join names "
        "with + to combine them, e.g. child+far+noisy): " + variants_help(skip_base=True),
    )
    p.add_argument(
        "--max-frames", type=int, default=None, help="keep only the first N frames of each"
    )
    p.add_argument("--preview", action="store_true", help="also write a PNG strip")
    p.add_argument("--preview-path", default=None, help="where to write the preview PNG")
    p.set_defaults(func=run)
