"""``gaitflow bench <name>``: benchmarks that print a table, or JSON with --json."""

from __future__ import annotations

import argparse

from gaitflow.cli import add_bench_parsers


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="run a benchmark and print its figures",
        description="Run a benchmark. Every benchmark prints a table, or one JSON object "
        "with --json.",
        epilog="Example: gaitflow bench bus --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    bsub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    add_bench_parsers(bsub)
