"""``gaitflow tap``: a live summary of one stream, for researchers watching the pipeline.

Once a second it prints the message rate, the latency from publish to receive and from
capture to receive (ms, this machine's clock; both ends must share a clock), and the key
fields of the latest message: camera, trial, frame index, array shapes and scalar fields.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from gaitflow.bus import stream_selector
from gaitflow.commands._bus_args import add_bus_args, bus_config, stop_on_signals
from gaitflow.commands.record import check_streams
from gaitflow.errors import SchemaError
from gaitflow.schemas import STREAMS, Message, decode


@dataclass
class TapWindow:
    """Messages seen since the last summary (fed from the bus callback thread)."""

    stream: str
    count: int = 0
    malformed: int = 0
    last_error: str = ""
    pub_lat_ms: list[float] = field(default_factory=list)
    cap_lat_ms: list[float] = field(default_factory=list)
    last: Message | None = None
    last_key: str = ""

    def add(self, key: str, payload: bytes, recv_ns: int) -> None:
        try:
            msg = decode(STREAMS[self.stream], payload)
        except SchemaError as exc:
            self.malformed += 1
            self.last_error = str(exc)
            return
        self.count += 1
        self.pub_lat_ms.append((recv_ns - msg.header.publish_ns) / 1e6)
        self.cap_lat_ms.append((recv_ns - msg.header.capture_ns) / 1e6)
        self.last, self.last_key = msg, key


def _lat(values: list[float]) -> str:
    if not values:
        return "-"
    return (
        f"mean {statistics.fmean(values):.1f}  p50 {statistics.median(values):.1f}  "
        f"max {max(values):.1f}"
    )


def key_fields(msg: Message) -> list[str]:
    """``name=value`` for each field: array shapes (and NaN counts), scalars, list lengths."""
    out = []
    for f in dataclasses.fields(msg):
        if f.name == "header":
            continue
        v = getattr(msg, f.name)
        if isinstance(v, np.ndarray):
            s = f"{f.name}{list(v.shape)}"
            if v.dtype.kind == "f" and v.size:
                s += f" nan={int(np.isnan(v).sum())}"
            elif v.dtype.kind in "ui" and v.size:
                s += f" {int(v.min())}..{int(v.max())}"
            out.append(s)
        elif isinstance(v, list | dict):
            out.append(f"{f.name}=<{len(v)} items>")
        elif isinstance(v, float):
            out.append(f"{f.name}={v:.4g}")
        else:
            out.append(f"{f.name}={v!r}")
    return out


def format_summary(w: TapWindow, seconds: float, total: int) -> str:
    """One summary block for a window of ``seconds``."""
    rate = w.count / seconds if seconds > 0 else float("nan")
    lines = [f"{w.stream}: {rate:.1f} Hz  ({w.count} in {seconds:.1f} s, {total} total)"]
    if w.malformed:
        lines.append(f"  malformed: {w.malformed}  last: {w.last_error}")
    if w.last is not None:
        h = w.last.header
        lines.append(f"  latency publish->receive ms: {_lat(w.pub_lat_ms)}")
        lines.append(f"  latency capture->receive ms: {_lat(w.cap_lat_ms)}")
        lines.append(
            f"  last: {w.last_key}  trial={h.trial} frame={h.frame}" + ("  LAST" if h.last else "")
        )
        lines.append("  " + "  ".join(key_fields(w.last)))
    elif not w.malformed:
        lines.append("  (no messages)")
    return "\n".join(lines)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "tap",
        help="print a live summary of a stream",
        description=__doc__,
        epilog="Example: gaitflow tap blobs --camera cam0 --seconds 10",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("stream", help=f"one of {', '.join(sorted(STREAMS))}")
    p.add_argument("--camera", default="*", help="camera id, or * (default)")
    p.add_argument("--seconds", type=float, help="stop after this many seconds")
    p.add_argument("--every", type=float, default=1.0, help="seconds between summaries")
    add_bus_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gaitflow.bus import Bus

    (stream,) = check_streams([args.stream])
    cfg = bus_config(args)
    sel = stream_selector(cfg.site, stream, args.camera)
    lock = threading.Lock()
    window = TapWindow(stream)
    total = 0

    def on_sample(key: str, payload: bytes) -> None:
        recv = time.time_ns()
        with lock:
            window.add(key, payload, recv)

    with stop_on_signals() as stop:
        bus = Bus(cfg)
        try:
            bus.subscribe(sel, on_sample)
            print(f"tap: listening on {sel}", file=sys.stderr, flush=True)
            t_end = None if args.seconds is None else time.monotonic() + args.seconds
            t_win = time.monotonic()
            while True:
                now = time.monotonic()
                due = t_win + args.every
                if t_end is not None:
                    due = min(due, t_end)
                finished = stop.wait(max(0.0, due - now))
                now = time.monotonic()
                with lock:
                    w = window
                    window = TapWindow(stream)
                total += w.count
                print(format_summary(w, now - t_win, total), flush=True)
                t_win = now
                if finished or (t_end is not None and now >= t_end):
                    break
        finally:
            bus.close()
    return 0
