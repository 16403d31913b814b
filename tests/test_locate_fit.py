"""locate's surface fit (plane + curvature extrapolated to the centroid) on literal frames."""

from __future__ import annotations

import numpy as np
import pytest
from gaitflow.stages import locate


def params(**kw):
    # The fit is off by default (see locate's docstring); these tests are about the fit.
    return locate.PARAMS.resolve({"surface_fit": True, **kw})


CEN = (40.3, 30.6)


def surface(f, shape=(60, 80), hole=2.5, seed=0, noise=1.5) -> np.ndarray:
    """Depth f(du, dv) mm around CEN, Gaussian noise, the marker's hole as 0."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    du, dv = cc - CEN[0], rr - CEN[1]
    d = f(du, dv) + rng.normal(0.0, noise, shape)
    d[np.hypot(du, dv) <= hole] = 0
    return np.clip(d, 0, 65535).astype(np.uint16)


def depth(d: np.ndarray, **kw) -> float:
    return locate.locate_depth(d, CEN, 2.5, params(**kw))[0]


@pytest.mark.parametrize("seed", range(3))
def test_curved_skin_depth_at_the_hole_not_the_ring(seed: int) -> None:
    # A convex limb under the marker: depth grows with the squared distance from it. The
    # ring is a few mm deeper than the skin under the marker; the fit removes that.
    d = surface(lambda u, v: 2500.0 + 0.8 * (u * u + v * v), seed=seed)
    assert depth(d, surface_fit=False) > 2506.0  # R8: the ring's depth
    assert abs(depth(d) - 2500.0) < 2.0


@pytest.mark.parametrize("seed", range(3))
def test_one_sided_slope_extrapolated_to_the_centroid(seed: int) -> None:
    # A marker on the silhouette of a surface sloping away (12 mm per px towards +u), the
    # background metres behind on the other side: only the body half is in the layer.
    d = surface(lambda u, v: np.where(u <= 1.0, 2500.0 - 12.0 * u, 4200.0), seed=seed)
    assert depth(d, surface_fit=False) > 2508.0  # R8 averages the body half only
    assert abs(depth(d) - 2500.0) < 4.0


def test_fit_falls_back_to_alg3_with_too_few_pixels() -> None:
    d = surface(lambda u, v: 2500.0 + 0.8 * (u * u + v * v))
    ref = depth(d, surface_fit=False)
    # More pixels required than the window holds: R5-R8's value, exactly.
    assert depth(d, fit_min_px=500) == ref
    # A fit that would leave its layer by more than fit_max_step is not used either.
    assert depth(d, fit_max_step=0.0, fit_max_se=1e9) in (ref, pytest.approx(2500.0, abs=2.0))


def test_standard_error_gate_keeps_alg3_for_poor_fits() -> None:
    d = surface(lambda u, v: 2500.0 + 0.8 * (u * u + v * v), noise=25.0, seed=4)
    ref = depth(d, surface_fit=False)
    assert depth(d, fit_max_se=0.5) == ref
    assert depth(d, fit_max_se=1e9) != ref


def test_weighted_lsq_recovers_a_plane_and_its_standard_error() -> None:
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-4, 4, (2, 40))
    A = np.stack([np.ones_like(x), x, y])
    z = 3.0 + 2.0 * x - 1.5 * y
    # Two jobs: the exact plane (zero residual, zero standard error) and a noisy copy.
    AA = np.concatenate([A, A], axis=1)
    zz = np.concatenate([z, z + rng.normal(0, 2.0, 40)])
    runs = np.array([0, 40]), np.array([40, 40])
    coef, se, _ = locate._weighted_lsq(*runs, np.vstack([AA, zz]), None)
    np.testing.assert_allclose(coef[0], [3.0, 2.0, -1.5], atol=1e-6)
    assert se[0] < 1e-3
    assert 0.1 < se[1] < 1.5  # about sigma / sqrt(n) = 0.32 mm


def test_curvature_term_can_be_switched_off() -> None:
    d = surface(lambda u, v: 2500.0 + 0.8 * (u * u + v * v))
    # A plane through a bowl's ring sits at the ring's depth, not at the bottom.
    assert depth(d, fit_curvature=False) > 2506.0
    assert abs(depth(d, fit_curvature=True) - 2500.0) < 2.0


def test_positions_use_radius_plus_base() -> None:
    from gaitflow.camera import Camera

    d = surface(lambda u, v: np.full_like(u, 2500.0, dtype=float), noise=0.0)
    cen = np.array([CEN])
    rr = np.array([2.5])
    _, p0 = locate.locate_all(d, cen, rr, Camera(), params(surface_offset=False))
    _, p1 = locate.locate_all(d, cen, rr, Camera(), params(marker_base_mm=4.0), 20.0)
    shrink = np.linalg.norm(p0[0, 0]) - np.linalg.norm(p1[0, 0])
    assert shrink == pytest.approx(10.0 + 4.0)
