"""The edge ring, the server-side de-duplication and the uplink's backfill (in memory)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import FakeBus
from gaitflow.schemas import RawFrame, decode

from gaitflow.acl import router_token_key
from gaitflow.edgebuffer import Deduper, Ring, StageWatcher, Uplink, dedupe
from gaitflow.errors import BusError, ConfigError
from gaitflow.recording import iter_messages

SITE = "clinic"
KEY = f"gaitflow/{SITE}/cam-1/raw"


def frame(i: int, camera: str = "cam-1", trial: str = "walk-01") -> bytes:
    z = np.full((2, 3), i, np.uint16)
    return RawFrame(header=RawFrame.make_header(camera, trial, i, 1000 + i), ir=z, depth=z).encode()


def dedup_server() -> tuple[FakeBus, list[int], Deduper, object]:
    """A server bus that records the raw frame indices it receives, duplicates dropped,
    with its router's liveliness token up."""
    server = FakeBus()
    received: list[int] = []
    d = Deduper()
    server.subscribe(
        f"gaitflow/{SITE}/*/raw",
        dedupe(lambda k, p: received.append(decode(RawFrame, p).header.frame), d),
    )
    return server, received, d, server.liveliness_token(router_token_key(SITE))


def test_ring_reads_back_in_order_across_segments(tmp_path: Path) -> None:
    ring = Ring(tmp_path, segment_messages=4)
    payloads = [frame(i) for i in range(10)]
    for i, p in enumerate(payloads):
        assert ring.append(KEY, p) == i
    got = [(s, decode(RawFrame, p).header.frame) for s, _, p in ring.read_from(3)]
    assert got == [(i, i) for i in range(3, 10)]
    # Closed segments are complete MCAP files with the payload byte for byte.
    segs = sorted(tmp_path.glob("ring-*.mcap"))
    assert len(segs) == 3  # two closed, one open
    assert [m.payload for m in iter_messages(segs[1])] == payloads[4:8]
    ring.close()


def test_ring_evicts_oldest_and_counts(tmp_path: Path) -> None:
    one = len(frame(0))
    ring = Ring(tmp_path, segment_messages=2, max_bytes=3 * 2 * one)
    for i in range(20):
        ring.append(KEY, frame(i))
    assert ring.evicted > 0
    assert ring.first_seq == ring.evicted
    seqs = [s for s, _, _ in ring.read_from(0)]
    assert seqs == list(range(ring.first_seq, 20))
    ring.close()


def test_deduper_keeps_first_copy_per_camera_trial_frame_stream() -> None:
    d = Deduper()
    seen: list[int] = []
    cb = dedupe(lambda k, p: seen.append(decode(RawFrame, p).header.frame), d)
    for i in (0, 1, 1, 2, 0, 3):
        cb(KEY, frame(i))
    cb(KEY, frame(1, camera="cam-2"))  # another camera's frame 1 is not a duplicate
    cb(KEY, frame(1, trial="walk-02"))
    assert seen == [0, 1, 2, 3, 1, 1]
    assert d.duplicates == 2
    assert d.first(b"\x00not msgpack") is True
    assert d.unreadable == 1


class FlakyLink:
    """A remote session over FakeBus whose link can die silently (puts vanish)."""

    def __init__(self, net_bus: FakeBus) -> None:
        self.bus = net_bus.connected()
        self.dead = False
        self.vanished = 0

    def put(self, key: str, payload: bytes) -> None:
        if self.dead:
            self.vanished += 1
            return
        self.bus.put(key, payload)

    def __getattr__(self, name: str):  # watch_liveliness, liveliness_token, close
        return getattr(self.bus, name)


def _wait(cond, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.005)
    return bool(cond())


def test_uplink_backfills_after_silent_link_loss(tmp_path: Path) -> None:
    server, received, d, token = dedup_server()
    attempts = {"n": 0}
    link = FlakyLink(server)

    def factory() -> FlakyLink:
        attempts["n"] += 1
        if attempts["n"] == 1:
            raise BusError("router not up yet")
        return link

    local = FakeBus()
    up = Uplink(
        local, factory, SITE, "cam-1", ["raw"], Ring(tmp_path, segment_messages=8),
        router_token_key(SITE), resend_margin_s=5.0,
    ).start()  # fmt: skip
    try:
        assert _wait(lambda: up.link_up)
        for i in range(10):
            local.put(KEY, frame(i))
        assert _wait(lambda: len(received) == 10)
        # The link dies silently: frames 10..14 are sent into the void before the
        # router's token is seen to vanish.
        link.dead = True
        for i in range(10, 15):
            local.put(KEY, frame(i))
        assert _wait(lambda: up.backlog == 0)
        token.undeclare()
        assert _wait(lambda: not up.link_up)
        for i in range(15, 40):  # recorded to the ring only
            local.put(KEY, frame(i))
        assert len(received) == 10
        link.dead = False
        token = server.liveliness_token(router_token_key(SITE))
        assert _wait(lambda: len(received) == 40)
        assert received == list(range(40))
        assert link.vanished == 5
        assert up.stats.resent >= 5 and d.duplicates == up.stats.resent - 5
        assert up.stats.link_downs == 1
    finally:
        up.stop()
        token.undeclare()


def test_uplink_needs_streams(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        Uplink(FakeBus(), FakeBus, SITE, "cam-1", [], Ring(tmp_path), router_token_key(SITE))


def test_watcher_exports_stage_up_from_liveliness() -> None:
    bus = FakeBus()
    w = StageWatcher(bus.connected(), SITE, [("grab", 0), ("detect", 0)])
    assert w.value("grab") == 0 and w.value("detect") == 0
    tok = bus.liveliness_token(f"gaitflow/{SITE}/@alive/grab/0")
    assert w.value("grab") == 1 and w.value("detect") == 0
    tok.undeclare()
    assert w.value("grab") == 0


class SlowLink(FlakyLink):
    """A server that takes 50 ms per frame (a slow consumer behind a blocking link)."""

    def put(self, key: str, payload: bytes) -> None:
        time.sleep(0.05)
        super().put(key, payload)


def test_slow_server_never_blocks_the_edge(tmp_path: Path) -> None:
    server = FakeBus()
    received: list[int] = []
    server.subscribe(
        f"gaitflow/{SITE}/*/raw", lambda k, p: received.append(decode(RawFrame, p).header.frame)
    )
    token = server.liveliness_token(router_token_key(SITE))
    local = FakeBus()
    up = Uplink(
        local, lambda: SlowLink(server), SITE, "cam-1", ["raw"], Ring(tmp_path),
        router_token_key(SITE),
    ).start()  # fmt: skip
    try:
        assert _wait(lambda: up.link_up)
        payloads = [frame(i) for i in range(30)]
        t = time.perf_counter()
        for p in payloads:
            local.put(KEY, p)  # what grab's publisher waits for: the uplink's callback
        spent = time.perf_counter() - t
        # Blocking on the server would take 30 x 50 ms = 1.5 s.
        assert spent < 0.5, f"the edge waited {spent * 1e3:.0f} ms on a slow server"
        assert up.backlog > 0  # the ring absorbed what the server could not take yet
        assert _wait(lambda: len(received) == 30, 10)
        assert received == list(range(30))
    finally:
        up.stop()
        token.undeclare()


def test_ring_survives_a_restart_and_a_crash(tmp_path: Path) -> None:
    payloads = [frame(i) for i in range(14)]
    ring = Ring(tmp_path, segment_messages=4)
    for p in payloads[:10]:
        ring.append(KEY, p)
    ring.close()  # a clean stop: two closed segments and a finished open one
    again = Ring(tmp_path, segment_messages=4)
    assert (again.first_seq, again.next_seq) == (0, 10)
    for p in payloads[10:13]:
        again.append(KEY, p)
    # A crash: the writer is never closed; the open segment has no footer.
    crashed = Ring(tmp_path, segment_messages=4)
    assert crashed.next_seq == 13
    assert [p for _, _, p in crashed.read_from(0)] == payloads[:13]
    assert crashed.append(KEY, payloads[13]) == 13
    crashed.close()
    again.close()


def test_uplink_restart_forwards_the_backlog_of_the_previous_run(tmp_path: Path) -> None:
    server, received, _d, token = dedup_server()
    local = FakeBus()

    def uplink() -> Uplink:
        ring = Ring(tmp_path, segment_messages=4)
        return Uplink(
            local, lambda: FlakyLink(server), SITE, "cam-1", ["raw"], ring, router_token_key(SITE)
        ).start()

    first = uplink()
    assert _wait(lambda: first.link_up)
    for i in range(10):
        local.put(KEY, frame(i))
    assert _wait(lambda: len(received) == 10)
    token.undeclare()  # the link goes down; the edge keeps recording
    assert _wait(lambda: not first.link_up)
    for i in range(10, 25):
        local.put(KEY, frame(i))
    first.stop()  # ... and then the uplink process is restarted
    token = server.liveliness_token(router_token_key(SITE))
    second = uplink()
    try:
        assert _wait(lambda: len(received) == 25)
        assert received == list(range(25))
        assert second.stats.received == 0  # all of it came from the first run's ring
    finally:
        second.stop()
        token.undeclare()
