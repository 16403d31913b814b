"""Shared output for ``gaitflow bench``: a human table, or one JSON object with --json."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np


def add_json_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def mean_sd(values: Sequence[float | None]) -> tuple[float, float]:
    """Mean and sample standard deviation of the finite ``values`` (None and NaN left
    out): the pair the paper's tables give per figure. NaN mean without values, NaN SD
    with fewer than two."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    mean = float(v.mean()) if v.size else float("nan")
    return mean, float(v.std(ddof=1)) if v.size > 1 else float("nan")


def plus_minus(mean: float | None, sd: float | None, signed: bool = False) -> str:
    """``mean ± sd`` as a table cell, 2 decimals (``signed``: the mean with its sign);
    "-" without a mean, the mean alone without an SD."""
    if mean is None or not np.isfinite(mean):
        return "-"
    out = f"{mean:+.2f}" if signed else f"{mean:.2f}"
    return out + (f" ± {sd:.2f}" if sd is not None and np.isfinite(sd) else "")


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
