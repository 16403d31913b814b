"""record and replay over real Zenoh on 127.0.0.1 (router in this process, free ports).

The recorder runs as its own ``gaitflow record`` process, as in production, so SIGTERM
reaches it the way a supervisor or Ctrl-C would.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import Bus
from gaitflow.bus.router import Router, client_config, local_endpoint
from gaitflow.schemas import Blobs, RawFrame, peek_header

from gaitflow.recording import McapReader

pytestmark = [pytest.mark.integration, pytest.mark.slow]

RAW = "gaitflow/clinic/cam0/raw"
BLOBS = "gaitflow/clinic/cam0/blobs"
STATS = re.compile(r"received (\d+), written (\d+), dropped (\d+), malformed (\d+)")


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "gaitflow.cli", *args]


def _env() -> dict[str, str]:
    return {**os.environ, "GAITFLOW_QUIET": "1"}


def _start_recorder(ep: str, out: Path, *streams: str) -> subprocess.Popen[str]:
    p = subprocess.Popen(
        _cli("record", "--tap", *streams, "--connect", ep, "--out", str(out), "-q"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    line = p.stderr.readline() if p.stderr else ""
    assert "record: recording" in line, line + (p.stderr.read() if p.stderr else "")
    _wait_matching(ep, RAW)
    return p


def _wait_matching(ep: str, key: str, timeout: float = 10.0) -> None:
    """Wait until a publisher on ``key`` sees a subscriber (the recorder's) via the router."""
    with Bus(client_config(ep)) as bus:
        pub = bus.publisher(key)
        deadline = time.monotonic() + timeout
        while not pub._inner.matching_status.matching:
            assert time.monotonic() < deadline, f"no subscriber on {key} after {timeout} s"
            time.sleep(0.02)


def _stop_recorder(p: subprocess.Popen[str]) -> tuple[int, int, int]:
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=20)
    assert p.returncode == 0, err
    m = STATS.search(out)
    assert m, out + err
    received, written, dropped, malformed = map(int, m.groups())
    assert malformed == 0
    return received, written, dropped


def _raw(i: int, base: np.ndarray) -> bytes:
    ir = base.copy()
    ir[0, :8] = i  # every frame distinct
    hdr = RawFrame.make_header("cam0", "walk-01", i, time.time_ns())
    return RawFrame(header=hdr, ir=ir, depth=base).encode()


def _blobs(raw_payload: bytes) -> bytes:
    h = peek_header(raw_payload)
    hdr = Blobs.make_header("cam0", h["trial"], h["frame"], h["capture_ns"])
    z = np.zeros
    return Blobs(
        header=hdr,
        centroid=z((1, 2)),
        marker_radius=z(1),
        region_radius=z(1),
        mean_ir=z(1),
        area=z(1, "i4"),
        threshold=float(h["frame"]),
    ).encode()


def _read(path: Path) -> tuple[list[tuple[str, bytes, int, int]], bool]:
    with McapReader(path) as r:
        msgs = [tuple(m) for m in r.messages()]
        return msgs, r.truncated


def test_record_then_replay_reproduces_payloads_and_timestamps(tmp_path: Path) -> None:
    ep = local_endpoint()
    base = np.random.default_rng(1).integers(0, 4000, (424, 512), dtype=np.uint16)
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    with Router(listen=(ep,)):
        rec = _start_recorder(ep, first, "raw", "blobs")
        sent: list[tuple[str, bytes]] = []
        with Bus(client_config(ep)) as bus:
            p_raw, p_blobs = bus.publisher(RAW), bus.publisher(BLOBS)
            for i in range(60):  # as fast as BLOCK allows: 868 KB frames under load
                raw = _raw(i, base)
                blobs = _blobs(raw)
                p_raw.put(raw)
                p_blobs.put(blobs)
                sent += [(RAW, raw), (BLOBS, blobs)]
            time.sleep(0.5)
        received, written, dropped = _stop_recorder(rec)
        assert (received, written, dropped) == (120, 120, 0)
        recorded, truncated = _read(first)
        assert not truncated
        for key in (RAW, BLOBS):
            assert [m[1] for m in recorded if m[0] == key] == [p for k, p in sent if k == key]
        for key, payload, log_ns, pub_ns in recorded:
            h = peek_header(payload)
            assert (log_ns, pub_ns) == (h["capture_ns"], h["publish_ns"]), key

        # Replay flat out into a second recorder.
        rec2 = _start_recorder(ep, second, "raw", "blobs")
        done = subprocess.run(
            _cli("replay", str(first), "--rate", "max", "--connect", ep, "-q"),
            capture_output=True,
            text=True,
            env=_env(),
            timeout=60,
        )
        assert done.returncode == 0, done.stderr
        assert "published 120 message(s)" in done.stdout
        time.sleep(0.5)
        assert _stop_recorder(rec2) == (120, 120, 0)
    replayed, truncated = _read(second)
    assert not truncated
    for key in (RAW, BLOBS):
        # Byte-identical payloads, identical log and publish times, same order per key.
        assert [m for m in replayed if m[0] == key] == [m for m in recorded if m[0] == key]


def test_sigterm_mid_stream_every_received_frame_is_in_the_file(tmp_path: Path) -> None:
    ep = local_endpoint()
    base = np.random.default_rng(2).integers(0, 4000, (424, 512), dtype=np.uint16)
    out = tmp_path / "killed.mcap"
    stop = threading.Event()
    published: list[int] = []
    with Router(listen=(ep,)):
        rec = _start_recorder(ep, out, "raw")
        with Bus(client_config(ep)) as bus:
            pub = bus.publisher(RAW)

            def produce() -> None:
                i = 0
                while not stop.is_set():
                    pub.put(_raw(i, base))
                    published.append(i)
                    i += 1
                    time.sleep(0.004)

            t = threading.Thread(target=produce)
            t.start()
            try:
                time.sleep(1.0)
                received, written, dropped = _stop_recorder(rec)  # while frames still flow
            finally:
                stop.set()
                t.join()
    assert received > 20 and received == written and dropped == 0
    recorded, truncated = _read(out)
    assert not truncated
    assert len(recorded) == received
    frames = [peek_header(m[1])["frame"] for m in recorded]
    assert frames == sorted(set(frames)) and set(frames) <= set(published)
    assert len(published) > frames[-1] + 1  # the producer outlived the recorder
