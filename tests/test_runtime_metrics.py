"""Stage metrics over HTTP, stage config files, and ``gaitflow stage`` errors."""

from __future__ import annotations

import itertools
import re
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import FakeBus
from gaitflow.schemas import RawFrame
from gaitflow.stages import relay
from gaitflow.stages.graph import Node
from gaitflow.stages.runtime import (
    LATENCY_BUCKETS,
    MetricsServer,
    RuntimeOptions,
    StageConfig,
    StageRuntime,
)

from gaitflow.cli import main
from gaitflow.errors import ConfigError

RELAY = Node("relay", "gaitflow.stages.relay", ("raw",), ("raw",), topics={"raw": "raw-1"})

GRAPH = """\
version: 1
site: mtest
stages:
  - name: relay
    module: gaitflow.stages.relay
    inputs: [raw]
    outputs: [raw]
    topics: {raw: raw-1}
"""


def test_latency_buckets_resolve_the_budget() -> None:
    b = LATENCY_BUCKETS
    assert b[0] == 0.001 and b[-1] == 0.25
    assert {0.03, 0.033, 0.04} <= set(b)
    assert all(y - x <= 0.0100001 for x, y in itertools.pairwise(b) if y <= 0.1)


def test_scrape_running_stage_finds_33ms_bucket() -> None:
    bus = FakeBus()
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}).start()
    server = MetricsServer(rt.metrics.registry, 0)
    try:
        for i in range(3):
            hdr = RawFrame.make_header("cam0", "walk-01", i, 0)
            z = np.zeros((424, 512), np.uint16)
            bus.put("gaitflow/clinic/cam0/raw", RawFrame(header=hdr, ir=z, depth=z).encode())
        bus.put("gaitflow/clinic/cam0/raw", b"junk")
        deadline_ok = False
        for _ in range(100):
            text = urllib.request.urlopen(server.url, timeout=5).read().decode()
            if 'gaitflow_stage_frames_out_total{stage="relay",worker="0"} 3.0' in text:
                deadline_ok = True
                break
        assert deadline_ok, text
        m = re.search(
            r'^gaitflow_stage_processing_seconds_bucket\{le="0.033",stage="relay",worker="0"\} '
            r"(\S+)$",
            text,
            re.M,
        )
        assert m is not None and float(m.group(1)) <= 3
        for name in (
            'gaitflow_stage_processing_seconds_bucket{le="0.03"',
            'gaitflow_stage_processing_seconds_bucket{le="0.04"',
            'gaitflow_stage_age_seconds_bucket{le="0.033"',
            "gaitflow_stage_frames_in_total",
            "gaitflow_stage_frames_dropped_total",
            'gaitflow_stage_frames_malformed_total{stage="relay",worker="0"} 1.0',
            "gaitflow_stage_frames_over_budget_total",
            "gaitflow_stage_restarts",
        ):
            assert name in text, name
        assert server.host == "127.0.0.1"
    finally:
        server.close()
        rt.stop()


def test_stage_config_sections(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(
        "bus: {connect: ['tcp/127.0.0.1:7999'], site: lab}\n"
        "params: {detect: {threshold: 0.5}, clean: {}}\n"
        "metrics: {port: 0}\n"
        "runtime: {queue_size: 8, reorder_timeout_s: 0.1}\n"
    )
    cfg = StageConfig.load(str(p))
    assert cfg.bus.connect == ("tcp/127.0.0.1:7999",) and cfg.site_set
    assert cfg.params_for("detect") == {"threshold": 0.5}
    assert cfg.params_for("label") == {}
    opt = cfg.options(worker=None, camera="cam1")
    assert opt == RuntimeOptions(queue_size=8, reorder_timeout_s=0.1, metrics_port=0, camera="cam1")
    p.write_text("runtime: {queue_policy: sometimes}\n")
    with pytest.raises(ConfigError, match="queue_policy"):
        StageConfig.load(str(p)).options()
    p.write_text("stages: {}\n")
    with pytest.raises(ConfigError, match="unknown section"):
        StageConfig.load(str(p))


def test_stage_command_bad_parameter_is_one_line_exit_2(tmp_path: Path, capsys) -> None:
    g = tmp_path / "g.yaml"
    g.write_text(GRAPH)
    c = tmp_path / "c.yaml"
    c.write_text("params: {speed: 3}\n")
    rc = main(["stage", "relay", "--graph", str(g), "--config", str(c)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and "speed" in err[0] and "not declared" in err[0]


def test_stage_command_unknown_stage(tmp_path: Path, capsys) -> None:
    g = tmp_path / "g.yaml"
    g.write_text(GRAPH)
    assert main(["stage", "nope", "--graph", str(g)]) == 2
    assert "no stage named 'nope'" in capsys.readouterr().err


def test_bad_replica_options() -> None:
    with pytest.raises(ConfigError, match="worker"):
        RuntimeOptions(replicas=2, worker=2)
