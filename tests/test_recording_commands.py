"""replay timing, tap summaries and inspect output, without a network."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from gaitflow.schemas import Blobs, LabelledMarkers

from gaitflow.cli import main
from gaitflow.commands.inspect import EXIT_TRUNCATED
from gaitflow.commands.replay import parse_rate, replay
from gaitflow.commands.tap import TapWindow, format_summary
from gaitflow.errors import ConfigError
from gaitflow.recording import McapWriter

KEY = "gaitflow/clinic/cam0/blobs"


def _blobs(i: int, cap: int, pub: int | None = None) -> bytes:
    return Blobs(
        header=Blobs.make_header("cam0", "walk-01", i, cap),
        centroid=np.zeros((2, 2)),
        marker_radius=np.ones(2),
        region_radius=np.ones(2),
        mean_ir=np.ones(2),
        area=np.ones(2, np.int32),
        threshold=100.0 + i,
    ).encode(publish_ns=pub)


def _recording(path: Path, caps_ms: list[float], chunk_size: int = 1 << 20) -> list[bytes]:
    payloads = [_blobs(i, int(c * 1e6)) for i, c in enumerate(caps_ms)]
    with McapWriter(path, chunk_size=chunk_size) as w:
        for p in payloads:
            w.write(KEY, p)
    return payloads


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        assert s > 0
        self.t += s


@pytest.mark.parametrize("rate", [1.0, 2.0])
def test_replay_keeps_original_timing(tmp_path: Path, rate: float) -> None:
    caps = [0.0, 33.3, 66.7, 50.0, 500.0]  # one message older than its predecessor
    payloads = _recording(tmp_path / "r.mcap", caps)
    clock = FakeClock()
    sent: list[tuple[float, str, bytes]] = []
    stats = replay(
        tmp_path / "r.mcap",
        lambda k, p: sent.append((clock(), k, p)),
        rate=rate,
        sleep=clock.sleep,
        clock=clock,
    )
    assert stats.published == 5 and [p for _, _, p in sent] == payloads
    assert {k for _, k, _ in sent} == {KEY}
    t = [s[0] - 100.0 for s in sent]
    # In file order; each at (capture - first capture) / rate, never going back in time.
    want = [0.0, 0.0333, 0.0667, 0.0667, 0.5]
    assert t == pytest.approx([w / rate for w in want], abs=2e-3)


def test_replay_max_rate_does_not_wait_and_loop_stops(tmp_path: Path) -> None:
    payloads = _recording(tmp_path / "r.mcap", [0.0, 1000.0, 2000.0])
    clock = FakeClock()
    sent: list[bytes] = []
    stop = threading.Event()

    def publish(k: str, p: bytes) -> None:
        sent.append(p)
        if len(sent) == 7:
            stop.set()

    stats = replay(
        tmp_path / "r.mcap",
        publish,
        rate=float("inf"),
        loop=True,
        stop=stop,
        sleep=clock.sleep,
        clock=clock,
    )
    assert clock.t == 100.0  # never slept
    assert sent == (payloads * 3)[:7] and stats.published == 7 and stats.passes == 3


def test_parse_rate() -> None:
    assert parse_rate("max") == float("inf") and parse_rate("0.5") == 0.5
    for bad in ("0", "-1", "fast"):
        with pytest.raises(ConfigError):
            parse_rate(bad)


def test_tap_summary_rate_latency_and_fields() -> None:
    w = TapWindow("blobs")
    for i in range(10):
        cap = 1_000_000_000 + i * 33_000_000
        w.add(KEY, _blobs(i, cap, pub=cap + 4_000_000), recv_ns=cap + 10_000_000)
    w.add(KEY, b"junk", recv_ns=0)
    text = format_summary(w, 2.0, 10)
    assert "blobs: 5.0 Hz" in text
    assert "publish->receive ms: mean 6.0" in text
    assert "capture->receive ms: mean 10.0" in text
    assert "frame=9" in text and "trial=walk-01" in text
    assert "centroid[2, 2]" in text and "threshold=109" in text and "area[2] 1..1" in text
    assert "malformed: 1" in text


def test_tap_summary_counts_nan_markers() -> None:
    pos = np.full((20, 3), np.nan)
    pos[:5] = 1.0
    m = LabelledMarkers(
        header=LabelledMarkers.make_header("cam0", "walk-01", 3, 0),
        position=pos,
        pixel=np.zeros((20, 2)),
        blob=np.zeros(20, np.int32),
    )
    w = TapWindow("labelled")
    w.add("k", m.encode(), recv_ns=0)
    assert "position[20, 3] nan=45" in format_summary(w, 1.0, 1)
    assert "(no messages)" in format_summary(TapWindow("labelled"), 1.0, 0)


def test_inspect_cli_complete_truncated_and_corrupt(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "r.mcap"
    _recording(path, [i * 33.3 for i in range(40)], chunk_size=2000)
    assert main(["inspect", str(path), "-q"]) == 0
    out = capsys.readouterr().out
    assert KEY in out and "gaitflow/blobs/v1" in out and "40" in out
    assert "TRUNCATED" not in out
    assert main(["inspect", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["messages"] == 40 and not doc["truncated"]
    assert doc["channels"][0]["schema_encoding"] == "jsonschema"

    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    assert main(["inspect", str(cut), "--json"]) == EXIT_TRUNCATED
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert doc["truncated"] and 0 < doc["messages"] < 40
    assert "truncated" in captured.err and str(cut) in captured.err
    assert len(captured.err.strip().splitlines()) == 1

    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + b"\x05" + (10**6).to_bytes(8, "little") + b"x" * 50)
    # A record claiming more bytes than the file holds reads as truncated, not as a crash.
    assert main(["inspect", str(junk)]) == EXIT_TRUNCATED
    capsys.readouterr()
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"PK\x03\x04 not mcap")
    assert main(["inspect", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err and "not an MCAP file" in err
