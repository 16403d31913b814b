"""Depth-camera geometry: intrinsics, Brown–Conrady distortion, projection.

Conventions (``../shared/spec/session-folder.md``):

- pixel (u, v) = (column, row); (0, 0) is the centre of the top-left pixel;
- camera space: X right, Y down, Z forward, millimetres; Kinect depth is Z, not ray length;
- distortion is Brown–Conrady with k1, k2, k3 radial and p1, p2 tangential, as in OpenCV.

Point arrays are (N, 3) for camera space and (N, 2) for pixels; NaN propagates.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gaitflow.errors import InputError

REQUIRED_KEYS = ("model", "width", "height", "fps", "depth_intrinsics")
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2")


@dataclass(frozen=True)
class Camera:
    """Depth-sensor intrinsics. Factory-like Kinect v2 values by default."""

    width: int = 512
    height: int = 424
    fps: float = 30.0
    fx: float = 365.5
    fy: float = 365.5
    cx: float = 254.9
    cy: float = 205.4
    k1: float = 0.0905
    k2: float = -0.268
    k3: float = 0.0951
    p1: float = 0.0
    p2: float = 0.0
    model: str = "kinect-v2"

    @property
    def matrix(self) -> np.ndarray:
        """3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Camera-space points (N, 3) mm -> distorted pixels (N, 2). Z <= 0 gives NaN."""
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        z = xyz[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = xyz[:, 0] / z
            y = xyz[:, 1] / z
        r2 = x * x + y * y
        radial = 1 + self.k1 * r2 + self.k2 * r2 * r2 + self.k3 * r2 * r2 * r2
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        uv[~(z > 0)] = np.nan
        return uv

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> normalised image coordinates (N, 2), x = X/Z, y = Y/Z."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        out = np.full_like(uv, np.nan)
        ok = np.isfinite(uv).all(axis=1)
        if ok.any():
            # Iterate past OpenCV's default of 5 so the round trip holds to 0.01 px at the
            # strongly distorted Kinect v2 corners.
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
            src = uv[ok].reshape(-1, 1, 2)
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
                pts = cv2.undistortPointsIter(src, self.matrix, self.dist, None, None, crit)
            else:  # OpenCV 5 folded the criteria into undistortPoints
                pts = cv2.undistortPoints(src, self.matrix, self.dist, None, None, None, crit)
            out[ok] = pts.reshape(-1, 2)
        return out

    def backproject(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) and Z depth (N,) mm -> camera-space points (N, 3) mm."""
        xy = self.undistort(uv)
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        return np.stack([xy[:, 0] * z, xy[:, 1] * z, z], axis=1)

    def to_json(self, **extra: Any) -> dict[str, Any]:
        """The camera.json form of ``../shared/spec/session-folder.md``."""
        d = asdict(self)
        doc = {
            "model": d["model"],
            "width": d["width"],
            "height": d["height"],
            "fps": d["fps"],
            "depth_intrinsics": {k: d[k] for k in INTRINSIC_KEYS},
        }
        doc.update(extra)
        return doc

    @classmethod
    def from_json(cls, doc: Mapping[str, Any], source: object = "camera.json") -> Camera:
        """Parse a camera.json document; a missing or bad key raises InputError naming it."""
        if not isinstance(doc, Mapping):
            raise InputError(source, "is not a JSON object")
        for key in REQUIRED_KEYS:
            if key not in doc:
                raise InputError(source, f"missing required key {key!r}")
        intr = doc["depth_intrinsics"]
        if not isinstance(intr, Mapping):
            raise InputError(source, "key 'depth_intrinsics' is not an object")
        for key in INTRINSIC_KEYS:
            if key not in intr:
                raise InputError(source, f"missing required key 'depth_intrinsics.{key}'")
        values: dict[str, Any] = {}
        for key in INTRINSIC_KEYS:
            v = intr[key]
            if not isinstance(v, int | float) or isinstance(v, bool) or not np.isfinite(v):
                raise InputError(source, f"key 'depth_intrinsics.{key}' is not a number: {v!r}")
            values[key] = float(v)
        for key in ("width", "height"):
            v = doc[key]
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                raise InputError(source, f"key {key!r} is not a positive integer: {v!r}")
        fps = doc["fps"]
        if not isinstance(fps, int | float) or isinstance(fps, bool) or fps <= 0:
            raise InputError(source, f"key 'fps' is not a positive number: {fps!r}")
        if values["fx"] <= 0 or values["fy"] <= 0:
            raise InputError(source, "focal lengths 'fx' and 'fy' must be positive")
        return cls(
            width=doc["width"],
            height=doc["height"],
            fps=float(fps),
            model=str(doc["model"]),
            **values,
        )

    @classmethod
    def from_doc(cls, doc: Mapping[str, Any] | None, source: object = "camera") -> Camera:
        """A camera.json document, or a flat mapping of Camera fields; the defaults when
        empty. A bad or unknown key raises InputError naming ``source``."""
        if not doc:
            return cls()
        if "depth_intrinsics" in doc:
            return cls.from_json(doc, source=source)
        unknown = sorted(set(doc) - set(cls.__dataclass_fields__))
        if unknown:
            raise InputError(source, f"unknown camera key {unknown[0]!r}")
        try:
            return cls(**dict(doc))
        except TypeError as exc:
            raise InputError(source, f"bad camera fields: {exc}") from exc

    @classmethod
    def load(cls, path: str | Path) -> Camera:
        """Read a camera.json file."""
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
        except FileNotFoundError as exc:
            raise InputError(path, "file not found") from exc
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(path, f"not valid JSON: {exc}") from exc
        return cls.from_json(doc, source=path)


DEFAULT_MARKER_DIAMETER_MM = 25.0


def doc_number(doc: Mapping[str, Any] | None, key: str, low: float, high: float) -> float | None:
    """A number a camera.json document gives for ``key`` within [low, high], else None.

    The stages read ``marker_diameter_mm`` and ``fps`` this way from the document the
    calibration record carries; a value out of range or of the wrong type is not used.
    """
    v = doc.get(key) if doc else None
    if isinstance(v, int | float) and not isinstance(v, bool) and low <= v <= high:
        return float(v)
    return None


def marker_diameter(param: float, doc: Mapping[str, Any] | None) -> float:
    """Marker diameter, mm: ``param`` when set (> 0), else the camera.json's, else 25 mm."""
    if param > 0:
        return float(param)
    v = doc_number(doc, "marker_diameter_mm", 5.0, 100.0)
    return DEFAULT_MARKER_DIAMETER_MM if v is None else v
