"""Session set-up shared by every test module."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile (or load) the numba kernels of clean, detect and locate once, first.

    On a fresh checkout the compile takes tens of seconds and lands in numba's disk cache;
    done here, the stage processes that bus tests start load it in about a second instead
    of each compiling it at once inside a test's time limits.
    """
    from gaitflow.stages import locate

    locate.SPEC.warmup(locate.PARAMS.resolve({}))
