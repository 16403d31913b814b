"""A session's camera.json reaches the stages: intrinsics, marker size, floor markers, fps."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gaitflow.stages import calibrate

from gaitflow.camera import Camera
from gaitflow.commands import analyze
from gaitflow.errors import InputError
from gaitflow.session import SessionWriter, session_stage_params
from gaitflow.sim.variants import OTHER_UNIT, VARIANTS, sim_config, variant_changes

DOC = OTHER_UNIT.to_json(marker_diameter_mm=20, calibration_markers=5, subject={"id": "S9"})


def test_camera_json_sets_the_stage_parameters() -> None:
    p = session_stage_params(DOC)
    assert calibrate.camera_from_param(p["calibrate"]["camera"]) == OTHER_UNIT
    assert p["calibrate"]["C"] == 5
    for stage in ("calibrate", "locate", "model"):
        assert p[stage]["marker_diameter_mm"] == 20.0
    assert p["label"]["fps"] == 30.0
    # the stages accept them (validated as at start-up)
    calibrate.PARAMS.resolve(p["calibrate"])


def test_explicit_parameters_win_and_optional_keys_may_be_absent() -> None:
    doc = Camera().to_json()  # no marker_diameter_mm, no calibration_markers
    p = session_stage_params(doc, {"locate": {"marker_diameter_mm": 30.0}, "gait": {"xi": 0.1}})
    assert p["locate"] == {"marker_diameter_mm": 30.0}
    assert p["gait"] == {"xi": 0.1}
    assert "C" not in p["calibrate"] and "model" not in p


def test_bad_camera_json_is_named() -> None:
    doc = {k: v for k, v in DOC.items() if k != "fps"}
    with pytest.raises(InputError, match="'fps'"):
        session_stage_params(doc)


def test_analyze_passes_the_session_camera_to_the_pipeline(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "S"
    w = SessionWriter(root, DOC)
    z = np.zeros((424, 512), np.uint16)
    for name in ("calibration", "static", "walk-01"):
        w.write_recording(name, ((k, 1000 * k, z, z) for k in range(2)))
    seen: dict[str, Any] = {}

    class Recorder:
        def __init__(self, graph: Any, params: Any = None, sink: Any = None) -> None:
            seen["params"] = params

        def push(self, msg: Any) -> None:
            seen.setdefault("frames", 0)
            seen["frames"] += 1

        def finish(self) -> None:
            pass

    monkeypatch.setattr("gaitflow.stages.inline.InlinePipeline", Recorder)
    analyze.run_inline_session(root, {"gait": {"xi": 0.2}})
    p = seen["params"]
    assert calibrate.camera_from_param(p["calibrate"]["camera"]) == OTHER_UNIT
    assert p["locate"]["marker_diameter_mm"] == 20.0 and p["gait"] == {"xi": 0.2}
    assert seen["frames"] == 6


def test_variants_change_the_scene_only() -> None:
    assert sim_config("unit2").camera == OTHER_UNIT
    assert sim_config("d20").marker_diameter_mm == 20.0
    assert sim_config("base") == sim_config()
    for name in VARIANTS:
        assert not {"params", "stage"} & set(variant_changes(name))
    with pytest.raises(Exception, match="'nope'"):
        variant_changes("nope")
