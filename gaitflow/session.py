"""Session folders: read and write the interchange format of ``shared/spec/session-folder.md``.

A session folder holds what one depth camera recorded during one visit::

    <session>/camera.json
    <session>/calibration/frames.csv, ir/000000.png, depth/000000.png
    <session>/static/...
    <session>/walk-01/...

Array conventions: IR and depth frames are uint16 (row, col) = (height, width) arrays, IR
amplitude 0..65535 (65535 = saturated), depth Z in mm (0 = invalid). Timestamps are int64
nanoseconds of capture time, any epoch, strictly increasing within a recording; a gap in
``index`` is a real gap in time (a frame the sensor dropped).

Bad input policy (issue 3, item 3): the reader never crashes halfway through a trial.

- ``camera.json`` missing, not JSON or lacking a required key: :class:`InputError` naming
  the file and the key, when the reader opens.
- ``frames.csv`` missing, malformed (header, column count, non-integer, index not strictly
  increasing) or with a timestamp that does not increase: :class:`InputError` naming
  ``frames.csv`` and the line, raised by :meth:`SessionReader.frames` *before the first
  frame of that recording is yielded*. A timestamp that goes backwards cannot be blamed on
  one row (the row before it may be the wrong one), so the whole recording is refused
  rather than guessed at.
- A single bad frame (PNG missing, unreadable, not a PNG, wrong size, not 16-bit, not
  single-channel): skipped and counted in :attr:`SessionReader.skipped` by reason, with a
  one-line warning naming the file in :attr:`SessionReader.warnings`.
"""

from __future__ import annotations

import json
import re
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gaitflow.camera import Camera
from gaitflow.errors import FrameError, InputError
from gaitflow.schemas import RawFrame

CAMERA_FILE = "camera.json"
FRAMES_FILE = "frames.csv"
FRAMES_HEADER = ("index", "timestamp_ns")
PROTOCOL = ("calibration", "static")
WALK_RE = re.compile(r"^walk-(\d+)$")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Kinect frames are dominated by sensor noise, which LZ77 matching cannot exploit: Huffman-only
# coding (after PNG's row filters) encodes simulator frames ~2x faster than OpenCV's default
# (zlib level 3) and ~1.3x faster than level 1, with files 2-4% smaller; with Huffman-only
# the zlib level makes no difference (docs/readme/session-io.md, `gaitflow bench session`).
DEFAULT_PNG_COMPRESSION = 1
DEFAULT_PNG_STRATEGY = "huffman"
PNG_STRATEGIES = {
    "default": cv2.IMWRITE_PNG_STRATEGY_DEFAULT,
    "filtered": cv2.IMWRITE_PNG_STRATEGY_FILTERED,
    "huffman": cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
    "rle": cv2.IMWRITE_PNG_STRATEGY_RLE,
}
# Keep the warning list bounded: a recording of nothing but bad frames must not eat memory.
MAX_WARNINGS = 200
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1

Frame = tuple[int, int, np.ndarray, np.ndarray]


def is_recording_name(name: str) -> bool:
    """True for the recording names the spec allows: calibration, static, walk-NN."""
    return name in PROTOCOL or WALK_RE.match(name) is not None


def recording_order(names: Iterable[str]) -> list[str]:
    """Sort recording names in protocol order: calibration, static, walk-01, walk-02, ...

    Walks sort by their number, so walk-10 comes after walk-9.
    """

    def key(name: str) -> tuple[int, int, str]:
        if name in PROTOCOL:
            return (PROTOCOL.index(name), 0, name)
        m = WALK_RE.match(name)
        return (len(PROTOCOL), int(m.group(1)) if m else 1 << 30, name)

    return sorted(names, key=key)


def frame_file(root: Path, name: str, kind: str, index: int) -> Path:
    """Path of one PNG: ``<root>/<name>/<kind>/<index:06d>.png``."""
    return root / name / kind / f"{index:06d}.png"


# --------------------------------------------------------------------------- writing


class SessionWriter:
    """Write a session folder.

    Parameters
    ----------
    root : folder to create (may exist; files in it are overwritten).
    camera_doc : the camera.json document (``Camera.to_json()`` form plus any extra keys
        such as ``marker_diameter_mm``). It is validated before anything is written.
    compression : PNG (zlib) compression level 0..9 passed to ``cv2.imwrite``.
    strategy : zlib strategy, one of :data:`PNG_STRATEGIES` (default Huffman-only).
    workers : PNG encoder threads (OpenCV releases the GIL while encoding).
    """

    def __init__(
        self,
        root: str | Path,
        camera_doc: Mapping[str, Any],
        compression: int = DEFAULT_PNG_COMPRESSION,
        workers: int = 1,
        strategy: str = DEFAULT_PNG_STRATEGY,
    ) -> None:
        self.root = Path(root)
        self.camera = Camera.from_json(camera_doc, source=self.root / CAMERA_FILE)
        self.camera_doc = dict(camera_doc)
        if not 0 <= compression <= 9:
            raise InputError(self.root, f"PNG compression level {compression} is not in 0..9")
        if strategy not in PNG_STRATEGIES:
            raise InputError(
                self.root, f"PNG strategy {strategy!r} is not in {list(PNG_STRATEGIES)}"
            )
        self.compression = int(compression)
        self._png_params = [
            cv2.IMWRITE_PNG_COMPRESSION,
            self.compression,
            cv2.IMWRITE_PNG_STRATEGY,
            PNG_STRATEGIES[strategy],
        ]
        self.workers = max(1, int(workers))
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / CAMERA_FILE).write_text(json.dumps(self.camera_doc, indent=2) + "\n")

    def _check(self, where: Path, kind: str, a: np.ndarray) -> np.ndarray:
        a = np.asarray(a)
        want = (self.camera.height, self.camera.width)
        if a.dtype != np.uint16 or a.shape != want:
            raise InputError(
                where, f"{kind} frame is {a.dtype} {a.shape}, expected uint16 {want} (row, col)"
            )
        return np.ascontiguousarray(a)

    def _write_png(self, path: Path, a: np.ndarray) -> None:
        if not cv2.imwrite(str(path), a, self._png_params):
            raise InputError(path, "could not be written")

    def write_recording(self, name: str, frames: Iterable[Frame]) -> int:
        """Write one recording folder from ``(index, timestamp_ns, ir, depth)`` tuples.

        ``ir`` and ``depth`` are uint16 (height, width). Indices and timestamps must
        increase strictly. ``frames.csv`` is written as frames arrive, so an interrupted
        write leaves a readable (shorter) recording. Returns the number of frames written.
        """
        if not is_recording_name(name):
            raise InputError(
                self.root / name, "is not a recording name (calibration, static or walk-NN)"
            )
        folder = self.root / name
        for kind in ("ir", "depth"):
            (folder / kind).mkdir(parents=True, exist_ok=True)
        csv_path = folder / FRAMES_FILE
        n = 0
        prev: tuple[int, int] | None = None
        pool = ThreadPoolExecutor(self.workers) if self.workers > 1 else None
        pending: deque[Future[None]] = deque()
        try:
            with csv_path.open("w", newline="") as csv:
                csv.write(",".join(FRAMES_HEADER) + "\n")
                for index, ts, ir, depth in frames:
                    index, ts = int(index), int(ts)
                    if index < 0 or not INT64_MIN <= ts <= INT64_MAX:
                        raise InputError(csv_path, f"bad frame index {index} or time {ts}")
                    if prev is not None and (index <= prev[0] or ts <= prev[1]):
                        raise InputError(
                            csv_path,
                            f"frame {index} at {ts} ns does not follow frame {prev[0]} "
                            f"at {prev[1]} ns (index and timestamp_ns must increase)",
                        )
                    prev = (index, ts)
                    jobs = (
                        (frame_file(self.root, name, "ir", index), self._check(folder, "IR", ir)),
                        (
                            frame_file(self.root, name, "depth", index),
                            self._check(folder, "depth", depth),
                        ),
                    )
                    for path, a in jobs:
                        if pool is None:
                            self._write_png(path, a)
                        else:
                            pending.append(pool.submit(self._write_png, path, a))
                    # Bound the queue so a fast producer cannot hold a whole trial in memory.
                    while len(pending) > 4 * self.workers:
                        pending.popleft().result()
                    csv.write(f"{index},{ts}\n")
                    n += 1
                while pending:
                    pending.popleft().result()
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        return n


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class FrameRow:
    """One row of frames.csv: the frame index and its capture time."""

    index: int
    timestamp_ns: int


def parse_frames_csv(text: str, source: object = FRAMES_FILE) -> list[FrameRow]:
    """Parse the text of a frames.csv; raise InputError naming ``source`` and the line.

    The header must start with ``index,timestamp_ns`` (further columns are ignored, as the
    spec ignores unknown keys); every row has the header's column count; indices are
    non-negative and strictly increasing; timestamps are int64 and strictly increasing.
    Blank lines are ignored.
    """
    lines = text.lstrip("\ufeff").splitlines()
    numbered = [(i + 1, ln.strip()) for i, ln in enumerate(lines) if ln.strip()]
    if not numbered:
        raise InputError(source, "is empty (expected header 'index,timestamp_ns')")
    head_no, head = numbered[0]
    cols = [c.strip() for c in head.split(",")]
    if tuple(cols[:2]) != FRAMES_HEADER:
        raise InputError(
            source, f"line {head_no}: header must start with 'index,timestamp_ns', got {head!r}"
        )
    rows: list[FrameRow] = []
    prev_line = 0
    for line_no, line in numbered[1:]:
        parts = [c.strip() for c in line.split(",")]
        if len(parts) != len(cols):
            raise InputError(
                source, f"line {line_no}: {len(parts)} columns, header has {len(cols)}: {line!r}"
            )
        try:
            index, ts = int(parts[0]), int(parts[1])
        except ValueError as exc:
            raise InputError(source, f"line {line_no}: not integers: {line!r}") from exc
        if index < 0:
            raise InputError(source, f"line {line_no}: negative index {index}")
        if not INT64_MIN <= ts <= INT64_MAX:
            raise InputError(source, f"line {line_no}: timestamp_ns {ts} is not an int64")
        if rows and index <= rows[-1].index:
            raise InputError(
                source,
                f"line {line_no}: index {index} does not increase "
                f"(line {prev_line} has {rows[-1].index})",
            )
        if rows and ts <= rows[-1].timestamp_ns:
            raise InputError(
                source,
                f"line {line_no}: timestamp_ns {ts} does not increase "
                f"(line {prev_line} has {rows[-1].timestamp_ns})",
            )
        rows.append(FrameRow(index, ts))
        prev_line = line_no
    return rows


def read_png16(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Read one 16-bit single-channel PNG of ``shape`` (rows, cols) as uint16.

    Raises FrameError (naming the file) when the file is missing, unreadable, not a PNG,
    not single-channel, not 16-bit or of another size.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError as exc:
        raise FrameError(path, "missing") from exc
    except OSError as exc:
        raise FrameError(path, f"unreadable: {exc.strerror or exc}") from exc
    if not data.startswith(PNG_SIGNATURE):
        raise FrameError(path, "unreadable: not a PNG file")
    try:
        a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise FrameError(path, f"unreadable: {str(exc).strip()}") from exc
    if a is None:
        raise FrameError(path, "unreadable: corrupt or truncated PNG")
    if a.ndim != 2:
        raise FrameError(path, f"has {a.shape[2]} channels, expected single-channel")
    if a.dtype != np.uint16:
        bits = a.dtype.itemsize * 8
        raise FrameError(path, f"is {bits}-bit ({a.dtype}), expected 16-bit")
    if a.shape != shape:
        raise FrameError(
            path,
            f"is {a.shape[1]}x{a.shape[0]} px, expected {shape[1]}x{shape[0]} from camera.json",
        )
    return a


def _skip_reason(exc: FrameError) -> str:
    r = exc.reason
    if r.startswith("missing"):
        return "missing"
    if r.startswith("unreadable"):
        return "unreadable"
    if "channels" in r:
        return "not_single_channel"
    if "-bit" in r:
        return "not_16bit"
    return "wrong_size"


class SessionReader:
    """Read a session folder.

    Opening reads and validates ``camera.json`` (InputError naming the file and key).
    Recordings are read lazily by :meth:`frames`.

    Attributes
    ----------
    camera : the depth-sensor intrinsics (``gaitflow.camera.Camera``).
    camera_doc : the camera.json document as read (unknown keys kept).
    frames_read : frames yielded so far, over all recordings.
    skipped : Counter of skipped frames by reason (missing, unreadable, not_16bit,
        not_single_channel, wrong_size); ``skipped.total()`` is the number skipped.
    warnings : one line per skipped frame naming the file (the first ``MAX_WARNINGS``).
    """

    def __init__(self, root: str | Path, workers: int = 1) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError(self.root, "session folder not found")
        path = self.root / CAMERA_FILE
        try:
            doc = json.loads(path.read_text())
        except FileNotFoundError as exc:
            raise InputError(path, "file not found") from exc
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(path, f"not valid JSON: {exc}") from exc
        self.camera = Camera.from_json(doc, source=path)
        self.camera_doc: dict[str, Any] = dict(doc)
        self.workers = max(1, int(workers))
        self.frames_read = 0
        self.skipped: Counter[str] = Counter()
        self.warnings: list[str] = []

    @property
    def shape(self) -> tuple[int, int]:
        """Frame shape (rows, cols) from camera.json."""
        return (self.camera.height, self.camera.width)

    def recordings(self) -> list[str]:
        """Recording folders present, in protocol order (calibration, static, walk-NN...).

        Folders with other names are not recordings and are left out.
        """
        names = [p.name for p in self.root.iterdir() if p.is_dir() and is_recording_name(p.name)]
        return recording_order(names)

    def missing(self, required: Iterable[str] = PROTOCOL) -> list[str]:
        """Required recordings (default: calibration and static) that are absent."""
        present = set(self.recordings())
        return [r for r in required if r not in present]

    def require(self, required: Iterable[str] = PROTOCOL) -> None:
        """Raise InputError naming the session folder if a required recording is absent."""
        miss = self.missing(required)
        if miss:
            what = ", ".join(f"{m}/" for m in miss)
            raise InputError(self.root, f"missing recording folder {what}")

    def rows(self, name: str) -> list[FrameRow]:
        """The validated rows of ``<name>/frames.csv`` (InputError naming it if bad)."""
        folder = self.root / name
        if not folder.is_dir():
            raise InputError(folder, "recording folder not found")
        path = folder / FRAMES_FILE
        try:
            text = path.read_text()
        except FileNotFoundError as exc:
            raise InputError(path, "file not found") from exc
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(path, f"unreadable: {exc}") from exc
        return parse_frames_csv(text, source=path)

    def _load(self, name: str, row: FrameRow) -> Frame:
        ir = read_png16(frame_file(self.root, name, "ir", row.index), self.shape)
        depth = read_png16(frame_file(self.root, name, "depth", row.index), self.shape)
        return row.index, row.timestamp_ns, ir, depth

    def _count(self, exc: FrameError) -> None:
        self.skipped[_skip_reason(exc)] += 1
        if len(self.warnings) < MAX_WARNINGS:
            self.warnings.append(f"skipped frame: {exc}")

    def frames(self, name: str) -> Iterator[Frame]:
        """Frames of one recording as ``(index, timestamp_ns, ir, depth)``, in order.

        frames.csv is parsed and validated *now* (InputError naming it), so a bad file is
        refused before any frame goes out. Bad single frames are skipped and counted.
        Timestamps are the original ones; gaps in ``index`` stay gaps.
        """
        rows = self.rows(name)
        if self.workers > 1:
            return self._frames_threaded(name, rows)
        return self._frames_serial(name, rows)

    def _frames_serial(self, name: str, rows: list[FrameRow]) -> Iterator[Frame]:
        for row in rows:
            try:
                frame = self._load(name, row)
            except FrameError as exc:
                self._count(exc)
                continue
            self.frames_read += 1
            yield frame

    def _frames_threaded(self, name: str, rows: list[FrameRow]) -> Iterator[Frame]:
        # PNG decoding releases the GIL, so a small read-ahead pool overlaps decodes while
        # keeping frame order.
        with ThreadPoolExecutor(self.workers) as pool:
            pending: deque[Future[Frame]] = deque()
            it = iter(rows)
            try:
                for row in it:
                    pending.append(pool.submit(self._load, name, row))
                    if len(pending) >= 2 * self.workers:
                        break
                while pending:
                    fut = pending.popleft()
                    nxt = next(it, None)
                    if nxt is not None:
                        pending.append(pool.submit(self._load, name, nxt))
                    try:
                        frame = fut.result()
                    except FrameError as exc:
                        self._count(exc)
                        continue
                    self.frames_read += 1
                    yield frame
            finally:
                for f in pending:
                    f.cancel()


def iter_raw_frames(
    reader: SessionReader, name: str, camera_id: str = "cam0"
) -> Iterator[RawFrame]:
    """A recording as ``RawFrame`` messages.

    Headers: trial = ``name``, frame = the index from frames.csv, capture_ns = its
    timestamp_ns, ``last=True`` on the final frame actually yielded (a skipped final frame
    moves the flag to the one before it). InputError for a bad frames.csv is raised at the
    call, before the first message.
    """
    frames = reader.frames(name)
    return _raw_frames(frames, name, camera_id, dict(reader.camera_doc))


def _raw_frames(
    frames: Iterator[Frame], name: str, camera_id: str, camera_doc: dict[str, Any]
) -> Iterator[RawFrame]:
    held: Frame | None = None
    for frame in frames:
        if held is not None:
            yield _raw(held, name, camera_id, camera_doc, last=False)
        held = frame
    if held is not None:
        yield _raw(held, name, camera_id, camera_doc, last=True)


def _raw(
    frame: Frame, name: str, camera_id: str, camera_doc: dict[str, Any], last: bool
) -> RawFrame:
    index, ts, ir, depth = frame
    return RawFrame(
        header=RawFrame.make_header(camera_id, name, index, ts, last=last),
        ir=ir,
        depth=depth,
        camera=camera_doc,
    )


def session_stage_params(
    camera_doc: Mapping[str, Any], params: Mapping[str, Mapping[str, Any]] | None = None
) -> dict[str, dict[str, Any]]:
    """Stage parameters a session's ``camera.json`` sets, with ``params`` laid over them.

    The stages are pure cores that read no files, so what the session folder says about its
    camera reaches them as parameters: the depth intrinsics and distortion (``calibrate``'s
    ``camera``; the calibration record carries them on to ``clean`` and ``locate``), the
    marker diameter (``calibrate``, ``locate``, ``model``), the number of floor markers
    (``calibrate``'s C) and the frame rate (``label``'s fps). Without this every stage
    assumed a factory Kinect v2 and 25 mm markers: another unit's intrinsics then scaled
    every length (about 1 % for 4 px of focal length).

    Parameters
    ----------
    camera_doc : the camera.json document (already validated, e.g. by :class:`SessionReader`).
    params : explicit per-stage overrides (``--param stage.name=value``); they win.

    Returns
    -------
    {stage: {name: value}}, a new dict.
    """
    Camera.from_json(camera_doc)  # InputError naming the bad key, before any stage starts
    out: dict[str, dict[str, Any]] = {"calibrate": {"camera": dict(camera_doc)}}
    diameter = camera_doc.get("marker_diameter_mm")
    if isinstance(diameter, int | float) and not isinstance(diameter, bool) and diameter > 0:
        for stage in ("calibrate", "locate", "model"):
            out.setdefault(stage, {})["marker_diameter_mm"] = float(diameter)
    markers = camera_doc.get("calibration_markers")
    if isinstance(markers, int) and not isinstance(markers, bool) and markers > 0:
        out["calibrate"]["C"] = markers
    out.setdefault("label", {})["fps"] = float(camera_doc["fps"])
    for stage, values in (params or {}).items():
        out.setdefault(stage, {}).update(values)
    return out
