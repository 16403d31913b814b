"""``gaitflow bench session`` runs and reports its figures as one JSON object."""

from __future__ import annotations

import json

from gaitflow.cli import main


def test_bench_session_json(capsys):
    assert main(["bench", "session", "--synthetic", "--frames", "2", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frames"] == 2 and (res["width"], res["height"]) == (512, 424)
    assert res["read_fps"] > 0 and res["write_fps"] > 0 and res["decode_fps"] > 0
    kinds = {(w["level"], w["strategy"], w["workers"]) for w in res["write"]}
    assert (1, "huffman", 1) in kinds and (3, "default", 2) in kinds
    # Random frames do not compress: level 0 and level 1 files are about the same size.
    sizes = {(w["level"], w["strategy"]): w["kib_per_frame"] for w in res["write"]}
    assert sizes[(1, "huffman")] > 0.8 * sizes[(0, "huffman")]


def test_bench_session_table(capsys):
    assert main(["bench", "session", "--synthetic", "--frames", "1"]) == 0
    out = capsys.readouterr().out
    assert "session folder write" in out and "session folder read" in out
