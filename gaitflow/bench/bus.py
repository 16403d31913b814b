"""``gaitflow bench bus``: 868 KB raw frames through 1, 3 and 5 relay hops, ours against raw Zenoh.

Each hop is a separate process connected to one ``gaitflow router`` on 127.0.0.1:

- **ours**: ``gaitflow stage relayK`` processes (the full stage runtime in its lossless
  ``block`` policy: decode with the schema class, re-order, driver, core, encode, publish),
  fed by a producer
  that encodes ``RawFrame`` messages and read by a consumer that decodes them;
- **raw** (the floor): minimal Python Zenoh relays that subscribe, take the payload as bytes
  and put the same bytes on the next key; the producer puts pre-built bytes and the consumer
  only reads an index and a timestamp from them. No codec, no queue, no threads of ours.

Throughput: ``--frames`` frames published back to back (congestion control BLOCK, the
relays' queues in ``block`` policy, so nothing is dropped), frames/s from the first put to
the last frame received. Latency: ``--latency-frames`` frames paced at 30 fps (the camera
rate), put-to-receive time p50/p99 through the hops. ``ratio`` is ours/raw cost
(raw throughput / our throughput, and our p50 latency / raw p50 latency).

Figures are from one run on a shared machine: compare the ratios more than the absolutes.
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow.benchutil import add_json_flag, emit, format_table
from gaitflow.bus import Bus
from gaitflow.bus.router import client_config, local_endpoint, wait_port
from gaitflow.schemas import RawFrame, decode
from gaitflow.stages.relay import chain_yaml

SITE = "bench"
GOAL_RATIO = 1.10
GOAL_FPS_3HOPS = 300.0


def _spawn(argv: list[str], log: Path) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with log.open("ab") as out:
        return subprocess.Popen(argv, stdout=out, stderr=out, env=env)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _wait_alive(bus: Bus, n: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while len(bus.alive(f"gaitflow/{SITE}/@alive/**")) < n:
        if time.monotonic() > deadline:
            raise RuntimeError(f"relays not up after {timeout} s")
        time.sleep(0.05)
    time.sleep(0.3)  # let subscriptions settle along the chain


class _Sink:
    """Consumer at the end of the chain: records (index, latency ns) per frame."""

    def __init__(self, ours: bool) -> None:
        self.ours = ours
        self.got: list[tuple[int, int]] = []
        self.last_ns = 0
        self.event = threading.Event()
        self.expect = 0
        self.t_reset = 0

    def __call__(self, key: str, payload: bytes) -> None:
        now = time.time_ns()
        if self.ours:
            h = decode(RawFrame, payload).header
            idx, sent = h.frame, h.capture_ns
        else:
            idx, sent = struct.unpack_from("<qq", payload, 0)
        self.got.append((idx, now - sent))
        self.last_ns = now
        if len(self.got) >= self.expect:
            self.event.set()

    def wait(self, idle_s: float = 3.0) -> None:
        """Until every expected frame arrived, or nothing arrived for ``idle_s``."""
        while not self.event.wait(0.1):
            if time.time_ns() - max(self.last_ns, self.t_reset) > idle_s * 1e9:
                return

    def reset(self, expect: int) -> None:
        self.t_reset = time.time_ns()
        self.got, self.expect = [], expect
        self.event.clear()


def _frames(ours: bool) -> tuple[np.ndarray, np.ndarray, bytes]:
    rng = np.random.default_rng(0)
    ir = rng.integers(0, 65535, (424, 512), dtype=np.uint16)
    depth = rng.integers(500, 8000, (424, 512), dtype=np.uint16)
    hdr = RawFrame.make_header("cam0", "walk-01", 0, 0)
    size = len(RawFrame(header=hdr, ir=ir, depth=depth).encode())
    return ir, depth, bytes(size)


def _payload(
    ours: bool, trial: str, i: int, last: bool, ir: np.ndarray, depth: np.ndarray, raw: bytearray
) -> bytes:
    now = time.time_ns()
    if ours:
        hdr = RawFrame.make_header("cam0", trial, i, now, last)
        return RawFrame(header=hdr, ir=ir, depth=depth).encode()
    struct.pack_into("<qq", raw, 0, i, now)
    return bytes(raw)


def _measure(
    bus: Bus, ours: bool, hops: int, frames: int, lat_frames: int, fps: float
) -> dict[str, Any]:
    """One throughput run and one paced latency run through ``hops`` relays."""
    topic = "raw" if ours else "floor"
    sink = _Sink(ours)
    h = bus.subscribe(f"gaitflow/{SITE}/*/{topic}-{hops}", sink)
    pub = bus.publisher(f"gaitflow/{SITE}/cam0/{topic}-0", block=True)
    ir, depth, blank = _frames(ours)
    raw = bytearray(blank)
    time.sleep(0.1)
    # warm-up: a few frames through the chain
    sink.reset(5)
    for i in range(5):
        pub.put(_payload(ours, "walk-00", i, i == 4, ir, depth, raw))
    sink.wait()
    # throughput, back to back
    sink.reset(frames)
    t0 = time.time_ns()
    for i in range(frames):
        pub.put(_payload(ours, "walk-01", i, i == frames - 1, ir, depth, raw))
    sink.wait()
    got = list(sink.got)
    tput = len(got) / max(1e-9, (sink.last_ns - t0) / 1e9)
    lost = frames - len({g[0] for g in got})
    ordered = [g[0] for g in got] == sorted(g[0] for g in got)
    # latency, paced at the camera rate
    sink.reset(lat_frames)
    t_start = time.perf_counter()
    for i in range(lat_frames):
        wait = t_start + i / fps - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        pub.put(_payload(ours, "walk-02", i, i == lat_frames - 1, ir, depth, raw))
    sink.wait()
    lat = np.array([g[1] for g in sink.got], dtype=np.float64) / 1e6
    lost += lat_frames - len(lat)
    h.undeclare()
    pub.undeclare()
    return {
        "fps": tput,
        "p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "lost": int(lost),
        "ordered": bool(ordered),
    }


def _median(runs: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "fps": float(np.median([r["fps"] for r in runs])),
        "p50_ms": float(np.median([r["p50_ms"] for r in runs])),
        "p99_ms": float(np.median([r["p99_ms"] for r in runs])),
        "lost": int(sum(r["lost"] for r in runs)),
        "ordered": all(r["ordered"] for r in runs),
        "runs": len(runs),
    }


def run_bench(
    frames: int = 300,
    latency_frames: int = 60,
    hops: tuple[int, ...] = (1, 3, 5),
    shm: str = "auto",
    fps: float = 30.0,
    repeat: int = 3,
    log_dir: Path | None = None,
) -> dict[str, Any]:
    """Run the benchmark; return the figures (see the module docstring).

    For each hop count both relay chains run side by side (idle while the other is
    measured) and the raw and our runs alternate ``repeat`` times; figures are medians,
    so a burst of load from elsewhere on the machine hits both variants alike.
    """
    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="gaitflow-bench-bus-") as tmp:
        d = Path(log_dir or tmp)
        log = d / "bench-bus.log"
        cfg = d / "bench-bus.yaml"
        extra = (
            ""
            if shm == "auto"
            else f"  extra: {{transport/shared_memory/enabled: {str(shm == 'on').lower()}}}\n"
        )
        cfg.write_text(
            f"bus:\n  site: {SITE}\n{extra}runtime:\n  queue_policy: block\n  shm: '{shm}'\n"
        )
        ep = local_endpoint()
        router = _spawn(
            [py, "-m", "gaitflow.cli", "router", "--listen", ep, "--config", str(cfg)], log
        )
        results: dict[str, Any] = {}
        try:
            wait_port(ep, 30)
            bus = Bus(client_config(ep, site=SITE), shm=shm)
            try:
                for h in hops:
                    graph = d / f"graph-{h}.yaml"
                    graph.write_text(chain_yaml(SITE, h, source_topic="raw-0"))
                    argv = [
                        [py, "-m", "gaitflow.cli", "stage", f"relay{k}", "--graph",
                         str(graph), "--config", str(cfg), "--connect", ep]
                        for k in range(1, h + 1)
                    ] + [
                        [py, "-m", "gaitflow.bench.bus", ep, f"floor-{k - 1}", f"floor-{k}",
                         str(k), shm]
                        for k in range(1, h + 1)
                    ]  # fmt: skip
                    procs = [_spawn(a, log) for a in argv]
                    runs: dict[str, list[dict[str, Any]]] = {"raw": [], "ours": []}
                    try:
                        _wait_alive(bus, 2 * h)
                        for _ in range(repeat):
                            for variant in ("raw", "ours"):
                                runs[variant].append(
                                    _measure(bus, variant == "ours", h, frames, latency_frames, fps)
                                )
                    finally:
                        _stop(procs)
                    row: dict[str, Any] = {k: _median(v) for k, v in runs.items()}
                    row["ratio_cost"] = row["raw"]["fps"] / row["ours"]["fps"]
                    row["ratio_p50"] = row["ours"]["p50_ms"] / row["raw"]["p50_ms"]
                    results[str(h)] = row
            finally:
                bus.close()
        finally:
            _stop([router])
    three = results.get("3")
    return {
        "frame_bytes": len(_frames(True)[2]),
        "frames": frames,
        "latency_frames": latency_frames,
        "latency_rate_fps": fps,
        "repeat": repeat,
        "shm": shm,
        "hops": results,
        "goals": {
            "ratio_max": GOAL_RATIO,
            "fps_3hops_min": GOAL_FPS_3HOPS,
            "ratio_met": all(r["ratio_cost"] <= GOAL_RATIO for r in results.values()),
            "fps_3hops_met": None if three is None else three["ours"]["fps"] >= GOAL_FPS_3HOPS,
        },
    }


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bus",
        help="868 KB frames through 1/3/5 relay processes: ours vs raw Zenoh",
        description=__doc__,
        epilog="Example: gaitflow bench bus --frames 300 --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--frames", type=int, default=300, help="frames for the throughput run")
    p.add_argument(
        "--latency-frames", type=int, default=60, help="frames for the 30 fps latency run"
    )
    p.add_argument("--hops", default="1,3,5", help="comma-separated hop counts")
    p.add_argument(
        "--shm",
        choices=("auto", "off", "on"),
        default="auto",
        help="Zenoh shared memory in every session (auto = Zenoh's default)",
    )
    p.add_argument("--repeat", type=int, default=3, help="alternating runs per variant (median)")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    hops = tuple(int(h) for h in args.hops.split(","))
    fig = run_bench(args.frames, args.latency_frames, hops, args.shm, repeat=args.repeat)
    rows = []
    for h, r in fig["hops"].items():
        rows.append(
            [
                h,
                r["raw"]["fps"],
                r["ours"]["fps"],
                r["ratio_cost"],
                r["raw"]["p50_ms"],
                r["ours"]["p50_ms"],
                r["raw"]["p99_ms"],
                r["ours"]["p99_ms"],
                r["ours"]["lost"] + r["raw"]["lost"],
            ]
        )
    g = fig["goals"]
    title = (
        f"bus: {fig['frame_bytes']} B frames, {fig['frames']} back to back, "
        f"latency at {fig['latency_rate_fps']:.0f} fps, shm={fig['shm']}, "
        f"median of {fig['repeat']} alternating runs"
    )
    cols = [
        "hops", "raw fps", "our fps", "our/raw cost", "raw p50 ms", "our p50 ms",
        "raw p99 ms", "our p99 ms", "lost",
    ]  # fmt: skip
    goals = (
        f"goals: our/raw <= {g['ratio_max']}: {'met' if g['ratio_met'] else 'NOT met'}; "
        f">= {g['fps_3hops_min']:.0f} fps through 3 hops: "
        f"{'-' if g['fps_3hops_met'] is None else 'met' if g['fps_3hops_met'] else 'NOT met'}"
    )
    emit(args, fig, [format_table(title, cols, rows) + "\n" + goals])
    return 0


def _raw_relay(endpoint: str, src: str, dst: str, index: str, shm: str) -> None:
    """The floor: subscribe, take the bytes, put them on the next key. No codec."""
    import signal

    bus = Bus(client_config(endpoint, site=SITE), shm=shm)
    pub = bus.publisher(f"gaitflow/{SITE}/cam0/{dst}", block=True)
    bus.subscribe(f"gaitflow/{SITE}/*/{src}", lambda k, p: pub.put(p))
    bus.liveliness_token(f"gaitflow/{SITE}/@alive/floor-relay/{index}")
    stop = threading.Event()
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, lambda *a: stop.set())
    stop.wait()
    bus.close()


if __name__ == "__main__":
    _raw_relay(*sys.argv[1:6])
