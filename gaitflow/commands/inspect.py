"""``gaitflow inspect``: channels, schemas, counts, duration and compression of a recording."""

from __future__ import annotations

import argparse
import json
import sys

from gaitflow.benchutil import format_table
from gaitflow.progress import add_quiet_flag, progress
from gaitflow.recording import RecordingInfo, inspect_recording

# Exit status of a readable but truncated recording (errors exit 2).
EXIT_TRUNCATED = 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect",
        help="summarize an MCAP recording",
        description="Print a recording's channels (key, stream, schema, message count, rate), "
        "duration and compression. A truncated file (recorder killed, disk full) is read up "
        f"to its last complete chunk, reported as truncated, and exits {EXIT_TRUNCATED}; a "
        "file that is not MCAP exits 2.",
        epilog="Example: gaitflow inspect walk.mcap",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", help="an .mcap recording")
    p.add_argument("--json", action="store_true", help="print one JSON object instead")
    add_quiet_flag(p)
    p.set_defaults(func=run)


def to_dict(info: RecordingInfo) -> dict:
    return {
        "path": info.path,
        "size_bytes": info.size,
        "library": info.library,
        "compression": sorted(info.compressions),
        "chunks": info.chunks,
        "messages": info.messages,
        "duration_s": info.duration_s,
        "start_ns": info.start_ns,
        "end_ns": info.end_ns,
        "truncated": info.truncated,
        "truncation": info.truncation,
        "channels": [
            {
                "topic": c.topic,
                "stream": c.stream,
                "schema": c.schema_name,
                "schema_encoding": c.schema_encoding,
                "message_encoding": c.message_encoding,
                "count": c.count,
                "first_ns": c.first_ns,
                "last_ns": c.last_ns,
            }
            for c in info.channels.values()
        ],
    }


def format_info(info: RecordingInfo) -> str:
    rows = []
    for c in info.channels.values():
        span = ((c.last_ns or 0) - (c.first_ns or 0)) / 1e9
        rate = (c.count - 1) / span if c.count > 1 and span > 0 else float("nan")
        rows.append([c.topic, c.stream, c.schema_name or "-", c.message_encoding, c.count, rate])
    lines = [
        f"file:        {info.path} ({info.size / 1e6:.1f} MB, written by {info.library or '?'})",
        f"compression: {', '.join(sorted(info.compressions)) or '-'} ({info.chunks} chunks)",
        f"messages:    {info.messages}",
        f"duration:    {info.duration_s:.3f} s (capture time)",
        "",
        format_table("channels", ["key", "stream", "schema", "encoding", "messages", "Hz"], rows),
    ]
    if info.truncated:
        lines += ["", f"TRUNCATED: {info.truncation}"]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    bar = progress(desc="inspect", unit="B", unit_scale=True, quiet=args.quiet)
    done = 0

    def tick(pos: int) -> None:
        nonlocal done
        bar.update(pos - done)
        done = pos

    try:
        import os

        bar.total = os.path.getsize(args.file) if os.path.exists(args.file) else None
        info = inspect_recording(args.file, progress=tick)
    finally:
        bar.close()
    if args.json:
        print(json.dumps(to_dict(info)))
    else:
        print(format_info(info))
    if info.truncated:
        print(f"gaitflow inspect: {args.file}: {info.truncation}", file=sys.stderr)
        return EXIT_TRUNCATED
    return 0
