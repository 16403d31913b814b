"""clean -> detect -> locate wired through the pipeline graph, and the mocap bench scoring."""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.schemas import Markers3D, RawFrame
from gaitflow.stages.graph import load
from gaitflow.stages.inline import run_inline

from gaitflow.bench import mocap
from gaitflow.camera import Camera

H, W = 212, 256
MARKERS = [(60.3, 50.6), (120.7, 90.2), (180.4, 150.8)]


def raw(k: int, trial: str = "walk-01") -> RawFrame:
    rng = np.random.default_rng(k)
    ir = rng.normal(900.0, 20.0, (H, W))
    depth = rng.normal(2600.0, 3.0, (H, W))
    rr, cc = np.mgrid[0:H, 0:W]
    for u, v in MARKERS:
        r = np.hypot(cc - u, rr - v)
        ir[r <= 2.5] = 65535
        depth[r <= 2.5] = 0
    return RawFrame(
        header=RawFrame.make_header("cam0", trial, k, k * 33_333_333, last=k == 2),
        ir=np.clip(ir, 0, 65535).astype(np.uint16),
        depth=depth.astype(np.uint16),
    )


def test_graph_runs_clean_detect_locate(flat_record) -> None:
    graph = load()
    # Frames arrive before the calibration record: they are held, then released in order.
    msgs = [raw(0), raw(1), flat_record(20000.0, frame=50), raw(2)]
    out = run_inline(graph, msgs, stages=["clean", "detect", "locate"], params={"detect": {"n": 3}})
    markers = out["markers"]
    assert [m.header.frame for m in markers] == [0, 1, 2]
    m = markers[-1]
    assert isinstance(m, Markers3D) and m.header.last
    assert m.centroid.shape == (3, 2)
    for u, v in MARKERS:
        # Hard-edged literal discs: pixel-quantised, so only wiring-level accuracy here.
        assert np.min(np.hypot(m.centroid[:, 0] - u, m.centroid[:, 1] - v)) < 0.3
    # Plane at 2600 mm; the published point is the marker centre, 12.5 + 2 (base) mm nearer.
    assert np.all(np.abs(m.depth[:, 0] - (2600.0 - 14.5)) < 3.0)


@pytest.mark.slow
def test_bench_stages_on_a_few_simulated_frames() -> None:
    from gaitflow.sim import SimConfig, list_trials, simulate_session

    cfg = SimConfig.quick()
    rec = simulate_session(list_trials()[0], 0, cfg).recordings["walk-01"]
    frames = [rec.frame(i) for i in range(30, 36)]  # the subject is in view
    mids = mocap.mid_exposure_pixels(frames, mocap.truth_lag_frames(cfg))
    score = mocap.Score()
    for method in ("adaptive", "static"):
        score = mocap.Score()
        cal = mocap.session_record(Camera().to_json(marker_diameter_mm=25))
        rendered = [(r, t, m, cal) for (r, t), m in zip(frames, mids, strict=True)]
        mocap.run_stages(rendered, method, score, gate=4.0)
        r = mocap.summarise(score)
        assert r["frames"] == 6 and r["visible"] > 30
        assert r["detected"] > 80.0
        assert r["recall@2.5"] > 80.0
        assert r["ms_detect+locate_p99"] > 0


@pytest.mark.slow
def test_bench_parameter_overrides_reach_the_stages_but_not_the_row_keys() -> None:
    from gaitflow.sim import SimConfig, list_trials, simulate_session

    cfg = SimConfig.quick()
    rec = simulate_session(list_trials()[0], 0, cfg).recordings["walk-01"]
    frames = [rec.frame(i) for i in range(30, 34)]
    mids = mocap.mid_exposure_pixels(frames, mocap.truth_lag_frames(cfg))
    cal = mocap.session_record(Camera().to_json(marker_diameter_mm=25))
    rendered = [(r, t, m, cal) for (r, t), m in zip(frames, mids, strict=True)]

    def run(overrides):
        score = mocap.Score()
        mocap.run_stages(rendered, "adaptive", score, gate=4.0, overrides=overrides)
        r = mocap.summarise(score)
        return r["detected"], r["recall@0.5"]

    plain = run(None)
    assert plain[0] > 80.0
    # No marker's image covers 500 px: with that smallest blob, nothing is detected.
    assert run({"detect": {"min_area": 500}})[0] == 0.0
    # The row's own method stays: a static override does not turn the adaptive row static.
    assert run({"detect": {"method": "static"}}) == plain


def test_bench_parameter_overrides_are_checked_before_rendering() -> None:
    from gaitflow.errors import ConfigError, ParameterError

    mocap._check_overrides({"detect": {"step6_saturated_only": True}, "locate": {}})
    with pytest.raises(ConfigError, match="'gait'"):
        mocap._check_overrides({"gait": {"xi": 0.1}})
    with pytest.raises(ParameterError, match="nope"):
        mocap._check_overrides({"detect": {"nope": 1}})
