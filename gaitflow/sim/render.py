"""Kinect v2 IR and depth rendering by per-pixel ray casting through the distortion model.

Images are (row, col) = (H, W); pixel (u, v) = (column, row). Camera space: X right, Y
down, Z forward, mm. Depth is Z (not ray length), uint16 mm, 0 = invalid. IR is uint16
amplitude, 65535 = saturated.

The pixel grid is undistorted once (:meth:`gaitflow.camera.Camera.undistort`), giving for
every pixel the ray (x, y, 1) whose points are Z * (x, y, 1); a surface hit at ray
parameter Z is therefore directly the depth. Sub-pixel rays (for anti-aliased marker
coverage) use the local Jacobian of that grid.

Effects, per frame:

- IR of diffuse surfaces (floor, wall, body): ``gain * albedo * cos(incidence) / r^2``
  (active illumination, r = ray length in m) times a radial vignetting, plus shot and read
  noise.
- Retro-reflective markers: radiance ``marker_gain * 65535 * (2.5 m / r)^2`` mixed with the
  background by the pixel's coverage (supersampled disc, averaged over the exposure for
  motion blur), clipped at 65535: saturated cores with partial-pixel edges. Spheres are
  z-buffered against the body and against each other per sub-sample, so a marker behind
  another one is hidden where the nearer sphere covers it.
- Depth: pixels covered by a marker beyond ``hole_coverage``, or saturated, are 0; partly
  covered ones mix marker and background depth. Axial noise follows Fankhauser et al.
  (2015), see :func:`axial_sigma_mm`. Depth edges give flying (mixed) and invalid pixels.
  Out-of-range (0.5-4.5 m), grazing and low-amplitude pixels are 0.
- Lens glare (optional, ``glare_fraction``; :meth:`Renderer._glare`): stray marker light
  around each marker's image brightens the IR and pulls the depth there towards the
  marker's, or invalidates it, so the depth hole grows beyond the marker's image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaitflow.sim.config import SimConfig

SAT = 65535


def axial_sigma_mm(z_mm: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """Kinect v2 axial (depth) noise standard deviation.

    Fankhauser, Bloesch, Rodriguez, Kaestner, Hutter, Siegwart, "Kinect v2 for mobile robot
    navigation: evaluation and modeling", ICAR 2015, eq. (2):
    ``sigma_z(z, theta) = 1.5 - 0.5 z + 0.3 z^2 + 0.1 z^1.5 theta^2 / (pi/2 - theta)^2``
    in mm, with z in m and theta the incidence angle in rad.

    Parameters
    ----------
    z_mm : (...) depth in mm.
    theta_rad : (...) incidence angle in rad, 0 = surface facing the camera.
    """
    z = np.asarray(z_mm, dtype=np.float64) / 1000.0
    th = np.minimum(np.asarray(theta_rad, dtype=np.float64), np.radians(89.0))
    return 1.5 - 0.5 * z + 0.3 * z * z + 0.1 * z**1.5 * th * th / (np.pi / 2 - th) ** 2


def camera_rotation(tilt_deg: float, pan_deg: float, roll_deg: float) -> np.ndarray:
    """World-to-camera rotation (3, 3): rows are the camera X (right), Y (down), Z axes.

    World: x along the walkway, y away from the camera, z up. Tilt > 0 looks down; pan > 0
    turns the optical axis towards +x.
    """
    t, p, r = np.radians([tilt_deg, pan_deg, roll_deg])
    f = np.array([np.sin(p) * np.cos(t), np.cos(p) * np.cos(t), -np.sin(t)])
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    # Roll about the optical axis.
    right, down = np.cos(r) * right + np.sin(r) * down, -np.sin(r) * right + np.cos(r) * down
    return np.stack([right, down, f])


def capsule_hit(
    rd: np.ndarray, a: np.ndarray, b: np.ndarray, r: float
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-capsule intersection for rays from the origin (analytic, after I. Quilez).

    Parameters
    ----------
    rd : (N, 3) unit ray directions (camera space).
    a, b : (3,) capsule end points, camera mm.
    r : radius mm.

    Returns
    -------
    t : (N,) ray length to the first hit, inf where missed.
    cos_inc : (N,) cosine of the incidence angle at the hit (0 where missed).
    """
    ba = b - a
    oa = -a
    baba = ba @ ba
    bard = rd @ ba
    baoa = ba @ oa
    rdoa = rd @ oa
    oaoa = oa @ oa
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    h = qb * qb - qa * (baba * oaoa - baoa * baoa - r * r * baba)
    t = np.full(len(rd), np.inf)
    cos_inc = np.zeros(len(rd))
    idx = np.flatnonzero(h >= 0)
    if len(idx) == 0:
        return t, cos_inc
    # Only the rays that meet the infinite cylinder can meet the capsule.
    rdi, bardi, qbi, qai = rd[idx], bard[idx], qb[idx], qa[idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = (-qbi - np.sqrt(h[idx])) / qai
    y = baoa + tc * bardi
    body = (y > 0) & (y < baba) & (tc > 0)
    ti = np.where(body, tc, np.inf)
    caps = ~body
    if caps.any():
        oc = np.where((y <= 0)[caps, None], oa, -b)
        rdc = rdi[caps]
        cb = (rdc * oc).sum(axis=1)
        hh = cb * cb - ((oc * oc).sum(axis=1) - r * r)
        ok = hh > 0
        tcap = -cb - np.sqrt(np.where(ok, hh, 0.0))
        ti[caps] = np.where(ok & (tcap > 0), tcap, np.inf)
    hit = np.isfinite(ti)
    p = rdi[hit] * ti[hit, None]
    w = np.clip(((p - a) @ ba) / max(baba, 1e-9), 0.0, 1.0)
    n = p - (a + w[:, None] * ba)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    hit_idx = idx[hit]
    t[hit_idx] = ti[hit]
    cos_inc[hit_idx] = np.clip(-(rdi[hit] * n).sum(axis=1), 0.0, 1.0)
    return t, cos_inc


@dataclass
class FramePose:
    """What stands in front of the camera during one frame, world mm.

    spheres : (B, N, 3) marker centres at B instants spread over the exposure.
    cap_a, cap_b : (S, 3) capsule end points at mid-exposure; cap_r (S,) radii.
    cap_albedo : (S,) IR albedo per capsule.
    markers : (N, 3) marker centres at mid-exposure, the ground truth's (a posed body's
        frames; None for the calibration's operator).
    """

    spheres: np.ndarray
    cap_a: np.ndarray
    cap_b: np.ndarray
    cap_r: np.ndarray
    cap_albedo: np.ndarray
    markers: np.ndarray | None = None


@dataclass
class RenderOut:
    """A rendered frame and per-sphere visibility.

    ir, depth : (H, W) uint16.
    seen : (N,) fraction of the sphere's unoccluded image footprint that is visible.
    in_view : (N,) centre inside the image and within the depth range.
    """

    ir: np.ndarray
    depth: np.ndarray
    seen: np.ndarray
    in_view: np.ndarray


class Renderer:
    """A static scene (floor, back wall, ceiling, stray reflectors) seen by one camera."""

    def __init__(self, cfg: SimConfig, bank_seed: int = 0) -> None:
        self.cfg = cfg
        cam = cfg.camera
        self.cam = cam
        self.H, self.W = cam.height, cam.width
        self.R = camera_rotation(cfg.tilt_deg, cfg.pan_deg, cfg.roll_deg)
        self.C = np.array([0.0, 0.0, cfg.camera_height_mm])
        vv, uu = np.mgrid[0 : self.H, 0 : self.W].astype(np.float64)
        xy = cam.undistort(np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(self.H, self.W, 2)
        self.rx, self.ry = xy[..., 0], xy[..., 1]
        self.rlen = np.sqrt(self.rx**2 + self.ry**2 + 1.0)  # ray length per unit Z
        # Local Jacobian of the ray grid, for sub-pixel rays.
        self.dx_du = np.gradient(self.rx, axis=1)
        self.dx_dv = np.gradient(self.rx, axis=0)
        self.dy_du = np.gradient(self.ry, axis=1)
        self.dy_dv = np.gradient(self.ry, axis=0)
        off = (np.arange(cfg.supersample) + 0.5) / cfg.supersample - 0.5
        du, dv = np.meshgrid(off, off)
        self._sub = (du.ravel()[:, None], dv.ravel()[:, None])
        self._rd = np.stack([self.rx, self.ry, np.ones_like(self.rx)], axis=-1)
        self._rd /= self.rlen[..., None]
        # Radial illumination fall-off towards the image corners.
        rr = np.hypot(self.rx, self.ry)
        self.vignette = 1.0 - cfg.vignetting * (rr / rr.max()) ** 2
        self._bank = np.random.default_rng(bank_seed).standard_normal(
            16 * self.H * self.W + 1, dtype=np.float32
        )
        self._background()

    # ------------------------------------------------------------------ geometry helpers
    def to_cam(self, p: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera space (..., 3)."""
        return (np.asarray(p) - self.C) @ self.R.T

    def floor_plane_cam(self) -> np.ndarray:
        """Floor plane in camera space as (nx, ny, nz, d) with n . X + d = 0, n unit, mm."""
        n = self.R @ np.array([0.0, 0.0, 1.0])
        d = -n @ self.to_cam(np.zeros(3))
        return np.r_[n, d]

    def _unit_rays(self, sl: tuple[slice, slice]) -> np.ndarray:
        """Unit ray directions (N, 3) of the pixels in a box, row-major."""
        return self._rd[sl].reshape(-1, 3)

    def _background(self) -> None:
        cfg = self.cfg
        H, W = self.H, self.W
        dirs_c = np.stack([self.rx, self.ry, np.ones_like(self.rx)], axis=-1)
        dirs_w = dirs_c @ self.R  # (H, W, 3) world directions per unit Z
        z = np.full((H, W), np.inf)
        albedo = np.zeros((H, W))
        normal_w = np.zeros((H, W, 3))
        wall_y = cfg.walk_distance_mm + cfg.back_wall_mm
        planes = [((0, 0, 1.0), 0.0, cfg.floor_albedo), ((0, 0, -1.0), 2800.0, 0.5)]
        if cfg.back_wall_mm > 0:
            planes.append(((0, -1.0, 0), wall_y, cfg.wall_albedo))
        for n, off, alb in planes:
            n = np.asarray(n)
            # Plane n.x = n.p0 with p0 on the plane at distance `off` along the axis.
            p0 = np.abs(n) * off
            denom = dirs_w @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                s = ((p0 - self.C) @ n) / denom
            s = np.where((s > 0) & np.isfinite(s), s, np.inf)
            take = s < z
            z[take] = s[take]
            albedo[take] = alb
            normal_w[take] = n
        extra = np.zeros((H, W))  # specular / retro-reflective radiance, counts
        pole_cos = None
        if cfg.stray_reflectors and cfg.back_wall_mm > 0:
            # Retro-reflective safety tape on the back wall: a long thin band, bright but
            # below saturation at that distance.
            p = self.C + dirs_w * np.where(np.isfinite(z), z, 0)[..., None]
            on_wall = np.isclose(p[..., 1], wall_y, atol=1.0)
            band = on_wall & (p[..., 0] > 350) & (p[..., 0] < 950)
            band &= (p[..., 2] > 1020) & (p[..., 2] < 1055)
            r_m = z * self.rlen / 1000.0
            extra[band] = 0.6 * SAT * (4.0 / np.maximum(r_m[band], 0.1)) ** 2
            # A chrome pole (e.g. a drip stand) near the wall: a thin specular highlight.
            a = self.to_cam(np.array([-1500.0, wall_y - 400.0, 0.0]))
            b = self.to_cam(np.array([-1500.0, wall_y - 400.0, 1300.0]))
            rd = self._unit_rays((slice(None), slice(None)))
            t, cosi = capsule_hit(rd, a, b, 14.0)
            zc = (t * rd[:, 2]).reshape(H, W)
            take = zc < z
            cosi = cosi.reshape(H, W)
            z[take] = zc[take]
            albedo[take] = 0.15
            pole_cos = np.where(take, cosi, 0.0)
            extra[take] += 1.4 * SAT * cosi[take] ** 60
        self.bg_z = z
        unit_w = dirs_w / np.linalg.norm(dirs_w, axis=-1, keepdims=True)
        self.bg_cos = np.clip(-(unit_w * normal_w).sum(axis=-1), 0.0, 1.0)
        if pole_cos is not None:
            self.bg_cos = np.where(pole_cos > 0, pole_cos, self.bg_cos)
        r_m = z * self.rlen / 1000.0
        with np.errstate(invalid="ignore"):
            ir = cfg.ir_gain * albedo * self.bg_cos / np.maximum(r_m, 0.1) ** 2
        # the scene without its static reflector spheres: a frame's body box starts from it
        # and z-buffers the spheres against the body (render)
        self.bg_ir_base = np.where(np.isfinite(z), ir * self.vignette + extra, 0.0)
        self.bg_cover = np.zeros((H, W))
        self.bg_zmark = np.full((H, W), np.inf)
        for c in cfg.static_reflectors:
            centre = self.to_cam(np.asarray(c, dtype=float))[None]  # (1 instant, 3)
            box = self._bbox(centre, cfg.marker_radius_mm, 1.5)
            if box is not None and centre[0, 2] > 0:
                self._sphere(centre, box, z, self.bg_cover, self.bg_zmark)
        self.bg_ir = self._marker_radiance(self.bg_ir_base, self.bg_cover, self.bg_zmark)
        finite = np.isfinite(z)
        zf = np.where(finite, z, 0.0)
        zf = self._marker_depth(zf, self.bg_cover, self.bg_zmark)
        self.bg_ir, zf, glared = self._glare(self.bg_ir, zf, self.bg_cover, self.bg_zmark)
        theta = np.arccos(self.bg_cos)
        self.bg_zf = zf.astype(np.float32)
        sigma = cfg.depth_noise_scale * axial_sigma_mm(np.maximum(zf, 1.0), theta)
        self.bg_sigma = sigma.astype(np.float32)
        bad = self._invalid(finite, zf, theta, self.bg_ir) | (self.bg_cover >= cfg.hole_coverage)
        bad |= glared
        self.bg_valid = (~bad).astype(np.float32)
        self.bg_edges = self._edge_pixels(zf)
        self.bg_ir32 = self.bg_ir.astype(np.float32)
        irsd = np.sqrt(cfg.ir_read_noise**2 + cfg.ir_shot_noise * self.bg_ir)
        self.bg_irsd = irsd.astype(np.float32)

    # ------------------------------------------------------------------ per frame
    def _boxes(self, pts_cam: np.ndarray, pad_mm: np.ndarray, pad_px: float) -> np.ndarray:
        """Pixel boxes around groups of camera points, all at once.

        pts_cam : (G, K, 3) camera mm (NaN = ignore); pad_mm : (G,) growth in mm.
        Returns (G, 4) int (v0, v1, u0, u1), clipped to the image; v0 >= v1 = empty.
        """
        offs = np.array(
            [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1]],
            dtype=np.float64,
        )
        G = pts_cam.shape[0]
        if G == 0:
            return np.zeros((0, 4), dtype=np.int64)
        cloud = pts_cam[:, :, None, :] + pad_mm[:, None, None, None] * offs[None, None]
        cloud = cloud.reshape(G, -1, 3)
        z = cloud[..., 2]
        ok = np.isfinite(z) & (z > 50.0)
        zs = np.where(ok, z, 1.0)
        x = np.where(ok, cloud[..., 0], 0.0) / zs
        y = np.where(ok, cloud[..., 1], 0.0) / zs
        c = self.cam
        r2 = x * x + y * y
        radial = 1 + c.k1 * r2 + c.k2 * r2 * r2 + c.k3 * r2 * r2 * r2
        xd = x * radial + 2 * c.p1 * x * y + c.p2 * (r2 + 2 * x * x)
        yd = y * radial + c.p1 * (r2 + 2 * y * y) + 2 * c.p2 * x * y
        # Both the pinhole and the distorted positions: the box must hold the true footprint
        # wherever the distortion moves it.
        us = np.concatenate([c.fx * x + c.cx, c.fx * xd + c.cx], axis=1)
        vs = np.concatenate([c.fy * y + c.cy, c.fy * yd + c.cy], axis=1)
        ok2 = np.concatenate([ok, ok], axis=1)
        u0 = np.floor(np.where(ok2, us, np.inf).min(axis=1) - pad_px)
        u1 = np.ceil(np.where(ok2, us, -np.inf).max(axis=1) + pad_px) + 1
        v0 = np.floor(np.where(ok2, vs, np.inf).min(axis=1) - pad_px)
        v1 = np.ceil(np.where(ok2, vs, -np.inf).max(axis=1) + pad_px) + 1
        out = np.zeros((G, 4), dtype=np.int64)
        good = ok.any(axis=1)
        out[good, 0] = np.clip(v0[good], 0, self.H)
        out[good, 1] = np.clip(v1[good], 0, self.H)
        out[good, 2] = np.clip(u0[good], 0, self.W)
        out[good, 3] = np.clip(u1[good], 0, self.W)
        return out

    def _bbox(self, pts_cam: np.ndarray, pad_mm: float, pad_px: float = 2.0):
        """Pixel box (row slice, col slice) around camera points (K, 3) grown by pad_mm."""
        v0, v1, u0, u1 = self._boxes(pts_cam[None], np.array([pad_mm]), pad_px)[0]
        if v0 >= v1 or u0 >= u1:
            return None
        return slice(int(v0), int(v1)), slice(int(u0), int(u1))

    def _noise(self, rng: np.random.Generator) -> np.ndarray:
        """A (H, W) standard-normal field: a random window of a precomputed noise bank.

        Drawing 2 x 217k normals per frame costs more than the whole rest of the frame, so
        each frame takes its fields at random offsets in a bank 16 times the image size;
        two frames share a field only if they draw the same offset (p ~ 3e-7).
        """
        n = self.H * self.W
        o = int(rng.integers(0, len(self._bank) - n))
        return self._bank[o : o + n].reshape(self.H, self.W)

    def _union_box(self, pose: FramePose) -> tuple[slice, slice] | None:
        """One pixel box holding every capsule and marker of the pose (plus an edge ring)."""
        pts = [pose.cap_a, pose.cap_b, pose.spheres.reshape(-1, 3)]
        pts_w = np.concatenate(pts)
        pts_w = pts_w[np.isfinite(pts_w).all(axis=1)]
        if len(pts_w) == 0:
            return None
        pad = float(max(pose.cap_r.max(initial=0.0), self.cfg.marker_radius_mm))
        return self._bbox(self.to_cam(pts_w), pad, pad_px=4.0)

    def render(self, pose: FramePose | None, rng: np.random.Generator) -> RenderOut:
        """Render one frame. ``pose`` None = empty scene.

        The static background's noise-free IR, depth, noise sigma and validity are
        precomputed; per frame only noise is drawn over the whole image, and the moving
        things are ray cast inside one box around them.
        """
        cfg = self.cfg
        H, W = self.H, self.W
        n_depth = self._noise(rng)
        n_ir = self._noise(rng)
        depth = self.bg_zf + self.bg_sigma * n_depth
        self._apply_edges(depth, self.bg_edges, rng)
        depth *= self.bg_valid
        ir = self.bg_ir32 + self.bg_irsd * n_ir
        n_sph = 0 if pose is None else pose.spheres.shape[1]
        seen = np.zeros(n_sph)
        in_view = np.zeros(n_sph, dtype=bool)
        box = None if pose is None else self._union_box(pose)
        if pose is not None and box is not None:
            v0, u0 = box[0].start, box[1].start
            z = self.bg_z[box].copy()
            cosi = self.bg_cos[box].copy()
            irb = self.bg_ir_base[box].copy()
            a_c = self.to_cam(pose.cap_a)
            b_c = self.to_cam(pose.cap_b)
            cboxes = self._boxes(np.stack([a_c, b_c], axis=1), pose.cap_r, 2.0)
            for k in range(len(a_c)):
                r = float(pose.cap_r[k])
                bv0, bv1, bu0, bu1 = (int(v) for v in cboxes[k])
                if bv0 >= bv1 or bu0 >= bu1:
                    continue
                cb = (slice(bv0, bv1), slice(bu0, bu1))
                loc = (
                    slice(cb[0].start - v0, cb[0].stop - v0),
                    slice(cb[1].start - u0, cb[1].stop - u0),
                )
                rd = self._unit_rays(cb)
                t, ci = capsule_hit(rd, a_c[k], b_c[k], r)
                zc = (t * rd[:, 2]).reshape(z[loc].shape)
                take = zc < z[loc]
                if not take.any():
                    continue
                ci = ci.reshape(zc.shape)
                rm = zc * self.rlen[cb] / 1000.0
                val = cfg.ir_gain * pose.cap_albedo[k] * ci / np.maximum(rm, 0.1) ** 2
                val *= self.vignette[cb]
                z[loc] = np.where(take, zc, z[loc])
                cosi[loc] = np.where(take, ci, cosi[loc])
                irb[loc] = np.where(take, val, irb[loc])
            if cfg.static_reflectors:
                # the static reflectors, except where the body is in front of them
                zmark = self.bg_zmark[box].copy()
                hidden = z < zmark
                cover = np.where(hidden, 0.0, self.bg_cover[box])
                zmark[hidden] = np.inf
            else:
                zmark = np.full(z.shape, np.inf)
                cover = np.zeros(z.shape)
            sph_c = self.to_cam(pose.spheres)  # (B, N, 3)
            # Mid-exposure: the middle sample, or the mean of the two middle ones (the
            # samples are symmetric about t_mid, so this is t_mid to first order).
            nb = sph_c.shape[0]
            mid = 0.5 * (sph_c[(nb - 1) // 2] + sph_c[nb // 2])
            with np.errstate(invalid="ignore"):
                uv = self.cam.project(np.where(np.isfinite(mid), mid, -1.0))
                in_view[:] = (
                    np.isfinite(mid).all(axis=1)
                    & (uv[:, 0] >= 0)
                    & (uv[:, 0] <= W - 1)
                    & (uv[:, 1] >= 0)
                    & (uv[:, 1] <= H - 1)
                    & (mid[:, 2] >= cfg.min_range_mm)
                    & (mid[:, 2] <= cfg.max_range_mm)
                )
            sboxes = self._boxes(
                np.swapaxes(sph_c, 0, 1), np.full(n_sph, cfg.marker_radius_mm), 1.5
            )
            usable = (
                (sboxes[:, 0] < sboxes[:, 1])
                & (sboxes[:, 2] < sboxes[:, 3])
                & np.isfinite(sph_c).all(axis=(0, 2))
            )
            # Pairs of marker boxes that overlap in the image: only these can hide each other.
            overlap = (
                (sboxes[:, None, 0] < sboxes[None, :, 1])
                & (sboxes[None, :, 0] < sboxes[:, None, 1])
                & (sboxes[:, None, 2] < sboxes[None, :, 3])
                & (sboxes[None, :, 2] < sboxes[:, None, 3])
                & usable[:, None]
                & usable[None, :]
            )
            np.fill_diagonal(overlap, False)
            for j in np.flatnonzero(usable):
                bv0, bv1, bu0, bu1 = (int(v) for v in sboxes[j])
                sb = (slice(bv0, bv1), slice(bu0, bu1))
                others = sph_c[:, overlap[j]]
                seen[j] = self._sphere(sph_c[:, j], sb, z, cover, zmark, (v0, u0), others)
            irb = self._marker_radiance(irb, cover, zmark, box)
            finite = np.isfinite(z)
            zf = self._marker_depth(np.where(finite, z, 0.0), cover, zmark)
            irb, zf, glared = self._glare(irb, zf, cover, zmark, box)
            theta = np.arccos(np.clip(cosi, 0.0, 1.0))
            sigma = cfg.depth_noise_scale * axial_sigma_mm(np.maximum(zf, 1.0), theta)
            db = zf + sigma * n_depth[box]
            self._apply_edges(db, self._edge_pixels(zf), rng)
            bad = self._invalid(finite, zf, theta, irb) | (cover >= cfg.hole_coverage) | glared
            depth[box] = np.where(bad, 0.0, db)
            ir_sd = np.sqrt(cfg.ir_read_noise**2 + cfg.ir_shot_noise * np.maximum(irb, 0.0))
            ir[box] = irb + ir_sd * n_ir[box]
        ir16 = np.clip(np.rint(ir), 0, SAT).astype(np.uint16)
        depth16 = np.clip(np.rint(depth), 0, SAT).astype(np.uint16)
        return RenderOut(ir16, depth16, seen, in_view)

    def _marker_radiance(
        self,
        ir: np.ndarray,
        cover: np.ndarray,
        zmark: np.ndarray,
        box: tuple[slice, slice] = (slice(None), slice(None)),
    ) -> np.ndarray:
        """IR with the marker spheres' coverage (``cover``, front depth ``zmark``) mixed in.

        A retro-reflector returns ``marker_gain`` times saturation at 2.5 m, falling off with
        the square of the distance; a pixel's value mixes it with what the rest shows.
        """
        hit = cover > 0
        if not hit.any():
            return ir
        return np.where(hit, self._marker_light(cover, zmark, box) + (1.0 - cover) * ir, ir)

    def _marker_light(
        self, cover: np.ndarray, zmark: np.ndarray, box: tuple[slice, slice]
    ) -> np.ndarray:
        """The light the marker spheres return into each pixel (0 where none covers it)."""
        hit = cover > 0
        rm = np.where(hit, zmark, 1.0) * self.rlen[box] / 1000.0
        rad = self.cfg.marker_gain * SAT * (2.5 / np.maximum(rm, 0.1)) ** 2
        return np.where(hit, cover * rad, 0.0)

    def _glare(
        self,
        ir: np.ndarray,
        zf: np.ndarray,
        cover: np.ndarray,
        zmark: np.ndarray,
        box: tuple[slice, slice] = (slice(None), slice(None)),
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lens glare around the markers: (IR, depth, pixels whose depth it invalidates).

        The optics scatter ``glare_fraction`` of each marker's light over the pixels around
        it (a Gaussian of ``glare_sigma_px``). A time-of-flight pixel measures the phase of
        all the light it gets, so the stray light, which carries the marker's depth, pulls
        the pixel's depth towards it by its share of the pixel's light (a linear mix: the
        phasor sum for depths within a fraction of the modulation wavelength), and where
        that share exceeds ``glare_invalid_share`` the depth is reported invalid: the hole
        around a marker grows beyond the marker's image. Off (``glare_fraction`` 0) by
        default; the ``glare`` variant turns it on.
        """
        cfg = self.cfg
        none = np.zeros(ir.shape, dtype=bool)
        if cfg.glare_fraction <= 0.0 or not (cover > 0).any():
            return ir, zf, none
        from scipy.ndimage import gaussian_filter

        light = self._marker_light(cover, zmark, box)
        spread = dict(sigma=cfg.glare_sigma_px, mode="constant", truncate=3.0)
        stray = cfg.glare_fraction * gaussian_filter(light, **spread)
        stray_z = gaussian_filter(light * np.where(cover > 0, zmark, 0.0), **spread)
        own = ir - cfg.glare_fraction * light  # the marker keeps what it does not scatter
        total = own + stray
        share = np.divide(stray, total, out=np.zeros_like(total), where=total > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            z_stray = np.where(stray > 0, cfg.glare_fraction * stray_z / stray, 0.0)
        mixed = np.where((zf > 0) & (stray > 0), (1.0 - share) * zf + share * z_stray, zf)
        return total, mixed, (share > cfg.glare_invalid_share) & (cover < cfg.hole_coverage)

    def _marker_depth(self, zf: np.ndarray, cover: np.ndarray, zmark: np.ndarray) -> np.ndarray:
        """Depth with the spheres' partly covered pixels mixing both surfaces (a pixel
        covered by ``hole_coverage`` or more becomes a hole later, in ``_invalid``'s caller)."""
        mix = (cover > 0) & (cover < self.cfg.hole_coverage)
        return np.where(mix, cover * np.where(mix, zmark, 0.0) + (1 - cover) * zf, zf)

    def _invalid(
        self, finite: np.ndarray, zf: np.ndarray, theta: np.ndarray, ir: np.ndarray
    ) -> np.ndarray:
        """Pixels a Kinect v2 reports as 0: no return, out of range, grazing, dark, saturated."""
        cfg = self.cfg
        bad = ~finite | (zf < cfg.min_range_mm) | (zf > cfg.max_range_mm)
        bad |= theta > np.radians(cfg.max_incidence_deg)
        bad |= ir < cfg.ir_min_valid
        bad |= ir >= SAT
        return bad

    def _edge_pixels(self, zf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth-edge pixels: flat indices, their own depth and the depth across the edge."""
        jump = self.cfg.edge_jump_mm
        far = np.zeros_like(zf)
        near = np.full_like(zf, np.inf)
        for sl_to, sl_from in (
            ((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
            ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
            ((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
            ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        ):
            nb = zf[sl_from]
            far[sl_to] = np.maximum(far[sl_to], nb)
            near[sl_to] = np.minimum(near[sl_to], np.where(nb > 0, nb, np.inf))
        fg = far - zf > jump  # this pixel is in front of a neighbour
        bg = zf - near > jump
        idx = np.flatnonzero(fg | bg)
        zz = zf.ravel()[idx]
        other = np.where(fg.ravel()[idx], far.ravel()[idx], near.ravel()[idx])
        return idx, zz, other

    def _apply_edges(
        self, depth: np.ndarray, edges: tuple[np.ndarray, np.ndarray, np.ndarray], rng
    ) -> None:
        """Flying (mixed-depth) and invalid pixels along depth edges, in place.

        A time-of-flight pixel that straddles an edge integrates both surfaces, so it
        reports a depth between them; the driver's filters remove some of them (0).
        """
        cfg = self.cfg
        idx, zz, other = edges
        if len(idx) == 0:
            return
        u = rng.random(len(idx))
        w = rng.random(len(idx))
        flat = depth.reshape(-1)
        fly = u < cfg.flying_prob
        flat[idx[fly]] = (w * zz + (1 - w) * other)[fly]
        inval = (u >= cfg.flying_prob) & (u < cfg.flying_prob + cfg.edge_invalid_prob)
        flat[idx[inval]] = 0.0

    def _sphere(
        self,
        centres: np.ndarray,
        box: tuple[slice, slice],
        z: np.ndarray,
        cover: np.ndarray,
        zmark: np.ndarray,
        origin: tuple[int, int] = (0, 0),
        others: np.ndarray | None = None,
    ) -> float:
        """Accumulate one marker's supersampled, motion-blurred coverage.

        centres : (B, 3) camera-space centres over the exposure; box : its pixel box.
        others : (B, M, 3) centres of the other markers whose boxes overlap this one; a
        sub-sample (sub-pixel ray at one instant) is this marker's only if no other sphere
        is hit nearer along that ray at that instant (a z-buffer between spheres), and no
        body surface is nearer (``z``).
        Updates ``cover`` (pixel coverage 0..1) and ``zmark`` (marker front depth) in
        place; these and ``z`` are views of a box whose top-left pixel is ``origin``
        (row, col). Returns the visible fraction of the marker's footprint.
        """
        cfg = self.cfg
        rad = cfg.marker_radius_mm
        du, dv = self._sub  # (S2, 1) sub-pixel offsets
        sl = box
        rx = self.rx[sl][..., None, None]
        ry = self.ry[sl][..., None, None]
        rx = rx + du * self.dx_du[sl][..., None, None] + dv * self.dx_dv[sl][..., None, None]
        ry = ry + du * self.dy_du[sl][..., None, None] + dv * self.dy_dv[sl][..., None, None]
        # Ray points Z * (rx, ry, 1); |Z d - c|^2 = rad^2 gives Z (the depth) directly.
        dd = rx * rx + ry * ry + 1.0  # (h, w, S2, 1)
        c = centres  # (B, 3)
        bq = rx * c[:, 0] + ry * c[:, 1] + c[:, 2]  # (h, w, S2, B)
        cq = (c * c).sum(axis=1) - rad * rad
        disc = bq * bq - dd * cq
        ok = disc >= 0
        zt = (bq - np.sqrt(np.where(ok, disc, 0.0))) / dd
        ok &= zt > 0
        loc = (
            slice(sl[0].start - origin[0], sl[0].stop - origin[0]),
            slice(sl[1].start - origin[1], sl[1].stop - origin[1]),
        )
        vis = ok & (zt < z[loc][..., None, None])
        if others is not None:
            for m in range(others.shape[1]):
                o = others[:, m]  # (B, 3)
                bo = rx * o[:, 0] + ry * o[:, 1] + o[:, 2]
                disc_o = bo * bo - dd * ((o * o).sum(axis=1) - rad * rad)
                hit_o = disc_o >= 0
                zo = (bo - np.sqrt(np.where(hit_o, disc_o, 0.0))) / dd
                vis &= ~(hit_o & (zo > 0) & (zo < zt))
        nvis = vis.sum(axis=(2, 3))
        cov = nvis / (ok.shape[2] * ok.shape[3])
        free = ok.sum()
        seen = float(nvis.sum() / free) if free > 0 else 0.0
        zfront = np.where(vis, zt, np.inf).min(axis=(2, 3))
        cv = cover[loc]
        zm = zmark[loc]
        # Sub-samples of different markers are disjoint (z-buffered above), so coverage
        # adds; the depth keeps the nearer front.
        np.minimum(cv + cov, 1.0, out=cv)
        np.minimum(zm, zfront, out=zm)
        return seen
