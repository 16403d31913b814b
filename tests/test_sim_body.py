"""Simulated subject: derived-marker rules and the capsule body."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from gaitflow.errors import ConfigError, InputError
from gaitflow.markers import MARKER_INDEX, MARKER_NAMES
from gaitflow.sim.body import (
    SEGMENT_INDEX,
    SEGMENT_NAMES,
    WAND_RADIUS_MM,
    build_body,
    crouch_trial,
    derive_markers,
    load_trial,
    pelvis_frame,
    scale_trial,
    trials_dir,
)
from gaitflow.sim.body import knee_flexion as sim_knee_flexion
from gaitflow.sim.config import SimConfig
from gaitflow.sim.walk import _period


def test_a_scaled_trial_is_a_smaller_subject_walking_the_same_gait() -> None:
    src = load_trial("c3dorg_s00_vicon_CGM24")
    child = scale_trial(src, 0.64)
    assert scale_trial(src, 1.0) is src
    for name in ("L_KNE", "R_HEE", "L_ASI"):
        np.testing.assert_allclose(child.markers[name], 0.64 * src.markers[name])
    np.testing.assert_allclose(child.t, 0.8 * src.t)  # Froude: times x sqrt(0.64)
    assert child.rate_hz == pytest.approx(src.rate_hz / 0.8)
    assert [(round(t / 0.8, 9), s, k) for t, s, k in child.events] == [
        (round(t, 9), s, k) for t, s, k in src.events
    ]

    # joint angles unchanged (the ankle's, between shank and foot markers)
    def ankle_angle(tr):
        a, b = tr.markers["L_KNE"] - tr.markers["L_ANK"], tr.markers["L_TOE"] - tr.markers["L_ANK"]
        cos = (a * b).sum(axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))

    np.testing.assert_allclose(ankle_angle(child), ankle_angle(src), atol=1e-9)
    # the body built from it stands 0.64 as tall: shoulders' mean height
    sho = MARKER_INDEX["L_SHO"]
    h = [build_body(tr, 12.5).markers[:, sho, 2].mean() for tr in (src, child)]
    assert h[1] == pytest.approx(0.64 * h[0], rel=0.02)
    with pytest.raises(ConfigError, match="body_scale"):
        SimConfig(body_scale=0.3)


def test_a_crouched_trial_keeps_the_feet_and_the_leg_lengths_and_bends_the_knees() -> None:
    src = load_trial("c3dorg_s00_vicon_CGM24")
    crouch = crouch_trial(src, 30.0)
    assert crouch_trial(src, 0.0) is src
    for name in ("L_ANK", "L_HEE", "R_TOE"):
        np.testing.assert_array_equal(crouch.markers[name], src.markers[name])
    for name in ("L_ASI", "R_PSI"):
        np.testing.assert_allclose(crouch.markers[name], src.markers[name] - [0.0, 0.0, 30.0])
    a, b = (derive_markers(tr, 12.5) for tr in (src, crouch))
    for side in "LR":
        for p, q in (("HJC", "KJC"), ("KJC", "AJC")):
            la, lb = (np.linalg.norm(m[f"{side}_{p}"] - m[f"{side}_{q}"], axis=1) for m in (a, b))
            assert np.abs(lb - la).max() < 3.0  # thigh and shank keep their lengths
        # the thigh marker stays on its thigh: same distance from hip and knee centres
        for j in ("HJC", "KJC"):
            da, db = (np.linalg.norm(m[f"{side}_THI"] - m[f"{side}_{j}"], axis=1) for m in (a, b))
            assert np.abs(db - da).max() < 3.0
    ka, kb = (sim_knee_flexion(build_body(tr, 12.5).markers) for tr in (src, crouch))
    assert ka.min() < 5.0 and kb.min() > 25.0  # never straight: flexed through stance
    assert np.isnan(crouch.knee_ref).all()  # the source's Plug-in Gait angle no longer applies
    with pytest.raises(ConfigError, match="crouch_mm"):
        SimConfig(crouch_mm=-5.0)


def test_harrington_hip_joint_centre() -> None:
    # A pelvis facing +x, left = +y, up = +z: PW = 240, PD = 160.
    pw, pd = 240.0, 160.0
    m = {
        "L_ASI": np.array([[0.0, pw / 2, 900.0]]),
        "R_ASI": np.array([[0.0, -pw / 2, 900.0]]),
        "L_PSI": np.array([[-pd, 40.0, 900.0]]),
        "R_PSI": np.array([[-pd, -40.0, 900.0]]),
    }
    pf = pelvis_frame(m)
    assert pf.width == pytest.approx(pw) and pf.depth == pytest.approx(pd)
    want_l = [-0.24 * pd - 9.9, 0.33 * pw + 7.3, 900.0 - 0.30 * pw - 10.9]
    np.testing.assert_allclose(pf.hjc["L"][0], want_l, atol=1e-9)
    np.testing.assert_allclose(pf.hjc["R"][0], [want_l[0], -want_l[1], want_l[2]], atol=1e-9)


def test_derived_markers_follow_the_rules() -> None:
    tr = load_trial("bz_HC002D_straight_HC002D06")  # has SACR but no PSI
    assert "L_PSI" not in tr.markers
    m = derive_markers(tr, 12.5)
    pf = pelvis_frame({k: tr.markers[k] for k in ("L_ASI", "R_ASI", "SACR")})
    gap = np.linalg.norm(m["L_PSI"] - m["R_PSI"], axis=1)
    np.testing.assert_allclose(gap, 0.36 * pf.width, rtol=1e-6)
    np.testing.assert_allclose(0.5 * (m["L_PSI"] + m["R_PSI"]), tr.markers["SACR"], atol=1e-6)
    # HIP lies lateral of the hip joint centre by the trochanter offset.
    for side, sgn in (("L", 1), ("R", -1)):
        d = m[f"{side}_HIP"] - m[f"{side}_HJC"]
        lateral = sgn * (d * pf.left).sum(axis=1)
        np.testing.assert_allclose(lateral, 85.0 + 12.5, atol=5.0)


@pytest.mark.parametrize("trial", ["btk_PiG_Motion-FlatFoot-Full", "c3dorg_s00_vicon_CGM24"])
def test_heel_rule_close_to_real_heel(trial: str) -> None:
    tr = load_trial(trial)
    m = {k: v for k, v in tr.markers.items() if not k.endswith("_HEE")}
    d = derive_markers(dataclasses.replace(tr, markers=m), 7.0)
    for side in ("L", "R"):
        err = np.linalg.norm(d[f"{side}_HEE"] - tr.markers[f"{side}_HEE"], axis=1)
        assert np.median(err) < 40.0


def test_only_markers_standing_off_the_limb_are_wands() -> None:
    # CGM24's thigh and tibia markers are on the skin (5-17 mm off the capsule limb): no
    # mount touches them. Motion3's stand 77-107 mm off: on sticks they get a 6 mm stick
    # instead of a patch, taped to the skin they move in onto the limb.
    S = len(SEGMENT_NAMES)
    wands = [MARKER_INDEX[f"{s}_{m}"] for s in "LR" for m in ("THI", "TIB")]
    cgm = load_trial("c3dorg_s00_vicon_CGM24")
    a, b = build_body(cgm, 12.5, wand_mount="patch"), build_body(cgm, 12.5, wand_mount="stick")
    np.testing.assert_array_equal(a.radius, b.radius)
    np.testing.assert_array_equal(a.markers, build_body(cgm, 12.5).markers)
    m3 = load_trial("btk_PiG_Motion3_FF")
    patch, stick = (
        build_body(m3, 12.5, wand_mount="patch"),
        build_body(m3, 12.5, wand_mount="stick"),
    )
    assert (stick.radius[S + np.array(wands)] == WAND_RADIUS_MM).all()
    assert (patch.radius[S + np.array(wands)] > WAND_RADIUS_MM).all()
    skin = build_body(m3, 12.5)  # the default mount
    moved = np.linalg.norm(skin.markers[:, wands] - patch.markers[:, wands], axis=2)
    assert np.median(moved) > 50.0
    others = [i for i in range(20) if i not in wands]
    np.testing.assert_allclose(skin.markers[:, others], patch.markers[:, others])
    with pytest.raises(ConfigError, match="wand_mount='glue'"):
        build_body(m3, 12.5, wand_mount="glue")


def test_markers_sit_outside_their_segment() -> None:
    tr = load_trial("btk_PiG_Motion-FlatFoot-Full")
    body = build_body(tr, 12.5)
    assert body.markers.shape == (len(tr.t), 20, 3)
    assert np.isfinite(body.markers).all()
    # The near-side knee marker is outside the lower thigh and shank by at least its radius.
    for side in ("L", "R"):
        p = body.markers[:, MARKER_INDEX[f"{side}_KNE"]]
        k = SEGMENT_INDEX[f"{side}_thigh_lo"]
        a, b, r = body.cap_a[:, k], body.cap_b[:, k], body.radius[k]
        ab = b - a
        w = np.clip(((p - a) * ab).sum(1) / (ab * ab).sum(1), 0, 1)
        dist = np.linalg.norm(p - (a + w[:, None] * ab), axis=1)
        assert np.percentile(dist - r, 5) >= 12.5
    # Feet on the floor: the heels come within a few cm of z = 0 in stance, but no marker
    # sphere sinks into it.
    hee = body.markers[:, [MARKER_INDEX["L_HEE"], MARKER_INDEX["R_HEE"]], 2]
    assert 12.5 <= hee.min() < 60.0
    assert body.markers[..., 2].min() >= 12.5
    assert len(MARKER_NAMES) == 20


def _heels(z: np.ndarray, t: np.ndarray) -> SimpleNamespace:
    m = np.zeros((len(t), 20, 3))
    m[:, MARKER_INDEX["L_HEE"], 2] = z
    return SimpleNamespace(markers=m, t=t)


def test_gait_period_from_the_heels_and_a_labelled_step() -> None:
    t = np.arange(0.0, 2.5, 0.01)
    cycle = np.sin(2 * np.pi * t / 1.08)
    assert _period(_heels(cycle, t)) == pytest.approx(1.08, abs=0.011)
    assert _period(_heels(cycle, t), around=1.0) == pytest.approx(1.08, abs=0.011)
    # A short trial whose heel signal is dominated by something else: over the whole
    # range the autocorrelation rises to the window's edge (1.8 s, no peak); around twice
    # a labelled step's time the edge is no peak either, and that time is the period.
    bump = 0.2 * cycle + 2.0 * np.exp(-(((t - 1.25) / 0.3) ** 2))
    assert _period(_heels(bump, t)) == pytest.approx(1.8, abs=0.011)
    assert _period(_heels(bump, t), around=1.08) == pytest.approx(1.08)


def test_a_trial_given_by_path_is_the_same_trial() -> None:
    by_path = load_trial(str(trials_dir() / "btk_PiG_Motion3_FF.npz"))
    by_id = load_trial("btk_PiG_Motion3_FF")
    np.testing.assert_array_equal(by_path.t, by_id.t)
    assert by_path.events == by_id.events
    with pytest.raises(InputError, match=r"nowhere\.npz"):
        load_trial("/nowhere.npz")
