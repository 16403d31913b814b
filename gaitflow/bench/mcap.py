"""``gaitflow bench mcap``: cost of recording raw frames to MCAP per chunk compression.

Writes ``--frames`` synthetic raw frames (512x424 IR + depth, uint16, 868 KB encoded) through
:class:`gaitflow.recording.McapWriter` with each compression, then reads them back, and
reports write and read time per frame (ms), file size per frame and compression ratio.
The frames imitate a Kinect v2 walk: a noisy floor and wall, a person-sized depth region,
IR with sensor noise and a few saturated marker disks. Real frames compress similarly (the
noise in the low bits dominates); the ratio between compressions is what decides the default.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from typing import Any

import numpy as np

from gaitflow.benchutil import add_json_flag, emit, format_table
from gaitflow.progress import add_quiet_flag, progress
from gaitflow.recording import DEFAULT_COMPRESSION, McapWriter, iter_messages
from gaitflow.schemas import RawFrame

# zstd at the library default (3) against a fast level, lz4 and none.
CANDIDATES = ("none", "lz4", "zstd:1", "zstd")  # keep "none" first: it is the baseline
KEY = "gaitflow/bench/cam0/raw"


def synthetic_frames(n_distinct: int = 8, seed: int = 0) -> list[bytes]:
    """Encoded raw frames (424, 512) with Kinect-like noise; fixed seed."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:424, 0:512]
    out = []
    for i in range(n_distinct):
        depth = 4500.0 - 6.0 * np.clip(rows - 200, 0, None)  # wall, then the floor
        cx = 120 + 30 * i
        person = ((cols - cx) / 45.0) ** 2 + ((rows - 230) / 170.0) ** 2 < 1.0
        depth[person] = 2500.0 + 0.5 * (cols[person] - cx)
        depth += rng.normal(0.0, 4.0, depth.shape)
        depth[rng.random(depth.shape) < 0.02] = 0.0  # invalid pixels
        ir = 300.0 + 0.5 * rows + rng.normal(0.0, 40.0, rows.shape)
        ir[person] += 400.0
        for _ in range(20):
            u, v = rng.integers(0, 512), rng.integers(0, 424)
            ir[(cols - u) ** 2 + (rows - v) ** 2 < 16] = 65535.0
        hdr = RawFrame.make_header("cam0", "walk-01", i, time.time_ns())
        msg = RawFrame(
            header=hdr,
            ir=np.clip(ir, 0, 65535).astype(np.uint16),
            depth=np.clip(depth, 0, 65535).astype(np.uint16),
        )
        out.append(msg.encode())
    return out


def measure(compression: str, frames: list[bytes], n: int, path: str) -> dict[str, float]:
    """Write ``n`` frames with ``compression`` then read them back; times per frame."""
    t0 = time.perf_counter()
    with McapWriter(path, compression=compression, flush_interval_s=None) as w:
        for i in range(n):
            w.write(KEY, frames[i % len(frames)], i * 33_333_333, i * 33_333_333)
    t_write = time.perf_counter() - t0
    size = os.path.getsize(path)
    t0 = time.perf_counter()
    count = sum(1 for _ in iter_messages(path))
    t_read = time.perf_counter() - t0
    if count != n:
        raise RuntimeError(f"{compression}: read {count} of {n} frames back")
    raw = sum(len(frames[i % len(frames)]) for i in range(n))
    return {
        "write_ms_per_frame": t_write / n * 1e3,
        "read_ms_per_frame": t_read / n * 1e3,
        "mb_per_frame": size / n / 1e6,
        "ratio": raw / size,
    }


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "mcap",
        help="MCAP write/read cost per raw frame for each chunk compression",
        description=__doc__,
        epilog="Example: gaitflow bench mcap --frames 120 --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--frames", type=int, default=90, help="raw frames per compression")
    p.add_argument(
        "--compressions",
        nargs="+",
        default=list(CANDIDATES),
        metavar="C",
        help=f"compressions to compare (default {' '.join(CANDIDATES)})",
    )
    add_json_flag(p)
    add_quiet_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    frames = synthetic_frames()
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="gaitflow-bench-mcap-") as tmp:
        for c in progress(args.compressions, desc="bench mcap", unit="codec", quiet=args.quiet):
            results[c] = measure(c, frames, args.frames, os.path.join(tmp, "bench.mcap"))
    figures = {
        "frames": args.frames,
        "frame_bytes": len(frames[0]),
        "default": DEFAULT_COMPRESSION,
        "budget_ms": 33.3,
        "compressions": results,
    }
    if "none" in results:
        base = results["none"]["write_ms_per_frame"]
        for r in results.values():
            r["compress_ms_per_frame"] = r["write_ms_per_frame"] - base
    rows = [
        [
            c,
            r["write_ms_per_frame"],
            r.get("compress_ms_per_frame", float("nan")),
            r["read_ms_per_frame"],
            r["mb_per_frame"],
            r["ratio"],
            "<- default" if c == DEFAULT_COMPRESSION else "",
        ]
        for c, r in results.items()
    ]
    title = (
        f"MCAP cost per raw frame ({len(frames[0]) / 1e3:.0f} KB encoded, "
        f"{args.frames} frames each; camera budget 33.3 ms/frame)"
    )
    cols = ["compression", "write ms", "of it compress", "read ms", "MB/frame", "ratio", ""]
    emit(args, figures, [format_table(title, cols, rows)])
    return 0
