"""The trial results JSON: builder, schema file and validator (shared/spec/results.md)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from gaitflow.errors import SchemaError
from gaitflow.markers import MARKER_NAMES
from gaitflow.results import (
    build_results,
    empty_results,
    read_results,
    schema,
    validate,
    validation_errors,
    write_results,
)


def small_doc() -> dict:
    pos = np.full((3, 20, 3), np.nan)
    pos[:, 5] = [[100.0, 200.0, 2500.0]] * 3
    pix = np.full((3, 20, 2), np.nan)
    pix[:, 5] = [[256.0, 212.0]] * 3
    return build_results(
        session="S01",
        trial="walk-01",
        camera_fps=30.0,
        frame_index=[0, 1, 3],
        frame_time_s=np.array([0.0, 1 / 30, 0.1]),
        positions=pos,
        pixels=pix,
        knee_time_s=np.array([0.0, 0.01, 0.02]),
        knee_deg={"L": np.array([5.0, np.nan, 6.0]), "R": np.array([1.0, 2.0, 3.0])},
        events=[{"side": "R", "kind": "heel_strike", "time_s": 1.233}],
        spatiotemporal={
            "R": {
                "step_length_mm": [600.0],
                "stride_length_mm": [],
                "stance_s": [0.6],
                "swing_s": [],
            },
            "cadence_steps_per_min": float("nan"),
            "speed_m_s": 1.1,
        },
        extra={"scope": "trial", "warnings": []},
    )


def test_built_document_follows_results_md():
    doc = small_doc()
    assert validation_errors(doc) == []
    assert doc["format"] == "gaitflow.trial-results" and doc["version"] == 1
    f0 = doc["frames"][0]
    assert set(f0["markers"]) == set(MARKER_NAMES) == set(f0["pixels"])
    assert f0["markers"]["L_KNE"] == [100.0, 200.0, 2500.0] and f0["markers"]["R_HEE"] is None
    assert doc["knee_flexion_deg"]["L"] == [5.0, None, 6.0]
    assert doc["spatiotemporal"]["cadence_steps_per_min"] is None
    assert doc["spatiotemporal"]["L"] == {
        "step_length_mm": [], "stride_length_mm": [], "stance_s": [], "swing_s": []
    }  # fmt: skip
    json.dumps(doc, allow_nan=False)  # no NaN can reach the file


@pytest.mark.parametrize(
    ("mutate", "expect"),
    [
        (lambda d: d.pop("events"), "missing required field 'events'"),
        (lambda d: d.update(version=2), "is not 1"),
        (lambda d: d["events"].append({"side": "X", "kind": "toe_off", "time_s": 1.0}), "'X'"),
        (lambda d: d["frames"][0]["markers"].update(KNEE=[1, 2, 3]), "KNEE"),
        (lambda d: d["frames"][0]["markers"].update(L_KNE=[1, 2]), "matches none"),
        (lambda d: d["knee_flexion_deg"]["R"].pop(), "values for 3 times"),
        (lambda d: d["spatiotemporal"]["L"].update(stance_s="0.6"), "not of type array"),
        (lambda d: d.update(camera_fps=float("nan")), "camera_fps"),
    ],
)
def test_schema_rejects_broken_documents(mutate, expect):
    doc = copy.deepcopy(small_doc())
    mutate(doc)
    errs = validation_errors(doc)
    assert any(expect in e for e in errs), errs
    with pytest.raises(SchemaError):
        validate(doc)


def test_schema_file_is_packaged_and_names_every_marker():
    s = schema()
    assert s["properties"]["format"]["const"] == "gaitflow.trial-results"
    names = s["$defs"]["frame"]["properties"]["markers"]["propertyNames"]["enum"]
    assert names == list(MARKER_NAMES)


def test_empty_result_is_valid_and_carries_the_warning():
    doc = empty_results("S01", "walk-02", 30.0, "subject never seen")
    assert validation_errors(doc) == []
    assert doc["frames"] == [] and doc["events"] == [] and doc["warnings"] == ["subject never seen"]


def test_write_and_read_round_trip(tmp_path):
    doc = small_doc()
    p = write_results(doc, tmp_path / "walk-01.json")
    assert read_results(p) == doc
    bad = copy.deepcopy(doc)
    del bad["frames"]
    with pytest.raises(SchemaError):
        write_results(bad, tmp_path / "bad.json")
    assert not (tmp_path / "bad.json").exists()
