"""Fault tests on real processes (127.0.0.1 only): router killed and restarted, stage
SIGKILLed. A relay stage stands for a stage; the launcher supervises router and stage.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from gaitflow.bus import Bus, BusConfig
from gaitflow.bus.router import local_endpoint
from gaitflow.schemas import RawFrame, decode
from gaitflow.stages.graph import load
from gaitflow.stages.launcher import Launcher

from gaitflow.deployment import RECONNECT

pytestmark = [pytest.mark.integration, pytest.mark.slow]

GRAPH = """\
version: 1
site: faults
stages:
  - name: relay
    module: gaitflow.stages.relay
    inputs: [raw]
    outputs: [raw]
    topics: {raw: raw-1}
"""


class Feed:
    """Publish raw frames at 30 fps and note when each relayed frame comes back."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.back: list[tuple[float, int]] = []
        self.put_errors = 0
        self._stop = threading.Event()
        bus.subscribe(
            "gaitflow/faults/cam-1/raw-1",
            lambda k, p: self.back.append((time.monotonic(), decode(RawFrame, p).header.frame)),
        )
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        z = np.zeros((4, 4), np.uint16)
        i = 0
        while not self._stop.wait(1 / 30):
            h = RawFrame.make_header("cam-1", "walk-01", i, time.time_ns())
            try:
                self.bus.put(
                    "gaitflow/faults/cam-1/raw", RawFrame(header=h, ir=z, depth=z).encode()
                )
            except Exception:  # noqa: BLE001 - the router is being killed: count, keep feeding
                self.put_errors += 1
            i += 1

    def start(self) -> Feed:
        self._t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._t.join(2)

    def flowing_since(self, t: float, timeout: float) -> float | None:
        """Seconds after ``t`` at which relayed frames arrive again, or None."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            later = [ts for ts, _ in self.back if ts > t]
            if len(later) >= 5:
                return later[0] - t
            time.sleep(0.05)
        return None


def test_router_restart_and_stage_sigkill(tmp_path: Path) -> None:
    gpath = tmp_path / "graph.yaml"
    gpath.write_text(GRAPH)
    ep = local_endpoint()
    # The reconnect settings the generated role configs give every client (RECONNECT).
    bus_doc = {"connect": [ep], "site": "faults", "extra": {"connect/retry": RECONNECT}}
    cfg_path = tmp_path / "stages.yaml"
    cfg_path.write_text(yaml.safe_dump({"bus": bus_doc}))
    la = Launcher(
        load(gpath),
        endpoint=ep,
        graph_path=gpath,
        config=cfg_path,
        metrics_port=0,
        echo=False,
        backoff_s=0.2,
    )
    with la:
        la.wait_ready(30)
        bus = Bus(BusConfig.from_mapping(bus_doc))
        feed = Feed(bus).start()
        try:
            assert feed.flowing_since(time.monotonic() - 1, 10) is not None, "pipeline never ran"
            # Kill the router: the launcher restarts it; stages and clients reconnect.
            router = la.child("router")
            os.kill(router.proc.pid, signal.SIGKILL)  # type: ignore[union-attr]
            killed = time.monotonic()
            assert _wait(lambda: router.restarts >= 1 and router.state == "running", 5), (
                "router was not restarted"
            )
            restarted = time.monotonic()
            resume = feed.flowing_since(restarted, 5.0)
            assert resume is not None, f"stages did not resume within 5 s (killed {killed:.1f})"
            print(f"frames flow again {resume:.2f} s after the router restart")
            # SIGKILL the stage: restarted and counted.
            stage = la.child("relay")
            os.kill(stage.proc.pid, signal.SIGKILL)  # type: ignore[union-attr]
            assert _wait(lambda: stage.restarts == 1 and stage.state == "running", 5)
            assert (
                la.registry.get_sample_value(
                    "gaitflow_launcher_restarts_total", {"stage": "relay", "worker": "0"}
                )
                == 1
            )
            assert feed.flowing_since(time.monotonic(), 10.0) is not None
        finally:
            feed.stop()
            bus.close()


def _wait(cond, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return bool(cond())
