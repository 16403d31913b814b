"""The core's deferred ``after`` work: same messages, same order, in-process or on the bus."""

from __future__ import annotations

import numpy as np
from gaitflow.schemas import RawFrame
from gaitflow.stages.base import StageSpec
from gaitflow.stages.driver import StageDriver
from gaitflow.stages.graph import Node

from gaitflow.params import ParamSet

NODE = Node("s", "m", ("raw",), ("raw",), side_inputs={"calibration": ("walk",)})


def frame(i: int) -> RawFrame:
    z = np.zeros((2, 2), np.uint16)
    return RawFrame(header=RawFrame.make_header("c", "walk-01", i, i), ir=z, depth=z)


def step(state: tuple[int, ...], inputs):  # type: ignore[no-untyped-def]
    # the step's output carries how many ``after`` runs the state has seen
    m = inputs["raw"]
    out = RawFrame(header=m.header, ir=m.ir, depth=np.full((2, 2), len(state), np.uint16))
    return state, [out]


def after(state: tuple[int, ...]):  # type: ignore[no-untyped-def]
    n = len(state)
    z = np.full((2, 2), 100 + n, np.uint16)
    return (*state, n), [RawFrame(header=RawFrame.make_header("c", "after", n, 0), ir=z, depth=z)]


SPEC = StageSpec("s", ParamSet([]), init=lambda p: (), step=step, after=after, stateful=True)


def tags(msgs: list[RawFrame]) -> list[str]:
    return [f"{m.header.trial}:{int(m.depth[0, 0])}" for m in msgs]


def test_after_runs_inline_or_deferred_with_the_same_result() -> None:
    inline = StageDriver(NODE, SPEC, {})
    bus = StageDriver(NODE, SPEC, {}, defer_after=True)
    got_inline: list[RawFrame] = []
    got_bus: list[RawFrame] = []
    # frames 0 and 1 are held until the side input comes, then run together
    for d, got in ((inline, got_inline), (bus, got_bus)):
        got += d.offer("raw", frame(0))
        got += d.offer("raw", frame(1))
        assert got == []
        got += d.offer("calibration", frame(0))  # any message stands for the side input
        if d.defer_after:
            # the last step's after work waits for the caller; an earlier step's did not
            assert tags(got) == ["walk-01:0", "after:100", "walk-01:1"]
            got += d.run_after()
        got += d.offer("raw", frame(2))
        got += d.finish()
    assert tags(got_inline) == [
        "walk-01:0", "after:100", "walk-01:1", "after:101", "walk-01:2", "after:102",
    ]  # fmt: skip
    assert tags(got_bus) == tags(got_inline)
