"""The fast paths of the stage runtime: inline steps under ``block``, reused encode buffers."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from gaitflow.bus import FakeBus
from gaitflow.schemas import Blobs, RawFrame, decode
from gaitflow.stages import relay
from gaitflow.stages.base import StageSpec
from gaitflow.stages.graph import Node
from gaitflow.stages.runtime import RuntimeOptions, StageRuntime

from gaitflow.errors import StageError
from gaitflow.params import ParamSet

IN = "gaitflow/clinic/cam0/raw"
OUT = "gaitflow/clinic/cam0/raw-1"
RELAY = Node("relay", "gaitflow.stages.relay", ("raw",), ("raw",), topics={"raw": "raw-1"})
BLOCK = RuntimeOptions(queue_policy="block")


def frame(i: int, last: bool = False) -> RawFrame:
    rng = np.random.default_rng(i)
    return RawFrame(
        header=RawFrame.make_header("cam0", "walk-01", i, 1_000_000_000 + i * 33_333_333, last),
        ir=rng.integers(0, 65535, (4, 5), dtype=np.uint16),
        depth=np.full((4, 5), i, dtype=np.uint16),
    )


def out_frames(bus: FakeBus) -> list[int]:
    return [decode(RawFrame, p).header.frame for k, p in bus.published if k == OUT]


def test_block_policy_runs_the_step_on_the_callback_thread_in_order() -> None:
    bus = FakeBus()
    src = bus.connected()
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}, BLOCK).start()
    # FakeBus delivers synchronously: an inline step has published before put() returns.
    src.put(IN, frame(0).encode())
    assert out_frames(bus) == [0]
    src.put(IN, frame(2).encode())  # 1 is missing: held by the re-order buffer
    assert out_frames(bus) == [0]
    src.put(IN, frame(1).encode())
    assert out_frames(bus) == [0, 1, 2]
    for i in range(3, 8):
        src.put(IN, frame(i, last=i == 7).encode())
    rt.stop()
    assert out_frames(bus) == list(range(8))
    assert rt.queue.unfinished == 0


def test_dropping_policies_still_hand_frames_to_the_worker() -> None:
    bus = FakeBus()
    src = bus.connected()
    seen: list[str] = []

    def step(state: None, inputs: Any) -> tuple[None, list[Any]]:
        import threading

        seen.append(threading.current_thread().name)
        return state, list(inputs.values())

    spec = StageSpec(name="relay", params=ParamSet("relay"), init=relay.init, step=step)
    rt = StageRuntime(bus, RELAY, spec, {}, RuntimeOptions(queue_policy="drop-oldest")).start()
    for i in range(4):
        src.put(IN, frame(i).encode())
    rt.stop()
    assert out_frames(bus) == [0, 1, 2, 3]
    assert seen and all(name.startswith("stage-relay-") for name in seen)


def test_a_crash_in_an_inline_step_stops_the_stage() -> None:
    bus = FakeBus()
    src = bus.connected()

    def step(state: None, inputs: Any) -> tuple[None, list[Any]]:
        if next(iter(inputs.values())).header.frame == 1:
            raise RuntimeError("core bug")
        return state, list(inputs.values())

    spec = StageSpec(name="relay", params=ParamSet("relay"), init=relay.init, step=step)
    rt = StageRuntime(bus, RELAY, spec, {}, BLOCK).start()
    for i in range(4):
        src.put(IN, frame(i).encode())
    assert rt.done.is_set()
    with pytest.raises(StageError, match="core bug"):
        rt.stop()
    assert out_frames(bus) == [0]  # nothing processed after the failure


def test_encode_into_gives_the_same_bytes_and_reuses_the_buffer() -> None:
    buf = bytearray()
    big = frame(3)
    out = big.encode_into(buf, publish_ns=5)
    assert out is buf and bytes(buf) == big.encode(publish_ns=5)
    rng = np.random.default_rng(1)
    small = Blobs.follow(
        big.header,
        centroid=rng.random((3, 2)),
        marker_radius=rng.random(3),
        region_radius=rng.random(3),
        mean_ir=rng.random(3),
        area=np.arange(3, dtype=np.int32),
        threshold=0.5,
    )
    small.encode_into(buf, publish_ns=7)  # shrinks in place
    assert bytes(buf) == small.encode(publish_ns=7)
    assert np.array_equal(decode(Blobs, bytes(buf)).centroid, small.centroid)
    big.encode_into(buf, publish_ns=9)  # grows again
    assert bytes(buf) == big.encode(publish_ns=9)
