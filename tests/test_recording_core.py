"""MCAP writer, recorder and reader: layout, round trips, truncation, corruption, replay timing."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from gaitflow.schemas import Blobs, RawFrame, decode, json_schema, messages_equal
from mcap.reader import make_reader

from gaitflow.errors import ConfigError, InputError
from gaitflow.recording import (
    Compression,
    McapReader,
    McapWriter,
    Recorder,
    count_hint,
    inspect_recording,
    iter_decoded,
    iter_messages,
)

RAW_KEY = "gaitflow/clinic/cam0/raw"
BLOBS_KEY = "gaitflow/clinic/cam0/blobs"


def _frames(n: int, size: tuple[int, int] = (24, 32), seed: int = 0) -> list[tuple[str, bytes]]:
    """Alternating raw and blobs payloads of ``n`` frames, capture times 33 ms apart."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        cap = 1_700_000_000_000_000_000 + i * 33_333_333
        raw = RawFrame(
            header=RawFrame.make_header("cam0", "walk-01", i, cap, last=i == n - 1),
            ir=rng.integers(0, 65535, size, dtype=np.uint16),
            depth=rng.integers(0, 4500, size, dtype=np.uint16),
        )
        k = int(rng.integers(0, 4))
        blobs = Blobs.follow(
            raw.header,
            centroid=rng.random((k, 2)) * 100,
            marker_radius=np.full(k, np.nan),
            region_radius=rng.random(k),
            mean_ir=rng.random(k),
            area=np.arange(k, dtype=np.int32),
            threshold=float(i),
        )
        out.append((RAW_KEY, raw.encode(publish_ns=cap + 1_000_000)))
        out.append((BLOBS_KEY, blobs.encode(publish_ns=cap + 5_000_000)))
    return out


def _write(path: Path, msgs: list[tuple[str, bytes]], **kw) -> None:
    with McapWriter(path, **kw) as w:
        for key, payload in msgs:
            w.write(key, payload)


@pytest.mark.parametrize("compression", ["zstd", "zstd:1", "lz4", "none"])
def test_round_trip_payloads_times_and_layout(tmp_path: Path, compression: str) -> None:
    msgs = _frames(12)
    path = tmp_path / "r.mcap"
    _write(path, msgs, compression=compression, chunk_size=4096)
    got = list(iter_messages(path))
    assert [(m.key, m.payload) for m in got] == msgs
    for m in got:
        dec = RawFrame if m.stream == "raw" else Blobs
        hdr = decode(dec, m.payload).header
        assert (m.log_time_ns, m.publish_time_ns) == (hdr.capture_ns, hdr.publish_ns)
    # The official mcap reader agrees: summary, schemas, encodings, counts.
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(msgs)
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {RAW_KEY, BLOBS_KEY}
        for topic, cls in ((RAW_KEY, RawFrame), (BLOBS_KEY, Blobs)):
            ch = topics[topic]
            sc = summary.schemas[ch.schema_id]
            assert ch.message_encoding == "msgpack" and sc.encoding == "jsonschema"
            assert json.loads(sc.data) == json_schema(cls)
            assert summary.statistics.channel_message_counts[ch.id] == 12
        want = "" if compression == "none" else compression.split(":")[0]
        assert {ci.compression for ci in summary.chunk_indexes} == {want}
        assert len(summary.chunk_indexes) > 1
        assert [m.data for _, _, m in reader.iter_messages(log_time_order=False)] == [
            p for _, p in msgs
        ]
    info = inspect_recording(path)
    assert not info.truncated and info.messages == len(msgs)
    assert {c.topic: c.count for c in info.channels.values()} == {RAW_KEY: 12, BLOBS_KEY: 12}
    assert info.duration_s == pytest.approx(11 * 0.033333333, abs=1e-6)


def test_decoded_iterator_and_stream_filter(tmp_path: Path) -> None:
    msgs = _frames(5)
    path = tmp_path / "r.mcap"
    _write(path, msgs)
    dec = list(iter_decoded(path, streams=["blobs"]))
    assert [d.stream for d in dec] == ["blobs"] * 5
    for d, (_, p) in zip(dec, msgs[1::2], strict=True):
        assert messages_equal(d.message, decode(Blobs, p))
        assert d.log_time_ns == d.message.header.capture_ns


def test_compression_spec_parsing() -> None:
    assert Compression.parse("ZSTD:1") == Compression("zstd", 1)
    assert Compression.parse("none").mcap_name == ""
    for bad in ("gzip", "zstd:x", "none:1"):
        with pytest.raises(ConfigError, match=bad.split(":")[0]):
            Compression.parse(bad)


def test_truncated_file_yields_whole_chunks_and_says_so(tmp_path: Path) -> None:
    msgs = _frames(20)
    full = tmp_path / "full.mcap"
    _write(full, msgs, compression="zstd", chunk_size=3000)
    data = full.read_bytes()
    cut_file = tmp_path / "cut.mcap"
    previous = 0
    seen = set()
    n_chunks = inspect_recording(full).chunks
    assert n_chunks >= 5
    for cut in range(8, len(data), max(1, len(data) // 150)):
        cut_file.write_bytes(data[:cut])
        with McapReader(cut_file) as r:
            got = [(m.key, m.payload) for m in r.messages()]
            assert r.truncated and "truncated" in r.info.truncation
        # What it reads is a prefix of what was written, made of whole chunks, growing.
        assert got == msgs[: len(got)]
        assert len(got) >= previous
        previous = len(got)
        seen.add(previous)
        assert r.info.messages == len(got)
    # Partial reads really happen: at least one distinct message count per whole chunk.
    assert len(seen - {0}) >= n_chunks - 1
    # Cut just before the footer: every message is there, but the file is still truncated.
    cut_file.write_bytes(data[: len(data) - 30])
    info = inspect_recording(cut_file)
    assert info.truncated and info.messages == len(msgs)
    # iter_messages: tolerant by default, strict on request.
    cut_file.write_bytes(data[: len(data) // 2])
    assert 0 < len(list(iter_messages(cut_file))) < len(msgs)
    with pytest.raises(InputError, match="truncated"):
        list(iter_messages(cut_file, allow_truncated=False))


def test_corrupt_and_foreign_files_raise_input_error_naming_the_file(tmp_path: Path) -> None:
    msgs = _frames(6)
    good = tmp_path / "good.mcap"
    _write(good, msgs, compression="zstd", chunk_size=2000)
    data = bytearray(good.read_bytes())
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_bytes(b"this is not a recording\n")
    with pytest.raises(InputError, match="not an MCAP file") as ei:
        inspect_recording(not_mcap)
    assert str(not_mcap) in str(ei.value)
    # Damage the compressed bytes inside the first chunk.
    with McapReader(good) as r:
        list(r.messages())
    first_chunk = data.find(b"zstd") + 40
    data[first_chunk : first_chunk + 16] = b"\xff" * 16
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(InputError, match="corrupt") as ei:
        inspect_recording(bad)
    assert str(bad) in str(ei.value)
    missing = tmp_path / "missing.mcap"
    with pytest.raises(InputError, match="cannot open"):
        inspect_recording(missing)


def test_flush_interval_makes_data_readable_before_close(tmp_path: Path) -> None:
    msgs = _frames(3)
    path = tmp_path / "live.mcap"
    w = McapWriter(path, chunk_size=1 << 30, flush_interval_s=0.0)
    for key, p in msgs:
        w.write(key, p)
    w.poll()
    with McapReader(path) as r:
        assert [(m.key, m.payload) for m in r.messages()] == msgs
        assert r.truncated  # no footer yet: a killed recorder's file looks like this
    w.close()
    assert not inspect_recording(path).truncated


def test_recorder_threads_every_accepted_payload_is_written(tmp_path: Path) -> None:
    msgs = _frames(50)
    path = tmp_path / "rec.mcap"
    rec = Recorder(path, compression="lz4")
    threads = [
        threading.Thread(target=lambda part=msgs[i::2]: [rec.offer(k, p) for k, p in part])
        for i in range(2)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stats = rec.close()
    assert stats.received == stats.written == len(msgs) and stats.dropped == 0
    got = list(iter_messages(path))
    assert sorted(m.payload for m in got) == sorted(p for _, p in msgs)
    # Per key, order is the order offered (each key came from one thread).
    for key in (RAW_KEY, BLOBS_KEY):
        assert [m.payload for m in got if m.key == key] == [p for k, p in msgs if k == key]


class _SlowWriter(McapWriter):
    def write(self, *a, **kw) -> None:
        time.sleep(0.01)
        super().write(*a, **kw)


def test_recorder_bounded_queue_drops_and_counts(tmp_path: Path) -> None:
    msgs = _frames(30, size=(64, 64))
    path = tmp_path / "rec.mcap"
    one = len(msgs[0][1])
    rec = Recorder(_SlowWriter(path), max_queue_bytes=3 * one)
    accepted = [rec.offer(k, p) for k, p in msgs]
    stats = rec.close()
    assert stats.dropped > 0 and stats.dropped == accepted.count(False)
    assert stats.received == accepted.count(True) == stats.written
    assert stats.received + stats.dropped == len(msgs)
    kept = [p for (k, p), ok in zip(msgs, accepted, strict=True) if ok]
    assert [m.payload for m in iter_messages(path)] == kept
    assert rec.offer(RAW_KEY, msgs[0][1]) is False  # closed: refused and counted as late
    assert rec.stats.dropped == stats.dropped and rec.stats.late == 1


def test_recorder_keeps_malformed_payloads_with_receive_time(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    rec = Recorder(path)
    before = time.time_ns()
    rec.offer(RAW_KEY, b"\x00garbage")
    stats = rec.close()
    assert stats.malformed == 1 and stats.written == 1
    (m,) = list(iter_messages(path))
    assert m.payload == b"\x00garbage" and m.log_time_ns >= before


def test_recorder_rotate_splits_files_in_order(tmp_path: Path) -> None:
    msgs = _frames(10)
    closed: list[str] = []
    rec = Recorder(tmp_path / "a.mcap", compression="none")
    for k, p in msgs[:7]:
        rec.offer(k, p)
    rec.rotate(tmp_path / "b.mcap", on_closed=closed.append)
    for k, p in msgs[7:]:
        rec.offer(k, p)
    stats = rec.close()
    assert closed == [str(tmp_path / "a.mcap")]
    assert stats.written == len(msgs)
    a = [m.payload for m in iter_messages(tmp_path / "a.mcap", allow_truncated=False)]
    b = [m.payload for m in iter_messages(tmp_path / "b.mcap", allow_truncated=False)]
    assert a == [p for _, p in msgs[:7]] and b == [p for _, p in msgs[7:]]
    with pytest.raises(InputError, match="after close"):
        rec.rotate(tmp_path / "c.mcap")


class _BrokenWriter(McapWriter):
    def write(self, *a, **kw) -> None:
        raise RuntimeError("disk on fire")


def test_recorder_writer_thread_failure_is_not_silent(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rec = Recorder(_BrokenWriter(tmp_path / "x.mcap"))
    assert rec.offer(RAW_KEY, b"payload")
    rec._thread.join(timeout=5)
    assert not rec.offer(RAW_KEY, b"payload")  # no longer accepted: counted as dropped
    with pytest.raises(InputError, match="disk on fire"):
        rec.close()
    assert rec.stats.received == 1 and rec.stats.written == 0 and rec.stats.dropped == 1
    assert "writer thread failed" in caplog.text


def test_damaged_files_never_crash_the_reader(tmp_path: Path) -> None:
    """Random byte damage anywhere: the reader returns what it can or raises InputError."""
    msgs = _frames(8)
    good = tmp_path / "good.mcap"
    _write(good, msgs, compression="lz4", chunk_size=2000)
    data = good.read_bytes()
    rng = np.random.default_rng(7)
    bad = tmp_path / "bad.mcap"
    outcomes = {"ok": 0, "error": 0}
    for _ in range(150):
        b = bytearray(data)
        for i in rng.integers(0, len(b), size=int(rng.integers(1, 4))):
            b[i] = int(rng.integers(0, 256))
        bad.write_bytes(bytes(b))
        try:
            inspect_recording(bad)
            outcomes["ok"] += 1
        except InputError as exc:
            assert str(bad) in str(exc)
            outcomes["error"] += 1
    assert outcomes["error"] > 0  # damage is detected, not just skipped over


def test_count_hint_from_summary_only_for_complete_files(tmp_path: Path) -> None:
    msgs = _frames(9)
    path = tmp_path / "r.mcap"
    _write(path, msgs, chunk_size=3000)
    assert count_hint(path) == 18
    assert count_hint(path, ["blobs"]) == 9 and count_hint(path, ["truth"]) == 0
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-5])
    assert count_hint(cut) is None
