"""``gaitflow replay``: republish a recording to its keys, with its timing or flat out."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gaitflow.commands._bus_args import add_bus_args, bus_config, stop_on_signals
from gaitflow.commands.record import check_streams
from gaitflow.errors import ConfigError
from gaitflow.progress import add_quiet_flag, progress
from gaitflow.recording import McapReader, RecordedMessage, count_hint


def parse_rate(text: str) -> float:
    """``max`` (as fast as the bus accepts) -> inf, else a positive speed factor."""
    if str(text).lower() == "max":
        return float("inf")
    try:
        r = float(text)
    except ValueError as exc:
        raise ConfigError(f"--rate {text!r} is not a number or 'max'") from exc
    if not r > 0:
        raise ConfigError(f"--rate {text!r} must be > 0")
    return r


@dataclass
class ReplayStats:
    published: int = 0
    passes: int = 0
    late_ms_max: float = 0.0
    truncated: str = ""


def replay(
    path: str | Path,
    publish: Callable[[str, bytes], None],
    rate: float = 1.0,
    streams: Iterable[str] | None = None,
    loop: bool = False,
    stop: threading.Event | None = None,
    on_message: Callable[[RecordedMessage], None] | None = None,
    sleep: Callable[[float], Any] = time.sleep,
    clock: Callable[[], float] = time.monotonic,
) -> ReplayStats:
    """Publish every recorded payload, byte for byte, to its recorded key.

    Messages go out in file order (the order the recorder received them). With a finite
    ``rate`` each message waits until ``(log_time - first log_time) / rate`` seconds after
    the start of the pass; a message whose log time lies before an earlier one's (a later
    stage's output of an older frame) goes out at once. ``rate=inf`` publishes without
    waiting; ``publish`` must then block rather than drop (congestion control BLOCK).
    """
    stats = ReplayStats()
    stop = stop or threading.Event()
    while not stop.is_set():
        t0: float | None = None
        log0 = 0
        with McapReader(path) as reader:
            for m in reader.messages(streams):
                if stop.is_set():
                    break
                if t0 is None:
                    t0, log0 = clock(), m.log_time_ns
                if rate != float("inf"):
                    due = t0 + (m.log_time_ns - log0) / 1e9 / rate
                    wait = due - clock()
                    if wait > 0:
                        # Sleep in slices so SIGINT/SIGTERM stop a long gap promptly.
                        while wait > 0 and not stop.is_set():
                            sleep(min(wait, 0.1))
                            wait = due - clock()
                    else:
                        stats.late_ms_max = max(stats.late_ms_max, -wait * 1e3)
                publish(m.key, m.payload)
                stats.published += 1
                if on_message is not None:
                    on_message(m)
            stats.truncated = reader.info.truncation if reader.truncated else ""
        stats.passes += 1
        if not loop or stats.published == 0:
            break
    return stats


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="republish an MCAP recording on the bus",
        description="Publish every recorded payload byte for byte to the key it was "
        "recorded from. --rate 1 keeps the original timing (from log_time = capture time), "
        "--rate 2 plays twice as fast, --rate max publishes as fast as the subscribers "
        "accept (congestion control BLOCK: nothing is dropped).",
        epilog="Example: gaitflow replay walk.mcap --rate max --streams raw",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", help="an .mcap recording")
    p.add_argument("--rate", default="1", help="speed factor, or max (default 1)")
    p.add_argument("--loop", action="store_true", help="start again at the end, until stopped")
    p.add_argument("--streams", nargs="+", metavar="STREAM", help="only these streams")
    p.add_argument(
        "--start-delay",
        type=float,
        default=0.5,
        metavar="S",
        help="wait after opening the session so subscriptions reach us (default 0.5 s)",
    )
    add_bus_args(p)
    add_quiet_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gaitflow.bus import Bus

    rate = parse_rate(args.rate)
    streams = check_streams(args.streams) if args.streams else None
    McapReader(args.file).close()  # fail early, with one line, on a missing or bad file
    cfg = bus_config(args)
    with stop_on_signals() as stop:
        bus = Bus(cfg)
        try:
            pubs: dict[str, Any] = {}

            def publish(key: str, payload: bytes) -> None:
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = bus.publisher(key, block=True)
                pub.put(payload)

            stop.wait(args.start_delay)
            per_pass = count_hint(args.file, streams)
            total = None if per_pass is None or args.loop else per_pass
            bar = progress(desc="replay", unit="msg", total=total, quiet=args.quiet)
            try:
                stats = replay(
                    args.file,
                    publish,
                    rate=rate,
                    streams=streams,
                    loop=args.loop,
                    stop=stop,
                    on_message=lambda m: bar.update(1),
                )
            finally:
                bar.close()
        finally:
            bus.close()
    print(
        f"{args.file}: published {stats.published} message(s) in {stats.passes} pass(es)",
        flush=True,
    )
    if stats.truncated:
        print(f"gaitflow replay: warning: {args.file}: {stats.truncated}", file=sys.stderr)
    return 0
