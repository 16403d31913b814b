"""Edge and server as two Zenoh "hosts" on one machine, over real Zenoh on 127.0.0.1.

The server side is a router with the generated access-control section, listening on
plain TCP (its own stages) and TLS with mutual authentication (edges). The edge side has
its own loopback router; its uplink is a TLS client of the server router. Between the
two, a loopback TCP relay (:class:`LinkProxy`) stands for the network and can be cut.
Everything binds 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import Bus, BusConfig
from gaitflow.bus.router import Router, free_port
from gaitflow.schemas import RawFrame, decode

from gaitflow.acl import router_token_key, server_acl, uplink_token_key
from gaitflow.certs import make_bundle, tls_section
from gaitflow.edgebuffer import Deduper, Ring, Uplink, dedupe
from gaitflow.errors import BusError

pytestmark = pytest.mark.integration

SITE = "clinic"


class LinkProxy:
    """A TCP relay 127.0.0.1:port -> 127.0.0.1:target that can be cut and restored."""

    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self.port = 0
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()
        self._lsock: socket.socket | None = None
        self.restore()

    def restore(self) -> None:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", self.port))
        s.listen(16)
        self.port = s.getsockname()[1]
        self._lsock = s
        threading.Thread(target=self._accept, args=(s,), daemon=True).start()

    def _accept(self, ls: socket.socket) -> None:
        while True:
            try:
                c, _ = ls.accept()
            except OSError:
                return
            try:
                u = socket.create_connection(self.target)
            except OSError:
                c.close()
                continue
            with self._lock:
                self._conns += [c, u]
            for a, b in ((c, u), (u, c)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(a: socket.socket, b: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                b.sendall(data)
        for x in (a, b):
            with contextlib.suppress(OSError):
                x.shutdown(socket.SHUT_RDWR)

    def cut(self) -> None:
        """Drop every connection and refuse new ones (like a pulled cable + reboot)."""
        if self._lsock is not None:
            with contextlib.suppress(OSError):
                self._lsock.shutdown(socket.SHUT_RDWR)
            self._lsock.close()
            self._lsock = None
        with self._lock:
            conns, self._conns = self._conns, []
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()


class Server:
    """The server side: router (TCP for local stages, TLS for edges, ACL) and its token."""

    def __init__(self, certs: dict, edges: dict[str, str]) -> None:
        self.tcp = f"tcp/127.0.0.1:{free_port()}"
        self.tls_port = free_port()
        acl = server_acl(SITE, edges, edge_stages=["grab"])
        cfg = BusConfig(
            site=SITE, tls=tls_section(certs["server"]), extra=(("access_control", acl),)
        )
        self.router = Router(cfg, listen=(self.tcp, f"tls/127.0.0.1:{self.tls_port}")).start()
        self.token = self.router.session.liveliness().declare_token(router_token_key(SITE))
        self.local = Bus(BusConfig(site=SITE, connect=(self.tcp,)))

    def close(self) -> None:
        self.local.close()
        self.token.undeclare()
        self.router.close()


def edge_cfg(issued: object, port: int, lease_ms: int = 2000) -> BusConfig:
    return BusConfig(
        site=SITE,
        connect=(f"tls/127.0.0.1:{port}",),
        tls=tls_section(issued),  # type: ignore[arg-type]
        extra=(("transport/link/tx/lease", lease_ms),),
    )


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = tmp_path_factory.mktemp("certs")
    good = make_bundle(d / "clinic", ["server", "edge-1", "edge-2"])
    rogue = make_bundle(d / "rogue", ["edge-1"])
    return {**good, "rogue-edge-1": rogue["edge-1"]}


@pytest.fixture
def server(certs: dict) -> Iterator[Server]:
    s = Server(certs, {"edge-1": "cam-1", "edge-2": "cam-2"})
    yield s
    s.close()


def frame(camera: str, i: int, last: bool = False) -> bytes:
    z = np.full((4, 4), i % 65535, np.uint16)
    h = RawFrame.make_header(camera, "walk-01", i, time.time_ns(), last=last)
    return RawFrame(header=h, ir=z, depth=z).encode()


def wait_for(cond, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_tls_pipeline_acl_and_refusal(server: Server, certs: dict) -> None:
    got: list[tuple[str, int]] = []
    server.local.subscribe(
        f"gaitflow/{SITE}/*/raw", lambda k, p: got.append((k, decode(RawFrame, p).header.frame))
    )
    edge = Bus(edge_cfg(certs["edge-1"], server.tls_port))
    try:
        time.sleep(0.3)
        pub = edge.publisher(f"gaitflow/{SITE}/cam-1/raw")
        for i in range(20):
            pub.put(frame("cam-1", i))
        # Edge-1 may publish only cam-1: these must never reach the server.
        for i in range(20):
            edge.put(f"gaitflow/{SITE}/cam-2/raw", frame("cam-2", i))
        assert wait_for(lambda: len(got) >= 20, 5.0)
        time.sleep(0.3)
        assert sorted(f for k, f in got if k.endswith("cam-1/raw")) == list(range(20))
        assert not [k for k, _ in got if "cam-2" in k]
    finally:
        edge.close()
    # A certificate from another CA, and no client certificate at all, are refused.
    with pytest.raises(BusError):
        Bus(edge_cfg(certs["rogue-edge-1"], server.tls_port)).close()
    with pytest.raises(BusError):
        Bus(
            BusConfig(
                site=SITE,
                connect=(f"tls/127.0.0.1:{server.tls_port}",),
                tls={"root_ca_certificate": str(certs["server"].ca)},
            )
        ).close()
    # Plain TCP to the TLS port is not a Zenoh link either.
    with pytest.raises(BusError):
        Bus(BusConfig(site=SITE, connect=(f"tcp/127.0.0.1:{server.tls_port}",))).close()


@pytest.mark.slow
def test_link_cut_mid_trial_is_backfilled(server: Server, certs: dict, tmp_path: Path) -> None:
    received: list[int] = []
    deduper = Deduper()
    server.local.subscribe(
        f"gaitflow/{SITE}/*/raw",
        dedupe(lambda k, p: received.append(decode(RawFrame, p).header.frame), deduper),
    )
    proxy = LinkProxy(server.tls_port)
    # The edge: its own loopback router, a grab-like publisher and the uplink.
    edge_ep = f"tcp/127.0.0.1:{free_port()}"
    edge_router = Router(BusConfig(site=SITE), listen=(edge_ep,)).start()
    grab = Bus(BusConfig(site=SITE, connect=(edge_ep,)))
    local = Bus(BusConfig(site=SITE, connect=(edge_ep,)))
    remote_cfg = edge_cfg(certs["edge-1"], proxy.port)
    uplink = Uplink(
        local,
        lambda: Bus(remote_cfg),
        SITE,
        "cam-1",
        ["raw"],
        Ring(tmp_path / "ring", segment_messages=32),
        router_token_key(SITE),
        uplink_token_key(SITE, "cam-1"),
        resend_margin_s=3.0,
    ).start()
    try:
        assert wait_for(lambda: uplink.link_up, 10.0), "uplink never saw the server"
        pub = grab.publisher(f"gaitflow/{SITE}/cam-1/raw")
        n, cut_at, restore_at = 225, 45, 195  # 30 fps: cut at 1.5 s for 5 s
        t0 = time.monotonic()
        for i in range(n):
            if i == cut_at:
                proxy.cut()
            if i == restore_at:
                during = len(received)
                proxy.restore()
            pub.put(frame("cam-1", i, last=i == n - 1))
            time.sleep(max(0.0, t0 + (i + 1) / 30 - time.monotonic()))
        assert during <= cut_at, "frames reached the server while the link was cut"
        assert uplink.stats.link_downs >= 1
        assert wait_for(lambda: uplink.backlog == 0 and len(received) >= n, 15.0)
        time.sleep(0.3)
        assert sorted(received) == list(range(n)), "a captured frame was lost"
        assert received == sorted(received), "backfill must arrive in capture order"
        assert uplink.stats.evicted_unsent == 0
    finally:
        uplink.stop()
        grab.close()
        local.close()
        edge_router.close()
        proxy.cut()
