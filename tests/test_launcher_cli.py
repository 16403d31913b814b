"""``gaitflow run``: starts a router and the graph's stages, stops them all on SIGINT."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from gaitflow.bus.router import local_endpoint
from gaitflow.stages.relay import chain_yaml

GRAPH = chain_yaml("rtest", 2, last_replicas=2)


@pytest.mark.integration
@pytest.mark.slow
def test_run_starts_every_worker_and_stops_cleanly_on_sigint(tmp_path: Path) -> None:
    g = tmp_path / "g.yaml"
    g.write_text(GRAPH)
    log = tmp_path / "run.log"
    ep = local_endpoint()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with log.open("wb") as out:
        p = subprocess.Popen(
            [sys.executable, "-m", "gaitflow.cli", "run", "--graph", str(g), "--endpoint", ep],
            stdout=out,
            stderr=out,
            env=env,
        )
    try:
        deadline = time.monotonic() + 30
        while log.read_text().count(" ready") < 3:
            assert time.monotonic() < deadline, log.read_text()
            assert p.poll() is None, log.read_text()
            time.sleep(0.1)
        text = log.read_text()
        assert "[relay2/0]" in text and "[relay2/1]" in text and "worker 1/2 ready" in text
        p.send_signal(signal.SIGINT)
        assert p.wait(30) == 0, log.read_text()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    # every child was stopped: nothing listens on the router's port any more
    host, port = ep.split("/", 1)[1].rsplit(":", 1)
    with pytest.raises(OSError), socket.create_connection((host, int(port)), timeout=0.5):
        pass
