"""Warm-up of the compiled kernels before a stage reports ready (``stages/warmup.py``)."""

from __future__ import annotations

import pytest
from gaitflow.stages import alg_kernels, clean, detect, locate
from gaitflow.stages.warmup import run_chain

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
