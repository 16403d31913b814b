"""Lengths along each pass's own line of progression; heel strikes of feet seen arriving.

Synthetic trajectories with known heading and events, and the simulator's true markers
with noise (``gaitflow.bench.gait``'s markers level) for the stage. Fixed seeds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gaitflow.stages import gait as gs

from gaitflow import gaitcore as gc
from gaitflow.bench import gait as bg
from gaitflow.sim import simulate_session

PLANE = np.array([0.0, -1.0, 0.0, 900.0])  # camera mm, Y down: the floor 900 mm below
RATE = 100.0


def rot_about(n: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix about the unit axis n (Rodrigues)."""
    n = n / np.linalg.norm(n)
    k = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    a = np.radians(deg)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def trunk_markers(heading_deg: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N,) s and (N, 4, 3) mm: four body markers walking at 1.2 m/s on the floor of PLANE
    at ``heading_deg`` from the camera X axis (about the floor normal), swaying 25 mm
    sideways and 30 mm up and down, each seen over a different part of the pass."""
    t = np.arange(0.0, 3.0, 1 / RATE)
    u = rot_about(PLANE[:3], heading_deg) @ np.array([1.0, 0.0, 0.0])
    side = np.cross(PLANE[:3], u)
    up = -PLANE[:3]
    path = np.outer(1200.0 * t, u) + np.outer(25.0 * np.sin(np.pi * t / 0.55), side)
    path += np.outer(30.0 * np.sin(2 * np.pi * t / 0.55), up)
    offsets = np.array([[0, 0, 2500], [0, 0, 2700], [-80, 0, 2600], [80, -400, 2600]], float)
    pts = path[:, None, :] + offsets[None, :, :]
    pts += np.random.default_rng(seed).normal(0, 3.0, pts.shape)
    pts[: int(0.8 * RATE), 0] = np.nan  # enters the view late
    pts[int(2.1 * RATE) :, 1] = np.nan  # leaves the view early
    pts[int(1.0 * RATE) : int(1.2 * RATE), 2] = np.nan  # hidden for a while
    return t, pts


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


@pytest.mark.parametrize("heading", [0.0, 3.0, -7.0])
def test_line_of_progression_recovers_the_heading(heading):
    t, pts = trunk_markers(heading)
    walkway = np.array([1.0, 0.0, 0.0])  # the calibration's axis, off by ``heading``
    u = gc.line_of_progression(t, pts, PLANE, walkway)
    truth = rot_about(PLANE[:3], heading) @ walkway
    assert angle_deg(u, truth) < 0.2, (heading, u)
    assert abs(u @ PLANE[:3]) < 1e-9 and np.linalg.norm(u) == pytest.approx(1.0)
    # the sign follows the pass: the return pass (ref reversed) moves the other way
    back = gc.line_of_progression(t[::-1].copy() * -1, pts[::-1], PLANE, -walkway)
    assert angle_deg(back, -truth) < 0.2


def test_line_of_progression_falls_back_to_the_walkway():
    t, pts = trunk_markers(4.0)
    ref = np.array([1.0, 0.0, 0.0])
    short = pts.copy()
    short[int(0.3 * RATE) :] = np.nan  # each marker seen for 0.3 s only
    assert gc.line_of_progression(t, short, PLANE, ref) is ref
    assert gc.line_of_progression(t, np.full_like(pts, np.nan), PLANE, ref) is ref
    # motion against the pass's direction is not this pass's walk
    back = -ref
    assert gc.line_of_progression(t, pts, PLANE, back) is back


def one_foot(start_s: float) -> tuple[np.ndarray, ...]:
    """Heel and toe of one foot (stance 0.62 of a 1.1 s cycle, strikes at 0.2 + k 1.1 s),
    the data beginning at ``start_s`` (the foot walks into the view then)."""
    period, stride = 1.1, 1200.0
    t = np.arange(0.0, 4.4, 1 / RATE)
    phase = ((t - 0.2) / period) % 1.0
    cycle = np.floor((t - 0.2) / period)
    stance = phase < 0.62
    sw = np.clip((phase - 0.62) / 0.38, 0, 1)
    smooth = sw * sw * (3 - 2 * sw)  # the foot speeds up and slows down in swing
    prog = (cycle + np.where(stance, 0.0, smooth)) * stride
    # the heel is down by 70 % of the swing and skims the floor while it slows down
    heel_h = 25.0 + np.where(stance, 0.0, 200.0 * np.sin(np.pi * np.clip(sw / 0.7, 0, 1)))
    toe_h = 30.0 + np.where(stance, 0.0, 90.0 * np.sin(np.pi * sw))
    keep = t >= start_s
    return t[keep], heel_h[keep], toe_h[keep], prog[keep]


def test_a_heel_strike_is_found_when_the_foot_walks_into_view():
    # data begin 0.1 s before the strike at 1.3 s: the heel is seen low and slowing down,
    # Alg. 6 sees no descent (open left end) but the strike itself is observed
    t, hh, th, prog = one_foot(1.2)
    cs = gc.foot_contacts(t, hh, th, prog, prog, "L")
    assert not np.isnan(cs[0].heel_strike)
    assert abs(cs[0].heel_strike - 1.3) <= 1 / 30
    assert [round(c.heel_strike, 2) for c in cs[1:]] == pytest.approx([2.4, 3.5], abs=1 / 30)
    # the Alg. 6 ends alone never time an open end
    none = gc.foot_contacts(t, hh, th, prog, prog, "L", refine="none")
    assert np.isnan(none[0].heel_strike)


def test_no_heel_strike_when_the_heel_is_already_down():
    # data begin mid-stance (the pass begins with the foot on the floor): no event there
    t, hh, th, prog = one_foot(1.5)
    cs = gc.foot_contacts(t, hh, th, prog, prog, "L")
    assert np.isnan(cs[0].heel_strike)
    assert abs(cs[1].heel_strike - 2.4) <= 1 / 30


@pytest.fixture(scope="module")
def walk():
    ses = simulate_session("btk_PiG_Motion3_FF", 0)
    name = ses.walks()[0]
    frames = list(bg._marker_frames(ses, name, noise_mm=3.0, seed=0))
    return frames, bg._true_calibration(ses, name)


def steps(frames, cal, **params) -> dict[float, float]:
    state = gs.init(gs.PARAMS.resolve(params))
    outs = []
    for m in frames:
        state, o = gs.SPEC.run(state, {"labelled": m, "calibration": cal})
        outs += o
    state, o = gs.finish(state)
    doc = [m.results for m in outs + o if m.STREAM == "summary"][-1]
    assert doc["scope"] == "trial"
    return {c["heel_strike_s"]: c["step_length_mm"] for c in doc["cycles"] if "step_length_mm" in c}


def turned(cal, deg: float):
    """The calibration with its end point turned ``deg`` about the floor normal at the start."""
    r = rot_about(np.asarray(cal.floor_plane[:3], dtype=float), deg)
    end = cal.start + r @ (np.asarray(cal.end) - np.asarray(cal.start))
    return dataclasses.replace(cal, end=end)


@pytest.mark.slow
def test_step_lengths_do_not_depend_on_the_walkway_axis(walk):
    frames, cal = walk
    off = turned(cal, 4.0)  # a calibration whose walkway is 4 degrees off
    for mode, most in (("pass", 1.0), ("walkway", None)):
        a = steps(frames, cal, progression=mode)
        b = steps(frames, off, progression=mode)
        common = sorted(set(a) & set(b))
        assert len(common) >= 6
        d = np.array([b[k] - a[k] for k in common])
        if most is not None:
            assert np.abs(d).max() <= most, (mode, d)
        else:
            # along the walkway the step width leaks in: w sin(4 deg), sign alternating
            assert np.abs(d).mean() > 2.0 and (d > 0).any() and (d < 0).any(), d
