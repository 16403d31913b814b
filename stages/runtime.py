"""The bus adapter: runs one graph node's pure core over Zenoh (or the in-memory FakeBus).

Data path of a processing stage (:class:`StageRuntime`)::

    Zenoh callback --decode--> [replica filter] --> bounded queue --> worker thread:
        re-order per (stream, camera, trial) --> StageDriver (join, side inputs, core)
        --> encode --> publish gaitflow/<site>/<camera>/<stream>

- **Decoding** uses the stream's schema class (``gaitflow.schemas.STREAMS``). A payload
  that does not decode (``SchemaError``) is counted as malformed, logged as one line, and
  the stage keeps serving.
- **Replication**: with ``replicas = N`` worker ``i`` takes the primary-input frames whose
  index mod N = i (side inputs go to every worker). Downstream re-ordering merges them.
- **Bounded queue** with an explicit policy: ``block`` (back-pressure to Zenoh and, with
  congestion control BLOCK, to the publisher), ``drop-oldest``, or the default
  ``block-then-drop-oldest`` (block up to ``block_timeout_s``, then drop the oldest queued
  message). Every drop is counted. With ``block`` the bus callback runs the step itself
  when nothing is queued (no thread hand-over per frame; see ``_try_inline``).
- **Re-ordering** by frame index within a bounded window and with a timeout: frame
  indices have real gaps (a dropped frame, a replica that skipped one), so a missing index
  is waited for at most ``reorder_timeout_s`` or until ``reorder_window`` later frames are
  buffered. A frame that arrives after a later one was released is dropped as late
  (counted): stateful cores see frames in order or not at all.
- **Shutdown** (SIGINT/SIGTERM, :meth:`StageRuntime.stop`): stop taking input, process
  what is queued and buffered, call the core's ``finish``, publish, close. Outputs of one
  step are published together, so there are no partial outputs.
- **Metrics** (Prometheus, a per-runtime ``CollectorRegistry``): processing latency and
  end-to-end age since capture (histograms with fine buckets 1-250 ms, edges at 30, 33 and
  40 ms), frames in/out/dropped (by reason)/malformed, frames over the 33 ms budget.

Source stages (:class:`SourceRuntime`, a ``SourceSpec``) publish what their iterator
yields, paced by capture time (``rate="1"``) or as fast as the bus accepts (``"max"``).

The join and side-input logic is not here: it is :class:`~gaitflow.stages.driver.StageDriver`,
shared with the in-process runner.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import os
import signal
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from types import FrameType
from typing import Any

from gaitflow.bus.keys import liveliness_key, stream_key, stream_selector
from gaitflow.schemas import STREAMS, Message, decode
from gaitflow.stages.base import SourceSpec, StageSpec
from gaitflow.stages.driver import StageDriver
from gaitflow.stages.graph import Node
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.exposition import start_http_server

from gaitflow.errors import ConfigError, GaitflowError, InputError, SchemaError, StageError

log = logging.getLogger("gaitflow.runtime")

QUEUE_POLICIES = ("block", "drop-oldest", "block-then-drop-oldest")
RATES = ("1", "max")
# Seconds. Fine around the 33 ms frame budget (30 fps) so a histogram resolves it.
LATENCY_BUCKETS = (
    0.001, 0.002, 0.003, 0.004, 0.005, 0.0075, 0.01, 0.0125, 0.015, 0.0175, 0.02, 0.0225,
    0.025, 0.0275, 0.03, 0.033, 0.035, 0.0375, 0.04, 0.045, 0.05, 0.06, 0.07, 0.08, 0.09,
    0.1, 0.125, 0.15, 0.175, 0.2, 0.25,
)  # fmt: skip
AGE_BUCKETS = (*LATENCY_BUCKETS, 0.5, 1.0, 2.5, 5.0)
MALFORMED_LOG_EVERY = 100


def worker_id(camera: str, replicas: int, worker: int) -> str:
    """A stage worker's name in liveliness keys, metric labels and the launcher's status.

    ``"0"`` for the one worker of a stage; the replica index for replicas; the camera
    for a worker that takes one camera (``"cam-1"``, or ``"cam-1/0"`` if replicated).
    """
    if camera == "*":
        return str(worker)
    return camera if replicas == 1 else f"{camera}/{worker}"


@dataclass(frozen=True)
class RuntimeOptions:
    """How one stage worker runs on the bus (not the stage's algorithm parameters).

    ``metrics_port``: None = no metrics endpoint, 0 = pick a free port.
    """

    camera: str = "*"
    replicas: int = 1
    worker: int = 0
    queue_size: int = 32
    queue_policy: str = "block-then-drop-oldest"
    block_timeout_s: float = 0.25
    reorder_window: int = 16
    reorder_timeout_s: float = 0.25
    budget_s: float = 0.033
    metrics_port: int | None = None
    metrics_host: str = "127.0.0.1"
    rate: str = "1"
    shm: str = "auto"
    # Ignore a repeated input payload (same camera, trial, frame, stream and capture time;
    # counted in gaitflow_stage_duplicates_total): set on the server role, whose inputs
    # cross an edge's uplink, which resends what may have died in flight on a link drop.
    dedupe: bool = False

    def __post_init__(self) -> None:
        if self.replicas < 1:
            raise ConfigError(f"replicas must be >= 1, got {self.replicas}")
        if not 0 <= self.worker < self.replicas:
            raise ConfigError(f"worker must be in 0..{self.replicas - 1}, got {self.worker}")
        if self.queue_policy not in QUEUE_POLICIES:
            raise ConfigError(f"queue_policy {self.queue_policy!r} is not one of {QUEUE_POLICIES}")
        if self.queue_size < 1 or self.reorder_window < 1:
            raise ConfigError("queue_size and reorder_window must be >= 1")
        if self.shm not in ("auto", "off", "on"):
            raise ConfigError(f"shm {self.shm!r} is not one of auto, off, on")
        if self.rate not in RATES:
            raise ConfigError(f"rate {self.rate!r} is not one of {RATES}")
        if self.metrics_port is not None and not 0 <= self.metrics_port < 65536:
            raise ConfigError(f"metrics port {self.metrics_port} is not a TCP port")

    @property
    def worker_id(self) -> str:
        """This worker's name (see :func:`worker_id`)."""
        return worker_id(self.camera, self.replicas, self.worker)

    @classmethod
    def from_mapping(cls, doc: Mapping[str, Any], source: str = "runtime config") -> RuntimeOptions:
        """Options from a ``runtime:`` config section (unknown keys are an error)."""
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(doc) - set(known))
        if unknown:
            raise ConfigError(f"{source}: unknown runtime key(s) {unknown}")
        kw: dict[str, Any] = {}
        for k, v in doc.items():
            if k == "shm" and isinstance(v, bool):
                v = "on" if v else "off"  # YAML 1.1 reads a bare on/off as a boolean
            want = type(getattr(cls(), k)) if getattr(cls(), k) is not None else int
            try:
                kw[k] = v if v is None else want(v)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{source}: runtime.{k}={v!r} is not {want.__name__}") from exc
        return cls(**kw)


class StageMetrics:
    """The Prometheus metrics of one stage worker, in their own registry."""

    def __init__(
        self, stage: str, worker: int | str, registry: CollectorRegistry | None = None
    ) -> None:
        self.registry = registry or CollectorRegistry()
        lab = ("stage", "worker")
        r = self.registry
        val = (stage, str(worker))
        self.latency = Histogram(
            "gaitflow_stage_processing_seconds",
            "Time the core took per processed frame (join to outputs)",
            lab,
            buckets=LATENCY_BUCKETS,
            registry=r,
        ).labels(*val)
        self.age = Histogram(
            "gaitflow_stage_age_seconds",
            "End-to-end age of published frames since capture",
            lab,
            buckets=AGE_BUCKETS,
            registry=r,
        ).labels(*val)
        self.frames_in = Counter(
            "gaitflow_stage_frames_in", "Messages accepted from the bus", lab, registry=r
        ).labels(*val)
        self.frames_out = Counter(
            "gaitflow_stage_frames_out", "Messages published", lab, registry=r
        ).labels(*val)
        self._dropped = Counter(
            "gaitflow_stage_frames_dropped",
            "Messages dropped (reason: queue, late, join)",
            (*lab, "reason"),
            registry=r,
        )
        self.dropped = {k: self._dropped.labels(*val, k) for k in ("queue", "late", "join")}
        self.malformed = Counter(
            "gaitflow_stage_frames_malformed", "Payloads that failed to decode", lab, registry=r
        ).labels(*val)
        self.errors = Counter(
            "gaitflow_stage_errors", "Frames whose processing raised a GaitflowError", lab,
            registry=r,
        ).labels(*val)  # fmt: skip
        self.over_budget = Counter(
            "gaitflow_stage_frames_over_budget",
            "Processed frames that took longer than the frame budget (33 ms)",
            lab,
            registry=r,
        ).labels(*val)
        self.gaps = Counter(
            "gaitflow_stage_reorder_gaps",
            "Frame indices skipped by the re-order buffer after a timeout or a full window",
            lab,
            registry=r,
        ).labels(*val)
        self.duplicates = Counter(
            "gaitflow_stage_duplicates",
            "Repeated input payloads ignored (an edge uplink's resend after a link drop)",
            lab,
            registry=r,
        ).labels(*val)
        self.restarts = Gauge(
            "gaitflow_stage_restarts",
            "Times the launcher restarted this stage worker before this run",
            lab,
            registry=r,
        ).labels(*val)
        self.queue_depth = Gauge(
            "gaitflow_stage_queue_depth", "Messages waiting in the input queue", lab, registry=r
        ).labels(*val)


class MetricsServer:
    """``/metrics`` of a registry over HTTP on ``host:port`` (port 0 = a free one)."""

    def __init__(self, registry: CollectorRegistry, port: int, host: str = "127.0.0.1") -> None:
        try:
            self._httpd, self._thread = start_http_server(port, addr=host, registry=registry)
        except OSError as exc:
            raise ConfigError(f"cannot serve metrics on {host}:{port}: {exc}") from exc
        self.host = host
        self.port = int(self._httpd.server_port)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/metrics"

    def close(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()


class BoundedQueue:
    """A FIFO of at most ``maxsize`` items with an explicit overflow policy.

    ``put`` returns how many items were dropped to make room (0 or 1). ``force=True``
    bypasses the bound (used for the shutdown marker). ``unfinished`` counts the items put
    and neither dropped nor marked done (:meth:`task_done`): an item the consumer has taken
    but not yet processed still counts, so "nothing unfinished" means nothing is in flight.
    """

    def __init__(self, maxsize: int, policy: str, block_timeout_s: float) -> None:
        if policy not in QUEUE_POLICIES:
            raise ConfigError(f"queue policy {policy!r} is not one of {QUEUE_POLICIES}")
        self.maxsize, self.policy, self.block_timeout_s = maxsize, policy, block_timeout_s
        self._items: deque[Any] = deque()
        self._cond = threading.Condition()
        self.dropped = 0
        self.unfinished = 0
        self._closed = False

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: Any, force: bool = False) -> int:
        with self._cond:
            if not force and len(self._items) >= self.maxsize and self.policy != "drop-oldest":
                timeout = None if self.policy == "block" else self.block_timeout_s
                self._cond.wait_for(
                    lambda: len(self._items) < self.maxsize or self._closed, timeout
                )
            dropped = 0
            if not force and len(self._items) >= self.maxsize:
                self._items.popleft()
                dropped = 1
                self.dropped += 1
                self.unfinished -= 1
            self._items.append(item)
            if not force:  # the shutdown marker is not work: it is never marked done
                self.unfinished += 1
            self._cond.notify_all()
            return dropped

    def get(self, timeout: float | None = None) -> Any | None:
        """The oldest item, or None after ``timeout`` seconds with nothing queued."""
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._items), timeout):
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def task_done(self) -> None:
        """Mark one item taken by :meth:`get` as processed."""
        with self._cond:
            self.unfinished -= 1

    def release_blocked(self) -> None:
        """Wake producers blocked on a full queue (at shutdown)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


@dataclass
class _Seq:
    expected: int
    heap: list[tuple[int, int, float, str, Message]] = field(default_factory=list)


class Reorderer:
    """Releases messages in frame order per (stream, camera, trial).

    Parameters
    ----------
    window : at most this many messages are buffered per sequence while a missing index is
        awaited; one more releases the oldest (the gap is skipped).
    timeout_s : a buffered message waits at most this long for the indices before it.
    step, start : the indices this worker expects (``start``, ``start + step``, ...); with
        replication ``step = N`` and ``start = i``.
    """

    def __init__(self, window: int, timeout_s: float, step: int = 1, start: int = 0) -> None:
        self.window, self.timeout_s, self.step, self.start = window, timeout_s, step, start
        self._seqs: dict[tuple[str, str, str], _Seq] = {}
        # Recently closed sequences: key -> (last frame, when), to drop stragglers.
        self._closed: OrderedDict[tuple[str, str, str], tuple[int, float]] = OrderedDict()
        self._tie = itertools.count()
        self.late = 0
        self.gaps = 0

    def __len__(self) -> int:
        return sum(len(s.heap) for s in self._seqs.values())

    @property
    def pending(self) -> bool:
        """True if any message is buffered (only then can :meth:`poll` release one)."""
        return any(s.heap for s in self._seqs.values())

    def push(self, stream: str, msg: Message, now: float) -> list[tuple[str, Message]]:
        h = msg.header
        key = (stream, h.camera, h.trial)
        seq = self._seqs.get(key)
        closed = self._closed.pop(key, None) if seq is None else None
        if closed is not None:
            last, at = closed
            near_end = last - self.window * self.step < h.frame <= last
            if near_end and now - at < max(self.timeout_s, 1.0):
                # A straggler of a trial already closed by its last frame. (A far jump
                # back is a new pass of the same trial: a replay loop.)
                self._closed[key] = closed
                self.late += 1
                return []
        if seq is None:
            seq = self._seqs[key] = _Seq(self.start)
        elif h.frame < seq.expected - 2 * self.window * self.step and not seq.heap:
            # A jump far back is a restarted sequence (a source restarted, a replay loop).
            seq.expected = self.start
        heapq.heappush(seq.heap, (h.frame, next(self._tie), now, stream, msg))
        out: list[tuple[str, Message]] = []
        self._drain(key, seq, now, out, force=False)
        return out

    def poll(self, now: float) -> list[tuple[str, Message]]:
        """Release what waited longer than the timeout."""
        out: list[tuple[str, Message]] = []
        for key, seq in list(self._seqs.items()):
            self._drain(key, seq, now, out, force=False)
        return out

    def flush(self) -> list[tuple[str, Message]]:
        """Release everything buffered, in order (at shutdown)."""
        out: list[tuple[str, Message]] = []
        for key, seq in list(self._seqs.items()):
            self._drain(key, seq, 0.0, out, force=True)
        return out

    def _drain(
        self, key: tuple[str, str, str], seq: _Seq, now: float, out: list, force: bool
    ) -> None:
        while seq.heap:
            frame, _, arrived, stream, msg = seq.heap[0]
            if frame < seq.expected:
                heapq.heappop(seq.heap)
                self.late += 1
                continue
            if not (
                force
                or frame == seq.expected
                or len(seq.heap) > self.window
                or now - arrived >= self.timeout_s
            ):
                return
            heapq.heappop(seq.heap)
            if frame > seq.expected:
                self.gaps += (frame - seq.expected) // self.step
            seq.expected = frame + self.step
            out.append((stream, msg))
            if msg.header.last:
                # The trial is closed: forget it so memory stays bounded and a replayed
                # trial of the same name starts afresh. Stragglers (near the end, soon after)
                # are late.
                self.late += len(seq.heap)
                del self._seqs[key]
                self._closed[key] = (frame, now)
                while len(self._closed) > 1024:
                    self._closed.popitem(last=False)
                return


_STOP = object()


def _encode(msg: Message, pub: Any, scratch: bytearray) -> bytes | bytearray:
    """The payload of ``msg`` for ``pub``: written into ``scratch`` when the publisher copies
    payloads before ``put`` returns (a real Zenoh publisher), else a fresh ``bytes``.

    Reusing one warm buffer spares the allocation of a fresh payload per message, which for
    868 KB frames costs page faults on every frame (see ``schemas._codec.encode_into``).
    """
    if getattr(pub, "copies_payload", False):
        return msg.encode_into(scratch)
    return msg.encode()


class StageRuntime:
    """One worker of a processing stage on a bus (``Bus`` or ``FakeBus``).

    ``start()`` subscribes, declares the liveliness token and starts the worker thread;
    ``stop()`` shuts down cleanly (see the module docstring). ``error`` holds the exception
    that killed the worker, if any.
    """

    def __init__(
        self,
        bus: Any,
        node: Node,
        spec: StageSpec,
        params: dict[str, Any],
        options: RuntimeOptions | None = None,
        metrics: StageMetrics | None = None,
    ) -> None:
        self.bus, self.node, self.spec = bus, node, spec
        self.opt = options or RuntimeOptions()
        self.metrics = metrics or StageMetrics(node.name, self.opt.worker_id)
        # The core's ``after`` work runs once the step's outputs are out (see _offer).
        self.driver = StageDriver(node, spec, params, defer_after=True)
        self.queue = BoundedQueue(
            self.opt.queue_size, self.opt.queue_policy, self.opt.block_timeout_s
        )
        n = self.opt.replicas
        self.reorder = Reorderer(
            self.opt.reorder_window,
            self.opt.reorder_timeout_s,
            step=n,
            start=self.opt.worker if n > 1 else 0,
        )
        self._subs: list[Any] = []
        self._token: Any = None
        self._pubs: dict[str, Any] = {}
        self._scratch = bytearray()  # reused output buffer (see _encode)
        self._thread: threading.Thread | None = None
        self._accepting = False
        self._lock = threading.Lock()
        # Held while re-order buffer, driver and core run: by the worker thread, or by a
        # bus callback thread processing a frame inline (``block`` policy, see _on_payload).
        self._proc = threading.Lock()
        self._inline = self.opt.queue_policy == "block"
        self._counted = {"late": 0, "join": 0, "gaps": 0}
        self._deduper: Any = None
        if self.opt.dedupe:
            from gaitflow.edgebuffer import Deduper

            self._deduper = Deduper()
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.published = 0
        self.malformed = 0

    # -- input side (bus threads) ------------------------------------------------------

    def _on_payload(self, stream: str, key: str, payload: bytes) -> None:
        if not self._accepting:
            return
        try:
            msg = decode(STREAMS[stream], payload)
        except SchemaError as exc:
            self.metrics.malformed.inc()
            with self._lock:
                self.malformed += 1
                n = self.malformed
            if n <= 10 or n % MALFORMED_LOG_EVERY == 0:
                log.warning("%s: malformed message #%d on %s: %s", self.node.name, n, key, exc)
            return
        n = self.opt.replicas
        if n > 1 and stream in self.node.inputs and msg.header.frame % n != self.opt.worker:
            return
        if self._deduper is not None and not self._deduper.first_header(msg.header):
            # Taken once already: a stateful core must not see it again (the re-order
            # buffer would take a resend from far back for a restarted sequence).
            self.metrics.duplicates.inc()
            return
        self.metrics.frames_in.inc()
        if self._inline and self._try_inline(stream, msg):
            return
        if self.queue.put((stream, msg)):
            self.metrics.dropped["queue"].inc()
        self.metrics.queue_depth.set(len(self.queue))

    def _try_inline(self, stream: str, msg: Message) -> bool:
        """Process ``msg`` on this (bus callback) thread; False: it must be queued instead.

        Only with the ``block`` policy: there the callback may block anyway (lossless
        back-pressure through congestion control BLOCK), exactly as a plain Zenoh relay that
        puts from its callback, and handing each frame to the worker thread would only add
        a thread switch and a GIL hand-over per frame (the largest single cost of the
        runtime, measured). With the dropping policies the callback must return at once, so
        frames go through the queue. Order is kept: a frame is taken here only when the
        queue holds nothing unfinished; ``_proc`` serialises this with the worker (which
        still runs the re-order timeouts and the shutdown flush).
        """
        self._proc.acquire()
        try:
            if not self._accepting:
                return True  # stopped while waiting: the shutdown flush has run, drop it
            if self.queue.unfinished:
                return False
            self._process((stream, msg), time.monotonic())
            return True
        except Exception as exc:
            # As in the worker: a non-GaitflowError stops the stage (exit 1, restarted).
            self._accepting = False
            self.error = exc
            log.exception("%s: processing failed", self.node.name)
            self.done.set()
            return True
        finally:
            self._proc.release()

    # -- worker thread ---------------------------------------------------------------

    def _publish(self, msgs: Iterable[Message]) -> None:
        for m in msgs:
            if m.STREAM not in self.node.outputs:
                raise StageError(
                    self.node.name,
                    f"core produced stream {m.STREAM!r}, not among its outputs "
                    f"{list(self.node.outputs)}",
                )
            key = stream_key(self.bus.site, m.header.camera, self.node.out_topic(m.STREAM))
            pub = self._pubs.get(key)
            if pub is None:
                pub = self._pubs[key] = self.bus.publisher(key, block=True)
            pub.put(_encode(m, pub, self._scratch))
            self.published += 1
            self.metrics.frames_out.inc()
            self.metrics.age.observe(max(0.0, (time.time_ns() - m.header.capture_ns) / 1e9))

    def _offer(self, stream: str, msg: Message) -> None:
        before = self.driver.processed
        t0 = time.perf_counter()
        try:
            outs = self.driver.offer(stream, msg)
        except GaitflowError as exc:
            # A bad frame (e.g. FrameError) must not stop the stage: count it, one line.
            self.metrics.errors.inc()
            h = msg.header
            log.warning(
                "%s: frame %s/%s/%d failed: %s", self.node.name, h.camera, h.trial, h.frame, exc
            )
            return
        dt = time.perf_counter() - t0
        if self.driver.processed > before:
            self.metrics.latency.observe(dt)
            if dt > self.opt.budget_s:
                self.metrics.over_budget.inc()
        self._publish(outs)
        try:
            later = self.driver.run_after()
        except GaitflowError as exc:
            self.metrics.errors.inc()
            log.warning("%s: deferred work after %s failed: %s", self.node.name, stream, exc)
            return
        self._publish(later)

    def _sync_counts(self) -> None:
        for name, now, metric in (
            ("late", self.reorder.late, self.metrics.dropped["late"]),
            ("join", self.driver.dropped, self.metrics.dropped["join"]),
            ("gaps", self.reorder.gaps, self.metrics.gaps),
        ):
            if now > self._counted[name]:
                metric.inc(now - self._counted[name])
                self._counted[name] = now

    def _process(self, item: tuple[str, Message] | None, now: float) -> None:
        """Re-order, drive the core and publish; the caller holds ``_proc``."""
        released = self.reorder.poll(now) if self.reorder.pending else []
        if item is not None:
            stream, msg = item
            if stream in self.node.inputs:
                released += self.reorder.push(stream, msg, now)
            else:
                released.append((stream, msg))
        for stream, msg in released:
            self._offer(stream, msg)
        self._sync_counts()

    def _run(self) -> None:
        tick = max(0.005, min(0.05, self.opt.reorder_timeout_s / 4))
        try:
            while True:
                item = self.queue.get(timeout=tick)
                if item is _STOP:
                    break
                if self.error is not None:
                    return  # an inline step failed: stop like a failed worker
                with self._proc:
                    self._process(item, time.monotonic())
                    if item is not None:
                        self.queue.task_done()
                        self.metrics.queue_depth.set(len(self.queue))
            with self._proc:
                for stream, msg in self.reorder.flush():
                    self._offer(stream, msg)
                self._publish(self.driver.finish())
                self._sync_counts()
        except Exception as exc:
            # Not swallowed: stored for stop()/serve() to re-raise in the main thread.
            self.error = exc
            log.exception("%s: worker failed", self.node.name)
        finally:
            self.done.set()

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> StageRuntime:
        site = self.bus.site
        self._accepting = True
        for s in (*self.node.inputs, *self.node.side_inputs):
            if s not in STREAMS:
                raise ConfigError(f"stage {self.node.name!r}: unknown stream {s!r}")
            sel = stream_selector(site, self.node.in_topic(s), self.opt.camera)
            self._subs.append(self.bus.subscribe(sel, lambda k, p, s=s: self._on_payload(s, k, p)))
        self._thread = threading.Thread(
            target=self._run, name=f"stage-{self.node.name}-{self.opt.worker_id}", daemon=True
        )
        self._thread.start()
        self._token = self.bus.liveliness_token(
            liveliness_key(site, self.node.name, self.opt.worker_id)
        )
        return self

    def stop(self, timeout: float = 30.0) -> None:
        """Stop taking input, drain, finish, publish. Re-raises a worker failure."""
        self._accepting = False
        for h in self._subs:
            h.undeclare()
        self._subs.clear()
        self.queue.release_blocked()
        self.queue.put(_STOP, force=True)
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise StageError(self.node.name, f"worker did not finish within {timeout} s")
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self.error is not None:
            raise StageError(self.node.name, f"worker failed: {self.error}") from self.error


class SourceRuntime:
    """A source stage: publishes what ``spec.open(params)`` yields.

    ``rate="1"`` paces publication by the headers' capture times; ``"max"`` publishes as
    fast as the bus accepts (publishers use congestion control BLOCK, so nothing is lost).
    """

    def __init__(
        self,
        bus: Any,
        node: Node,
        spec: SourceSpec,
        params: dict[str, Any],
        options: RuntimeOptions | None = None,
        metrics: StageMetrics | None = None,
    ) -> None:
        self.bus, self.node, self.spec, self.params = bus, node, spec, params
        self.opt = options or RuntimeOptions()
        self.metrics = metrics or StageMetrics(node.name, self.opt.worker_id)
        self._pubs: dict[str, Any] = {}
        self._scratch = bytearray()  # reused output buffer (see _encode)
        self.published = 0
        self.error: BaseException | None = None
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._token: Any = None

    def _publish(self, msgs: Iterable[Message]) -> None:
        for m in msgs:
            if m.STREAM not in self.node.outputs:
                raise StageError(self.node.name, f"source produced undeclared {m.STREAM!r}")
            key = stream_key(self.bus.site, m.header.camera, self.node.out_topic(m.STREAM))
            pub = self._pubs.get(key)
            if pub is None:
                pub = self._pubs[key] = self.bus.publisher(key, block=True)
            pub.put(_encode(m, pub, self._scratch))
            self.published += 1
            self.metrics.frames_out.inc()

    def _run(self) -> None:
        first: tuple[int, int] | None = None
        trial: str | None = None
        try:
            for batch in self.spec.open(self.params):
                if self._stop.is_set():
                    break
                if not batch:
                    continue
                if self.opt.rate == "1":
                    cap = batch[0].header.capture_ns
                    # Recordings of a session were captured minutes apart: pace within a
                    # trial, and start the next one straight away.
                    if first is None or batch[0].header.trial != trial:
                        first = (cap, time.monotonic_ns())
                        trial = batch[0].header.trial
                    wait = (first[1] + (cap - first[0]) - time.monotonic_ns()) / 1e9
                    if wait > 0 and self._stop.wait(wait):
                        break
                t0 = time.perf_counter()
                self._publish(batch)
                self.metrics.latency.observe(time.perf_counter() - t0)
        except Exception as exc:
            self.error = exc
            log.exception("%s: source failed", self.node.name)
        finally:
            self.done.set()

    def start(self) -> SourceRuntime:
        self._thread = threading.Thread(target=self._run, name=f"source-{self.node.name}")
        self._thread.daemon = True
        self._token = self.bus.liveliness_token(
            liveliness_key(self.bus.site, self.node.name, self.opt.worker_id)
        )
        self._thread.start()
        return self

    def stop(self, timeout: float = 30.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self.error is not None:
            raise StageError(self.node.name, f"source failed: {self.error}") from self.error


def make_runtime(
    bus: Any,
    node: Node,
    params_override: Mapping[str, Any] | None = None,
    options: RuntimeOptions | None = None,
    spec: StageSpec | SourceSpec | None = None,
) -> StageRuntime | SourceRuntime:
    """The runtime for ``node``: its spec's parameters resolved (graph params, then
    ``params_override``), validated by the stage's ParamSet (ParameterError if bad)."""
    if spec is None:
        spec = _load_spec(node)
    params = spec.params.resolve({**node.params, **dict(params_override or {})})
    if isinstance(spec, SourceSpec):
        return SourceRuntime(bus, node, spec, params, options)
    return StageRuntime(bus, node, spec, params, options)


def _load_spec(node: Node) -> StageSpec | SourceSpec:
    import importlib

    try:
        mod = importlib.import_module(node.module)
    except ImportError as exc:
        raise ConfigError(f"stage {node.name!r}: cannot import {node.module}: {exc}") from exc
    spec = getattr(mod, "SPEC", None)
    if not isinstance(spec, StageSpec | SourceSpec):
        raise ConfigError(f"stage {node.name!r}: {node.module} has no SPEC")
    return spec


def serve(
    node: Node,
    bus_factory: Callable[[], Any],
    params_override: Mapping[str, Any] | None = None,
    options: RuntimeOptions | None = None,
    on_ready: Callable[[str], None] | None = None,
    restarts: int = 0,
) -> int:
    """Run one stage worker until SIGINT/SIGTERM (or until a source is exhausted).

    Returns the exit code: 0 after a clean stop, 1 if the worker failed. Configuration
    errors (bad parameters, unknown stage) raise before anything starts.
    """
    opt = options or RuntimeOptions()
    spec = _load_spec(node)
    params = spec.params.resolve({**node.params, **dict(params_override or {})})
    if isinstance(spec, StageSpec) and spec.warmup is not None:
        # before subscribing: a first-frame stall would let a joined input run ahead
        t0 = time.perf_counter()
        spec.warmup(params)
        log.info("%s: warm-up %.2f s", node.name, time.perf_counter() - t0)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    server: MetricsServer | None = None
    bus = bus_factory()
    try:
        rt: StageRuntime | SourceRuntime
        if isinstance(spec, SourceSpec):
            rt = SourceRuntime(bus, node, spec, params, opt)
        else:
            rt = StageRuntime(bus, node, spec, params, opt)
        rt.metrics.restarts.set(restarts)
        if opt.metrics_port is not None:
            server = MetricsServer(rt.metrics.registry, opt.metrics_port, opt.metrics_host)
        rt.start()
        where = f" metrics {server.url}" if server else ""
        msg = f"worker {opt.worker}/{opt.replicas} ready{where}"
        if on_ready is not None:
            on_ready(msg)
        parent = int(os.environ.get("GAITFLOW_PARENT_PID", "0") or 0)
        while not stop.wait(0.1):
            if rt.done.is_set():
                break
            if parent and os.getppid() != parent:
                log.warning("%s: the launcher (pid %d) is gone: stopping", node.name, parent)
                break
        try:
            rt.stop()
        except StageError as exc:
            log.error("%s", exc)
            # Bad input (a broken session folder or recording) will not mend by restarting:
            # exit 2 like a configuration error. A crashed worker is a runtime failure
            # (exit 1: the launcher restarts it).
            return 2 if isinstance(exc.__cause__, InputError) else 1
        return 0
    finally:
        if server is not None:
            server.close()
        bus.close()
        for s, h in old.items():
            signal.signal(s, h)


def replace_options(opt: RuntimeOptions, **kw: Any) -> RuntimeOptions:
    """``opt`` with the given fields changed (None values leave a field as it is)."""
    return replace(opt, **{k: v for k, v in kw.items() if v is not None})


@dataclass(frozen=True)
class StageConfig:
    """A stage/launcher config file (YAML or JSON).

    ::

        bus: {connect: [tcp/127.0.0.1:7447], site: clinic}   # BusConfig.from_mapping
        params: {threshold: 0.8}          # overrides for the stage run alone, or
        params: {detect: {threshold: 0.8}, clean: {...}}     # per stage (launcher)
        metrics: {port: 0, host: 127.0.0.1}
        runtime: {queue_size: 32, queue_policy: block-then-drop-oldest, ...}
    """

    bus: Any = None
    params: Mapping[str, Any] = field(default_factory=dict)
    metrics: Mapping[str, Any] = field(default_factory=dict)
    runtime: Mapping[str, Any] = field(default_factory=dict)
    source: str = ""
    site_set: bool = False

    @classmethod
    def load(cls, path: str | None) -> StageConfig:
        from pathlib import Path

        import yaml
        from gaitflow.bus.config import BusConfig

        if path is None:
            return cls(bus=BusConfig())
        p = Path(path)
        try:
            doc = yaml.safe_load(p.read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"{p}: cannot read config: {exc}") from exc
        if not isinstance(doc, dict):
            raise ConfigError(f"{p}: not a mapping")
        unknown = sorted(set(doc) - {"bus", "params", "metrics", "runtime"})
        if unknown:
            raise ConfigError(f"{p}: unknown section(s) {unknown}")
        sections = {}
        for k in ("params", "metrics", "runtime"):
            v = doc.get(k) or {}
            if not isinstance(v, dict):
                raise ConfigError(f"{p}: {k} must be a mapping, got {v!r}")
            sections[k] = v
        unknown_m = sorted(set(sections["metrics"]) - {"port", "host"})
        if unknown_m:
            raise ConfigError(f"{p}: unknown metrics key(s) {unknown_m}")
        bus_doc = doc.get("bus") or {}
        bus = BusConfig.from_mapping(bus_doc, str(p))
        return cls(bus=bus, source=str(p), site_set="site" in bus_doc, **sections)

    def params_for(self, stage: str) -> dict[str, Any]:
        """The overrides of ``stage``: its own section if ``params`` has one, else all."""
        own = self.params.get(stage)
        if isinstance(own, dict):
            return dict(own)
        if any(isinstance(v, dict) for v in self.params.values()):
            return {}  # a per-stage params file without a section for this stage
        return dict(self.params)

    def options(self, **overrides: Any) -> RuntimeOptions:
        """Runtime options: ``runtime:`` section, ``metrics:``, then non-None overrides."""
        opt = RuntimeOptions.from_mapping(self.runtime, self.source or "runtime config")
        if "port" in self.metrics:
            opt = replace(opt, metrics_port=int(self.metrics["port"]))
        if "host" in self.metrics:
            opt = replace(opt, metrics_host=str(self.metrics["host"]))
        return replace_options(opt, **overrides)
