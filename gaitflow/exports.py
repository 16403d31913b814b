"""Trial results in the formats of researchers' tools: C3D, OpenSim's TRC and MOT, CSV.

A results document (``../shared/spec/results.md``) holds the labelled markers per camera
frame and the gait events. :func:`trial_arrays` turns it into arrays on the camera's frame
grid (a frame the sensor dropped is a row of NaN, so row k is always k frame intervals
after the first); :func:`c3d_bytes`, :func:`trc_text` and :func:`mot_text` write those.

Conventions: axis 0 is time (camera frames), axis 1 follows
:data:`gaitflow.markers.MARKER_NAMES`, axis 2 is (X, Y, Z) in mm. NaN means not seen; the
C3D writes it as an invalid point (residual -1), the TRC as an empty field. The positions
are those the pipeline measured, never gap-filled. Two frames (``frame``):

- ``lab`` (the default where the results carry the calibration's ``walkway``): the
  pipeline's floor frame (``stages/model.FloorFrame``): origin at the walking line's start
  on the floor, X along the walkway (toward the image's right), Z up (the
  floor normal) and Y = Z x X (away from the camera) in the C3D, the ISB / Vicon lab
  convention; X along the walkway, Y up and Z toward the camera in the TRC, OpenSim's.
  Both right-handed; the frame stays put when the subject walks back.
- ``camera``: the results' camera space (X right, Y down, Z forward).

Formats:

- C3D (read by Vicon Nexus, Visual3D, Mokka, ezc3d, btk, kineticstoolkit): the 20 markers
  as 3D points (``POINT:LABELS`` = the marker names, ``POINT:UNITS`` mm, the screen axes
  set so that a viewer shows the walkway across and Z up, or in camera space the image
  the right way up), the heel strikes and toe offs as events
  (``EVENT:CONTEXTS`` Left/Right, ``EVENT:LABELS`` "Foot Strike"/"Foot Off", the Vicon
  convention, ``EVENT:TIMES`` minutes and seconds from the first frame), the knee flexion
  as Plug-in Gait's angle outputs (points ``LKneeAngles``, ``RKneeAngles`` listed in
  ``POINT:ANGLES``: X = flexion in degrees, Y and Z not measured, 0) and the session and
  trial names (``GAITFLOW:SESSION``, ``GAITFLOW:TRIAL``).
- TRC (OpenSim's marker file, tab-separated text): the same markers and frame grid, with
  the frame number and time from the first frame.
- MOT (OpenSim's motion / Storage file, version 1, ``inDegrees=yes``): the knee flexion on
  the results' own time base (100 Hz, gap-filled as the results carry it, not the camera's
  grid), time from the first frame, columns ``knee_flexion_l`` and ``knee_flexion_r``
  (flexion positive, 0 = straight: the results' definition, not an OpenSim model's
  coordinate, whose sign differs between models); ``NaN`` where the results have none.
- CSV (spreadsheets, R, pandas): the gait cycles, one row per heel strike (the results'
  ``cycles``): pass number and direction, side, the strike, toe off and next strike times
  (s from the first frame), step and stride length (mm), stance and swing (s); an empty
  cell where a figure was not measured.
"""

from __future__ import annotations

import csv
import io
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow.errors import InputError
from gaitflow.markers import MARKER_NAMES
from gaitflow.results import floats
from gaitflow.stages.model import FloorFrame

EVENT_LABEL = {"heel_strike": "Foot Strike", "toe_off": "Foot Off"}
EVENT_CONTEXT = {"L": "Left", "R": "Right"}
KNEE_ANGLES = ("LKneeAngles", "RKneeAngles")  # Plug-in Gait's names


@dataclass(frozen=True)
class TrialArrays:
    """One trial's labelled markers and events on the camera's frame grid.

    frame : (F,) camera frame index of each row (consecutive, from the first frame seen).
    time_s : (F,) s from the first row (frame k is k / rate).
    xyz : (F, 20, 3) mm, camera space; NaN where not seen (or the frame was dropped).
    events : ((side, kind, time_s), ...) with time_s from the first row.
    floor : the pipeline's floor frame of the results' walkway (``stages/model.FloorFrame``:
        walkway axis, away from the camera, up; origin the line's start on the floor); None
        without a walkway.
    knee : (F, 2) knee flexion, degrees (L, R), the results' ``knee_flexion_deg`` at each
        row's time (linear between its samples; NaN where no sample lies within
        ``KNEE_REACH_S``).
    knee_time_s : (K,) the results' own knee time base, s from the first row.
    knee_deg : (K, 2) the results' knee flexion (L, R) on it, degrees; NaN where unknown.
    """

    session: str
    trial: str
    rate: float
    frame: np.ndarray
    time_s: np.ndarray
    xyz: np.ndarray
    events: tuple[tuple[str, str, float], ...]
    floor: FloorFrame | None = None
    knee: np.ndarray | None = None
    knee_time_s: np.ndarray | None = None
    knee_deg: np.ndarray | None = None

    def positions(self, frame: str, y_up: bool) -> np.ndarray:
        """(F, 20, 3) mm in ``frame`` ("lab" or "camera"); ``y_up``: OpenSim's lab axes
        (X walkway, Y up, Z toward the camera) instead of Z up."""
        if frame == "camera":
            return self.xyz
        if frame != "lab":
            raise InputError(frame, "unknown frame: use lab or camera")
        if self.floor is None:
            raise InputError(
                self.trial, "the results carry no walkway (calibration): use frame camera"
            )
        q = self.floor.to_floor(self.xyz)  # (walkway, away from the camera, up)
        return np.stack([q[..., 0], q[..., 2], -q[..., 1]], axis=-1) if y_up else q


def trial_arrays(doc: Mapping[str, Any], source: object = "results") -> TrialArrays:
    """The markers and events of a results document (validated by the caller).

    Raises :class:`InputError` naming ``source`` if the trial has no frame or its frame
    indices are not increasing.
    """
    frames = doc["frames"]
    rate = float(doc["camera_fps"])
    if not frames:
        raise InputError(source, "the trial has no frame to export")
    index = np.array([int(f["index"]) for f in frames])
    if np.any(np.diff(index) <= 0):
        raise InputError(source, "frame indices are not increasing")
    first = int(index[0])
    n = int(index[-1]) - first + 1
    xyz = np.full((n, len(MARKER_NAMES), 3), np.nan)
    for f, k in zip(frames, index - first, strict=True):
        for j, name in enumerate(MARKER_NAMES):
            p = f["markers"].get(name)
            if p is not None:
                xyz[k, j] = p
    walk = doc.get("walkway")
    floor = (
        None
        if walk is None
        else FloorFrame.from_walkway(walk["floor_plane"], walk["start"], walk["end"])
    )
    t0 = float(frames[0]["time_s"])
    events = tuple(
        (str(e["side"]), str(e["kind"]), float(e["time_s"]) - t0)
        for e in doc.get("events", [])
        if e.get("kind") in EVENT_LABEL and e.get("side") in EVENT_CONTEXT
    )
    time_s = np.arange(n) / rate
    knee_t, knee_deg = _knee_samples(doc.get("knee_flexion_deg") or {})
    return TrialArrays(
        session=str(doc.get("session", "")),
        trial=str(doc.get("trial", "")),
        rate=rate,
        frame=np.arange(first, first + n),
        time_s=time_s,
        xyz=xyz,
        events=events,
        floor=floor,
        knee=_knee_on_grid(knee_t - t0, knee_deg, time_s),
        knee_time_s=knee_t - t0,
        knee_deg=knee_deg,
    )


KNEE_REACH_S = 0.02  # a knee sample farther than this from a row's time does not reach it


def _knee_samples(knee: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(K,) time (s, the results' time) with a finite time and (K, 2) flexion (L, R).

    A side whose list does not match the time base is unknown throughout (NaN).
    """
    tk = floats(knee.get("time_s", []))
    deg = np.full((len(tk), 2), np.nan)
    for j, side in enumerate("LR"):
        v = floats(knee.get(side, []))
        if len(v) == len(tk):
            deg[:, j] = v
    keep = np.isfinite(tk)
    return tk[keep], deg[keep]


def _knee_on_grid(tk: np.ndarray, deg: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(F, 2) the knee flexion samples (``tk``, ``deg`` (K, 2)) at times ``t``."""
    out = np.full((len(t), 2), np.nan)
    for j in range(2):
        ok = np.isfinite(deg[:, j])
        if ok.sum() < 2:
            continue
        ts, vs = tk[ok], deg[ok, j]
        k = np.clip(np.searchsorted(ts, t), 1, len(ts) - 1)
        near = np.minimum(np.abs(t - ts[k - 1]), np.abs(ts[k] - t))
        out[:, j] = np.where(near <= KNEE_REACH_S, np.interp(t, ts, vs), np.nan)
    return out


def c3d_bytes(arr: TrialArrays, frame: str = "lab") -> bytes:
    """The trial as a C3D file (floating-point points, no analog channels)."""
    import c3d

    xyz = arr.positions(frame, y_up=False)
    w = c3d.Writer(point_rate=arr.rate, point_units="mm  ")
    # the knee flexion as Vicon's model outputs are stored: an "angle" point per side
    # (X = flexion, deg; Y and Z, abduction and rotation, are not measured: 0)
    knee = arr.knee if arr.knee is not None else np.full((len(xyz), 2), np.nan)
    w.set_point_labels([*MARKER_NAMES, *KNEE_ANGLES])
    text, width = c3d.Writer.pack_labels(list(KNEE_ANGLES))
    w.point_group.add_str("ANGLES", "Angle outputs", text, width, len(KNEE_ANGLES))
    w.point_group.add_str("ANGLE_UNITS", "Angle unit", "deg", 3)
    # what a viewer shows to the right and up: the walkway and the vertical, or the image
    # axes (Y points down it)
    w.set_screen_axis(*(("+X", "+Z") if frame == "lab" else ("+X", "-Y")))
    vals = np.concatenate([xyz, np.zeros((len(xyz), 2, 3))], axis=1)
    vals[:, len(MARKER_NAMES) :, 0] = knee
    pts = np.zeros((len(xyz), vals.shape[1], 5), np.float32)
    seen = np.isfinite(vals).all(axis=2)
    pts[..., :3] = np.where(seen[..., None], vals, 0.0)
    pts[..., 3] = np.where(seen, 0.0, -1.0)  # residual -1: an invalid point
    empty = np.zeros((0, 0), np.float32)
    w.add_frames([(p, empty) for p in pts])
    if arr.events:
        g = w.get_create("EVENT")
        g.add("USED", "Number of events", 2, "<H", len(arr.events))
        contexts = [EVENT_CONTEXT[s] for s, _, _ in arr.events]
        labels = [EVENT_LABEL[k] for _, k, _ in arr.events]
        for key, what, values in (("CONTEXTS", "Event contexts", contexts),
                                  ("LABELS", "Event labels", labels)):  # fmt: skip
            text, width = c3d.Writer.pack_labels(values)
            g.add_str(key, what, text, width, len(values))
        t = np.array([e[2] for e in arr.events])
        minutes = np.floor(t / 60.0)
        times = np.stack([minutes, t - 60.0 * minutes], axis=1).astype("<f4")  # (N, 2)
        # C3D dimensions are column-major: (2, N) holds each event's minutes and seconds
        # together, which is the byte order of the (N, 2) array
        g.add_param(
            "TIMES",
            desc="Event times (minutes, seconds)",
            bytes_per_element=4,
            bytes=times.tobytes(),
            dimensions=[2, len(times)],
        )
    # where the trial came from, in a group of our own (C3D's SUBJECTS holds a subject's
    # name, which the results do not carry)
    own = w.get_create("GAITFLOW")
    for key, what, value in (("SESSION", "Session folder", arr.session),
                             ("TRIAL", "Trial (recording)", arr.trial)):  # fmt: skip
        if value:
            text, width = c3d.Writer.pack_labels([value])
            own.add_str(key, what, text, width, 1)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        # the library's note that the file has no analog channels: by design here
        warnings.filterwarnings("ignore", message="No analog data found", category=UserWarning)
        w.write(buf)
    return buf.getvalue()


def trc_text(arr: TrialArrays, file_name: str, frame: str = "lab") -> str:
    """The trial as an OpenSim TRC marker file (tab-separated; empty = not seen)."""
    xyz = arr.positions(frame, y_up=True)
    n, m = len(xyz), len(MARKER_NAMES)
    rate = f"{arr.rate:.2f}"
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{file_name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{n}\t{m}\tmm\t{rate}\t1\t{n}",
        "Frame#\tTime\t" + "\t\t\t".join(MARKER_NAMES),
        "\t\t" + "\t".join(f"{a}{j + 1}" for j in range(m) for a in "XYZ"),
    ]
    cells = np.where(np.isfinite(xyz), np.char.mod("%.3f", np.nan_to_num(xyz)), "").reshape(
        n, 3 * m
    )
    rows = [
        f"{k + 1}\t{t:.5f}\t" + "\t".join(row)
        for k, (t, row) in enumerate(zip(arr.time_s, cells, strict=True))
    ]
    return "\n".join([*head, "", *rows]) + "\n"


MOT_COLUMNS = ("time", "knee_flexion_l", "knee_flexion_r")


def mot_text(arr: TrialArrays, name: str) -> str:
    """The knee flexion as an OpenSim motion file (Storage version 1, degrees, tab-separated).

    One row per sample of the results' knee time base (time from the first frame); ``NaN``
    where a side's flexion is unknown.
    """
    t = arr.knee_time_s if arr.knee_time_s is not None else np.zeros(0)
    deg = arr.knee_deg if arr.knee_deg is not None else np.zeros((0, 2))
    head = [name, "version=1", f"nRows={len(t)}", f"nColumns={len(MOT_COLUMNS)}",
            "inDegrees=yes", "endheader", "\t".join(MOT_COLUMNS)]  # fmt: skip
    rows = [
        f"{ti:.5f}\t" + "\t".join("NaN" if not np.isfinite(v) else f"{v:.4f}" for v in d)
        for ti, d in zip(t, deg, strict=True)
    ]
    return "\n".join([*head, *rows]) + "\n"


CYCLE_COLUMNS = ("heel_strike_s", "toe_off_s", "next_heel_strike_s", "step_length_mm",
                 "stride_length_mm", "stance_s", "swing_s")  # fmt: skip
CYCLE_TIMES = ("heel_strike_s", "toe_off_s", "next_heel_strike_s")


def cycles_csv(doc: Mapping[str, Any]) -> str:
    """The results' gait cycles as CSV, one row per heel strike (header only without any).

    Columns: ``pass`` (1-based, the pass whose time span holds the strike; empty if none),
    ``direction`` (+1 toward the walkway's end, -1 back), ``side``, then
    :data:`CYCLE_COLUMNS`; times in s from the first frame.
    """
    frames = doc.get("frames") or []
    t0 = float(frames[0]["time_s"]) if frames else 0.0
    passes = doc.get("passes") or []
    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    out.writerow(["pass", "direction", "side", *CYCLE_COLUMNS])
    for c in doc.get("cycles") or []:
        hs = float(c["heel_strike_s"])
        k = next((i for i, p in enumerate(passes) if p["start_s"] <= hs <= p["end_s"]), None)
        cells = []
        for key in CYCLE_COLUMNS:
            v = c.get(key)
            cells.append("" if v is None else str(round(v - t0 if key in CYCLE_TIMES else v, 4)))
        where = ["", ""] if k is None else [k + 1, passes[k]["direction"]]
        out.writerow([*where, c["side"], *cells])
    return buf.getvalue()


FORMATS = ("c3d", "trc", "mot", "csv")


def export_formats(text: str) -> tuple[str, ...]:
    """The formats of a comma-separated list (a command-line option's type)."""
    import argparse

    out = tuple(s.strip().lower() for s in text.split(",") if s.strip())
    bad = [s for s in out if s not in FORMATS]
    if bad or not out:
        raise argparse.ArgumentTypeError(f"unknown format(s) {bad or text!r}: use {FORMATS}")
    return out


def write_exports(
    doc: Mapping[str, Any],
    folder: Path,
    stem: str,
    formats: tuple[str, ...] = FORMATS,
    frame: str = "auto",
    source: object = "results",
) -> tuple[list[Path], str]:
    """Write ``folder/<stem>.c3d``, ``.trc``, ``.mot`` and/or ``.csv`` of a validated results
    document.

    ``frame`` "auto" is the lab frame where the document carries the walkway, else the
    camera's. Returns (paths written, frame used); :class:`InputError` naming ``source``
    if the trial cannot be exported (no frame, no walkway for ``frame="lab"``).
    """
    arr = trial_arrays(doc, source)
    if frame == "auto":
        frame = "lab" if arr.floor is not None else "camera"
    data = {}
    for fmt in formats:  # everything is made before anything is written
        if fmt == "c3d":
            data[fmt] = c3d_bytes(arr, frame)
        elif fmt == "trc":
            data[fmt] = trc_text(arr, f"{stem}.trc", frame).encode()
        elif fmt == "mot":
            data[fmt] = mot_text(arr, f"{stem}.mot").encode()
        elif fmt == "csv":
            data[fmt] = cycles_csv(doc).encode()
        else:
            raise InputError(fmt, f"unknown export format: use {FORMATS}")
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for fmt, blob in data.items():
        paths.append(folder / f"{stem}.{fmt}")
        paths[-1].write_bytes(blob)
    return paths, frame
