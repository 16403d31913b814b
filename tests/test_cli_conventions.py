"""CLI conventions: --help lists every command, every command's help has an example,
errors are one line with a non-zero exit, tracebacks only with --debug."""

from __future__ import annotations

import argparse
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

import gaitflow.bench
import gaitflow.commands
from gaitflow.cli import build_parser, main


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _modules(pkg) -> set[str]:
    return {m.name for m in pkgutil.iter_modules(pkg.__path__) if not m.name.startswith("_")}


COMMANDS = _subcommands(build_parser())
BENCHES = _subcommands(COMMANDS["bench"])


def _example(text: str) -> str:
    """The text after an ``Example:`` (or ``Examples:``) line, or empty."""
    m = re.search(r"^Examples?:(.*)", text, re.MULTILINE | re.DOTALL)
    return m.group(1) if m else ""


def _help(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as ei:
        main([*argv, "--help"])
    assert ei.value.code == 0
    return capsys.readouterr().out


def test_top_level_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    text = _help([], capsys)
    # Every module under gaitflow.commands registers a command (the module name).
    assert _modules(gaitflow.commands) <= set(COMMANDS)
    for name in COMMANDS:
        assert f"    {name}" in text, name
    for name in ("record", "replay", "tap", "inspect", "bench"):
        assert name in COMMANDS


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_help_has_an_example(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    text = _help([name], capsys)
    assert f"gaitflow {name}" in _example(text), f"gaitflow {name} --help has no example"


@pytest.mark.parametrize("name", sorted(BENCHES))
def test_every_bench_help_has_an_example(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    text = _help(["bench", name], capsys)
    assert f"gaitflow bench {name}" in _example(text), f"bench {name} --help has no example"
    assert "--json" in text


def test_benches_registered() -> None:
    assert _modules(gaitflow.bench) <= set(BENCHES)
    assert "mcap" in BENCHES


def test_error_is_one_line_and_nonzero(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing.mcap"
    assert main(["inspect", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(missing) in err and "Traceback" not in err
    assert main(["record", "--tap", "nosuchstream", "--out", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nosuchstream" in err
    assert main(["replay", str(missing), "--rate", "fast"]) == 2
    assert "--rate" in capsys.readouterr().err


def test_traceback_only_with_debug(tmp_path: Path) -> None:
    missing = str(tmp_path / "missing.mcap")
    env = {**os.environ, "GAITFLOW_QUIET": "1"}
    plain = subprocess.run(
        [sys.executable, "-m", "gaitflow.cli", "inspect", missing],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert plain.returncode == 2
    assert plain.stderr.count("\n") == 1 and "Traceback" not in plain.stderr
    debug = subprocess.run(
        [sys.executable, "-m", "gaitflow.cli", "--debug", "inspect", missing],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert debug.returncode != 0 and "Traceback" in debug.stderr and "InputError" in debug.stderr


def test_no_command_prints_help_and_fails(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "COMMAND" in capsys.readouterr().out


@pytest.mark.parametrize("bench", ["gait", "model", "mocap"])
def test_benches_refuse_an_unknown_variant_before_running(
    bench: str, capsys: pytest.CaptureFixture[str]
) -> None:
    flag = "--variants" if bench == "mocap" else "--variant"
    assert main(["bench", bench, flag, "child+moon"]) == 2
    err = capsys.readouterr().err
    assert "'moon'" in err and err.count("\n") == 1
