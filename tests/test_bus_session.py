"""The real Zenoh Bus on 127.0.0.1: pub/sub of frame-sized payloads, liveliness, router."""

from __future__ import annotations

import threading
import time

import pytest
from gaitflow.bus import Bus, BusConfig
from gaitflow.bus.router import Router, client_config, local_endpoint

from gaitflow.errors import ConfigError

pytestmark = pytest.mark.integration


def _wait(pred, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


def test_pubsub_liveliness_through_router() -> None:
    ep = local_endpoint()
    with Router(listen=(ep,)):
        a, b = Bus(client_config(ep)), Bus(client_config(ep))
        try:
            got: list[tuple[str, int, int]] = []
            alive: list[tuple[str, bool]] = []
            done = threading.Event()

            def on(k: str, p: bytes) -> None:
                got.append((k, len(p), p[0]))
                if len(got) == 20:
                    done.set()

            b.subscribe("gaitflow/clinic/*/raw", on)
            b.watch_liveliness("gaitflow/clinic/@alive/**", lambda k, x: alive.append((k, x)))
            tok = a.liveliness_token("gaitflow/clinic/@alive/relay/0")
            assert _wait(lambda: alive == [("gaitflow/clinic/@alive/relay/0", True)])
            pub = a.publisher("gaitflow/clinic/cam0/raw")
            for i in range(20):
                pub.put(bytes([i]) * 868_224)
            assert done.wait(5)
            assert [g[2] for g in got] == list(range(20))
            assert {g[1] for g in got} == {868_224}
            want = ["gaitflow/clinic/@alive/relay/0"]
            assert _wait(lambda: b.alive("gaitflow/clinic/@alive/**") == want)
            tok.undeclare()
            assert _wait(lambda: alive[-1] == ("gaitflow/clinic/@alive/relay/0", False))
        finally:
            a.close()
            b.close()


def test_callback_exception_is_counted_and_delivery_continues() -> None:
    ep = local_endpoint()
    with Router(listen=(ep,)):
        a, b = Bus(client_config(ep)), Bus(client_config(ep))
        try:
            got: list[bytes] = []

            def on(k: str, p: bytes) -> None:
                if p == b"bad":
                    raise ValueError("boom")
                got.append(p)

            b.subscribe("t/**", on)
            time.sleep(0.2)
            for p in (b"a", b"bad", b"c"):
                a.put("t/x", p)
            assert _wait(lambda: got == [b"a", b"c"])
            assert b.callback_errors == 1
        finally:
            a.close()
            b.close()


def test_bad_mode_is_config_error() -> None:
    with pytest.raises(ConfigError, match="bus mode"):
        BusConfig(mode="broker")
