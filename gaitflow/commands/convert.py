"""``gaitflow convert RESULTS.json... --to c3d,trc,mot,csv``: results for researchers' tools.

Each trial results JSON that ``gaitflow analyze`` wrote (``../shared/spec/results.md``)
becomes a C3D file (markers, gait events and knee angles: Vicon Nexus, Visual3D, Mokka,
ezc3d, btk), an OpenSim TRC marker file, an OpenSim MOT of the knee flexion and a CSV of
the gait cycles (spreadsheets, R, pandas), beside it or in ``--out`` (``gaitflow.exports``).
Markers are in the lab frame (X along the calibrated walkway, Z up in the C3D, Y up in the
TRC) where the results carry the calibration's walkway, else in camera space (``--frame``).
A file that is not a valid results document is named on stderr, counted and skipped; the
others are converted (exit 1 if any was skipped).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gaitflow.exports import FORMATS, export_formats


def run(args: argparse.Namespace) -> int:
    from gaitflow.errors import GaitflowError, InputError
    from gaitflow.exports import write_exports
    from gaitflow.results import read_results

    if args.out is not None:
        # one folder for all: two results of one name would overwrite each other's files
        stems = [src.stem for src in args.results]
        twice = sorted({s for s in stems if stems.count(s) > 1})
        if twice:
            raise InputError("--out", f"results named alike would overwrite each other: {twice}")
    skipped = 0
    for src in args.results:
        try:
            doc = read_results(src)
            paths, frame = write_exports(
                doc, args.out or src.parent, src.stem, args.to, args.frame, src
            )
        except GaitflowError as exc:
            print(f"error: skipped: {exc}", file=sys.stderr)
            skipped += 1
            continue
        n, events = len(doc["frames"]), len(doc["events"])
        for p in paths:
            if p.suffix == ".mot":
                print(f"{p}: knee flexion, {len(doc['knee_flexion_deg']['time_s'])} samples")
            elif p.suffix == ".csv":
                print(f"{p}: gait cycles, {len(doc.get('cycles') or [])} rows")
            else:
                print(f"{p}: {n} frames, {events} events, {frame} frame")
    if skipped:
        print(f"{skipped} file(s) skipped", file=sys.stderr)
    return 1 if skipped else 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "convert",
        help="trial results JSON to C3D, OpenSim TRC / MOT and CSV (markers, events, knee, cycles)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example:\n  gaitflow analyze sessions/S01 --out results/S01\n"
        "  gaitflow convert results/S01/walk-01.json --to c3d,csv",
    )
    p.add_argument("results", type=Path, nargs="+", help="trial results JSON file(s)")
    p.add_argument(
        "--to",
        type=export_formats,
        default=FORMATS,
        help="comma-separated: c3d, trc, mot, csv (default all four)",
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
