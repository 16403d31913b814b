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


def chain_yaml(site: str, hops: int, source_topic: str = "raw", last_replicas: int = 1) -> str:
    """A pipeline description of ``hops`` relays in a chain, for tests and ``bench bus``.

    Relay k reads ``raw`` under topic ``raw-{k-1}`` (the first one under ``source_topic``)
    and publishes it under ``raw-{k}``; the last relay runs ``last_replicas`` ways.
    """
    lines = ["version: 1", f"site: {site}", "stages:"]
    for k in range(1, hops + 1):
        src = source_topic if k == 1 else f"raw-{k - 1}"
        lines += [
            f"  - name: relay{k}",
            "    module: gaitflow.stages.relay",
            "    inputs: [raw]",
            f"    input_topics: {{raw: {src}}}",
            "    outputs: [raw]",
            f"    topics: {{raw: raw-{k}}}",
        ]
        if k == hops and last_replicas > 1:
            lines.append(f"    replicas: {last_replicas}")
    return "\n".join(lines) + "\n"
