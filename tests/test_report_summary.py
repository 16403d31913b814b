"""The report's per-side summary: knee ROM from complete cycles, else from one-stride windows.

Conventions: a results document (``shared/spec/results.md``) built from literals; time s,
knee flexion deg, NaN (None) = unknown.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gaitflow.report import knee_windows, render_html, side_summary

PERIOD = 1.0  # s per stride: cadence 120 steps/min


def _doc(known_r: np.ndarray | None = None) -> dict:
    t = np.round(np.arange(0.0, 4.0, 0.01), 3)
    knee = 30.0 + 30.0 * np.sin(2 * np.pi * t / PERIOD)  # ROM 60 deg
    r = knee.copy()
    if known_r is not None:
        r[~known_r] = np.nan
    empty = {"step_length_mm": [], "stride_length_mm": [], "stance_s": [], "swing_s": []}
    return {
        "session": "S01",
        "trial": "walk-01",
        "camera_fps": 30.0,
        "frames": [],
        "events": [],
        "passes": [],
        "event_uncertainty_s": 1 / 60,
        "knee_flexion_deg": {
            "time_s": t.tolist(),
            "L": knee.tolist(),
            "R": [None if math.isnan(v) else v for v in r],
        },
        "spatiotemporal": {"L": empty, "R": empty, "cadence_steps_per_min": 120.0},
        # the left foot's strikes were seen, the right foot's not
        "cycles": [
            {"side": "L", "heel_strike_s": a, "next_heel_strike_s": a + PERIOD}
            for a in (0.25, 1.25, 2.25)
        ],
    }


def test_a_side_without_a_complete_cycle_gets_its_rom_from_stride_windows() -> None:
    summ = side_summary(_doc())
    assert summ["L"]["cycles"] == 3 and summ["L"]["rom_windows"] == 0
    assert summ["L"]["knee_rom_deg"] == pytest.approx(60.0, abs=0.1)
    assert summ["R"]["cycles"] == 0 and summ["R"]["rom_windows"] == 3
    assert summ["R"]["knee_rom_deg"] == pytest.approx(60.0, abs=0.1)
    assert summ["R"]["knee_peak_deg"] == pytest.approx(60.0, abs=0.1)


def test_stride_windows_skip_a_gap_and_need_the_window_known() -> None:
    t = np.arange(0.0, 4.0, 0.01)
    gap = (t > 1.2) & (t < 1.5)  # 30 % of the second window: it moves past the gap
    doc = _doc(~gap)
    w = knee_windows(doc, "R", PERIOD)
    assert w.shape == (3, 2)
    np.testing.assert_allclose(w, [[0.0, 60.0]] * 3, atol=0.1)
    half = _doc(np.arange(len(t)) % 2 == 0)  # every other sample: 50 % known
    assert len(knee_windows(half, "R", PERIOD)) == 0
    assert math.isnan(side_summary(half)["R"]["knee_rom_deg"])
    assert len(knee_windows(doc, "R", float("nan"))) == 0  # no cadence: no stride time


def test_the_report_says_where_a_knee_rom_comes_from() -> None:
    html = render_html(_doc())
    assert "Right knee ROM and peak: no complete gait cycle" in html
    assert "from 3 windows of one stride time" in html
    assert "Left knee ROM and peak" not in html
