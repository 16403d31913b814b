"""Warm-up of the compiled (numba) kernels before a stage process reports ready.

The kernels of clean, detect and locate (``alg_kernels``) are compiled on first use and
cached on disk; loading them still takes about a second, and compiling them on a fresh
machine tens of seconds. Taken at the first frame, that stall lets the other input of a
joined stage (locate takes ``clean`` and ``blobs``) run ahead of it by more than the join
window. So the runtime calls a stage's ``warmup`` before it subscribes and declares its
liveliness token, and the launcher (``wait_ready``) starts the source only after that.

Warm-up runs the stage cores themselves on a small synthetic frame (a plane with two bright
discs) that went through the bus codec, so the kernels see exactly the array types of a
decoded message (read-only, C-contiguous), and on the same arrays made writeable, as the
in-process runner passes them. Each stage runs the chain up to itself: default parameters
upstream, its own parameters for itself. Nothing is published and no state is kept.

Array conventions: images (row, col), uint16; depth mm, 0 = invalid.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import numpy as np
from gaitflow.schemas import Message, RawFrame, decode

from gaitflow.errors import StageError

CHAIN = ("clean", "detect", "locate")
M = TypeVar("M", bound=Message)
FRAME_SHAPE = (48, 64)  # rows, cols: small, the kernels' types do not depend on the size


def synthetic_raw(readonly: bool) -> RawFrame:
    """A decoded raw frame of a walk: a plane at 2.5 m and two bright marker discs with
    depth holes, as a camera would see them."""
    rows, cols = np.mgrid[: FRAME_SHAPE[0], : FRAME_SHAPE[1]]
    ir = np.full(FRAME_SHAPE, 800, np.uint16)
    depth = np.full(FRAME_SHAPE, 2500, np.uint16)
    for r0, c0 in ((16, 20), (30, 44)):
        disc = (rows - r0) ** 2 + (cols - c0) ** 2 <= 9
        ir[disc] = 60000
        depth[disc] = 0
    msg = RawFrame(header=RawFrame.make_header("warmup", "walk-01", 0, 0), ir=ir, depth=depth)
    return _through_codec(msg, readonly)


def _through_codec(msg: M, readonly: bool) -> M:
    """``msg`` encoded and decoded as the bus runtime has it (read-only arrays), or with
    every array field copied (writeable), as the in-process runner has it."""
    out = decode(type(msg), msg.encode())
    if readonly:
        return out
    arrays = {
        f.name: getattr(out, f.name).copy()
        for f in dataclasses.fields(out)
        if isinstance(getattr(out, f.name), np.ndarray)
    }
    return dataclasses.replace(out, **arrays)


def run_chain(upto: str, params: Mapping[str, Any]) -> None:
    """Run clean, detect and locate up to ``upto`` on the synthetic frame, read-only and
    writeable; ``params`` are ``upto``'s resolved parameters.

    Raises StageError when a core produces no message where the next one needs it.
    """
    import importlib

    if upto not in CHAIN:
        raise StageError(upto, f"no warm-up chain for stage {upto!r}")
    for readonly in (True, False):
        msgs: dict[str, Message] = {"raw": synthetic_raw(readonly)}
        for name in CHAIN[: CHAIN.index(upto) + 1]:
            mod = importlib.import_module(f"gaitflow.stages.{name}")
            spec = mod.SPEC
            p = dict(params) if name == upto else spec.params.resolve({})
            _, out = spec.step(spec.init(p), msgs)
            if name == upto:
                break
            if len(out) != 1:
                raise StageError(name, f"warm-up produced {len(out)} messages, expected 1")
            msgs[out[0].STREAM] = _through_codec(out[0], readonly)


def stage_warmup(stage: str) -> Callable[[dict[str, Any]], None]:
    """The ``StageSpec.warmup`` of a stage of :data:`CHAIN`: :func:`run_chain` up to it."""
    if stage not in CHAIN:
        raise StageError(stage, f"no warm-up chain for stage {stage!r}")
    return functools.partial(run_chain, stage)
