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


def test_floor_markers_from_calibration_are_masked_from_the_first_frame(flat_record) -> None:
    cal = flat_record(20000.0, 2.0, [[100.0, 100.0]], 99, 5, camera={"model": "x"})
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


def test_interferers_are_matched_at_the_level_they_were_learned_at(flat_record) -> None:
    # A chrome pole whose highlight dims between bright stretches: at the level the empty
    # walkway's first frame gives (about 17 000) it is nine pieces, at the calibration
    # record's w (10 000) one long component. At the walk's level that component matched
    # none of the pieces' tracks, lifted their boxes and showed the pole.
    def pole(k: int, trial: str) -> RawFrame:
        f = raw(k, trial=trial)
        ir = f.ir.copy()
        ir[10:98, 60] = 40000
        ir[16:98:11, 60] = 12000  # the dim rows that part the pieces
        return RawFrame(header=f.header, ir=ir, depth=f.depth)

    cal = flat_record(10000.0, 2.0, frame=99, capture_ns=5, camera={})
    st = clean.init(clean.PARAMS.resolve())
    for k in range(35):
        st, _ = clean.step(st, {"raw": pole(k, "calibration")})
    learned = st.cameras["cam0"]
    assert sum(t.source == "still" for t in learned.tracks) == 10  # nine pieces and REFLECTOR
    for k in range(40):
        st, (out,) = clean.step(st, {"raw": pole(k, "walk-01"), "calibration": cal})
        assert out.mask[10:98, 60].all() and (out.ir[10:98, 60] == 0).all(), k
        assert out.mask[REFLECTOR].all(), k
    walk = st.cameras["cam0"]
    assert walk.level == 10000.0 and walk.candidates == ()  # the joined pole is explained
    assert {t.level for t in walk.tracks} == {learned.level}  # the level learned at

    def walk_frame(k: int, rows: slice, cols: slice, value: int) -> CleanFrame:
        nonlocal st
        f = pole(k, "walk-01")
        ir = f.ir.copy()
        ir[rows, cols] = value
        st, (out,) = clean.step(
            st, {"raw": RawFrame(header=f.header, ir=ir, depth=f.depth), "calibration": cal}
        )
        return out

    # Noise breaks a piece in two at the learned level: both halves lie inside its bar's
    # box, so they are pieces of it there too, and the pole stays masked.
    out = walk_frame(39, slice(21, 22), slice(60, 61), 12000)
    assert out.mask[10:98, 60].all() and out.interferers == 10
    # A marker too dim for the learned level but above the walk's still lifts a box it
    # touches: it holds no interferer's component.
    out = walk_frame(40, slice(25, 28), slice(31, 34), 14000)
    assert out.mask[REFLECTOR].sum() == 0 and out.ir[26, 32] == 14000
    assert out.mask[10:98, 60].all()
    # A marker touching the pole joins its component at both levels; at the learned level
    # that changed piece matches no track, so the marker lifts the pole's boxes.
    out = walk_frame(41, slice(50, 53), slice(61, 64), 65535)
    assert out.ir[51, 62] == 65535 and out.mask[51, 61:64].sum() == 0
    # A marker too dim to show at the learned level joins the pole at the walk's; it sticks
    # out of the pieces' boxes, so it lifts them too.
    out = walk_frame(42, slice(50, 53), slice(61, 64), 14000)
    assert out.ir[51, 63] == 14000 and out.mask[51, 61:64].sum() == 0


def test_a_reflector_learned_below_the_walks_level_stays_masked(flat_record) -> None:
    # A reflector with a dimmer rim: 4 x 4 px above the empty walkway's level, its 2 x 2
    # core above the calibration record's w (30 000). At the walk's level the core is a
    # component of its own, which must not lift the box learned for the whole reflector.
    def halo(k: int, trial: str) -> RawFrame:
        f = raw(k, trial=trial)
        ir = f.ir.copy()
        ir[60:64, 100:104] = 20000
        ir[61:63, 101:103] = 65535
        return RawFrame(header=f.header, ir=ir, depth=f.depth)

    cal = flat_record(30000.0, 2.0, frame=99, capture_ns=5, camera={})
    st = clean.init(clean.PARAMS.resolve())
    for k in range(35):
        st, _ = clean.step(st, {"raw": halo(k, "calibration")})
    for k in range(40):
        st, (out,) = clean.step(st, {"raw": halo(k, "walk-01"), "calibration": cal})
        assert out.mask[60:64, 100:104].all() and out.mask[REFLECTOR].all(), k
    assert st.cameras["cam0"].candidates == ()
