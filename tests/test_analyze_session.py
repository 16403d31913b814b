"""``gaitflow analyze``: bad session folders, the same results inline and over the bus, and a
walk in which nobody is ever in view."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gaitflow.cli import main
from gaitflow.commands.analyze import NO_SUMMARY, analyze_session
from gaitflow.errors import InputError
from gaitflow.exports import cycles_csv, mot_text, trc_text, trial_arrays
from gaitflow.results import validation_errors
from gaitflow.session import SessionWriter
from gaitflow.sim import SimConfig, simulate_session

TRIAL = "btk_PiG_Motion-FlatFoot-Full"
WALK_FRAMES = 75  # 2.5 s: the subject walks into the view


def _frames(rec, ks):
    for k in ks:
        raw, _ = rec.frame(k, last=k == len(rec) - 1)
        yield raw.header.frame, raw.header.capture_ns, raw.ir, raw.depth


@pytest.mark.parametrize("missing", ["calibration", "static"])
def test_missing_recording_folder_is_named(tmp_path: Path, missing: str) -> None:
    ses = simulate_session(TRIAL, 0, SimConfig.quick())
    w = SessionWriter(tmp_path / "S", ses.camera_json)
    present = [n for n in ("calibration", "static") if n != missing]
    for name in (*present, "walk-01"):
        w.write_recording(name, _frames(ses.recordings[name], range(2)))
    with pytest.raises(InputError, match=f"missing recording folder {missing}/"):
        analyze_session(tmp_path / "S", tmp_path / "out", inline=True)
    assert main(["analyze", str(tmp_path / "S"), "--out", str(tmp_path / "o"), "--inline"]) == 2


@pytest.fixture(scope="module")
def tiny_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Calibration and static of a quick simulated session; walk-01 = the first 2.5 s of the
    walk; walk-02 = the empty walkway (the last calibration frames): nobody ever in view."""
    root = tmp_path_factory.mktemp("analyze") / "S01"
    ses = simulate_session(TRIAL, 0, SimConfig.quick())
    w = SessionWriter(root, ses.camera_json)
    cal = ses.recordings["calibration"]
    w.write_recording("calibration", _frames(cal, range(len(cal))))
    st = ses.recordings["static"]
    w.write_recording("static", _frames(st, range(len(st))))
    walk = ses.recordings["walk-01"]
    w.write_recording("walk-01", _frames(walk, range(WALK_FRAMES)))
    empty = [f for f in _frames(cal, range(len(cal) - 20, len(cal)))]
    t0 = empty[0][1]
    w.write_recording(
        "walk-02", ((k, 5_000_000_000 + ts - t0, ir, d) for k, (_, ts, ir, d) in enumerate(empty))
    )
    return root


@pytest.mark.slow
@pytest.mark.integration
def test_inline_and_bus_give_identical_results(tiny_session: Path, tmp_path: Path) -> None:
    a = analyze_session(tiny_session, tmp_path / "inline", inline=True)
    b = analyze_session(tiny_session, tmp_path / "bus", inline=False)
    assert [o.trial for o in a] == [o.trial for o in b] == ["walk-01", "walk-02"]
    for oa, ob in zip(a, b, strict=True):
        ja = json.loads(oa.json_path.read_text())
        jb = json.loads(ob.json_path.read_text())
        assert ja == jb, oa.trial
        assert validation_errors(ja) == []
        assert oa.html_path.exists() and "<svg" in oa.html_path.read_text()
    walk = json.loads(a[0].json_path.read_text())
    assert walk["session"] == "S01" and len(walk["frames"]) == WALK_FRAMES
    seen = sum(any(v is not None for v in f["markers"].values()) for f in walk["frames"])
    assert seen > WALK_FRAMES // 3
    # walk-02: nobody ever in view -> a valid, empty result with a warning, not a crash
    empty = json.loads(a[1].json_path.read_text())
    assert empty["events"] == [] and empty["spatiotemporal"]["L"]["stride_length_mm"] == []
    assert a[1].warnings and any(
        "never seen" in w or w == NO_SUMMARY or "no walking pass" in w for w in a[1].warnings
    )


@pytest.mark.slow
def test_analyze_files_a_session_in_the_patient_store(
    tiny_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--store``: the results under STORE/<camera.json subject.id>/<session>/, a session
    record beside them, and ``gaitflow progress`` reading them back."""
    subject = json.loads((tiny_session / "camera.json").read_text())["subject"]["id"]
    store = tmp_path / "clinic"
    argv = ["analyze", str(tiny_session), "--store", str(store), "--inline", "-q"]
    assert main([*argv, "--date", "2026-11-21", "--export", "c3d,trc,mot,csv"]) == 0
    folder = store / subject / "S01"
    # --export: the walk as C3D, TRC, MOT and CSV beside its JSON, in the walkway's lab frame
    walk_doc = json.loads((folder / "walk-01.json").read_text())
    trc = (folder / "walk-01.trc").read_text()
    assert trc == trc_text(trial_arrays(walk_doc), "walk-01.trc", "lab")
    assert (folder / "walk-01.c3d").stat().st_size > 10_000
    mot = (folder / "walk-01.mot").read_text()
    assert mot == mot_text(trial_arrays(walk_doc), "walk-01.mot")
    assert int(mot.split("\n")[2].removeprefix("nRows=")) > 100  # the 100 Hz knee
    csv_text = (folder / "walk-01.csv").read_text()
    assert csv_text == cycles_csv(walk_doc)
    assert len(csv_text.splitlines()) == 1 + len(walk_doc.get("cycles", []))
    # walk-02, nobody in view: its frames with every marker unseen
    rows = (folder / "walk-02.trc").read_text().split("\n")[6:-1]
    assert len(rows) == 20 and all(r.split("\t")[2:] == [""] * 60 for r in rows)
    record = json.loads((folder / "session.json").read_text())
    assert record["subject"] == subject and record["date"] == "2026-11-21"
    assert record["trials"] == ["walk-01", "walk-02"]
    walk = json.loads((folder / "walk-01.json").read_text())
    assert validation_errors(walk) == [] and walk["session"] == "S01"
    capsys.readouterr()
    assert main(["progress", str(store), subject]) == 0
    out = capsys.readouterr().out
    assert "2026-11-21" in out and "S01" in out
    assert (store / subject / "progress.html").exists()
    # --out and --store together, or --date without a store: refused, nothing run
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    assert main(["analyze", str(tiny_session), "--out", str(tmp_path / "o"), "--date", "x"]) == 2
    assert not (tmp_path / "o").exists()
