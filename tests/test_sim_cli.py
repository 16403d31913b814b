"""``gaitflow simulate`` writes a session folder that reads back byte-identical."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gaitflow.cli import main
from gaitflow.session import SessionReader
from gaitflow.sim.config import SimConfig
from gaitflow.sim.session import simulate_session


@pytest.mark.slow
def test_simulate_writes_session_folder_read_back_identical(tmp_path) -> None:
    out = tmp_path / "S01"
    prev = tmp_path / "prev.png"
    rc = main(
        [
            "simulate",
            "c3dorg_s00_vicon_CGM24",
            "--out",
            str(out),
            "--quick",
            "--seed",
            "3",
            "--preview",
            "--preview-path",
            str(prev),
            "--max-frames",
            "12",
        ]
    )
    assert rc == 0
    assert prev.stat().st_size > 10_000
    cam = json.loads((out / "camera.json").read_text())
    assert cam["marker_diameter_mm"] == 25 and cam["width"] == 512
    reader = SessionReader(out)
    assert reader.recordings() == ["calibration", "static", "walk-01"]
    # Ground truth lives beside the recordings, never inside them.
    assert not any((out / "walk-01").glob("*.npz"))
    truth = np.load(out / "truth" / "walk-01.npz")
    summary = json.loads((out / "truth" / "walk-01.json").read_text())
    assert summary["events"] and summary["spatiotemporal"]["strides"]
    assert (out / "walk-01" / "ir" / "000000.png").exists()
    ses = simulate_session("c3dorg_s00_vicon_CGM24", seed=3, config=SimConfig.quick())
    rec = ses.recordings["walk-01"]
    frames = list(reader.frames("walk-01"))
    assert len(frames) == 12 == len(truth["index"])
    for k in (0, 5, 11):
        idx, ts, ir, depth = frames[k]
        raw, gt = rec.frame(k)
        assert idx == raw.header.frame == truth["index"][k]
        assert ts == raw.header.capture_ns == truth["timestamp_ns"][k]
        assert ir.tobytes() == raw.ir.tobytes()
        assert depth.tobytes() == raw.depth.tobytes()
        np.testing.assert_array_equal(truth["visible"][k], gt.visible)


def test_simulate_writes_a_named_variant_of_the_benches(tmp_path) -> None:
    """``--variant`` is the set-up of ``bench gait --variant``: here another sensor."""
    out = tmp_path / "K01"
    args = ["c3dorg_s00_vicon_CGM24", "--out", str(out), "--quick", "--max-frames", "2"]
    assert main(["simulate", *args, "--variant", "k4a"]) == 0
    cam = json.loads((out / "camera.json").read_text())
    assert (cam["width"], cam["height"], cam["model"]) == (640, 576, "azure-kinect-nfov")
    _, _, ir, depth = next(iter(SessionReader(out).frames("walk-01")))
    assert ir.shape == depth.shape == (576, 640)


def test_simulate_refuses_an_unknown_variant(tmp_path, capsys) -> None:
    out = tmp_path / "X"
    args = ["simulate", "c3dorg_s00_vicon_CGM24", "--out", str(out)]
    assert main([*args, "--variant", "moon"]) == 2
    assert "'moon'" in capsys.readouterr().err
    # combined set-ups whose parts set one thing differently are refused, naming it
    assert main([*args, "--variant", "d20+d30"]) == 2
    assert "marker_diameter_mm" in capsys.readouterr().err
    assert not out.exists()
