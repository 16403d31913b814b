"""The gait stage's heel extension (``gaitcore.extend_back``) on small literal tracks, and on
a walk whose heel labels start only at each landing (the stage end to end)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_gait_stage import run_stage

from gaitflow import gaitcore as gc
from gaitflow.bench import gait as bg
from gaitflow.markers import MARKER_INDEX
from gaitflow.sim import simulate_session

HEE = MARKER_INDEX["L_HEE"]
ANK = MARKER_INDEX["L_ANK"]


def _track(n: int = 8, named_from: int = 4):
    """A left heel moving +10 px and -5 mm depth a frame, named from ``named_from`` on; its
    blob in the frames before is left unnamed (a spare), at the pixel and depth it had."""
    pix = np.full((n, 20, 2), np.nan)
    pos = np.full((n, 20, 3), np.nan)
    u = 100.0 + 10.0 * np.arange(n)
    z = 2500.0 - 5.0 * np.arange(n)
    pix[named_from:, HEE] = np.c_[u, np.full(n, 300.0)][named_from:]
    pos[named_from:, HEE] = np.c_[u, np.zeros(n), z][named_from:]
    spare_pix = [np.zeros((0, 2)) for _ in range(n)]
    spare_pos = [np.zeros((0, 3)) for _ in range(n)]
    for f in range(named_from):
        spare_pix[f] = np.array([[u[f], 300.0]])
        spare_pos[f] = np.array([[u[f], 0.0, z[f]]])
    return np.arange(n), pix, pos, spare_pix, spare_pos


def _extend(idx, pix, pos, sp, sq, in_pass=None, **kw):
    in_pass = np.ones(len(idx), dtype=bool) if in_pass is None else in_pass
    return gc.extend_back(idx, pix, pos, sp, sq, [HEE], in_pass, **kw)


def test_a_heel_run_is_extended_back_onto_its_unnamed_blobs():
    idx, pix, pos, sp, sq = _track()
    p2, q2, added = _extend(idx, pix, pos, sp, sq)
    assert added[:4, HEE].all() and not added[4:].any()
    np.testing.assert_allclose(p2[:4, HEE, 0], [100, 110, 120, 130])
    np.testing.assert_allclose(q2[:4, HEE, 2], [2500, 2495, 2490, 2485])
    # the inputs are not changed
    assert np.isnan(pix[:4, HEE]).all() and np.isnan(pos[:4, HEE]).all()


def test_the_extension_stops_after_max_frames():
    idx, pix, pos, sp, sq = _track()
    _, _, added = _extend(idx, pix, pos, sp, sq, max_frames=2)
    assert added[:, HEE].tolist() == [False, False, True, True] + [False] * 4


def test_the_extension_stops_where_a_second_blob_is_as_near():
    idx, pix, pos, sp, sq = _track()
    # frame 2: a second unnamed blob 6 px from the heel's (within the 8 px separation)
    sp[2] = np.vstack([sp[2], sp[2] + [0.0, 6.0]])
    sq[2] = np.vstack([sq[2], sq[2]])
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert added[:, HEE].tolist() == [False, False, False, True] + [False] * 4
    # 20 px away it is no rival
    sp[2][1] = sp[2][0] + [0.0, 20.0]
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert added[:4, HEE].all()


def test_a_blob_another_marker_predicts_is_not_taken():
    idx, pix, pos, sp, sq = _track()
    # the ankle, named with the heel from frame 4 on, moves with it 4 px below: its own
    # prediction for frame 3 lies 4 px from the heel's blob there (within the 8 px
    # separation), so the heel's track cannot tell the two apart and stops
    pix[4:, ANK] = pix[4:, HEE] + [0.0, 4.0]
    pos[4:, ANK] = pos[4:, HEE]
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert not added.any()
    pix[4:, ANK] = pix[4:, HEE] + [0.0, 20.0]  # 20 px below: no rival
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert added[:4, HEE].all()


def test_a_depth_that_breaks_the_track_stops_it():
    idx, pix, pos, sp, sq = _track()
    sq[2] = sq[2] - [0.0, 0.0, 80.0]  # 80 mm nearer: another surface
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert added[:, HEE].tolist() == [False, False, False, True] + [False] * 4
    # within a looser bound it is taken, and frames 1 and 0 (85 and 5 mm from the last)
    _, _, added = _extend(idx, pix, pos, sp, sq, depth_mm=100.0)
    assert added[:4, HEE].all()


def test_a_blob_off_the_predicted_path_is_not_taken():
    idx, pix, pos, sp, sq = _track()
    sp[3] = sp[3] + [0.0, 20.0]  # 20 px off; the gate is 6 px + half of 10 px/frame
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert not added.any()


def test_no_extension_outside_a_pass_across_a_dropped_frame_or_from_one_label():
    idx, pix, pos, sp, sq = _track()
    in_pass = np.ones(8, dtype=bool)
    in_pass[:2] = False
    _, _, added = _extend(idx, pix, pos, sp, sq, in_pass=in_pass)
    assert added[:, HEE].tolist() == [False, False, True, True] + [False] * 4
    dropped = idx.copy()
    dropped[:2] -= 1  # frame 1 -> 0 and 0 -> -1: frame 1 (index 2 - 1) was dropped
    _, _, added = _extend(dropped, pix, pos, sp, sq)
    assert added[:, HEE].tolist() == [False, False, True, True] + [False] * 4
    # a run of one label gives no velocity: not extended
    pix[5:, HEE] = np.nan
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert not added.any()


# --- the stage end to end ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def late_heels():
    """A walk of true markers whose heels are named only from each heel strike on: for the
    six frames before one, the heel's blob is left unnamed (a spare) and that foot's toe is
    unseen. No ankle is named, as for a far foot (label does not name the far ankle): a
    named ankle beside the heel's blob would stop the extension (a foot's markers cannot
    trade places)."""
    ses = simulate_session("btk_PiG_Motion-FlatFoot-Full", 0)
    name = ses.walks()[0]
    frames = list(bg._marker_frames(ses, name, noise_mm=3.0, seed=0))
    t = ses.recordings[name].times.time_s
    truth = bg.observable_events(ses, name)
    hidden = np.zeros((len(frames), 20), dtype=bool)
    unseen = np.zeros((len(frames), 20), dtype=bool)
    for e in truth:
        if e["kind"] == "FS":
            k = MARKER_INDEX[f"{e['side']}_HEE"]
            f = int(np.searchsorted(t, e["time_s"]))
            hidden[max(f - 6, 0) : f + 1, k] = True
            unseen[max(f - 6, 0) : f + 1, MARKER_INDEX[f"{e['side']}_TOE"]] = True
    unseen[:, [MARKER_INDEX["L_ANK"], MARKER_INDEX["R_ANK"]]] = True
    out = []
    for i, m in enumerate(frames):
        pix, pos = np.array(m.pixel), np.array(m.position)
        ks = np.flatnonzero(hidden[i] & np.isfinite(pix).all(axis=1))
        spare_pix, spare_pos = pix[ks].copy(), pos[ks].copy()
        pix[ks] = pos[ks] = np.nan
        pix[unseen[i]] = pos[unseen[i]] = np.nan
        # the labeller knows the walking direction inside the passes
        out.append(
            dataclasses.replace(
                m,
                pixel=pix,
                position=pos,
                direction=1,
                spare_pixel=spare_pix,
                spare_heel=spare_pos,
            )
        )
    return ses, name, frames, out, truth, bg._true_calibration(ses, name)


def _events(frames, cal, **params):
    return run_stage(frames, cal, **params)[-1].results["events"]


def test_heels_named_only_after_landing_still_give_their_heel_strikes(late_heels):
    _, _, whole, late, truth, cal = late_heels
    seen = bg.match_events(truth, _events(whole, cal))["heel_strike"]
    without = bg.match_events(truth, _events(late, cal, heel_extend_frames=0))["heel_strike"]
    with_it = bg.match_events(truth, _events(late, cal))["heel_strike"]
    # named late, the heel strikes are lost (no descent seen) ...
    assert without["miss"] >= seen["miss"] + 0.5 * seen["n_truth"], (without, seen)
    # ... and the extension finds them again, as timely as with every label given
    assert with_it["miss"] == seen["miss"] and with_it["false"] == seen["false"], (with_it, seen)
    assert np.mean(np.abs(with_it["errors_s"])) <= np.mean(np.abs(seen["errors_s"])) + 0.005


def test_a_named_marker_nearer_the_prediction_stops_it():
    idx, pix, pos, sp, sq = _track()
    toe = MARKER_INDEX["L_TOE"]
    # frame 2: the heel's blob 3 px off its predicted pixel (120, 300), a marker named
    # there 1 px off it (named in that frame only, so no track of its own predicts it)
    sp[2] = sp[2] + [3.0, 0.0]
    pix[2, toe] = [121.0, 300.0]
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert added[:, HEE].tolist() == [False, False, False, True] + [False] * 4
    pix[2, toe] = [160.0, 300.0]
    _, _, added = _extend(idx, pix, pos, sp, sq)
    assert added[:4, HEE].all()
