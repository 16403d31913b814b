"""The fast paths of the gait stage give exactly (bit for bit) what the plain ones give.

Vectorised rounding, percentiles and medians against Python's and numpy's own; the batched
gap filling and resampling against one marker at a time; the incremental resampling of a
growing trial against computing from scratch; the stage with its caches against the stage
with its caches emptied before every frame. Inputs are random with fixed seeds, or the
simulator's markers (``gaitflow.bench.gait``'s markers level) for the stage.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from gaitflow.stages import gait as gs

from gaitflow import gaitcore as gc
from gaitflow.bench import gait as bg
from gaitflow.markers import MARKER_NAMES
from gaitflow.results import frame_record, frame_records, round_array
from gaitflow.sim import simulate_session


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.array_equal(a.view(np.int64), b.view(np.int64)))


@pytest.mark.parametrize("ndigits", [1, 2, 3, 4, 6])
def test_round_array_is_pythons_round(ndigits):
    rng = np.random.default_rng(ndigits)
    ties = (rng.integers(-(10**6), 10**6, 20000) + 0.5) / 10**ndigits  # near-ties
    x = np.concatenate(
        [
            rng.normal(0, 1000, 20000),
            ties,
            [0.0, -0.0, -0.04, 2.675, 0.125, 1e15, -1e16, 1e300, 5e-324, np.inf, -np.inf, np.nan],
        ]
    )
    got = round_array(x, ndigits)
    want = np.array([round(float(v), ndigits) if np.isfinite(v) else v for v in x])
    assert same_bits(got, want)  # signs of zeros included


def test_frame_record_one_and_vectorised_agree():
    rng = np.random.default_rng(3)
    pos = rng.normal(0, 800, (40, 20, 3))
    pix = np.round(rng.normal(0, 300, (40, 20, 2)) * 8) / 8  # exact ties at 2 digits
    pos[rng.random((40, 20)) < 0.3] = np.nan
    pix[rng.random((40, 20)) < 0.3] = np.nan
    pos[5, 2, 1] = np.nan  # one coordinate missing: the whole marker is null
    t = np.cumsum(rng.uniform(0.03, 0.04, 40))
    many = frame_records(list(range(40)), t, pos, pix)
    one = [frame_record(i, t[i], pos[i], pix[i]) for i in range(40)]
    assert json.dumps(many) == json.dumps(one)
    assert many[5]["markers"][MARKER_NAMES[2]] is None


def test_percentile_and_median_equal_numpys():
    rng = np.random.default_rng(4)
    for n in [1, 2, 3, 4, 7, 50, 501]:
        x = rng.normal(0, 100, n)
        for q in ([1.0, 99.0], [90], [0, 50, 100]):
            assert same_bits(gc.percentile_linear(x, q), np.percentile(x, q))
    x = rng.normal(0, 100, (300, 20))
    x[rng.random(x.shape) < 0.4] = np.nan
    x[:2] = np.nan
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        want = np.nanmedian(x, axis=1)
    assert same_bits(gc.nanmedian_last(x), want)
    for row in x[2:40]:  # the one-row path
        assert same_bits(gc.nanmedian_last(row), np.nanmedian(row))


def random_markers(rng: np.random.Generator, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Irregular times and M random-walk markers with gaps of all lengths, some to the end."""
    t = np.cumsum(rng.choice([1 / 30, 2 / 30, 1 / 30 + 1e-4], n, p=[0.85, 0.1, 0.05]))
    x = rng.normal(size=(n, m, 3)).cumsum(axis=0) * 10
    for k in range(m):
        for _ in range(int(rng.integers(0, 6))):
            a = int(rng.integers(0, n))
            x[a : a + int(rng.choice([1, 2, 5, 9, 30])), k] = np.nan
        if rng.random() < 0.3:
            x[int(rng.integers(0, n)) :, k] = np.nan
    return t - t[0], x


def test_batched_fill_and_resample_equal_one_marker_at_a_time():
    rng = np.random.default_rng(5)
    for _ in range(20):
        t, x = random_markers(rng, int(rng.integers(3, 120)), 4)
        filled, was = gc.fill_gaps_markers(t, x, 0.3)
        tq, xq = gc.resample_markers(t, filled, 100.0)
        for k in range(4):
            f1, w1 = gc.fill_gaps(t, x[:, k], 0.3)
            tq1, q1 = gc.resample(t, f1, 100.0)
            assert same_bits(filled[:, k], f1) and np.array_equal(was[:, k], w1)
            assert same_bits(tq, tq1) and same_bits(xq[:, k], q1)
        # a tail evaluated alone is the tail of the whole
        first = len(tq) // 2
        assert same_bits(gc.resample_markers(t, filled, 100.0, first=first)[1], xq[first:])


def test_level_runs_are_runs_per_level():
    rng = np.random.default_rng(6)
    y = rng.random(300)
    y[rng.random(300) < 0.05] = np.nan
    levels = np.linspace(0.05, 1.0, 20)
    got = gc.level_runs(y, levels)
    with np.errstate(invalid="ignore"):
        assert got == [gc.runs(y <= k) for k in levels]


def test_incremental_resampling_equals_from_scratch_and_computes_only_the_tail(monkeypatch):
    rng = np.random.default_rng(7)
    evaluated = []
    plain = gc.resample_markers

    def counting(t, x, rate_hz=100.0, first=0):
        tq, xq = plain(t, x, rate_hz, first)
        evaluated.append(len(xq))
        return tq, xq

    monkeypatch.setattr(gc, "resample_markers", counting)
    for _ in range(40):
        t, x = random_markers(rng, int(rng.integers(20, 200)), 5)
        gap = float(rng.choice([0.1, 0.3, 1.0]))
        prev = None
        for n in sorted({*rng.integers(2, len(t), 5).tolist(), len(t)}):
            xn = x[:n].copy()
            if rng.random() < 0.2 and n > 4:
                xn[-3:] += 0.5  # the newest frames changed (as after a filter)
            got = gc.fill_resample_markers(t[:n], xn, gap, 100.0, prev)
            filled, was = gc.fill_gaps_markers(t[:n], xn, gap)
            tq, xq = plain(t[:n], filled, 100.0)
            assert same_bits(got.filled, filled) and np.array_equal(got.was_filled, was)
            assert same_bits(got.tq, tq) and same_bits(got.xq, xq)
            prev = got
    # a trial growing by 15 frames: only the samples near its end are evaluated again
    t, x = random_markers(np.random.default_rng(8), 400, 3)
    x[:, :, :] = np.nan_to_num(x, nan=1.0)  # no gaps
    evaluated.clear()
    prev = gc.fill_resample_markers(t[:385], x[:385], 0.3, 100.0)
    gc.fill_resample_markers(t, x, 0.3, 100.0, prev)
    assert evaluated[0] > 1000 and evaluated[1] < 100, evaluated


@pytest.fixture(scope="module")
def walk():
    ses = simulate_session("btk_PiG_Motion3_FF", 1)
    name = ses.walks()[0]
    frames = list(bg._marker_frames(ses, name, noise_mm=3.0, seed=1))
    return frames, bg._true_calibration(ses, name)


def outputs(frames, cal, fresh: bool, **params):
    """Every output of the stage; ``fresh`` empties its caches before each frame."""
    state = gs.init(gs.PARAMS.resolve(params))
    out = []
    for m in frames:
        if fresh:
            state = dataclasses.replace(state, memo=(), series=None)
        state, o = gs.SPEC.run(state, {"labelled": m, "calibration": cal})
        out.extend(o)
    return out + gs.finish(state)[1]


def fields(msg) -> list:
    """A message's content (the publish time aside) as comparable values."""
    out = [dataclasses.replace(msg.header, publish_ns=0)]
    for f in dataclasses.fields(msg):
        v = getattr(msg, f.name)
        if f.name != "header":
            out.append(v.tobytes() if isinstance(v, np.ndarray) else json.dumps(v))
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    "params", [{}, {"depth_smooth_s": 0.3, "live_every": 7, "progression": "pass"}]
)
def test_the_stage_with_its_caches_equals_the_stage_without(walk, params):
    frames, cal = walk
    cached = outputs(frames, cal, False, **params)
    plain = outputs(frames, cal, True, **params)
    assert len(cached) == len(plain)
    assert sum(o.STREAM == "summary" for o in cached) >= 2  # a pass summary and the trial
    for a, b in zip(cached, plain, strict=True):
        assert fields(a) == fields(b)
