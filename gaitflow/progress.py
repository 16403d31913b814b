"""Progress bars for long batch work (tqdm), quiet when not on a terminal or with --quiet.

Commands add the flag with :func:`add_quiet_flag` and wrap their loops::

    for item in progress(items, desc="replay", unit="frame", quiet=args.quiet):
        ...

The bar goes to stderr, so stdout stays clean for tables and JSON.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterable
from typing import Any, TextIO, TypeVar

from tqdm import tqdm

T = TypeVar("T")


def add_quiet_flag(p: argparse.ArgumentParser) -> None:
    """Add ``-q/--quiet``: no progress bars or periodic status lines."""
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or status lines")


def enabled(quiet: bool = False, stream: TextIO | None = None) -> bool:
    """True when a bar should be drawn: not quiet, stream is a TTY, GAITFLOW_QUIET unset."""
    s = sys.stderr if stream is None else stream
    if quiet or os.environ.get("GAITFLOW_QUIET", "") not in ("", "0"):
        return False
    isatty = getattr(s, "isatty", None)
    return bool(isatty and isatty())


def progress(
    iterable: Iterable[T] | None = None,
    total: float | None = None,
    desc: str = "",
    unit: str = "it",
    quiet: bool = False,
    stream: TextIO | None = None,
    **kw: Any,
) -> tqdm:
    """A tqdm bar on stderr, disabled (no output at all) when :func:`enabled` is false.

    Use it as an iterable wrapper, or with ``iterable=None`` and ``total`` and call
    ``update(n)`` / ``close()`` (or use it as a context manager).
    """
    s = sys.stderr if stream is None else stream
    return tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        file=s,
        disable=not enabled(quiet, s),
        dynamic_ncols=True,
        leave=False,
        **kw,
    )
