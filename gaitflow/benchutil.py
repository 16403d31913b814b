"""Shared output for ``gaitflow bench``: a human table, or one JSON object with --json."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from typing import Any


def add_json_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _cell(v: Any) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "-"
        return f"{v:.3g}" if abs(v) < 1e-2 or abs(v) >= 1e5 else f"{v:.2f}"
    return "-" if v is None else str(v)


def format_table(title: str, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A plain-text table with a title line."""
    cells = [[_cell(v) for v in r] for r in rows]
    widths = [max([len(c), *(len(r[i]) for r in cells)]) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))
    out = [title, line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join(out)


def emit(args: argparse.Namespace, figures: dict[str, Any], tables: Sequence[str]) -> None:
    """Print ``figures`` as JSON (with --json) or the human ``tables``."""
    if getattr(args, "json", False):
        print(json.dumps(figures, default=float, allow_nan=True))
    else:
        print("\n\n".join(tables))
