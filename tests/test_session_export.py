"""``gaitflow export``: an MCAP recording becomes a session folder, frames byte-identical."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import pytest
from gaitflow.stages.grab import SPEC

from gaitflow.camera import Camera
from gaitflow.cli import main
from gaitflow.errors import InputError
from gaitflow.session import SessionReader

SAMPLE = Path(str(resources.files("gaitflow.recordings").joinpath("sample.mcap")))


def test_export_sample_to_session_folder(tmp_path, capsys):
    out = tmp_path / "S"
    assert main(["export", str(SAMPLE), "--out", str(out), "--max-frames", "8"]) == 0
    assert "frames in 1 recording(s)" in capsys.readouterr().out
    reader = SessionReader(out)
    assert reader.recordings() == ["walk-01"]
    assert reader.camera == Camera()
    # the camera.json the recorded frames carry (the simulator's: it names the marker size)
    assert "marker_diameter_mm" not in Camera().to_json()
    assert reader.camera_doc["marker_diameter_mm"] == 25
    params = {"source": "mcap", "path": str(SAMPLE), "max_frames": 8}
    want = list(SPEC.open(SPEC.params.resolve(params)))
    got = list(reader.frames("walk-01"))
    assert len(got) == len(want) == 8
    for (i, ts, ir, depth), (raw, _truth) in zip(got, want, strict=True):
        assert (i, ts) == (raw.header.frame, raw.header.capture_ns)
        assert ir.tobytes() == raw.ir.tobytes() and depth.tobytes() == raw.depth.tobytes()


def test_export_checks_camera_json(tmp_path, capsys):
    doc = Camera(width=100, height=80).to_json()
    cam = tmp_path / "camera.json"
    cam.write_text(json.dumps(doc))
    args = ["export", str(SAMPLE), "--max-frames", "2", "--camera-json", str(cam), "--out"]
    # The frames are 512x424: a camera.json of another size is refused, naming the sizes.
    assert main([*args, str(tmp_path / "S")]) == 2
    assert "expected uint16 (80, 100)" in capsys.readouterr().err
    del doc["fps"]
    cam.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="missing required key 'fps'"):
        main(["--debug", *args, str(tmp_path / "T")])
