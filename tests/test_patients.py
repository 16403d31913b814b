"""The patient store and ``gaitflow progress``: sessions filed per subject, read back in visit
order, pooled into one row of figures per visit; unreadable files named, counted, left out.

Conventions: results documents (``shared/spec/results.md``) built from literals; lengths mm,
times s, knee flexion deg; NaN (null) = not measured.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from gaitflow.cli import main
from gaitflow.errors import InputError
from gaitflow.patients import (
    format_progress,
    load_subject,
    progress_table,
    render_progress_html,
    session_date,
    session_dir,
    session_figures,
    subject_of,
    write_manifest,
    write_progress_csv,
)
from gaitflow.report import write_report
from gaitflow.results import build_results, write_results

PERIOD = 1.0  # s per stride


def _doc(session: str, trial: str, step: float, rom: float, stance: float = 0.6) -> dict:
    """A trial whose left steps are ``step`` mm, right steps ``step - 40``, knee ROM ``rom``."""
    t = np.round(np.arange(0.0, 4.0, 0.01), 3)
    knee = 0.5 * rom + 0.5 * rom * np.sin(2 * np.pi * t / PERIOD)
    side = {
        "L": {
            "step_length_mm": [step, step + 10.0],
            "stride_length_mm": [2 * step - 40.0],
            "stance_s": [stance, stance],
            "swing_s": [PERIOD - stance] * 2,
        },
        "R": {
            "step_length_mm": [step - 40.0],
            "stride_length_mm": [2 * step - 30.0],
            "stance_s": [stance],
            "swing_s": [PERIOD - stance],
        },
    }
    cycles = [
        {"side": s, "heel_strike_s": a, "next_heel_strike_s": a + PERIOD}
        for s in ("L", "R")
        for a in (0.25, 1.25, 2.25)
    ]
    return build_results(
        session=session,
        trial=trial,
        camera_fps=30.0,
        frame_index=[],
        frame_time_s=np.zeros(0),
        positions=np.zeros((0, 20, 3)),
        pixels=np.zeros((0, 20, 2)),
        knee_time_s=t,
        knee_deg={"L": knee, "R": knee},
        events=[],
        spatiotemporal={**side, "cadence_steps_per_min": 120.0, "speed_m_s": step / 600.0},
        extra={"scope": "trial", "cycles": cycles, "passes": []},
    )


def _store_session(store: Path, subject: str, session: str, docs: list[dict], visit=None) -> Path:
    folder = session_dir(store, subject, session)
    for d in docs:
        write_results(d, folder / f"{d['trial']}.json")
        write_report(d, folder / f"{d['trial']}.html")
    write_manifest(folder, subject, session, visit, [d["trial"] for d in docs])
    return folder


def test_a_session_pools_its_walks_into_one_row_of_figures() -> None:
    a, b = _doc("S", "walk-01", 600.0, 40.0), _doc("S", "walk-02", 700.0, 50.0)
    fig = session_figures([a, b])
    assert fig["trials"] == 2 and fig["steps"] == 6
    # every left step of both walks: 600, 610, 700, 710
    assert fig["step_length_mm"]["L"] == pytest.approx(655.0)
    assert fig["step_length_mm"]["R"] == pytest.approx(610.0)
    assert fig["stride_length_mm"]["L"] == pytest.approx((1160.0 + 1360.0) / 2)
    assert fig["stance_pct"]["L"] == pytest.approx(60.0)
    assert fig["knee_rom_deg"]["R"] == pytest.approx(45.0, abs=0.2)
    assert fig["speed_m_s"] == pytest.approx((1.0 + 700.0 / 600.0) / 2, abs=1e-4)  # 4 decimals
    assert fig["step_symmetry_pct"] == pytest.approx(100.0 * 45.0 / 632.5)


def test_a_session_without_steps_gives_nan_not_an_error() -> None:
    empty = _doc("S", "walk-01", 600.0, 40.0)
    for s in ("L", "R"):
        for k in empty["spatiotemporal"][s]:
            empty["spatiotemporal"][s][k] = []
    fig = session_figures([empty])
    assert fig["steps"] == 0
    assert math.isnan(fig["step_length_mm"]["L"]) and math.isnan(fig["stance_pct"]["R"])
    assert math.isnan(fig["step_symmetry_pct"])


def test_sessions_are_read_back_in_visit_order(tmp_path: Path) -> None:
    _store_session(tmp_path, "S01", "S01-2026-12-05", [_doc("x", "walk-01", 640.0, 50.0)],
                   "2026-12-05")  # fmt: skip
    _store_session(tmp_path, "S01", "S01-2026-11-21", [_doc("x", "walk-01", 600.0, 40.0)],
                   "2026-11-21")  # fmt: skip
    _store_session(tmp_path, "S01", "extra-visit", [_doc("x", "walk-01", 660.0, 55.0)])
    _store_session(tmp_path, "S02", "S02-2026-11-22", [_doc("x", "walk-01", 500.0, 30.0)])
    sessions, errors = load_subject(tmp_path, "S01")
    assert errors == []
    assert [s.session for s in sessions] == ["S01-2026-11-21", "S01-2026-12-05", "extra-visit"]
    assert [round(session_figures(s.docs)["step_length_mm"]["L"]) for s in sessions] == [
        605,
        645,
        665,
    ]
    assert all(len(s.reports) == 1 for s in sessions)
    header, rows = progress_table(sessions)
    assert header == ["figure", "2026-11-21", "2026-12-05", "extra-visit", "change"]
    step_l = next(r for r in rows if r[0] == "step length L, mm")
    assert step_l[2] == pytest.approx([605.0, 645.0, 665.0]) and step_l[3] == pytest.approx(60.0)
    assert "+60" in format_progress("S01", sessions)
    text = write_progress_csv(sessions, tmp_path / "p.csv").read_text()
    rows = list(csv.DictReader(text.splitlines()))
    assert [r["date"] for r in rows] == ["2026-11-21", "2026-12-05", ""]
    assert [float(r["step_length_mm_L"]) for r in rows] == [605.0, 645.0, 665.0]
    assert rows[0]["speed_m_s"] and rows[0]["trials"] == "1"


def test_an_unreadable_file_is_named_counted_and_the_rest_shown(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = _store_session(tmp_path, "S01", "S01-2026-11-21", [_doc("x", "walk-01", 600.0, 40.0),
                          _doc("x", "walk-02", 620.0, 40.0)], "2026-11-21")  # fmt: skip
    (good / "walk-02.json").write_text('{"format": "gaitflow.trial-results", "vers')
    broken = session_dir(tmp_path, "S01", "S01-2026-12-05")
    broken.mkdir(parents=True)
    (broken / "session.json").write_text(json.dumps({"format": "gaitflow.session-record"}))
    odd = session_dir(tmp_path, "S01", "S01-2026-12-19")
    odd.mkdir(parents=True)
    record = {
        "format": "gaitflow.session-record",
        "version": 1,
        "session": "x",
        "analysed_at": "2026-12-19T10:00:00+00:00",
        "trials": ["../../S02/walk-01"],
    }
    (odd / "session.json").write_text(json.dumps(record))
    sessions, errors = load_subject(tmp_path, "S01")
    assert [s.session for s in sessions] == ["S01-2026-11-21"]
    assert len(sessions[0].docs) == 1
    assert len(errors) == 3
    named = " ".join(str(e) for e in errors)
    assert "walk-02.json" in named and "S01-2026-12-05/session.json" in named
    assert "not a list of trial names" in named  # nothing read from outside the session

    assert main(["progress", str(tmp_path), "S01"]) == 0
    out = capsys.readouterr()
    assert "S01-2026-11-21" in out.out and "3 file(s) left out" in out.err
    assert "walk-02.json" in out.err
    page = (tmp_path / "S01" / "progress.html").read_text()
    assert "left out" in page and "walk-02.json" in page


def test_the_progress_page_opens_offline_and_links_the_trial_reports(tmp_path: Path) -> None:
    for visit, step in (("2026-11-21", 600.0), ("2026-12-05", 650.0)):
        _store_session(tmp_path, "S01", f"S01-{visit}", [_doc("x", "walk-01", step, 45.0)], visit)
    sessions, errors = load_subject(tmp_path, "S01")
    base = (tmp_path / "S01").resolve()
    page = render_progress_html("S01", sessions, errors, base)
    assert page.count("<svg") == 7  # one chart per figure
    # no script, style sheet, image or font fetched: every src/href is a local file or a
    # reference inside the page (the SVG's own marker definitions)
    for url in re.findall(r"""(?:src|href)=['"]([^'"#][^'"]*)['"]""", page):
        assert not url.startswith(("http:", "https:", "//")), url
        assert (base / url).exists(), url
    assert "S01-2026-11-21/walk-01.html" in page and "<script" not in page


def test_the_subject_comes_from_camera_json_or_the_flag_and_must_be_a_folder_name() -> None:
    assert subject_of({"subject": {"id": "s-3f9a1c2b7d"}}) == "s-3f9a1c2b7d"
    assert subject_of({"subject": {"id": "S01"}}, "S07") == "S07"
    with pytest.raises(InputError, match=r"camera\.json.*no subject\.id"):
        subject_of({"model": "kinect-v2"})
    for bad in ("../S01", "S 01", ".hidden", "a/b"):
        with pytest.raises(InputError, match="cannot name a store folder"):
            subject_of({"subject": {"id": bad}})


def test_the_visit_date_is_given_or_read_from_the_session_name() -> None:
    assert session_date("S01-2026-11-21") == "2026-11-21"
    assert session_date("S01_visit3") is None
    assert session_date("S01-2026-13-40-2026-11-21") == "2026-11-21"  # the first real date
    assert session_date("S01-2026-11-21", "2026-12-01") == "2026-12-01"
    with pytest.raises(InputError, match=r"--date.*not a date"):
        session_date("S01", "21/11/2026")


def test_a_missing_subject_is_an_error_that_names_it(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no stored sessions for subject 'S09'"):
        load_subject(tmp_path, "S09")
    assert main(["progress", str(tmp_path), "S09"]) == 2
