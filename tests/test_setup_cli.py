"""``gaitflow setup``: the operator's console (status lines, a recorded calibration, the
live stream from an in-memory bus)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
from gaitflow.bus import FakeBus, stream_key
from gaitflow.schemas.calibration import CalibrationRecord, CalibrationStatus

from gaitflow.cli import main
from gaitflow.commands.setup import ADVICE, StatusConsole, listen


def _status(frame: int, status: str, found: int, message: str = "") -> CalibrationStatus:
    hdr = CalibrationStatus.make_header("cam0", "calibration", frame, frame * 33_000_000)
    return CalibrationStatus(
        header=hdr,
        floor_pixels=np.zeros((found, 2)),
        status=status,
        markers_found=found,
        message=message,
    )


def _record(status: str, message: str = "") -> CalibrationRecord:
    hdr = CalibrationRecord.make_header("cam0", "calibration", 130, 130 * 33_000_000, last=True)
    return CalibrationRecord(
        header=hdr,
        floor_pixels=np.zeros((4, 2)),
        floor_points=np.zeros((4, 3)),
        floor_plane=np.array([0.0, -1.0, 0.0, 800.0]),
        start=np.zeros(3),
        end=np.array([4000.0, 0.0, 0.0]),
        status=status,
        markers_found=4,
        length_mm=4000.0,
        tilt_deg=-1.5,
        pan_deg=5.9,
        offset_mm=296.0,
        plane_rms_mm=0.5,
        message=message,
    )


def test_one_line_per_change_of_advice() -> None:
    c = StatusConsole(4)
    lines = [
        c.status_line(_status(0, "Uninitialized", 0)),
        c.status_line(_status(1, "Uninitialized", 0)),
        c.status_line(_status(2, "Uninitialized", 1)),
        c.status_line(_status(3, "Move Right", 4, "quad centre is +309 mm off; move right")),
        # the numbers move by a few mm from frame to frame: no new line
        c.status_line(_status(4, "Move Right", 4, "quad centre is +304 mm off; move right")),
        c.status_line(_status(5, "Done", 4, "calibration done")),
    ]
    assert lines[1] is None and lines[4] is None
    assert lines[0] == f"[cam0] 0/4 floor markers  Uninitialized: {ADVICE['Uninitialized']}"
    assert lines[2].startswith("[cam0] 1/4 floor markers  Uninitialized")
    move = "Move Right: quad centre is +309 mm off; move right"
    assert lines[3] == f"[cam0] 4/4 floor markers  {move}"
    assert lines[5] == "[cam0] 4/4 floor markers  Done: calibration done"


def test_the_outcome_says_usable_and_gives_the_pose_or_what_went_wrong() -> None:
    done = StatusConsole.outcome_lines(_record("Done"))
    assert done[0] == (
        "[cam0] calibration Done: usable for analysis; 4 floor markers, walking line 4.00 m"
    )
    assert "tilt -1.5 deg, pan +5.9 deg, walkway centre +296 mm" in done[1]
    bad = StatusConsole.outcome_lines(_record("Replace Markers", "marker 3 is 41 mm off"))
    assert bad == ["[cam0] calibration Replace Markers: marker 3 is 41 mm off"]


def test_a_recorded_calibration_is_checked(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from gaitflow.session import SessionWriter
    from gaitflow.sim import simulate_session
    from gaitflow.sim.variants import sim_config

    ses = simulate_session("c3dorg_s00_vicon_CGM24", 0, sim_config("base"))
    root = tmp_path / "S01"
    SessionWriter(root, ses.camera_json).write_recording(
        "calibration", ses.recordings["calibration"].frames()
    )
    assert main(["setup", "--session", str(root)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split("  ")[0] for line in out[:4]] == [
        f"[cam0] {k}/4 floor markers" for k in range(4)
    ]
    assert out[-3].startswith("[cam0] calibration Done: usable for analysis; 4 floor markers")
    # no calibration in the folder: a one-line error naming it
    empty = tmp_path / "S02"
    SessionWriter(empty, ses.camera_json)
    assert main(["setup", "--session", str(empty)]) == 2
    assert "no calibration/ recording" in capsys.readouterr().err


def test_live_lines_from_the_bus_until_the_record(capsys: pytest.CaptureFixture) -> None:
    bus = FakeBus()
    cam = bus.connected()
    site = bus.site
    lines: list[str] = []

    def camera() -> None:
        key = stream_key(site, "cam0", "calstatus")
        cam.put(key, _status(0, "Uninitialized", 0).encode())
        cam.put(key, b"\x00not msgpack")  # counted and skipped; listening goes on
        cam.put(key, _status(1, "Uninitialized", 0).encode())
        cam.put(key, _status(2, "Tilt Down", 4, "optical axis is +6.0 deg; tilt down").encode())
        # another camera's status is not ours
        cam.put(stream_key(site, "cam1", "calstatus"), _status(2, "Pan Left", 4).encode())
        cam.put(stream_key(site, "cam0", "calibration"), _record("Done").encode())

    started = threading.Timer(0.2, camera)
    started.start()
    rc = listen(bus, "cam0", seconds=10.0, out=lines.append)
    started.join()
    assert rc == 0
    assert lines[0].endswith(ADVICE["Uninitialized"])
    assert lines[1] == "[cam0] 4/4 floor markers  Tilt Down: optical axis is +6.0 deg; tilt down"
    assert lines[2].startswith("[cam0] calibration Done")
    assert not any("cam1" in line or "Pan Left" in line for line in lines)
    assert "1 malformed messages skipped" in capsys.readouterr().err
    # a record that is not Done: exit status 1
    bus2 = FakeBus()
    threading.Timer(
        0.2,
        lambda: bus2.connected().put(
            stream_key(bus2.site, "cam0", "calibration"), _record("Replace Markers").encode()
        ),
    ).start()
    assert listen(bus2, "cam0", seconds=10.0, out=lines.append) == 1
