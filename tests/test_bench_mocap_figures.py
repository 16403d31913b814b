"""``gaitflow bench mocap``'s figures over several trials: the pooled ones, and Tables II
and III's mean ± SD over trials."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gaitflow.schemas import GroundTruth, Markers3D

from gaitflow.bench import mocap
from gaitflow.markers import MARKER_NAMES


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


def _leg_positions(z_left: float, z_right: float) -> np.ndarray:
    pos = np.zeros((len(MARKER_NAMES), 3))
    for i, name in enumerate(MARKER_NAMES):
        pos[i] = [10.0 * i, 0.0, z_left if name.startswith("L_") else z_right]
    return pos


@pytest.mark.parametrize(("z_left", "z_right", "near"), [(2500.0, 2700.0, "L"), (2700, 2500, "R")])
def test_the_sagittal_model_is_the_near_side_and_the_far_heel_and_toe(
    z_left: float, z_right: float, near: str
) -> None:
    got = mocap.sagittal_model_markers(_leg_positions(z_left, z_right))
    want = {n for n in MARKER_NAMES if n[0] == near} | {
        n for n in MARKER_NAMES if n.endswith(("_HEE", "_TOE"))
    }
    assert {n for n, g in zip(MARKER_NAMES, got, strict=True) if g} == want
    assert got.sum() == 12


def test_the_sagittal_model_is_empty_without_the_legs() -> None:
    pos = _leg_positions(2500.0, 2700.0)
    pos[[MARKER_NAMES.index(f"R_{s}") for s in mocap.NEAR_SIDE_SITES]] = np.nan
    assert not mocap.sagittal_model_markers(pos).any()


def literal_frame(
    pixel: np.ndarray,
    visible: np.ndarray,
    position: np.ndarray,
    centroid: np.ndarray,
    located: np.ndarray,
) -> tuple[Markers3D, GroundTruth]:
    """A located frame (blob centroids (K, 2), positions (K, 3, 3) under the three modes)
    and its truth (pixels (20, 2), visible flags, true centres (20, 3))."""
    h = GroundTruth.make_header("cam0", "walk-01", 0, 0)
    gt = GroundTruth(
        header=h,
        position=position,
        pixel=pixel,
        visible=visible,
        occluded=np.zeros(len(MARKER_NAMES), bool),
        knee_flexion=np.zeros(2),
    )
    k = len(centroid)
    mk = Markers3D.follow(
        h,
        centroid=centroid,
        marker_radius=np.ones(k),
        region_radius=np.ones(k),
        depth=located[:, :, 2],
        position=located,
    )
    return mk, gt


def test_bench_scoring_on_literal_messages() -> None:
    truth_px = np.full((20, 2), np.nan)
    truth_px[:3] = [[10.0, 10.0], [50.0, 50.0], [52.0, 50.0]]  # the last two merge
    visible = np.zeros(20, bool)
    visible[:3] = True
    pos = np.full((20, 3), np.nan)
    pos[:3] = [[0, 0, 2500.0], [100, 0, 2500.0], [105, 0, 2500.0]]
    cen = np.array([[10.3, 10.0], [51.0, 50.0], [200.0, 200.0]])
    p3 = np.zeros((3, 3, 3))
    p3[0, :] = [0, 0, 2504.0]
    p3[1, :] = [100, 0, 2510.0]
    mk, gt = literal_frame(truth_px, visible, pos, cen, p3)
    s = mocap.Score()
    mocap.score_frame(s, mk, gt, gate=4.0)
    r = mocap.summarise(s)
    assert r["visible"] == 3
    assert r["detected"] == pytest.approx(200 / 3)
    assert r["recall@0.5"] == pytest.approx(100 / 3)
    assert r["recall@1.5"] == pytest.approx(200 / 3)
    assert r["missed_merged"] == pytest.approx(100 / 3)
    assert r["false_blobs_per_frame"] == 1
    assert sorted(s.errors) == pytest.approx([4.0, 10.0])
    assert r["visible_12"] == 0  # no leg markers known: no near side


def test_the_twelve_marker_figures_count_only_the_model_markers() -> None:
    pos = _leg_positions(2500.0, 2700.0)  # left side nearer
    idx = {n: MARKER_NAMES.index(n) for n in ("L_KNE", "R_KNE", "R_HEE", "L_ASI")}
    pixel = np.full((len(MARKER_NAMES), 2), np.nan)
    visible = np.zeros(len(MARKER_NAMES), bool)
    for j, i in enumerate(idx.values()):
        pixel[i] = [20.0 + 40.0 * j, 100.0]
        visible[i] = True
    # blobs at the near knee (0.2 px off) and the far heel (1.0 px off); the far knee,
    # which is not in the model, and the near ASI are missed
    cen = np.array([pixel[idx["L_KNE"]] + [0.2, 0.0], pixel[idx["R_HEE"]] + [0.0, 1.0]])
    mk, gt = literal_frame(pixel, visible, pos, cen, np.zeros((2, 3, 3)))
    s = mocap.Score()
    mocap.score_frame(s, mk, gt, gate=4.0)
    r = mocap.summarise(s)
    assert (r["visible"], r["visible_12"]) == (4, 3)
    assert r["detected"] == pytest.approx(50.0)
    assert r["detected_12"] == pytest.approx(200 / 3)
    assert r["recall@0.5_12"] == pytest.approx(100 / 3)
    assert r["recall@1.5_12"] == pytest.approx(200 / 3)
    spread = mocap.trial_spread([s, mocap.Score(visible=1)])  # a trial without model markers
    assert spread["detected_12_trial_mean"] == pytest.approx(200 / 3)
    assert math.isnan(spread["detected_12_trial_sd"])


def test_the_twelve_marker_3d_error_leaves_out_the_far_leg() -> None:
    pos = _leg_positions(2500.0, 2700.0)  # left side nearer: the right knee is not in the model
    near, far = MARKER_NAMES.index("L_KNE"), MARKER_NAMES.index("R_KNE")
    pixel = np.full((len(MARKER_NAMES), 2), np.nan)
    visible = np.zeros(len(MARKER_NAMES), bool)
    pixel[[near, far]] = [[20.0, 100.0], [60.0, 100.0]]
    visible[[near, far]] = True
    # both knees found and located, the near one 3 mm too far, the far one 40 mm
    located = np.zeros((2, 3, 3))
    located[0, :] = pos[near] + [0.0, 0.0, 3.0]
    located[1, :] = pos[far] + [0.0, 0.0, 40.0]
    mk, gt = literal_frame(pixel, visible, pos, pixel[[near, far]], located)
    s = mocap.Score()
    mocap.score_frame(s, mk, gt, gate=4.0)
    r = mocap.summarise(s)
    assert sorted(s.errors) == pytest.approx([3.0, 40.0])
    assert r["err_median_mm"] == pytest.approx(21.5)
    assert r["err_median_mm_12"] == pytest.approx(3.0)
    assert r["err_p95_mm_12"] == pytest.approx(3.0)
    pooled = mocap.summarise(mocap.merge_scores([s, s]))
    assert pooled["err_median_mm_12"] == pytest.approx(3.0)
