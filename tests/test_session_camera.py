"""A session's camera.json reaches the stages: intrinsics, marker size, floor markers, fps."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gaitflow.schemas import CalibrationRecord, Markers3D, RawFrame
from gaitflow.stages import calibrate, grab, label, model

from gaitflow.camera import Camera, marker_diameter
from gaitflow.commands import analyze
from gaitflow.errors import ConfigError, InputError, ParameterError, StageError
from gaitflow.evaluate_label import calibration_record
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


def test_variants_joined_with_plus_combine_their_set_ups() -> None:
    cfg = sim_config("child+far+noisy")
    assert (cfg.body_scale, cfg.walk_distance_mm, cfg.depth_noise_scale) == (0.72, 3500.0, 2.0)
    # two camera changes merge field by field: the other unit's intrinsics at 15 frames/s
    cam = sim_config("unit2+fps15").camera
    assert cam == dataclasses.replace(OTHER_UNIT, fps=15.0)
    assert sim_config("fps15+unit2").camera == cam
    # the same value twice is no conflict
    assert variant_changes("strays+strays_late") == variant_changes("strays_late")
    with pytest.raises(ConfigError, match=r"'unit2\+k4a'.*camera's fx"):
        variant_changes("unit2+k4a")
    with pytest.raises(ConfigError, match=r"marker_diameter_mm \(20.0, 30.0\)"):
        variant_changes("d20+d30")
    with pytest.raises(ConfigError, match=r"'nope' in 'child\+nope'"):
        variant_changes("child+nope")


# --- the camera.json travels with the frames (gaitflow run, a grab stage on its own) ------


def _raw(doc: dict[str, Any], last: bool = False) -> RawFrame:
    z = np.zeros((424, 512), np.uint16)
    return RawFrame(
        header=RawFrame.make_header("cam0", "calibration", 0, 0, last=last),
        ir=z,
        depth=z,
        camera=doc,
    )


def test_calibrate_adopts_the_camera_the_frames_carry() -> None:
    st = calibrate.init(calibrate.PARAMS.resolve({}))
    st, out = calibrate.step(st, {"raw": _raw(DOC, last=True)})
    assert st.camera == OTHER_UNIT
    assert st.params["C"] == 5 and st.params["marker_diameter_mm"] == 20.0
    record = out[-1]
    assert isinstance(record, CalibrationRecord)
    # the record carries the document on to clean, locate, model and label
    assert Camera.from_json(record.camera) == OTHER_UNIT
    assert record.camera["marker_diameter_mm"] == 20 and record.camera["fps"] == 30.0
    assert "subject" not in record.camera


def test_an_explicit_camera_parameter_wins_over_the_frames() -> None:
    mine = Camera(fx=500.0, fy=500.0)
    st = calibrate.init(calibrate.PARAMS.resolve({"camera": mine.to_json()}))
    st, out = calibrate.step(st, {"raw": _raw(DOC, last=True)})
    assert st.camera == mine and st.params["C"] == 4
    assert Camera.from_json(out[-1].camera) == mine


def test_a_bad_camera_document_on_a_frame_is_a_stage_error_naming_the_key() -> None:
    st = calibrate.init(calibrate.PARAMS.resolve({}))
    bad = {
        **DOC,
        "depth_intrinsics": {k: v for k, v in DOC["depth_intrinsics"].items() if k != "k2"},
    }
    with pytest.raises(StageError, match="k2"):
        calibrate.step(st, {"raw": _raw(bad)})
    with pytest.raises(ParameterError, match=r"\b99\b"):
        calibrate.step(st, {"raw": _raw({**DOC, "calibration_markers": 99})})


def _no_blobs() -> Markers3D:
    """A walking frame without blobs."""
    return Markers3D(
        header=Markers3D.make_header("cam0", "walk-01", 0, 0),
        centroid=np.zeros((0, 2)),
        marker_radius=np.zeros(0),
        region_radius=np.zeros(0),
        depth=np.zeros((0, 3)),
        position=np.zeros((0, 3, 3)),
    )


def test_model_and_label_read_marker_size_and_fps_from_the_record() -> None:
    record = dataclasses.replace(
        calibration_record(), camera={**Camera().to_json(), "fps": 15, "marker_diameter_mm": 20}
    )
    assert marker_diameter(model.PARAMS.resolve({})["marker_diameter_mm"], record.camera) == 20.0
    assert marker_diameter(14.0, record.camera) == 14.0
    assert marker_diameter(0.0, {}) == 25.0
    mk = _no_blobs()
    for fps_param, expect in ((0.0, 15.0), (60.0, 60.0)):
        st = label.init(label.PARAMS.resolve({"fps": fps_param}))
        st, _ = label.step(st, {"markers": mk, "calibration": record})
        assert st.fps == expect


def test_label_takes_the_image_bounds_from_the_record_camera() -> None:
    mk = _no_blobs()
    record = dataclasses.replace(calibration_record(), camera=DOC)
    st, _ = label.step(label.init(label.PARAMS.resolve({})), {"markers": mk, "calibration": record})
    assert st.sides[4] == OTHER_UNIT
    off = label.PARAMS.resolve({"view_gate": False})
    st, _ = label.step(label.init(off), {"markers": mk, "calibration": record})
    assert st.sides[4] is None
    st, _ = label.step(
        label.init(label.PARAMS.resolve({})), {"markers": mk, "calibration": calibration_record()}
    )
    assert st.sides[4] is None  # a record without a camera: no bounds, no gate
    bad = dataclasses.replace(calibration_record(), camera={"depth_intrinsics": {"fx": 1.0}})
    with pytest.raises(StageError, match=r"label.*camera"):
        label.step(label.init(label.PARAMS.resolve({})), {"markers": mk, "calibration": bad})


def test_session_frames_carry_their_camera_json(tmp_path: Path) -> None:
    root = tmp_path / "S"
    w = SessionWriter(root, DOC)
    z = np.zeros((424, 512), np.uint16)
    for name in ("calibration", "static", "walk-01"):
        w.write_recording(name, ((k, 1000 * k, z, z) for k in range(2)))
    src = grab.SPEC.open(grab.PARAMS.resolve({"source": "session", "path": str(root)}))
    frames = [m for group in src for m in group]
    assert len(frames) == 6
    assert all(Camera.from_json(f.camera) == OTHER_UNIT for f in frames)
    assert frames[0].camera["marker_diameter_mm"] == 20
