"""Alg. 1 (adaptive threshold) and Alg. 2 (blobs) on small literal frames."""

from __future__ import annotations

import functools
import time

import cv2
import numpy as np
import pytest
from gaitflow.schemas import Blobs, CleanFrame
from gaitflow.stages import detect


def disc(img: np.ndarray, u0: float, v0: float, radius: float, gain: float, ss: int = 8) -> None:
    """Add a supersampled disc of ``radius`` px at (u0, v0), amplitude ``gain``, in place."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    h, w = img.shape
    for r in range(max(int(v0 - radius) - 1, 0), min(int(v0 + radius) + 2, h)):
        for c in range(max(int(u0 - radius) - 1, 0), min(int(u0 + radius) + 2, w)):
            yy, xx = np.meshgrid(r + o, c + o, indexing="ij")
            img[r, c] += gain * np.mean((xx - u0) ** 2 + (yy - v0) ** 2 <= radius * radius)


def frame(shape=(120, 160), bg=800.0, noise=20.0, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(bg, noise, shape)


def u16(img: np.ndarray) -> np.ndarray:
    return np.clip(img, 0, 65535).astype(np.uint16)


def params(**kw):
    return detect.PARAMS.resolve(kw)


def clean_msg(
    ir: np.ndarray, trial: str = "walk-01", idx: int = 0, camera: str = "cam0"
) -> CleanFrame:
    return CleanFrame(
        header=CleanFrame.make_header(camera, trial, idx, idx * 33_000_000),
        ir=ir,
        depth=np.full(ir.shape, 2500, np.uint16),
        mask=np.zeros(ir.shape, np.uint8),
    )


@pytest.mark.parametrize("u0, v0", [(60.37, 40.81), (80.5, 61.25), (101.13, 70.66)])
def test_centroid_of_subpixel_disc_within_005px(u0: float, v0: float) -> None:
    img = frame(noise=0.0)
    disc(img, u0, v0, 2.6, 40000.0)
    # The optional refinement (off by default): the rim of partly covered pixels.
    det = detect.detect_frame(u16(img), 12000.0, 2.0, (), params(n=1, refine=True))
    assert det.blobs.count == 1
    err = np.hypot(det.centroid[0, 0] - u0, det.centroid[0, 1] - v0)
    assert err < 0.05, (det.centroid, u0, v0)


def test_alg2_weighted_centroid_of_gaussian_blob() -> None:
    # Alg. 2 alone (no refinement): weights P - e_d on a symmetric profile are unbiased.
    u0, v0 = 70.3, 50.7
    rr, cc = np.mgrid[0:100, 0:140]
    img = 500.0 + 50000.0 * np.exp(-((cc - u0) ** 2 + (rr - v0) ** 2) / (2 * 1.5**2))
    roi = detect.compact_roi(u16(img), 10000.0)
    c = detect.components(roi, 10000.0)
    assert c.count == 1
    assert np.hypot(c.centroid[0, 0] - u0, c.centroid[0, 1] - v0) < 0.05
    # r_r is the extent (max distance), r_m the weighted mean distance: r_m < r_r.
    assert 0 < c.marker_radius[0] < c.region_radius[0]


def test_saturated_marker_refinement_beats_flat_top() -> None:
    # A flat-topped (saturated) marker: refinement uses the partly covered edge pixels.
    rng = np.random.default_rng(3)
    errs = {True: [], False: []}
    for _ in range(12):
        u0, v0 = 60 + rng.random(), 50 + rng.random()
        img = frame(noise=0.0)
        disc(img, u0, v0, 2.2, 3 * 65535.0)
        for refine in (True, False):
            det = detect.detect_frame(u16(img), 60000.0, 2.0, (), params(n=1, refine=refine))
            errs[refine].append(np.hypot(*(det.centroid[0] - (u0, v0))))
    assert np.mean(errs[True]) < np.mean(errs[False])
    assert max(errs[True]) < 0.3


def markers_and_noise(seed: int = 1) -> tuple[np.ndarray, list[tuple[float, float]]]:
    rng = np.random.default_rng(seed)
    img = frame((200, 240), seed=seed)
    pts = []
    for k in range(12):
        u, v = 30 + (k % 4) * 55 + rng.random(), 30 + (k // 4) * 60 + rng.random()
        disc(img, u, v, 2.0 + rng.random(), 2 * 65535.0)
        pts.append((u, v))
    for k in range(5):  # dim, small noise blobs: reflections off clothing
        disc(img, 50 + k * 40 + rng.random(), 185 + rng.random(), 1.3, 9000.0)
    return u16(img), pts


def test_alg1_converges_to_n_blobs_with_noise_blobs() -> None:
    ir, pts = markers_and_noise()
    # w below the noise blobs: f > n at first, step 5 raises e_d until only markers remain.
    roi = detect.compact_roi(ir, 2000.0)
    assert detect.components(roi, 2000.0).count == 17
    det = detect.detect_frame(ir, 2000.0, 2.5, (), params(n=12))
    assert det.blobs.count == 12
    assert det.threshold > 2000.0
    assert 1 <= det.iterations <= 10
    got = det.centroid
    for u, v in pts:
        assert np.min(np.hypot(got[:, 0] - u, got[:, 1] - v)) < 0.5


def test_alg1_history_picks_threshold_closest_to_n() -> None:
    ir, _ = markers_and_noise()
    hist = (
        detect.HistoryEntry(2000.0, 60000.0, 3.0),  # 17 blobs
        detect.HistoryEntry(30000.0, 60000.0, 3.0),  # 12 blobs
        detect.HistoryEntry(2500.0, 60000.0, 3.0),  # 17 blobs, most recent
    )
    det = detect.detect_frame(ir, 2000.0, 2.5, hist, params(n=12))
    assert det.threshold == 30000.0
    assert det.iterations == 0
    assert det.blobs.count == 12


def test_alg1_iteration_cap_bounds_work() -> None:
    ir, _ = markers_and_noise()
    det = detect.detect_frame(ir, 2000.0, 2.5, (), params(n=3, max_iterations=1))
    assert det.iterations == 1


def test_static_method_uses_fixed_threshold() -> None:
    ir, _ = markers_and_noise()
    st = detect.init(params(method="static", static_threshold=2000.0))
    _, (out,) = detect.step(st, {"clean": clean_msg(ir)})
    assert isinstance(out, Blobs)
    assert out.threshold == 2000.0 and out.iterations == 0 and out.method == "static"
    assert out.centroid.shape == (17, 2)


@pytest.mark.parametrize("seed", range(6))
def test_roi_components_match_full_frame(seed: int) -> None:
    rng = np.random.default_rng(seed)
    img = frame((97, 131), seed=seed)
    for _ in range(rng.integers(1, 30)):
        u, v = rng.uniform(2, 128), rng.uniform(2, 94)
        disc(img, u, v, rng.uniform(0.6, 5), rng.uniform(3e3, 9e4))
    ir = u16(img)
    level = 1500.0
    roi = detect.compact_roi(ir, level)
    for e in (level, 5000.0, 30000.0):
        c = detect.components(roi, e, min_area=1)
        n, _, stats, _ = cv2.connectedComponentsWithStats((ir > e).astype(np.uint8), 8)
        assert c.count == n - 1
        assert sorted(c.area.tolist()) == sorted(stats[1:, 4].tolist())


def test_calibration_record_sets_w_and_r_b(flat_record) -> None:
    ir, _ = markers_and_noise()
    cal = flat_record(2000.0, frame=9)
    st = detect.init(params())
    st, (out,) = detect.step(st, {"clean": clean_msg(ir), "calibration": cal})
    cs = st.cameras["cam0"]
    assert (cs.w, cs.r_b) == (2000.0, 2.5)
    assert out.centroid.shape[0] == 12
    # Without a record, w and r_b come from the image and detection still works.
    st2, (out2,) = detect.step(detect.init(params()), {"clean": clean_msg(ir)})
    assert np.isfinite(st2.cameras["cam0"].w) and st2.cameras["cam0"].r_b > 0
    assert out2.centroid.shape[0] == 12


def test_history_is_per_trial_and_bounded() -> None:
    ir, _ = markers_and_noise()
    st = detect.init(params(b=3))
    for k in range(5):
        st, _ = detect.step(st, {"clean": clean_msg(ir, idx=k)})
    assert len(st.cameras["cam0"].history) == 3
    st, _ = detect.step(st, {"clean": clean_msg(ir, trial="walk-02")})
    assert len(st.cameras["cam0"].history) == 1


def _timed_step(ir: np.ndarray) -> tuple[Blobs, float]:
    st = detect.init(params())
    t = time.perf_counter()
    _, (out,) = detect.step(st, {"clean": clean_msg(ir)})
    return out, time.perf_counter() - t


def test_all_zero_frame_gives_no_blobs() -> None:
    out, dt = _timed_step(np.zeros((424, 512), np.uint16))
    assert out.centroid.shape == (0, 2) and out.status == "empty"
    assert dt < 2.0


def test_saturated_frame_is_rejected_not_a_marker() -> None:
    out, dt = _timed_step(np.full((424, 512), 65535, np.uint16))
    assert out.centroid.shape == (0, 2)
    assert out.status == "empty" and out.rejected >= 1
    assert dt < 2.0


def test_frame_with_300_blobs_is_bounded() -> None:
    img = np.full((424, 512), 500.0)
    rr, cc = np.mgrid[0:20, 0:15]
    ys, xs = 10 + rr.ravel() * 20, 10 + cc.ravel() * 33
    for y, x in zip(ys, xs, strict=True):
        img[y - 1 : y + 2, x - 1 : x + 2] = 65535
    out, dt = _timed_step(u16(img))
    assert out.status == "too-many"
    assert out.centroid.shape == (64, 2)  # max_blobs
    assert dt < 2.0


# Optional splitting of blobs shaped like two merged markers (``split_merged``).


def scene(pair_gap: float) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Four single markers and one pair ``pair_gap`` px apart (centre to centre)."""
    img = frame(noise=10.0, seed=3)
    singles = [(20.3, 20.6), (60.7, 25.2), (120.1, 30.4), (40.5, 90.9)]
    for u, v in singles:
        disc(img, u, v, 2.5, 60000.0)
    pair = [(100.0, 80.0), (100.0 + pair_gap, 80.4)]
    for u, v in pair:
        disc(img, u, v, 2.5, 60000.0)
    return u16(img), singles + pair


def only(name: str, on: bool = True) -> dict[str, bool]:
    """The detect options with splitter ``name`` on (or off) and the other two off: each
    test below is about one splitter."""
    return {s: on and s == name for s in detect.SPLITTERS}


def run(img: np.ndarray, split: bool) -> detect.Detection:
    p = detect.PARAMS.resolve({"n": 6, **only("split_merged", split)})
    return detect.detect_frame(img, 12000.0, 2.5, (), p)


def nearest(cen: np.ndarray, pts: list[tuple[float, float]], axis: int = 0) -> np.ndarray:
    """Distance from each point to its nearest centroid (axis 0), or from each centroid to
    its nearest point (axis 1)."""
    t = np.array(pts)
    return np.hypot(cen[:, None, 0] - t[None, :, 0], cen[:, None, 1] - t[None, :, 1]).min(axis)


def test_merged_pair_is_split_into_two_blobs_near_each_marker() -> None:
    img, truth = scene(4.2)
    off = run(img, False)
    assert off.blobs.count == 5  # the pair is one blob
    on = run(img, True)
    assert on.blobs.count == 6
    assert on.centroid.shape == (6, 2)
    err = nearest(on.centroid, truth)
    assert err.max() < 0.6, err
    # The single markers keep their Alg. 2 centroids exactly.
    single_off = off.centroid[nearest(off.centroid, truth[:4], axis=1) < 0.5]
    assert len(single_off) == 4
    for c in single_off:
        assert np.min(np.hypot(*(on.centroid - c).T)) == 0.0


def test_separate_markers_are_not_split() -> None:
    img, _ = scene(9.0)  # the pair does not touch: six round blobs
    on = run(img, True)
    off = run(img, False)
    assert on.blobs.count == off.blobs.count == 6
    np.testing.assert_array_equal(on.centroid, off.centroid)


def streak_scene(length: float) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Four single markers and one marker blurred along u over ``length`` px (saturated:
    one flat stadium, as two touching discs would be)."""
    img = frame(noise=10.0, seed=3)
    singles = [(20.3, 20.6), (60.7, 25.2), (120.1, 30.4), (40.5, 90.9)]
    for u, v in singles:
        disc(img, u, v, 2.5, 60000.0)
    for k in range(24):
        disc(img, 100.0 - length / 2 + length * k / 23, 80.2, 2.5, 30000.0)
    return u16(img), singles


def previous_record(points: list[tuple[float, float]]) -> np.ndarray:
    return np.array([[u, v, 20.0, 20.0, 3.0] for u, v in points])


@pytest.mark.parametrize("length", [5.0, 7.0, 9.0])
def test_a_blurred_marker_is_not_split_when_its_motion_draws_the_streak(length: float) -> None:
    img, singles = streak_scene(length)
    p = detect.PARAMS.resolve({"n": 5, **only("split_merged")})
    alone = detect.detect_frame(img, 12000.0, 2.5, (), p)
    assert alone.blobs.count == 6  # in one frame the streak looks like two merged markers
    # the frame before: the marker 1.25 streak lengths back along u (an exposure of 0.8 of
    # the frame interval), the others still
    moved = previous_record([*singles, (100.0 - 1.25 * length, 80.2)])
    det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=moved)
    assert det.blobs.count == 5
    # moving across its streak, or not seen in the frame before: the streak is unexplained
    across = previous_record([*singles, (100.0, 80.2 - 1.25 * length)])
    assert detect.detect_frame(img, 12000.0, 2.5, (), p, previous=across).blobs.count == 6
    others = previous_record(singles)
    assert detect.detect_frame(img, 12000.0, 2.5, (), p, previous=others).blobs.count == 6


def test_a_streak_whose_previous_blob_went_to_a_nearer_blob_is_not_split() -> None:
    # Three markers in a row along u, moving 12 px a frame: nearest first, the frame
    # before's second and third markers match this frame's first and second, and its first
    # lies 36 px from this frame's third, past the gate. The third, blurred into a 7 px
    # streak, is matched to nothing though blobs of the frame before lie 12 px from it: its
    # motion is unknown, so its streak is not read as two markers.
    img, singles = streak_scene(7.0)  # the streak is centred at (100.0, 80.2)
    ahead = [(76.0, 80.2), (88.0, 80.2)]
    raw = img.astype(np.float64)
    for u, v in ahead:
        disc(raw, u, v, 2.5, 60000.0)
    img = u16(raw)
    p = detect.PARAMS.resolve({"n": 7, **only("split_merged")})
    assert detect.detect_frame(img, 12000.0, 2.5, (), p).blobs.count == 8  # one frame: split
    before = previous_record([*singles, (64.0, 80.2), *ahead])
    det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=before)
    assert det.blobs.count == 7
    assert nearest(det.centroid, [(100.0, 80.2)]).min() < 0.3
    # a blob with no blob of the frame before within the gate has just come into view: it
    # is tested as in a first frame
    far = previous_record([*singles, *((u - 40.0, v) for u, v in ahead)])
    assert detect.detect_frame(img, 12000.0, 2.5, (), p, previous=far).blobs.count == 8


def test_a_merged_pair_moving_slower_than_its_separation_is_still_split() -> None:
    img, truth = scene(4.2)  # the pair's centres lie 4.2 px apart along u
    p = detect.PARAMS.resolve({"n": 6, **only("split_merged")})
    slow = previous_record([*truth[:4], (102.1 - 3.0, 80.2)])
    det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=slow)
    assert det.blobs.count == 6
    assert nearest(det.centroid, truth).max() < 0.6
    # faster along its own axis than its separation per frame: read as one blurred marker
    fast = previous_record([*truth[:4], (102.1 - 6.0, 80.2)])
    assert detect.detect_frame(img, 12000.0, 2.5, (), p, previous=fast).blobs.count == 5


def test_a_pair_moving_along_its_axis_is_split_under_the_cameras_streak_ratio() -> None:
    # The two PSI seen side-on: 4.2 px apart along u, moving 6 px a frame along u. With an
    # exposure as long as the frame interval (ratio 1) the blob could be one marker's
    # streak; a camera whose single markers streak over at most 0.3 of their motion cannot
    # draw 4.2 px from 6 px of motion.
    img, truth = scene(4.2)
    p = detect.PARAMS.resolve({"n": 6, **only("split_merged")})
    fast = previous_record([*truth[:4], (102.1 - 6.0, 80.2)])
    assert detect.detect_frame(img, 12000.0, 2.5, (), p, previous=fast).blobs.count == 5
    det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=fast, streak_ratio=0.3)
    assert det.blobs.count == 6
    assert nearest(det.centroid, truth).max() < 0.6


def test_a_blurred_marker_within_the_cameras_streak_ratio_is_not_split() -> None:
    img, singles = streak_scene(5.0)
    p = detect.PARAMS.resolve({"n": 5, **only("split_merged")})
    # a 5 px streak drawn over 20 px of motion: a quarter of the frame interval
    moved = previous_record([*singles, (100.0 - 20.0, 80.2)])
    for ratio in (0.3, 1.0):
        det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=moved, streak_ratio=ratio)
        assert det.blobs.count == 5, ratio
    # the same streak from 8 px of motion is longer than 0.3 of it: two markers
    near = previous_record([*singles, (100.0 - 8.0, 80.2)])
    det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=near, streak_ratio=0.3)
    assert det.blobs.count == 6


def streak_sample(img: np.ndarray, previous: np.ndarray, n: int = 5) -> np.ndarray:
    p = detect.PARAMS.resolve({"n": n, **only("split_merged")})
    det = detect.detect_frame(img, 12000.0, 2.5, (), p, previous=previous, sample_streaks=True)
    return det.streaks


STILL = [(20.3, 20.6), (60.7, 25.2), (120.1, 30.4), (40.5, 90.9)]


def streaked(u: float, length: float, extra: list[tuple[float, float]] | None = None) -> np.ndarray:
    """The four ``STILL`` markers (radius 2.5 px), markers at ``extra``, and a smaller one
    (radius 2 px, farther away) streaked over ``length`` px along u, centred at (u, 60.3)."""
    img = frame(noise=10.0, seed=int(u) % 7)
    for a, b in [*STILL, *(extra or [])]:
        disc(img, a, b, 2.5, 60000.0)
    for k in range(12):
        disc(img, u - length / 2 + length * k / 11, 60.3, 2.0, 30000.0)
    return u16(img)


def test_streak_ratios_measure_an_isolated_moving_marker() -> None:
    # a 3 px streak along u after 12 px of motion along u: the exposure is a quarter of a
    # frame (the pixel grid resolves the streak's length to about a pixel)
    img = streaked(100.0, 3.0)
    got = streak_sample(img, previous_record([*STILL, (88.0, 60.3)]))
    assert got.shape == (1,)
    assert 0.15 <= got[0] <= 0.35, got
    # not seen in the frame before, or moving less than min_motion: no sample
    assert streak_sample(img, previous_record(STILL)).size == 0
    assert streak_sample(img, previous_record([*STILL, (98.0, 60.3)])).size == 0
    # without sample_streaks nothing is measured
    p = detect.PARAMS.resolve({"n": 5, **only("split_merged")})
    moved = previous_record([*STILL, (88.0, 60.3)])
    assert detect.detect_frame(img, 12000.0, 2.5, (), p, previous=moved).streaks.size == 0


def test_streak_ratios_skip_a_marker_with_a_neighbour_or_of_a_pairs_size() -> None:
    img, truth = scene(4.2)  # the pair is one blob of about twice a marker's area
    moved = previous_record([*truth[:4], (102.1 - 15.0, 80.2)])
    assert streak_sample(img, moved).size == 0
    crowded = streaked(100.0, 3.0, [(100.0, 68.0)])  # a marker 8 px away
    near = previous_record([*STILL, (100.0, 68.0), (88.0, 60.3)])
    assert streak_sample(crowded, near, n=6).size == 0
    # the same marker 18 px away: far enough
    assert streak_sample(streaked(100.0, 3.0, [(100.0, 78.0)]), near, n=6).size == 1


def test_learned_streak_ratio_is_a_quantile_capped_at_one() -> None:
    samples = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    assert detect.learned_streak_ratio(samples, 0.5, 5) == pytest.approx(0.3)
    assert detect.learned_streak_ratio(samples, 1.0, 5) == pytest.approx(0.5)
    assert detect.learned_streak_ratio(samples, 0.5, 6) == 1.0  # too few yet
    assert detect.learned_streak_ratio(np.array([0.9, 1.4, 2.0]), 0.9, 3) == 1.0


def moving_scene(streak_at: float, pair_at: float | None) -> np.ndarray:
    """:func:`streaked` with a 3 px streak at u = ``streak_at`` and (optionally) a pair
    4.2 px apart along u centred at (``pair_at``, 100.2)."""
    pair = [] if pair_at is None else [(pair_at - 2.1, 100.2), (pair_at + 2.1, 100.2)]
    return streaked(streak_at, 3.0, pair)


def test_the_stage_learns_the_streak_ratio_and_keeps_it_for_the_camera() -> None:
    # One marker crosses the view at 12 px a frame with a 3 px streak (ratio about 0.25);
    # once three samples are in, a pair moving 6 px a frame along its own axis is split.
    opts = {"n": 6, **only("split_merged"), "default_w": 12000.0, "default_r_b": 2.5}
    learn = {"streak_learned": True, "streak_min_samples": 3, "streak_every": 1}
    p = detect.PARAMS.resolve({**opts, **learn})

    def last_count(state, frames, trial="walk-01"):
        for i, img in enumerate(frames):
            state, (out,) = detect.step(state, {"clean": clean_msg(img, trial, i)})
        return state, len(out.centroid)

    walk = [moving_scene(30.0 + 12.0 * i, None) for i in range(5)]
    pair = [moving_scene(100.0, 60.0), moving_scene(112.0, 66.0)]
    learned, n = last_count(detect.init(p), walk + pair)
    assert n == 7
    cam = learned.cameras["cam0"]
    assert cam.streaks.size >= 3
    assert detect.learned_streak_ratio(cam.streaks, 0.9, 3) < 0.5
    # a fresh camera has no ratio yet: the pair reads as one streaked marker
    assert last_count(detect.init(p), pair)[1] == 6
    # the ratio is the camera's: a new trial keeps it
    assert last_count(learned, pair, trial="walk-02")[1] == 7
    # off (the default): nothing is sampled and the bound stays the whole motion
    off = detect.PARAMS.resolve({**opts, **learn, "streak_learned": False})
    state, n = last_count(detect.init(off), walk + pair)
    assert n == 6
    assert state.cameras["cam0"].streaks.size == 0


def line_scene(length: float) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """Four single markers and a thin bright line ``length`` px long along u (a glint on
    an edge, a flying-pixel seam): 1.5-3 times a marker's area, elongated, but far longer
    than two touching markers."""
    img = frame(noise=10.0, seed=3)
    singles = [(20.3, 20.6), (60.7, 25.2), (120.1, 30.4), (40.5, 90.9)]
    for u, v in singles:
        disc(img, u, v, 2.5, 60000.0)
    for k in range(int(4 * length) + 1):
        disc(img, 90.0 + k / 4, 80.2, 0.9, 30000.0)
    return u16(img), singles


@pytest.mark.parametrize("length", [18.0, 20.0])
def test_a_line_longer_than_two_touching_markers_is_not_split(
    length: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    # bz_HC034A_straight_HC034A07, frame 50 with every splitter on: a thin 23 px streak
    # beside the hidden hip, 1.5 times the median area, was split into two parts 10 px
    # (6.7 median marker radii) apart, and one took the hip label. Two merged discs lie at
    # most about three radii apart (touching at e_d, blur along their common motion aside).
    img, singles = line_scene(length)
    p = detect.PARAMS.resolve({"n": 5, **only("split_merged")})
    det = detect.detect_frame(img, 12000.0, 2.5, (), p)
    assert det.blobs.count == 5
    assert nearest(det.centroid, singles).max() < 0.5
    # without the bound on the halves' separation the line is two "markers"
    unbounded = functools.partial(detect.split_merged, separation_max=np.inf)
    monkeypatch.setattr(detect, "split_merged", unbounded)
    assert detect.detect_frame(img, 12000.0, 2.5, (), p).blobs.count == 6


def test_every_splitter_is_on_by_default() -> None:
    # since the thirtieth session (module docstring): the 41 rows of the gait variation
    # table find more events with them, for 0.1 point of labelling
    assert all(detect.PARAMS.resolve({})[s] is True for s in detect.SPLITTERS)


# Splitting blobs that hold two separate bright cores (``split_cores``).


def streak(img: np.ndarray, u0: float, v0: float, du: float, dv: float, radius: float,
           gain: float, samples: int = 8) -> None:  # fmt: skip
    """A motion-blurred disc: ``samples`` discs from (u0, v0) to (u0+du, v0+dv), averaged."""
    acc = np.zeros_like(img)
    for t in np.linspace(0.0, 1.0, samples):
        disc(acc, u0 + t * du, v0 + t * dv, radius, gain / samples)
    img += acc


def split_run(img: np.ndarray, n: int, w: float = 12000.0, **kw) -> detect.Detection:
    p = detect.PARAMS.resolve({"n": n, **only("split_cores"), **kw})
    return detect.detect_frame(u16(img), w, 2.5, (), p)


@pytest.mark.parametrize(
    "gap, gain, w",
    [
        (3.8, 3 * 65535.0, 45000.0),
        (4.2, 3 * 65535.0, 45000.0),
        (4.6, 3 * 65535.0, 45000.0),
        (5.0, 3 * 65535.0, 30000.0),
        (4.6, 50000.0, 12000.0),
    ],
)
def test_touching_markers_are_split_near_each_centre(gap: float, gain: float, w: float) -> None:
    # Two markers (radius 1.9 px) whose rims touch (heel and ankle): saturated, joined at a
    # threshold near 3/4 of full scale by a neck 1-3 px wide (first four cases: the widest,
    # diagonal, needs the 3x3 erosion), or unsaturated, joined through an intensity valley.
    img = frame(noise=10.0, seed=5)
    pair = [(60.3, 50.2), (60.3 + gap * 0.8, 50.2 + gap * 0.6)]
    for u, v in pair:
        disc(img, u, v, 1.9, gain)
    singles = [(20.4, 20.7), (120.6, 90.1)]
    for u, v in singles:
        disc(img, u, v, 1.9, gain)
    off = split_run(img, 3, w, split_cores=False)
    assert off.blobs.count == 3  # the pair is one blob
    on = split_run(img, 3, w)
    assert on.blobs.count == 4
    err = nearest(on.centroid, pair + singles)
    assert err.max() < 0.35, err
    # Single markers keep their Alg. 2 statistics exactly.
    for c in off.centroid[nearest(off.centroid, singles, axis=1) < 0.5]:
        assert np.min(np.hypot(*(on.centroid - c).T)) == 0.0


@pytest.mark.parametrize(
    "du, dv, radius", [(6.0, 0.0, 1.7), (4.5, 4.5, 1.7), (-3.0, 5.5, 2.2), (9.0, 3.0, 2.6)]
)
def test_motion_blurred_single_marker_is_not_split(du: float, dv: float, radius: float) -> None:
    for gain in (3 * 65535.0, 45000.0):
        img = frame(noise=12.0, seed=7)
        streak(img, 70.2, 60.7, du, dv, radius, gain)
        det = split_run(img, 1)
        assert det.blobs.count == 1, (du, dv, radius, gain)


def test_bright_line_is_not_split() -> None:
    # Reflective tape: a long thin band with a ripple along it has several "cores" but is
    # not a compact group of markers (area / (pi r_r^2) far below split_min_fill).
    img = frame(noise=12.0, seed=8)
    cc = np.arange(20, 140)
    img[60:63, 20:140] += 30000.0 + 6000.0 * np.sin(cc / 6.0)[None, :]
    disc(img, 40.2, 20.3, 2.0, 3 * 65535.0)
    disc(img, 90.7, 100.4, 2.0, 3 * 65535.0)
    for w in (12000.0, 28000.0):
        off = split_run(img, 3, w, split_cores=False)
        on = split_run(img, 3, w)
        assert on.blobs.count == off.blobs.count
        np.testing.assert_array_equal(on.centroid, off.centroid)


def test_roi_with_overlapping_group_boxes_matches_full_frame() -> None:
    # An L-shaped group's bounding box holds another group's tiles: boxes are merged, and
    # components, centroids and radii equal the full frame's.
    img = frame((96, 128), noise=12.0, seed=9)
    img[8:60, 8:12] = 40000.0  # vertical bar of the L
    img[56:60, 8:90] = 40000.0  # horizontal bar
    for u, v in [(40.3, 30.6), (70.8, 20.1), (100.2, 80.7)]:
        disc(img, u, v, 2.3, 3 * 65535.0)
    ir = u16(img)
    roi = detect.compact_roi(ir, 2000.0)
    full = detect.Roi(ir, np.zeros(ir.shape, np.int32), np.zeros(1, np.intp),
                      np.zeros(1, np.intp), 2000.0)  # fmt: skip
    for e in (2000.0, 30000.0, 50000.0):
        a = detect.components(roi, e, extent=True)
        b = detect.components(full, e, extent=True)
        assert a.count == b.count
        ia, ib = np.lexsort(a.centroid.T), np.lexsort(b.centroid.T)
        for name in ("centroid", "marker_radius", "region_radius", "mean_ir", "area", "box"):
            np.testing.assert_allclose(getattr(a, name)[ia], getattr(b, name)[ib], atol=1e-9)


def test_alg1_alternating_blob_sets_stop_before_the_cap() -> None:
    # Markers of mixed brightness: step 5 raises e_d until fewer than n blobs remain, step 6
    # lowers it until more than n appear, and so on. A repeated blob set ends the loop.
    rng = np.random.default_rng(0)
    img = frame((80, 120), noise=10.0, seed=0)
    k = int(rng.integers(3, 9))
    for i in range(k):
        u, v = 10 + (i % 4) * 28 + rng.random(), 15 + (i // 4) * 35 + rng.random()
        disc(img, u, v, rng.uniform(1.0, 3.0), rng.uniform(8000, 80000))
    ir = u16(img)
    capped = detect.detect_frame(ir, 5000.0, 2.0, (), params(n=4, max_iterations=100))
    assert capped.iterations < 10
    det = detect.detect_frame(ir, 5000.0, 2.0, (), params(n=4))
    assert det.iterations == capped.iterations
    assert abs(det.blobs.count - 4) <= 1


@pytest.mark.parametrize("kind", ["zero", "saturated", "300 blobs", "300 touching pairs"])
def test_bad_input_with_splitting_is_bounded(kind: str) -> None:
    img = np.full((424, 512), 500.0)
    if kind == "zero":
        img[:] = 0.0
    elif kind == "saturated":
        img[:] = 65535.0
    else:
        rr, cc = np.mgrid[0:20, 0:15]
        for y, x in zip(10 + rr.ravel() * 20, 10 + cc.ravel() * 33, strict=True):
            img[y - 1 : y + 2, x - 1 : x + 2] = 65535
            if kind == "300 touching pairs":  # a second 3x3 marker touching diagonally
                img[y + 2 : y + 5, x + 2 : x + 5] = 65535
    st = detect.init(params(split_cores=True, split_merged=True))
    t = time.perf_counter()
    _, (out,) = detect.step(st, {"clean": clean_msg(u16(img))})
    dt = time.perf_counter() - t
    assert dt < 2.0
    assert out.centroid.shape[0] <= 64  # max_blobs
    if kind in ("zero", "saturated"):
        assert out.status == "empty" and out.centroid.shape == (0, 2)
    else:
        assert out.status == "too-many"
        assert np.isfinite(out.centroid).all()


def _four_markers(gain: float) -> np.ndarray:
    img = frame((60, 160), noise=10.0, seed=3)
    for i, g in enumerate((0.3, 0.45, 0.7, 1.0)):
        disc(img, 20.0 + 38.0 * i, 30.0, 2.5, g * gain)
    return u16(img)


def test_alg1_step6_never_raises_the_threshold_over_unsaturated_markers() -> None:
    # Markers that do not saturate (peaks 6 000-20 000): from a history threshold that keeps
    # only the two brightest (f = 2 < n = 4), the literal step 6 pulls e_d towards the
    # history's bright largest blob, above every marker. The option keeps e_d instead.
    ir = _four_markers(20000.0)
    hist = (detect.HistoryEntry(12000.0, 60000.0, 3.0),)
    literal = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=4, step6_saturated_only=False))
    det = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=4, step6_saturated_only=True))
    assert literal.threshold > 20000.0
    assert literal.blobs.count == 0
    assert det.threshold == 12000.0
    assert det.blobs.count == 2
    roi = detect.compact_roi(ir, 3000.0)
    assert not detect.saturated(roi, detect.components(roi, 12000.0)).any()


def test_alg1_step6_over_saturated_markers_is_the_literal_one() -> None:
    # The same scene with saturated markers (every core clipped at full scale): raising
    # e_d loses none of them, and the option changes nothing.
    ir = _four_markers(400000.0)
    hist = (detect.HistoryEntry(20000.0, 65000.0, 3.0),)
    a = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=5, step6_saturated_only=False))
    b = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=5, step6_saturated_only=True))
    roi = detect.compact_roi(ir, 3000.0)
    assert detect.saturated(roi, detect.components(roi, 20000.0)).all()
    assert a.threshold > 40000.0  # step 6 raised e_d (f = 4 < n = 5)
    assert a.blobs.count == 4
    assert (a.threshold, a.iterations, a.blobs.count) == (b.threshold, b.iterations, b.blobs.count)
    np.testing.assert_array_equal(a.centroid, b.centroid)


def test_alg1_step6_is_the_literal_one_where_the_markers_were_seen_saturating() -> None:
    ir = _four_markers(20000.0)
    hist = (detect.HistoryEntry(12000.0, 60000.0, 3.0),)
    literal = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=4, step6_saturated_only=False))
    seen = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=4), markers_saturate=True)
    kept = detect.detect_frame(ir, 3000.0, 2.5, hist, params(n=4))
    assert (seen.threshold, seen.blobs.count) == (literal.threshold, literal.blobs.count)
    assert (kept.threshold, kept.blobs.count) == (12000.0, 2)


def test_detect_learns_from_saturated_blobs_that_the_markers_saturate() -> None:
    # Four saturated markers in one frame tell the stage that this camera's markers
    # saturate; the flag holds for its later frames and trials, not for another camera.
    p = params(n=5, saturating_markers=4)
    dim, bright = _four_markers(20000.0), _four_markers(400000.0)
    st = detect.init(p)
    st, _ = detect.step(st, {"clean": clean_msg(dim)})
    assert not st.cameras["cam0"].markers_saturate
    st, (out,) = detect.step(st, {"clean": clean_msg(bright, idx=1)})
    assert out.centroid.shape[0] == 4
    assert st.cameras["cam0"].markers_saturate
    st, _ = detect.step(st, {"clean": clean_msg(dim, trial="walk-02")})
    assert st.cameras["cam0"].markers_saturate
    st, _ = detect.step(st, {"clean": clean_msg(dim, camera="cam1")})
    assert not st.cameras["cam1"].markers_saturate
    # Three saturated blobs are not enough at saturating_markers = 4.
    img = frame((60, 160), noise=10.0, seed=3)
    for i, peak in enumerate((400000.0, 400000.0, 400000.0, 15000.0)):
        disc(img, 20.0 + 38.0 * i, 30.0, 2.5, peak)
    st3, (out3,) = detect.step(detect.init(p), {"clean": clean_msg(u16(img))})
    assert out3.centroid.shape[0] >= 3  # the three saturated markers
    assert not st3.cameras["cam0"].markers_saturate


# ---- split_tracked: a blob split into the two markers the previous frame saw apart


def pair_frame(centres: list[tuple[float, float]], seed: int) -> np.ndarray:
    img = frame(noise=10.0, seed=seed)
    for u, v in centres:
        disc(img, u, v, 1.9, 3 * 65535.0)
    return u16(img)


SINGLES = [(20.4, 20.7), (120.6, 90.1)]


def tracked_run(ir: np.ndarray, previous: np.ndarray | None, on: bool = True):
    p = detect.PARAMS.resolve({"n": 4, **only("split_tracked", on)})
    return detect.detect_frame(ir, 45000.0, 2.5, (), p, previous=previous)


@pytest.mark.parametrize("gap", [2.6, 3.0, 3.4])
def test_merged_pair_seen_apart_in_the_frame_before_is_split(gap: float) -> None:
    # Heel and ankle 6 px apart, then overlapping (one blob, one centroid between them)
    # after the foot moved 7 px: the frame before tells the blob holds two markers.
    before = [(60.2, 50.3), (65.0, 53.9), *SINGLES]
    after = [(67.1, 50.6), (67.1 + gap * 0.8, 50.6 + gap * 0.6), *SINGLES]
    first = tracked_run(pair_frame(before, 1), None)
    assert first.blobs.count == 4
    off = tracked_run(pair_frame(after, 2), first.record, on=False)
    assert off.blobs.count == 3  # the pair is one blob
    on = tracked_run(pair_frame(after, 2), first.record)
    assert on.blobs.count == 4
    err = nearest(on.centroid, after)
    assert err.max() < 0.5, err  # the bench's strictest recall radius
    # the other blobs keep their Alg. 2 statistics exactly
    for c in off.centroid[nearest(off.centroid, SINGLES, axis=1) < 0.5]:
        assert np.min(np.hypot(*(on.centroid - c).T)) == 0.0
    # the next frame, still merged, is split again from the split parts
    later = [(u + 5.0, v) for u, v in after[:2]] + SINGLES
    again = tracked_run(pair_frame(later, 3), on.record)
    assert again.blobs.count == 4
    assert nearest(again.centroid, later).max() < 0.5


def test_a_marker_hidden_beside_another_does_not_split_it() -> None:
    # The ankle is hidden in the second frame: the heel's blob did not grow, so the
    # previous frame's pair does not split it.
    before = [(60.2, 50.3), (65.0, 53.9), *SINGLES]
    first = tracked_run(pair_frame(before, 1), None)
    alone = [(62.0, 50.5), *SINGLES]
    det = tracked_run(pair_frame(alone, 2), first.record)
    assert det.blobs.count == 3
    assert nearest(det.centroid, alone).max() < 0.3
    # and a split pair whose blob shrinks to one marker's is not split any more
    merged = [(67.1, 50.6), (69.5, 52.4), *SINGLES]
    split = tracked_run(pair_frame(merged, 3), first.record)
    assert split.blobs.count == 4
    det = tracked_run(pair_frame([(70.0, 51.0), *SINGLES], 4), split.record)
    assert det.blobs.count == 3


def test_a_blob_without_a_previous_pair_is_not_split() -> None:
    merged = [(67.1, 50.6), (69.5, 52.4), *SINGLES]
    assert tracked_run(pair_frame(merged, 3), None).blobs.count == 3
    # two markers far apart in the frame before are no pair
    far = [(40.2, 50.3), (67.8, 51.5), *SINGLES]
    first = tracked_run(pair_frame(far, 1), None)
    assert tracked_run(pair_frame(merged, 3), first.record).blobs.count == 3


def test_the_stage_carries_the_previous_blobs_within_a_trial_only() -> None:
    p = {"n": 4, **only("split_tracked"), "default_w": 45000.0, "default_r_b": 2.5}
    before = pair_frame([(60.2, 50.3), (65.0, 53.9), *SINGLES], 1)
    merged = pair_frame([(67.1, 50.6), (69.5, 52.4), *SINGLES], 2)
    state = detect.init(detect.PARAMS.resolve(p))
    state, _ = detect.step(state, {"clean": clean_msg(before, idx=0)})
    state, (out,) = detect.step(state, {"clean": clean_msg(merged, idx=1)})
    assert len(out.centroid) == 4
    state, _ = detect.step(state, {"clean": clean_msg(before, idx=0)})
    state, (out,) = detect.step(state, {"clean": clean_msg(merged, trial="walk-02", idx=0)})
    assert len(out.centroid) == 3  # a new trial starts without the previous frame


def test_every_splitter_together_keeps_each_part_once() -> None:
    # split_tracked, split_cores and split_merged in turn. A part one of them appended has
    # no pixels of its own in ``labels`` and is left to the next: the halves of a large
    # pair among small markers are 1.5-3x the median area, split_merged's candidates (it
    # crashed on them).
    small = [(20.4, 20.7), (120.6, 90.1), (100.3, 30.2), (30.8, 95.4)]

    def scene(pair: list[tuple[float, float]], seed: int) -> np.ndarray:
        img = frame(noise=10.0, seed=seed)
        for u, v in pair:
            disc(img, u, v, 2.4, 3 * 65535.0)
        for u, v in small:
            disc(img, u, v, 1.3, 3 * 65535.0)
        return u16(img)

    before, after = [(60.2, 50.3), (66.0, 54.6)], [(67.1, 50.6), (70.0, 52.6)]
    opts = {"split_tracked": True, "split_cores": True, "split_merged": True}
    p = detect.PARAMS.resolve({"n": 6, **opts})
    first = detect.detect_frame(scene(before, 1), 45000.0, 2.5, (), p)
    assert first.blobs.count == 6
    det = detect.detect_frame(scene(after, 2), 45000.0, 2.5, (), p, previous=first.record)
    assert det.blobs.count == 6
    assert nearest(det.centroid, after + small).max() < 0.5
