"""Simulated sessions: API, determinism, protocol, ground truth."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from gaitflow.schemas._codec import decode
from gaitflow.schemas.raw import RawFrame
from gaitflow.schemas.truth import GroundTruth

from gaitflow.camera import Camera
from gaitflow.errors import ConfigError
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES
from gaitflow.sim import list_trials
from gaitflow.sim.body import build_body, knee_flexion, load_trial
from gaitflow.sim.config import SimConfig
from gaitflow.sim.render import SAT
from gaitflow.sim.session import simulate_session

TRIAL = "btk_PiG_Motion-FlatFoot-Full"
OTHER_SIDE = {"L": "R", "R": "L"}


@pytest.fixture(scope="module")
def ses():
    return simulate_session(TRIAL, seed=7, config=SimConfig.quick())


def test_bundled_trials_and_attribution() -> None:
    names = list_trials()
    assert len(names) >= 4
    assert "btk_c3dorg_sample04_Matt" in names
    for name in names:
        tr = load_trial(name)
        assert tr.meta.get("licence") and tr.meta.get("source")
        assert len(tr.events) >= 4


def test_api_and_camera_json(ses) -> None:
    assert list(ses.recordings)[:3] == ["calibration", "static", "walk-01"]
    cam = Camera.from_json(ses.camera_json)
    assert cam == ses.camera
    assert ses.camera_json["marker_diameter_mm"] == 25
    assert ses.camera_json["calibration_markers"] == 4
    assert ses.camera_json["subject"] == {"id": "S01"}
    json.dumps(ses.camera_json)


def test_frames_are_deterministic_for_a_seed(ses) -> None:
    other = simulate_session(TRIAL, seed=7, config=SimConfig.quick())
    third = simulate_session(TRIAL, seed=8, config=SimConfig.quick())
    for k in (0, 40):
        a, ga = ses.recordings["walk-01"].frame(k)
        b, gb = other.recordings["walk-01"].frame(k)
        c, _ = third.recordings["walk-01"].frame(k)
        assert a.ir.tobytes() == b.ir.tobytes() and a.depth.tobytes() == b.depth.tobytes()
        assert ga.encode(publish_ns=0) == gb.encode(publish_ns=0)
        assert a.ir.tobytes() != c.ir.tobytes()


def test_timestamps_jitter_and_drops() -> None:
    s = simulate_session(TRIAL, seed=1, config=SimConfig.quick(drop_prob=0.1))
    rec = s.recordings["walk-01"]
    idx, t = rec.times.index, rec.times.time_s
    assert idx[0] == 0 and np.all(np.diff(idx) >= 1) and np.any(np.diff(idx) > 1)
    dt = np.diff(t) / np.diff(idx)
    assert np.all(np.diff(t) > 0)
    assert abs(np.median(dt) - 1 / 30) < 1e-3 and dt.std() > 1e-5
    raw, _ = rec.frame(len(rec) - 1, last=True)
    assert raw.header.last and raw.header.trial == "walk-01"


def test_the_walk_back_can_leave_the_walking_line(ses) -> None:
    # return_offset_mm: the subject walks back 300 mm farther from the camera; the walk
    # out stays where it was (world y = away from the camera).
    off = simulate_session(TRIAL, seed=7, config=SimConfig.quick(return_offset_mm=300.0))
    pelvis = [MARKER_INDEX[n] for n in ("L_ASI", "R_ASI", "L_PSI", "R_PSI")]
    depth = {}
    for name, s in (("base", ses), ("offset", off)):
        wm = s.recordings["walk-01"].motion
        for p in wm.passes:
            t = p.t0 + np.linspace(0.2, 0.8, 7) * wm.pass_dur
            depth[name, p.name] = wm.markers_caps(t)[0][:, pelvis, 1].mean()
    assert depth["offset", "out"] == pytest.approx(depth["base", "out"], abs=0.1)
    assert depth["offset", "back"] - depth["base", "back"] == pytest.approx(300.0, abs=0.1)


def test_the_walk_can_start_from_the_images_right_edge(ses) -> None:
    # start_side "right" (the camera on the walkway's other side): the first pass walks
    # toward -x with the left side nearer the camera, the second the other way, and the
    # static pose faces the first pass's way; the same gait, so the same stride lengths.
    mir = simulate_session(TRIAL, seed=7, config=SimConfig.quick(start_side="right"))
    sho = [MARKER_INDEX["L_SHO"], MARKER_INDEX["R_SHO"]]
    for s, first, near_first in ((ses, 1.0, "R"), (mir, -1.0, "L")):
        wm = s.recordings["walk-01"].motion
        sides = (near_first, OTHER_SIDE[near_first])
        for p, sign, near in zip(wm.passes, (first, -first), sides, strict=True):
            t = p.t0 + np.array([0.3, 0.7]) * wm.pass_dur
            m = wm.markers_caps(t)[0]
            pelvis_x = m[:, [MARKER_INDEX["L_ASI"], MARKER_INDEX["R_ASI"]], 0].mean(axis=1)
            assert np.sign(pelvis_x[1] - pelvis_x[0]) == sign
            y = m[:, sho, 1].mean(axis=0)  # world y: away from the camera
            assert (y[0] < y[1]) == (near == "L")
        summary = s.truth_summary("walk-01")
        assert [q["side_facing_camera"] for q in summary["passes"]] == list(sides)
        _raw, gt = s.recordings["static"].frame(3)
        y = gt.position[sho]  # camera space: Z away from the camera
        assert (y[0, 2] < y[1, 2]) == (near_first == "L")
        names = [f"{near_first}_{x}" for x in ("SHO", "ASI", "HIP", "KNE", "ANK", "HEE", "TOE")]
        assert gt.visible[[MARKER_INDEX[n] for n in names]].all()
    strides = [
        sorted(q["length_mm"] for q in x.truth_summary("walk-01")["spatiotemporal"]["strides"])
        for x in (ses, mir)
    ]
    assert len(strides[0]) >= 4
    assert strides[1] == pytest.approx(strides[0], abs=1e-6)
    with pytest.raises(ConfigError, match="start_side"):
        SimConfig.quick(start_side="middle")


def test_messages_round_trip(ses) -> None:
    raw, gt = ses.recordings["walk-01"].frame(30)
    assert raw.ir.dtype == np.uint16 and raw.ir.shape == (424, 512)
    r2 = decode(RawFrame, raw.encode())
    g2 = decode(GroundTruth, gt.encode())
    assert np.array_equal(r2.depth, raw.depth)
    assert g2.header.stream if hasattr(g2.header, "stream") else g2.header.schema == "truth"
    np.testing.assert_array_equal(g2.visible, gt.visible)
    assert g2.header.frame == raw.header.frame


def test_walk_ground_truth_matches_image(ses) -> None:
    """Visible markers are saturated at their pixel; both sides face the camera once."""
    rec = ses.recordings["walk-01"]
    facing = {"out": set(), "back": set()}
    n_vis = 0
    for k in range(0, len(rec), 6):
        raw, gt = rec.frame(k)
        for j in np.flatnonzero(gt.visible):
            u, v = np.rint(gt.pixel[j]).astype(int)
            assert raw.ir[max(v - 1, 0) : v + 2, max(u - 1, 0) : u + 2].max() == SAT
            n_vis += 1
        if gt.pass_name in facing:
            facing[gt.pass_name] |= {
                MARKER_NAMES[j][0]
                for j in np.flatnonzero(gt.visible)
                if MARKER_NAMES[j][2:] in ("KNE", "ANK", "TIB")
            }
        # Z of a visible marker agrees with its pixel through the camera model.
        ok = np.isfinite(gt.position).all(axis=1)
        uv = ses.camera.project(gt.position[ok])
        np.testing.assert_allclose(uv, gt.pixel[ok], atol=1e-9)
    assert n_vis > 100
    # Outward pass shows the right side's knee/ankle/tibia, the return the left side's.
    assert "R" in facing["out"] and "L" in facing["back"]


def test_arm_hides_pelvis_markers_sometimes(ses) -> None:
    rec = ses.recordings["walk-01"]
    occl = np.zeros(20, dtype=int)
    vv, uu = np.mgrid[0:424, 0:512]
    vis = np.zeros(20, dtype=int)
    for k in range(0, len(rec), 3):
        raw, gt = rec.frame(k)
        occl += gt.occluded
        vis += gt.visible
        for j in np.flatnonzero(gt.occluded):
            u, v = np.rint(gt.pixel[j]).astype(int)
            if not (0 <= u < 512 and 0 <= v < 424):
                continue
            # No other (even partly) seen marker within 8 px: the occluded one must be dark.
            seen = np.asarray(gt.visible_fraction) > 0
            others = [
                i
                for i in np.flatnonzero(seen)
                if i != j and np.hypot(*(gt.pixel[i] - gt.pixel[j])) < 8
            ]
            if not others:
                # At most a sliver of its disc shows: most of the footprint is not saturated.
                rad = ses.camera.fx * 12.5 / gt.position[j, 2]
                win = (slice(max(v - 8, 0), v + 9), slice(max(u - 8, 0), u + 9))
                disc = np.hypot(uu[win] - gt.pixel[j, 0], vv[win] - gt.pixel[j, 1]) <= rad
                ir = raw.ir[win]
                assert (ir[disc] == SAT).mean() < 0.75
                if gt.visible_fraction[j] == 0.0:
                    assert (ir[disc] == SAT).sum() == 0
    near_hip = occl[MARKER_INDEX["R_HIP"]] + occl[MARKER_INDEX["R_THI"]]
    assert near_hip > 0  # the swinging right arm passes in front of them
    assert vis[MARKER_INDEX["R_HIP"]] > 0  # ... but not all the time


def test_static_pose_shows_all_near_side_markers(ses) -> None:
    _raw, gt = ses.recordings["static"].frame(3)
    near = [
        MARKER_INDEX[f"R_{s}"]
        for s in ("SHO", "ASI", "HIP", "THI", "KNE", "TIB", "ANK", "HEE", "TOE")
    ]
    assert gt.visible[near].all()
    assert gt.pass_name == ""


def test_calibration_markers_appear_one_at_a_time(ses) -> None:
    rec = ses.recordings["calibration"]
    summ = ses.truth_summary("calibration")
    pts = np.array(summ["calibration_markers_cam"])
    assert pts.shape == (4, 3)
    plane = np.array(summ["floor_plane_cam"])
    # Marker centres sit one radius above the floor plane (normal points up).
    np.testing.assert_allclose(pts @ plane[:3] + plane[3], 12.5, atol=1e-6)
    counts = []
    for k in range(0, len(rec), 4):
        raw, _ = rec.frame(k)
        px = np.array(summ["calibration_markers_px"])
        n = 0
        for u, v in np.rint(px).astype(int):
            n += raw.ir[v - 1 : v + 2, u - 1 : u + 2].max() == SAT
        counts.append(n)
    assert counts[0] == 0 and counts[-1] == 4
    assert np.all(np.diff(counts) >= 0) and set(counts) == {0, 1, 2, 3, 4}


def test_knee_flexion_tracks_plug_in_gait() -> None:
    tr = load_trial(TRIAL)
    body = build_body(tr, 12.5)
    sim = knee_flexion(body.markers)
    ref = tr.knee_ref
    ok = np.isfinite(ref).all(axis=1)
    for k in range(2):
        r = np.corrcoef(sim[ok, k], ref[ok, k])[0, 1]
        assert r > 0.9
        assert np.sqrt(np.mean((sim[ok, k] - ref[ok, k]) ** 2)) < 12.0


def test_spatiotemporal_parameters_plausible(ses) -> None:
    summ = ses.truth_summary("walk-01")
    ev = summ["events"]
    assert {e["pass"] for e in ev} == {"out", "back"}
    st = summ["spatiotemporal"]
    speed = st["mean"]["speed_m_s"]
    assert abs(speed - 1.158) / 1.158 < 0.15  # index.csv mean speed of this trial
    for side in ("L", "R"):
        m = st["mean"][side]
        assert 1000 < m["stride_length_mm"] < 1700
        assert (
            0.9 * m["stride_length_mm"] / 2
            < m["step_length_mm"]
            < 1.1 * m["stride_length_mm"] / 2 + 60
        )
        assert 55 < m["stance_pct"] < 70
    # Events reach the per-frame messages.
    rec = ses.recordings["walk-01"]
    t_ev = ev[2]["time_s"]
    k = int(np.argmin(np.abs(rec.times.time_s - t_ev)))
    _, gt = rec.frame(k)
    if abs(rec.times.time_s[k] - t_ev) < 0.5 / 30:
        assert [ev[2]["side"], ev[2]["kind"]] in [e[:2] for e in gt.events]


@pytest.mark.parametrize("trial", list_trials())
def test_walk_events_alternate_on_every_trial(trial: str) -> None:
    """Source plus copied events form a regular L/R sequence on both passes."""
    ses = simulate_session(trial, seed=0, config=SimConfig.quick())
    summ = ses.truth_summary("walk-01")
    wm = ses.recordings["walk-01"].motion
    for p in ("out", "back"):
        ev = [e for e in summ["events"] if e["pass"] == p]
        fs = [e["side"] for e in ev if e["kind"] == "FS"]
        fo = [e["side"] for e in ev if e["kind"] == "FO"]
        assert len(fs) >= 4 and len(fo) >= 4
        assert all(a != b for a, b in itertools.pairwise(fs))
        assert all(a != b for a, b in itertools.pairwise(fo))
        # Every event lies within its pass, and the source's own events are all there.
        ps = next(q for q in summ["passes"] if q["name"] == p)
        assert all(ps["start_s"] <= e["time_s"] <= ps["end_s"] for e in ev)
        assert sum(not e["copied"] for e in ev) == len(wm.trial.events)
    # The subject starts and ends each pass outside the image.
    for p in wm.passes:
        for t in (p.t0, p.t0 + wm.pass_dur):
            m = ses.renderer.to_cam(wm.markers_caps(np.array([t]))[0][0])
            uv = ses.camera.project(m)
            assert not ((uv[:, 0] >= 0) & (uv[:, 0] < 512)).any()


def _ring_depth(depth: np.ndarray, uv: np.ndarray, r_px: float) -> float:
    """Median valid depth in the ring 0.5-2.5 px outside a marker's disc (NaN if < 4 px)."""
    v0, u0 = int(uv[1]), int(uv[0])
    h, w = depth.shape
    sl = (slice(max(v0 - 12, 0), min(v0 + 13, h)), slice(max(u0 - 12, 0), min(u0 + 13, w)))
    vv, uu = np.mgrid[sl]
    d = np.hypot(uu - uv[0], vv - uv[1])
    ring = (d > r_px + 0.5) & (d <= r_px + 2.5) & (depth[sl] > 0)
    return float(np.median(depth[sl][ring])) if ring.sum() >= 4 else float("nan")


def test_markers_sit_on_the_skin(ses) -> None:
    """Around each marker's depth hole is the skin under it, not a surface 40-70 mm away.

    Static side view: every visible, unmerged marker whose skin normal faces the camera
    (within 45 degrees); the ring's median depth is within 15 mm of centre depth + radius.
    """
    rec = ses.recordings["static"]
    raw, gt = rec.frame(len(rec) // 2)
    body = rec.motion.body
    rmark = ses.config.marker_radius_mm
    checked = []
    for j, name in enumerate(MARKER_NAMES):
        if not gt.visible[j] or gt.merged[j]:
            continue
        c = gt.position[j]
        n_cam = ses.renderer.R @ body.normal[0, j]
        if -(n_cam @ c) / np.linalg.norm(c) < np.cos(np.radians(45.0)):
            continue
        ring = _ring_depth(raw.depth, gt.pixel[j], ses.camera.fx * rmark / c[2])
        checked.append(name)
        assert abs(ring - (c[2] + rmark)) < 15.0, (name, ring - c[2] - rmark)
    assert {"R_HIP", "R_THI", "R_KNE", "R_TIB", "R_ANK"} <= set(checked), checked


def test_lateral_markers_sit_on_the_skin_while_walking(ses) -> None:
    """The lateral limb markers of the near side, over the walk: ring median within 15 mm."""
    rec = ses.recordings["walk-01"]
    rmark = ses.config.marker_radius_mm
    err: dict[str, list[float]] = {}
    for k in range(0, len(rec), 5):
        raw, gt = rec.frame(k)
        for site in ("HIP", "THI", "KNE", "TIB", "ANK"):
            near = "R" if gt.pass_name == "out" else "L"
            j = MARKER_INDEX[f"{near}_{site}"]
            if gt.pass_name not in ("out", "back") or not gt.visible[j] or gt.merged[j]:
                continue
            c = gt.position[j]
            ring = _ring_depth(raw.depth, gt.pixel[j], ses.camera.fx * rmark / c[2])
            if np.isfinite(ring):
                err.setdefault(site, []).append(ring - c[2] - rmark)
    for site, e in err.items():
        assert len(e) >= 5, (site, len(e))
        assert abs(np.median(e)) < 15.0, (site, np.median(e))


def test_wand_markers_stand_off_the_limb_with_nothing_under_them() -> None:
    """On sticks, the thigh and tibia wands of this trial (48 mm off the limb) carry no
    skin patch: the ring around their depth hole is the limb behind, while the knee and
    ankle markers still sit on the skin."""
    wands = simulate_session(TRIAL, seed=7, config=SimConfig.quick(wand_mount="stick"))
    rec = wands.recordings["static"]
    raw, gt = rec.frame(len(rec) // 2)
    rmark = wands.config.marker_radius_mm
    behind = {}
    for name in ("R_THI", "R_TIB", "R_KNE", "R_ANK"):
        j = MARKER_INDEX[name]
        assert gt.visible[j] and not gt.merged[j], name
        c = gt.position[j]
        ring = _ring_depth(raw.depth, gt.pixel[j], wands.camera.fx * rmark / c[2])
        behind[name] = ring - (c[2] + rmark)
    assert behind["R_THI"] > 30.0 and behind["R_TIB"] > 30.0, behind
    assert abs(behind["R_KNE"]) < 15.0 and abs(behind["R_ANK"]) < 15.0, behind


def test_wand_markers_taped_to_the_skin_sit_on_the_limb(ses) -> None:
    """The default mount (``skin``) moves this trial's wands in onto the limb: the thigh
    and tibia markers' ring is their own skin, and they stand 30+ mm nearer the limb's
    axis than where the source lab's wands held them (the ``patch`` mount)."""
    assert ses.config.wand_mount == "skin"
    patch = simulate_session(TRIAL, seed=7, config=SimConfig.quick(wand_mount="patch"))
    rec = ses.recordings["static"]
    raw, gt = rec.frame(len(rec) // 2)
    rmark = ses.config.marker_radius_mm
    _, gt0 = patch.recordings["static"].frame(len(rec) // 2)
    for name in ("R_THI", "R_TIB"):
        j = MARKER_INDEX[name]
        c = gt.position[j]
        ring = _ring_depth(raw.depth, gt.pixel[j], ses.camera.fx * rmark / c[2])
        assert abs(ring - (c[2] + rmark)) < 15.0, (name, ring - c[2] - rmark)
        assert c[2] - gt0.position[j][2] > 30.0, (name, c[2] - gt0.position[j][2])
    with pytest.raises(ConfigError, match="wand_mount='glue'"):
        SimConfig.quick(wand_mount="glue")


def test_truth_is_at_mid_exposure(ses) -> None:
    """Ground truth = marker positions at the frame's time, not at a blur sample."""
    rec = ses.recordings["walk-01"]
    cfg = ses.config
    assert cfg.blur_samples % 2 == 0  # the case where no blur sample is at mid-exposure
    k = len(rec) // 3
    _raw, gt = rec.frame(k)
    t = float(rec.times.time_s[k])
    exact = ses.renderer.to_cam(rec.motion.markers_caps(np.array([t]))[0][0])
    np.testing.assert_allclose(gt.position, exact, atol=1e-9)
    pose = rec.motion.pose(t, cfg.exposure_ms / 1000.0, cfg.blur_samples)
    late = ses.renderer.to_cam(pose.spheres[cfg.blur_samples // 2])
    assert np.nanmax(np.linalg.norm(late - gt.position, axis=1)) > 1.0  # feet move > 1 mm


def test_overlapping_markers_are_flagged_merged(ses) -> None:
    """Left and right PSI overlap in a side view: merged (or the far one occluded)."""
    rec = ses.recordings["walk-01"]
    li, ri = MARKER_INDEX["L_PSI"], MARKER_INDEX["R_PSI"]
    n_both = n_merged = 0
    for k in range(0, len(rec), 4):
        _raw, gt = rec.frame(k)
        assert len(gt.merged) == len(MARKER_NAMES)
        assert not np.any(np.asarray(gt.merged) & ~gt.visible)
        if gt.visible[li] and gt.visible[ri]:
            n_both += 1
            d = np.linalg.norm(gt.pixel[li] - gt.pixel[ri])
            if d < 3.0:
                assert gt.merged[li] and gt.merged[ri], d
                n_merged += 1
    assert n_merged > 0, n_both


def test_reflectors_put_down_after_the_calibration() -> None:
    """``strays_late``: the static reflectors are missing from the calibration recording
    and present from the static pose on; ``strays`` has them throughout."""
    from gaitflow.sim.variants import STRAYS, sim_config

    floor_marker = STRAYS[3]  # on the floor, never hidden by the subject standing still
    for name, in_calibration in (("strays", True), ("strays_late", False)):
        s = simulate_session(TRIAL, seed=7, config=sim_config(name))
        uv = s.renderer.cam.project(s.renderer.to_cam(np.array(floor_marker))[None])[0]
        win = (slice(round(uv[1]) - 5, round(uv[1]) + 6), slice(round(uv[0]) - 5, round(uv[0]) + 6))
        cal, _ = s.recordings["calibration"].frame(0)
        static, _ = s.recordings["static"].frame(0)
        assert bool(cal.ir[win].max() == SAT) == in_calibration
        assert static.ir[win].max() == SAT and (static.depth[win] == 0).any()
    with pytest.raises(ConfigError, match="reflectors_from"):
        SimConfig(reflectors_from="walkway")


def test_shoe_reflectors_ride_on_the_foot_and_stay_out_of_the_truth() -> None:
    """``shoes``: a reflector in the foot's frame (forward heel -> toe, up, outward to the
    ankle marker's side), saturating in the image where no marker is, never in the truth."""
    from gaitflow.sim.variants import sim_config
    from gaitflow.sim.walk import shoe_reflectors

    m = np.zeros((1, 20, 3))
    for side, y in (("L", 100.0), ("R", -100.0)):
        m[0, MARKER_INDEX[f"{side}_HEE"]] = (0.0, y, 40.0)
        m[0, MARKER_INDEX[f"{side}_TOE"]] = (200.0, y, 40.0)
        # the lateral malleolus lies outward: +y for the left foot, -y for the right
        m[0, MARKER_INDEX[f"{side}_ANK"]] = (50.0, y + np.sign(y) * 30.0, 80.0)
    got = shoe_reflectors(m, [(60.0, -10.0, 45.0)], scale=2.0)
    np.testing.assert_allclose(got[0], [[120.0, 190.0, 20.0], [120.0, -190.0, 20.0]])
    with pytest.raises(ConfigError, match="shoe_reflectors"):
        SimConfig(shoe_reflectors=((1.0, 2.0),))

    cfg = sim_config("shoes")
    plain = simulate_session(TRIAL, seed=7, config=sim_config("base"))
    shod = simulate_session(TRIAL, seed=7, config=cfg)
    a, ta = plain.recordings["static"].frame(0)
    b, tb = shod.recordings["static"].frame(0)
    np.testing.assert_array_equal(np.asarray(ta.position), np.asarray(tb.position))
    assert np.asarray(tb.visible).shape == (20,)
    # the near shoe's reflector saturates pixels that were not saturated without it
    assert ((b.ir == SAT) & (a.ir < SAT)).sum() >= 4


def _swings(events: list[dict], side: str, pas: str) -> np.ndarray:
    """Toe off to the next strike of one foot in one pass, s."""
    ev = [e for e in events if e["pass"] == pas and e["side"] == side]
    fs = np.array([e["time_s"] for e in ev if e["kind"] == "FS"])
    out = []
    for e in ev:
        later = fs[fs > e["time_s"]] if e["kind"] == "FO" else ()
        if len(later):
            out.append(later[0] - e["time_s"])
    return np.array(out)


def test_a_paretic_swing_lasts_longer_and_the_body_slows_smoothly() -> None:
    """The paretic leg's swing lasts ``paretic_swing`` times as long; the other leg's swing
    and every position along the path are unchanged (only the timing is warped)."""
    sym, par = (
        simulate_session(TRIAL, seed=0, config=SimConfig.quick(paretic_swing=k)) for k in (1.0, 1.5)
    )
    a, b = (s.truth_summary("walk-01") for s in (sym, par))
    for pas in ("out", "back"):
        la, lb = (_swings(x["events"], "L", pas) for x in (a, b))
        np.testing.assert_allclose(lb, 1.5 * la, rtol=0.01)
        ra, rb = (_swings(x["events"], "R", pas) for x in (a, b))
        np.testing.assert_allclose(rb, ra, atol=1e-9)
    ma, mb = (x["spatiotemporal"]["mean"] for x in (a, b))
    for side, sign in (("L", -1), ("R", 1)):
        # The paretic leg's stance is a smaller share of its cycle, the other's a larger.
        assert sign * (mb[side]["stance_pct"] - ma[side]["stance_pct"]) > 5.0
        assert mb[side]["stride_length_mm"] == pytest.approx(ma[side]["stride_length_mm"], rel=1e-6)
    ws, wp = (s.recordings["walk-01"].motion for s in (sym, par))
    # Same places, later: the heel at each strike, and the pass's end.
    hee = MARKER_INDEX["L_HEE"]
    for es, ep in zip(a["events"], b["events"], strict=True):
        assert (es["side"], es["kind"], es["pass"]) == (ep["side"], ep["kind"], ep["pass"])
        pa = ws.markers_caps(np.array([es["time_s"]]))[0][0, hee]
        pb = wp.markers_caps(np.array([ep["time_s"]]))[0][0, hee]
        np.testing.assert_allclose(pb, pa, atol=0.5)
    assert wp.pass_dur > ws.pass_dur + 0.5
    p = wp.passes[1]
    tau = np.linspace(-p.pre, wp.src_dur + p.post, 50)
    np.testing.assert_allclose(wp._tau(p, wp.time_at(p, tau)), tau, atol=1e-6)
    # The shoulder slows to about half its speed mid-swing, without a jump in speed.
    v = {}
    for name, w in (("sym", ws), ("par", wp)):
        t = np.arange(0.3, w.pass_dur - 0.3, 0.005)  # the outward pass
        v[name] = np.diff(w.markers_caps(t)[0][:, MARKER_INDEX["R_SHO"], 0]) / 0.005
    assert v["par"].min() < 0.75 * v["sym"].min()
    assert np.abs(np.diff(v["par"])).max() < 60.0  # mm/s per 5 ms: at most 12 m/s^2
    with pytest.raises(ConfigError, match="paretic_swing"):
        SimConfig(paretic_swing=0.8)
    with pytest.raises(ConfigError, match="paretic_side"):
        SimConfig(paretic_side="X")
