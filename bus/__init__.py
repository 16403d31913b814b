"""The Zenoh bus: configuration, key scheme, sessions, and an in-memory fake.

``Bus`` (real Zenoh) and ``FakeBus`` (in memory, for adapter tests) share one interface:

- ``publisher(key, block=True) -> Publisher`` with ``put(payload: bytes)``;
- ``put(key, payload)``;
- ``subscribe(selector, callback) -> handle`` with ``callback(key: str, payload: bytes)``
  and ``handle.undeclare()``;
- ``liveliness_token(key)``;
- ``watch_liveliness(selector, callback(key, alive: bool), history=True) -> handle`` and
  ``alive(selector) -> list[str]`` to see which stage workers are up;
- ``close()``.
"""

from gaitflow.bus.config import DEFAULT_ROUTER, BusConfig
from gaitflow.bus.fake import FakeBus
from gaitflow.bus.keys import liveliness_key, parse_key, stream_key, stream_selector
from gaitflow.bus.session import Bus

__all__ = [
    "DEFAULT_ROUTER",
    "Bus",
    "BusConfig",
    "FakeBus",
    "liveliness_key",
    "parse_key",
    "stream_key",
    "stream_selector",
]
