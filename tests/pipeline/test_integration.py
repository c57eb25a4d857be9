"""Normal integration (pipeline.surface.integration) against analytic surfaces, an independent sparse
least-squares solve, and two public datasets (BiNI's DiLiGenT depth maps, Queau's vase)."""

import cv2
import numpy as np
import pytest
import scipy.io

from pipeline.surface.integration import integrate_gradient, integrate_normals, log_depth_gradients
from tests.pipeline.surfaces import plate_camera, render_cylinder, sparse_least_squares
from tests.realdata import BINI, VASE, load_bini, made_after_median_scale


@pytest.fixture(scope="module")
def plate():
    """The paper's geometry (3 m plate at 3 m, R = 5 m) at 1/4 of 1224x1024: fx ~ 225 px."""
    K = plate_camera(306, 256, 225.0)
    n, mask, depth = render_cylinder(K, (256, 306))
    return K, n, mask, depth


def rms(a):
    return float(np.sqrt(np.nanmean(np.square(a))))


# ------------------------------------------------------------------------------ the gradient formula


def test_log_depth_gradient_matches_rendered_surface(plate):
    K, n, mask, depth = plate
    p, q, usable = log_depth_gradients(n, mask, np.linalg.inv(K))
    assert np.array_equal(usable, mask)  # every normal of the plate usable, none outside it
    t = np.log(depth)
    c = np.s_[2:-2, 2:-2]
    # fourth-order central differences of the true log depth (3-point ones are off by ~1e-7 here)
    fd_u = (-t[2:-2, 4:] + 8 * t[2:-2, 3:-1] - 8 * t[2:-2, 1:-3] + t[2:-2, :-4]) / 12
    fd_v = (-t[4:, 2:-2] + 8 * t[3:-1, 2:-2] - 8 * t[1:-3, 2:-2] + t[:-4, 2:-2]) / 12
    inner = np.isfinite(fd_u) & np.isfinite(fd_v)
    # their error ~ h^4 t^(5) / 30 is ~1e-11; the gradients are ~1e-3
    np.testing.assert_allclose(p[c][inner], fd_u[inner], atol=1e-9)
    np.testing.assert_allclose(q[c][inner], fd_v[inner], atol=1e-9)
    assert np.abs(p[mask]).max() > 1e-4  # non-trivial: the plate is tilted and curved
    # a normal facing away from the camera, or not a unit vector, gives no slope and is flagged
    i, j = np.argwhere(mask)[len(np.argwhere(mask)) // 2]
    bent = n.copy()
    bent[i, j] *= -1.0
    bent[i, j + 1] *= 2.0
    p2, q2, usable2 = log_depth_gradients(bent, mask, np.linalg.inv(K))
    assert not usable2[i, j] and not usable2[i, j + 1] and p2[i, j] == q2[i, j + 1] == 0.0
    assert np.count_nonzero(mask & ~usable2) == 2


# ------------------------------------------------------------------------------ accuracy on the plate


def test_cylinder_with_reference_depth_is_metric_to_microns(plate):
    K, n, mask, depth = plate
    ref = float(np.median(depth[mask]))
    res = integrate_normals(n, mask, K, reference_depth_mm=ref)
    assert res.depth_mm.shape == mask.shape and res.depth_mm.dtype == np.float64
    assert np.all(np.isnan(res.depth_mm[~mask])) and np.all(np.isfinite(res.depth_mm[mask]))
    assert res.residual <= 1e-6 and 0 < res.iterations < 30
    assert np.median(res.depth_mm[mask]) == pytest.approx(ref, rel=1e-12)
    # exact gradients; the only error is the trapezoid rule along neighbour pairs, O(h^2 t''') ~ 2 um here
    assert rms(res.depth_mm - depth) < 0.01
    assert np.nanmax(np.abs(res.depth_mm - depth)) < 0.05


def test_convex_plate_tilted_other_way(plate):
    K = plate[0]
    n, mask, depth = render_cylinder(
        K, (256, 306), convex=True, tilt_rad=(-0.09, 0.03), radius_mm=3000.0
    )
    res = integrate_normals(n, mask, K, reference_depth_mm=float(np.median(depth[mask])))
    assert rms(res.depth_mm - depth) < 0.01  # same reason as above


def test_prior_alone_fixes_the_scale(plate):
    K, n, mask, depth = plate
    rng = np.random.default_rng(3)
    prior = np.where(
        rng.random(mask.shape) < 0.05, 1.03 * depth, np.nan
    )  # 5 % of pixels, scale 1.03
    res = integrate_normals(n, mask, K, prior_depth_mm=prior)
    # normals and prior agree up to the scale factor, so the fused depth is exactly 1.03 x truth
    # (up to the 2-um discretisation error of the normals)
    np.testing.assert_allclose(res.depth_mm[mask], 1.03 * depth[mask], rtol=5e-6)


def test_prior_gives_scale_and_normals_give_detail(plate):
    K, n, mask, depth = plate
    rng = np.random.default_rng(7)
    sigma_mm = 3.0  # stereo-like depth noise
    prior = depth + rng.normal(0.0, sigma_mm, depth.shape)
    res = integrate_normals(n, mask, K, prior_depth_mm=prior, prior_weight=1e-2)
    # the prior's white noise is averaged over ~ (1/sqrt(w))^2 = 100 px by the normals' smoothness, and
    # the scale is fixed by ~46 000 prior pixels: the error drops by far more than sqrt(100)
    err = rms(res.depth_mm - depth)
    assert err < sigma_mm / 10
    assert abs(np.mean(res.depth_mm[mask] - depth[mask])) < 0.1  # no scale bias


def test_noisy_normals_degrade_gracefully(plate):
    K, n, mask, depth = plate
    rng = np.random.default_rng(11)
    errs = []
    for sigma in (0.002, 0.01):  # ~0.1 deg and ~0.6 deg of normal noise
        noisy = n + rng.normal(0.0, sigma, n.shape)
        noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
        res = integrate_normals(noisy, mask, K, reference_depth_mm=float(np.median(depth[mask])))
        errs.append(rms(res.depth_mm - depth))
    # integration averages white gradient noise: the depth error grows ~linearly with the noise and
    # stays at the mm level for 0.6 deg on a 3 m plate (1 px ~ 13 mm here)
    assert errs[0] < 0.5 and errs[1] < 2.5
    assert 2.0 < errs[1] / errs[0] < 8.0


# ------------------------------------------------------------------------------ it is the least-squares solution


def irregular_mask(rng, hw):
    """A blob with holes and ragged edges (one connected part is not guaranteed)."""
    noise = cv2.GaussianBlur(rng.normal(size=hw), (0, 0), 6.0)
    return noise > np.quantile(noise, 0.35)


def test_solver_equals_direct_sparse_solve_on_an_irregular_mask():
    rng = np.random.default_rng(5)
    hw = (96, 128)
    K = plate_camera(128, 96, 110.0)
    n, _, depth = render_cylinder(K, hw, plate_mm=(9000.0, 9000.0))
    n = n + rng.normal(
        0.0, 0.02, n.shape
    )  # a non-integrable field: the LS solution is not the truth
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = irregular_mask(rng, hw)
    prior = np.where(rng.random(hw) < 0.1, depth * np.exp(rng.normal(0, 0.01, hw)), np.nan)
    res = integrate_normals(n, mask, K, prior_depth_mm=prior, prior_weight=0.05, tol=1e-10)
    ref = np.exp(sparse_least_squares(n, mask, K, np.log(prior), np.float32(0.05)))
    # the weights are used in float32 (0.05 -> 0.0500000007); tol 1e-10 leaves ~1e-9 relative error
    np.testing.assert_allclose(res.depth_mm[mask], ref[mask], rtol=1e-8)


def test_parts_without_prior_take_the_reference_or_are_left_out():
    K = plate_camera(120, 80, 100.0)
    n, _, depth = render_cylinder(K, (80, 120), plate_mm=(9000.0, 9000.0))
    mask = np.zeros((80, 120), bool)
    mask[5:40, 5:50] = True
    mask[45:75, 60:115] = True
    mask[60, 10] = True  # an isolated pixel: no neighbour equation at all
    res = integrate_normals(n, mask, K, reference_depth_mm=2500.0)
    for part in (np.s_[5:40, 5:50], np.s_[45:75, 60:115]):
        assert np.median(res.depth_mm[part]) == pytest.approx(2500.0, rel=1e-12)
        # shape within a part is right up to its own scale (and the trapezoid-rule error, ~3e-5 relative
        # on this coarse 100-px-focal view of a strongly curved surface)
        ratio = res.depth_mm[part] / depth[part]
        assert np.ptp(ratio) / ratio.mean() < 1e-4
    assert res.depth_mm[60, 10] == pytest.approx(2500.0)

    prior = np.full((80, 120), np.nan)
    prior[20, 20] = depth[20, 20]  # the prior reaches only the first part
    res = integrate_normals(n, mask, K, prior_depth_mm=prior, reference_depth_mm=2500.0)
    np.testing.assert_allclose(res.depth_mm[5:40, 5:50], depth[5:40, 5:50], rtol=1e-4)
    assert np.median(res.depth_mm[45:75, 60:115]) == pytest.approx(2500.0, rel=1e-12)
    # without a reference, the parts the prior does not reach have no metric depth: NaN, and left out
    # of the result's mask (the isolated pixel too)
    res = integrate_normals(n, mask, K, prior_depth_mm=prior)
    np.testing.assert_allclose(res.depth_mm[5:40, 5:50], depth[5:40, 5:50], rtol=1e-4)
    assert np.all(np.isnan(res.depth_mm[45:75, 60:115])) and np.isnan(res.depth_mm[60, 10])
    expected = np.zeros_like(mask)
    expected[5:40, 5:50] = True
    np.testing.assert_array_equal(res.mask, expected)
    with pytest.raises(
        ValueError, match=r"prior_depth_mm: expected at least one depth with a weight > 0 inside"
    ):
        integrate_normals(n, mask, K, prior_depth_mm=np.full(mask.shape, np.nan))


def test_fronto_parallel_plane_gives_constant_depth():
    K = plate_camera(64, 48, 60.0)
    n = np.zeros((48, 64, 3), np.float32)
    n[..., 2] = -1.0
    res = integrate_normals(n, np.ones((48, 64), bool), K, reference_depth_mm=1234.0)
    np.testing.assert_allclose(res.depth_mm, 1234.0, rtol=1e-12)
    assert res.iterations == 0 and res.residual == 0.0


# ------------------------------------------------------------------------------ bad input


@pytest.fixture(scope="module")
def small():
    K = plate_camera(40, 30, 40.0)
    n, mask, depth = render_cylinder(K, (30, 40), plate_mm=(9000.0, 9000.0))
    return n, mask, K, depth


def test_bad_input_is_rejected(small):
    n, mask, K, _depth = small
    with pytest.raises(ValueError, match=r"normals: expected shape \(H, W, 3\), got \(30, 40\)"):
        integrate_normals(n[..., 0], mask, K, reference_depth_mm=1.0)
    with pytest.raises(ValueError, match=r"mask: expected shape \(30, 40\), got \(30, 41\)"):
        integrate_normals(n, np.ones((30, 41), bool), K, reference_depth_mm=1.0)
    with pytest.raises(ValueError, match=r"mask: expected dtype bool, got uint8"):
        integrate_normals(n, mask.astype(np.uint8), K, reference_depth_mm=1.0)
    with pytest.raises(ValueError, match=r"mask: expected at least one valid"):
        integrate_normals(n, np.zeros_like(mask), K, reference_depth_mm=1.0)
    with pytest.raises(ValueError, match=r"K: expected \[\[fx, s, cx\]"):
        integrate_normals(n, mask, -K, reference_depth_mm=1.0)
    with pytest.raises(
        ValueError, match=r"prior_depth_mm, reference_depth_mm: expected at least one"
    ):
        integrate_normals(n, mask, K)
    with pytest.raises(
        ValueError, match=r"reference_depth_mm: expected a positive depth in mm, got -5"
    ):
        integrate_normals(n, mask, K, reference_depth_mm=-5.0)
    with pytest.raises(ValueError, match=r"tol: expected a relative residual in \(0, 1\), got 0"):
        integrate_normals(n, mask, K, reference_depth_mm=1.0, tol=0.0)
    with pytest.raises(ValueError, match=r"max_iter: expected a positive integer, got 0"):
        integrate_normals(n, mask, K, reference_depth_mm=1.0, max_iter=0)


def test_bad_normals_are_counted_not_dropped(small):
    n, mask, K, _depth = small
    bad = n.copy()
    bad[10, 10] = -bad[10, 10]  # facing away from the camera
    bad[11, 11] = np.nan
    bad[12, 12] *= 1.5  # not unit
    with pytest.raises(
        ValueError, match=r"normals: expected finite unit vectors facing the camera .* got 3 pixel"
    ):
        integrate_normals(bad, mask, K, reference_depth_mm=1.0)
    outside = n.copy()
    m2 = mask.copy()
    m2[10, 10] = False
    outside[10, 10] = np.nan  # ignored outside the mask
    assert np.isnan(integrate_normals(outside, m2, K, reference_depth_mm=1.0).depth_mm[10, 10])


def test_bad_prior_is_rejected(small):
    n, mask, K, depth = small
    with pytest.raises(
        ValueError, match=r"prior_depth_mm: expected shape \(30, 40\), got \(30, 39\)"
    ):
        integrate_normals(n, mask, K, prior_depth_mm=depth[:, 1:])
    neg = depth.copy()
    neg[3, 3] = -1.0
    with pytest.raises(
        ValueError, match=r"prior_depth_mm: expected depths > 0 mm or NaN, got 1 pixel"
    ):
        integrate_normals(n, mask, K, prior_depth_mm=neg)
    with pytest.raises(ValueError, match=r"prior_weight: expected a finite weight >= 0, got -1"):
        integrate_normals(n, mask, K, prior_depth_mm=depth, prior_weight=-1.0)
    with pytest.raises(
        ValueError, match=r"prior_weight: expected a scalar or shape \(30, 40\), got \(3,\)"
    ):
        integrate_normals(n, mask, K, prior_depth_mm=depth, prior_weight=np.ones(3))


def test_bad_gradients_are_rejected():
    mask = np.ones((20, 30), bool)
    g = np.zeros((20, 30))
    with pytest.raises(
        ValueError, match=r"grad_v: expected shape \(20, 30\) like grad_u, got \(20, 31\)"
    ):
        integrate_gradient(g, np.zeros((20, 31)), mask)
    bad = g.copy()
    bad[3, 4] = np.inf
    with pytest.raises(ValueError, match=r"grad_u: expected finite values inside the mask, got 1"):
        integrate_gradient(bad, g, mask)


# ------------------------------------------------------------------------------ orthographic helper


def test_integrate_gradient_recovers_a_quadratic_on_an_irregular_mask():
    rng = np.random.default_rng(2)
    hw = (80, 100)
    v, u = np.mgrid[0:80, 0:100].astype(float)
    height = 0.01 * (u - 40) ** 2 - 0.02 * (u - 40) * (v - 30) + 0.005 * v**2 + 0.3 * u
    gu = 0.02 * (u - 40) - 0.02 * (v - 30) + 0.3
    gv = -0.02 * (u - 40) + 0.01 * v
    mask = irregular_mask(rng, hw)
    res = integrate_gradient(gu, gv, mask)
    # averaged endpoint gradients are exact for a quadratic: only the solver tolerance remains
    from scipy.ndimage import label

    labels, k = label(mask)
    for part in range(1, k + 1):
        sel = labels == part
        expected = height[sel] - height[sel].mean()
        np.testing.assert_allclose(res.height[sel], expected, atol=1e-6 * np.ptp(height))
    assert np.all(np.isnan(res.height[~mask]))


# ------------------------------------------------------------------------------ real data


@pytest.mark.skipif(not BINI.is_dir(), reason=f"BiNI DiLiGenT data not found at {BINI}")
def test_bini_cat_and_pot2_depth_error():
    # plain least squares smooths over depth discontinuities (BiNI handles them): on cat it is
    # 0.40 mm vs BiNI's 0.074; on pot2 (few discontinuities) it is 0.16 mm vs BiNI's 0.22
    bounds = {"cat": 0.45, "pot2": 0.2}
    for obj, bound in bounds.items():
        n, mask, K, gt = load_bini(obj)
        res = integrate_normals(n, mask, K, reference_depth_mm=1500.0)
        assert made_after_median_scale(res.depth_mm, gt, mask) < bound, obj


@pytest.mark.skipif(not VASE.is_file(), reason=f"Queau's vase not found at {VASE}")
def test_vase_plain_least_squares_rmse():
    m = scipy.io.loadmat(VASE)
    # the file's p is dh/d(row, downwards) = our grad_v; q is dh/d(col) = our grad_u
    mask = m["mask"] > 0
    res = integrate_gradient(m["q"], m["p"], mask)
    truth = m["u"] - m["u"][mask].mean()
    err = float(np.sqrt(np.mean((res.height[mask] - truth[mask]) ** 2)))
    # SOURCE.txt: the same least-squares equations solved by spsolve give 0.108
    assert err == pytest.approx(0.108, abs=0.002)


def test_multigrid_preconditioner_is_symmetric_and_positive():
    # conjugate gradients needs a symmetric positive preconditioner: the V-cycle must be its own
    # adjoint (pre-smoothing red-black, post-smoothing black-red, restriction = prolongation^T)
    from pipeline.solvers import Multigrid
    from pipeline.surface.integration import _fine_system

    rng = np.random.default_rng(4)
    hw = (70, 90)
    mask = irregular_mask(rng, hw)
    h, w = hw
    ex, ey, wdp, dg, idg = (np.zeros((h + 2, w + 2), np.float32) for _ in range(5))
    b = np.zeros((h + 2, w + 2))
    wd = np.where(rng.random(hw) < 0.05, 0.01, 0.0).astype(np.float32)
    _fine_system(mask, np.zeros(hw), np.zeros(hw), wd, np.zeros(hw), 0.0, ex, ey, wdp, dg, idg, b)
    mg = Multigrid(ex, ey, wdp, dg, idg)
    u, v = (np.zeros((h + 2, w + 2)) for _ in range(2))
    u[1:-1, 1:-1][mask] = rng.normal(size=mask.sum())
    v[1:-1, 1:-1][mask] = rng.normal(size=mask.sum())
    mu = mg.apply(u)[0].astype(np.float64)
    mv = mg.apply(v)[0].astype(np.float64)
    # float32 arithmetic inside the cycle: symmetric to ~1e-6 relative
    assert abs(np.vdot(v, mu) - np.vdot(u, mv)) < 1e-5 * np.vdot(u, mu)
    assert np.vdot(u, mu) > 0 and np.vdot(v, mv) > 0
    assert np.all(mu[1:-1, 1:-1][~mask] == 0)


def test_bad_prior_weight_map_is_rejected(small):
    n, mask, K, depth = small
    weight = np.full(mask.shape, 0.01)
    weight[5, 5] = np.nan
    weight[6, 6] = -1.0
    with pytest.raises(
        ValueError,
        match=r"prior_weight: expected finite weights >= 0 where the prior is known, got 2",
    ):
        integrate_normals(n, mask, K, prior_depth_mm=depth, prior_weight=weight)


def render_sphere(K, hw, *, radius_mm, centre_mm):
    """Ray-trace the near side of a sphere (camera frame, mm); returns normals, mask, depth."""
    h, w = hw
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    c = np.asarray(centre_mm, dtype=float)
    a = np.sum(rays * rays, -1)
    half_b = -np.sum(rays * c, -1)
    disc = half_b**2 - a * (c @ c - radius_mm**2)
    lam = (-half_b - np.sqrt(np.maximum(disc, 0.0))) / a  # the nearer hit
    pts = lam[..., None] * rays
    n = (pts - c) / radius_mm
    mask = disc > 0
    return n, mask, np.where(mask, lam, np.nan)


def test_sphere_cap_off_axis_with_prior_on_a_few_pixels():
    # double curvature, off the optical axis, fx != fy: nothing cylinder-specific
    K = plate_camera(320, 240, 260.0)
    n, mask, depth = render_sphere(
        K, (240, 320), radius_mm=4000.0, centre_mm=(600.0, -300.0, 7200.0)
    )
    mask &= (
        np.sum(n * np.array([0.0, 0.0, -1.0]), -1) > 0.9
    )  # the cap within ~25 deg of facing the camera
    rng = np.random.default_rng(9)
    prior = np.where(rng.random(mask.shape) < 0.02, depth, np.nan)
    res = integrate_normals(n, mask, K, prior_depth_mm=prior)
    # exact normals and exact sparse prior: only the trapezoid-rule error remains (2.4 um RMS here; it
    # is second order: 0.6 um at twice the resolution). On steeper caps it grows along the thin pixel
    # chains of the mask border (slopes up to 53 deg: 0.18 mm RMS, 20 mm at one border pixel)
    assert rms(res.depth_mm - depth) < 0.02
    assert np.nanmax(np.abs(res.depth_mm - depth)) < 0.1
