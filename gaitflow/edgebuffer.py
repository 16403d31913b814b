"""Edge fault tolerance: the uplink to the server, with an MCAP ring as its queue.

On an edge, the stages talk over a loopback router; the **uplink** is the one process that
talks to the server. It subscribes to the camera's streams on the local bus and appends
every payload to an on-disk **ring** of MCAP segments (``gaitflow.recording.McapWriter``
files, one channel per key, the bus payload byte for byte). A sender thread forwards the
ring to the server's router in order, as a Zenoh client over mutual TLS. The ring *is*
the queue, so:

- while the link is down the edge keeps recording (the ring grows; the oldest segments
  are evicted beyond ``max_bytes``, and evicted frames that were never sent are counted);
- when the link returns the sender resumes from where the server last certainly had
  frames, so the backlog is forwarded in capture order and no captured frame is lost;
- a slow or absent server never blocks the local bus: the subscriber callback only
  appends to the ring, so grab never drops a frame the recorder needs on the uplink's
  account.

**Link detection**: the server's router holds a liveliness token
(``gaitflow/<site>/@alive/router/<server>``); the uplink watches it on the remote session.
A vanished token (router gone, link cut, lease expired) marks the link down. Frames sent
in the last ``resend_margin_s`` before the drop was noticed may have died in flight, so
the sender rewinds to them: the server drops the duplicates with :class:`Deduper`, keyed
by (camera, trial, frame, stream, capture time) from the message header (the server role's
stages do it on their inputs: ``runtime.dedupe`` in the generated stage config).

Times: ``time.monotonic()`` seconds for link bookkeeping; payload headers carry ns.
"""

from __future__ import annotations

import bisect
import json
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from types import FrameType
from typing import Any

from gaitflow.bus.config import BusConfig
from gaitflow.bus.keys import stream_key
from gaitflow.errors import BusError, ConfigError, GaitflowError, SchemaError
from gaitflow.recording import McapWriter, iter_messages
from gaitflow.schemas import Header, peek_header

log = logging.getLogger("gaitflow.edgebuffer")

# How often the uplink records how far it got (a restart resends at most this much).
CURSOR_SAVE_S = 0.5


# --------------------------------------------------------------------------- ring


@dataclass
class _Segment:
    first: int
    count: int
    path: Path
    size: int


class Ring:
    """An append-only sequence of bus payloads kept as MCAP segments in ``directory``.

    Sequence numbers grow by one per appended payload. The open segment is also held in
    memory (it is not a finished MCAP file yet); closed segments are read back from disk.
    Thread-safe.

    **Restarts**: segments left by a previous run (a crash, a reboot, an upgrade while the
    link was down) are kept and numbered from their file names; a segment cut short by a
    crash is read up to its last complete chunk. The uplink saves how far it got
    (:meth:`save_cursor`, ``cursor.json``) and resumes from there, so a backlog survives
    the uplink process.

    Parameters
    ----------
    directory : where segment files ``ring-<first seq>.mcap`` go (created).
    max_bytes : evict the oldest closed segments beyond this total size on disk.
    segment_messages : close a segment after this many payloads.
    compression : MCAP chunk compression of the segments.

    Every payload is its own MCAP chunk, handed to the OS as it arrives: a crash of the
    uplink process loses nothing it had received (a power cut, what the OS had not
    written yet).
    """

    def __init__(
        self,
        directory: str | Path,
        max_bytes: int = 4 << 30,
        segment_messages: int = 256,
        compression: str = "none",
    ) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.max_bytes = int(max_bytes)
        self.segment_messages = max(1, int(segment_messages))
        self.compression = compression
        self._lock = threading.Condition()
        self._closed: list[_Segment] = []
        self._open_first = 0
        self._open: list[tuple[str, bytes]] = []
        self._writer: McapWriter | None = None
        self.next_seq = 0
        self.first_seq = 0
        self.evicted = 0
        self._resume()

    def _resume(self) -> None:
        """Take over the segments a previous run left, in sequence order."""
        found = []
        for path in self.dir.glob("ring-*.mcap"):
            try:
                first = int(path.stem.split("-", 1)[1])
            except ValueError:
                log.warning("ring: ignoring %s (not ring-<seq>.mcap)", path)
                continue
            found.append((first, path))
        for first, path in sorted(found):
            try:
                count = sum(1 for _ in iter_messages(path))
            except GaitflowError as exc:
                log.warning("ring: segment %s unreadable, skipped: %s", path, exc)
                continue
            if not self._closed:
                self.first_seq = first
            elif first < self.next_seq:
                log.warning("ring: segment %s overlaps the previous one, skipped", path)
                continue
            self._closed.append(_Segment(first, count, path, path.stat().st_size))
            self.next_seq = first + count
        self._open_first = self.next_seq

    def save_cursor(self, seq: int) -> None:
        """Remember that everything before ``seq`` was sent (atomic replace)."""
        tmp = self.dir / "cursor.json.tmp"
        tmp.write_text(json.dumps({"next": int(seq)}))
        os.replace(tmp, self.dir / "cursor.json")

    def load_cursor(self) -> int:
        """The saved cursor, or the oldest payload kept when there is none."""
        try:
            seq = int(json.loads((self.dir / "cursor.json").read_text())["next"])
        except FileNotFoundError:
            return self.first_seq
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("ring: unreadable cursor.json (%s): resending everything kept", exc)
            return self.first_seq
        return max(self.first_seq, min(seq, self.next_seq))

    def _writer_for(self) -> McapWriter:
        if self._writer is None:
            path = self.dir / f"ring-{self._open_first:012d}.mcap"
            self._writer = McapWriter(path, compression=self.compression, flush_interval_s=None)
        return self._writer

    def append(self, key: str, payload: bytes) -> int:
        """Add one payload; return its sequence number."""
        with self._lock:
            w = self._writer_for()
            w.write(key, payload)
            w.flush()
            self._open.append((key, payload))
            seq = self.next_seq
            self.next_seq += 1
            if len(self._open) >= self.segment_messages:
                self._close_segment()
            self._lock.notify_all()
            return seq

    def _close_segment(self) -> None:
        w = self._writer
        if w is None:
            return
        w.close()
        path = Path(w.path)
        self._closed.append(_Segment(self._open_first, len(self._open), path, path.stat().st_size))
        self._writer = None
        self._open_first = self.next_seq
        self._open = []
        total = sum(s.size for s in self._closed)
        while self._closed and total > self.max_bytes:
            old = self._closed.pop(0)
            total -= old.size
            old.path.unlink(missing_ok=True)
            self.first_seq = old.first + old.count
            self.evicted += old.count

    def wait(self, seq: int, timeout: float) -> bool:
        """Wait until payload ``seq`` exists; True if it does."""
        with self._lock:
            return self._lock.wait_for(lambda: self.next_seq > seq, timeout)

    def read_from(self, seq: int) -> Iterator[tuple[int, str, bytes]]:
        """Yield ``(seq, key, payload)`` from ``seq`` on (or from the oldest kept one)."""
        with self._lock:
            seq = max(seq, self.first_seq)
            segs = [s for s in self._closed if s.first + s.count > seq]
            open_first, open_items = self._open_first, list(self._open)
        for s in segs:
            try:
                for i, m in enumerate(iter_messages(s.path)):
                    if s.first + i >= seq:
                        yield s.first + i, m.key, m.payload
            except (GaitflowError, FileNotFoundError) as exc:
                # Evicted while we read: what was in it is lost (counted at eviction).
                log.warning("ring segment %s unreadable: %s", s.path, exc)
        for i, (key, payload) in enumerate(open_items):
            if open_first + i >= seq:
                yield open_first + i, key, payload

    def close(self) -> None:
        with self._lock:
            if self._writer is not None:
                self._writer.close()
                self._writer = None


# --------------------------------------------------------------------------- server side


class Deduper:
    """Drop payloads already seen, by (camera, trial, frame, stream, capture time) of their
    header.

    The uplink may resend frames around a link drop; the server keeps the first copy. A
    resend is the same payload, so its capture time is the same; the capture time is part of
    the identity because trial names and frame indices repeat (the next session's
    ``walk-01`` frame 0 is not a duplicate of this one's). A payload whose header cannot be
    read is passed on (and counted): the consumer decides.
    """

    def __init__(self, window: int = 1 << 16) -> None:
        self._seen: set[tuple[str, str, int, str, int]] = set()
        self._order: deque[tuple[str, str, int, str, int]] = deque()
        self.window = int(window)
        self.duplicates = 0
        self.unreadable = 0
        self._lock = threading.Lock()

    def first(self, payload: bytes) -> bool:
        """True the first time a (camera, trial, frame, stream, capture time) is seen."""
        try:
            h = peek_header(payload)
            ident = (
                str(h["camera"]),
                str(h["trial"]),
                int(h["frame"]),
                str(h["schema"]),
                int(h["capture_ns"]),
            )
        except (SchemaError, KeyError, TypeError, ValueError):
            self.unreadable += 1
            return True
        return self._first(ident)

    def first_header(self, h: Header) -> bool:
        """:meth:`first` for a decoded message's header."""
        return self._first((h.camera, h.trial, int(h.frame), h.schema, int(h.capture_ns)))

    def _first(self, ident: tuple[str, str, int, str, int]) -> bool:
        with self._lock:
            if ident in self._seen:
                self.duplicates += 1
                return False
            self._seen.add(ident)
            self._order.append(ident)
            if len(self._order) > self.window:
                self._seen.discard(self._order.popleft())
            return True


def dedupe(
    callback: Callable[[str, bytes], None], deduper: Deduper
) -> Callable[[str, bytes], None]:
    """Wrap a bus callback so it sees each (camera, trial, frame, stream) once."""

    def cb(key: str, payload: bytes) -> None:
        if deduper.first(payload):
            callback(key, payload)

    return cb


# --------------------------------------------------------------------------- uplink


@dataclass
class UplinkStats:
    """Counters of one uplink."""

    received: int = 0
    sent: int = 0
    resent: int = 0
    link_downs: int = 0
    link_ups: int = 0
    send_errors: int = 0
    evicted_unsent: int = 0
    cursor_save_errors: int = 0

    def line(self) -> str:
        return (
            f"received {self.received}, sent {self.sent} ({self.resent} resent), "
            f"link up {self.link_ups}x / down {self.link_downs}x, "
            f"evicted unsent {self.evicted_unsent}"
        )


class Uplink:
    """Forward a camera's streams from the local bus to the server, through a ring.

    Parameters
    ----------
    local : the edge's local bus (``Bus`` or ``FakeBus``): the uplink subscribes to it.
    remote_factory : opens a session to the server's router (called again after failures).
    site, camera : whose streams (keys ``gaitflow/<site>/<camera>/<stream>``).
    streams : stream names to forward.
    ring : the ring (its sequence numbers are the send order).
    server_token : the router's liveliness key; its presence means "link up".
    token : this uplink's own liveliness key on the remote side (None: none).
    resend_margin_s : on a link drop, resend what was sent this long before it was noticed.
    """

    def __init__(
        self,
        local: Any,
        remote_factory: Callable[[], Any],
        site: str,
        camera: str,
        streams: list[str] | tuple[str, ...],
        ring: Ring,
        server_token: str,
        token: str | None = None,
        resend_margin_s: float = 2.0,
    ) -> None:
        if not streams:
            raise ConfigError("uplink: no streams to forward")
        self.local, self.remote_factory = local, remote_factory
        self.site, self.camera, self.streams = site, camera, tuple(streams)
        self.ring, self.server_token, self.token = ring, server_token, token
        self.resend_margin_s = float(resend_margin_s)
        self.stats = UplinkStats()
        self._up = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._cursor = 0
        self._rewind_to: int | None = None
        # (monotonic send time, seq) of recent sends, for the rewind on a drop.
        self._sent_times: deque[tuple[float, int]] = deque()
        self._remote: Any = None
        self._max_sent = -1
        self._saved_at = 0.0
        self._subs: list[Any] = []
        self._thread: threading.Thread | None = None

    @property
    def link_up(self) -> bool:
        return self._up.is_set()

    @property
    def backlog(self) -> int:
        """Payloads in the ring not yet sent."""
        return self.ring.next_seq - self._cursor

    def _on_local(self, key: str, payload: bytes) -> None:
        self.ring.append(key, payload)
        self.stats.received += 1

    def _on_server(self, key: str, alive: bool) -> None:
        if alive:
            if not self._up.is_set():
                self.stats.link_ups += 1
                log.info("uplink %s: server link up", self.camera)
            self._up.set()
            return
        if self._up.is_set():
            self._mark_down()

    def _mark_down(self) -> None:
        with self._lock:
            if not self._up.is_set():
                return
            self._up.clear()
            self.stats.link_downs += 1
            since = time.monotonic() - self.resend_margin_s
            times = [t for t, _ in self._sent_times]
            i = bisect.bisect_left(times, since)
            target = self._cursor
            if i < len(self._sent_times):
                target = min(target, self._sent_times[i][1])
            self._rewind_to = target
            self._sent_times.clear()
        log.warning("uplink %s: server link down; recording to the ring", self.camera)

    def start(self) -> Uplink:
        # Resume after a restart: frames a previous run recorded but did not send go first.
        self._cursor = self.ring.load_cursor()
        self._max_sent = self._cursor - 1
        for s in self.streams:
            self._subs.append(
                self.local.subscribe(stream_key(self.site, self.camera, s), self._on_local)
            )
        self._thread = threading.Thread(target=self._run, name="uplink", daemon=True)
        self._thread.start()
        return self

    def _connect(self) -> bool:
        try:
            remote = self.remote_factory()
        except BusError as exc:
            log.info("uplink %s: server not reachable yet: %s", self.camera, exc)
            return False
        self._remote = remote
        remote.watch_liveliness(self.server_token, self._on_server, history=True)
        if self.token:
            remote.liveliness_token(self.token)
        return True

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._remote is None and not self._connect():
                self._stop.wait(0.5)
                continue
            if not self._up.wait(0.1):
                continue
            with self._lock:
                if self._rewind_to is not None:
                    self.stats.resent += max(0, self._max_sent + 1 - self._rewind_to)
                    self._cursor = max(self._rewind_to, self.ring.first_seq)
                    self._rewind_to = None
            self._save_cursor()
            if not self.ring.wait(self._cursor, 0.1):
                continue
            self._send_available()
        self._save_cursor(force=True)

    def _save_cursor(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._saved_at >= CURSOR_SAVE_S:
            self._saved_at = now
            with self._lock:
                # What was sent within the resend margin may still die with this process
                # (socket buffers): a restart resends it, as a link drop would.
                safe = self._cursor if self._rewind_to is None else self._rewind_to
                while self._sent_times and now - self._sent_times[0][0] > self.resend_margin_s:
                    self._sent_times.popleft()
                if self._sent_times:
                    safe = min(safe, self._sent_times[0][1])
            try:
                self.ring.save_cursor(safe)
            except OSError as exc:
                # A full disk must not stop forwarding; the cursor is an optimisation.
                self.stats.cursor_save_errors += 1
                log.warning("uplink %s: cannot save the ring cursor: %s", self.camera, exc)

    def _send_available(self) -> None:
        for seq, key, payload in self.ring.read_from(self._cursor):
            if self._stop.is_set() or not self._up.is_set():
                return
            self._save_cursor()
            with self._lock:
                if self._rewind_to is not None:
                    return
                if seq > self._cursor:
                    # Evicted before it could be sent: counted, never silent.
                    self.stats.evicted_unsent += seq - self._cursor
                # The cursor names the frame in flight, so a drop noticed meanwhile
                # rewinds to it at the latest.
                self._cursor = seq
            # Not under the lock: a put may block on a dying link until Zenoh closes it,
            # and the liveliness callback that marks the link down must not wait for it.
            try:
                self._remote.put(key, payload)
            except Exception as exc:  # noqa: BLE001 - any transport failure: count, retry
                with self._lock:
                    self.stats.send_errors += 1
                    if self._rewind_to is None:
                        self._rewind_to = seq
                log.warning("uplink %s: send failed (will retry): %s", self.camera, exc)
                # The link state stays with liveliness; pause so a broken session does
                # not spin, then resend from this frame.
                self._stop.wait(0.2)
                return
            with self._lock:
                self.stats.sent += 1
                self._max_sent = max(self._max_sent, seq)
                now = time.monotonic()
                self._sent_times.append((now, seq))
                while self._sent_times and now - self._sent_times[0][0] > self.resend_margin_s:
                    self._sent_times.popleft()
                if self._rewind_to is not None:
                    return
                self._cursor = seq + 1

    def drain(self, timeout: float) -> bool:
        """Wait until everything in the ring was sent (True) or ``timeout`` passed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._up.is_set() and self.backlog == 0:
                return True
            time.sleep(0.02)
        return False

    def stop(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs = []
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        if self._remote is not None:
            self._remote.close()
            self._remote = None
        self.ring.close()


# --------------------------------------------------------------------------- processes


def _role(path: str | Path) -> dict[str, Any]:
    from gaitflow.deployment import load_role

    return load_role(path)


def _wait_signal(stop: threading.Event) -> dict[int, Any]:
    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    return {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}


def router_config(role: dict[str, Any]) -> tuple[BusConfig, tuple[str, ...]]:
    """The router BusConfig and listen endpoints of a role config."""
    r = role.get("router") or {}
    extra: list[tuple[str, Any]] = [(str(k), v) for k, v in (r.get("extra") or {}).items()]
    if r.get("access_control"):
        extra.append(("access_control", r["access_control"]))
    cfg = BusConfig(site=str(role.get("site", "clinic")), tls=dict(r.get("tls") or {}))
    cfg = replace(cfg, extra=tuple(extra))
    listen = tuple(r.get("listen") or ())
    if not listen:
        raise ConfigError("role config: router.listen is empty")
    return cfg, listen


def run_router(path: str | Path, ready: threading.Event | None = None) -> int:
    """Run a role's router (with its liveliness token) until SIGINT/SIGTERM."""
    from gaitflow.bus.router import Router

    role = _role(path)
    cfg, listen = router_config(role)
    token = (role.get("router") or {}).get("token")
    stop = threading.Event()
    old = _wait_signal(stop)
    try:
        with Router(cfg, listen) as router:
            tok = router.session.liveliness().declare_token(token) if token else None
            print(f"gaitflow router ({role['role']}): listening on {', '.join(listen)}", flush=True)
            if ready is not None:
                ready.set()
            while not stop.wait(0.5):
                pass
            if tok is not None:
                tok.undeclare()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    return 0


def uplink_from_role(role: dict[str, Any], local: Any | None = None) -> Uplink:
    """Build (not start) the uplink of an edge role config."""
    from gaitflow.bus.session import Bus

    if role.get("role") != "edge":
        raise ConfigError(f"uplink: role config is {role.get('role')!r}, not edge")
    up = role["uplink"]
    remote_cfg = BusConfig.from_mapping(up["bus"], "uplink.bus")
    if local is None:
        local = Bus(BusConfig.from_mapping(role["bus"], "bus"))
    ring_doc = up.get("ring") or {}
    ring = Ring(
        ring_doc.get("dir", "ring"),
        max_bytes=int(ring_doc.get("max_bytes", 4 << 30)),
        segment_messages=int(ring_doc.get("segment_messages", 256)),
    )
    return Uplink(
        local,
        lambda: Bus(remote_cfg),
        site=str(role["site"]),
        camera=str(role["camera"]),
        streams=list(up["streams"]),
        ring=ring,
        server_token=str(up["server_token"]),
        token=up.get("token"),
        resend_margin_s=float(ring_doc.get("resend_margin_s", 2.0)),
    )


def run_uplink(path: str | Path) -> int:
    """Run an edge's uplink until SIGINT/SIGTERM."""
    role = _role(path)
    stop = threading.Event()
    old = _wait_signal(stop)
    uplink = uplink_from_role(role)
    try:
        uplink.start()
        print(
            f"gaitflow uplink {role['camera']}: forwarding {', '.join(uplink.streams)}", flush=True
        )
        while not stop.wait(5.0):
            log.info("uplink %s: %s", role["camera"], uplink.stats.line())
    finally:
        uplink.stop()
        uplink.local.close()
        for s, h in old.items():
            signal.signal(s, h)
    print(f"gaitflow uplink {role['camera']}: {uplink.stats.line()}", flush=True)
    return 0


# --------------------------------------------------------------------------- watcher


class StageWatcher:
    """``gaitflow_stage_up{stage, worker}`` (1/0) from the stages' liveliness tokens.

    Expected stages (from the role config) start at 0, so a stage that never came up
    alerts as well as one that went away.
    """

    def __init__(self, bus: Any, site: str, expected: list[tuple[str, int | str]]) -> None:
        from prometheus_client import CollectorRegistry, Gauge

        self.registry = CollectorRegistry()
        self.up = Gauge(
            "gaitflow_stage_up",
            "1 while a stage worker's liveliness token is present",
            ("stage", "worker"),
            registry=self.registry,
        )
        for stage, worker in expected:
            self.up.labels(stage, str(worker)).set(0)
        self.site = site
        self._handle = bus.watch_liveliness(f"gaitflow/{site}/@alive/**", self._on, history=True)

    def _on(self, key: str, alive: bool) -> None:
        parts = key.split("/")
        if len(parts) < 5:
            return
        self.up.labels(parts[3], "/".join(parts[4:])).set(1 if alive else 0)

    def value(self, stage: str, worker: str = "0") -> float:
        v = self.registry.get_sample_value("gaitflow_stage_up", {"stage": stage, "worker": worker})
        return float("nan") if v is None else v


def run_watch(path: str | Path, port: int | None = None) -> int:
    """Serve ``gaitflow_stage_up`` for a role's machine until SIGINT/SIGTERM."""
    from prometheus_client.exposition import start_http_server

    from gaitflow.bus.session import Bus

    role = _role(path)
    w = role.get("watch") or {}
    host = str(w.get("metrics_host", "127.0.0.1"))
    port = int(w.get("metrics_port", 9100) if port is None else port)
    from gaitflow.deployment import role_plan

    expected: list[tuple[str, int | str]] = [(w.stage, w.worker_id) for w in role_plan(role)]
    stop = threading.Event()
    old = _wait_signal(stop)
    bus = Bus(BusConfig.from_mapping(role["bus"], "bus"))
    try:
        watcher = StageWatcher(bus, str(role["site"]), expected)
        httpd, _thread = start_http_server(port, addr=host, registry=watcher.registry)
        print(f"gaitflow watch: http://{host}:{port}/metrics", flush=True)
        while not stop.wait(0.5):
            pass
        httpd.shutdown()
    finally:
        bus.close()
        for s, h in old.items():
            signal.signal(s, h)
    return 0
