"""MCAP recordings of bus traffic: a writer, a queued recorder and a truncation-tolerant reader.

Layout of a gaitflow recording:

- one MCAP channel per bus key (``gaitflow/<site>/<camera>/<stream>``), topic = the key;
- one MCAP schema per stream, encoding ``jsonschema``: the stream's JSON Schema
  (:func:`gaitflow.schemas.json_schema`), named ``gaitflow/<stream>/v<version>``;
- message encoding ``msgpack``: each MCAP message is the bus payload byte for byte;
- ``log_time`` = the header's capture time, ``publish_time`` = the header's publish time
  (both ns). A payload whose header cannot be read is still recorded (the recorder keeps what
  was on the bus), with the receive time as both times, and counted as malformed;
- chunk compression ``zstd`` (optionally with a level, ``zstd:1``), ``lz4`` or ``none``.
  Chunks are closed when they exceed ``chunk_size`` bytes or are older than
  ``flush_interval_s``, so a killed recorder loses at most that much.

The reader scans records in file order. On a file cut short (a recorder killed, a disk
full) it yields every message of the complete chunks and reports the file as truncated
instead of failing; a file that is not MCAP at all raises :class:`InputError`.
"""

from __future__ import annotations

import io
import json
import logging
import os
import queue
import struct
import threading
import time
import zlib
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import zstandard
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
    SummaryOffset,
)

from gaitflow import __version__
from gaitflow.errors import ConfigError, InputError, SchemaError
from gaitflow.schemas import STREAMS, decode, json_schema, peek_header
from gaitflow.schemas import Message as BusMessage

log = logging.getLogger("gaitflow.recording")

MAGIC = b"\x89MCAP0\r\n"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "msgpack"
PROFILE = "gaitflow"
# Chosen by ``gaitflow bench mcap`` (see docs/readme/recording.md): zstd level 1 compresses a
# raw frame in about the time lz4 takes (~2.3 ms) but makes files ~28% smaller; zstd at its
# default level 3 costs ~3x more per frame for another ~13%.
DEFAULT_COMPRESSION = "zstd:1"
DEFAULT_CHUNK_SIZE = 4 << 20
DEFAULT_FLUSH_INTERVAL_S = 1.0
COMPRESSIONS = ("zstd", "lz4", "none")
# Record header: opcode (u8) and length (u64).
_REC_HDR = struct.Struct("<BQ")


# --------------------------------------------------------------------------- compression


@dataclass(frozen=True)
class Compression:
    """A chunk compression: ``name`` in zstd/lz4/none and an optional ``level``."""

    name: str
    level: int | None = None

    @classmethod
    def parse(cls, spec: str) -> Compression:
        """``zstd``, ``zstd:<level>``, ``lz4``, ``lz4:<level>`` or ``none``."""
        name, _, lvl = str(spec).strip().lower().partition(":")
        if name not in COMPRESSIONS:
            raise ConfigError(f"compression {spec!r} is not one of zstd[:level], lz4, none")
        if not lvl:
            return cls(name)
        if name == "none":
            raise ConfigError(f"compression {spec!r}: 'none' takes no level")
        try:
            return cls(name, int(lvl))
        except ValueError as exc:
            raise ConfigError(f"compression {spec!r}: level {lvl!r} is not an integer") from exc

    @property
    def label(self) -> str:
        return self.name if self.level is None else f"{self.name}:{self.level}"

    @property
    def mcap_name(self) -> str:
        """The chunk ``compression`` string MCAP readers expect."""
        return "" if self.name == "none" else self.name

    def compressor(self) -> Callable[[bytes], bytes]:
        if self.name == "zstd":
            import zstandard

            # Level 3 is zstandard's (and the mcap library's) default.
            zc = zstandard.ZstdCompressor(level=3 if self.level is None else self.level)
            return zc.compress
        if self.name == "lz4":
            import lz4.frame

            lvl = 0 if self.level is None else self.level
            return lambda data: lz4.frame.compress(data, compression_level=lvl)
        return bytes


def _decompress(name: str, data: bytes, size: int) -> bytes:
    if name == "":
        return data
    if name == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if name == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise McapError(f"unsupported chunk compression {name!r}")


# --------------------------------------------------------------------------- writing


def stream_of(key: str) -> str:
    """The stream name of a bus key: its last segment."""
    return str(key).rsplit("/", 1)[-1]


def _header_times(payload: bytes, fallback_ns: int) -> tuple[int, int, bool]:
    """(log_time, publish_time, ok) from a payload's header; fallback when unreadable."""
    try:
        hdr = peek_header(payload)
        cap, pub = hdr.get("capture_ns"), hdr.get("publish_ns")
        if isinstance(cap, int) and isinstance(pub, int) and cap >= 0 and pub >= 0:
            return cap, pub, True
    except SchemaError:
        pass  # counted by the caller through ok=False
    return fallback_ns, fallback_ns, False


@dataclass
class WriterStats:
    """What a writer has written so far."""

    messages: int = 0
    payload_bytes: int = 0
    chunks: int = 0
    malformed: int = 0
    per_key: dict[str, int] = field(default_factory=lambda: defaultdict(int))


class McapWriter:
    """Write bus payloads to an MCAP file, one channel per key (not thread-safe).

    Parameters
    ----------
    path : output file (created or truncated) or a binary stream.
    compression : ``Compression`` or spec string (``zstd``, ``zstd:1``, ``lz4``, ``none``).
    chunk_size : close a chunk once its uncompressed size exceeds this many bytes.
    flush_interval_s : also close a chunk (and flush the file) when its first message is
        older than this, so a killed writer loses at most this much. ``None``: size only.
    metadata : string pairs stored in the file as an MCAP metadata record ``gaitflow``.
    """

    def __init__(
        self,
        path: str | Path | BinaryIO,
        compression: Compression | str = DEFAULT_COMPRESSION,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval_s: float | None = DEFAULT_FLUSH_INTERVAL_S,
        metadata: dict[str, str] | None = None,
    ) -> None:
        self.compression = (
            compression if isinstance(compression, Compression) else Compression.parse(compression)
        )
        self._compress = self.compression.compressor()
        self.chunk_size = int(chunk_size)
        self.flush_interval_s = flush_interval_s
        if isinstance(path, str | Path):
            self.path: str = str(path)
            try:
                self._f: BinaryIO = open(path, "wb")  # noqa: SIM115 - closed in close()
            except OSError as exc:
                raise InputError(path, f"cannot create recording: {exc.strerror}") from exc
            self._own = True
        else:
            self.path, self._f, self._own = getattr(path, "name", "<stream>"), path, False
        self._pos = 0
        self._schemas: dict[str, Schema] = {}
        self._schemas_written: set[int] = set()
        self._channels: dict[str, Channel] = {}
        self._seq: dict[int, int] = defaultdict(int)
        self._chunk = RecordBuilder()
        self._chunk_msgs = 0
        self._chunk_start = 0
        self._chunk_end = 0
        self._chunk_index: dict[int, list[tuple[int, int]]] = {}
        self._chunk_opened = 0.0
        self._chunk_indexes: list[ChunkIndex] = []
        self._start_time: int | None = None
        self._end_time = 0
        self._counts: dict[int, int] = defaultdict(int)
        self.stats = WriterStats()
        self._metadata_count = 1 if metadata else 0
        self.closed = False
        self._write(MAGIC)
        b = RecordBuilder()
        Header(profile=PROFILE, library=f"gaitflow/{__version__}").write(b)
        if metadata:
            Metadata(name="gaitflow", metadata=dict(metadata)).write(b)
        self._write(b.end())

    def _write(self, data: bytes) -> None:
        self._f.write(data)
        self._pos += len(data)

    def _schema_for(self, stream: str) -> Schema | None:
        cls = STREAMS.get(stream)
        if cls is None:
            return None
        if stream not in self._schemas:
            self._schemas[stream] = Schema(
                id=len(self._schemas) + 1,
                name=f"gaitflow/{stream}/v{cls.VERSION}",
                encoding=SCHEMA_ENCODING,
                data=json.dumps(json_schema(cls)).encode(),
            )
        return self._schemas[stream]

    def _channel_for(self, key: str) -> Channel:
        ch = self._channels.get(key)
        if ch is None:
            stream = stream_of(key)
            schema = self._schema_for(stream)
            ch = Channel(
                id=len(self._channels) + 1,
                topic=key,
                message_encoding=MESSAGE_ENCODING,
                schema_id=schema.id if schema else 0,
                metadata={"stream": stream},
            )
            self._channels[key] = ch
            # Schema and channel records go into the data section before the first chunk
            # that uses them, so a truncated file stays readable up to its last chunk.
            b = RecordBuilder()
            if schema is not None and schema.id not in self._schemas_written:
                schema.write(b)
                self._schemas_written.add(schema.id)
            ch.write(b)
            self._write(b.end())
        return ch

    def write(
        self,
        key: str,
        payload: bytes | bytearray | memoryview,
        log_time_ns: int | None = None,
        publish_time_ns: int | None = None,
    ) -> None:
        """Append one payload on ``key``; times default to the payload header's."""
        if self.closed:
            raise InputError(self.path, "write after close")
        data = bytes(payload)
        if log_time_ns is None or publish_time_ns is None:
            lt, pt, ok = _header_times(data, time.time_ns())
            if not ok:
                self.stats.malformed += 1
            log_time_ns = lt if log_time_ns is None else log_time_ns
            publish_time_ns = pt if publish_time_ns is None else publish_time_ns
        ch = self._channel_for(key)
        seq = self._seq[ch.id]
        self._seq[ch.id] = seq + 1
        if self._chunk_msgs == 0:
            self._chunk_start = self._chunk_end = log_time_ns
            self._chunk_opened = time.monotonic()
        self._chunk_start = min(self._chunk_start, log_time_ns)
        self._chunk_end = max(self._chunk_end, log_time_ns)
        self._chunk_index.setdefault(ch.id, []).append((log_time_ns, self._chunk.count))
        Message(
            channel_id=ch.id,
            sequence=seq & 0xFFFFFFFF,
            log_time=log_time_ns,
            publish_time=publish_time_ns,
            data=data,
        ).write(self._chunk)
        self._chunk_msgs += 1
        self._counts[ch.id] += 1
        self._start_time = (
            log_time_ns if self._start_time is None else min(self._start_time, log_time_ns)
        )
        self._end_time = max(self._end_time, log_time_ns)
        self.stats.messages += 1
        self.stats.payload_bytes += len(data)
        self.stats.per_key[key] += 1
        if self._chunk.count >= self.chunk_size:
            self._finish_chunk()
        else:
            self.poll()

    def poll(self) -> None:
        """Close the open chunk if it is older than ``flush_interval_s``."""
        if (
            self._chunk_msgs
            and self.flush_interval_s is not None
            and time.monotonic() - self._chunk_opened >= self.flush_interval_s
        ):
            self.flush()

    def _finish_chunk(self) -> None:
        if not self._chunk_msgs:
            return
        raw = self._chunk.end()
        comp = self._compress(raw)
        chunk = Chunk(
            message_start_time=self._chunk_start,
            message_end_time=self._chunk_end,
            uncompressed_size=len(raw),
            uncompressed_crc=zlib.crc32(raw),
            compression=self.compression.mcap_name,
            data=comp,
        )
        b = RecordBuilder()
        chunk.write(b)
        chunk_bytes = b.end()
        chunk_offset = self._pos
        self._write(chunk_bytes)
        index_start = self._pos
        offsets: dict[int, int] = {}
        for cid, recs in self._chunk_index.items():
            offsets[cid] = index_start + b.count
            MessageIndex(channel_id=cid, records=recs).write(b)
        index_bytes = b.end()
        self._write(index_bytes)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=chunk.message_start_time,
                message_end_time=chunk.message_end_time,
                chunk_start_offset=chunk_offset,
                chunk_length=len(chunk_bytes),
                message_index_offsets=offsets,
                message_index_length=len(index_bytes),
                compression=chunk.compression,
                compressed_size=len(comp),
                uncompressed_size=len(raw),
            )
        )
        self.stats.chunks += 1
        self._chunk_msgs = 0
        self._chunk_index = {}

    def flush(self) -> None:
        """Close the open chunk and flush the file (it stays readable up to here)."""
        self._finish_chunk()
        self._f.flush()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self.closed:
            return
        self._finish_chunk()
        b = RecordBuilder()
        DataEnd(data_section_crc=0).write(b)
        self._write(b.end())
        summary_start = self._pos
        groups: list[tuple[int, bytes]] = []
        for opcode, recs in (
            (Opcode.SCHEMA, list(self._schemas.values())),
            (Opcode.CHANNEL, list(self._channels.values())),
            (
                Opcode.STATISTICS,
                [
                    Statistics(
                        message_count=self.stats.messages,
                        schema_count=len(self._schemas),
                        channel_count=len(self._channels),
                        attachment_count=0,
                        metadata_count=self._metadata_count,
                        chunk_count=self.stats.chunks,
                        message_start_time=self._start_time or 0,
                        message_end_time=self._end_time,
                        channel_message_counts=dict(self._counts),
                    )
                ],
            ),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
        ):
            for r in recs:
                r.write(b)
            groups.append((opcode, b.end()))
        summary = b""
        offsets = RecordBuilder()
        pos = summary_start
        for opcode, data in groups:
            if data:
                SummaryOffset(group_opcode=opcode, group_start=pos, group_length=len(data)).write(
                    offsets
                )
            summary += data
            pos += len(data)
        offset_start = summary_start + len(summary)
        summary += offsets.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
        self._write(summary)
        footer = Footer(
            summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc
        )
        footer.write(b)
        self._write(b.end() + MAGIC)
        self._f.flush()
        if self._own:
            os.fsync(self._f.fileno())
            self._f.close()
        self.closed = True

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class RecorderStats:
    """Counts of a :class:`Recorder`.

    ``received``: accepted into the queue (each is written or counted in ``write_errors``);
    ``dropped``: refused because the queue was full; ``late``: arrived after ``close``
    began (a callback racing the shutdown), not recorded.
    """

    received: int = 0
    written: int = 0
    dropped: int = 0
    late: int = 0
    malformed: int = 0
    write_errors: int = 0
    queue_peak_bytes: int = 0

    def line(self) -> str:
        return (
            f"received {self.received}, written {self.written}, dropped {self.dropped}, "
            f"malformed {self.malformed}, write errors {self.write_errors}, "
            f"late {self.late}"
        )


@dataclass(frozen=True)
class _Rotate:
    path: str | Path | McapWriter
    on_closed: Callable[[str], None] | None


class Recorder:
    """A thread-safe recorder: bus callbacks enqueue, a writer thread writes MCAP.

    The bus callback (``offer``) only copies the payload reference into a queue, so Zenoh's
    threads never wait for compression or the disk. The queue is bounded by bytes
    (``max_queue_bytes``); when it is full the newest payload is dropped and counted,
    because a recorder must never stall the pipeline it observes. ``close`` stops
    accepting, writes everything queued, and closes the file: every payload ``offer``
    accepted (``stats.received``) is in the file.

    Parameters
    ----------
    path : output MCAP file, or an already open :class:`McapWriter` (e.g. a ring buffer
        that rotates files).
    max_queue_bytes : bound on queued payload bytes (default 512 MiB, ~600 raw frames).
    **writer_kw : passed to :class:`McapWriter` (compression, chunk_size, ...).
    """

    def __init__(
        self,
        path: str | Path | McapWriter,
        max_queue_bytes: int = 512 << 20,
        **writer_kw: Any,
    ) -> None:
        self.writer = path if isinstance(path, McapWriter) else McapWriter(path, **writer_kw)
        self.max_queue_bytes = int(max_queue_bytes)
        self.stats = RecorderStats()
        self._writer_kw = writer_kw
        self._q: queue.Queue[Any] = queue.Queue()
        self._lock = threading.Lock()
        self._queued_bytes = 0
        self._accepting = True
        self._closed = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="gaitflow-recorder", daemon=True)
        self._thread.start()

    def offer(self, key: str, payload: bytes) -> bool:
        """Queue one payload (call from the bus callback). False when dropped."""
        n = len(payload)
        with self._lock:
            if self._closed:
                self.stats.late += 1
                return False
            if not self._accepting or self._queued_bytes + n > self.max_queue_bytes:
                self.stats.dropped += 1
                return False
            self._queued_bytes += n
            self.stats.queue_peak_bytes = max(self.stats.queue_peak_bytes, self._queued_bytes)
            self.stats.received += 1
        self._q.put((key, payload, time.time_ns()))
        return True

    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:
            # The writer thread must not die silently while offers keep being accepted:
            # stop accepting (later offers count as dropped) and let close() raise.
            with self._lock:
                self._accepting = False
            self._error = exc
            log.exception("recorder: writer thread failed")

    def _loop(self) -> None:
        while True:
            try:
                item = self._q.get(timeout=0.2)
            except queue.Empty:
                self._poll()
                continue
            if item is None:
                return
            if isinstance(item, _Rotate):
                self._switch(item)
                continue
            key, payload, recv_ns = item
            with self._lock:
                self._queued_bytes -= len(payload)
            try:
                lt, pt, ok = _header_times(payload, recv_ns)
                self.writer.write(key, payload, lt, pt)
            except (OSError, InputError, McapError) as exc:
                self.stats.write_errors += 1
                self._error = exc
                log.error("recorder: cannot write %s: %s", key, exc)
                continue
            self.stats.written += 1
            if not ok:
                self.stats.malformed += 1

    def _poll(self) -> None:
        try:
            self.writer.poll()
        except OSError as exc:
            self.stats.write_errors += 1
            self._error = exc
            log.error("recorder: cannot flush %s: %s", self.writer.path, exc)

    def rotate(
        self,
        path: str | Path | McapWriter,
        on_closed: Callable[[str], None] | None = None,
    ) -> None:
        """Continue in a new file: payloads offered before go to the old one, after to the new.

        The switch happens on the writer thread, in queue order; the old file is closed
        (complete, with its summary) and ``on_closed(old_path)`` is called there, e.g. for a
        ring buffer to delete its oldest file.
        """
        with self._lock:
            if self._closed:
                raise InputError(self.writer.path, "rotate after close")
        self._q.put(_Rotate(path, on_closed))

    def _switch(self, item: _Rotate) -> None:
        old = self.writer
        try:
            old.close()
            new = item.path
            self.writer = new if isinstance(new, McapWriter) else McapWriter(new, **self._writer_kw)
        except (OSError, InputError) as exc:
            self.stats.write_errors += 1
            self._error = exc
            log.error("recorder: cannot rotate %s: %s", old.path, exc)
            return
        if item.on_closed is not None:
            item.on_closed(old.path)

    @property
    def queued_bytes(self) -> int:
        return self._queued_bytes

    def close(self) -> RecorderStats:
        """Stop accepting, write what is queued, close the file; return the counts."""
        with self._lock:
            if self._closed:
                return self.stats
            self._closed = True
            self._accepting = False
        self._q.put(None)
        self._thread.join()
        try:
            self.writer.close()
        except OSError as exc:
            self._error = self._error or exc
        if self._error is not None:
            raise InputError(self.writer.path, f"recording incomplete: {self._error}")
        return self.stats

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- reading


class RecordedMessage(NamedTuple):
    """One recorded bus message: unpacks as ``(key, payload, log_time_ns, publish_time_ns)``."""

    key: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int

    @property
    def stream(self) -> str:
        return stream_of(self.key)


class DecodedMessage(NamedTuple):
    """A recorded message decoded with its stream's schema."""

    key: str
    message: BusMessage
    log_time_ns: int
    publish_time_ns: int

    @property
    def stream(self) -> str:
        return stream_of(self.key)


@dataclass
class ChannelInfo:
    id: int
    topic: str
    stream: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None


@dataclass
class RecordingInfo:
    """What :func:`inspect_recording` found in a file."""

    path: str
    size: int
    library: str = ""
    profile: str = ""
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    compressions: set[str] = field(default_factory=set)
    chunks: int = 0
    messages: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    truncated: bool = False
    truncation: str = ""
    read_bytes: int = 0

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9


class McapReader:
    """Scan an MCAP file in order, tolerating a truncated tail.

    After iterating, ``truncated`` tells whether the file ended before its footer, and
    ``truncation`` says where and why. ``info`` accumulates channels, counts and times.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        try:
            self._f = open(path, "rb")  # noqa: SIM115 - closed in close()
        except OSError as exc:
            raise InputError(path, f"cannot open recording: {exc.strerror}") from exc
        self.size = os.fstat(self._f.fileno()).st_size
        head = self._f.read(len(MAGIC))
        if head != MAGIC:
            self._f.close()
            raise InputError(path, "not an MCAP file (bad magic)")
        self.info = RecordingInfo(self.path, self.size)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}

    @property
    def truncated(self) -> bool:
        return self.info.truncated

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> McapReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _truncated(self, pos: int, why: str) -> None:
        self.info.truncated = True
        self.info.truncation = (
            f"file is truncated at byte {pos} of {self.size} ({why}); read "
            f"{self.info.chunks} complete chunk(s), {self.info.messages} message(s)"
        )

    def _note(self, rec: Any) -> None:
        if isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            if rec.id not in self.channels:
                self.channels[rec.id] = rec
                sc = self.schemas.get(rec.schema_id)
                self.info.channels[rec.id] = ChannelInfo(
                    rec.id,
                    rec.topic,
                    rec.metadata.get("stream", stream_of(rec.topic)),
                    sc.name if sc else "",
                    sc.encoding if sc else "",
                    rec.message_encoding,
                )
        elif isinstance(rec, Header):
            self.info.library, self.info.profile = rec.library, rec.profile

    def records(self, progress: Callable[[int], None] | None = None) -> Iterator[Any]:
        """Yield the records of the data section, chunks expanded, in file order."""
        f, pos = self._f, len(MAGIC)
        f.seek(pos)
        while True:
            hdr = f.read(_REC_HDR.size)
            if len(hdr) == 0:
                self._truncated(pos, "no footer")
                return
            if len(hdr) < _REC_HDR.size:
                self._truncated(pos, "partial record header")
                return
            opcode, length = _REC_HDR.unpack(hdr)
            if pos + _REC_HDR.size + length > self.size:
                self._truncated(pos, f"record of {length} bytes runs past the end")
                return
            body = f.read(length)
            start, pos = pos, pos + _REC_HDR.size + length
            if progress is not None:
                progress(pos)
            self.info.read_bytes = pos
            if opcode == Opcode.FOOTER:
                return
            if opcode not in (
                Opcode.HEADER,
                Opcode.SCHEMA,
                Opcode.CHANNEL,
                Opcode.MESSAGE,
                Opcode.CHUNK,
            ):
                continue  # indexes, statistics and summaries are recomputed from the data
            try:
                rec = _read_record(opcode, body, length)
            except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
                raise InputError(self.path, f"corrupt record at byte {start}: {exc}") from exc
            if isinstance(rec, Chunk):
                yield from self._chunk_records(rec, start)
                self.info.chunks += 1
                self.info.compressions.add(rec.compression or "none")
            else:
                self._note(rec)
                yield rec

    def _chunk_records(self, chunk: Chunk, start: int) -> Iterator[Any]:
        try:
            data = _decompress(chunk.compression, chunk.data, chunk.uncompressed_size)
        except (zstandard.ZstdError, RuntimeError, McapError, ValueError) as exc:
            raise InputError(self.path, f"corrupt chunk at byte {start}: {exc}") from exc
        if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
            raise InputError(self.path, f"corrupt chunk at byte {start}: CRC mismatch")
        pos, end = 0, len(data)
        out = []
        while pos < end:
            if pos + _REC_HDR.size > end:
                raise InputError(self.path, f"corrupt chunk at byte {start}: partial record")
            opcode, length = _REC_HDR.unpack_from(data, pos)
            body = data[pos + _REC_HDR.size : pos + _REC_HDR.size + length]
            if len(body) < length:
                raise InputError(self.path, f"corrupt chunk at byte {start}: partial record")
            pos += _REC_HDR.size + length
            if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                try:
                    rec = _read_record(opcode, body, length)
                except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
                    raise InputError(self.path, f"corrupt chunk at byte {start}: {exc}") from exc
                self._note(rec)
                out.append(rec)
        # A chunk counts only once it is fully parsed: yield afterwards.
        yield from out

    def messages(
        self,
        streams: Iterable[str] | None = None,
        progress: Callable[[int], None] | None = None,
    ) -> Iterator[RecordedMessage]:
        """Yield recorded messages in file order, optionally only of ``streams``."""
        want = set(streams) if streams else None
        for rec in self.records(progress):
            if not isinstance(rec, Message):
                continue
            ch = self.channels.get(rec.channel_id)
            if ch is None:
                raise InputError(
                    self.path, f"message on unknown channel {rec.channel_id} (corrupt file)"
                )
            ci = self.info.channels[ch.id]
            ci.count += 1
            ci.first_ns = rec.log_time if ci.first_ns is None else min(ci.first_ns, rec.log_time)
            ci.last_ns = rec.log_time if ci.last_ns is None else max(ci.last_ns, rec.log_time)
            self.info.messages += 1
            s, e = self.info.start_ns, self.info.end_ns
            self.info.start_ns = rec.log_time if s is None else min(s, rec.log_time)
            self.info.end_ns = rec.log_time if e is None else max(e, rec.log_time)
            if want is not None and ci.stream not in want:
                continue
            yield RecordedMessage(ch.topic, rec.data, rec.log_time, rec.publish_time)


def count_hint(path: str | Path, streams: Iterable[str] | None = None) -> int | None:
    """Message count from a complete file's summary (None if there is none), for progress.

    Reads only the footer and the summary section, so it is cheap; a truncated file has
    no summary and gives None (the reader then finds out what is there).
    """
    want = set(streams) if streams else None
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        tail = _REC_HDR.size + 20 + len(MAGIC)
        if size < len(MAGIC) + tail:
            return None
        f.seek(size - tail)
        end = f.read(tail)
        opcode, length = _REC_HDR.unpack_from(end)
        if end[-len(MAGIC) :] != MAGIC or opcode != Opcode.FOOTER or length != 20:
            return None
        summary_start, offsets_start, _crc = struct.unpack_from("<QQI", end, _REC_HDR.size)
        summary_end = offsets_start or size - tail
        if not 0 < summary_start <= summary_end <= size - tail:
            return None
        f.seek(summary_start)
        summary = f.read(summary_end - summary_start)
    stats, streams_of = None, {}
    pos = 0
    while pos + _REC_HDR.size <= len(summary):
        opcode, length = _REC_HDR.unpack_from(summary, pos)
        body = summary[pos + _REC_HDR.size : pos + _REC_HDR.size + length]
        pos += _REC_HDR.size + length
        try:
            if opcode == Opcode.STATISTICS:
                stats = Statistics.read(ReadDataStream(io.BytesIO(body)))
            elif opcode == Opcode.CHANNEL:
                ch = Channel.read(ReadDataStream(io.BytesIO(body)))
                streams_of[ch.id] = ch.metadata.get("stream", stream_of(ch.topic))
        except (McapError, struct.error, UnicodeDecodeError, ValueError):
            return None  # a damaged summary is only a missing hint; the scan reports damage
    if stats is None:
        return None
    if want is None:
        return int(stats.message_count)
    counts = stats.channel_message_counts
    return sum(int(n) for cid, n in counts.items() if streams_of.get(cid) in want)


def _read_record(opcode: int, body: bytes, length: int) -> Any:
    s = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.MESSAGE:
        return Message.read(s, length)
    return {
        Opcode.HEADER: Header,
        Opcode.SCHEMA: Schema,
        Opcode.CHANNEL: Channel,
        Opcode.CHUNK: Chunk,
    }[Opcode(opcode)].read(s)


def iter_messages(
    path: str | Path,
    streams: Iterable[str] | None = None,
    allow_truncated: bool = True,
) -> Iterator[RecordedMessage]:
    """Yield ``(key, payload, log_time_ns, publish_time_ns)`` of a recording in file order.

    A truncated file yields every message of its complete chunks, then logs a warning, or
    raises :class:`InputError` when ``allow_truncated`` is false.
    """
    with McapReader(path) as r:
        yield from r.messages(streams)
        if r.truncated:
            if not allow_truncated:
                raise InputError(path, r.info.truncation)
            log.warning("%s: %s", path, r.info.truncation)


def iter_decoded(
    path: str | Path,
    streams: Iterable[str] | None = None,
    allow_truncated: bool = True,
) -> Iterator[DecodedMessage]:
    """Like :func:`iter_messages`, with each payload decoded by its stream's schema.

    Raises :class:`SchemaError` for a payload of an unknown stream or a bad payload.
    """
    for m in iter_messages(path, streams, allow_truncated):
        cls = STREAMS.get(m.stream)
        if cls is None:
            raise SchemaError(m.stream, "header.schema", f"unknown stream in {path}")
        yield DecodedMessage(m.key, decode(cls, m.payload), m.log_time_ns, m.publish_time_ns)


def inspect_recording(
    path: str | Path, progress: Callable[[int], None] | None = None
) -> RecordingInfo:
    """Scan a recording: channels, schemas, counts, times, compression, truncation."""
    with McapReader(path) as r:
        for _ in r.messages(progress=progress):
            pass
        return r.info
