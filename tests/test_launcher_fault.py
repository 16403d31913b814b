"""The launcher supervises stage processes: SIGKILL a relay mid-stream, it comes back."""

from __future__ import annotations

import os
import signal
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import Bus
from gaitflow.bus.router import client_config, local_endpoint
from gaitflow.schemas import RawFrame, decode
from gaitflow.stages import graph as graph_mod
from gaitflow.stages.launcher import Launcher
from gaitflow.stages.relay import chain_yaml

GRAPH = chain_yaml("ftest", 2)


def _scrape(url: str, name: str) -> float:
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    for line in text.splitlines():
        if line.startswith(name):
            return float(line.split()[-1])
    raise AssertionError(f"{name} not in {url}")


@pytest.mark.integration
@pytest.mark.slow
def test_sigkilled_relay_is_restarted_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "graph.yaml"
    path.write_text(GRAPH)
    ep = local_endpoint()
    la = Launcher(
        graph_mod.load(path),
        endpoint=ep,
        graph_path=path,
        metrics_port=0,
        stage_metrics=True,
        backoff_s=0.1,
        echo=False,
    )
    la.start()
    bus = None
    try:
        la.wait_ready(20)
        assert la.metrics is not None
        bus = Bus(client_config(ep, site="ftest"))
        got: list[int] = []
        bus.subscribe(
            "gaitflow/ftest/*/raw-2", lambda k, p: got.append(decode(RawFrame, p).header.frame)
        )
        deadline = time.monotonic() + 10
        while len(bus.alive("gaitflow/ftest/@alive/**")) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.2)
        pub = bus.publisher("gaitflow/ftest/cam0/raw")
        ir = np.random.default_rng(3).integers(0, 65535, (424, 512), dtype=np.uint16)
        killed = threading.Event()
        first_pid = la.child("relay1").proc.pid

        def frames(lo: int, hi: int) -> None:
            for i in range(lo, hi):
                hdr = RawFrame.make_header("cam0", "walk-01", i, time.time_ns())
                pub.put(RawFrame(header=hdr, ir=ir, depth=ir).encode())
                time.sleep(1 / 30)

        frames(0, 30)
        os.kill(first_pid, signal.SIGKILL)
        killed.set()
        # Keep streaming while the launcher notices and restarts relay1.
        deadline = time.monotonic() + 15
        i = 30
        while la.child("relay1").restarts < 1 or not la.child("relay1").ready.is_set():
            assert time.monotonic() < deadline, la.status()
            frames(i, i + 3)
            i += 3
        while len(bus.alive("gaitflow/ftest/@alive/relay1/**")) < 1:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.2)
        frames(1000, 1030)
        deadline = time.monotonic() + 5
        while sum(f >= 1000 for f in got) < 30 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert got[:30] == list(range(30))  # before the kill: all, in order
        assert [f for f in got if f >= 1000] == list(range(1000, 1030))  # after the restart
        row = next(r for r in la.status() if r["name"] == "relay1")
        assert row["restarts"] == 1 and row["pid"] != first_pid and row["state"] == "running"
        assert (
            _scrape(la.metrics.url, 'gaitflow_launcher_restarts_total{stage="relay1",worker="0"}')
            == 1
        )
        assert _scrape(la.metrics.url, 'gaitflow_launcher_restarts_total{stage="relay2"') == 0
        assert _scrape(la.child("relay1").metrics_url, "gaitflow_stage_restarts{") == 1
    finally:
        if bus is not None:
            bus.close()
        la.stop()
    assert all(r["exit_code"] == 0 for r in la.status())


def test_stage_with_config_error_is_not_restarted(tmp_path: Path) -> None:
    path = tmp_path / "graph.yaml"
    path.write_text(GRAPH.replace("module: gaitflow.stages.relay", "module: gaitflow.nope", 1))
    graph = graph_mod.load(path)
    la = Launcher(
        graph, stages=["relay1"], router=False, graph_path=path, backoff_s=0.05, echo=False
    )
    la.start()
    try:
        deadline = time.monotonic() + 20
        while la.child("relay1").state != "failed":
            assert time.monotonic() < deadline, la.status()
            time.sleep(0.05)
        time.sleep(0.3)
        c = la.child("relay1")
        assert c.restarts == 0 and c.exit_code == 2
        assert any("cannot import gaitflow.nope" in line for line in c.lines)
    finally:
        la.stop()
