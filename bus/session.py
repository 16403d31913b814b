"""A Zenoh session with gaitflow's small publish/subscribe interface.

:class:`Bus` wraps one ``zenoh.Session`` built from a :class:`~gaitflow.bus.config.BusConfig`.
Payloads are ``bytes`` (the schema codec's output); callbacks receive ``(key, payload)``.
The same interface is implemented in memory by :class:`gaitflow.bus.fake.FakeBus`, so stage
adapters can be tested without a network.

Frames go out with congestion control BLOCK: a slow subscriber slows the publisher rather
than losing frames silently. Where a stage must not block (it has its own bounded queue),
the runtime drops explicitly and counts.

Shared memory (``zenoh.shm``), option ``shm``:

- ``"auto"`` (default): Zenoh's own defaults. Zenoh 1.x enables its shared-memory
  *transport optimisation*: messages over 3 KB between processes on one machine are moved
  through a shared pool (16 MB) instead of the TCP socket, without any code here.
- ``"off"``: shared memory disabled for this session (everything goes through TCP).
- ``"on"``: explicit: the publisher allocates each payload in a ``ShmProvider`` buffer of
  its own (64 MB pool) and Zenoh passes a reference.

Which pays for 868 KB frames is measured by ``gaitflow bench bus --shm MODE``; see the
README figures.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from gaitflow.bus.config import BusConfig

from gaitflow.errors import BusError

log = logging.getLogger("gaitflow.bus")

Callback = Callable[[str, bytes], None]
LivelinessCallback = Callable[[str, bool], None]

# One shared-memory pool per process; large enough for a few dozen raw frames in flight.
SHM_POOL_BYTES = 64 << 20
SHM_MODES = ("auto", "off", "on")


class Handle:
    """Something declared on the bus that can be undeclared (subscriber, token)."""

    def __init__(self, inner: Any, on_undeclare: Callable[[], None] | None = None) -> None:
        self._inner = inner
        self._on_undeclare = on_undeclare
        self._done = False

    def undeclare(self) -> None:
        if self._done:
            return
        self._done = True
        try:
            self._inner.undeclare()
        finally:
            if self._on_undeclare is not None:
                self._on_undeclare()


class Publisher:
    """A declared Zenoh publisher on one key.

    ``put`` has Zenoh copy the payload (into its own buffer or a shared-memory one) before
    it returns, so a caller may reuse a ``bytearray`` for the next payload
    (``copies_payload``; the in-memory FakeBus keeps references and does not say so).
    """

    copies_payload = True

    def __init__(self, bus: Bus, key: str, inner: Any) -> None:
        self.bus, self.key, self._inner = bus, key, inner

    def put(self, payload: bytes | bytearray | memoryview) -> None:
        self._inner.put(self.bus._zbytes(payload))

    def undeclare(self) -> None:
        self._inner.undeclare()


class Bus:
    """A real Zenoh session.

    Parameters
    ----------
    cfg : how to open the session (mode, endpoints, TLS; loopback-only by default).
    shm : ``"auto"``, ``"off"`` or ``"on"`` (see the module docstring).
    """

    def __init__(self, cfg: BusConfig | None = None, shm: str = "auto") -> None:
        import zenoh

        if shm not in SHM_MODES:
            raise BusError(f"shm mode {shm!r} is not one of {SHM_MODES}")
        self.cfg = cfg or BusConfig()
        self._zenoh = zenoh
        zcfg = self.cfg.to_zenoh()
        if shm != "auto":
            zcfg.insert_json5("transport/shared_memory/enabled", json.dumps(shm == "on"))
        try:
            self.session = zenoh.open(zcfg)
        except zenoh.ZError as exc:
            raise BusError(f"cannot open a Zenoh {self.cfg.mode} session: {exc}") from exc
        self._lock = threading.Lock()
        self._handles: list[Handle] = []
        self._shm: Any = None
        if shm == "on":
            try:
                self._shm = zenoh.shm.ShmProvider.default_backend(SHM_POOL_BYTES)
            except zenoh.ZError as exc:
                self.session.close()
                raise BusError(
                    f"cannot create a {SHM_POOL_BYTES >> 20} MB shared-memory pool "
                    f"(is /dev/shm large enough?): {exc}"
                ) from exc
        self.callback_errors = 0
        self.shm_fallbacks = 0
        self._closed = False

    @property
    def site(self) -> str:
        return self.cfg.site

    def _zbytes(self, payload: bytes | bytearray | memoryview) -> Any:
        data = payload if isinstance(payload, bytes | bytearray) else bytes(payload)
        if self._shm is None:
            return data
        shm = self._zenoh.shm
        try:
            # Reclaim buffers subscribers have released; never block the publisher here.
            buf = self._shm.alloc(len(data), shm.GarbageCollect())
        except self._zenoh.ZError:
            self.shm_fallbacks += 1  # pool exhausted: this payload goes by the socket
            return data
        buf[0 : len(data)] = data
        return buf

    def publisher(
        self, key: str, block: bool = True, express: bool = False, priority: str = "DATA"
    ) -> Publisher:
        """Declare a publisher on ``key``.

        ``block=True`` (frames): congestion control BLOCK, nothing is dropped by Zenoh.
        ``express=True`` sends each message without batching (lower latency for small ones).
        """
        z = self._zenoh
        cc = z.CongestionControl.BLOCK if block else z.CongestionControl.DROP
        try:
            inner = self.session.declare_publisher(
                key, congestion_control=cc, express=express, priority=getattr(z.Priority, priority)
            )
        except (z.ZError, AttributeError) as exc:
            raise BusError(f"cannot declare a publisher on {key!r}: {exc}") from exc
        return Publisher(self, key, inner)

    def put(self, key: str, payload: bytes | bytearray | memoryview, block: bool = True) -> None:
        """Publish one payload without declaring a publisher."""
        z = self._zenoh
        cc = z.CongestionControl.BLOCK if block else z.CongestionControl.DROP
        self.session.put(key, self._zbytes(payload), congestion_control=cc)

    def _guard(self, where: str, fn: Callable[..., None]) -> Callable[..., None]:
        def run(*args: Any) -> None:
            try:
                fn(*args)
            except Exception:
                # An exception must not vanish inside Zenoh's thread: count and log it.
                self.callback_errors += 1
                log.exception("bus callback for %s failed", where)

        return run

    def subscribe(self, selector: str, callback: Callback) -> Handle:
        """Call ``callback(key, payload)`` for every sample matching ``selector``.

        Callbacks run on a Zenoh thread, one at a time per subscriber; keep them short
        (the runtime only enqueues).
        """
        guarded = self._guard(selector, callback)

        def on_sample(sample: Any) -> None:
            guarded(str(sample.key_expr), sample.payload.to_bytes())

        try:
            sub = self.session.declare_subscriber(selector, on_sample)
        except self._zenoh.ZError as exc:
            raise BusError(f"cannot subscribe to {selector!r}: {exc}") from exc
        return self._track(Handle(sub))

    def liveliness_token(self, key: str) -> Handle:
        """Declare a liveliness token: it disappears when undeclared or the process dies."""
        try:
            tok = self.session.liveliness().declare_token(key)
        except self._zenoh.ZError as exc:
            raise BusError(f"cannot declare liveliness token {key!r}: {exc}") from exc
        return self._track(Handle(tok))

    def watch_liveliness(
        self, selector: str, callback: LivelinessCallback, history: bool = True
    ) -> Handle:
        """Call ``callback(key, alive)`` when a token matching ``selector`` appears/vanishes.

        With ``history`` the tokens already present are reported first.
        """
        z = self._zenoh
        guarded = self._guard(selector, callback)

        def on_sample(sample: Any) -> None:
            guarded(str(sample.key_expr), sample.kind == z.SampleKind.PUT)

        sub = self.session.liveliness().declare_subscriber(selector, on_sample, history=history)
        return self._track(Handle(sub))

    def alive(self, selector: str, timeout: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens matching ``selector`` right now.

        Under heavy load a liveliness query was seen (rarely) to complete empty although a
        token was up; an empty answer is therefore asked again once, 50 ms later.
        """
        for attempt in range(2):
            keys = set()
            for r in self.session.liveliness().get(selector, timeout=timeout):
                if r.ok is not None:
                    keys.add(str(r.ok.key_expr))
            if keys or attempt:
                return sorted(keys)
            time.sleep(0.05)
        return []

    def _track(self, h: Handle) -> Handle:
        with self._lock:
            self._handles.append(h)
        return h

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        if self._closed:
            return
        self._closed = True
        with self._lock:
            handles, self._handles = self._handles, []
        for h in handles:
            try:
                h.undeclare()
            except self._zenoh.ZError as exc:
                log.warning("undeclare at close failed: %s", exc)
        self.session.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
