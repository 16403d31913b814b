"""A pass-through stage for tests and benchmarks of the bus runtime.

The core re-publishes every primary input it is given, unchanged (the runtime re-encodes
it, so each hop pays the full decode/encode cost of a real stage). It has no algorithm
and no parameters. Chain relays in a graph with ``topics`` so that each hop publishes
under its own key, e.g. ``inputs: [raw]``, ``input_topics: {raw: raw}``,
``topics: {raw: raw-1}``.
"""

from __future__ import annotations

from typing import Any

from gaitflow.schemas import Message
from gaitflow.stages.base import Inputs, StageSpec

from gaitflow.params import ParamSet


def init(params: dict[str, Any]) -> None:
    """Stateless: no state."""
    return None


def step(state: None, inputs: Inputs) -> tuple[None, list[Message]]:
    """Return every input message as an output, in the order given."""
    return state, list(inputs.values())


SPEC = StageSpec(
    name="relay",
    params=ParamSet("relay"),
    init=init,
    step=step,
    doc="Pass-through: publishes its inputs unchanged (bus tests and benchmarks).",
)
