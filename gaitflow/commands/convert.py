"""``gaitflow convert RESULTS.json... --to c3d,trc``: trial results for researchers' tools.

Each trial results JSON that ``gaitflow analyze`` wrote (``../shared/spec/results.md``)
becomes a C3D file (markers and gait events: Vicon Nexus, Visual3D, Mokka, ezc3d, btk) and
an OpenSim TRC marker file, beside it or in ``--out`` (``gaitflow.exports``). Markers are
in the lab frame (X along the calibrated walkway, Z up in the C3D, Y up in the TRC) where
the results carry the calibration's walkway, else in camera space (``--frame``). A file
that is not a valid results document is named on stderr, counted and skipped; the others
are converted (exit 1 if any was skipped).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

FORMATS = ("c3d", "trc")


def _formats(text: str) -> tuple[str, ...]:
    out = tuple(s.strip().lower() for s in text.split(",") if s.strip())
    bad = [s for s in out if s not in FORMATS]
    if bad or not out:
        raise argparse.ArgumentTypeError(f"unknown format(s) {bad or text!r}: use {FORMATS}")
    return out


def run(args: argparse.Namespace) -> int:
    from gaitflow.errors import GaitflowError
    from gaitflow.exports import c3d_bytes, trc_text, trial_arrays
    from gaitflow.results import read_results

    skipped = 0
    for src in args.results:
        try:
            arr = trial_arrays(read_results(src), src)
        except GaitflowError as exc:
            print(f"error: skipped: {exc}", file=sys.stderr)
            skipped += 1
            continue
        frame = args.frame
        if frame == "auto":
            frame = "lab" if arr.floor is not None else "camera"
        folder = args.out or src.parent
        folder.mkdir(parents=True, exist_ok=True)
        for fmt in args.to:
            dst = folder / f"{src.stem}.{fmt}"
            try:
                if fmt == "c3d":
                    dst.write_bytes(c3d_bytes(arr, frame))
                else:
                    dst.write_text(trc_text(arr, dst.name, frame))
            except GaitflowError as exc:
                print(f"error: skipped: {exc}", file=sys.stderr)
                skipped += 1
                break
            print(f"{dst}: {len(arr.xyz)} frames, {len(arr.events)} events, {frame} frame")
    if skipped:
        print(f"{skipped} file(s) skipped", file=sys.stderr)
    return 1 if skipped else 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "convert",
        help="trial results JSON to C3D and OpenSim TRC (markers, gait events)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example:\n  gaitflow analyze sessions/S01 --out results/S01\n"
        "  gaitflow convert results/S01/walk-01.json --to c3d,trc",
    )
    p.add_argument("results", type=Path, nargs="+", help="trial results JSON file(s)")
    p.add_argument(
        "--to", type=_formats, default=FORMATS, help="formats, comma-separated (default both)"
    )
    p.add_argument("--out", type=Path, help="folder for the files (default: beside each JSON)")
    p.add_argument(
        "--frame",
        choices=("auto", "lab", "camera"),
        default="auto",
        help="lab (the walkway's: X along it, vertical up), camera (the results' camera "
        "space), or auto: lab where the results carry the walkway (default)",
    )
    p.set_defaults(func=run)
