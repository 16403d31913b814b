"""``gaitflow bench mocap``'s figures over several trials: the pooled ones, and Tables II
and III's mean ± SD over trials."""

from __future__ import annotations

import math

import pytest

from gaitflow.bench import mocap


def _score(visible: int, detected: int, recalled: tuple[int, int, int]) -> mocap.Score:
    s = mocap.Score(visible=visible, detected=detected, frames=visible // 10)
    s.recalled = dict(zip(mocap.BETAS, recalled, strict=True))
    s.errors = [float(visible)]
    s.errors_by_site = {"KNE": [float(visible)]}
    s.add_ms("detect", 0.1 * visible)
    return s


def test_merged_scores_pool_the_trials_views() -> None:
    a, b = _score(100, 90, (80, 85, 90)), _score(300, 294, (270, 290, 294))
    pooled = mocap.summarise(mocap.merge_scores([a, b]))
    assert pooled["visible"] == 400 and pooled["frames"] == 40
    assert pooled["detected"] == pytest.approx(100.0 * 384 / 400)
    assert pooled["recall@0.5"] == pytest.approx(100.0 * 350 / 400)
    assert pooled["err_median_mm_by_site"]["KNE"] == pytest.approx(200.0)
    assert pooled["ms_detect_p50"] == pytest.approx(20.0)
    # the inputs are left as they were
    assert a.visible == 100 and a.errors == [100.0] and a.ms["detect"] == [10.0]


def test_trial_spread_is_the_mean_and_sd_of_each_trials_percentage() -> None:
    a, b = _score(100, 90, (80, 85, 90)), _score(300, 294, (270, 290, 294))
    spread = mocap.trial_spread([a, b, mocap.Score()])  # a trial with nothing visible: left out
    assert spread["detected_trial_mean"] == pytest.approx((90.0 + 98.0) / 2)
    assert spread["detected_trial_sd"] == pytest.approx(math.sqrt(2 * 4.0**2))
    assert spread["recall@0.5_trial_mean"] == pytest.approx((80.0 + 90.0) / 2)
    one = mocap.trial_spread([a])
    assert one["detected_trial_mean"] == pytest.approx(90.0)
    assert math.isnan(one["detected_trial_sd"])
