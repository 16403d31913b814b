"""Drive one stage's core from a stream of messages: join, side inputs, state.

:class:`StageDriver` is the one place that decides when a stage's ``step`` runs. The bus
adapter (``runtime``) and the in-process runner (``inline``) both feed it decoded messages
in frame order, so both give identical results.

- Primary inputs are joined per (camera, trial, frame): ``step`` runs when every input
  stream of the node has delivered that frame.
- Side inputs keep the latest message per camera. A frame whose trial kind needs a side
  input that has not arrived yet is held (bounded) and released, in order, when it does.
- Trials the node does not take (``Node.trials``) are ignored.
- Both buffers are bounded; what falls out is counted in ``dropped``.
- A core sees one camera: the driver keeps one state per camera, made by ``init`` when
  that camera's first frame arrives, so several cameras can share one stage process.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from typing import Any

from gaitflow.schemas import Message
from gaitflow.stages.base import StageSpec
from gaitflow.stages.graph import Node

from gaitflow.markers import trial_kind

FrameKey = tuple[str, str, int]


class StageDriver:
    """Feeds one node's core. Not thread-safe: call from one thread."""

    def __init__(
        self,
        node: Node,
        spec: StageSpec,
        params: dict[str, Any],
        max_join: int = 64,
        max_held: int = 1024,
        defer_after: bool = False,
    ) -> None:
        self.node, self.spec, self.params = node, spec, params
        # The core's ``after`` work: run inside ``offer`` (False), or left for the caller
        # to run with :meth:`run_after` once it has published what ``offer`` returned.
        self.defer_after = defer_after
        self._after_due: list[str] = []
        self.states: dict[str, Any] = {}
        self.max_join, self.max_held = max_join, max_held
        self._join: OrderedDict[FrameKey, dict[str, Message]] = OrderedDict()
        self._side: dict[tuple[str, str], Message] = {}
        self._held: deque[dict[str, Message]] = deque()
        self.processed = 0
        self.dropped = 0
        self.ignored = 0

    def offer(self, stream: str, msg: Message) -> list[Message]:
        """Take one decoded message; return the messages the core produced (maybe none)."""
        kind = trial_kind(msg.header.trial)
        out: list[Message] = []
        if stream in self.node.side_inputs:
            self._side[(msg.header.camera, stream)] = msg
            out.extend(self._release())
        if stream not in self.node.inputs:
            return out
        if kind not in self.node.trials:
            self.ignored += 1
            return out
        h = msg.header
        key = (h.camera, h.trial, h.frame)
        if key not in self._join and len(self._join) >= self.max_join:
            oldest = next(iter(self._join))
            if oldest[:2] == key[:2] and key[2] < oldest[2]:
                # behind a full window whose partners were already dropped: evicting the
                # oldest slot for it would make every later arrival of this input miss its
                # partner in turn, and the join would never complete a frame again
                self.dropped += 1
                return out
        slot = self._join.setdefault(key, {})
        slot[stream] = msg
        if len(slot) < len(self.node.inputs):
            while len(self._join) > self.max_join:
                self._join.popitem(last=False)
                self.dropped += 1
            return out
        del self._join[key]
        if self._held or not self._ready(slot):
            self._held.append(slot)
            while len(self._held) > self.max_held:
                self._held.popleft()
                self.dropped += 1
            return out
        out.extend(self._run(slot))
        return out

    def _needs(self, inputs: dict[str, Message]) -> list[str]:
        first = next(iter(inputs.values()))
        kind = trial_kind(first.header.trial)
        return [s for s, kinds in self.node.side_inputs.items() if kind in kinds]

    def _ready(self, inputs: dict[str, Message]) -> bool:
        cam = next(iter(inputs.values())).header.camera
        return all((cam, s) in self._side for s in self._needs(inputs))

    def _release(self) -> list[Message]:
        out: list[Message] = []
        while self._held and self._ready(self._held[0]):
            out.extend(self._run(self._held.popleft()))
        return out

    def _run(self, inputs: dict[str, Message]) -> list[Message]:
        # Deferred work of an earlier step runs before the next step, whoever drives: the
        # next step's state includes it (held frames released together run in turn).
        out = self.run_after()
        cam = next(iter(inputs.values())).header.camera
        full = dict(inputs)
        for s in self.node.side_inputs:
            if (cam, s) in self._side:
                full[s] = self._side[(cam, s)]
        state = self.states[cam] if cam in self.states else self.spec.init(self.params)
        self.states[cam], outputs = self.spec.step(state, full)
        self.processed += 1
        out.extend(outputs)
        if self.spec.after is not None:
            self._after_due.append(cam)
            if not self.defer_after:
                out.extend(self.run_after())
        return out

    def run_after(self) -> list[Message]:
        """The core's deferred ``after`` work for every step run since the last call."""
        out: list[Message] = []
        while self._after_due:
            cam = self._after_due.pop(0)
            self.states[cam], outputs = self.spec.after(self.states[cam])  # type: ignore[misc]
            out.extend(outputs)
        return out

    @property
    def held(self) -> int:
        return len(self._held)

    def finish(self) -> list[Message]:
        """Flush at shutdown: the core's ``finish``; held frames are counted as dropped."""
        pending = self.run_after()
        self.dropped += len(self._held) + len(self._join)
        self._held.clear()
        self._join.clear()
        if self.spec.finish is None:
            return pending
        out: list[Message] = pending
        for cam in sorted(self.states):
            self.states[cam], outputs = self.spec.finish(self.states[cam])
            out.extend(outputs)
        return out
