"""Grab sources: session folder and MCAP replay give correct headers, counts and errors."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from gaitflow.schemas import GroundTruth, RawFrame
from gaitflow.stages.base import SourceSpec
from gaitflow.stages.grab import SPEC

from gaitflow.camera import Camera
from gaitflow.errors import InputError, ParameterError
from gaitflow.recording import McapWriter
from gaitflow.session import SessionWriter

H, W = 24, 32
T0 = 5_000_000_000
PERIOD = 33_333_333
PROTOCOL = {"calibration": (0, 1, 2), "static": (0, 1), "walk-01": (0, 1, 3, 4)}


def frames(seed: int, indices):
    rng = np.random.default_rng(seed)
    return [
        (
            i,
            T0 + i * PERIOD,
            rng.integers(0, 65536, (H, W), dtype=np.uint16),
            rng.integers(0, 4500, (H, W), dtype=np.uint16),
        )
        for i in indices
    ]


@pytest.fixture
def session(tmp_path: Path) -> tuple[Path, dict]:
    root = tmp_path / "session"
    w = SessionWriter(root, Camera(width=W, height=H).to_json())
    data = {}
    for seed, (name, idx) in enumerate(PROTOCOL.items()):
        data[name] = frames(seed, idx)
        w.write_recording(name, data[name])
    return root, data


def grab(**params):
    return SPEC.open(SPEC.params.resolve(params))


def test_spec_is_a_source_with_declared_params():
    assert isinstance(SPEC, SourceSpec) and SPEC.name == "grab"
    names = [p.name for p in SPEC.params.params]
    for n in ("source", "path", "trial", "seed", "camera", "recordings", "loop"):
        assert n in names
    with pytest.raises(ParameterError, match="source='webcam'"):
        SPEC.params.resolve({"source": "webcam"})


def test_session_source_headers(session):
    root, data = session
    out = list(grab(source="session", path=str(root), camera="camA"))
    assert all(len(g) == 1 and isinstance(g[0], RawFrame) for g in out)
    hdrs = [g[0].header for g in out]
    assert [h.trial for h in hdrs] == [n for n, idx in PROTOCOL.items() for _ in idx]
    assert [h.frame for h in hdrs] == [i for idx in PROTOCOL.values() for i in idx]
    assert [h.capture_ns for h in hdrs] == [
        T0 + i * PERIOD for idx in PROTOCOL.values() for i in idx
    ]
    assert [h.last for h in hdrs] == [False, False, True, False, True, False, False, False, True]
    assert {h.camera for h in hdrs} == {"camA"}
    assert out[-1][0].depth.tobytes() == data["walk-01"][-1][3].tobytes()


def test_session_source_selects_recordings_and_limits(session):
    root, _ = session
    out = list(grab(source="session", path=str(root), recordings="walk-01"))
    assert [g[0].header.frame for g in out] == [0, 1, 3, 4]
    out = list(grab(source="session", path=str(root), recordings="walk-01,static", max_frames=3))
    assert [(g[0].header.trial, g[0].header.frame, g[0].header.last) for g in out] == [
        ("static", 0, False),
        ("static", 1, True),
        ("walk-01", 0, True),  # the limit ends the trial: flagged so stages close it
    ]


def test_session_source_loop_keeps_time_increasing(session):
    root, _ = session
    src = grab(source="session", path=str(root), recordings="static", loop=True, max_frames=5)
    hdrs = [g[0].header for g in src]
    assert [h.frame for h in hdrs] == [0, 1, 0, 1, 0]
    ts = [h.capture_ns for h in hdrs]
    assert ts == [T0 + k * PERIOD for k in range(5)]
    assert [h.last for h in hdrs] == [False, True, False, True, True]


def test_session_source_errors_at_open(session, tmp_path):
    root, _ = session
    with pytest.raises(InputError, match="session folder not found"):
        grab(source="session", path=str(tmp_path / "nope"))
    with pytest.raises(InputError, match="needs path="):
        grab(source="session")
    with pytest.raises(InputError, match=r"no recording folder walk-02/"):
        grab(source="session", path=str(root), recordings="walk-02")
    for f in (root / "static").rglob("*"):
        if f.is_file():
            f.unlink()
    for d in sorted((root / "static").rglob("*"), reverse=True):
        d.rmdir()
    (root / "static").rmdir()
    with pytest.raises(InputError, match=r"missing recording folder static/"):
        grab(source="session", path=str(root))


def test_session_source_counts_bad_frames_and_goes_on(session):
    root, _ = session
    (root / "walk-01" / "ir" / "000001.png").write_bytes(b"garbage")
    (root / "walk-01" / "depth" / "000004.png").unlink()
    src = grab(source="session", path=str(root), recordings="walk-01")
    out = list(src)
    assert [(g[0].header.frame, g[0].header.last) for g in out] == [(0, False), (3, True)]
    assert src.counters == {"unreadable": 1, "missing": 1}
    assert len(src.warnings) == 2 and "walk-01/ir/000001.png" in src.warnings[0]


def test_session_source_bad_frames_csv_fails_at_open(session):
    root, _ = session
    (root / "static" / "frames.csv").write_text("index,timestamp_ns\n0,10\n1,5\n")
    # Refused before any frame of any trial goes out, so nothing stops halfway.
    with pytest.raises(InputError, match=r"static/frames\.csv: line 3: timestamp_ns 5"):
        grab(source="session", path=str(root))
    # The other recordings can still be played on their own.
    assert len(list(grab(source="session", path=str(root), recordings="calibration"))) == 3


# --------------------------------------------------------------------------- MCAP


def _truth(hdr_raw: RawFrame) -> GroundTruth:
    return GroundTruth.follow(
        hdr_raw.header,
        position=np.zeros((20, 3)),
        pixel=np.zeros((20, 2)),
        visible=np.ones(20, bool),
        occluded=np.zeros(20, bool),
        knee_flexion=np.zeros(2),
    )


def write_mcap(path: Path, session_data: dict, with_truth: bool, cut_last: bool = False) -> None:
    with McapWriter(path, compression="zstd") as w:
        for name, fr in session_data.items():
            for k, (i, ts, ir, depth) in enumerate(fr):
                last = k == len(fr) - 1 and not (cut_last and name == "walk-01")
                raw = RawFrame(
                    header=RawFrame.make_header("cam9", name, i, ts, last=last), ir=ir, depth=depth
                )
                if with_truth:
                    # truth first for odd frames: grouping must not depend on the order
                    msgs = [raw, _truth(raw)] if i % 2 == 0 else [_truth(raw), raw]
                else:
                    msgs = [raw]
                for m in msgs:
                    w.write(f"gaitflow/clinic/cam9/{m.STREAM}", m.encode(publish_ns=ts + 1))
                w.write("gaitflow/clinic/cam9/calstatus", b"\x93\x80\x80\x90")  # not replayed


def test_mcap_source_replays_raw_and_truth(session, tmp_path):
    _, data = session
    path = tmp_path / "rec.mcap"
    write_mcap(path, data, with_truth=True)
    out = list(grab(source="mcap", path=str(path)))
    assert len(out) == sum(len(idx) for idx in PROTOCOL.values())
    for g in out:
        assert [type(m) for m in g] == [RawFrame, GroundTruth]
        assert g[0].header.frame == g[1].header.frame and g[0].header.trial == g[1].header.trial
        assert g[0].header.camera == "cam0"  # re-stamped with the grab's camera id
    hdrs = [g[0].header for g in out]
    assert [h.trial for h in hdrs] == [n for n, idx in PROTOCOL.items() for _ in idx]
    assert [h.capture_ns for h in hdrs] == [
        T0 + i * PERIOD for idx in PROTOCOL.values() for i in idx
    ]
    assert [h.last for h in hdrs] == [False, False, True, False, True, False, False, False, True]
    assert out[4][0].ir.tobytes() == data["static"][1][2].tobytes()


def test_mcap_source_flags_a_cut_trial_and_selects(session, tmp_path):
    _, data = session
    path = tmp_path / "cut.mcap"
    write_mcap(path, {"walk-01": data["walk-01"]}, with_truth=False, cut_last=True)
    out = list(grab(source="mcap", path=str(path), camera="cam9", recordings="walk-01"))
    assert [(g[0].header.frame, g[0].header.last) for g in out] == [
        (0, False),
        (1, False),
        (3, False),
        (4, True),
    ]
    assert all(len(g) == 1 for g in out)
    assert list(grab(source="mcap", path=str(path), recordings="static")) == []


def test_mcap_source_bad_input(session, tmp_path):
    _, data = session
    with pytest.raises(InputError, match="recording not found"):
        grab(source="mcap", path=str(tmp_path / "none.mcap"))
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(InputError, match="not an MCAP file"):
        list(grab(source="mcap", path=str(bad)))
    # A corrupt payload on the raw channel is counted and skipped.
    path = tmp_path / "corrupt.mcap"
    with McapWriter(path) as w:
        i, ts, ir, depth = data["static"][0]
        raw = RawFrame(header=RawFrame.make_header("c", "static", i, ts), ir=ir, depth=depth)
        payload = raw.encode()
        w.write("gaitflow/clinic/c/raw", payload[: len(payload) // 2], ts, ts)
        w.write("gaitflow/clinic/c/raw", payload, ts + 1, ts + 1)
    src = grab(source="mcap", path=str(path))
    out = list(src)
    assert len(out) == 1 and out[0][0].header.last
    assert src.counters == {"bad_payload": 1}


def test_live_source_uses_driver(monkeypatch):
    # A fake camera library: three frames, then the device disappears.
    from test_drivers_fake import fake_realsense

    rs = fake_realsense()
    monkeypatch.setitem(sys.modules, "pyrealsense2", rs)
    out = list(grab(source="realsense", recordings="static", max_frames=2))
    assert [(g[0].header.trial, g[0].header.frame, g[0].header.last) for g in out] == [
        ("static", 0, False),
        ("static", 1, True),
    ]
    assert out[0][0].ir.shape == (480, 848)
    assert rs.calls[-1] == ("stop",)  # the camera was released when the source ended


# --------------------------------------------------------------------------- simulator


def test_sim_source_yields_raw_and_truth_deterministically():
    from gaitflow.sim import list_trials

    trial = list_trials()[0]
    params = dict(source="sim", trial=trial, seed=3, quick=True, recordings="static", max_frames=3)
    src = grab(camera="camS", **params)
    assert src.camera_doc is not None and src.camera_doc["width"] == 512
    out = list(src)
    assert len(out) == 3
    for raw, truth in out:
        assert isinstance(raw, RawFrame) and isinstance(truth, GroundTruth)
        assert raw.header.camera == truth.header.camera == "camS"
        assert (raw.header.trial, raw.header.frame) == (truth.header.trial, truth.header.frame)
        assert raw.ir.shape == (424, 512) and raw.depth.dtype == np.uint16
    assert [g[0].header.trial for g in out] == ["static"] * 3
    assert [g[0].header.last for g in out] == [False, False, True]
    assert [g[1].header.last for g in out] == [False, False, True]
    again = list(grab(camera="camS", **params))
    assert [g[0].ir.tobytes() for g in again] == [g[0].ir.tobytes() for g in out]
    assert [g[0].depth.tobytes() for g in again] == [g[0].depth.tobytes() for g in out]


def test_sim_source_rejects_unknown_trial():
    with pytest.raises(InputError, match="is not a bundled trial"):
        grab(source="sim", trial="nobody")
