"""An in-memory bus with the same interface as :class:`gaitflow.bus.session.Bus`.

Delivery is synchronous: ``put`` calls every matching subscriber's callback in the caller's
thread before it returns, so adapter tests are deterministic. Key expressions follow
Zenoh's rules for the part gaitflow uses: chunks separated by ``/``, ``*`` matches exactly
one chunk, ``**`` matches zero or more chunks.

Several :class:`FakeBus` objects made with :meth:`FakeBus.connected` share one in-memory
network, like sessions connected to one router.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

from gaitflow.bus.config import BusConfig

Callback = Callable[[str, bytes], None]
LivelinessCallback = Callable[[str, bool], None]


@lru_cache(maxsize=4096)
def _chunks(expr: str) -> tuple[str, ...]:
    return tuple(expr.split("/"))


def _inter(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a:
        return all(c == "**" for c in b)
    if not b:
        return all(c == "**" for c in a)
    if a[0] == "**":
        return _inter(a[1:], b) or _inter(a, b[1:])
    if b[0] == "**":
        return _inter(a, b[1:]) or _inter(a[1:], b)
    if a[0] == "*" or b[0] == "*" or a[0] == b[0]:
        return _inter(a[1:], b[1:])
    return False


def intersects(a: str, b: str) -> bool:
    """True when key expressions ``a`` and ``b`` have a key in common (``*`` and ``**``)."""
    return _inter(_chunks(a), _chunks(b))


@dataclass
class _Net:
    """The shared in-memory network: subscribers and live tokens."""

    lock: threading.RLock = field(default_factory=threading.RLock)
    subs: list[tuple[str, Callback]] = field(default_factory=list)
    tokens: dict[int, str] = field(default_factory=dict)
    watchers: list[tuple[str, LivelinessCallback]] = field(default_factory=list)
    next_id: int = 0


class FakeHandle:
    def __init__(self, undeclare: Callable[[], None]) -> None:
        self._undeclare = undeclare
        self._done = False

    def undeclare(self) -> None:
        if not self._done:
            self._done = True
            self._undeclare()


class FakePublisher:
    def __init__(self, bus: FakeBus, key: str) -> None:
        self.bus, self.key = bus, key

    def put(self, payload: bytes | bytearray | memoryview) -> None:
        self.bus.put(self.key, payload)

    def undeclare(self) -> None:
        pass


class FakeBus:
    """In-memory bus for tests. ``published`` logs every (key, payload) put on it."""

    def __init__(self, cfg: BusConfig | None = None, net: _Net | None = None) -> None:
        self.cfg = cfg or BusConfig()
        self._net = net or _Net()
        self._mine: list[FakeHandle] = []
        self.published: list[tuple[str, bytes]] = []
        self.callback_errors = 0
        self._closed = False

    @property
    def site(self) -> str:
        return self.cfg.site

    def connected(self) -> FakeBus:
        """Another session on the same in-memory network."""
        return FakeBus(self.cfg, self._net)

    def publisher(
        self, key: str, block: bool = True, express: bool = False, priority: str = "DATA"
    ) -> FakePublisher:
        return FakePublisher(self, key)

    def put(self, key: str, payload: bytes | bytearray | memoryview, block: bool = True) -> None:
        if self._closed:
            raise RuntimeError("FakeBus is closed")
        data = bytes(payload)
        self.published.append((key, data))
        with self._net.lock:
            subs = list(self._net.subs)
        for sel, cb in subs:
            if intersects(sel, key):
                cb(key, data)

    def subscribe(self, selector: str, callback: Callback) -> FakeHandle:
        entry = (selector, callback)
        with self._net.lock:
            self._net.subs.append(entry)

        def undeclare() -> None:
            with self._net.lock:
                if entry in self._net.subs:
                    self._net.subs.remove(entry)

        return self._keep(FakeHandle(undeclare))

    def liveliness_token(self, key: str) -> FakeHandle:
        with self._net.lock:
            tid = self._net.next_id
            self._net.next_id += 1
            self._net.tokens[tid] = key
            watchers = list(self._net.watchers)
        for sel, cb in watchers:
            if intersects(sel, key):
                cb(key, True)

        def undeclare() -> None:
            with self._net.lock:
                self._net.tokens.pop(tid, None)
                ws = list(self._net.watchers)
            for sel, cb in ws:
                if intersects(sel, key):
                    cb(key, False)

        return self._keep(FakeHandle(undeclare))

    def watch_liveliness(
        self, selector: str, callback: LivelinessCallback, history: bool = True
    ) -> FakeHandle:
        entry = (selector, callback)
        with self._net.lock:
            self._net.watchers.append(entry)
            present = [k for k in self._net.tokens.values() if intersects(selector, k)]
        if history:
            for k in present:
                callback(k, True)

        def undeclare() -> None:
            with self._net.lock:
                if entry in self._net.watchers:
                    self._net.watchers.remove(entry)

        return self._keep(FakeHandle(undeclare))

    def alive(self, selector: str, timeout: float = 1.0) -> list[str]:
        with self._net.lock:
            return sorted(k for k in self._net.tokens.values() if intersects(selector, k))

    def _keep(self, h: FakeHandle) -> FakeHandle:
        self._mine.append(h)
        return h

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for h in self._mine:
            h.undeclare()
        self._mine.clear()

    def __enter__(self) -> FakeBus:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
