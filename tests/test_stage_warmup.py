"""Warm-up of the compiled kernels before a stage reports ready (``stages/warmup.py``)."""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.schemas import Blobs, CleanFrame
from gaitflow.stages import alg_kernels, clean, detect, locate
from gaitflow.stages.warmup import _through_codec, run_chain
from test_locate_alg import locate_inputs

from gaitflow.errors import StageError


def test_locate_warmup_loads_the_kernels_for_decoded_and_writeable_frames() -> None:
    locate.SPEC.warmup(locate.PARAMS.resolve({}))
    # a decoded bus message is read-only: numba compiles that as its own signature, which
    # the first frame off the bus would otherwise wait for
    for kernel in (alg_kernels.locate_depths, alg_kernels.complete_occluded):
        depth_types = {sig[0] for sig in kernel.signatures}
        assert {t.mutable for t in depth_types} == {True, False}, kernel


def test_every_kernel_stage_declares_its_warmup() -> None:
    for mod in (clean, detect, locate):
        assert mod.SPEC.warmup is not None


def test_a_stage_without_a_chain_is_named() -> None:
    with pytest.raises(StageError, match="gait"):
        run_chain("gait", {})


def _kernel_signatures() -> dict[str, int]:
    return {
        name: len(obj.signatures)
        for name, obj in vars(alg_kernels).items()
        if hasattr(obj, "signatures")
    }


def _frame(blobs: int, readonly: bool) -> tuple[CleanFrame, Blobs]:
    """A clean frame (a plane at 2.5 m with marker holes) and its blobs, decoded from the
    bus (read-only) or writeable."""
    rows, cols = np.mgrid[:48, :64]
    depth = np.full((48, 64), 2500, np.uint16)
    centres = np.array([[12.3, 10.6], [30.2, 20.4], [50.7, 33.1]])[:blobs]
    for u, v in centres:
        depth[(cols - u) ** 2 + (rows - v) ** 2 <= 4] = 0
    cf, bl = locate_inputs(depth, centres, np.full(blobs, 2.5), np.full(blobs, 13))
    return _through_codec(cf, readonly), _through_codec(bl, readonly)


@pytest.mark.parametrize("blobs", [0, 1, 3])
def test_no_kernel_compiles_after_warmup_whatever_the_blob_count(blobs: int) -> None:
    # A kernel compiled at the first real frame stalls the stage for seconds on a fresh
    # machine, and the joined input runs ahead: every array a kernel takes must have the
    # types warm-up saw (a column of an (N, 3) array is strided for N > 1 only).
    params = locate.PARAMS.resolve({})
    locate.SPEC.warmup(params)
    before = _kernel_signatures()
    for readonly in (True, False):
        cf, bl = _frame(blobs, readonly)
        locate.step(locate.init(params), {"clean": cf, "blobs": bl})
    assert _kernel_signatures() == before
