"""``gaitflow bench pipeline --cameras N``: the real pipeline at 30 fps per camera.

Every stage runs as its own process (``gaitflow run``'s :class:`Launcher`, a router on
``tcp/127.0.0.1:<free port>``). A feeder in this process stands for the cameras: it replays
one simulated session (calibration, static and walking trials, rendered once with
``--seed``) for each of N cameras, each with its own camera id, paced at 30 fps per camera,
with every header re-stamped (camera id, ``capture_ns`` = the moment it is published).
Camera i starts 7 i frames after camera 0, so the cameras are not in lock-step.

Two scopes (``--scope``):

- ``server`` (default; the deploy goal): the server role alone (model, label, gait). The
  feeder publishes what the edges would forward (calibration and per-frame markers, made
  once by running the edge stages in-process), so N cameras share one server;
- ``all``: the whole pipeline on this machine (calibrate, clean, detect, locate, model,
  label, gait), fed raw frames; grab's work is the feeder's.

**End-to-end** time of a walking frame = receipt of its ``gait`` message here minus its
capture time (the feeder's stamp), so it includes every hop and queue. A camera count is
*sustained* when no walking frame's ``gait`` output is missing and p99 <= 33 ms.

**Where the time goes**: each stage's CPU time (``/proc/<pid>/stat``, user + system) per
fed frame, and its processing-time p50/p99 from its own Prometheus histogram (scraped from
127.0.0.1). Figures come from one run on a shared 2-core machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import threading
import time
import urllib.request
from collections.abc import Sequence
from typing import Any

import numpy as np
import yaml

from gaitflow.benchutil import add_json_flag, emit, format_table
from gaitflow.bus import Bus
from gaitflow.bus.keys import stream_key
from gaitflow.bus.router import client_config, local_endpoint
from gaitflow.deployment import (
    RECONNECT,
    REORDER_TIMEOUT_S,
    Topology,
    render_all_in_one,
    render_server,
    stage_config,
)
from gaitflow.errors import ConfigError
from gaitflow.schemas import Message, peek_header

BUDGET_S = 0.033
FPS = 30.0
EDGE_STAGES = ("calibrate", "clean", "detect", "locate")
SERVER_STAGES = ("model", "label", "gait")
STAGGER_FRAMES = 7


def _session(seed: int) -> list[list[Message]]:
    """One simulated session (quick protocol) as grab yields it: a list per camera frame."""
    from gaitflow.stages import grab

    params = grab.SPEC.params.resolve({"source": "sim", "quick": True, "seed": seed})
    return [[m for m in batch if m.STREAM == "raw"] for batch in grab.SPEC.open(params)]


def _reference(frames: list[list[Message]]) -> tuple[list[list[Message]], int]:
    """Run the whole pipeline in-process once.

    Returns, per camera frame, what an edge's uplink forwards to the server stages
    (calibration, markers), and how many walking frames get a ``gait`` message: the count
    every camera must reach on the bus.
    """
    from gaitflow.stages.graph import load
    from gaitflow.stages.inline import InlinePipeline

    graph = load()
    keep = ("calibration", "markers")
    batch: list[Message] = []
    walk_gait: set[tuple[str, int]] = set()

    def sink(stream: str, m: Message) -> None:
        if stream in keep:
            batch.append(m)
        elif stream == "gait" and m.header.trial.startswith("walk"):
            walk_gait.add((m.header.trial, m.header.frame))

    pipe = InlinePipeline(graph, (*EDGE_STAGES, *SERVER_STAGES), sink=sink)
    out: list[list[Message]] = []
    for f in frames:
        for m in f:
            pipe.push(m)
        out.append(batch[:])
        batch.clear()
    pipe.finish()
    if batch:
        out.append(batch[:])
    return [b for b in out if b], len(walk_gait)


def _restamp(m: Message, camera: str, now_ns: int) -> bytes:
    h = dataclasses.replace(m.header, camera=camera, capture_ns=now_ns)
    return dataclasses.replace(m, header=h).encode()


def _cpu_s(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/stat") as f:
            parts = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def _hist_quantiles(url: str, name: str) -> tuple[float, float, float]:
    """(count, p50, p99) of a histogram from a /metrics page (bucket upper edges, s)."""
    from prometheus_client.parser import text_string_to_metric_families

    try:
        with urllib.request.urlopen(url, timeout=2) as r:
            text = r.read().decode()
    except OSError:
        return float("nan"), float("nan"), float("nan")
    buckets: list[tuple[float, float]] = []
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if s.name == name + "_bucket":
                buckets.append((float(s.labels["le"]), s.value))
    buckets.sort()
    if not buckets or buckets[-1][1] == 0:
        return 0.0, float("nan"), float("nan")
    total = buckets[-1][1]

    def q(p: float) -> float:
        for le, c in buckets:
            if c >= p * total:
                return le
        return float("inf")

    return total, q(0.5), q(0.99)


class _Sink:
    """Receives ``gait`` messages; end-to-end time per (camera, frame)."""

    def __init__(self) -> None:
        self.e2e: dict[tuple[str, int], float] = {}
        self.lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        now = time.time_ns()
        h = peek_header(payload)
        if not str(h["trial"]).startswith("walk"):
            return
        with self.lock:
            self.e2e.setdefault((str(h["camera"]), int(h["frame"])), (now - h["capture_ns"]) / 1e9)


def _feed(bus: Bus, site: str, seq: list[list[Message]], cameras: list[str]) -> float:
    """Publish ``seq`` for every camera at 30 fps per camera; return the lag p99 (s).

    Camera i starts ``STAGGER_FRAMES * i`` frames after camera 0: every camera replays the
    same session, and without the offset each stage's heaviest frames (a trial's last
    frame, label's re-initialisations) would hit all cameras in the same frame period,
    which real patients walking in different rooms do not do.
    """
    pubs: dict[str, Any] = {}
    lags = []
    t0 = time.monotonic()
    ticks = len(seq) + STAGGER_FRAMES * (len(cameras) - 1)
    for t in range(ticks):
        due = t0 + t / FPS
        wait = due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        lags.append(time.monotonic() - due)
        for c, cam in enumerate(cameras):
            i = t - STAGGER_FRAMES * c
            if not 0 <= i < len(seq):
                continue
            now = time.time_ns()
            for m in seq[i]:
                key = stream_key(site, cam, m.STREAM)
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = bus.publisher(key, block=True)
                pub.put(_restamp(m, cam, now))
    return float(np.percentile(lags, 99)) if lags else 0.0


def run_once(
    n: int,
    scope: str,
    seq: list[list[Message]],
    expected: int,
    drain_s: float,
    reorder_timeout_s: float,
    workdir: str,
) -> dict[str, Any]:
    """One run with ``n`` cameras; figures and per-stage costs."""
    from gaitflow.stages.graph import load
    from gaitflow.stages.launcher import Launcher

    graph = load()
    stages = SERVER_STAGES if scope == "server" else (*EDGE_STAGES, *SERVER_STAGES)
    ep = local_endpoint()
    cameras = [f"cam-{i + 1}" for i in range(n)]
    sink = _Sink()
    mid = _Sink()
    # The stage config a deployed role gives its stages (gaitflow.deployment), on this run's
    # router.
    bus_doc = {"connect": [ep], "site": graph.site, "extra": {"connect/retry": RECONNECT}}
    cfg = os.path.join(workdir, f"stages-{n}.yaml")
    # The runtime options the deployed role's stage config gives (queue policy, duplicate
    # filter, re-order timeout), from the same generator.
    role = (render_server if scope == "server" else render_all_in_one)(graph, Topology())
    runtime = {**stage_config(role)["runtime"], "reorder_timeout_s": reorder_timeout_s}
    with open(cfg, "w") as f:
        yaml.safe_dump({"bus": bus_doc, "runtime": runtime}, f)
    # The worker processes a server role serving these cameras runs (a label and a gait
    # worker per camera), as `gaitflow deploy render` plans them.
    la = Launcher(
        graph,
        stages=stages,
        endpoint=ep,
        config=cfg,
        stage_metrics=True,
        echo=False,
        cameras=cameras,
    )
    la.start()
    bus: Bus | None = None
    try:
        la.wait_ready(60)
        bus = Bus(client_config(ep, site=graph.site))
        bus.subscribe(f"gaitflow/{graph.site}/*/gait", sink)
        bus.subscribe(f"gaitflow/{graph.site}/*/labelled", mid)
        time.sleep(0.3)
        procs = [c for c in la.children if not c.is_router and c.proc is not None]
        cpu0 = {c.label: _cpu_s(c.proc.pid) for c in procs}  # type: ignore[union-attr]
        t0 = time.monotonic()
        feed_lag = _feed(bus, graph.site, seq, cameras)
        fed_s = time.monotonic() - t0
        deadline = time.monotonic() + drain_s
        while time.monotonic() < deadline and len(sink.e2e) < expected * n:
            time.sleep(0.05)
        wall = time.monotonic() - t0
        cpu1 = {c.label: _cpu_s(c.proc.pid) for c in procs}  # type: ignore[union-attr]
        per_stage = []
        for c in procs:
            count, p50, p99 = _hist_quantiles(
                c.metrics_url or "", "gaitflow_stage_processing_seconds"
            )
            per_stage.append(
                {
                    "stage": c.label,
                    "cpu_s": cpu1[c.label] - cpu0[c.label],
                    "cpu_share": (cpu1[c.label] - cpu0[c.label]) / wall,
                    "frames": count,
                    "p50_ms": p50 * 1e3,
                    "p99_ms": p99 * 1e3,
                    "restarts": c.restarts,
                }
            )
    finally:
        if bus is not None:
            bus.close()
        la.stop()
    e2e = np.array(list(sink.e2e.values())) if sink.e2e else np.array([np.nan])
    lab = np.array(list(mid.e2e.values())) if mid.e2e else np.array([np.nan])
    lost = expected * n - len(sink.e2e)
    p99 = float(np.percentile(e2e, 99)) * 1e3
    return {
        "cameras": n,
        "expected": expected * n,
        "received": len(sink.e2e),
        "lost": lost,
        "e2e_p50_ms": float(np.percentile(e2e, 50)) * 1e3,
        "e2e_p99_ms": p99,
        "e2e_max_ms": float(np.max(e2e)) * 1e3,
        "labelled_p50_ms": float(np.percentile(lab, 50)) * 1e3,
        "labelled_p99_ms": float(np.percentile(lab, 99)) * 1e3,
        "feeder_lag_p99_ms": feed_lag * 1e3,
        "slowest": [
            [cam, frame, round(t * 1e3, 1)]
            for (cam, frame), t in sorted(sink.e2e.items(), key=lambda kv: -kv[1])[:8]
        ],
        "fed_s": fed_s,
        "sustained": bool(lost == 0 and p99 <= BUDGET_S * 1e3),
        "stages": per_stage,
    }


def run_bench(
    cameras: Sequence[int],
    scope: str = "server",
    seed: int = 0,
    drain_s: float = 10.0,
    reorder_timeout_s: float = REORDER_TIMEOUT_S,
) -> dict[str, Any]:
    if scope not in ("server", "all"):
        raise ConfigError(f"bench pipeline: --scope {scope!r} is not server or all")
    frames = _session(seed)
    edge_out, expected = _reference(frames)
    seq = edge_out if scope == "server" else frames
    with tempfile.TemporaryDirectory(prefix="gaitflow-bench-") as work:
        runs = [
            run_once(n, scope, seq, expected, drain_s, reorder_timeout_s, work) for n in cameras
        ]
    ok = [r["cameras"] for r in runs if r["sustained"]]
    return {
        "scope": scope,
        "fps_per_camera": FPS,
        "budget_ms": BUDGET_S * 1e3,
        "walk_frames_per_camera": expected,
        "reorder_timeout_s": reorder_timeout_s,
        "frames_per_camera": len(seq),
        "largest_sustained_cameras": max(ok) if ok else 0,
        "runs": runs,
    }


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "pipeline",
        help="the real pipeline at 30 fps per camera: largest camera count sustained",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example: gaitflow bench pipeline --cameras 1,2,4 --scope server",
    )
    p.add_argument("--cameras", default="1,2,4", help="camera counts to try (comma-separated)")
    p.add_argument("--scope", choices=("server", "all"), default="server")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("--drain-s", type=float, default=10.0, help="wait for outputs after feeding")
    p.add_argument(
        "--reorder-timeout-s",
        type=float,
        default=REORDER_TIMEOUT_S,
        help=f"stages' wait for a missing frame (default {REORDER_TIMEOUT_S}, as deployed)",
    )
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    try:
        cams = [int(c) for c in str(args.cameras).split(",") if c.strip()]
    except ValueError as exc:
        raise ConfigError(f"--cameras {args.cameras!r}: not a list of integers") from exc
    if not cams or min(cams) < 1:
        raise ConfigError(f"--cameras {args.cameras!r}: need camera counts >= 1")
    fig = run_bench(cams, args.scope, args.seed, args.drain_s, args.reorder_timeout_s)
    rows = [
        [
            r["cameras"],
            r["expected"],
            r["lost"],
            r["e2e_p50_ms"],
            r["e2e_p99_ms"],
            r["e2e_max_ms"],
            "yes" if r["sustained"] else "no",
        ]
        for r in fig["runs"]
    ]
    t1 = format_table(
        f"bench pipeline ({fig['scope']} scope, 30 fps per camera, budget 33 ms, reorder "
        f"timeout {fig['reorder_timeout_s'] * 1e3:.0f} ms): largest sustained = "
        f"{fig['largest_sustained_cameras']} camera(s)",
        ["cameras", "walk frames", "lost", "e2e p50 ms", "e2e p99 ms", "max ms", "sustained"],
        rows,
    )
    tables = [t1]
    for r in fig["runs"]:
        srows = [
            [s["stage"], s["cpu_share"] * 100, s["frames"], s["p50_ms"], s["p99_ms"], s["restarts"]]
            for s in sorted(r["stages"], key=lambda s: -s["cpu_s"])
        ]
        tables.append(
            format_table(
                f"where the time goes, {r['cameras']} camera(s) (processing p50/p99 are "
                "histogram bucket edges)",
                ["stage", "cpu % of a core", "frames", "p50 ms", "p99 ms", "restarts"],
                srows,
            )
        )
    emit(args, fig, tables)
    return 0
