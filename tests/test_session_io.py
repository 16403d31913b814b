"""Session folders: write, read back byte-identical, and every kind of bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gaitflow.camera import Camera
from gaitflow.errors import InputError
from gaitflow.session import (
    SessionReader,
    SessionWriter,
    iter_raw_frames,
    parse_frames_csv,
    recording_order,
)

H, W = 48, 64  # small frames keep the tests fast; one test uses the full Kinect v2 size
INDICES = (0, 1, 2, 4, 5, 9)  # gaps at 3 and 6-8 are dropped frames


def camera_doc(width: int = W, height: int = H) -> dict:
    return Camera(width=width, height=height).to_json(marker_diameter_mm=25, extra_key="kept")


def make_frames(seed: int, indices=INDICES, shape=(H, W)):
    rng = np.random.default_rng(seed)
    out = []
    for i in indices:
        ir = rng.integers(0, 65536, shape, dtype=np.uint16)
        ir[0, :3] = 65535  # saturated pixels survive
        depth = rng.integers(0, 4500, shape, dtype=np.uint16)
        depth[1, :3] = 0  # invalid pixels survive
        out.append((i, 1_700_000_000_000_000_000 + i * 33_333_333 + seed, ir, depth))
    return out


@pytest.fixture
def session(tmp_path: Path) -> tuple[Path, dict[str, list]]:
    root = tmp_path / "S01"
    w = SessionWriter(root, camera_doc())
    frames = {
        "calibration": make_frames(1, (0, 1)),
        "static": make_frames(2, (0, 1, 2)),
        "walk-01": make_frames(3),
    }
    for name, fr in frames.items():
        assert w.write_recording(name, fr) == len(fr)
    return root, frames


def read_all(reader: SessionReader, name: str) -> list:
    return list(reader.frames(name))


def assert_same(got: list, want: list) -> None:
    assert len(got) == len(want)
    for (gi, gt, gir, gd), (wi, wt, wir, wd) in zip(got, want, strict=True):
        assert (gi, gt) == (wi, wt)
        assert gir.dtype == np.uint16 and gd.dtype == np.uint16
        assert gir.tobytes() == wir.tobytes()
        assert gd.tobytes() == wd.tobytes()


# --------------------------------------------------------------------------- round trip


def test_round_trip_is_byte_identical(session):
    root, frames = session
    r = SessionReader(root)
    assert r.recordings() == ["calibration", "static", "walk-01"]
    for name, want in frames.items():
        assert_same(read_all(r, name), want)
    assert r.frames_read == sum(len(f) for f in frames.values())
    assert r.skipped.total() == 0 and r.warnings == []
    assert r.camera == Camera(width=W, height=H)
    assert r.camera_doc["extra_key"] == "kept"  # unknown keys are ignored, not lost
    text = (root / "walk-01" / "frames.csv").read_text().splitlines()
    assert text[0] == "index,timestamp_ns"
    assert [int(t.split(",")[0]) for t in text[1:]] == list(INDICES)
    assert (root / "walk-01" / "ir" / "000009.png").is_file()


def test_full_size_kinect_frame_is_16bit_single_channel_png(tmp_path):
    doc = Camera().to_json()
    w = SessionWriter(tmp_path, doc)
    want = make_frames(5, (0, 1), shape=(424, 512))
    w.write_recording("static", want)
    png = cv2.imread(str(tmp_path / "static" / "depth" / "000001.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.shape == (424, 512)
    assert_same(read_all(SessionReader(tmp_path), "static"), want)


def test_threaded_reader_and_writer_match_serial(tmp_path):
    want = make_frames(7, tuple(range(12)))
    SessionWriter(tmp_path, camera_doc(), workers=2, compression=6).write_recording("walk-01", want)
    assert_same(read_all(SessionReader(tmp_path, workers=2), "walk-01"), want)


def test_recording_order_is_protocol_order(tmp_path):
    w = SessionWriter(tmp_path, camera_doc())
    for name in ("walk-10", "walk-02", "static", "calibration", "walk-1"):
        w.write_recording(name, make_frames(0, (0,)))
    (tmp_path / "notes").mkdir()  # not a recording
    r = SessionReader(tmp_path)
    assert r.recordings() == ["calibration", "static", "walk-1", "walk-02", "walk-10"]
    assert recording_order(["walk-3", "static"]) == ["static", "walk-3"]


def test_missing_protocol_folders_are_reported(tmp_path):
    w = SessionWriter(tmp_path, camera_doc())
    w.write_recording("walk-01", make_frames(0, (0,)))
    r = SessionReader(tmp_path)
    assert r.missing() == ["calibration", "static"]
    with pytest.raises(InputError, match=r"missing recording folder calibration/, static/"):
        r.require()
    with pytest.raises(InputError, match="recording folder not found"):
        r.frames("walk-02")


def test_raw_frames_carry_headers(session):
    root, frames = session
    msgs = list(iter_raw_frames(SessionReader(root), "walk-01", "cam7"))
    want = frames["walk-01"]
    assert [m.header.frame for m in msgs] == list(INDICES)
    assert [m.header.capture_ns for m in msgs] == [f[1] for f in want]
    assert [m.header.last for m in msgs] == [False] * (len(INDICES) - 1) + [True]
    assert {m.header.trial for m in msgs} == {"walk-01"}
    assert {m.header.camera for m in msgs} == {"cam7"}
    assert msgs[2].ir.tobytes() == want[2][2].tobytes()


def test_writer_rejects_bad_frames(tmp_path):
    w = SessionWriter(tmp_path, camera_doc())
    ok = make_frames(0, (0, 1))
    with pytest.raises(InputError, match="expected uint16"):
        w.write_recording("walk-01", [(0, 0, ok[0][2].astype(np.uint8), ok[0][3])])
    with pytest.raises(InputError, match="expected uint16"):
        w.write_recording("walk-01", [(0, 0, ok[0][2][:-1], ok[0][3])])
    with pytest.raises(InputError, match="must increase"):
        w.write_recording("walk-01", [ok[1], ok[0]])
    with pytest.raises(InputError, match="not a recording name"):
        w.write_recording("walking", ok)
    with pytest.raises(InputError, match="missing required key 'fps'"):
        SessionWriter(tmp_path / "x", {k: v for k, v in camera_doc().items() if k != "fps"})


# --------------------------------------------------------------------------- camera.json


@pytest.mark.parametrize("key", ["model", "width", "height", "fps", "depth_intrinsics"])
def test_missing_camera_key_names_key_and_file(session, key):
    root, _ = session
    doc = camera_doc()
    del doc[key]
    (root / "camera.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=rf"camera\.json: missing required key '{key}'"):
        SessionReader(root)


def test_missing_intrinsic_key_and_bad_json(session):
    root, _ = session
    doc = camera_doc()
    del doc["depth_intrinsics"]["k2"]
    (root / "camera.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"missing required key 'depth_intrinsics\.k2'"):
        SessionReader(root)
    (root / "camera.json").write_text("{not json")
    with pytest.raises(InputError, match=r"camera\.json: not valid JSON"):
        SessionReader(root)
    (root / "camera.json").unlink()
    with pytest.raises(InputError, match=r"camera\.json: file not found"):
        SessionReader(root)
    with pytest.raises(InputError, match="session folder not found"):
        SessionReader(root / "nope")


# --------------------------------------------------------------------------- bad frames


def _png_path(root: Path, kind: str, index: int) -> Path:
    return root / "walk-01" / kind / f"{index:06d}.png"


def test_bad_frames_are_skipped_counted_and_named(session):
    root, frames = session
    want = frames["walk-01"]
    # One bad file per frame, of every kind; frame 0 and 9 stay good.
    _png_path(root, "ir", 1).write_bytes(b"this is not a png")
    good = _png_path(root, "depth", 2).read_bytes()
    _png_path(root, "depth", 2).write_bytes(good[: len(good) // 3])  # truncated PNG
    cv2.imwrite(str(_png_path(root, "ir", 4)), np.zeros((H, W + 2), np.uint16))  # wrong size
    cv2.imwrite(str(_png_path(root, "depth", 5)), np.zeros((H, W), np.uint8))  # 8-bit
    r = SessionReader(root)
    got = read_all(r, "walk-01")
    assert [g[0] for g in got] == [0, 9]
    assert_same(got, [want[0], want[-1]])
    assert r.skipped == {"unreadable": 2, "wrong_size": 1, "not_16bit": 1}
    assert r.skipped.total() == 4
    assert len(r.warnings) == 4
    joined = "\n".join(r.warnings)
    assert "ir/000001.png: unreadable: not a PNG file" in joined
    assert "depth/000002.png: unreadable" in joined
    assert "ir/000004.png: is 66x48 px, expected 64x48 from camera.json" in joined
    assert "depth/000005.png: is 8-bit (uint8), expected 16-bit" in joined
    # The reader kept going and the other recordings are untouched.
    assert_same(read_all(r, "static"), frames["static"])


def test_missing_and_colour_pngs_are_skipped(session):
    root, _ = session
    _png_path(root, "ir", 0).unlink()
    cv2.imwrite(str(_png_path(root, "depth", 9)), np.zeros((H, W, 3), np.uint16))
    r = SessionReader(root)
    msgs = list(iter_raw_frames(r, "walk-01"))
    assert [m.header.frame for m in msgs] == [1, 2, 4, 5]
    # The final frame was bad: the last flag moves to the last frame sent.
    assert [m.header.last for m in msgs] == [False, False, False, True]
    assert r.skipped == {"missing": 1, "not_single_channel": 1}
    assert any("ir/000000.png: missing" in w for w in r.warnings)
    assert any("has 3 channels" in w for w in r.warnings)


# --------------------------------------------------------------------------- frames.csv


def _csv(root: Path) -> Path:
    return root / "walk-01" / "frames.csv"


def test_non_increasing_timestamp_names_file_and_line(session):
    root, frames = session
    rows = [f"{i},{t}" for i, t, _, _ in frames["walk-01"]]
    rows[3] = rows[3].split(",")[0] + "," + rows[2].split(",")[1]  # equal to the previous
    _csv(root).write_text("index,timestamp_ns\n" + "\n".join(rows) + "\n")
    r = SessionReader(root)
    with pytest.raises(InputError) as exc:
        r.frames("walk-01")  # raised at the call: no frame of the trial went out
    msg = str(exc.value)
    assert "walk-01/frames.csv" in msg and "line 5" in msg and "does not increase" in msg
    assert r.frames_read == 0


def test_decreasing_timestamp_is_refused(session):
    root, _ = session
    _csv(root).write_text("index,timestamp_ns\n0,100\n1,300\n2,200\n")
    with pytest.raises(InputError, match=r"line 4: timestamp_ns 200 does not increase"):
        SessionReader(root).frames("walk-01")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "is empty"),
        ("frame,time\n0,1\n", "header must start with 'index,timestamp_ns'"),
        ("index,timestamp_ns\n0,1,2\n", "line 2: 3 columns, header has 2"),
        ("index,timestamp_ns\n0,abc\n", "line 2: not integers"),
        ("index,timestamp_ns\n0,1.5\n", "line 2: not integers"),
        ("index,timestamp_ns\n-1,1\n", "line 2: negative index"),
        ("index,timestamp_ns\n0,1\n0,2\n", "line 3: index 0 does not increase"),
        ("index,timestamp_ns\n0,99999999999999999999\n", "is not an int64"),
    ],
)
def test_malformed_frames_csv_names_it(session, text, expected):
    root, _ = session
    _csv(root).write_text(text)
    with pytest.raises(InputError, match=r"frames\.csv") as exc:
        SessionReader(root).frames("walk-01")
    assert expected in str(exc.value)


def test_missing_frames_csv(session):
    root, _ = session
    _csv(root).unlink()
    with pytest.raises(InputError, match=r"walk-01/frames\.csv: file not found"):
        SessionReader(root).frames("walk-01")


def test_frames_csv_tolerates_extra_columns_blank_lines_and_bom():
    rows = parse_frames_csv("\ufeffindex,timestamp_ns,note\n\n0,10,a\n2,30,b\n\n")
    assert [(r.index, r.timestamp_ns) for r in rows] == [(0, 10), (2, 30)]


def test_png_that_cannot_be_read_as_a_file_is_counted(session):
    root, _ = session
    p = _png_path(root, "ir", 2)
    p.unlink()
    p.mkdir()  # reading it raises IsADirectoryError: an OS error, counted like the rest
    r = SessionReader(root)
    assert [f[0] for f in read_all(r, "walk-01")] == [0, 1, 4, 5, 9]
    assert r.skipped == {"unreadable": 1}
    assert "ir/000002.png: unreadable" in r.warnings[0]
