"""The ``gaitflow`` command line.

Each command lives in its own module under ``gaitflow.commands`` and exposes
``register(subparsers)``, which adds a sub-parser whose ``func(args) -> int`` runs it.
Benchmarks live under ``gaitflow.bench`` the same way, as ``gaitflow bench <name>``.

Errors: a :class:`GaitflowError` prints one clear line and exits 2; any other exception
prints one line and exits 1. ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

from gaitflow import __version__
from gaitflow.errors import GaitflowError


class _Formatter(argparse.RawDescriptionHelpFormatter):
    pass


def _register_all(sub: argparse._SubParsersAction, package: str) -> None:
    pkg = importlib.import_module(package)
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{package}.{info.name}")
        register = getattr(mod, "register", None)
        if register is not None:
            register(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gaitflow",
        description="Motion capture and gait analysis with one depth camera.",
        epilog="Example: gaitflow demo",
        formatter_class=_Formatter,
    )
    parser.add_argument("--version", action="version", version=f"gaitflow {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _register_all(sub, "gaitflow.commands")
    return parser


def add_bench_parsers(sub: argparse._SubParsersAction) -> None:
    """Used by the ``bench`` command to collect ``gaitflow.bench.*`` benchmarks."""
    _register_all(sub, "gaitflow.bench")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except GaitflowError as exc:
        if args.debug:
            raise
        print(f"gaitflow {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if args.debug:
            raise
        print(f"gaitflow {args.command}: unexpected {type(exc).__name__}: {exc}", file=sys.stderr)
        print("  (run again with --debug for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
