"""The trial results JSON (``../shared/spec/results.md``, version 1): build, validate, write.

The document is a stable contract that other tools read. :func:`build_results` makes it from
the gait stage's arrays; :func:`validate` checks a document against the JSON Schema shipped at
``gaitflow/data/results.schema.json`` with a small built-in validator (the subset of JSON
Schema the file uses: type, const, enum, properties, required, additionalProperties, items,
minItems, maxItems, minimum, maximum, anyOf, propertyNames, $ref to ``#/$defs``), so no extra
dependency is needed.

Conventions: positions are camera-space mm (X right, Y down, Z forward), pixels (u, v),
times in seconds from the trial's first frame, angles in degrees. NaN in an input array
becomes JSON ``null``. Fields beyond results.md are additions (allowed by the contract):
``passes``, ``phases``, ``event_uncertainty_s``, ``scope``, ``warnings`` and ``parameters``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow.errors import InputError, SchemaError
from gaitflow.markers import MARKER_NAMES

FORMAT = "gaitflow.trial-results"
VERSION = 1


def floats(xs: Sequence[float | None]) -> np.ndarray:
    """A results list of numbers as a float array, ``null`` (None) as NaN."""
    return np.array([np.nan if v is None else v for v in xs], dtype=float)


def _num(v: Any, ndigits: int = 3) -> float | None:
    """A JSON-safe float (None for NaN/inf), rounded to keep files small."""
    if v is None:
        return None
    f = float(v)
    return round(f, ndigits) if math.isfinite(f) else None


def round_array(a: np.ndarray, ndigits: int) -> np.ndarray:
    """``a`` rounded exactly as Python's ``round(float(x), ndigits)`` rounds each value.

    ``np.round`` scales, rounds and unscales, which can land on the other side of a tie that
    the scaling made inexact; Python rounds the exact binary value. Both give the same double
    except where the scaled value lies within rounding error of a half (or is huge), so those
    few values, and only they, are rounded by Python. Non-finite values pass through.

    a : (...) float. Returns (...) float64.
    """
    a = np.asarray(a, dtype=float)
    scale = 10.0**ndigits
    with np.errstate(invalid="ignore", over="ignore"):
        y = a * scale
        out = np.rint(y) / scale
        tie = np.abs(y - np.floor(y) - 0.5) <= 1e-9 * (1.0 + np.abs(y))
    doubt = np.flatnonzero((tie | ~(np.abs(a) < 1e12)) & np.isfinite(a))
    if doubt.size:
        flat = out.reshape(-1)
        src = a.reshape(-1)
        for i in doubt.tolist():
            flat[i] = round(float(src[i]), ndigits)
        out = flat.reshape(a.shape)
    return np.where(np.isfinite(a), out, a)


def _nums(x: np.ndarray, ndigits: int) -> list[float | None]:
    """``[_num(v, ndigits) for v in x]`` for a 1-D array, vectorised."""
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x).tolist()
    return [v if k else None for v, k in zip(round_array(x, ndigits).tolist(), ok, strict=True)]


def _rows(a: np.ndarray, ndigits: int) -> list[dict[str, list[float] | None]]:
    """(F, 20, D) -> per frame ``{marker name: rounded [D values], or None if any is not
    finite}``, in ``MARKER_NAMES`` order."""
    a = np.asarray(a, dtype=float)
    ok = np.isfinite(a).all(axis=-1)
    vals = round_array(np.where(ok[..., None], a, 0.0), ndigits).tolist()
    for f, k in np.argwhere(~ok).tolist():
        vals[f][k] = None
    return [dict(zip(MARKER_NAMES, row, strict=True)) for row in vals]


def frame_record(
    index: int, time_s: float, position: np.ndarray, pixel: np.ndarray
) -> dict[str, Any]:
    """One entry of :func:`frame_records` (position (20, 3), pixel (20, 2)), for one frame
    a plain loop is cheaper than the vectorised path; the values are the same."""

    def row(r: list[float], ok: bool, nd: int) -> list[float] | None:
        return [round(v, nd) for v in r] if ok else None

    pos, pix = np.asarray(position, dtype=float), np.asarray(pixel, dtype=float)
    ok_p = np.isfinite(pos).all(axis=1).tolist()
    ok_x = np.isfinite(pix).all(axis=1).tolist()
    return {
        "index": int(index),
        "time_s": _num(time_s, 4),
        "markers": {
            n: row(r, k, 1) for n, r, k in zip(MARKER_NAMES, pos.tolist(), ok_p, strict=True)
        },
        "pixels": {
            n: row(r, k, 2) for n, r, k in zip(MARKER_NAMES, pix.tolist(), ok_x, strict=True)
        },
    }


def frame_records(
    frame_index: Sequence[int],
    frame_time_s: np.ndarray,
    positions: np.ndarray,
    pixels: np.ndarray,
) -> list[dict[str, Any]]:
    """The ``frames`` entries of a results document (see :func:`build_results`).

    Made once, they serve the trial's document and, sliced, those of its passes.
    """
    # vectorised rounding: element-by-element rounding dominated the cost of a document
    times = _nums(np.asarray(frame_time_s, dtype=float), 4)
    markers = _rows(positions, 1)
    pix = _rows(pixels, 2)
    return [
        {"index": int(idx), "time_s": ts, "markers": m, "pixels": p}
        for idx, ts, m, p in zip(frame_index, times, markers, pix, strict=True)
    ]


def _clean(obj: Any) -> Any:
    """Recursively replace NaN/inf by None and numpy scalars by Python ones."""
    if isinstance(obj, Mapping):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, np.bool_ | bool):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return _num(obj, 6)
    return obj


def build_results(
    *,
    session: str,
    trial: str,
    camera_fps: float,
    frame_index: Sequence[int],
    frame_time_s: np.ndarray,
    positions: np.ndarray,
    pixels: np.ndarray,
    knee_time_s: np.ndarray,
    knee_deg: Mapping[str, np.ndarray],
    events: Sequence[Mapping[str, Any]],
    spatiotemporal: Mapping[str, Any],
    extra: Mapping[str, Any] | None = None,
    records: Sequence[Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """The results document of one trial.

    Parameters
    ----------
    frame_index : (F,) camera frame indices; frame_time_s : (F,) s from the first frame.
    positions : (F, 20, 3) camera mm, NaN = not seen (as labelled, not gap-filled).
    pixels : (F, 20, 2) (u, v), NaN = not seen.
    knee_time_s : (Q,) s (the resampled time base); knee_deg : {"L": (Q,), "R": (Q,)}.
    events : ``{"side", "kind", "time_s"}`` records. spatiotemporal : per side lists plus
        ``cadence_steps_per_min`` and ``speed_m_s`` (NaN allowed, written as null).
    extra : further top-level fields (additions to results.md version 1).
    records : the ``frames`` entries when already made by :func:`frame_records` from these
        arrays (shared, not copied: a document is read, not edited).
    """
    if records is None:
        frames = frame_records(frame_index, frame_time_s, positions, pixels)
    else:
        frames = list(records)
    knee = {
        "time_s": _nums(knee_time_s, 4),
        "L": _nums(knee_deg["L"], 2),
        "R": _nums(knee_deg["R"], 2),
    }
    st: dict[str, Any] = {}
    for side in ("L", "R"):
        s = spatiotemporal.get(side, {})
        st[side] = {
            k: [_num(x, 4) for x in s.get(k, [])]
            for k in ("step_length_mm", "stride_length_mm", "stance_s", "swing_s")
        }
    st["cadence_steps_per_min"] = _num(spatiotemporal.get("cadence_steps_per_min"), 3)
    st["speed_m_s"] = _num(spatiotemporal.get("speed_m_s"), 4)
    doc: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "session": session,
        "trial": trial,
        "camera_fps": _num(camera_fps, 3),
        "frames": frames,
        "knee_flexion_deg": knee,
        "events": [
            {"side": e["side"], "kind": e["kind"], "time_s": _num(e["time_s"], 4)} for e in events
        ],
        "spatiotemporal": st,
    }
    for k, v in (extra or {}).items():
        if k in doc:
            raise SchemaError("summary", k, "an extra field may not replace a results.md field")
        doc[k] = _clean(v)
    return doc


def empty_results(session: str, trial: str, camera_fps: float, warning: str) -> dict[str, Any]:
    """A valid document with no frames, events or parameters, carrying one warning."""
    return build_results(
        session=session,
        trial=trial,
        camera_fps=camera_fps,
        frame_index=[],
        frame_time_s=np.zeros(0),
        positions=np.zeros((0, 20, 3)),
        pixels=np.zeros((0, 20, 2)),
        knee_time_s=np.zeros(0),
        knee_deg={"L": np.zeros(0), "R": np.zeros(0)},
        events=[],
        spatiotemporal={},
        extra={"scope": "trial", "warnings": [warning], "passes": [], "phases": {"L": [], "R": []}},
    )


# ---------------------------------------------------------------------------------------------
# schema and validation


def schema() -> dict[str, Any]:
    """The JSON Schema of the results document (``gaitflow/data/results.schema.json``)."""
    text = resources.files("gaitflow").joinpath("data/results.schema.json").read_text()
    return json.loads(text)


_TYPES: dict[str, Any] = {
    "object": dict,
    "array": list,
    "string": str,
    "boolean": bool,
    "null": type(None),
}


def _is_type(v: Any, t: str) -> bool:
    if t == "integer":
        return isinstance(v, int) and not isinstance(v, bool)
    if t == "number":
        return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
    return isinstance(v, _TYPES[t])


def _check(v: Any, s: Mapping[str, Any], root: Mapping[str, Any], path: str, errs: list[str]):
    if "$ref" in s:
        ref = s["$ref"]
        if not ref.startswith("#/$defs/"):
            raise SchemaError("results", path, f"unsupported $ref {ref!r}")
        s = root["$defs"][ref.split("/")[-1]]
    if "anyOf" in s:
        for alt in s["anyOf"]:
            sub: list[str] = []
            _check(v, alt, root, path, sub)
            if not sub:
                break
        else:
            errs.append(f"{path}: {_short(v)} matches none of the allowed forms")
            return
    if "type" in s:
        types = s["type"] if isinstance(s["type"], list) else [s["type"]]
        if not any(_is_type(v, t) for t in types):
            errs.append(f"{path}: {_short(v)} is not of type {' or '.join(types)}")
            return
    if "const" in s and v != s["const"]:
        errs.append(f"{path}: {_short(v)} is not {s['const']!r}")
    if "enum" in s and v not in s["enum"]:
        errs.append(f"{path}: {_short(v)} is not one of {s['enum']}")
    if isinstance(v, int | float) and not isinstance(v, bool):
        if "minimum" in s and v < s["minimum"]:
            errs.append(f"{path}: {v} < minimum {s['minimum']}")
        if "maximum" in s and v > s["maximum"]:
            errs.append(f"{path}: {v} > maximum {s['maximum']}")
    if isinstance(v, list):
        if "minItems" in s and len(v) < s["minItems"]:
            errs.append(f"{path}: {len(v)} items, fewer than {s['minItems']}")
        if "maxItems" in s and len(v) > s["maxItems"]:
            errs.append(f"{path}: {len(v)} items, more than {s['maxItems']}")
        if "items" in s:
            for i, item in enumerate(v):
                _check(item, s["items"], root, f"{path}[{i}]", errs)
    if isinstance(v, dict):
        for k in s.get("required", []):
            if k not in v:
                errs.append(f"{path}: missing required field {k!r}")
        props = s.get("properties", {})
        names = s.get("propertyNames")
        for k, item in v.items():
            if names is not None:
                _check(k, names, root, f"{path}.{k} (name)", errs)
            if k in props:
                _check(item, props[k], root, f"{path}.{k}", errs)
            elif s.get("additionalProperties") is False:
                errs.append(f"{path}: unexpected field {k!r}")
            elif isinstance(s.get("additionalProperties"), dict):
                _check(item, s["additionalProperties"], root, f"{path}.{k}", errs)


def _short(v: Any) -> str:
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def validation_errors(doc: Any, max_errors: int = 20) -> list[str]:
    """Every way ``doc`` breaks the results schema (empty list = valid), at most max_errors."""
    errs: list[str] = []
    root = schema()
    _check(doc, root, root, "$", errs)
    # cross-field rules the schema language cannot say
    if isinstance(doc, dict) and not errs:
        knee = doc["knee_flexion_deg"]
        n = len(knee["time_s"])
        for side in ("L", "R"):
            if len(knee[side]) != n:
                errs.append(f"$.knee_flexion_deg.{side}: {len(knee[side])} values for {n} times")
    return errs[:max_errors]


def validate(doc: Any, source: object = "results") -> None:
    """Raise :class:`SchemaError` naming the first problems if ``doc`` is not valid."""
    errs = validation_errors(doc)
    if errs:
        more = f" (and {len(errs) - 3} more)" if len(errs) > 3 else ""
        raise SchemaError("results", str(source), "; ".join(errs[:3]) + more)


def write_results(doc: Mapping[str, Any], path: str | Path) -> Path:
    """Validate and write one results document as JSON (NaN never appears)."""
    p = Path(path)
    validate(doc, p)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(doc, allow_nan=False, separators=(",", ":")) + "\n")
    return p


def read_results(path: str | Path) -> dict[str, Any]:
    """Read and validate a results document."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(p, f"cannot read results JSON: {exc}") from exc
    validate(doc, p)
    return doc
