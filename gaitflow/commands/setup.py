"""``gaitflow setup``: the operator's console while the camera is set up and calibrated.

Alg. 4 publishes a live status on every calibration frame (``calstatus``): how many floor
markers are found, and what to do next (Move Left/Right, Tilt Down/Up, Pan Left/Right,
Replace Markers, Done), and at the end a calibration record. This command prints them in
plain words, one line whenever the advice changes, and the outcome once the record arrives:

- live (default): it listens on the bus for a camera's ``calstatus`` and ``calibration``
  while ``gaitflow run`` (or the edge role) runs the camera; Ctrl-C or ``--seconds`` stops;
- ``--session DIR``: it runs the calibration recording of a session folder through the
  calibrate stage here and prints what the operator would have seen (a check of a recorded
  calibration before the session is analysed).

Exit status: 0 when the calibration record says Done, 1 when it says anything else, 2 on
bad input; live without a record yet, 0.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gaitflow.commands._bus_args import add_bus_args, bus_config, stop_on_signals
from gaitflow.errors import InputError, SchemaError

# What the operator does once the camera is set (the live Done and the record's outcome).
NEXT_STEP = "record the subject's static pose"
# What each status asks of the operator, in plain words (the record's message adds numbers).
ADVICE = {
    "Uninitialized": "place the next floor marker on the walkway and step out of view",
    "Replace Markers": "the floor markers do not form a usable quad; place them again",
    "Move Left": "move the camera left along the walkway",
    "Move Right": "move the camera right along the walkway",
    "Tilt Down": "tilt the camera down",
    "Tilt Up": "tilt the camera up",
    "Pan Left": "turn the camera left",
    "Pan Right": "turn the camera right",
    "Done": f"the camera is set: {NEXT_STEP} next",
}


class StatusConsole:
    """Turns calibration statuses into operator lines, one per change of advice."""

    def __init__(self, markers_expected: int = 4) -> None:
        self.markers_expected = markers_expected
        self.last: tuple[str, str, int] | None = None
        self.final = ""  # the calibration record's status, once it arrived

    def feed(self, stream: str, msg: Any) -> list[str]:
        """The lines for one ``calstatus`` or ``calibration`` message."""
        if stream == "calibration":
            self.final = msg.status
            return self.outcome_lines(msg)
        line = self.status_line(msg)
        return [] if line is None else [line]

    def status_line(self, msg: Any) -> str | None:
        """The line for a ``CalibrationStatus``, or None when the advice did not change
        (the numbers in its message move by a few mm from frame to frame)."""
        key = (msg.header.camera, msg.status, int(msg.markers_found))
        if key == self.last:
            return None
        self.last = key
        found = f"{msg.markers_found}/{self.markers_expected} floor markers"
        # the stage's message carries the numbers and the advice; the table covers the rest
        text = msg.message if msg.message and msg.status != "Uninitialized" else ""
        return f"[{msg.header.camera}] {found}  {msg.status}: {text or ADVICE.get(msg.status, '')}"

    @staticmethod
    def outcome_lines(rec: Any) -> list[str]:
        """The lines for the final ``CalibrationRecord``."""
        head = f"[{rec.header.camera}] calibration {rec.status}"
        if rec.status != "Done":
            return [f"{head}: {rec.message or ADVICE.get(rec.status, '')}"]

        def num(v: float, fmt: str) -> str:
            return format(v, fmt) if math.isfinite(v) else "-"

        return [
            f"{head}: usable for analysis; {rec.markers_found} floor markers, walking line "
            f"{num(rec.length_mm / 1000.0, '.2f')} m",
            f"  camera pose kept in the record: tilt {num(rec.tilt_deg, '+.1f')} deg, pan "
            f"{num(rec.pan_deg, '+.1f')} deg, walkway centre {num(rec.offset_mm, '+.0f')} mm "
            f"off the optical axis; floor plane fit {num(rec.plane_rms_mm, '.1f')} mm rms",
            f"  next: {NEXT_STEP}",
        ]


def replay_session(root: Path, out: Callable[[str], None] = print) -> str:
    """Run a session folder's calibration recording through calibrate; print as live.

    Returns the record's status ("" when the recording gave none).
    """
    from gaitflow.session import SessionReader, iter_raw_frames, session_stage_params
    from gaitflow.stages.graph import load
    from gaitflow.stages.inline import InlinePipeline

    reader = SessionReader(root)
    if "calibration" not in reader.recordings():
        raise InputError(root, "no calibration/ recording in this session folder")
    expected = int(reader.camera_doc.get("calibration_markers", 4))
    console = StatusConsole(expected)

    def sink(stream: str, msg: Any) -> None:
        if stream in ("calstatus", "calibration"):
            for line in console.feed(stream, msg):
                out(line)

    params = session_stage_params(reader.camera_doc, None)
    pipe = InlinePipeline(load(), stages=("calibrate",), params=params, sink=sink)
    for raw in iter_raw_frames(reader, "calibration"):
        pipe.push(raw)
    pipe.finish()
    return console.final


def listen(
    bus: Any,
    camera: str,
    markers: int = 4,
    seconds: float | None = None,
    stop: threading.Event | None = None,
    out: Callable[[str], None] = print,
) -> int:
    """Print a camera's live calibration statuses from ``bus`` until its record arrives,
    ``seconds`` pass or ``stop`` is set. Returns the exit status (see the module doc).

    A malformed message is reported on stderr, counted and skipped; listening goes on.
    """
    from gaitflow.bus import stream_selector
    from gaitflow.schemas import STREAMS, decode

    console = StatusConsole(markers)
    lock = threading.Lock()
    malformed = 0
    stop = stop or threading.Event()

    def handler(stream: str) -> Callable[[str, bytes], None]:
        def on_sample(key: str, payload: bytes) -> None:
            nonlocal malformed
            try:
                msg = decode(STREAMS[stream], payload)
            except SchemaError as exc:
                with lock:
                    malformed += 1
                print(f"setup: malformed {stream} message on {key}: {exc}", file=sys.stderr)
                return
            with lock:
                for line in console.feed(stream, msg):
                    out(line)

        return on_sample

    for stream in ("calstatus", "calibration"):
        bus.subscribe(stream_selector(bus.site, stream, camera), handler(stream))
    t_end = None if seconds is None else time.monotonic() + seconds
    while not stop.is_set():
        if t_end is not None and time.monotonic() >= t_end:
            break
        with lock:
            if console.final:
                break
        stop.wait(0.05)
    if malformed:
        print(f"setup: {malformed} malformed messages skipped", file=sys.stderr)
    return 0 if console.final in ("", "Done") else 1


def run(args: argparse.Namespace) -> int:
    if args.session is not None:
        status = replay_session(Path(args.session))
        if not status:
            raise InputError(args.session, "the calibration recording gave no calibration record")
        return 0 if status == "Done" else 1
    from gaitflow.bus import Bus

    with stop_on_signals() as stop:
        bus = Bus(bus_config(args))
        try:
            print(f"setup: waiting for camera {args.camera}'s calibration", file=sys.stderr)
            return listen(
                bus, args.camera, args.markers, args.seconds, stop, lambda s: print(s, flush=True)
            )
        finally:
            bus.close()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "setup",
        help="the operator's console for setting up and calibrating the camera",
        description=__doc__,
        epilog="Examples:\n  gaitflow setup --camera cam0\n  gaitflow setup --session out/S01",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--session", metavar="DIR", help="check a session folder's calibration")
    p.add_argument("--camera", default="cam0", help="camera id (live; default cam0)")
    p.add_argument("--markers", type=int, default=4, help="floor markers expected (live)")
    p.add_argument("--seconds", type=float, help="live: stop after this many seconds")
    add_bus_args(p)
    p.set_defaults(func=run)
