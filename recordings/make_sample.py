"""Regenerate ``recordings/sample.mcap``, the small recording committed for tests and docs.

    python -m gaitflow.recordings.make_sample [--out recordings/sample.mcap]

What it holds: the ``raw`` and ``truth`` streams of the simulator's first walking trial
(quick protocol, bundled trial ``SAMPLE_TRIAL``, seed 0) as ``gaitflow record`` would have
written them from a ``grab source=sim`` stage: one MCAP channel per bus key
``gaitflow/clinic/cam0/<stream>``, msgpack payloads, log time = capture time.

One departure from a live recording, to fit a few seconds in a few megabytes: the
simulator's per-pixel sensor noise (IR read and shot noise, depth noise) is switched off.
Every other effect stays (saturated marker blobs over depth holes, flying and invalid edge
pixels, motion blur, arm occlusion, dropped frames, timing jitter). Noise-free frames
repeat the static background exactly, which zstd finds across the frames of a chunk: about
15 KiB per frame instead of about 450 KiB with noise.

The output is deterministic: payload publish times are set to the capture times, chunks
close by size only, and the simulator is deterministic per seed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

SAMPLE_TRIAL = "bz_HC002D_straight_HC002D06"
SAMPLE_SEED = 0
# zstd's slowest level and large chunks: the file is written once and read often. Level 22
# with 64 MB chunks makes the walk 4.4 MB instead of 5.1 MB at level 19 with 32 MB chunks,
# for minutes instead of seconds of compression.
SAMPLE_COMPRESSION = "zstd:22"
SAMPLE_CHUNK_BYTES = 64 << 20
KEY = "gaitflow/clinic/cam0/{stream}"


def sample_config():
    """The simulator configuration of the sample: quick protocol, no per-pixel noise."""
    from gaitflow.sim.config import SimConfig

    return SimConfig.quick(ir_read_noise=0.0, ir_shot_noise=0.0, depth_noise_scale=0.0)


def make_sample(out: Path, recording: str = "walk-01", max_frames: int = 0) -> int:
    """Write the sample MCAP; return the number of frames written."""
    from gaitflow.recording import McapWriter
    from gaitflow.sim.session import simulate_session

    ses = simulate_session(SAMPLE_TRIAL, SAMPLE_SEED, sample_config())
    rec = ses.recordings[recording]
    n = len(rec) if max_frames <= 0 else min(max_frames, len(rec))
    meta = {
        "generator": "python -m gaitflow.recordings.make_sample",
        "source": "sim",
        "trial": SAMPLE_TRIAL,
        "seed": str(SAMPLE_SEED),
        "recording": recording,
        "sensor_noise": "off",
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    with McapWriter(
        out,
        compression=SAMPLE_COMPRESSION,
        chunk_size=SAMPLE_CHUNK_BYTES,
        flush_interval_s=None,
        metadata=meta,
    ) as w:
        for k in range(n):
            raw, truth = rec.frame(k, last=k == n - 1)
            for msg in (raw, truth):
                ts = msg.header.capture_ns
                w.write(KEY.format(stream=msg.STREAM), msg.encode(publish_ns=ts), ts, ts)
    return n


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gaitflow.recordings.make_sample")
    p.add_argument("--out", type=Path, default=Path(__file__).with_name("sample.mcap"))
    p.add_argument("--recording", default="walk-01", help="simulated recording to write")
    p.add_argument("--max-frames", type=int, default=0, help="cut after this many frames")
    args = p.parse_args(argv)
    n = make_sample(args.out, args.recording, args.max_frames)
    size = args.out.stat().st_size
    print(f"{args.out}: {n} frames, {size / 1e6:.2f} MB ({size / n / 1024:.0f} KiB/frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
