"""Photometric normals (pipeline/surface/normals/) against analytic truth and real benchmark data."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.camera import undistorted_rays
from pipeline.formats import CaptureError
from pipeline.surface.normals import NormalField, estimate_normals
from tests import realdata as rd

H, W = 128, 160


def ring_lights(n: int = 12, polar_deg: float = 40.0, offset_deg: float = 0.0) -> np.ndarray:
    """n unit light directions on a cone of ``polar_deg`` around the camera's -z axis (OpenCV frame)."""
    phi = np.radians(offset_deg) + np.linspace(0, 2 * np.pi, n, endpoint=False)
    t = np.radians(polar_deg)
    return np.stack(
        [np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), -np.full(n, np.cos(t))], axis=1
    )


def curved_plate() -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) of a gently curved, tilted plate (tilts up to ~15 deg) and a varying albedo."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    p = 0.1 + 0.4 * (u - W / 2) / W  # dZ/dx
    q = 0.15 * np.sin(2 * np.pi * v / H)  # dZ/dy
    n = np.stack([p, q, -np.ones_like(p)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    albedo = 0.6 + 0.2 * np.cos(2 * np.pi * u / W) * np.sin(np.pi * v / H)
    return n, albedo


def sphere(radius_px: float = 58.0) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) of a sphere centred in the image (NaN outside) and its (H, W) mask (r < 0.97 R)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = (u - W / 2 + 0.5) / radius_px, (v - H / 2 + 0.5) / radius_px
    r2 = x**2 + y**2
    mask = r2 < 0.97**2
    n = np.stack([x, y, -np.sqrt(np.clip(1 - r2, 0, None))], axis=-1)
    n[~mask] = np.nan
    return n, mask


def render(normals, albedo, lights, rng, *, noise=0.005, specular=0.0, shininess=40.0):
    """Lambertian images rho max(0, n.l) (+ Blinn-Phong lobe, viewer at -z) + Gaussian noise: (N, H, W) float32."""
    shading = np.einsum("hwc,kc->khw", np.nan_to_num(normals), lights)
    images = albedo * np.maximum(shading, 0.0)
    if specular:
        half = lights + np.array([0.0, 0.0, -1.0])
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        nh = np.maximum(np.einsum("hwc,kc->khw", np.nan_to_num(normals), half), 0.0)
        images = images + specular * nh**shininess * (shading > 0)
    images = images + rng.normal(0.0, noise, images.shape)
    return images.astype(np.float32)


def angle_deg(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return rd.angular_error_deg(a, b, mask)


# --------------------------------------------------------------------------- synthetic


@pytest.mark.parametrize("method", ["lstsq", "robust"])
def test_recovers_curved_plate(method):
    rng = np.random.default_rng(3)
    n_true, rho = curved_plate()
    lights = ring_lights(12)
    images = render(n_true, rho, lights, rng, noise=0.005)
    mask = np.ones((H, W), dtype=bool)
    field = estimate_normals(images, lights, mask, method=method)

    assert isinstance(field, NormalField)
    assert field.normals.shape == (H, W, 3) and field.normals.dtype == np.float32
    assert field.albedo.shape == (H, W) and field.albedo.dtype == np.float32
    assert field.n_filled == 0 and not field.filled.any()
    assert np.array_equal(field.mask, mask)
    assert np.all(field.normals[..., 2] < 0)  # towards the camera, no flip applied
    np.testing.assert_allclose(np.linalg.norm(field.normals, axis=-1), 1.0, atol=1e-5)
    err = angle_deg(field.normals, n_true, mask)
    # Noise-limited: sigma 0.005 on rho ~0.6 with 12 lights at 40 deg gives a per-pixel
    # angular standard deviation of ~0.6 deg (sigma / rho * sqrt(trace((L^T L)^-1) in the
    # tangent plane)); median of the error ~0.4 deg. Trimming in the robust fit costs a little.
    assert np.median(err) < 0.6, np.median(err)
    assert np.percentile(err, 99) < 2.0
    rel = np.abs(field.albedo / rho - 1.0)
    assert np.median(rel) < 0.01


def test_lstsq_is_exact_without_noise():
    n_true, rho = curved_plate()
    lights = ring_lights(7, polar_deg=30.0)
    images = render(n_true, rho, lights, np.random.default_rng(0), noise=0.0)
    field = estimate_normals(images, lights, np.ones((H, W), bool), method="lstsq")
    # float32 images and solve: ~1e-6 relative
    assert angle_deg(field.normals, n_true, field.mask).max() < 1e-3
    np.testing.assert_allclose(field.albedo, rho, rtol=1e-4)


def test_robust_beats_lstsq_on_shadows_and_highlights():
    rng = np.random.default_rng(11)
    n_true, mask = sphere()
    rho = np.full((H, W), 0.7)
    lights = ring_lights(12, polar_deg=50.0)
    # attached shadows near the rim come from max(0, n.l); add strong highlights and cast shadows
    images = render(n_true, rho, lights, rng, noise=0.005, specular=0.8, shininess=30.0)
    v, u = np.mgrid[0:H, 0:W]
    for k, (a, b, c) in zip([0, 4, 8], [(1, 1, -150), (1, -1, 0), (-1, 1, 40)]):
        images[k][a * u + b * v + c > 0] *= 0.05  # a cast shadow over half-planes of three images
    errors = {}
    for method in ("lstsq", "robust"):
        field = estimate_normals(images, lights, mask, method=method)
        assert field.n_filled == 0
        errors[method] = angle_deg(field.normals, n_true, mask).mean()
    # measured here: lstsq 10.4 deg, robust 1.1 deg; the robust estimator must remove most of it
    assert errors["robust"] < 0.25 * errors["lstsq"], errors
    assert errors["robust"] < 2.0, errors


@pytest.mark.parametrize("method", ["lstsq", "robust"])
def test_saturated_samples_excluded_by_valid(method):
    rng = np.random.default_rng(5)
    n_true, rho = curved_plate()
    lights = ring_lights(12)
    images = render(n_true, rho, lights, rng, noise=0.003)
    saturation = np.float32(0.5)  # about a quarter of the samples clip
    saturated = images >= saturation
    assert 0.2 < saturated.mean() < 0.4
    clipped = np.minimum(images, saturation)
    mask = np.ones((H, W), bool)
    biased = estimate_normals(clipped, lights, mask, method="lstsq").normals
    field = estimate_normals(clipped, lights, mask, valid=~saturated, method=method)
    # the brightest pixels keep fewer than 3 unclipped samples: holes, filled and counted
    holes = (~saturated).sum(axis=0) < 3
    assert np.array_equal(field.filled, holes) and field.n_filled == holes.sum() > 0
    affected = mask & ~holes & saturated.any(axis=0)  # estimated from fewer samples
    err = angle_deg(field.normals, n_true, affected)
    err_biased = angle_deg(biased, n_true, affected)
    # with the clipped samples dropped, 3..11 samples remain: noise-limited again (0.6 deg
    # as in test_recovers_curved_plate), while the clipped samples bias plain least squares
    assert np.median(err) < 0.6 and np.median(err_biased) > 2.0, (
        np.median(err),
        np.median(err_biased),
    )


@pytest.mark.parametrize("method", ["lstsq", "robust"])
def test_holes_filled_and_counted(method):
    rng = np.random.default_rng(7)
    n_true, rho = curved_plate()
    lights = ring_lights(12)
    images = render(n_true, rho, lights, rng, noise=0.002)
    mask = np.ones((H, W), bool)
    mask[:, :4] = False
    valid = np.ones(images.shape, bool)
    valid[2:, 40:46, 60:67] = False  # only 2 usable samples: too few
    valid[:, 90:93, 100:104] = False  # none
    valid[3:, 10, 10] = False  # exactly 3: still estimated with min_samples=3
    images[:, 90:93, 100:104] = np.nan  # unusable samples may hold anything
    field = estimate_normals(images, lights, mask, valid=valid, method=method)

    expected = np.zeros((H, W), bool)
    expected[40:46, 60:67] = True
    expected[90:93, 100:104] = True
    assert field.n_filled == expected.sum() == 54
    assert np.array_equal(field.filled, expected)
    assert np.array_equal(field.mask, mask)
    assert np.all(np.isnan(field.normals[~mask])) and np.all(np.isnan(field.albedo[~mask]))
    np.testing.assert_allclose(np.linalg.norm(field.normals[mask], axis=-1), 1.0, atol=1e-5)
    # the plate is smooth: harmonic interpolation over a 6x7 hole is within ~0.5 deg
    assert angle_deg(field.normals, n_true, expected).max() < 0.5

    stricter = estimate_normals(images, lights, mask, valid=valid, method=method, min_samples=4)
    assert stricter.filled[10, 10] and stricter.n_filled == 55


def test_degenerate_light_subset_is_a_hole():
    n_true, rho = curved_plate()
    # lights 0..2 lie in the x-z plane (coplanar with the origin): rank 2 on their own
    lights = np.concatenate(
        [[[np.sin(t), 0.0, -np.cos(t)] for t in (-0.5, 0.0, 0.5)], ring_lights(6)]
    )
    images = render(n_true, rho, lights, np.random.default_rng(1), noise=0.0)
    valid = np.ones(images.shape, bool)
    valid[3:, 20:23, 30:34] = False
    for method in ("lstsq", "robust"):
        field = estimate_normals(images, lights, np.ones((H, W), bool), valid=valid, method=method)
        assert field.n_filled == 12 and field.filled[20:23, 30:34].all()


def test_unfillable_component_warns_and_leaves_mask():
    n_true, rho = curved_plate()
    lights = ring_lights(12)
    images = render(n_true, rho, lights, np.random.default_rng(2), noise=0.0)
    mask = np.zeros((H, W), bool)
    mask[10:60, 10:60] = True
    mask[80:100, 100:130] = True  # a separate component with no usable sample at all
    valid = np.ones(images.shape, bool)
    valid[:, 80:100, 100:130] = False
    with pytest.warns(RuntimeWarning, match="600 mask pixels in holes with no estimated neighbour"):
        field = estimate_normals(images, lights, mask, valid=valid, method="lstsq")
    assert field.n_filled == 0
    assert not field.mask[80:100, 100:130].any() and field.mask[10:60, 10:60].all()


@pytest.mark.parametrize("method", ["lstsq", "robust"])
def test_dark_images_are_a_capture_error(method):
    lights = ring_lights(6)
    with pytest.raises(CaptureError, match="no pixel of the mask"):
        estimate_normals(
            np.zeros((6, 20, 30), np.float32), lights, np.ones((20, 30), bool), method=method
        )


@pytest.mark.parametrize("method", ["lstsq", "robust"])
def test_nonfinite_used_sample_rejected(method):
    lights = ring_lights(6)
    images = np.full((6, 20, 30), 0.5, np.float32)
    images[2, 5, 7] = np.nan
    with pytest.raises(ValueError, match=r"images: expected finite values.*\(row 5, col 7\)"):
        estimate_normals(images, lights, np.ones((20, 30), bool), method=method)


# --------------------------------------------------------------------------- bad inputs


def _ok_inputs():
    lights = ring_lights(6)
    return np.full((6, 20, 30), 0.5, np.float32), lights, np.ones((20, 30), bool)


@pytest.mark.parametrize(
    "change, match",
    [
        (
            lambda i, d, m: (i, d[:5], m),
            r"light_dirs: expected shape \(6, 3\) to match 6 images, got \(5, 3\)",
        ),
        (
            lambda i, d, m: (i, d * 1.1, m),
            r"light_dirs\[0\]: expected a unit vector, got length 1.1000",
        ),
        (
            lambda i, d, m: (i, d * [1, 1, -1], m),
            r"light_dirs\[0\]: expected a light on the camera side \(l_z < 0",
        ),
        (
            lambda i, d, m: (i, np.where(np.isnan(d), 0, np.nan), m),
            "light_dirs: expected finite numbers",
        ),
        (
            lambda i, d, m: (i, d, m[:, :20]),
            r"mask: expected shape \(20, 30\) to match images, got \(20, 20\)",
        ),
        (
            lambda i, d, m: (i, d, m.astype(np.uint8)),
            "mask: expected a bool array, got dtype uint8",
        ),
        (lambda i, d, m: (i[0], d, m), r"images: expected shape \(N, H, W\), got \(20, 30\)"),
        (lambda i, d, m: (i.astype(np.uint16), d, m), "images: expected a float array"),
    ],
)
def test_bad_inputs(change, match):
    images, lights, mask = change(*_ok_inputs())
    with pytest.raises(ValueError, match=match):
        estimate_normals(images, lights, mask)


def test_bad_options():
    images, lights, mask = _ok_inputs()
    with pytest.raises(
        ValueError, match=r"method: expected one of \('robust', 'lstsq'\), got 'l1'"
    ):
        estimate_normals(images, lights, mask, method="l1")
    with pytest.raises(ValueError, match=r"min_samples: expected an integer in \[3, 6\]"):
        estimate_normals(images, lights, mask, min_samples=2)
    with pytest.raises(ValueError, match=r"min_samples: expected an integer in \[3, 6\]"):
        estimate_normals(images, lights, mask, min_samples=7)
    with pytest.raises(
        ValueError, match=r"valid: expected shape \(6, 20, 30\) to match images, got \(5, 20, 30\)"
    ):
        estimate_normals(images, lights, mask, valid=np.ones((5, 20, 30), bool))
    with pytest.raises(ValueError, match="valid: expected a bool array"):
        estimate_normals(images, lights, mask, valid=np.ones((6, 20, 30)))
    coplanar = np.array([[np.sin(t), 0.0, -np.cos(t)] for t in np.linspace(-0.6, 0.6, 6)])
    with pytest.raises(
        ValueError, match="light_dirs: expected at least 3 directions spanning 3D, got 6 of rank 2"
    ):
        estimate_normals(images, coplanar, mask)


# --------------------------------------------------------------------------- real data

needs_diligent = pytest.mark.skipif(
    not rd.data_available("diligent"), reason=f"real data not found: {rd.DATA_ROOT / 'diligent'}"
)


@needs_diligent
def test_diligent_ball16_lstsq_reproduces_benchmark_baseline():
    data = rd.load_diligent_ball16()
    field = estimate_normals(data.images, data.light_dirs, data.mask, method="lstsq")
    assert field.n_filled == 0
    err = angle_deg(field.normals, data.normals_gt, data.mask)
    assert abs(err.mean() - 4.10) <= 0.1, err.mean()  # published L2 baseline 4.10 deg
    # and pixel for pixel the benchmark's own result file (float32 here vs float64 there)
    assert angle_deg(field.normals, rd.load_diligent_ball16_l2(), data.mask).max() < 0.01


@needs_diligent
@pytest.mark.parametrize("obj, published", [("ball", 4.41), ("cat", 8.76), ("pot1", 9.83)])
def test_diligent_crop8_lstsq_and_robust(obj, published):
    data = rd.load_diligent_crop8(obj)
    lstsq = estimate_normals(data.images, data.light_dirs, data.mask, method="lstsq")
    e_lstsq = angle_deg(lstsq.normals, data.normals_gt, data.mask).mean()
    assert abs(e_lstsq - published) <= 0.1, e_lstsq
    robust = estimate_normals(data.images, data.light_dirs, data.mask, method="robust")
    ok = robust.mask & data.mask
    assert ok.sum() == data.mask.sum()  # every object pixel has a normal (estimated or filled)
    e_robust = angle_deg(robust.normals, data.normals_gt, data.mask).mean()
    # shadows and highlights break the plain model on cat and pot1: robust must gain >= 15 %
    # (measured: ball 2.57, cat 6.42, pot1 7.55 deg)
    assert e_robust <= 0.85 * e_lstsq, (e_robust, e_lstsq)


@pytest.mark.skipif(
    not rd.data_available("uw_spheres"),
    reason=f"real data not found: {rd.DATA_ROOT / 'uw_spheres'}",
)
def test_uw_grey_sphere_lstsq():
    data = rd.load_uw_gray_sphere()
    field = estimate_normals(data.images, data.light_dirs, data.mask, method="lstsq")
    disc = rd.uw_sphere_disc(data, 0.9)
    err = angle_deg(field.normals, data.normals_gt, disc).mean()
    assert abs(err - 4.7) <= 0.1, err  # SOURCE.txt: about 4.7 deg inside 0.9 R


# --------------------------------------------------------------------------- specular stage


def pinhole(f_px: float = 150.0) -> np.ndarray:
    """K of a centred pinhole camera with focal f_px."""
    return np.array([[f_px, 0.0, W / 2 - 0.5], [0.0, f_px, H / 2 - 0.5], [0.0, 0.0, 1.0]])


def perspective_view(K: np.ndarray) -> np.ndarray:
    """Per-pixel unit view directions (H, W, 3) of the camera K: -normalize(K^-1 (u, v, 1))."""
    rays = undistorted_rays(K, (W, H))
    return -rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def render_lobe(normals, albedo, lights, view, rng, *, noise, specular, lobe):
    """rho max(0, n.l) + specular * lobe(n.h) [n.l > 0] with the per-pixel half vector + noise: (N, H, W) float32."""
    n = np.nan_to_num(normals)
    images = []
    for light in lights:
        nl = n @ light
        half = light + view
        half /= np.linalg.norm(half, axis=-1, keepdims=True)
        nh = np.clip(np.einsum("hwc,hwc->hw", n, half), 0.0, 1.0)
        images.append(albedo * np.maximum(nl, 0.0) + specular * lobe(nh) * (nl > 0))
    images = np.array(images) + rng.normal(0.0, noise, (len(lights), H, W))
    return images.astype(np.float32)


def smoothed_bias_deg(normals, truth, mask, size=33):
    """RMS over the mask's interior of the box-averaged normal error (x and y components), deg."""
    import scipy.ndimage as ndi

    err = np.where(mask[..., None], np.nan_to_num(normals - truth), 0.0)
    weight = ndi.uniform_filter(mask.astype(float), size)
    inner = ndi.binary_erosion(mask, iterations=size // 2) & (weight > 0)
    parts = [ndi.uniform_filter(err[..., c], size)[inner] / weight[inner] for c in (0, 1)]
    return float(np.degrees(np.sqrt(np.mean(parts[0] ** 2 + parts[1] ** 2))))


@pytest.mark.parametrize(
    "lobe_name, lobe, exponent",
    [
        ("blinn-phong e=40", lambda c: c**40, 40.0),
        # another shape than the fitted family c^e: a Gaussian in the half-vector angle
        ("gaussian 12 deg", lambda c: np.exp(-((np.arccos(c) / np.radians(12.0)) ** 2)), None),
    ],
)
def test_specular_lobe_with_perspective_view_is_modelled(lobe_name, lobe, exponent):
    rng = np.random.default_rng(17)
    n_true, rho = curved_plate()
    rho = 0.25 * rho  # a dark coating: the lobe is as bright as the diffuse part
    lights = ring_lights(12, polar_deg=45.0)
    K = pinhole()
    images = render_lobe(
        n_true, rho, lights, perspective_view(K), rng, noise=0.002, specular=0.3, lobe=lobe
    )
    mask = np.ones((H, W), bool)
    plain = estimate_normals(images, lights, mask, method="robust")
    field = estimate_normals(images, lights, mask, method="robust", camera_matrix=K)
    assert field.specular is not None and field.specular.modelled, field.specular
    if exponent is not None:
        # a 1-D search over a 28-point grid refined by a parabola: within a few %
        assert abs(field.specular.exponent / exponent - 1) < 0.05, field.specular
    b_plain = smoothed_bias_deg(plain.normals, n_true, mask)
    b_spec = smoothed_bias_deg(field.normals, n_true, mask)
    err = angle_deg(field.normals, n_true, mask)
    # measured: the rejection-only estimate keeps a smooth bias of 4.3 deg (Blinn-Phong) and
    # 3.4 deg (Gaussian): the lobe is in every sample; the modelled lobe leaves 0.53 and 0.43 deg
    # (amplitude fitted ~12 % low on this small, strongly curved view: see the report)
    assert b_spec < 0.2 * b_plain, (b_spec, b_plain)
    # noise: sigma 0.002 on rho ~0.15 gives ~1 deg median for Lambertian least squares
    # (scaled from test_recovers_curved_plate); the lobe adds information, it must not add noise
    assert np.median(err) < 1.0 and np.median(err) < np.median(
        angle_deg(plain.normals, n_true, mask)
    ), np.median(err)


def test_specular_stage_leaves_a_matte_plate_alone():
    rng = np.random.default_rng(3)
    n_true, rho = curved_plate()
    lights = ring_lights(12)
    images = render(n_true, rho, lights, rng, noise=0.005)
    mask = np.ones((H, W), bool)
    plain = estimate_normals(images, lights, mask, method="robust")
    field = estimate_normals(images, lights, mask, method="robust", camera_matrix=pinhole())
    # no lobe in the data: the F-ratio stays near 1 (noise), the stage stops, the estimate is the robust one
    assert (
        field.specular is not None and not field.specular.modelled and field.specular.f_ratio < 4.0
    )
    np.testing.assert_array_equal(field.normals, plain.normals)


@pytest.mark.parametrize("amplitude", [0.0, 0.006, 0.008, 0.01, 0.02])
def test_the_lobes_pretest_stops_only_where_the_whole_search_would(monkeypatch, amplitude):
    # lobes from none to clear (F-ratio about 0.5, 2.7, ~4, 6, 22 on this plate): the pretest on a
    # quarter of the search pixels decides as the search on all of them, to the bit
    from pipeline.surface.normals import specular

    rng = np.random.default_rng(17)
    n_true, rho = curved_plate()
    lights, K = ring_lights(12, polar_deg=45.0), pinhole()
    images = render_lobe(
        n_true,
        0.25 * rho,
        lights,
        perspective_view(K),
        rng,
        noise=0.002,
        specular=amplitude,
        lobe=lambda c: c**40,
    )
    mask = np.ones((H, W), bool)
    field = estimate_normals(images, lights, mask, method="robust", camera_matrix=K)
    monkeypatch.setattr(specular, "LOBE_PRETEST_PIXELS", 10**9)  # no pretest: one search on all
    whole = estimate_normals(images, lights, mask, method="robust", camera_matrix=K)
    assert field.specular is not None and whole.specular is not None
    assert field.specular.modelled == whole.specular.modelled
    np.testing.assert_array_equal(field.normals, whole.normals)


def test_specular_stage_on_a_sphere_with_orthographic_view():
    rng = np.random.default_rng(23)
    n_true, mask = sphere()
    rho = np.full((H, W), 0.3)
    lights = ring_lights(12, polar_deg=40.0)
    view = np.array([0.0, 0.0, -1.0])
    images = render_lobe(
        n_true,
        rho,
        lights,
        np.broadcast_to(view, (H, W, 3)),
        rng,
        noise=0.003,
        specular=0.5,
        lobe=lambda c: c**60,
    )
    plain = estimate_normals(images, lights, mask, method="robust")
    field = estimate_normals(images, lights, mask, method="robust", view_dirs=view)
    inner = mask & (np.hypot(n_true[..., 0], n_true[..., 1]) < 0.8)  # away from the grazing rim
    e_plain = angle_deg(plain.normals, n_true, inner).mean()
    e_spec = angle_deg(field.normals, n_true, inner).mean()
    assert abs(field.specular.exponent / 60.0 - 1) < 0.05, field.specular
    # measured: rejection only 0.99 deg, modelled lobe 0.63 deg (noise sigma 0.003 on rho 0.3)
    assert e_spec < 0.75 * e_plain, (e_spec, e_plain)


def test_bad_view_dirs():
    images, lights, mask = _ok_inputs()
    with pytest.raises(
        ValueError, match=r"view_dirs: expected shape \(3,\) \(a distant camera; camera_matrix"
    ):
        estimate_normals(images, lights, mask, view_dirs=np.zeros((20, 30, 3)))
    with pytest.raises(ValueError, match=r"view_dirs: expected a unit vector, got length 2.0000"):
        estimate_normals(images, lights, mask, view_dirs=np.array([0.0, 0.0, -2.0]))
    with pytest.raises(
        ValueError, match=r"view_dirs: expected a vector from the surface towards the camera"
    ):
        estimate_normals(images, lights, mask, view_dirs=np.array([0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="view_dirs: expected finite numbers"):
        estimate_normals(images, lights, mask, view_dirs=np.full(3, np.nan))
    with pytest.raises(ValueError, match="view_dirs, camera_matrix: expected at most one"):
        estimate_normals(
            images, lights, mask, view_dirs=np.array([0.0, 0.0, -1.0]), camera_matrix=pinhole()
        )
    with pytest.raises(ValueError, match=r"camera_matrix: expected \[\[fx, s, cx\]"):
        estimate_normals(images, lights, mask, camera_matrix=-pinhole())
    with pytest.raises(ValueError, match=r"camera_matrix: expected a finite \(3, 3\) matrix"):
        estimate_normals(images, lights, mask, camera_matrix=np.eye(4))
