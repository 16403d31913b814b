"""The stage contract: a pure core plus declared parameters.

A stage is a :class:`StageSpec`:

- ``params``: its declared parameters (``gaitflow.params.ParamSet``);
- ``init(params) -> state``: the explicit initial state (a frozen dataclass, or None for a
  stateless stage);
- ``step(state, inputs) -> (state, outputs)``: the core. ``inputs`` maps stream name to the
  decoded message of this frame (the joined primary inputs) and, for side inputs, to the
  latest message of that stream for the camera (or is absent). ``outputs`` is a list of
  messages to publish, in order;
- ``finish(state) -> (state, outputs)``: optional, called at shutdown to flush;
- ``after(state) -> (state, outputs)``: optional deferred work of the step just run (a
  heavy analysis whose results are not part of this frame's output). The bus adapter runs
  it once the step's outputs are published, so they are not delayed by it; the in-process
  runner right after the step. Both publish the same messages in the same order.

No I/O, no bus, no globals in a core: the bus adapter (``gaitflow.stages.runtime``) and the
in-process runner (``gaitflow.stages.inline``) both drive the same spec, so they give
identical results. Which streams a stage reads and writes is not declared here but in the
pipeline description, ``deploy/pipeline.yaml`` (see ``gaitflow.stages.graph``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from gaitflow.schemas import Message

from gaitflow.params import ParamSet

Inputs = Mapping[str, Message]
StepResult = tuple[Any, list[Message]]


@dataclass(frozen=True)
class StageSpec:
    """A stage: declared parameters and its pure core functions."""

    name: str
    params: ParamSet
    init: Callable[[dict[str, Any]], Any]
    step: Callable[[Any, Inputs], StepResult]
    finish: Callable[[Any], StepResult] | None = None
    after: Callable[[Any], StepResult] | None = None
    # run once by the bus runtime before the stage reports ready (e.g. load compiled kernels)
    warmup: Callable[[dict[str, Any]], None] | None = None
    stateful: bool = False
    doc: str = ""

    def run(self, state: Any, inputs: Inputs) -> StepResult:
        """``step`` then ``after``, as the in-process runner drives a core."""
        state, out = self.step(state, inputs)
        if self.after is None:
            return state, out
        state, later = self.after(state)
        return state, [*out, *later]


@dataclass(frozen=True)
class SourceSpec:
    """A source stage (grab): no inputs; yields frames.

    ``open(params)`` returns an iterator; each item is the list of messages of one camera
    frame (for the simulator: a ``RawFrame`` and its ``GroundTruth``), in capture order.
    Headers carry capture times, so the runtime can pace publication at the original rate
    (``rate == "1"``) or publish as fast as the pipeline accepts (``rate == "max"``).
    """

    name: str
    params: ParamSet
    open: Callable[[dict[str, Any]], Iterator[list[Message]]]
    doc: str = ""
