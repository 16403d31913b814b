"""The per-frame join of a stage with two inputs when one input runs far ahead."""

from __future__ import annotations

import numpy as np
from gaitflow.schemas import RawFrame
from gaitflow.stages.base import StageSpec
from gaitflow.stages.driver import StageDriver
from gaitflow.stages.graph import Node

from gaitflow.params import ParamSet

NODE = Node("j", "m", ("raw", "clean"), ("raw",))


def frame(i: int) -> RawFrame:
    z = np.zeros((2, 2), np.uint16)
    return RawFrame(header=RawFrame.make_header("c", "walk-01", i, i), ir=z, depth=z)


def step(state: None, inputs):  # type: ignore[no-untyped-def]
    return state, [inputs["raw"]]


SPEC = StageSpec("j", ParamSet([]), init=lambda p: None, step=step)


def test_a_lagging_input_joins_again_after_the_window_overflowed() -> None:
    d = StageDriver(NODE, SPEC, {}, max_join=8)
    for i in range(20):  # one input runs 20 frames ahead of the other: 12 fall out
        assert d.offer("raw", frame(i)) == []
    done = [m.header.frame for i in range(20) for m in d.offer("clean", frame(i))]
    # the 8 frames still in the window join; the 12 whose partners fell out are dropped
    # without pushing the window's frames out in turn
    assert done == list(range(12, 20))
    assert d.dropped == 12 + 12
