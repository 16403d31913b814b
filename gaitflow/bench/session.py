"""``gaitflow bench session``: session-folder write and read speed (16-bit PNG frames).

Frames come from the simulator (a stretch of a quick walking trial) so the PNGs compress
like real Kinect v2 frames; ``--synthetic`` uses random-noise frames instead (the worst
case for PNG) and needs no simulator. Writes are timed with several PNG settings,
reads with one and two decoder threads; "decode" is PNG decoding from memory alone, i.e.
the ceiling of a reader whose file system costs nothing.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gaitflow.benchutil import add_json_flag, emit, format_table
from gaitflow.camera import Camera
from gaitflow.session import (
    DEFAULT_PNG_COMPRESSION,
    DEFAULT_PNG_STRATEGY,
    SessionReader,
    SessionWriter,
)

Frames = list[tuple[int, int, np.ndarray, np.ndarray]]


def sim_frames(n: int, seed: int = 0) -> tuple[Frames, dict[str, Any]]:
    """``n`` consecutive simulated walking frames and the session's camera.json."""
    from gaitflow.sim import list_trials
    from gaitflow.sim.config import SimConfig
    from gaitflow.sim.session import simulate_session

    ses = simulate_session(list_trials()[0], seed, SimConfig.quick())
    rec = ses.recordings["walk-01"]
    # Start a third of the way in, where the subject is in view.
    start = min(len(rec) // 3, max(0, len(rec) - n))
    out: Frames = []
    for k in range(start, min(len(rec), start + n)):
        raw, _truth = rec.frame(k)
        out.append((raw.header.frame, raw.header.capture_ns, raw.ir, raw.depth))
    return out, dict(ses.camera_json)


def synthetic_frames(n: int, seed: int = 0) -> tuple[Frames, dict[str, Any]]:
    """``n`` random frames of Kinect v2 size: incompressible, the PNG worst case."""
    rng = np.random.default_rng(seed)
    cam = Camera()
    shape = (cam.height, cam.width)
    out = [
        (
            i,
            i * 33_333_333,
            rng.integers(0, 65536, shape, dtype=np.uint16),
            rng.integers(500, 4500, shape, dtype=np.uint16),
        )
        for i in range(n)
    ]
    return out, cam.to_json()


def _folder_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*.png"))


# (PNG level, zlib strategy): no compression, the default, and zlib's default strategy at
# level 1 and at OpenCV's default level 3 for comparison.
WRITE_CONFIGS = (
    (0, "huffman"),
    (DEFAULT_PNG_COMPRESSION, DEFAULT_PNG_STRATEGY),
    (1, "default"),
    (3, "default"),
)


def run(frames: Frames, doc: dict[str, Any]) -> dict[str, Any]:
    """Time writes (per PNG setting, 1 and 2 threads) and reads; return the figures."""
    n = len(frames)
    configs = WRITE_CONFIGS
    res: dict[str, Any] = {"frames": n, "width": doc["width"], "height": doc["height"]}
    writes = []
    with tempfile.TemporaryDirectory(prefix="gaitflow-bench-session-") as tmp:
        root = Path(tmp)
        for level, strategy in configs:
            for workers in (1, 2):
                folder = root / f"l{level}{strategy}w{workers}"
                w = SessionWriter(
                    folder, doc, compression=level, workers=workers, strategy=strategy
                )
                t0 = time.perf_counter()
                w.write_recording("walk-01", frames)
                dt = time.perf_counter() - t0
                writes.append(
                    {
                        "level": level,
                        "strategy": strategy,
                        "workers": workers,
                        "fps": n / dt,
                        "kib_per_frame": _folder_bytes(folder) / n / 1024,
                    }
                )
        res["write"] = writes
        folder = root / f"l{DEFAULT_PNG_COMPRESSION}{DEFAULT_PNG_STRATEGY}w1"
        reads = []
        for workers in (1, 2):
            r = SessionReader(folder, workers=workers)
            t0 = time.perf_counter()
            got = sum(1 for _ in r.frames("walk-01"))
            dt = time.perf_counter() - t0
            if got != n or r.skipped.total():
                raise RuntimeError(f"read back {got} of {n} frames")  # a bench must not lie
            reads.append({"workers": workers, "fps": n / dt})
        res["read"] = reads
        blobs = [
            (folder / "walk-01" / kind / f"{i:06d}.png").read_bytes()
            for i, *_ in frames
            for kind in ("ir", "depth")
        ]
        t0 = time.perf_counter()
        for b in blobs:
            cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_UNCHANGED)
        res["decode_fps"] = n / (time.perf_counter() - t0)
    res["read_fps"] = reads[0]["fps"]
    res["write_fps"] = next(
        w["fps"]
        for w in writes
        if (w["level"], w["strategy"], w["workers"])
        == (DEFAULT_PNG_COMPRESSION, DEFAULT_PNG_STRATEGY, 1)
    )
    res["realtime_factor_read"] = res["read_fps"] / float(doc.get("fps", 30))
    return res


def _main(args: argparse.Namespace) -> int:
    if args.synthetic:
        frames, doc = synthetic_frames(args.frames)
        res = run(frames, doc)
        res["frames_from"] = "synthetic noise"
    else:
        frames, doc = sim_frames(args.frames)
        res = run(frames, doc)
        res["frames_from"] = "simulator (walk-01, quick protocol, seed 0)"
    write_rows = [
        [w["level"], w["strategy"], w["workers"], w["fps"], w["kib_per_frame"]]
        for w in res["write"]
    ]
    rate = float(doc.get("fps", 30))
    read_rows = [[r["workers"], r["fps"], r["fps"] / rate] for r in res["read"]]
    read_rows.append(["decode only", res["decode_fps"], res["decode_fps"] / rate])
    tables = [
        format_table(
            f"session folder write: {res['frames']} frames {res['width']}x{res['height']} "
            f"from {res['frames_from']}",
            ["png level", "zlib strategy", "threads", "frames/s", "KiB/frame"],
            write_rows,
        ),
        format_table(
            f"session folder read (PNG level {DEFAULT_PNG_COMPRESSION}, {DEFAULT_PNG_STRATEGY})",
            ["threads", "frames/s", "x real time"],
            read_rows,
        ),
    ]
    emit(args, res, tables)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "session",
        help="session-folder read and write speed (16-bit PNG)",
        description=__doc__,
        epilog="Example: gaitflow bench session --frames 60 --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--frames", type=int, default=30, help="frames to write and read (default 30)")
    p.add_argument(
        "--synthetic", action="store_true", help="random-noise frames instead of simulated ones"
    )
    add_json_flag(p)
    p.set_defaults(func=_main)
