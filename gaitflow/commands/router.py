"""``gaitflow router``: a Zenoh router as a Python process."""

from __future__ import annotations

import argparse

from gaitflow.bus.config import DEFAULT_ROUTER, BusConfig
from gaitflow.bus.router import serve


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "router",
        help="run a Zenoh router (stages connect to it)",
        description="Run a Zenoh router until SIGINT or SIGTERM. Multicast scouting is off; "
        "it listens only on the endpoints given (loopback by default). TLS settings come "
        "from the bus: section of --config.",
        epilog="Example: gaitflow router --listen tcp/127.0.0.1:7447",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--listen",
        metavar="ENDPOINT",
        action="append",
        help=f"endpoint to listen on (repeatable; default {DEFAULT_ROUTER})",
    )
    p.add_argument("--config", metavar="FILE", help="YAML/JSON file with a bus: section")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    cfg = BusConfig.load(args.config) if args.config else BusConfig()
    listen = tuple(args.listen) if args.listen else (cfg.listen or (DEFAULT_ROUTER,))
    return serve(cfg, tuple(listen))
