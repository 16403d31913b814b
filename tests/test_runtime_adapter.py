"""The stage runtime over the in-memory FakeBus: decode -> core -> encode -> publish."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from gaitflow.bus import FakeBus
from gaitflow.schemas import RawFrame, decode
from gaitflow.stages import relay
from gaitflow.stages.base import SourceSpec, StageSpec
from gaitflow.stages.graph import Node
from gaitflow.stages.runtime import (
    BoundedQueue,
    Reorderer,
    RuntimeOptions,
    SourceRuntime,
    StageRuntime,
    make_runtime,
)

from gaitflow.errors import ConfigError, ParameterError, StageError
from gaitflow.params import ParamSet

IN = "gaitflow/clinic/cam0/raw"
OUT = "gaitflow/clinic/cam0/raw-1"
RELAY = Node("relay", "gaitflow.stages.relay", ("raw",), ("raw",), topics={"raw": "raw-1"})


def frame(i: int, trial: str = "walk-01", last: bool = False, cam: str = "cam0") -> RawFrame:
    rng = np.random.default_rng(i)
    return RawFrame(
        header=RawFrame.make_header(cam, trial, i, 1_000_000_000 + i * 33_333_333, last),
        ir=rng.integers(0, 65535, (4, 5), dtype=np.uint16),
        depth=np.full((4, 5), i, dtype=np.uint16),
    )


def outputs(bus: FakeBus, key: str = OUT) -> list[RawFrame]:
    return [decode(RawFrame, p) for k, p in bus.published if k == key]


def metric(rt: StageRuntime, name: str, **labels: str) -> float:
    v = rt.metrics.registry.get_sample_value(name, {"stage": rt.node.name, "worker": "0", **labels})
    return 0.0 if v is None else v


def test_relay_decodes_runs_core_encodes_and_publishes() -> None:
    bus = FakeBus()
    src = bus.connected()
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}).start()
    assert src.alive("gaitflow/clinic/@alive/**") == ["gaitflow/clinic/@alive/relay/0"]
    sent = [frame(i) for i in range(5)]
    for m in sent:
        src.put(IN, m.encode())
    rt.stop()
    got = outputs(bus)
    assert [m.header.frame for m in got] == [0, 1, 2, 3, 4]
    for a, b in zip(sent, got, strict=True):
        assert np.array_equal(a.ir, b.ir) and np.array_equal(a.depth, b.depth)
    assert metric(rt, "gaitflow_stage_frames_in_total") == 5
    assert metric(rt, "gaitflow_stage_frames_out_total") == 5
    assert metric(rt, "gaitflow_stage_processing_seconds_count") == 5
    assert src.alive("gaitflow/clinic/@alive/**") == []


def test_malformed_payload_is_counted_and_stage_keeps_serving(caplog) -> None:
    bus = FakeBus()
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}).start()
    bus.put(IN, frame(0).encode())
    bus.put(IN, b"\x93garbage")
    bus.put(IN, frame(1).encode()[:-7])
    bus.put(IN, frame(1).encode())
    rt.stop()
    assert [m.header.frame for m in outputs(bus)] == [0, 1]
    assert metric(rt, "gaitflow_stage_frames_malformed_total") == 2
    lines = [r.getMessage() for r in caplog.records if "malformed" in r.getMessage()]
    assert len(lines) == 2 and all("\n" not in s and "'raw'" in s for s in lines)


def test_out_of_order_input_is_reordered() -> None:
    bus = FakeBus()
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}).start()
    for i in (2, 0, 1, 4, 3, 5):
        bus.put(IN, frame(i).encode())
    rt.stop()
    assert [m.header.frame for m in outputs(bus)] == [0, 1, 2, 3, 4, 5]


def test_gap_is_released_after_timeout_not_at_shutdown() -> None:
    bus = FakeBus()
    opt = RuntimeOptions(reorder_timeout_s=0.05)
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}, opt).start()
    for i in (0, 1, 3, 4):
        bus.put(IN, frame(i).encode())
    deadline = time.monotonic() + 3
    while len(outputs(bus)) < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [m.header.frame for m in outputs(bus)] == [0, 1, 3, 4]
    bus.put(IN, frame(2).encode())  # too late: frame 3 was already released
    rt.stop()
    assert len(outputs(bus)) == 4
    assert metric(rt, "gaitflow_stage_frames_dropped_total", reason="late") == 1
    assert metric(rt, "gaitflow_stage_reorder_gaps_total") == 1


def test_reorderer_window_last_and_restart() -> None:
    r = Reorderer(window=3, timeout_s=10.0)
    out = []
    for i in (1, 2, 3):
        out += r.push("raw", frame(i), 0.0)
    assert out == []  # waiting for 0 within the window
    out += r.push("raw", frame(4), 0.0)  # window overflows: 1 is released, 0 skipped
    assert [m.header.frame for _, m in out] == [1, 2, 3, 4]
    assert r.gaps == 1
    out = r.push("raw", frame(5, last=True), 0.0)
    assert [m.header.frame for _, m in out] == [5]
    # the trial was closed: a straggler of its end is late, not a new sequence
    assert r.push("raw", frame(4), 0.1) == [] and r.late == 1
    # a replay of the same trial (a jump far back) starts afresh at 0
    r2 = Reorderer(window=3, timeout_s=10.0)
    for i in range(10):
        r2.push("raw", frame(i, last=i == 9), 0.0)
    assert [m.header.frame for _, m in r2.push("raw", frame(0), 0.0)] == [0]
    assert [m.header.frame for _, m in r.push("raw", frame(0), 0.0)] == [0]
    # trials and cameras are separate sequences
    assert [m.header.frame for _, m in r.push("raw", frame(0, trial="walk-02"), 0.0)] == [0]
    assert [m.header.frame for _, m in r.push("raw", frame(0, cam="cam1"), 0.0)] == [0]


def test_replicas_split_by_frame_index_and_downstream_reorders() -> None:
    bus = FakeBus()
    workers = [
        StageRuntime(bus, RELAY, relay.SPEC, {}, RuntimeOptions(replicas=2, worker=w)).start()
        for w in (0, 1)
    ]
    down = Node(
        "sink",
        "gaitflow.stages.relay",
        ("raw",),
        ("raw",),
        input_topics={"raw": "raw-1"},
        topics={"raw": "raw-2"},
    )
    sink = StageRuntime(bus, down, relay.SPEC, {}).start()
    for i in range(10):
        bus.put(IN, frame(i).encode())
    for w in workers:
        w.stop()
    sink.stop()
    assert sorted(m.header.frame for m in outputs(bus)) == list(range(10))
    assert workers[0].driver.processed == 5 and workers[1].driver.processed == 5
    assert [m.header.frame for m in outputs(bus, "gaitflow/clinic/cam0/raw-2")] == list(range(10))


def _blocking_spec(entered: threading.Event, release: threading.Event) -> StageSpec:
    def step(state: Any, inputs: Any) -> tuple[Any, list]:
        entered.set()
        release.wait(10)
        return state, list(inputs.values())

    return StageSpec("slow", ParamSet("slow"), lambda p: None, step)


def test_bounded_queue_drops_oldest_and_counts() -> None:
    bus = FakeBus()
    entered, release = threading.Event(), threading.Event()
    opt = RuntimeOptions(queue_size=3, queue_policy="drop-oldest")
    rt = StageRuntime(bus, RELAY, _blocking_spec(entered, release), {}, opt).start()
    bus.put(IN, frame(0).encode())
    assert entered.wait(5)
    for i in range(1, 11):
        bus.put(IN, frame(i).encode())
    release.set()
    rt.stop()
    assert [m.header.frame for m in outputs(bus)] == [0, 8, 9, 10]
    assert metric(rt, "gaitflow_stage_frames_dropped_total", reason="queue") == 7
    assert metric(rt, "gaitflow_stage_frames_in_total") == 11


def test_block_then_drop_oldest_waits_first() -> None:
    q = BoundedQueue(2, "block-then-drop-oldest", block_timeout_s=0.1)
    assert q.put(1) == 0 and q.put(2) == 0
    t0 = time.monotonic()
    assert q.put(3) == 1
    assert time.monotonic() - t0 >= 0.09
    assert [q.get(0), q.get(0), q.get(0)] == [2, 3, None]
    assert q.dropped == 1


def test_shutdown_flushes_finish_outputs() -> None:
    def step(n: int, inputs: Any) -> tuple[int, list]:
        return n + 1, []

    def finish(n: int) -> tuple[int, list]:
        return n, [frame(n, last=True)]

    spec = StageSpec("count", ParamSet("count"), lambda p: 0, step, finish, stateful=True)
    bus = FakeBus()
    rt = StageRuntime(bus, RELAY, spec, {}).start()
    for i in range(7):
        bus.put(IN, frame(i).encode())
    assert outputs(bus) == []
    rt.stop()
    got = outputs(bus)
    assert [(m.header.frame, m.header.last) for m in got] == [(7, True)]


def test_core_publishing_undeclared_stream_fails_the_stage() -> None:
    node = Node("relay", "gaitflow.stages.relay", ("raw",), ("clean",))
    bus = FakeBus()
    rt = StageRuntime(bus, node, relay.SPEC, {}).start()
    bus.put(IN, frame(0).encode())
    with pytest.raises(StageError, match="not among its outputs"):
        rt.stop()


def test_bad_parameter_is_rejected_at_start() -> None:
    with pytest.raises(ParameterError, match="speed"):
        make_runtime(FakeBus(), RELAY, {"speed": 3})


def _source(n: int) -> SourceSpec:
    def open_(params: dict[str, Any]) -> Iterator[list[RawFrame]]:
        for i in range(n):
            yield [frame(i, last=i == n - 1)]

    return SourceSpec("src", ParamSet("src"), open_)


@pytest.mark.parametrize(("rate", "lo", "hi"), [("1", 0.12, 2.0), ("max", 0.0, 0.1)])
def test_source_paces_by_capture_time(rate: str, lo: float, hi: float) -> None:
    bus = FakeBus()
    node = Node("grab", "x", (), ("raw",))
    rt = SourceRuntime(bus, node, _source(5), {}, RuntimeOptions(rate=rate))
    t0 = time.monotonic()
    rt.start()
    assert rt.done.wait(5)
    dt = time.monotonic() - t0
    rt.stop()
    assert lo <= dt <= hi  # 4 intervals of 33.3 ms at rate 1
    assert [m.header.frame for m in outputs(bus, IN)] == [0, 1, 2, 3, 4]


def test_frame_error_in_core_is_counted_and_other_exceptions_fail_the_worker() -> None:
    from gaitflow.errors import FrameError

    def step(state: Any, inputs: Any) -> tuple[Any, list]:
        m = inputs["raw"]
        if m.header.frame == 1:
            raise FrameError("frame 1", "unreadable")
        if m.header.frame == 3:
            raise RuntimeError("bug")
        return state, [m]

    spec = StageSpec("flaky", ParamSet("flaky"), lambda p: None, step)
    bus = FakeBus()
    rt = StageRuntime(bus, RELAY, spec, {}).start()
    for i in range(3):
        bus.put(IN, frame(i).encode())
    assert rt.done.wait(0.3) is False  # a FrameError does not stop the worker
    bus.put(IN, frame(3).encode())
    assert rt.done.wait(5)
    with pytest.raises(StageError, match="bug"):
        rt.stop()
    assert [m.header.frame for m in outputs(bus)] == [0, 2]
    assert metric(rt, "gaitflow_stage_errors_total") == 1


def test_per_camera_worker_takes_its_camera_only_and_names_itself_by_it() -> None:
    bus = FakeBus()
    src = bus.connected()
    opt = RuntimeOptions(camera="cam-2")
    rt = StageRuntime(bus, RELAY, relay.SPEC, {}, opt).start()
    assert src.alive("gaitflow/clinic/@alive/**") == ["gaitflow/clinic/@alive/relay/cam-2"]
    for i in range(3):
        for cam in ("cam-1", "cam-2"):
            src.put(f"gaitflow/clinic/{cam}/raw", frame(i, cam=cam).encode())
    rt.stop()
    assert outputs(bus, "gaitflow/clinic/cam-1/raw-1") == []
    assert [m.header.frame for m in outputs(bus, "gaitflow/clinic/cam-2/raw-1")] == [0, 1, 2]
    labels = {"stage": "relay", "worker": "cam-2"}
    assert rt.metrics.registry.get_sample_value("gaitflow_stage_frames_in_total", labels) == 3


def test_per_camera_stage_may_not_also_be_replicated() -> None:
    from gaitflow.stages.graph import parse

    doc = {
        "version": 1,
        "stages": [
            {"name": "src", "module": "m", "outputs": ["raw"]},
            {"name": "r", "module": "m", "inputs": ["raw"], "outputs": ["clean"],
             "per_camera": True, "replicas": 2},
        ]
    }  # fmt: skip
    with pytest.raises(ConfigError, match="per_camera"):
        parse(doc, "test graph")
    doc["stages"][1]["replicas"] = 1
    doc["stages"][1]["per_camera"] = "yes"
    with pytest.raises(ConfigError, match="true or false"):
        parse(doc, "test graph")
