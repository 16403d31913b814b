"""A 5 s link cut mid-trial, and the server's *results* still cover every frame.

The deployed shape on 127.0.0.1: the server's router (``gaitflow deploy router``, TLS +
access control) with the server-role stages (model, label, gait) as processes under the
launcher, as ``gaitflow run --role server --no-router --config server.stages.yaml`` starts
them (the generated stage config, e.g. the 20 ms re-order timeout); the edge's router and
its uplink (``gaitflow deploy router`` / ``gaitflow deploy uplink edge-1.yaml``); between
the two a TCP relay standing for the network (``LinkProxy``), cut for 5 s in the middle of
the walking trial: with a reset, or silently (a pulled cable, noticed through the lease).

On the edge, a publisher stands for the edge stages: it replays, at 30 fps, what an edge
forwards for one camera of a simulated quick session (the calibration record and the
static and walking ``markers``), computed once in-process by the real edge stages on
``gaitflow bench pipeline``'s simulated session (``_session``). Capture stamps are kept:
gait times come from them, so the server's documents can be compared with the in-process
run of the server stages on the same messages.

Checks: every walking frame the reference gives a ``gait`` message gets exactly one from
the server, with the same values; the server's ``summary`` documents (per pass and per
trial) equal the reference's, floats bit for bit; no stage dropped, failed or mis-decoded a
frame, and its re-order gaps are exactly the frame indices the simulator dropped (the
stages' Prometheus counters); the uplink's resends reached the server and were ignored.

What this test found (fixed in the server role's generated stage config): without
``runtime.dedupe`` the resent frames ran through label and gait a second time; with the
runtime's default ``block-then-drop-oldest`` queue the backlog burst lost a frame at gait.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gaitflow.bus import Bus, BusConfig, FakeBus
from gaitflow.bus.keys import stream_key
from gaitflow.schemas import GaitFrame, Message, RawFrame, TrialSummary, decode
from gaitflow.stages import relay
from gaitflow.stages.graph import Node, load
from gaitflow.stages.inline import InlinePipeline, run_inline
from gaitflow.stages.launcher import Launcher
from gaitflow.stages.runtime import RuntimeOptions, StageRuntime
from prometheus_client.parser import text_string_to_metric_families
from test_deploy_twohosts import LinkProxy, installed, wait_for

from gaitflow import deployment
from gaitflow.bench.pipeline import EDGE_STAGES, SERVER_STAGES, _session

SITE = "clinic"
CAMERA = "cam-1"
FPS = 30.0
CUT_S = 5.0
# Cut this many walking frames into the trial (of 286): the cut ends ~1.8 s before the
# trial does, so the backlog and the live frames after it meet at the server.
CUT_AT_WALK_FRAME = 80
# What the edge's uplink forwards that the server stages read.
FORWARDED = ("calibration", "markers")


@dataclasses.dataclass
class Reference:
    seq: list[list[Message]]  # what the edge forwards, per camera frame
    streams: dict[str, list[Message]]  # every message the server stages read or publish
    gait: dict[tuple[str, int], GaitFrame]  # walking frame -> its gait message
    summaries: list[dict[str, Any]]  # results documents, in publication order


def _on_camera(m: Message) -> Message:
    return dataclasses.replace(m, header=dataclasses.replace(m.header, camera=CAMERA))


@functools.cache
def _reference_run(seed: int = 0) -> Reference:
    """The edge stages in-process on the bench's simulated session, then the server stages
    in-process on exactly what the edge forwards: the reference the bus run must reproduce.
    Cached: both cut variants replay the same session."""
    forwarded: list[Message] = []

    def keep(stream: str, m: Message) -> None:
        if stream in FORWARDED:
            forwarded.append(_on_camera(m))

    edge = InlinePipeline(load(), EDGE_STAGES, sink=keep)
    for frame in _session(seed):
        for m in frame:
            edge.push(m)
    edge.finish()
    # One message per camera frame: the calibration record, then a frame's markers.
    seq = [[m] for m in forwarded]
    out = run_inline(load(), forwarded, stages=SERVER_STAGES)
    # Through the codec, as the bus delivers them (msgpack keeps float64 bit for bit).
    gait = {
        (m.header.trial, m.header.frame): decode(GaitFrame, m.encode())
        for m in out.get("gait", [])
        if m.header.trial.startswith("walk")
    }
    summaries = [decode(TrialSummary, m.encode()).results for m in out.get("summary", [])]
    streams = {**out, "markers": [m for b in seq for m in b if m.STREAM == "markers"]}
    return Reference(seq, streams, gait, summaries)


def _same(a: Any, b: Any, where: str = "results") -> list[str]:
    """Paths where two decoded documents differ (NaN equals NaN; floats compared exactly)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{where}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in _same(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            return [f"{where}: length {len(a)} != {len(b)}"]
        pairs = enumerate(zip(a, b, strict=True))
        return [d for i, (x, y) in pairs for d in _same(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b and type(a) is type(b) else [f"{where}: {a!r} != {b!r}"]


def _counters(url: str) -> dict[tuple[str, str], float]:
    """(sample name, reason label) -> value of a stage's /metrics page."""
    with urllib.request.urlopen(url, timeout=5) as r:
        text = r.read().decode()
    return {
        (s.name, s.labels.get("reason", "")): s.value
        for fam in text_string_to_metric_families(text)
        for s in fam.samples
        if s.name.endswith("_total")
    }


class _Results:
    """The server's ``gait`` and ``summary`` messages, as a results consumer sees them."""

    def __init__(self) -> None:
        self.gait: dict[tuple[str, int], list[GaitFrame]] = {}
        self.summaries: list[dict[str, Any]] = []
        self.lock = threading.Lock()

    def on_gait(self, key: str, payload: bytes) -> None:
        m = decode(GaitFrame, payload)
        with self.lock:
            self.gait.setdefault((m.header.trial, m.header.frame), []).append(m)

    def on_summary(self, key: str, payload: bytes) -> None:
        m = decode(TrialSummary, payload)
        with self.lock:
            self.summaries.append(m.results)


def _raw(i: int, capture_ns: int, last: bool = False) -> bytes:
    z = np.full((2, 3), i, np.uint16)
    h = RawFrame.make_header(CAMERA, "walk-01", i, capture_ns, last=last)
    return RawFrame(header=h, ir=z, depth=z).encode()


def test_server_runtime_drops_an_uplink_resend_once_taken() -> None:
    """What the server role's ``dedupe`` option is for: after a link drop the uplink resends
    frames the stage already took, from up to ``resend_margin_s`` (5 s) back. Without the
    option the re-order buffer takes a jump that far back for a restarted sequence and the
    stateful core sees those frames twice. A new session's frame with the same trial name
    and index (a new capture time) is not a duplicate."""
    bus = FakeBus()
    node = Node("relay", "gaitflow.stages.relay", ("raw",), ("raw",), topics={"raw": "raw-1"})
    rt = StageRuntime(bus, node, relay.SPEC, {}, RuntimeOptions(dedupe=True)).start()
    key = stream_key(SITE, CAMERA, "raw")
    sent = [_raw(i, 10**9 + i * 33_333_333) for i in range(60)]
    for p in sent[:50]:
        bus.put(key, p)
    for p in sent[5:60]:  # the rewind: 45 repeats, then the backlog
        bus.put(key, p)
    bus.put(key, _raw(0, 5 * 10**12))  # the next session's walk-01
    rt.stop()
    out = [decode(RawFrame, p) for k, p in bus.published if k.endswith("/raw-1")]
    assert [m.header.frame for m in out] == [*range(60), 0]
    dup = rt.metrics.registry.get_sample_value(
        "gaitflow_stage_duplicates_total", {"stage": "relay", "worker": "0"}
    )
    assert dup == 45


@pytest.fixture
def deployed(tmp_path: Path) -> Iterator[tuple[deployment.Topology, LinkProxy, Path]]:
    """Rendered roles and certificates; server and edge routers and the uplink running."""
    with installed(tmp_path, CAMERA) as d:
        yield d


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.parametrize("cut", ["reset", "silent"])
def test_link_cut_mid_walk_server_results_backfilled(
    deployed: tuple[deployment.Topology, LinkProxy, Path], cut: str
) -> None:
    """``reset``: the relay closes its connections (the server's switch rebooting), seen at
    once. ``silent``: a pulled cable, no FIN or RST, seen only through the 3 s lease, so
    what the uplink put meanwhile is lost in flight and comes back by its rewind."""
    topo, proxy, roles = deployed
    graph = load()
    # The server role's stages, as `gaitflow run --role server --no-router` starts them.
    la = Launcher(
        graph,
        role="server",
        endpoint=topo.local_endpoint,
        router=False,
        config=roles / "server.stages.yaml",
        stage_metrics=True,
        echo=False,
    )
    la.start()
    server = edge = None
    try:
        # While the processes start: the session is rendered and run in-process once for
        # both cuts (~27 s on this 2-core machine at load average 12).
        ref = _reference_run()
        assert len(ref.gait) > 200 and ref.summaries, "the reference run found no gait"
        la.wait_ready(60)
        res = _Results()
        server = Bus(BusConfig(site=SITE, connect=(topo.local_endpoint,)))
        server.subscribe(f"gaitflow/{SITE}/*/gait", res.on_gait)
        server.subscribe(f"gaitflow/{SITE}/*/summary", res.on_summary)
        assert wait_for(lambda: server.alive(f"gaitflow/{SITE}/@alive/uplink/{CAMERA}", 0.5), 30), (
            "the uplink never reached the server over TLS"
        )
        edge = Bus(BusConfig(site=SITE, connect=(topo.edge_local_endpoint,)))
        pubs = {s: edge.publisher(stream_key(SITE, CAMERA, s)) for s in FORWARDED}
        time.sleep(0.3)
        first_walk = next(i for i, b in enumerate(ref.seq) if b[0].header.trial.startswith("walk"))
        cut_at = first_walk + CUT_AT_WALK_FRAME
        restore_at = cut_at + int(CUT_S * FPS)
        assert restore_at < len(ref.seq) - 30, "the cut must end inside the walking trial"
        during = -1
        t0 = time.monotonic()
        for i, batch in enumerate(ref.seq):
            if i == cut_at:
                proxy.cut(silent=cut == "silent")
            if i == restore_at:
                with res.lock:
                    during = len(res.gait)
                proxy.restore()
            for m in batch:
                pubs[m.STREAM].put(m.encode())
            time.sleep(max(0.0, t0 + (i + 1) / FPS - time.monotonic()))
        n_trial = sum(1 for d in ref.summaries if d.get("scope") == "trial")
        done = wait_for(
            lambda: (
                len(res.gait) >= len(ref.gait)
                and sum(1 for d in res.summaries if d.get("scope") == "trial") >= n_trial
            ),
            60,
        )
        time.sleep(0.5)  # anything late (a duplicate) would show now
        stage_urls = {c.name: c.metrics_url for c in la.children if not c.is_router}
        counters = {name: _counters(url) for name, url in stage_urls.items() if url}
    finally:
        for b in (edge, server):
            if b is not None:
                b.close()
        la.stop()

    diag = {n: {k: v for k, v in c.items() if v and "dropped" in k[0]} for n, c in counters.items()}
    # Nothing after the cut reached the server until the link came back.
    assert during <= CUT_AT_WALK_FRAME, f"{during} gait results before the restore"
    # (1) Every walking frame has its gait message, once, equal to the reference's.
    missing = sorted(set(ref.gait) - set(res.gait))
    assert done and not missing, (
        f"{len(missing)} walking frames without gait: {missing[:10]}; drops {diag}"
    )
    assert set(res.gait) == set(ref.gait), "gait for frames the reference has none for"
    twice = sorted(k for k, v in res.gait.items() if len(v) > 1)
    assert not twice, f"gait published more than once for {twice[:10]}"
    for k, ms in res.gait.items():
        m, r = ms[0], ref.gait[k]
        diff = _same(
            [m.knee_flexion.tolist(), m.heel_height.tolist(), m.toe_height.tolist(), m.time_s],
            [r.knee_flexion.tolist(), r.heel_height.tolist(), r.toe_height.tolist(), r.time_s],
            f"gait{k}",
        )
        diff += _same(m.events, r.events, f"gait{k}.events")
        assert not diff, diff[:5]
    # (2) The summaries (each pass, then the trial) equal the reference's documents.
    assert len(res.summaries) == len(ref.summaries)
    for got, want in zip(res.summaries, ref.summaries, strict=True):
        diff = _same(got, want)
        assert not diff, diff[:10]
    # (3) No stage dropped, failed or mis-decoded a frame. The uplink resent what it had
    # sent just before it saw the link drop (it cannot know what arrived): the stages
    # ignore those repeats (counted as duplicates, not drops: nothing is lost). A stage
    # skips only frame indices that never existed (the simulator drops ~1 % of frames; the
    # reference has the same gaps).
    for node in graph.nodes:
        if node.name not in SERVER_STAGES:
            continue
        c = counters[node.name]
        total = {k: v for k, v in c.items() if v}
        for name in ("errors", "frames_malformed"):
            assert not c.get((f"gaitflow_stage_{name}_total", ""), 0), f"{node.name}: {total}"
        for reason in ("queue", "late", "join"):
            assert not c.get(("gaitflow_stage_frames_dropped_total", reason), 0), (
                f"{node.name}: dropped ({reason}): {total}"
            )
        gaps = c.get(("gaitflow_stage_reorder_gaps_total", ""), 0)
        assert gaps == _index_gaps(ref, node.inputs), f"{node.name}: {total}"
    resent = counters["label"].get(("gaitflow_stage_duplicates_total", ""), 0)
    assert resent > 0, "the uplink resent nothing: the cut was not seen as a link drop"
    sent_before_cut = sum(len(b) for b in ref.seq[:cut_at])
    if cut == "silent":
        # Seen only after the lease: the rewind (5 s back from then) starts after the
        # session's first messages, and what it resent beyond the repeats had been lost.
        assert resent < sent_before_cut, f"{resent} repeats: the cut was not silent"


def _index_gaps(ref: Reference, streams: tuple[str, ...]) -> int:
    """Frame indices missing from the reference's sequences of ``streams`` (from 0, as the
    re-order buffer counts them)."""
    n = 0
    for s in streams:
        frames: dict[str, set[int]] = {}
        for m in ref.streams.get(s, []):
            frames.setdefault(m.header.trial, set()).add(m.header.frame)
        n += sum(max(f) + 1 - len(f) for f in frames.values())
    return n
