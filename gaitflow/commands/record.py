"""``gaitflow record``: record bus streams to an MCAP file until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import sys
import time

from gaitflow.bus import stream_selector
from gaitflow.commands._bus_args import add_bus_args, bus_config, stop_on_signals
from gaitflow.errors import ConfigError
from gaitflow.progress import add_quiet_flag
from gaitflow.recording import COMPRESSIONS, DEFAULT_COMPRESSION, Compression, Recorder
from gaitflow.schemas import STREAMS


def check_streams(streams: list[str]) -> list[str]:
    """The stream names, checked against the schema registry."""
    for s in streams:
        if s not in STREAMS:
            raise ConfigError(f"unknown stream {s!r} (known: {', '.join(sorted(STREAMS))})")
    return list(dict.fromkeys(streams))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="record bus streams to an MCAP file",
        description="Subscribe to streams on the bus and write each key to its own MCAP "
        "channel (msgpack payloads, JSON Schema embedded, log_time = capture time). "
        "Stops on Ctrl-C/SIGTERM (or after --seconds), flushes, closes the file and prints "
        "how many frames it received and wrote.",
        epilog="Example: gaitflow record --tap raw blobs --camera '*' --out walk.mcap",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--tap", nargs="+", required=True, metavar="STREAM", help="streams to record")
    p.add_argument("--camera", default="*", help="camera id, or * for every camera (default)")
    p.add_argument("--out", required=True, metavar="FILE", help="output .mcap file")
    p.add_argument(
        "--compression",
        default=DEFAULT_COMPRESSION,
        metavar="|".join(COMPRESSIONS),
        help=f"chunk compression, zstd may take a level as zstd:1 (default {DEFAULT_COMPRESSION})",
    )
    p.add_argument("--seconds", type=float, help="stop after this many seconds")
    p.add_argument(
        "--max-queue-mb",
        type=float,
        default=512,
        help="bound on payloads waiting for the disk; beyond it frames are dropped and counted",
    )
    add_bus_args(p)
    add_quiet_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gaitflow.bus import Bus

    streams = check_streams(args.tap)
    comp = Compression.parse(args.compression)
    cfg = bus_config(args)
    selectors = [stream_selector(cfg.site, s, args.camera) for s in streams]
    with stop_on_signals() as stop:
        bus = Bus(cfg)
        try:
            rec = Recorder(
                args.out,
                max_queue_bytes=int(args.max_queue_mb * (1 << 20)),
                compression=comp,
                metadata={"streams": " ".join(streams), "camera": args.camera, "site": cfg.site},
            )
            handles = []
            try:
                handles = [bus.subscribe(sel, rec.offer) for sel in selectors]
                print(
                    f"record: recording {', '.join(selectors)} to {args.out} ({comp.label})",
                    file=sys.stderr,
                    flush=True,
                )
                t_end = None if args.seconds is None else time.monotonic() + args.seconds
                last = time.monotonic()
                while not stop.wait(0.1):
                    now = time.monotonic()
                    if t_end is not None and now >= t_end:
                        break
                    if not args.quiet and now - last >= 5.0:
                        last = now
                        print(f"record: {rec.stats.line()}", file=sys.stderr, flush=True)
            finally:
                # No callback may run once the file is closed: undeclare first, then drain.
                for h in handles:
                    h.undeclare()
                stats = rec.close()
        finally:
            bus.close()
    print(f"{args.out}: {stats.line()}", flush=True)
    for key, n in sorted(rec.writer.stats.per_key.items()):
        print(f"  {key}: {n}", flush=True)
    if stats.dropped:
        print(
            f"record: warning: {stats.dropped} frame(s) dropped (queue full); "
            "raise --max-queue-mb or use a cheaper --compression",
            file=sys.stderr,
        )
    return 0
