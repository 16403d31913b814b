"""Source pacing across trials, and bad input at a source's start."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from gaitflow.bus import FakeBus
from gaitflow.schemas import RawFrame
from gaitflow.stages.base import SourceSpec
from gaitflow.stages.graph import Node
from gaitflow.stages.runtime import RuntimeOptions, SourceRuntime, serve

from gaitflow.errors import InputError
from gaitflow.params import ParamSet

NODE = Node("grab", "x", (), ("raw",))


def _frame(trial: str, i: int, capture_ns: int) -> RawFrame:
    return RawFrame(
        header=RawFrame.make_header("cam0", trial, i, capture_ns),
        ir=np.zeros((2, 3), np.uint16),
        depth=np.zeros((2, 3), np.uint16),
    )


def test_rate_1_paces_within_a_trial_not_across_the_gap_between_recordings() -> None:
    def open_(params: dict[str, Any]) -> Iterator[list[RawFrame]]:
        for trial, t0 in (("static", 0), ("walk-01", 60_000_000_000)):  # captured 60 s apart
            for i in range(3):
                yield [_frame(trial, i, t0 + i * 33_333_333)]

    rt = SourceRuntime(
        FakeBus(), NODE, SourceSpec("src", ParamSet("src"), open_), {}, RuntimeOptions(rate="1")
    )
    t0 = time.monotonic()
    rt.start()
    assert rt.done.wait(10)
    rt.stop()
    dt = time.monotonic() - t0
    assert rt.published == 6
    assert 0.1 <= dt < 5.0  # 2 x 2 intervals of 33 ms, not a minute


def test_bad_input_at_source_start_exits_2_so_the_launcher_does_not_retry() -> None:
    def open_(params: dict[str, Any]) -> Iterator[list[RawFrame]]:
        raise InputError("/sessions/S01/camera.json", "missing required key 'fps'")
        yield []

    import gaitflow.stages.runtime as runtime

    spec = SourceSpec("src", ParamSet("src"), open_)
    original = runtime._load_spec
    runtime._load_spec = lambda node: spec
    try:
        code = serve(NODE, FakeBus, options=RuntimeOptions(rate="max"))
    finally:
        runtime._load_spec = original
    assert code == 2
