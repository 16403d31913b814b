"""The three parts a clinic records, as world-space motions over time.

World frame (see :mod:`gaitflow.sim.config`): x along the walkway, y away from the camera,
z up, floor at z = 0, mm; time in s from the recording's first frame.

- :class:`WalkMotion`: the trial's pass across the field of view (the subject's right side
  faces the camera), a turn, and the same trial rotated 180 degrees about the vertical
  (the return pass shows the left side). Walking is never mirrored, so left stays left.
- :class:`StaticMotion`: the subject standing side-on at the start point, arms folded,
  with a few mm of postural sway.
- :class:`CalibrationMotion`: the empty walkway; C floor markers placed one at a time by
  an operator whose leg and arm enter the view, with still periods in between.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaitflow.sim.body import SEGMENT_INDEX, Body, Trial, build_body
from gaitflow.sim.config import SimConfig
from gaitflow.sim.render import FramePose

Z_UP = np.array([0.0, 0.0, 1.0])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _albedo(body: Body, cfg: SimConfig) -> np.ndarray:
    return np.where(body.skin, cfg.skin_albedo, cfg.clothes_albedo)


def _smooth(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3 - 2 * s)


@dataclass(frozen=True)
class Pass:
    """One straight pass: world = std @ R.T + T, world time t0 + src_time / speed."""

    t0: float
    R: np.ndarray
    T: np.ndarray
    name: str


class WalkMotion:
    """A trial's pass, a turn, and its rotated return."""

    def __init__(self, trial: Trial, body: Body, cfg: SimConfig) -> None:
        self.trial, self.body, self.cfg = trial, body, cfg
        speed = cfg.speed_factor
        self.src_dur = float(body.t[-1])
        self.pass_dur = self.src_dur / speed
        pelvis = body.cap_a[:, SEGMENT_INDEX["pelvis"]] + body.cap_b[:, SEGMENT_INDEX["pelvis"]]
        pelvis = 0.5 * pelvis
        x_mid = 0.5 * (pelvis[0, 0] + pelvis[-1, 0])
        y_mean = float(pelvis[:, 1].mean())
        # Centre the pass on the optical axis's crossing of the walking line.
        x_view = cfg.walk_distance_mm * np.tan(np.radians(cfg.pan_deg))
        D = cfg.walk_distance_mm
        out = Pass(0.0, np.eye(3), np.array([x_view - x_mid, D - y_mean, 0.0]), "out")
        R2 = rot_z(np.pi)
        ret = Pass(
            self.pass_dur + cfg.turn_s, R2, np.array([x_view + x_mid, D + y_mean, 0.0]), "back"
        )
        self.passes = (out, ret)
        self.duration_s = 2 * self.pass_dur + cfg.turn_s
        self.albedo = _albedo(body, cfg)

    def _posed(self, p: Pass, t_src: np.ndarray):
        m, a, b = self.body.at(t_src)
        return m @ p.R.T + p.T, a @ p.R.T + p.T, b @ p.R.T + p.T

    def markers_caps(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Markers (K, 20, 3) and capsule ends (K, S, 3) x2 in world mm at times t (K,)."""
        t = np.asarray(t, dtype=np.float64)
        speed = self.cfg.speed_factor
        out_p, back_p = self.passes
        m1, a1, b1 = self._posed(out_p, np.clip(t, 0, self.pass_dur) * speed)
        m2, a2, b2 = self._posed(back_p, np.clip(t - back_p.t0, 0, self.pass_dur) * speed)
        in_turn = (t > self.pass_dur) & (t < back_p.t0)
        first = (t <= self.pass_dur)[:, None, None]
        m, a, b = (np.where(first, x, y) for x, y in ((m1, m2), (a1, a2), (b1, b2)))
        if in_turn.any():
            s = _smooth((t[in_turn] - self.pass_dur) / self.cfg.turn_s)
            mt, at, bt = self._turn(s)
            m[in_turn], a[in_turn], b[in_turn] = mt, at, bt
        return m, a, b

    def _turn(self, s: np.ndarray):
        """Blend the last outward pose into the first return pose while turning 180 deg."""
        out_p, back_p = self.passes
        end = [x[0] for x in self._posed(out_p, np.array([self.src_dur]))]
        start = [x[0] for x in self._posed(back_p, np.array([0.0]))]
        c0 = end[1][SEGMENT_INDEX["pelvis"]] * 0.5 + end[2][SEGMENT_INDEX["pelvis"]] * 0.5
        c1 = start[1][SEGMENT_INDEX["pelvis"]] * 0.5 + start[2][SEGMENT_INDEX["pelvis"]] * 0.5
        c0 = c0 * [1, 1, 0]
        c1 = c1 * [1, 1, 0]
        R1inv = rot_z(-np.pi)
        res = []
        for e, st in zip(end, start, strict=True):
            loc0 = e - c0
            loc1 = (st - c1) @ R1inv.T
            outs = []
            for sk in s:
                shape = (1 - sk) * loc0 + sk * loc1
                # A small step away from the walking line during the turn.
                c = (1 - sk) * c0 + sk * c1 + np.array([0.0, 150.0 * np.sin(np.pi * sk), 0.0])
                outs.append(shape @ rot_z(np.pi * sk).T + c)
            res.append(np.stack(outs))
        return res

    def pose(self, t_mid: float, exposure_s: float, blur_samples: int) -> FramePose:
        ts = t_mid + exposure_s * (np.arange(blur_samples) + 0.5) / blur_samples - exposure_s / 2
        m, _, _ = self.markers_caps(ts)
        _, a, b = self.markers_caps(np.array([t_mid]))
        return FramePose(m, a[0], b[0], self.body.radius, self.albedo)

    def events(self) -> list[tuple[float, str, str, str]]:
        """Source events mapped onto the composed walk: (time_s, side, kind, pass)."""
        out = []
        for p in self.passes:
            for tt, side, kind in self.trial.events:
                out.append((p.t0 + tt / self.cfg.speed_factor, side, kind, p.name))
        return sorted(out)

    def knee_ref(self, t: np.ndarray) -> np.ndarray:
        """Source Plug-in Gait knee flexion (K, 2) at times t, NaN in the turn."""
        t = np.asarray(t, dtype=np.float64)
        out = np.full((len(t), 2), np.nan)
        for p in self.passes:
            ts = (t - p.t0) * self.cfg.speed_factor
            ok = (ts >= 0) & (ts <= self.src_dur)
            for k in range(2):
                out[ok, k] = np.interp(ts[ok], self.trial.t, self.trial.knee_ref[:, k])
        return out

    def start_point(self) -> np.ndarray:
        """World position (3,) of the pelvis at the start of the outward pass."""
        _, a, b = self._posed(self.passes[0], np.array([0.0]))
        k = SEGMENT_INDEX["pelvis"]
        return 0.5 * (a[0, k] + b[0, k])


def standing_trial(trial: Trial) -> Trial:
    """A one-frame standing pose built from the trial's mid-stance frames.

    The right leg, pelvis and upper body come from the right mid-stance frame (right ankle
    below the right hip, foot flat); the left leg from the left mid-stance frame, moved with
    the left hip. Both legs are then near-vertical with flat feet, as when standing.
    """
    m = trial.markers
    pel = 0.5 * (m["L_ASI"] + m["R_ASI"])

    def mid_stance(side: str) -> int:
        ank = m[f"{side}_ANK"]
        low = ank[:, 2] < np.nanpercentile(ank[:, 2], 40)
        score = np.abs(ank[:, 0] - pel[:, 0]) + np.where(low, 0.0, 1e6)
        return int(np.nanargmin(score))

    fr, fl = mid_stance("R"), mid_stance("L")
    out = {k: v[fr : fr + 1].copy() for k, v in m.items()}
    shift = pel[fr] - pel[fl]
    shift[2] = 0.0
    for name in list(m):
        if name.startswith("L_") and name[2:] in ("THI", "KNE", "TIB", "ANK", "HEE", "TOE"):
            out[name] = m[name][fl : fl + 1] + shift
    return Trial(
        trial.name,
        np.zeros(1),
        out,
        np.full((1, 2), np.nan),
        [],
        trial.rate_hz,
        trial.meta,
    )


class StaticMotion:
    """The subject standing side-on at the walk's start point, with postural sway."""

    def __init__(self, trial: Trial, cfg: SimConfig, at: np.ndarray, seed: int) -> None:
        self.cfg = cfg
        st = standing_trial(trial)
        body = build_body(
            st,
            cfg.marker_radius_mm,
            cfg.source_marker_diameter_mm / 2,
            cfg.arm_swing_gain,
            static=True,
        )
        k = SEGMENT_INDEX["pelvis"]
        centre = 0.5 * (body.cap_a[0, k] + body.cap_b[0, k])
        self.T = np.array([at[0] - centre[0], at[1] - centre[1], 0.0])
        self.body = body
        self.albedo = _albedo(body, cfg)
        self.duration_s = cfg.static_s
        rng = np.random.default_rng(seed)
        # Quiet-standing sway: a few mm at 0.1-0.6 Hz (centre-of-pressure literature).
        self.f = rng.uniform(0.1, 0.6, size=(3, 2))
        self.ph = rng.uniform(0, 2 * np.pi, size=(3, 2))
        self.amp = np.array([4.0, 3.0, 0.8])

    def _offset(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)[:, None, None]
        return (self.amp[:, None] * np.sin(2 * np.pi * self.f * t + self.ph)).sum(-1)

    def markers_caps(self, t: np.ndarray):
        t = np.asarray(t, dtype=np.float64)
        off = self._offset(t)[:, None, :] + self.T
        m = np.repeat(self.body.markers, len(t), 0) + off
        a = np.repeat(self.body.cap_a, len(t), 0) + off
        b = np.repeat(self.body.cap_b, len(t), 0) + off
        return m, a, b

    def pose(self, t_mid: float, exposure_s: float, blur_samples: int) -> FramePose:
        ts = t_mid + exposure_s * (np.arange(blur_samples) + 0.5) / blur_samples - exposure_s / 2
        m, _, _ = self.markers_caps(ts)
        _, a, b = self.markers_caps(np.array([t_mid]))
        return FramePose(m, a[0], b[0], self.body.radius, self.albedo)

    def events(self) -> list[tuple[float, str, str, str]]:
        return []

    def knee_ref(self, t: np.ndarray) -> np.ndarray:
        return np.full((len(np.asarray(t)), 2), np.nan)


class CalibrationMotion:
    """Empty walkway; an operator places C floor markers one at a time.

    Timeline: a still period, then for each marker a placing period (the operator walks in
    from the nearer image side, bends, puts the marker down, walks out) and a still period.
    """

    def __init__(self, cfg: SimConfig, seed: int) -> None:
        self.cfg = cfg
        D = cfg.walk_distance_mm
        x_view = D * np.tan(np.radians(cfg.pan_deg))
        r = cfg.marker_radius_mm
        rng = np.random.default_rng(seed)
        corners = np.array([[-1000, -450], [1000, -450], [1000, 450], [-1000, 450]], float)
        C = cfg.calibration_markers
        if C != 4:
            ang = np.linspace(0, 2 * np.pi, C, endpoint=False) + np.pi * 1.25
            corners = np.stack([1000 * np.cos(ang), 450 * np.sin(ang)], axis=1)
        corners += rng.normal(0, 30.0, size=corners.shape)
        self.markers = np.c_[corners[:, 0] + x_view, corners[:, 1] + D, np.full(C, r)]
        self.t_place = np.array(
            [cfg.calib_still_s + k * (cfg.calib_place_s + cfg.calib_still_s) for k in range(C)]
        )
        # The marker appears mid-way through the placing period.
        self.t_drop = self.t_place + 0.5 * cfg.calib_place_s
        self.duration_s = cfg.calib_still_s + C * (cfg.calib_place_s + cfg.calib_still_s)
        self.x_view = x_view

    def _operator(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        cfg = self.cfg
        if not cfg.show_operator:
            return None
        k = np.flatnonzero((t >= self.t_place) & (t < self.t_place + cfg.calib_place_s))
        if len(k) == 0:
            return None
        k = int(k[0])
        s = (t - self.t_place[k]) / cfg.calib_place_s  # 0..1
        target = self.markers[k]
        side = -1.0 if target[0] < self.x_view else 1.0
        walk = _smooth(1.0 - np.clip(np.minimum(s, 1 - s) / 0.3, 0, 1))  # 1 = far away
        reach = _smooth(np.clip((0.5 - abs(s - 0.5)) / 0.2, 0, 1))  # 1 = hand on floor
        base = target + np.array([side * (250.0 + 2600.0 * walk), 380.0, -target[2]])
        hip_h, knee_h = 880.0, 480.0
        legs_a, legs_b = [], []
        for dx in (-110.0, 110.0):
            foot = base + np.array([dx, 0.0, 60.0])
            knee = base + np.array([dx - 60.0 * reach * side, -80.0 * reach, knee_h])
            hip = base + np.array([dx * 0.8, 80.0 * reach, hip_h - 250.0 * reach])
            legs_a += [foot, knee]
            legs_b += [knee, hip]
        pelvis = base + np.array([0.0, 80.0 * reach, hip_h - 250.0 * reach])
        chest = pelvis + np.array([0.0, -350.0 * reach, 500.0 - 250.0 * reach])
        shoulder = chest + np.array([-side * 160.0, 0.0, 80.0])
        hand = (1 - reach) * (shoulder + np.array([0.0, 0.0, -600.0])) + reach * (
            target + np.array([0.0, 30.0, 40.0])
        )
        elbow = 0.5 * (shoulder + hand) + np.array([0.0, 80.0, 40.0])
        a = np.array([*legs_a, pelvis, shoulder, elbow, chest + [0, 0, 330]])
        b = np.array([*legs_b, chest, elbow, hand, chest + [0, 0, 360]])
        r = np.array([50.0, 60.0, 50.0, 60.0, 130.0, 45.0, 38.0, 95.0])
        return a, b, r

    def pose(self, t_mid: float, exposure_s: float, blur_samples: int) -> FramePose:
        present = t_mid >= self.t_drop
        sph = np.repeat(self.markers[None], blur_samples, axis=0)
        # Markers not yet placed are absent (NaN).
        sph[:, ~present] = np.nan
        op = self._operator(t_mid)
        if op is None:
            a = np.zeros((0, 3))
            return FramePose(sph, a, a, np.zeros(0), np.zeros(0))
        a, b, r = op
        alb = np.full(len(r), self.cfg.clothes_albedo)
        return FramePose(sph, a, b, r, alb)

    def events(self) -> list[tuple[float, str, str, str]]:
        return []
