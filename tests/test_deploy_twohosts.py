"""Edge and server as two Zenoh "hosts" on one machine, over real Zenoh on 127.0.0.1.

The server side is a router with the generated access-control section, listening on
plain TCP (its own stages) and TLS with mutual authentication (edges). The edge side has
its own loopback router; its uplink is a TLS client of the server router. Between the
two, a loopback TCP relay (:class:`LinkProxy`) stands for the network and can be cut.
Everything binds 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from gaitflow.bus import Bus, BusConfig
from gaitflow.bus.router import Router, free_port, wait_port
from gaitflow.schemas import RawFrame, decode

from gaitflow import deployment
from gaitflow.acl import router_token_key, server_acl
from gaitflow.certs import make_bundle, tls_section
from gaitflow.edgebuffer import Deduper, dedupe
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
        self._quiet = threading.Event()  # a silent cut: bytes vanish, nothing is closed
        self.restore()

    def restore(self) -> None:
        if self._quiet.is_set():
            self.cut()  # the quiet connections are dead: Zenoh's lease closed them
            self._quiet.clear()
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

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := a.recv(65536):
                if not self._quiet.is_set():
                    b.sendall(data)
        for x in (a, b):
            with contextlib.suppress(OSError):
                x.shutdown(socket.SHUT_RDWR)

    def cut(self, silent: bool = False) -> None:
        """Drop every connection and refuse new ones (like a pulled cable + reboot).

        ``silent``: a pulled cable alone, no FIN and no RST: new connections are refused,
        the open ones stay up but every byte on them vanishes until :meth:`restore`, so the
        ends notice only through their lease (Zenoh's ``transport/link/tx/lease``).
        """
        if self._lsock is not None:
            with contextlib.suppress(OSError):
                self._lsock.shutdown(socket.SHUT_RDWR)
            self._lsock.close()
            self._lsock = None
        if silent:
            self._quiet.set()
            return
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


def _spawn(*args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "gaitflow.cli", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL,
    )


@contextlib.contextmanager
def installed(
    tmp_path: Path, camera: str = "cam-1"
) -> Iterator[tuple[deployment.Topology, LinkProxy, Path]]:
    """The installed shape on free 127.0.0.1 ports: ``gaitflow deploy render`` and
    ``gaitflow certs`` into ``tmp_path``, then the server and edge routers and the edge's
    uplink as processes (``gaitflow deploy router`` x2, ``gaitflow deploy uplink``), the
    uplink dialling the server through a :class:`LinkProxy` (the network, cuttable).

    Yields the topology, the relay and the rendered ``roles`` directory.
    """
    ports = [free_port() for _ in range(3)]
    topo = deployment.Topology(
        edges={"edge-1": camera},
        local_port=ports[0],
        edge_local_port=ports[1],
        server_tls_port=ports[2],
        certs_dir=str(tmp_path / "certs"),
        state_dir=str(tmp_path / "state"),
        metrics_base_port=free_port(),
    )
    deployment.write(tmp_path, deployment.render(topo=topo))
    make_bundle(tmp_path / "certs", ["server", "edge-1"])
    roles = tmp_path / "roles"
    # The network between the machines: a relay that can be cut.
    proxy = LinkProxy(topo.server_tls_port)
    edge_doc = yaml.safe_load((roles / "edge-1.yaml").read_text())
    edge_doc["uplink"]["bus"]["connect"] = [f"tls/127.0.0.1:{proxy.port}"]
    (roles / "edge-1.yaml").write_text(yaml.safe_dump(edge_doc))
    procs = [
        _spawn("deploy", "router", str(roles / "server.yaml")),
        _spawn("deploy", "router", str(roles / "edge-1.yaml")),
    ]
    try:
        wait_port(topo.local_endpoint, 30)
        wait_port(topo.edge_local_endpoint, 30)
        procs.append(_spawn("deploy", "uplink", str(roles / "edge-1.yaml")))
        yield topo, proxy, roles
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        proxy.cut()


@pytest.mark.slow
def test_generated_roles_edge_to_server_with_link_cut(tmp_path: Path) -> None:
    """The installed shape: ``gaitflow deploy render`` + ``gaitflow certs`` and the deploy
    processes (server router, edge router, edge uplink). A 225-frame trial at 30 fps goes
    from a grab-like publisher on the edge to a recorder-like subscriber on the server; the
    link is cut for 5 s in the middle. Every frame arrives, in order, backfilled from the
    edge's MCAP ring."""
    got: list[int] = []
    deduper = Deduper()
    server_local = edge_local = None
    with installed(tmp_path) as (topo, proxy, _roles):
        try:
            server_local = Bus(BusConfig(site=SITE, connect=(topo.local_endpoint,)))
            server_local.subscribe(
                f"gaitflow/{SITE}/*/raw",
                dedupe(lambda k, p: got.append(decode(RawFrame, p).header.frame), deduper),
            )
            assert wait_for(
                lambda: server_local.alive(f"gaitflow/{SITE}/@alive/uplink/cam-1", 0.5), 20
            ), "the uplink never reached the server over TLS"
            edge_local = Bus(BusConfig(site=SITE, connect=(topo.edge_local_endpoint,)))
            pub = edge_local.publisher(f"gaitflow/{SITE}/cam-1/raw")
            time.sleep(0.3)
            n, cut_at, restore_at = 225, 45, 195  # 30 fps: cut at 1.5 s for 5 s
            t0 = time.monotonic()
            for i in range(n):
                if i == cut_at:
                    proxy.cut()
                if i == restore_at:
                    during = len(got)
                    proxy.restore()
                pub.put(frame("cam-1", i, last=i == n - 1))
                time.sleep(max(0.0, t0 + (i + 1) / 30 - time.monotonic()))
            assert during <= cut_at, "frames reached the server while the link was cut"
            assert wait_for(lambda: len(got) >= n, 15)
            time.sleep(0.3)
            assert sorted(got) == list(range(n)), f"lost: {sorted(set(range(n)) - set(got))[:20]}"
            assert got == sorted(got), "the backlog must arrive in capture order"
            # The ring is on the edge's disk, under the role's state directory.
            assert list((tmp_path / "state" / "ring" / "cam-1").glob("ring-*.mcap"))
        finally:
            for b in (edge_local, server_local):
                if b is not None:
                    b.close()
