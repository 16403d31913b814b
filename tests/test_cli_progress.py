"""The progress helper: drawn on a terminal, silent when piped, with --quiet or GAITFLOW_QUIET."""

from __future__ import annotations

import io

import pytest

from gaitflow.progress import enabled, progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_draws_on_a_tty_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("GAITFLOW_QUIET", raising=False)
    tty, pipe = _Tty(), io.StringIO()
    assert list(progress(range(5), desc="work", stream=tty)) == [0, 1, 2, 3, 4]
    assert "work" in tty.getvalue()
    assert list(progress(range(5), desc="work", stream=pipe)) == [0, 1, 2, 3, 4]
    assert pipe.getvalue() == ""
    quiet = _Tty()
    assert list(progress(range(3), stream=quiet, quiet=True)) == [0, 1, 2]
    assert quiet.getvalue() == ""
    assert enabled(stream=_Tty())
    monkeypatch.setenv("GAITFLOW_QUIET", "1")
    assert not enabled(stream=_Tty())


def test_manual_updates(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("GAITFLOW_QUIET", raising=False)
    tty = _Tty()
    with progress(total=10, desc="bytes", stream=tty) as bar:
        bar.update(4)
        bar.update(6)
        assert bar.n == 10
    assert "bytes" in tty.getvalue()
