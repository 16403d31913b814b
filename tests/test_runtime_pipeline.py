"""Over real Zenoh on 127.0.0.1: a router and relay stages as processes (``gaitflow stage``).

A producer sends 300 raw frames of 868 KB at 30 fps through two relays: none lost, order
kept. The relays' /metrics are scraped for the latency histogram's 33 ms bucket.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import Bus
from gaitflow.bus.router import client_config, local_endpoint, wait_port
from gaitflow.schemas import RawFrame, decode
from gaitflow.stages.relay import chain_yaml

pytestmark = [pytest.mark.integration, pytest.mark.slow]

GRAPH = chain_yaml("itest", 2)


def _spawn(log: Path, *args: str) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with log.open("wb") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "gaitflow.cli", *args], stdout=out, stderr=out, env=env
        )


def _ready_line(log: Path, timeout: float = 20.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            if "ready" in line:
                return line
        time.sleep(0.05)
    raise AssertionError(f"not ready: {log.read_text()}")


def test_300_frames_through_two_relay_processes(tmp_path: Path) -> None:
    graph = tmp_path / "graph.yaml"
    graph.write_text(GRAPH)
    ep = local_endpoint()
    logs = [tmp_path / f"{n}.log" for n in ("router", "relay1", "relay2")]
    procs = [_spawn(logs[0], "router", "--listen", ep)]
    try:
        wait_port(ep, 20)
        common = ("--graph", str(graph), "--connect", ep)
        procs.append(_spawn(logs[1], "stage", "relay1", *common, "--metrics-port", "0"))
        procs.append(_spawn(logs[2], "stage", "relay2", *common))
        metrics_url = _ready_line(logs[1]).rsplit("metrics ", 1)[1].strip()
        _ready_line(logs[2])
        bus = Bus(client_config(ep, site="itest"))
        try:
            got: list[tuple[int, int]] = []
            done = threading.Event()
            n = 300

            def on(key: str, payload: bytes) -> None:
                m = decode(RawFrame, payload)
                got.append((m.header.frame, int(m.ir[0, 0])))
                if len(got) == n:
                    done.set()

            bus.subscribe("gaitflow/itest/*/raw-2", on)
            deadline = time.monotonic() + 10
            while len(bus.alive("gaitflow/itest/@alive/**")) < 2:
                assert time.monotonic() < deadline
                time.sleep(0.05)
            time.sleep(0.2)
            pub = bus.publisher("gaitflow/itest/cam0/raw")
            rng = np.random.default_rng(7)
            ir = rng.integers(0, 65535, (424, 512), dtype=np.uint16)
            depth = rng.integers(0, 8000, (424, 512), dtype=np.uint16)
            size = 0
            t0 = time.perf_counter()
            for i in range(n):
                wait = t0 + i / 30 - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                ir[0, 0] = i
                hdr = RawFrame.make_header("cam0", "walk-01", i, time.time_ns(), i == n - 1)
                payload = RawFrame(header=hdr, ir=ir, depth=depth).encode()
                size = len(payload)
                pub.put(payload)
            assert done.wait(15), f"received {len(got)} of {n}"
            assert size > 868_000
            assert got == [(i, i) for i in range(n)]
            text = urllib.request.urlopen(metrics_url, timeout=5).read().decode()
            bucket = [
                line
                for line in text.splitlines()
                if line.startswith("gaitflow_stage_processing_seconds_bucket")
                and 'le="0.033"' in line
            ]
            assert len(bucket) == 1 and 'stage="relay1"' in bucket[0]
            count = [
                line
                for line in text.splitlines()
                if line.startswith("gaitflow_stage_processing_seconds_count")
            ]
            assert count and float(count[0].split()[-1]) == n
        finally:
            bus.close()
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            assert p.wait(15) == 0
