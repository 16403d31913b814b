"""FakeBus: key-expression matching, synchronous delivery, liveliness."""

from __future__ import annotations

import pytest
from gaitflow.bus import FakeBus
from gaitflow.bus.fake import intersects


@pytest.mark.parametrize(
    ("a", "b", "want"),
    [
        ("gaitflow/clinic/cam0/raw", "gaitflow/clinic/cam0/raw", True),
        ("gaitflow/clinic/*/raw", "gaitflow/clinic/cam0/raw", True),
        ("gaitflow/clinic/*/raw", "gaitflow/clinic/cam0/clean", False),
        ("gaitflow/clinic/*", "gaitflow/clinic/cam0/raw", False),
        ("gaitflow/**", "gaitflow/clinic/cam0/raw", True),
        ("gaitflow/**/raw", "gaitflow/clinic/cam0/raw", True),
        ("gaitflow/**/raw", "gaitflow/raw", True),
        ("gaitflow/**/raw", "gaitflow/clinic/cam0/raws", False),
        ("gaitflow/clinic/**", "gaitflow/other/cam0/raw", False),
        ("gaitflow/*/cam0/**", "gaitflow/clinic/*/raw", True),
    ],
)
def test_intersects(a: str, b: str, want: bool) -> None:
    assert intersects(a, b) is want
    assert intersects(b, a) is want


def test_put_delivers_synchronously_to_matching_subscribers_only() -> None:
    bus = FakeBus()
    other = bus.connected()
    got: list[tuple[str, bytes]] = []
    h = other.subscribe("gaitflow/clinic/*/raw", lambda k, p: got.append((k, p)))
    pub = bus.publisher("gaitflow/clinic/cam0/raw")
    pub.put(b"one")
    bus.put("gaitflow/clinic/cam0/clean", b"nope")
    bus.put("gaitflow/clinic/cam1/raw", memoryview(b"two"))
    assert got == [("gaitflow/clinic/cam0/raw", b"one"), ("gaitflow/clinic/cam1/raw", b"two")]
    h.undeclare()
    pub.put(b"three")
    assert len(got) == 2
    assert len(bus.published) == 4


def test_liveliness_history_and_undeclare() -> None:
    bus = FakeBus()
    seen: list[tuple[str, bool]] = []
    tok = bus.liveliness_token("gaitflow/clinic/@alive/relay/0")
    bus.connected().watch_liveliness("gaitflow/clinic/@alive/**", lambda k, a: seen.append((k, a)))
    assert seen == [("gaitflow/clinic/@alive/relay/0", True)]
    assert bus.alive("gaitflow/clinic/@alive/relay/*") == ["gaitflow/clinic/@alive/relay/0"]
    tok.undeclare()
    assert seen[-1] == ("gaitflow/clinic/@alive/relay/0", False)
    assert bus.alive("gaitflow/clinic/@alive/**") == []


def test_close_undeclares_subscriptions_and_tokens() -> None:
    a = FakeBus()
    b = a.connected()
    got: list[bytes] = []
    b.subscribe("k/**", lambda k, p: got.append(p))
    b.liveliness_token("k/@alive/x/0")
    b.close()
    a.put("k/x", b"x")
    assert got == []
    assert a.alive("k/**") == []
    with pytest.raises(RuntimeError):
        b.put("k/x", b"y")
