"""The pipeline as data: loading and checking ``deploy/pipeline.yaml``.

The launcher, the in-process runner, the deploy generators and the docs all read this one
description. A node names its stage module (which exposes ``SPEC``), the streams it joins
per frame (``inputs``), the latest-value streams it needs (``side_inputs``, each with the
trial kinds that need it), its ``outputs``, its machine ``role`` and ``replicas``.

``per_camera: true`` marks a stateful per-frame stage that scales out by camera: where a
machine serves several cameras (the server role), it runs one worker process per camera,
so one camera's heavy step (a trial's summary, a re-initialised track) never delays
another camera's frames. ``replicas`` (frame index mod N) is for stateless stages only.

Optional ``topics`` / ``input_topics`` map a stream to the key segment a node publishes /
reads it under (default: the stream name). They let test and benchmark graphs chain
pass-through stages (relay -> relay) without a stream having two producers.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from gaitflow.schemas import STREAMS
from gaitflow.stages.base import StageSpec

from gaitflow.errors import ConfigError

ROLES = ("edge", "server")
TRIAL_KINDS = ("calibration", "static", "walk")


@dataclass(frozen=True)
class Node:
    """One stage in the graph."""

    name: str
    module: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    side_inputs: dict[str, tuple[str, ...]] = field(default_factory=dict)
    trials: tuple[str, ...] = TRIAL_KINDS
    role: str = "server"
    replicas: int = 1
    per_camera: bool = False
    optional_roles: tuple[str, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)
    topics: dict[str, str] = field(default_factory=dict)
    input_topics: dict[str, str] = field(default_factory=dict)

    def out_topic(self, stream: str) -> str:
        """The key segment this node publishes ``stream`` under."""
        return self.topics.get(stream, stream)

    def in_topic(self, stream: str) -> str:
        """The key segment this node reads ``stream`` from."""
        return self.input_topics.get(stream, stream)

    def spec(self) -> StageSpec:
        """Import the stage module and return its ``SPEC``."""
        try:
            mod = importlib.import_module(self.module)
        except ImportError as exc:
            raise ConfigError(f"stage {self.name!r}: cannot import {self.module}: {exc}") from exc
        spec = getattr(mod, "SPEC", None)
        if not isinstance(spec, StageSpec):
            raise ConfigError(f"stage {self.name!r}: {self.module} has no StageSpec named SPEC")
        return spec


@dataclass(frozen=True)
class Graph:
    """The whole pipeline description."""

    site: str
    nodes: tuple[Node, ...]
    source: str = ""

    def node(self, name: str) -> Node:
        for n in self.nodes:
            if n.name == name:
                return n
        raise ConfigError(f"{self.source}: no stage named {name!r}")

    def producers(self) -> dict[str, str]:
        """Stream name (or remapped topic) -> name of the stage that publishes it."""
        return {n.out_topic(s): n.name for n in self.nodes for s in n.outputs}

    def order(self) -> list[Node]:
        """Nodes in topological order (producers before consumers)."""
        prod = self.producers()
        done: list[Node] = []
        seen: set[str] = set()

        def visit(n: Node, path: tuple[str, ...]) -> None:
            if n.name in seen:
                return
            if n.name in path:
                raise ConfigError(f"{self.source}: cycle through {' -> '.join((*path, n.name))}")
            for s in (*n.inputs, *n.side_inputs):
                if n.in_topic(s) in prod:
                    visit(self.node(prod[n.in_topic(s)]), (*path, n.name))
            seen.add(n.name)
            done.append(n)

        for n in self.nodes:
            visit(n, ())
        return done


def _as_tuple(v: Any, where: str) -> tuple[str, ...]:
    if v is None:
        return ()
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{where}: expected a list of names, got {v!r}")
    return tuple(v)


def _as_bool(v: Any, where: str) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(f"{where}: expected true or false, got {v!r}")
    return v


def _as_topics(v: Any, where: str) -> dict[str, str]:
    if v is None:
        return {}
    if not isinstance(v, dict) or not all(
        isinstance(k, str) and isinstance(x, str) for k, x in v.items()
    ):
        raise ConfigError(f"{where}: expected a mapping stream -> key segment, got {v!r}")
    return dict(v)


def parse(doc: Any, source: str = "pipeline.yaml") -> Graph:
    """Build and check a Graph from a parsed YAML document."""
    if not isinstance(doc, dict) or "stages" not in doc:
        raise ConfigError(f"{source}: missing required key 'stages'")
    if doc.get("version") != 1:
        raise ConfigError(f"{source}: unsupported version {doc.get('version')!r} (expected 1)")
    nodes = []
    names: set[str] = set()
    for i, s in enumerate(doc["stages"]):
        where = f"{source}: stages[{i}]"
        if not isinstance(s, dict):
            raise ConfigError(f"{where}: not a mapping")
        for key in ("name", "module"):
            if key not in s:
                raise ConfigError(f"{where}: missing required key {key!r}")
        name = s["name"]
        if name in names:
            raise ConfigError(f"{where}: duplicate stage name {name!r}")
        names.add(name)
        side_raw = s.get("side_inputs") or {}
        if not isinstance(side_raw, dict):
            raise ConfigError(f"{where}: side_inputs must map stream -> trial kinds")
        side = {k: _as_tuple(v, f"{where}.side_inputs.{k}") for k, v in side_raw.items()}
        node = Node(
            name=name,
            module=s["module"],
            inputs=_as_tuple(s.get("inputs"), f"{where}.inputs"),
            outputs=_as_tuple(s.get("outputs"), f"{where}.outputs"),
            side_inputs=side,
            trials=_as_tuple(s.get("trials", list(TRIAL_KINDS)), f"{where}.trials"),
            role=s.get("role", "server"),
            replicas=int(s.get("replicas", 1)),
            per_camera=_as_bool(s.get("per_camera", False), f"{where}.per_camera"),
            optional_roles=_as_tuple(s.get("optional_roles"), f"{where}.optional_roles"),
            params=dict(s.get("params") or {}),
            topics=_as_topics(s.get("topics"), f"{where}.topics"),
            input_topics=_as_topics(s.get("input_topics"), f"{where}.input_topics"),
        )
        if node.role not in ROLES:
            raise ConfigError(f"{where}: role {node.role!r} is not one of {ROLES}")
        if node.replicas < 1:
            raise ConfigError(f"{where}: replicas must be >= 1, got {node.replicas}")
        if node.per_camera and node.replicas > 1:
            raise ConfigError(
                f"{where}: per_camera stages scale by camera; replicas must be 1, "
                f"got {node.replicas}"
            )
        for st in (*node.inputs, *node.outputs, *node.side_inputs):
            if st not in STREAMS:
                raise ConfigError(f"{where}: unknown stream {st!r}")
        for kinds in (node.trials, *node.side_inputs.values()):
            for k in kinds:
                if k not in TRIAL_KINDS:
                    raise ConfigError(f"{where}: unknown trial kind {k!r}")
        nodes.append(node)
    graph = Graph(site=str(doc.get("site", "clinic")), nodes=tuple(nodes), source=source)
    prod: dict[str, str] = {}
    for n in graph.nodes:
        for s in map(n.out_topic, n.outputs):
            if s in prod:
                raise ConfigError(f"{source}: stream {s!r} published by {prod[s]} and {n.name}")
            prod[s] = n.name
    for n in graph.nodes:
        if "truth" in (*n.inputs, *n.side_inputs):
            raise ConfigError(f"{source}: stage {n.name!r} may not read ground truth")
    graph.order()
    return graph


def load(path: str | Path | None = None) -> Graph:
    """Load the pipeline description (default: the packaged ``deploy/pipeline.yaml``)."""
    if path is None:
        text = resources.files("gaitflow.deploy").joinpath("pipeline.yaml").read_text()
        source = "deploy/pipeline.yaml"
    else:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read: {exc}") from exc
        source = str(p)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{source}: not valid YAML: {exc}") from exc
    return parse(doc, source)


def markdown_table(graph: Graph) -> str:
    """The graph as a Markdown table, for the README (kept in sync by a test)."""
    rows = [
        "| stage | reads (joined per frame) | side inputs (trial kinds) | trials | writes | role |",
        "|---|---|---|---|---|---|",
    ]
    for n in graph.order():
        side = ", ".join(f"{s} ({'/'.join(k)})" for s, k in n.side_inputs.items()) or "-"
        role = n.role + "".join(f", or {r}" for r in n.optional_roles)
        rows.append(
            f"| {n.name} | {', '.join(n.inputs) or '-'} | {side} | {'/'.join(n.trials)} "
            f"| {', '.join(n.outputs)} | {role} |"
        )
    return "\n".join(rows)


if __name__ == "__main__":
    print(markdown_table(load()))
