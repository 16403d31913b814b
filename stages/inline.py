"""Run a pipeline graph in one process, through the same cores and drivers as the bus.

Used by ``gaitflow analyze --inline``, by benchmarks and by tests. Messages from the source
are routed breadth-first to every node that reads their stream, in topological order.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from gaitflow.schemas import Message
from gaitflow.stages.driver import StageDriver
from gaitflow.stages.graph import Graph

Sink = Callable[[str, Message], None]


class InlinePipeline:
    """A set of graph nodes driven in-process.

    Parameters
    ----------
    graph : the pipeline description.
    stages : names of the nodes to run (default: every node that has inputs, i.e. all but
        the source).
    params : per-stage parameter overrides, on top of the graph's own ``params``.
    sink : called with (stream, message) for every message any node publishes.
    """

    def __init__(
        self,
        graph: Graph,
        stages: Iterable[str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        sink: Sink | None = None,
    ) -> None:
        names = set(stages) if stages is not None else {n.name for n in graph.nodes if n.inputs}
        self.drivers: list[StageDriver] = []
        for node in graph.order():
            if node.name not in names:
                continue
            spec = node.spec()
            overrides = {**node.params, **dict((params or {}).get(node.name, {}))}
            self.drivers.append(StageDriver(node, spec, spec.params.resolve(overrides)))
        self.sink = sink

    def _route(self, queue: deque[tuple[str, Message]]) -> None:
        while queue:
            stream, msg = queue.popleft()
            if self.sink is not None:
                self.sink(stream, msg)
            for d in self.drivers:
                if stream in d.node.inputs or stream in d.node.side_inputs:
                    for out in d.offer(stream, msg):
                        queue.append((out.STREAM, out))

    def push(self, msg: Message) -> None:
        """Feed one source message (its stream is the message's own)."""
        self._route(deque([(msg.STREAM, msg)]))

    def finish(self) -> None:
        """Flush every node, upstream first."""
        for d in self.drivers:
            self._route(deque((o.STREAM, o) for o in d.finish()))


def run_inline(
    graph: Graph,
    messages: Iterable[Message],
    stages: Iterable[str] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, list[Message]]:
    """Push every source message through the graph; return all outputs by stream."""
    out: dict[str, list[Message]] = {}
    pipe = InlinePipeline(graph, stages, params, sink=lambda s, m: out.setdefault(s, []).append(m))
    for m in messages:
        pipe.push(m)
    pipe.finish()
    return out
