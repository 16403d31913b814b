"""The three parts a clinic records, as world-space motions over time.

World frame (see :mod:`gaitflow.sim.config`): x along the walkway, y away from the camera,
z up, floor at z = 0, mm; time in s from the recording's first frame.

- :class:`WalkMotion`: the trial's pass across the field of view (the subject's right side
  faces the camera), a turn, and the same trial rotated 180 degrees about the vertical
  (the return pass shows the left side); with ``SimConfig.start_side`` "right" the two
  passes swap (the left side first). Walking is never mirrored, so left stays left.
- :class:`StaticMotion`: the subject standing side-on at the start point, arms folded,
  with a few mm of postural sway, facing the way the first pass walks.
- :class:`CalibrationMotion`: the empty walkway; C floor markers placed one at a time by
  an operator whose leg and arm enter the view, with still periods in between.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from gaitflow.markers import MARKER_INDEX
from gaitflow.sim.body import SEGMENT_INDEX, Body, Trial, build_body
from gaitflow.sim.config import SimConfig
from gaitflow.sim.render import FramePose

Z_UP = np.array([0.0, 0.0, 1.0])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _albedo(body: Body, cfg: SimConfig) -> np.ndarray:
    table = {"skin": cfg.skin_albedo, "shirt": cfg.clothes_albedo, "shorts": cfg.shorts_albedo}
    return np.array([table[m] for m in body.material])


def _smooth(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3 - 2 * s)


@dataclass(frozen=True)
class Pass:
    """One straight pass: world = std @ R.T + T.

    World time t maps to pass time tau (s of source time; tau in [0, src_dur] is the source
    trial itself, before and after it whole gait cycles of the trial are repeated so that the
    subject walks in from outside the view and out of it) through the walk's clock:
    tau = (t - t0) * speed - pre, or a warped clock for a paretic swing
    (:meth:`WalkMotion.time_at`).
    """

    t0: float
    R: np.ndarray
    T: np.ndarray
    name: str
    pre: float
    post: float

    @property
    def direction(self) -> np.ndarray:
        """(3,) the walking direction in the world (the source's +x turned by R)."""
        return self.R[:, 0]


@dataclass(frozen=True)
class Cycle:
    """A gait cycle of the source (FS to the next FS of one foot) used to extend a pass."""

    start: float
    period: float
    shift: np.ndarray  # (3,) std-frame displacement over one cycle


def _cycles(trial: Trial, body: Body) -> tuple[Cycle, Cycle] | None:
    """The first and last full gait cycles of the trial (from its labelled foot strikes)."""
    k = SEGMENT_INDEX["pelvis"]
    pelvis = 0.5 * (body.cap_a[:, k] + body.cap_b[:, k])
    found = []
    for side in ("L", "R"):
        fs = [e[0] for e in trial.events if e[1] == side and e[2] == "FS"]
        for t0, t1 in itertools.pairwise(fs):
            if 0.6 < t1 - t0 < 2.5:
                found.append((t0, t1))
    if not found:
        # Fewer than two strikes of one foot: take the period from the heels' height
        # (autocorrelation), starting at the first labelled strike.
        strikes = sorted((e[0], e[1]) for e in trial.events if e[2] == "FS")
        steps = [b[0] - a[0] for a, b in itertools.pairwise(strikes) if a[1] != b[1]]
        around = 2.0 * steps[0] if steps and 0.3 < steps[0] < 1.25 else None
        period = _period(body, around)
        if period is None:
            return None
        fs = [e[0] for e in trial.events if e[2] == "FS"] or [0.0]
        t0 = fs[0] if fs[0] + period <= body.t[-1] else 0.0
        if t0 + period > body.t[-1]:
            return None
        found = [(t0, t0 + period)]

    def make(t0: float, t1: float) -> Cycle:
        p0 = np.array([np.interp(t0, body.t, pelvis[:, i]) for i in range(3)])
        p1 = np.array([np.interp(t1, body.t, pelvis[:, i]) for i in range(3)])
        shift = p1 - p0
        shift[2] = 0.0
        return Cycle(t0, t1 - t0, shift)

    found.sort()
    first = make(*found[0])
    last = make(*max(found, key=lambda c: c[1]))
    return first, last


def _cycle_phases(events: list[tuple[float, str, str]], cyc: Cycle) -> list[tuple[str, str, float]]:
    """One (side, kind, time) per side and kind (each happens once a cycle), in the window.

    The event labelled nearest to the cycle window [start, start + period) is used, moved
    into the window by whole periods.
    """
    end = cyc.start + cyc.period

    def outside(t: float) -> float:
        return max(cyc.start - t, t - end, 0.0)

    kept: dict[tuple[str, str], float] = {}
    for tt, side, kind in sorted(events, key=lambda e: outside(e[0])):
        if (side, kind) not in kept:
            kept[(side, kind)] = cyc.start + (tt - cyc.start) % cyc.period
    return [(side, kind, ph) for (side, kind), ph in kept.items()]


def _period(body: Body, around: float | None = None) -> float | None:
    """Gait period (s) from the autocorrelation of the heels' height difference.

    ``around`` (s): a rough period (twice a labelled step's time), searched within 25 %;
    else 0.7-1.8 s. On a short trial the autocorrelation can rise towards the window's
    edge, far from the true period: then ``around`` itself is the period.
    """
    from gaitflow.markers import MARKER_INDEX

    z = body.markers[:, MARKER_INDEX["L_HEE"], 2] - body.markers[:, MARKER_INDEX["R_HEE"], 2]
    z = z - z.mean()
    dt = float(np.median(np.diff(body.t)))
    lo, hi = (0.75 * around, 1.25 * around) if around else (0.7, 1.8)
    lags = np.arange(max(1, round(lo / dt)), min(round(hi / dt), len(z) - round(0.3 / dt)) + 1)
    if len(lags) == 0:
        return None
    score = [
        np.dot(z[:-lag], z[lag:]) / np.sqrt(np.dot(z[:-lag], z[:-lag]) * np.dot(z[lag:], z[lag:]))
        for lag in lags
    ]
    best = int(np.argmax(score))
    if around and best in (0, len(score) - 1):
        # a maximum at the window's edge is no peak: the labelled step's time is better
        return float(around)
    if score[best] < 0.5:
        return None
    return float(lags[best] * dt)


def shoe_reflectors(markers: np.ndarray, offsets: Any, scale: float = 1.0) -> np.ndarray:
    """Reflectors on both shoes, carried by each foot's heel, toe and ankle markers.

    markers : (B, 20, 3) world mm. offsets : (K, 3) mm in the foot's frame: forward (heel
    marker to toe marker), up (the world's vertical made normal to forward), outward (to
    the side the ankle marker, on the lateral malleolus, lies). Returns (B, 2K, 3): the
    left foot's K, then the right's; NaN where a foot marker is missing.
    """
    off = np.asarray(offsets, dtype=np.float64).reshape(-1, 3) * scale
    out = []
    for side in ("L", "R"):
        hee, toe, ank = (markers[:, MARKER_INDEX[f"{side}_{m}"]] for m in ("HEE", "TOE", "ANK"))
        fwd = toe - hee
        fwd = fwd / np.linalg.norm(fwd, axis=-1, keepdims=True)
        up = np.array([0.0, 0.0, 1.0]) - fwd[:, 2:3] * fwd
        up = up / np.linalg.norm(up, axis=-1, keepdims=True)
        lat = np.cross(fwd, up)
        lat = lat * np.sign(((ank - hee) * lat).sum(axis=-1, keepdims=True))
        out.append(
            hee[:, None]
            + off[None, :, 0:1] * fwd[:, None]
            + off[None, :, 1:2] * up[:, None]
            + off[None, :, 2:3] * lat[:, None]
        )
    return np.concatenate(out, axis=1)


def _blurred_pose(motion: Any, t_mid: float, exposure_s: float, blur_samples: int) -> FramePose:
    """A posed body's frame: markers at ``blur_samples`` instants over the exposure, the
    capsules and the markers (the ground truth's) at mid-exposure. ``motion`` has
    ``markers_caps``, ``body``, ``albedo`` and ``cfg`` (:class:`WalkMotion`,
    :class:`StaticMotion`). The shoes' reflectors (``SimConfig.shoe_reflectors``) follow the
    markers as spheres of their own, never in the truth."""
    ts = t_mid + exposure_s * (np.arange(blur_samples) + 0.5) / blur_samples - exposure_s / 2
    m, _, _ = motion.markers_caps(ts)
    cfg = motion.cfg
    if cfg.shoe_reflectors:
        extra = shoe_reflectors(m, cfg.shoe_reflectors, cfg.body_scale)
        m = np.concatenate([m, extra], axis=1)
    mid, a, b = motion.markers_caps(np.array([t_mid]))
    return FramePose(m, a[0], b[0], motion.body.radius, motion.albedo, mid[0])


class WalkMotion:
    """A trial's pass, a turn, and its rotated return, each pass crossing the whole view.

    Parameters
    ----------
    trial, body : the source trial and its posed body (standard frame).
    cfg : simulator configuration.
    view_x : (x_left, x_right) world x (mm) of the image edges on the walking line. Each
        pass is extended with repeated gait cycles until the subject starts and ends
        ``margin_mm`` outside them.
    """

    BLEND_S = 0.25  # cross-fade between the source and its repeated cycles

    def __init__(
        self,
        trial: Trial,
        body: Body,
        cfg: SimConfig,
        view_x: tuple[float, float] | None = None,
        margin_mm: float = 500.0,
    ) -> None:
        self.trial, self.body, self.cfg = trial, body, cfg
        speed = cfg.speed_factor
        self.src_dur = float(body.t[-1])
        k = SEGMENT_INDEX["pelvis"]
        pelvis = 0.5 * (body.cap_a[:, k] + body.cap_b[:, k])
        x_mid = 0.5 * (pelvis[0, 0] + pelvis[-1, 0])
        y_mean = float(pelvis[:, 1].mean())
        D = cfg.walk_distance_mm
        # Centre the source pass on the optical axis's crossing of the walking line.
        x_view = D * np.tan(np.radians(cfg.pan_deg))
        self.cycles = _cycles(trial, body)
        self._resid: list[tuple[np.ndarray, ...]] = []
        self._events: tuple[tuple[float, str, str, str], ...] | None = None
        for cyc in self.cycles or ():
            start = self.body.at(np.array([cyc.start]))
            end = self.body.at(np.array([cyc.start + cyc.period]))
            self._resid.append(
                tuple(e[0] - s0[0] - cyc.shift for e, s0 in zip(end, start, strict=True))
            )
        half = 0.5 * (pelvis[-1, 0] - pelvis[0, 0])
        pre = post = 0.0
        if view_x is not None and self.cycles is not None:
            v = np.linalg.norm(self.cycles[0].shift) / self.cycles[0].period
            v_end = np.linalg.norm(self.cycles[1].shift) / self.cycles[1].period
            need_left = (x_view - half) - (view_x[0] - margin_mm)
            need_right = (view_x[1] + margin_mm) - (x_view + half)
            pre = max(0.0, need_left / v, need_right / v)
            post = max(0.0, need_right / v_end, need_left / v_end)
        self.pass_src = pre + self.src_dur + post
        self._warp = self._clock(pre, post)
        self.pass_dur = self.pass_src / speed if self._warp is None else float(self._warp[1][-1])
        # Walking toward +x (the source's own frame) or toward -x (turned 180 degrees).
        toward_x = (np.eye(3), np.array([x_view - x_mid, D - y_mean, 0.0]))
        toward_minus_x = (rot_z(np.pi), np.array([x_view + x_mid, D + y_mean, 0.0]))
        first, second = toward_x, toward_minus_x
        if cfg.start_side == "right":
            first, second = second, first
        back_off = np.array([0.0, cfg.return_offset_mm, 0.0])
        out = Pass(0.0, first[0], first[1], "out", pre, post)
        ret = Pass(self.pass_dur + cfg.turn_s, second[0], second[1] + back_off, "back", pre, post)
        self.passes = (out, ret)
        self.duration_s = 2 * self.pass_dur + cfg.turn_s
        self.albedo = _albedo(body, cfg)

    # ------------------------------------------------------------------ the clock
    CLOCK_STEP_S = 0.002

    def _clock(self, pre: float, post: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(tau, elapsed s) on a fine grid for a paretic swing; None for the source's timing.

        Each swing of the paretic foot (its toe off to its next strike, in pass time) is
        slowed by a raised cosine, whose mean over the swing is half its peak: the swing
        lasts ``paretic_swing`` times as long, the body slows with it (the other leg's
        single stance lengthens), and the speed changes smoothly at both ends.
        """
        cfg = self.cfg
        if cfg.paretic_swing == 1.0 or self.cycles is None:
            return None
        n = int(np.ceil(self.pass_src / self.CLOCK_STEP_S)) + 1
        tau = np.linspace(-pre, self.src_dur + post, n)
        rate = np.ones(n)
        events = self._events_tau(pre, post)
        side = cfg.paretic_side
        strikes = np.array(sorted(t for t, s, k, _ in events if s == side and k == "FS"))
        longest = 0.6 * self.cycles[0].period  # a swing is 35-45 % of the cycle
        peak = 2.0 * (cfg.paretic_swing - 1.0)
        for a in sorted(t for t, s, k, _ in events if s == side and k == "FO"):
            later = strikes[strikes > a]
            if not later.size or later[0] - a > longest:
                continue  # the pass ends in this swing, or its strike is not labelled
            b = float(later[0])
            sel = (tau > a) & (tau < b)
            rate[sel] += peak * np.sin(np.pi * (tau[sel] - a) / (b - a)) ** 2
        steps = 0.5 * (rate[1:] + rate[:-1]) * np.diff(tau)
        return tau, np.concatenate([[0.0], np.cumsum(steps)]) / cfg.speed_factor

    def time_at(self, p: Pass, tau: np.ndarray | float) -> np.ndarray | float:
        """World time (s) at pass time ``tau`` of pass ``p`` (the inverse of ``_tau``)."""
        if self._warp is None:
            return p.t0 + (tau + p.pre) / self.cfg.speed_factor
        return p.t0 + np.interp(tau, *self._warp)

    # ------------------------------------------------------------------ pass-local pose
    def _std(self, tau: np.ndarray):
        """Markers and capsule ends in the standard frame at pass times tau (K,)."""
        tau = np.asarray(tau, dtype=np.float64)
        m, a, b = self.body.at(np.clip(tau, 0.0, self.src_dur))
        if self.cycles is None:
            return m, a, b
        blend = self.BLEND_S
        c0, c1 = self.cycles
        w_pre = np.clip(1.0 - tau / blend, 0.0, 1.0)
        w_post = np.clip((tau - (self.src_dur - blend)) / blend, 0.0, 1.0)
        for cyc, w, resid in ((c0, w_pre, self._resid[0]), (c1, w_post, self._resid[1])):
            if not (w > 0).any():
                continue
            n = np.floor((tau - cyc.start) / cyc.period)
            phase = (tau - cyc.start) - n * cyc.period
            mc, ac, bc = self.body.at(cyc.start + phase)
            # Remove the cycle's non-periodic residual linearly over the cycle, so that
            # consecutive copies join without a jump.
            f = (phase / cyc.period)[:, None, None]
            sh = (n[:, None] * cyc.shift)[:, None, :]
            ww = w[:, None, None]
            m = (1 - ww) * m + ww * (mc - f * resid[0] + sh)
            a = (1 - ww) * a + ww * (ac - f * resid[1] + sh)
            b = (1 - ww) * b + ww * (bc - f * resid[2] + sh)
        return m, a, b

    def _posed(self, p: Pass, tau: np.ndarray):
        m, a, b = self._std(tau)
        return m @ p.R.T + p.T, a @ p.R.T + p.T, b @ p.R.T + p.T

    def _tau(self, p: Pass, t: np.ndarray) -> np.ndarray:
        elapsed = np.asarray(t, dtype=np.float64) - p.t0
        if self._warp is None:
            return elapsed * self.cfg.speed_factor - p.pre
        tau, el = self._warp
        return np.interp(elapsed, el, tau)

    def markers_caps(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Markers (K, 20, 3) and capsule ends (K, S, 3) x2 in world mm at times t (K,)."""
        t = np.asarray(t, dtype=np.float64)
        out_p, back_p = self.passes
        t1 = np.clip(t, 0, self.pass_dur)
        t2 = np.clip(t, back_p.t0, back_p.t0 + self.pass_dur)
        m1, a1, b1 = self._posed(out_p, self._tau(out_p, t1))
        m2, a2, b2 = self._posed(back_p, self._tau(back_p, t2))
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
        end = [x[0] for x in self._posed(out_p, np.array([self.src_dur + out_p.post]))]
        start = [x[0] for x in self._posed(back_p, np.array([-back_p.pre]))]
        k = SEGMENT_INDEX["pelvis"]
        flat = np.array([1.0, 1.0, 0.0])
        c0 = 0.5 * (end[1][k] + end[2][k]) * flat
        c1 = 0.5 * (start[1][k] + start[2][k]) * flat
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
        return _blurred_pose(self, t_mid, exposure_s, blur_samples)

    # ------------------------------------------------------------------ ground truth
    def events_detail(self) -> list[dict]:
        """Labelled events on the composed walk, both passes.

        Events of the source trial keep their labelled time. Where no event is labelled
        (the repeated cycles before and after the source, and unlabelled stretches of the
        source), copies of the labelled events at the same gait phase are added
        (``copied`` True). Times in s from the recording's first frame.
        """
        res = [
            {
                "time_s": float(self.time_at(p, tau)),
                "side": side,
                "kind": kind,
                "pass": p.name,
                "copied": copied,
            }
            for p in self.passes
            for tau, side, kind, copied in self._events_tau(p.pre, p.post)
        ]
        return sorted(res, key=lambda e: e["time_s"])

    def _events_tau(self, pre: float, post: float) -> list[tuple[float, str, str, bool]]:
        """(tau, side, kind, copied) of a pass's events, in pass time (events_detail)."""
        out = [(tt, side, kind, False) for tt, side, kind in self.trial.events]
        if self.cycles is None:
            return out
        mid = 0.5 * self.src_dur
        for cyc, lo, hi in (
            (self.cycles[0], -pre, mid),
            (self.cycles[1], mid, self.src_dur + post),
        ):
            for side, kind, ph in _cycle_phases(self.trial.events, cyc):
                n0 = int(np.floor((lo - ph) / cyc.period))
                for n in range(n0, n0 + int((hi - lo) / cyc.period) + 3):
                    tau = ph + n * cyc.period
                    if not lo <= tau < hi:
                        continue
                    # Inside the source span only where the source left it unlabelled.
                    near = [
                        e
                        for e in self.trial.events
                        if e[1] == side and e[2] == kind and abs(e[0] - tau) < 0.4 * cyc.period
                    ]
                    if not near:
                        out.append((tau, side, kind, True))
        return out

    def events(self) -> list[tuple[float, str, str, str]]:
        """(time_s, side, kind, pass) of every event, source and copied.

        Built once per walk: the ground truth of every frame asks for them (0.75 ms a frame,
        3 % of a walking frame's render, when they were rebuilt each time).
        """
        if self._events is None:
            self._events = tuple(
                (e["time_s"], e["side"], e["kind"], e["pass"]) for e in self.events_detail()
            )
        return list(self._events)

    def knee_ref(self, t: np.ndarray) -> np.ndarray:
        """Source Plug-in Gait knee flexion (K, 2) at times t, NaN in the turn.

        In the repeated cycles it is the value at the corresponding source time.
        """
        t = np.asarray(t, dtype=np.float64)
        out = np.full((len(t), 2), np.nan)
        for p in self.passes:
            ts = self._tau(p, t)
            if self.cycles is not None:
                for cyc, sel in ((self.cycles[0], ts < 0), (self.cycles[1], ts > self.src_dur)):
                    n = np.floor((ts[sel] - cyc.start) / cyc.period)
                    ts[sel] = ts[sel] - n * cyc.period
            ok = (ts >= 0) & (ts <= self.src_dur) & (t >= p.t0) & (t <= p.t0 + self.pass_dur)
            for k in range(2):
                out[ok, k] = np.interp(ts[ok], self.trial.t, self.trial.knee_ref[:, k])
        return out

    def start_point(self) -> np.ndarray:
        """World position (3,) of the pelvis where the source trial's outward pass begins."""
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


def _turned(x: np.ndarray, R: np.ndarray, centre: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Points (..., 3) turned by R about the vertical through ``centre``, that vertical
    moved to ``at`` (floor x, y)."""
    flat = np.array([1.0, 1.0, 0.0])
    return (x - centre * flat) @ R.T + np.asarray(at, dtype=np.float64) * flat


class StaticMotion:
    """The subject standing side-on at the walk's start point, with postural sway."""

    def __init__(
        self, trial: Trial, cfg: SimConfig, at: np.ndarray, seed: int, R: np.ndarray | None = None
    ) -> None:
        self.cfg = cfg
        st = standing_trial(trial)
        body = build_body(
            st,
            cfg.marker_radius_mm,
            cfg.source_marker_diameter_mm / 2,
            cfg.arm_swing_gain,
            static=True,
            marker_base_mm=cfg.marker_base_mm,
            patch_mm=cfg.skin_patch_mm,
            wand_mount=cfg.wand_mount,
            wand_mm=cfg.wand_mm,
        )
        k = SEGMENT_INDEX["pelvis"]
        centre = 0.5 * (body.cap_a[0, k] + body.cap_b[0, k])
        if R is not None and not np.allclose(R, np.eye(3)):
            # Facing the other way: the body turned about the vertical through its pelvis,
            # already standing at ``at``.
            body = dataclasses.replace(
                body,
                markers=_turned(body.markers, R, centre, at),
                cap_a=_turned(body.cap_a, R, centre, at),
                cap_b=_turned(body.cap_b, R, centre, at),
                normal=None if body.normal is None else body.normal @ R.T,
            )
            self.T = np.zeros(3)
        else:
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
        return _blurred_pose(self, t_mid, exposure_s, blur_samples)

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
        a = np.array([*legs_a, pelvis, shoulder, elbow, chest + np.array([0.0, 0.0, 330.0])])
        b = np.array([*legs_b, chest, elbow, hand, chest + np.array([0.0, 0.0, 360.0])])
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
