"""``gaitflow bench gait``'s length and phase figures: Table IV's mean ± SD of the signed %
errors, and the mean absolute error beside them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gaitflow.bench.gait import TABLE_IV, cadence_error_pct, empty_trials, table_iv_figures
from gaitflow.cli import main


def test_table_iv_figures_are_the_signed_mean_and_sd_with_the_absolute_mean_apart() -> None:
    fig = table_iv_figures([2.0, -2.0, 1.0, float("nan")])
    assert fig["n"] == 3
    assert fig["mean"] == pytest.approx(1.0 / 3.0)
    assert fig["sd"] == pytest.approx(math.sqrt((25 + 49 + 4) / 9 / 2))
    assert fig["abs"] == pytest.approx(5.0 / 3.0)


def test_table_iv_figures_of_one_error_have_no_sd_and_of_none_no_mean() -> None:
    one = table_iv_figures([-1.5])
    assert (one["mean"], one["abs"], one["n"]) == (-1.5, 1.5, 1)
    assert math.isnan(one["sd"])
    none = table_iv_figures([])
    assert none["n"] == 0 and math.isnan(none["mean"]) and math.isnan(none["abs"])


def test_bench_gait_summarises_the_trials_signed_errors_beside_table_iv(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["bench", "gait", "--level", "markers", "--trials", "btk_PiG_Motion3_FF"]
    assert main([*argv, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    (trial,) = doc["trials"].values()
    s = doc["summary"]
    for key in TABLE_IV:
        errs = np.asarray(trial[key], dtype=float)
        assert errs.size == s[f"{key}_matched"] > 1
        assert s[f"{key}_mean_pct"] == pytest.approx(errs.mean())
        assert s[f"{key}_sd_pct"] == pytest.approx(errs.std(ddof=1))
        assert s[f"{key}_err_pct"] == pytest.approx(np.abs(errs).mean())
    assert main(argv) == 0
    text = capsys.readouterr().out
    for key, (mean, sd) in TABLE_IV.items():
        row = next(r for r in text.splitlines() if r.startswith(f"{key} error %, mean ± SD"))
        assert f"{s[f'{key}_mean_pct']:+.2f} ± {s[f'{key}_sd_pct']:.2f}" in row
        assert f"{mean:.2f} ± {sd:.2f}" in row
    # the walk's cadence against the truth's, signed
    assert math.isfinite(trial["cadence_err_pct"])
    assert s["cadence_err_pct"] == pytest.approx(abs(trial["cadence_err_pct"]))
    row = next(r for r in text.splitlines() if r.startswith("cadence error %, mean ± SD"))
    assert f"{trial['cadence_err_pct']:+.2f}" in row


def test_cadence_error_is_signed_and_missing_where_either_cadence_is() -> None:
    assert cadence_error_pct(90.0, 120.0) == pytest.approx(-25.0)
    assert cadence_error_pct(126.0, 120.0) == pytest.approx(5.0)
    for ours, true in ((None, 120.0), (120.0, None), (float("nan"), 120.0), (120.0, 0.0)):
        assert math.isnan(cadence_error_pct(ours, true))


def test_bench_gait_says_why_a_trial_gave_no_gait_events() -> None:
    # A set-up whose calibration has no usable floor (``low+far`` before calibrate placed
    # markers without floor depth; ``near+k4a``, two floor markers out of view) gives empty
    # results; the bench printed a row of dashes and nothing else.
    why = "no floor calibration: the calibration record says Replace Markers"
    per = {"walk-a": {"why_empty": [why]}, "walk-b": {"events": {}}, "walk-c": {"why_empty": []}}
    assert empty_trials(per) == [
        f"walk-a: no gait events: {why}",
        "walk-c: no gait events: no reason given",
    ]
