"""``gaitflow export RECORDING.mcap --out SESSION_DIR``: an MCAP recording as a session folder.

The ``raw`` frames of a recording made by ``gaitflow record`` are written as a session folder
(``shared/spec/session-folder.md``): one recording folder per trial, in the order they were
recorded, with their original frame indices and capture times. The camera.json written is
``--camera-json`` (a camera.json file) when given, else the document the raw frames carry
(grab puts its source's camera.json on every frame), else the Kinect v2 factory-like
defaults (recordings made before the frames carried it).
"""

from __future__ import annotations

import argparse
import itertools
import json
from collections.abc import Callable
from pathlib import Path

from gaitflow.camera import Camera
from gaitflow.errors import InputError


def export_mcap(
    path: str | Path,
    out: str | Path,
    camera_doc: dict | None = None,
    recordings: str = "",
    max_frames: int = 0,
    log: Callable[[str], None] | None = print,
) -> dict[str, int]:
    """Write the raw frames of ``path`` as a session folder at ``out``; frames per trial."""
    from gaitflow.session import SessionWriter, is_recording_name
    from gaitflow.stages.grab import SPEC

    params = {
        "source": "mcap",
        "path": str(path),
        "recordings": recordings,
        "max_frames": max_frames,
    }
    src = SPEC.open(SPEC.params.resolve(params))
    writer = None
    counts: dict[str, int] = {}
    for trial, groups in itertools.groupby(src, key=lambda g: g[0].header.trial):
        if writer is None:
            first = next(groups)
            doc = camera_doc or dict(first[0].camera) or Camera().to_json()
            writer = SessionWriter(out, doc)
            groups = itertools.chain([first], groups)
        if not is_recording_name(trial):
            raise InputError(path, f"trial {trial!r} is not a session recording name")
        if trial in counts:
            raise InputError(path, f"trial {trial!r} appears twice; export one pass at a time")
        frames = ((g[0].header.frame, g[0].header.capture_ns, g[0].ir, g[0].depth) for g in groups)
        counts[trial] = writer.write_recording(trial, frames)
        if log is not None:
            log(f"{trial}: {counts[trial]} frames")
    if src.counters and log is not None:
        log(f"skipped: {src.counters}")
    return counts


def run(args: argparse.Namespace) -> int:
    doc = None
    if args.camera_json:
        p = Path(args.camera_json)
        try:
            doc = json.loads(p.read_text())
        except FileNotFoundError as exc:
            raise InputError(p, "file not found") from exc
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(p, f"not valid JSON: {exc}") from exc
        Camera.from_json(doc, source=p)
    counts = export_mcap(args.recording, args.out, doc, args.recordings, args.max_frames)
    if not counts:
        raise InputError(args.recording, "holds no raw frames")
    print(f"{args.out}: {sum(counts.values())} frames in {len(counts)} recording(s)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write the raw frames of an MCAP recording as a session folder",
        description=__doc__,
        epilog="Example: gaitflow export recordings/sample.mcap --out out/sample-session",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recording", help="an .mcap recording with a raw stream")
    p.add_argument("--out", type=Path, required=True, help="session folder to write")
    p.add_argument(
        "--camera-json",
        help="camera.json to use (default: the frames' own, else Kinect v2 defaults)",
    )
    p.add_argument("--recordings", default="", help="comma-separated trials (default: all)")
    p.add_argument("--max-frames", type=int, default=0, help="stop after N frames (0 = all)")
    p.set_defaults(func=run)
