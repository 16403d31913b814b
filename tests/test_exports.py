"""Trial results as C3D, OpenSim TRC and MOT, and CSV (``gaitflow.exports``, ``convert``)."""

from __future__ import annotations

import json
import warnings

import c3d
import numpy as np
import pytest

from gaitflow.cli import main
from gaitflow.errors import InputError
from gaitflow.exports import c3d_bytes, cycles_csv, mot_text, trc_text, trial_arrays
from gaitflow.markers import MARKER_INDEX
from gaitflow.results import build_results, write_results

KNE = MARKER_INDEX["R_KNE"]
HEE = MARKER_INDEX["L_HEE"]


# Floor 800 mm below the optical axis (camera Y points down), the walking line 2.75 m
# away from -2 m to +2 m: lab X = camera X + 2000, lab Y (away) = Z - 2750, up = 800 - Y.
WALKWAY = {"floor_plane": [0.0, -1.0, 0.0, 800.0], "start": [-2000.0, 800.0, 2750.0],
           "end": [2000.0, 800.0, 2750.0]}  # fmt: skip


def _doc(walkway: bool = True) -> dict:
    """Frames 10, 11 and 13 of a 30 fps trial (12 was dropped); the right knee seen in
    all three, the left heel only in 11; a heel strike and a toe off."""
    pos = np.full((3, 20, 3), np.nan)
    pos[:, KNE] = [[100.0, 200.0, 2500.0], [110.0, 201.0, 2501.5], [130.0, 203.0, 2503.0]]
    pos[1, HEE] = [-50.0, 700.0, 2800.0]
    pix = np.where(np.isfinite(pos[..., :2]), 100.0, np.nan)
    return build_results(
        session="S01-2026-11-27",
        trial="walk-01",
        camera_fps=30.0,
        frame_index=[10, 11, 13],
        frame_time_s=np.array([0.0, 1 / 30, 3 / 30]),
        positions=pos,
        pixels=pix,
        # 100 Hz: left 10 + 100 t deg throughout, right only up to 0.03 s
        knee_time_s=np.arange(11) / 100,
        knee_deg={"L": 10 + np.arange(11), "R": np.where(np.arange(11) <= 3, 20.0, np.nan)},
        events=[
            {"side": "L", "kind": "heel_strike", "time_s": 0.05},
            {"side": "R", "kind": "toe_off", "time_s": 0.1},
        ],
        spatiotemporal={},
        extra={"walkway": WALKWAY} if walkway else None,
    )


def test_trial_arrays_put_a_dropped_frame_on_the_grid_as_missing() -> None:
    arr = trial_arrays(_doc())
    assert arr.frame.tolist() == [10, 11, 12, 13]
    np.testing.assert_allclose(arr.time_s, [0.0, 1 / 30, 2 / 30, 3 / 30])
    assert np.isnan(arr.xyz[2]).all()  # the dropped frame
    np.testing.assert_array_equal(arr.xyz[3, KNE], [130.0, 203.0, 2503.0])
    assert np.isnan(arr.xyz[0, HEE]).all() and arr.xyz[1, HEE, 1] == 700.0
    assert arr.events == (("L", "heel_strike", 0.05), ("R", "toe_off", 0.1))
    # the knee at the rows' times; none where no sample lies within 20 ms
    np.testing.assert_allclose(arr.knee[:, 0], 10 + 100 * arr.time_s)
    np.testing.assert_allclose(arr.knee[:, 1], [20.0, 20.0, np.nan, np.nan])


def test_lab_and_camera_positions() -> None:
    arr = trial_arrays(_doc())
    np.testing.assert_allclose(arr.positions("lab", y_up=False)[3, KNE], [2130, -247, 597])
    np.testing.assert_allclose(arr.positions("lab", y_up=True)[3, KNE], [2130, 597, 247])
    assert arr.positions("camera", y_up=True) is arr.xyz
    with pytest.raises(InputError, match="walkway"):
        trial_arrays(_doc(walkway=False)).positions("lab", y_up=False)


def test_a_trial_without_frames_cannot_be_exported() -> None:
    doc = _doc()
    doc["frames"] = []
    with pytest.raises(InputError, match="no frame"):
        trial_arrays(doc, "walk-09.json")


def test_the_c3d_reads_back_with_markers_invalid_points_and_events() -> None:
    import io

    with warnings.catch_warnings():
        # the reader's note that the file has no analog channels (none are written)
        warnings.filterwarnings("ignore", message="No analog data found", category=UserWarning)
        r = c3d.Reader(io.BytesIO(c3d_bytes(trial_arrays(_doc()))))
        pts = np.array([p for _, p, _ in r.read_frames()])
    assert r.point_rate == 30.0 and r.frame_count == 4
    assert [s.strip() for s in r.point_labels][KNE] == "R_KNE"
    assert pts.shape == (4, 22, 5)  # the 20 markers, then the two knee angle points
    np.testing.assert_allclose(pts[3, KNE, :3], [2130.0, -247.0, 597.0])  # lab, Z up
    assert pts[3, KNE, 3] >= 0  # a valid point
    assert (pts[2, :20, 3] == -1).all()  # the dropped frame: every marker invalid
    assert pts[0, HEE, 3] == -1 and pts[1, HEE, 3] >= 0
    angles = [s.strip() for s in r.get("POINT").get("ANGLES").string_array]
    assert angles == [s.strip() for s in r.point_labels][20:] == ["LKneeAngles", "RKneeAngles"]
    np.testing.assert_allclose(pts[:, 20, 0], 10 + 100 * np.arange(4) / 30, rtol=1e-6)
    assert (pts[:, 20, 3] >= 0).all() and (pts[:, 21, 3] == [0, 0, -1, -1]).all()
    ev = r.get("EVENT")
    assert [s.strip() for s in ev.get("CONTEXTS").string_array] == ["Left", "Right"]
    assert [s.strip() for s in ev.get("LABELS").string_array] == ["Foot Strike", "Foot Off"]
    # (minutes, seconds) per event
    np.testing.assert_allclose(ev.get("TIMES").float_array, [[0.0, 0.05], [0.0, 0.1]])
    own = r.get("GAITFLOW")
    assert own.get("TRIAL").string_array[0].strip() == "walk-01"
    assert own.get("SESSION").string_array[0].strip() == "S01-2026-11-27"


def test_the_trc_has_opensims_header_and_empty_fields_where_unseen() -> None:
    text = trc_text(trial_arrays(_doc()), "walk-01.trc")
    lines = text.split("\n")
    assert lines[0].split("\t")[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    assert lines[2].split("\t")[:5] == ["30.00", "30.00", "4", "20", "mm"]
    assert lines[3].split("\t")[2 + 3 * KNE] == "R_KNE"
    rows = [ln.split("\t") for ln in lines[6:] if ln]
    assert len(rows) == 4 and all(len(r) == 2 + 60 for r in rows)
    assert rows[3][:2] == ["4", "0.10000"]
    assert rows[3][2 + 3 * KNE : 5 + 3 * KNE] == ["2130.000", "597.000", "247.000"]  # Y up
    assert rows[2][2:] == [""] * 60  # the dropped frame
    assert rows[0][2 + 3 * HEE] == "" and rows[1][2 + 3 * HEE] == "1950.000"
    cam = trc_text(trial_arrays(_doc()), "walk-01.trc", "camera").split("\n")[9].split("\t")
    assert cam[2 + 3 * KNE : 5 + 3 * KNE] == ["130.000", "203.000", "2503.000"]


def test_mot_holds_the_knee_on_the_results_time_base_from_the_first_frame() -> None:
    doc = _doc()
    # a trial whose clock does not start at 0: times in the file are from the first frame
    for f in doc["frames"]:
        f["time_s"] += 5.0
    doc["knee_flexion_deg"]["time_s"] = [t + 5.0 for t in doc["knee_flexion_deg"]["time_s"]]
    lines = mot_text(trial_arrays(doc), "walk-01.mot").split("\n")
    assert lines[:7] == ["walk-01.mot", "version=1", "nRows=11", "nColumns=3", "inDegrees=yes",
                         "endheader", "time\tknee_flexion_l\tknee_flexion_r"]  # fmt: skip
    rows = np.array([[float(x) for x in r.split("\t")] for r in lines[7:-1]])
    assert rows.shape == (11, 3) and lines[-1] == ""
    np.testing.assert_allclose(rows[:, 0], np.arange(11) / 100)
    np.testing.assert_allclose(rows[:, 1], 10 + np.arange(11))
    np.testing.assert_allclose(rows[:4, 2], 20.0)
    assert np.isnan(rows[4:, 2]).all() and lines[11].endswith("\tNaN")


def test_csv_holds_one_row_per_heel_strike_with_its_pass() -> None:
    doc = _doc()
    for f in doc["frames"]:
        f["time_s"] += 5.0  # times in the file are from the first frame
    doc["passes"] = [{"direction": 1, "start_s": 5.0, "end_s": 6.0},
                     {"direction": -1, "start_s": 8.0, "end_s": 9.0}]  # fmt: skip
    doc["cycles"] = [
        {"side": "L", "heel_strike_s": 5.25, "toe_off_s": 5.9, "next_heel_strike_s": 6.3,
         "step_length_mm": 612.5, "stride_length_mm": 1250.25, "stance_s": 0.65},
        {"side": "R", "heel_strike_s": 8.5},
        {"side": "R", "heel_strike_s": 7.0, "step_length_mm": 600.0},  # in no pass
    ]  # fmt: skip
    rows = cycles_csv(doc).split("\n")
    assert rows[0] == ("pass,direction,side,heel_strike_s,toe_off_s,next_heel_strike_s,"
                       "step_length_mm,stride_length_mm,stance_s,swing_s")  # fmt: skip
    assert rows[1] == "1,1,L,0.25,0.9,1.3,612.5,1250.25,0.65,"
    assert rows[2] == "2,-1,R,3.5,,,,,,"
    assert rows[3] == ",,R,2.0,,,600.0,,,"
    assert rows[4:] == [""]
    # results without cycles: the header alone
    assert cycles_csv(_doc()) == rows[0] + "\n"


def test_convert_writes_all_and_names_a_bad_file_without_stopping(tmp_path, capsys) -> None:
    good = write_results(_doc(), tmp_path / "walk-01.json")
    bad = tmp_path / "walk-02.json"
    bad.write_text(json.dumps({"format": "something else"}))
    out = tmp_path / "exports"
    assert main(["convert", str(bad), str(good), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "walk-02.json" in err and "1 file(s) skipped" in err
    names = sorted(p.name for p in out.iterdir())
    assert names == ["walk-01.c3d", "walk-01.csv", "walk-01.mot", "walk-01.trc"]
    assert (out / "walk-01.trc").read_text() == trc_text(trial_arrays(_doc()), "walk-01.trc")
    # results without the calibration's walkway: camera space (auto)
    old = write_results(_doc(walkway=False), tmp_path / "old" / "walk-03.json")
    assert main(["convert", str(old), "--to", "trc"]) == 0
    assert "camera frame" in capsys.readouterr().out
    text = (old.parent / "walk-03.trc").read_text()
    assert text == trc_text(trial_arrays(_doc(walkway=False)), "walk-03.trc", "camera")


def test_convert_refuses_an_unknown_format(tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as e:
        main(["convert", str(tmp_path / "walk-01.json"), "--to", "c3d,xlsx"])
    assert e.value.code == 2 and "xlsx" in capsys.readouterr().err


def test_convert_refuses_two_results_of_one_name_into_one_folder(tmp_path) -> None:
    a = write_results(_doc(), tmp_path / "S01" / "walk-01.json")
    b = write_results(_doc(), tmp_path / "S02" / "walk-01.json")
    out = tmp_path / "exports"
    assert main(["convert", str(a), str(b), "--out", str(out)]) == 2
    assert not out.exists()
    # beside each JSON (no --out) they do not collide
    assert main(["convert", str(a), str(b)]) == 0
    assert (tmp_path / "S01" / "walk-01.c3d").exists() and (
        tmp_path / "S02" / "walk-01.trc"
    ).exists()
