"""Bus options shared by the recording commands (record, replay, tap)."""

from __future__ import annotations

import argparse
import dataclasses
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from gaitflow.bus.config import BusConfig


def add_bus_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="YAML/JSON file with a bus: section")
    p.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        help="router endpoint to connect to (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--site", help="site segment of the keys (default from the config)")


def bus_config(args: argparse.Namespace) -> BusConfig:
    """The bus config named by --config, with --connect and --site applied."""
    cfg = BusConfig.load(args.config) if args.config else BusConfig()
    if args.connect:
        cfg = dataclasses.replace(cfg, connect=tuple(args.connect))
    if args.site:
        cfg = dataclasses.replace(cfg, site=args.site)
    return cfg


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs (handlers restored after)."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)
