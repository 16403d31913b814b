"""Edge and server in two network namespaces joined by a veth pair (created and removed here).

The server namespace runs the router (TLS with mutual authentication and the generated
access control) and a subscriber standing for the recorder; the edge namespace runs the
uplink with its MCAP ring, fed at 30 fps. The link is cut by taking the edge's veth down
for 5 s mid-trial (no FIN, no RST: the loss is only noticed through Zenoh's lease), then
brought back. Skipped, with the reason, where namespaces cannot be made (not root, no
``ip``, a container without CAP_NET_ADMIN). Traffic stays inside the two namespaces.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from gaitflow.certs import make_bundle

pytestmark = [pytest.mark.integration, pytest.mark.slow]

NET = "10.231.77"
SERVER_IP, EDGE_IP = f"{NET}.1", f"{NET}.2"
PORT = 7448


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


@pytest.fixture
def namespaces() -> Iterator[tuple[str, str]]:
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command: cannot make network namespaces")
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (CAP_NET_ADMIN); the loopback tests cover this")
    tag = uuid.uuid4().hex[:6]
    srv, edge = f"gf-srv-{tag}", f"gf-edge-{tag}"
    made: list[str] = []
    try:
        for ns in (srv, edge):
            r = _ip("netns", "add", ns)
            if r.returncode != 0:
                pytest.skip(f"cannot create a network namespace here: {r.stderr.strip()}")
            made.append(ns)
        steps = [
            ("link", "add", f"v{tag}s", "netns", srv, "type", "veth", "peer", "name", f"v{tag}e",
             "netns", edge),
            ("-n", srv, "addr", "add", f"{SERVER_IP}/24", "dev", f"v{tag}s"),
            ("-n", edge, "addr", "add", f"{EDGE_IP}/24", "dev", f"v{tag}e"),
            ("-n", srv, "link", "set", f"v{tag}s", "up"),
            ("-n", edge, "link", "set", f"v{tag}e", "up"),
            ("-n", srv, "link", "set", "lo", "up"),
            ("-n", edge, "link", "set", "lo", "up"),
        ]  # fmt: skip
        for s in steps:
            r = _ip(*s)
            if r.returncode != 0:
                pytest.skip(f"cannot set up the veth link ({' '.join(s)}): {r.stderr.strip()}")
        yield srv, edge
    finally:
        for ns in made:
            _ip("netns", "del", ns)


SERVER = """
import json, sys, time
from gaitflow.acl import router_token_key, server_acl
from gaitflow.bus import Bus, BusConfig
from gaitflow.bus.router import Router
from gaitflow.certs import Issued, tls_section
from gaitflow.edgebuffer import Deduper, dedupe
from gaitflow.schemas import peek_header
d = sys.argv[1]
iss = Issued("server", d + "/server/cert.pem", d + "/server/key.pem", d + "/server/ca.pem")
acl = server_acl("clinic", {"edge-1": "cam-1"})
cfg = BusConfig(site="clinic", tls=tls_section(iss), extra=(("access_control", acl),
      ("transport/link/tx/lease", 2000)))
r = Router(cfg, listen=("tcp/127.0.0.1:7447", "tls/@IP@:@PORT@")).start()
tok = r.session.liveliness().declare_token(router_token_key("clinic"))
local = Bus(BusConfig(site="clinic", connect=("tcp/127.0.0.1:7447",)))
got = []
dd = Deduper()
local.subscribe("gaitflow/clinic/*/raw", dedupe(
    lambda k, p: got.append([k.split("/")[2], peek_header(p)["frame"]]), dd))
print("ready", flush=True)
sys.stdin.readline()
print(json.dumps({"got": got, "duplicates": dd.duplicates}), flush=True)
local.close(); tok.undeclare(); r.close()
""".replace("@IP@", SERVER_IP).replace("@PORT@", str(PORT))

EDGE = """
import json, sys, time, numpy as np
from gaitflow.acl import router_token_key
from gaitflow.bus import Bus, BusConfig, FakeBus
from gaitflow.certs import Issued, tls_section
from gaitflow.edgebuffer import Ring, Uplink
from gaitflow.schemas import RawFrame
d, ring_dir, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
iss = Issued("edge-1", d + "/edge-1/cert.pem", d + "/edge-1/key.pem", d + "/edge-1/ca.pem")
from gaitflow.deployment import RECONNECT
cfg = BusConfig(site="clinic", connect=("tls/@IP@:@PORT@",), tls=tls_section(iss),
                extra=(("transport/link/tx/lease", 2000), ("connect/retry", RECONNECT)))
local = FakeBus()
ring = Ring(ring_dir, segment_messages=32)
up = Uplink(local, lambda: Bus(cfg), "clinic", "cam-1", ["raw"], ring,
            router_token_key("clinic"), resend_margin_s=4.0).start()
t = time.monotonic()
while not up.link_up and time.monotonic() - t < 15: time.sleep(0.05)
print("up" if up.link_up else "never-up", flush=True)
sys.stdin.readline()
z = np.zeros((4, 4), np.uint16)
t0 = time.monotonic()
for i in range(n):
    h = RawFrame.make_header("cam-1", "walk-01", i, time.time_ns(), last=i == n - 1)
    local.put("gaitflow/clinic/cam-1/raw", RawFrame(header=h, ir=z, depth=z).encode())
    # Edge-1 may not publish another camera's stream: the router's ACL drops it.
    if i % 10 == 0 and up.link_up:
        up._remote.put("gaitflow/clinic/cam-2/raw", RawFrame(header=h, ir=z, depth=z).encode())
    if i == 45: print("cut", flush=True)
    if i == 195: print("restore", flush=True)
    time.sleep(max(0.0, t0 + (i + 1) / 30 - time.monotonic()))
up.drain(20.0)
print(json.dumps({"stats": vars(up.stats), "backlog": up.backlog}), flush=True)
up.stop()
""".replace("@IP@", SERVER_IP).replace("@PORT@", str(PORT))


def _spawn(ns: str, code: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        ["ip", "netns", "exec", ns, sys.executable, "-c", textwrap.dedent(code), *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def _line(p: subprocess.Popen[str], timeout: float = 30.0) -> str:
    assert p.stdout is not None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = p.stdout.readline()
        if line:
            return line.strip()
        if p.poll() is not None:
            break
    raise AssertionError(f"no output from child (exit {p.poll()})")


def test_two_namespaces_tls_acl_and_link_cut(namespaces: tuple[str, str], tmp_path: Path) -> None:
    srv_ns, edge_ns = namespaces
    certs = tmp_path / "certs"
    make_bundle(certs, ["server", "edge-1"], sans=("localhost", "127.0.0.1", SERVER_IP, EDGE_IP))
    n = 225
    server = _spawn(srv_ns, SERVER, str(certs))
    edge = None
    try:
        assert _line(server) == "ready"
        edge = _spawn(edge_ns, EDGE, str(certs), str(tmp_path / "ring"), str(n))
        assert _line(edge) == "up", "edge could not reach the server router over TLS"
        assert edge.stdin is not None and server.stdin is not None
        edge.stdin.write("\n")
        edge.stdin.flush()
        veth = next(
            ln.split(":")[1].split("@")[0].strip()
            for ln in _ip("-n", edge_ns, "-o", "link").stdout.splitlines()
            if "veth" in ln or "@" in ln
        )
        assert _line(edge) == "cut"
        _ip("-n", edge_ns, "link", "set", veth, "down")
        assert _line(edge, 15) == "restore"
        _ip("-n", edge_ns, "link", "set", veth, "up")
        stats = json.loads(_line(edge, 60))
        server.stdin.write("\n")
        server.stdin.flush()
        result = json.loads(_line(server))
    finally:
        for p in (edge, server):
            if p is None:
                continue
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
            for f in (p.stdin, p.stdout):
                if f is not None:
                    f.close()
    cams = {c for c, _ in result["got"]}
    frames = sorted(f for c, f in result["got"] if c == "cam-1")
    assert cams == {"cam-1"}, "a publish denied by the ACL was delivered"
    assert stats["backlog"] == 0
    assert stats["stats"]["link_downs"] >= 1, "the cut was not noticed"
    assert frames == list(range(n)), f"lost frames: {sorted(set(range(n)) - set(frames))[:20]}"
    arrival = [f for c, f in result["got"] if c == "cam-1"]
    assert arrival == frames, "the backlog must arrive in capture order"
