"""The clean stage: invalid depth, still stray reflectors masked, moving markers kept."""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.schemas import CalibrationRecord, CleanFrame, RawFrame
from gaitflow.stages import clean

from gaitflow.errors import ParameterError

H, W = 120, 160
REFLECTOR = (slice(20, 24), slice(30, 34))  # a still 4x4 stray reflector


def raw(k: int, trial: str = "walk-01", marker_u: float | None = None, seed: int = 0) -> RawFrame:
    rng = np.random.default_rng([seed, k])
    ir = rng.normal(800.0, 15.0, (H, W))
    ir[REFLECTOR] = 65535
    if marker_u is not None:  # a moving 3x3 marker along row 80
        c = round(marker_u)
        ir[79:82, c - 1 : c + 2] = 65535
    depth = np.full((H, W), 2500.0)
    depth[0:5, :] = 9000  # beyond range
    depth[5:8, :] = 100  # too near
    return RawFrame(
        header=RawFrame.make_header("cam0", trial, k, k * 33_333_333),
        ir=np.clip(ir, 0, 65535).astype(np.uint16),
        depth=depth.astype(np.uint16),
    )


def run(frames: list[RawFrame], cal: CalibrationRecord | None = None, **kw) -> list:
    st = clean.init(clean.PARAMS.resolve(kw))
    outs = []
    for f in frames:
        inputs = {"raw": f} if cal is None else {"raw": f, "calibration": cal}
        st, out = clean.step(st, inputs)
        outs.append(out)
    return outs


def test_invalid_depth_is_zeroed_and_ir_kept() -> None:
    (out,) = run([raw(0)])[0]
    assert isinstance(out, CleanFrame)
    assert (out.depth[0:8] == 0).all()
    assert (out.depth[8:] == 2500).all()
    assert out.ir[REFLECTOR].min() == 65535  # not yet known as interference


def test_still_reflector_masked_moving_marker_not() -> None:
    n = 45
    outs = run([raw(k, marker_u=20 + 2.5 * k) for k in range(n)])
    last = outs[-1][0]
    assert last.mask[REFLECTOR].all()
    assert (last.ir[REFLECTOR] == 0).all()
    assert last.interferers == 1
    # The moving marker was never masked, in any frame.
    for k, (o,) in enumerate(outs):
        c = round(20 + 2.5 * k)
        assert o.ir[80, c] == 65535, k
        assert o.mask[80, c] == 0
    # Masking starts once the reflector has been still for still_frames.
    first = next(k for k, (o,) in enumerate(outs) if o.mask.any())
    assert first == clean.PARAMS.defaults()["still_frames"] - 1


def test_marker_crossing_the_reflector_lifts_the_mask() -> None:
    # A marker moving down column 32 crosses the masked reflector at rows 20-23.
    frames = [raw(k) for k in range(35)]
    st = clean.init(clean.PARAMS.resolve())
    for f in frames:
        st, _ = clean.step(st, {"raw": f})
    f = raw(35)
    ir = f.ir.copy()
    ir[25:28, 31:34] = 65535  # the marker right below the box, overlapping its margin
    f = RawFrame(header=f.header, ir=ir, depth=f.depth)
    st, (out,) = clean.step(st, {"raw": f})
    assert out.mask.sum() == 0  # lifted for this frame
    assert out.ir[26, 32] == 65535
    st, (out2,) = clean.step(st, {"raw": raw(36)})
    assert out2.mask[REFLECTOR].all()  # and back once the marker has gone


def test_pieces_of_a_tall_reflector_half_hidden_stay_masked() -> None:
    # A chrome pole's highlight: one pixel wide, rows 10-99 of column 60. The passing body
    # hides rows 40-69: the two pieces left match no track; they lifted the box before and
    # came out as marker-like blobs. A marker crossing the pole still lifts it.
    def pole(k: int, hidden: slice | None = None, marker: bool = False) -> RawFrame:
        f = raw(k)
        ir = f.ir.copy()
        ir[10:100, 60] = 65535
        if hidden is not None:
            ir[hidden, 55:66] = 800
        if marker:
            ir[50:53, 59:62] = 65535
        return RawFrame(header=f.header, ir=ir, depth=f.depth)

    st = clean.init(clean.PARAMS.resolve())
    for k in range(35):
        st, (out,) = clean.step(st, {"raw": pole(k)})
    assert out.mask[10:100, 60].all()
    st, (out,) = clean.step(st, {"raw": pole(35, hidden=slice(40, 70))})
    assert out.mask[10:40, 60].all() and out.mask[70:100, 60].all()
    assert (out.ir[10:100, 60] == 0).all()
    st, (out,) = clean.step(st, {"raw": pole(36, hidden=slice(40, 70), marker=True)})
    assert out.mask[10:100, 60].sum() == 0 and out.ir[51, 60] == 65535
    assert out.mask[REFLECTOR].all()  # the other reflector stays masked
    # A compact reflector's piece still lifts its box: there a marker may lie inside it.
    f = pole(37)
    ir = f.ir.copy()
    ir[21:24, 30:34] = 800  # all but its top row hidden
    st, (out,) = clean.step(st, {"raw": RawFrame(header=f.header, ir=ir, depth=f.depth)})
    assert out.mask[REFLECTOR].sum() == 0 and out.mask[10:100, 60].all()


def test_static_trial_does_not_learn_a_standing_subject() -> None:
    outs = run([raw(k, trial="static") for k in range(45)])
    assert not outs[-1][0].mask.any()


def test_calibration_frames_learn_and_publish_nothing() -> None:
    st = clean.init(clean.PARAMS.resolve())
    for k in range(35):
        st, out = clean.step(st, {"raw": raw(k, trial="calibration")})
        assert out == []
    st, (out,) = clean.step(st, {"raw": raw(0, trial="walk-01")})
    assert out.mask[REFLECTOR].all()  # known from the calibration recording


def test_floor_markers_from_calibration_are_masked_from_the_first_frame() -> None:
    cal = CalibrationRecord(
        header=CalibrationRecord.make_header("cam0", "calibration", 99, 5, last=True),
        floor_pixels=np.array([[100.0, 100.0]]),
        floor_points=np.zeros((1, 3)),
        floor_plane=np.array([0.0, -1.0, 0.0, 800.0]),
        start=np.zeros(3),
        end=np.zeros(3),
        status="Done",
        w=20000.0,
        r_b=2.0,
        camera={"model": "x"},
    )
    f = raw(0)
    ir = f.ir.copy()
    ir[99:102, 99:102] = 65535
    f = RawFrame(header=f.header, ir=ir, depth=f.depth)
    ((out,),) = run([f], cal)
    assert out.mask[100, 100] == 1 and out.ir[100, 100] == 0
    assert out.camera == {"model": "x"}  # the session intrinsics travel to locate
    ((out2,),) = run([f], cal, mask_floor_markers=False)
    assert out2.mask[100, 100] == 0


def test_inconsistent_depth_range_is_rejected_at_start() -> None:
    with pytest.raises(ParameterError, match="min_depth"):
        clean.init(clean.PARAMS.resolve({"min_depth": 5000.0, "max_depth": 4000.0}))
    with pytest.raises(ParameterError, match="still_frames"):
        clean.PARAMS.resolve({"still_frames": 0})
