"""Point lights in the capture format and the Lights model (issue 10, item 1)."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from pipeline.formats import InputError
from pipeline.io import light_calibration_document, load_capture, load_light_calibration
from pipeline.lights import fit as light_fit
from pipeline.lights.model import CAMERA_HEAD_RADIUS_MM, Lights, light_vectors_block

from .bundles import write_bundle


def _point_lights(doc, positions, **extra):
    doc["photometric"]["lights"] = [
        {"position_mm": list(p), "intensity": 9.0, **extra} for p in positions
    ]


def _ring_positions(n, radius=1600.0, z=200.0):
    phi = 2 * np.pi * np.arange(n) / n
    return [(radius * math.cos(a), radius * math.sin(a), z) for a in phi]


def test_point_lights_load_with_axis_and_profile(tmp_path):
    axis = [0.0, 0.0, 1.0]
    bundle = write_bundle(
        tmp_path, mutate=lambda d: _point_lights(d, _ring_positions(4), axis=axis, mu=1.5)
    )
    cap = load_capture(bundle)
    assert cap.lights.is_point.all() and cap.lights.any_point
    np.testing.assert_allclose(cap.lights.positions_mm, _ring_positions(4))
    np.testing.assert_allclose(cap.lights.axes, np.tile(axis, (4, 1)))
    np.testing.assert_array_equal(cap.lights.mu, 1.5)
    np.testing.assert_array_equal(cap.light_intensity, 9.0)
    assert np.isnan(cap.light_dirs).all()  # no distant direction for a point light


@pytest.mark.parametrize(
    ("light", "field", "problem"),
    [
        ({"intensity": 1.0}, "lights[1]", "expected exactly one of them"),
        ({"direction": [0, 0, -1.0], "position_mm": [0, 0, 100.0]}, "lights[1]", "got both"),
        (
            {"position_mm": [1000, 0, 0], "axis": [0, 0, 2.0]},
            "lights[1].axis",
            "expected a unit vector",
        ),
        ({"position_mm": [1000, 0, 0], "mu": -1.0}, "lights[1].mu", "greater than or equal to 0"),
        ({"direction": [0.5, 0, -0.866], "mu": 1.0}, "lights[1]", "only a point light"),
        ({"position_mm": [1000, 0]}, "lights[1].position_mm", "at least 3"),
    ],
)
def test_bad_lights_name_the_light(tmp_path, light, field, problem):
    def mutate(doc):
        doc["photometric"]["lights"][1] = light

    bundle = write_bundle(tmp_path, mutate=mutate)
    with pytest.raises(
        InputError, match=re.escape(f"capture.json: photometric.{field}") + f".*{problem}"
    ):
        load_capture(bundle)


def test_a_light_inside_the_camera_head_is_a_named_error(tmp_path):
    positions = _ring_positions(4)
    positions[2] = (30.0, 0.0, 10.0)
    bundle = write_bundle(tmp_path, mutate=lambda d: _point_lights(d, positions))
    with pytest.raises(
        InputError, match=r"photometric\.lights\[2\]\.position_mm: .*inside the camera head"
    ):
        load_capture(bundle)
    assert CAMERA_HEAD_RADIUS_MM > 30


def test_a_light_near_the_right_camera_is_inside_the_head_too(tmp_path):
    positions = _ring_positions(4)
    positions[0] = (100.0, 0.0, 0.0)  # the test rig's right camera sits at x = +100 mm
    bundle = write_bundle(tmp_path, mutate=lambda d: _point_lights(d, positions))
    with pytest.raises(InputError, match=r"lights\[0\]\.position_mm: .*right camera"):
        load_capture(bundle)


def test_a_light_behind_the_plate_is_a_named_error(tmp_path):
    positions = _ring_positions(4)
    positions[3] = (500.0, 0.0, 3200.0)
    bundle = write_bundle(
        tmp_path, working_distance_mm=3000.0, mutate=lambda d: _point_lights(d, positions)
    )
    with pytest.raises(InputError, match=r"lights\[3\]\.position_mm: .*behind the plate"):
        load_capture(bundle)


def test_irradiance_follows_the_documented_model():
    P = np.array([[0.0, 0.0, 0.0]])
    axis = np.array([[0.0, 0.0, 1.0]])
    lights = Lights.points(P, [2.0], axes=axis, mu=[2.0])
    X = np.array([[0.0, 0.0, 1000.0], [0.0, 0.0, 2000.0], [1000.0, 0.0, 1000.0]])
    n = np.array([[0.0, 0.0, -1.0]] * 3)
    E = lights.irradiance(X, n)[0]
    # on the axis facing the light at 1000 mm: the intensity; at 2000 mm a quarter
    assert E[0] == pytest.approx(2.0)
    assert E[1] == pytest.approx(0.5)
    # 45 deg off the axis at sqrt(2) m: (1/2) * cos(45)^2 (profile) * cos(45) (shading)
    c = math.cos(math.pi / 4)
    assert E[2] == pytest.approx(2.0 * 0.5 * c**2 * c)
    # a surface facing away gets nothing
    assert lights.irradiance(X[:1], -n[:1])[0, 0] == 0.0


def test_the_normals_kernels_light_model_is_the_documented_one():
    # lights.model.light_vectors_block, which the near-field normals' kernel calls, evaluates the model
    # a light at a time (the beam's power in single precision): it must give Lights.directions_at and
    # attenuation_at, for point lights with and without a beam profile and a distant light among them
    rng = np.random.default_rng(3)
    n_points = 5
    positions = np.c_[
        rng.uniform(-1500.0, 1500.0, (n_points, 2)), rng.uniform(-300.0, 300.0, n_points)
    ]
    axes = np.array([0.0, 0.0, 3000.0]) - positions
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    nan3 = np.full((1, 3), np.nan)
    lights = Lights(
        directions=np.r_[np.full((n_points, 3), np.nan), [[0.6, 0.0, -0.8]]],
        positions_mm=np.r_[positions, nan3],
        axes=np.r_[axes, nan3],
        mu=np.array([0.0, 1.0, 1.5, 2.3, 0.7, 0.0]),
        intensity=np.ones(n_points + 1),
    )
    n, h, w = lights.n, 4, 30
    K = np.array([[900.0, 0.0, 15.0], [0.0, 900.0, 2.0], [0.0, 0.0, 1.0]])
    depth = 3000.0 + rng.uniform(-200.0, 200.0, (h, w))
    depth[1, 7] = np.nan  # a pixel without a surface point
    geometry, ax, kind = lights.kernel_arrays()
    for i in range(h):
        samples = np.ones((n, w), np.float32)
        usable = np.ones((n, w), np.float32)
        m = np.full(w, n, np.int64)
        L = np.empty((n, 3, w), np.float32)
        light_vectors_block(
            depth, np.linalg.inv(K), geometry, ax, kind, lights.mu, 0.0, i, 0, samples, usable, m, L
        )
        X = depth[i, :, None] * (
            np.c_[np.arange(w), np.full(w, i), np.ones(w)] @ np.linalg.inv(K).T
        )
        seen = np.isfinite(X[:, 2])
        np.testing.assert_allclose(
            L[:, :, seen], lights.directions_at(X[seen]).transpose(0, 2, 1), rtol=0, atol=1e-6
        )
        np.testing.assert_allclose(
            samples[:, seen], 1.0 / lights.attenuation_at(X[seen]), rtol=2e-6
        )
        assert not L[:, :, ~seen].any() and (samples[:, ~seen] == 1.0).all()
        assert (m == n).all() and usable.all()


def test_nominal_directions_keep_the_irradiance_at_the_centre():
    lights = Lights.points(
        [[1500.0, 0.0, 200.0], [-1500.0, 300.0, 100.0]],
        [9.0, 11.0],
        axes=[[-0.5, 0, 0.866], [0.5, 0, 0.866]],
        mu=[1.0, 1.0],
    )
    centre = np.array([0.0, 0.0, 3000.0])
    nominal = lights.nominal_directions(centre)
    assert not nominal.any_point
    dirs = (lights.positions_mm - centre) / np.linalg.norm(
        lights.positions_mm - centre, axis=1, keepdims=True
    )
    np.testing.assert_allclose(nominal.directions, dirs)
    n = np.array([0.0, 0.0, -1.0])
    np.testing.assert_allclose(nominal.irradiance(centre, n), lights.irradiance(centre, n))


def test_light_calibration_round_trip_and_errors(tmp_path):
    lights = Lights.points(
        _ring_positions(4), [9.0, 9.5, 10.0, 10.5], axes=[[0, 0, 1.0]] * 4, mu=[1.2] * 4
    )
    doc = light_calibration_document(lights, 0.004)
    path = tmp_path / "lights.json"
    path.write_text(json.dumps(doc))
    back, rms = load_light_calibration(path)
    np.testing.assert_allclose(back.positions_mm, lights.positions_mm)
    np.testing.assert_allclose(back.intensity, lights.intensity)
    assert rms == 0.004
    doc["lights"][2]["axis"] = [0.0, 0.0, 0.5]
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"lights\.json: lights\[2\]\.axis: .*unit vector"):
        load_light_calibration(path)
    with pytest.raises(InputError, match=r"format"):
        load_light_calibration({"format": "light-calibration/2", "lights": []})


def test_a_light_held_on_its_ray_finds_its_distance_and_keeps_its_direction():
    """The joint fit with ``rays``: LEDs whose directions from the plate's centre are known keep them
    exactly and the images find only how far along them each light is (its axis, beam and intensity
    too)."""
    rng = np.random.default_rng(3)
    centre = np.array([0.0, 0.0, 3000.0])
    positions = np.asarray(_ring_positions(8))
    towards_centre = centre - positions
    truth = Lights.points(
        positions,
        rng.uniform(9.0, 11.0, 8),
        axes=towards_centre / np.linalg.norm(towards_centre, axis=1, keepdims=True),
        mu=np.full(8, 1.5),
    )
    xy = rng.uniform(-1400.0, 1400.0, (1500, 2))
    sag = 5000.0 - np.sqrt(
        5000.0**2 - xy[:, 0] ** 2
    )  # a cylinder R 5000 mm bent towards the cameras
    points = np.column_stack([xy, centre[2] - sag])
    normals = np.column_stack([xy[:, 0] / 5000.0, np.zeros(len(xy)), -(5000.0 - sag) / 5000.0])
    albedo = rng.uniform(0.3, 0.9, len(xy))
    data = light_fit.Samples(
        intensity=albedo[:, None] * truth.irradiance(points, normals).T,
        points=points,
        normals=normals,
    )
    rays = (positions - centre) / np.linalg.norm(positions - centre, axis=1, keepdims=True)
    start = Lights.points(
        centre + 0.7 * (positions - centre), np.full(8, 10.0), axes=-rays, mu=np.ones(8)
    )
    fit = light_fit.joint_fit(start, data, rays=rays)
    off = fit.lights.positions_mm - centre
    across = np.linalg.norm(np.cross(off, rays), axis=1)
    assert np.all(across < 1e-6 * np.linalg.norm(off, axis=1))  # on the ray, exactly
    assert np.allclose(fit.lights.positions_mm, positions, atol=1.0), fit.lights.positions_mm
    assert np.allclose(fit.lights.mu, 1.5, atol=0.01)


def _glossy_samples(rng, truth, centre, s, e, n=2000):
    """Samples of a cylinder R 5000 mm under ``truth`` with a Blinn-Phong lobe ``s max(0, n.h)^e``
    per unit irradiance (the simulated cell's), the camera at the origin."""
    xy = rng.uniform(-1400.0, 1400.0, (n, 2))
    sag = 5000.0 - np.sqrt(5000.0**2 - xy[:, 0] ** 2)
    points = np.column_stack([xy, centre[2] - sag])
    normals = np.column_stack([xy[:, 0] / 5000.0, np.zeros(n), -(5000.0 - sag) / 5000.0])
    albedo = rng.uniform(0.1, 0.6, n)
    lobe = light_fit.lobe_of(truth, points, normals, e)
    intensity = albedo[:, None] * truth.irradiance(points, normals).T + s * lobe
    return light_fit.Samples(intensity=intensity, points=points, normals=normals)


def _led_ring(rng, centre, n=12):
    ring = centre + np.asarray(_ring_positions(n, radius=1600.0, z=0.0)) - [0, 0, 2800.0]
    towards = centre - ring
    return Lights.points(
        ring,
        rng.uniform(9.0, 11.0, n),
        axes=towards / np.linalg.norm(towards, axis=1, keepdims=True),
        mu=np.full(n, 1.5),
    )


@pytest.mark.parametrize("kind", ["point", "distant"])
def test_the_normal_equations_with_a_lobe_match_finite_differences(kind):
    """The analytic Jacobian of the variable-projection residuals with the lobe's amplitude and
    exponent (and the lights' dependence of the lobe) against central differences, for point lights
    and for distant ones."""
    rng = np.random.default_rng(0)
    centre = np.array([0.0, 0.0, 3000.0])
    truth = _led_ring(rng, centre, n=5)
    if kind == "distant":
        truth = Lights.distant(truth.directions_at(centre), truth.intensity)
    data = _glossy_samples(rng, truth, centre, 0.4, 30.0, n=60)
    model = light_fit._PointModel(truth) if kind == "point" else light_fit._DistantModel(truth)
    problem = light_fit._Problem(model, data, lobe=True)
    x = np.append(problem.model.vector(truth), [0.3, np.log(20.0)])
    if kind == "point":
        x[3 : problem.n_light : 7] += 0.01  # off the given axes and the truth
        x[0 : problem.n_light : 7] += 40.0
    else:
        x[0 : problem.n_light : 3] += 0.01  # off the given directions
        x[1 : problem.n_light : 3] -= 0.02
    A, g = problem.normal_equations(x)

    def residuals(v):
        return problem.cost(v)[1].ravel()

    J = np.empty((data.intensity.size, x.size))
    for i in range(x.size):
        h = 1e-6 * max(1.0, abs(x[i]))
        step = np.zeros_like(x)
        step[i] = h
        J[:, i] = (residuals(x + step) - residuals(x - step)) / (2 * h)
    w2 = problem.gauge_weight**2
    A_num = J.T @ J + w2 * np.outer(problem.gauge_row, problem.gauge_row)
    g_num = J.T @ residuals(x) + w2 * (problem.gauge_row @ x) * problem.gauge_row
    assert np.abs(A - A_num).max() < 1e-7 * np.abs(A_num).max()
    assert np.abs(g - g_num).max() < 1e-7 * np.abs(g_num).max()


def test_distant_lights_over_a_glossy_plate_are_found_with_the_lobe():
    """Distant lights written a degree off over a glossy cylinder: fitted as if Lambertian the glare
    biases their directions; fitted jointly with the lobe (from a rough one), the directions, the
    intensities' ratios and the lobe come out."""
    rng = np.random.default_rng(5)
    centre = np.array([0.0, 0.0, 3000.0])
    ring = _led_ring(rng, centre, n=12)
    truth = Lights.distant(ring.directions_at(centre), ring.intensity)
    data = _glossy_samples(rng, truth, centre, 0.5, 30.0, n=1500)
    turn = np.radians(1.0)
    off = np.empty_like(truth.directions)
    for k, d in enumerate(truth.directions):
        across = np.cross(d, rng.normal(size=3))
        off[k] = np.cos(turn) * d + np.sin(turn) * across / np.linalg.norm(across)
    start = Lights.distant(off, np.full(12, 10.0))
    fit = light_fit.joint_fit_distant(start, data, lobe=(15.0, 0.2))
    assert fit.success
    cos = np.einsum("nc,nc->n", fit.lights.directions, truth.directions)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.02
    ratio = fit.lights.intensity / truth.intensity
    assert np.allclose(ratio / ratio.mean(), 1.0, atol=1e-3)
    assert fit.lobe_exponent == pytest.approx(30.0, rel=0.01)
    assert fit.lobe_amplitude * ratio.mean() == pytest.approx(0.5, rel=0.01)
    assert np.all(np.isnan(fit.position_std_mm)) and np.all(np.isfinite(fit.intensity_std))


def test_leds_over_a_glossy_plate_are_found_with_the_lobe_and_the_rays_origin():
    """Fitted as if Lambertian, the glare pulls LEDs on their rays far off their distance; fitted with
    the lobe (amplitude and exponent free) and the rays' common origin free (given 60 mm off, as the
    view's middle misses the plate's centre), the lights, the lobe and the origin come out."""
    rng = np.random.default_rng(4)
    centre = np.array([0.0, 0.0, 3000.0])
    truth = _led_ring(rng, centre)
    data = _glossy_samples(rng, truth, centre, 0.4, 40.0)
    rays = truth.directions_at(centre)
    guess = centre + np.array([50.0, -30.0, 10.0])  # where the rays are given from
    start = Lights.points(
        guess + 2600.0 * rays, np.full(truth.n, 10.0), axes=-rays, mu=np.ones(truth.n)
    )
    lambertian = light_fit.joint_fit(start, data, rays=rays)
    glossy = light_fit.joint_fit(start, data, rays=rays, free_origin=True, lobe=(20.0, 0.1))
    err = np.linalg.norm(glossy.lights.positions_mm - truth.positions_mm, axis=1)
    assert glossy.success and err.max() < 2.0, err
    assert glossy.lobe_exponent == pytest.approx(40.0, rel=1e-3)
    # the amplitude per unit of the fitted intensities, whose common factor the fit pins (ratios)
    gauge = np.exp(np.mean(np.log(truth.intensity / glossy.lights.intensity)))
    assert glossy.lobe_amplitude / gauge == pytest.approx(0.4, rel=1e-3)
    assert np.allclose(glossy.lights.mu, 1.5, atol=0.01)
    # the directions stay the given ones: every light moved along its ray plus one common shift
    shift = glossy.lights.positions_mm - start.positions_mm
    across = np.eye(3) - np.einsum("ni,nj->nij", rays, rays)  # off each ray
    common = np.linalg.solve(across.sum(axis=0), np.einsum("nij,nj->i", across, shift))
    off_ray = np.einsum("nij,nj->ni", across, shift - common)
    assert np.linalg.norm(off_ray, axis=1).max() < 1e-6 * 3000.0
    assert np.linalg.norm(guess + common - centre) < 2.0  # the origin found: the plate's centre
    lambertian_err = np.linalg.norm(lambertian.lights.positions_mm - truth.positions_mm, axis=1)
    assert lambertian_err.min() > 50.0  # what the lobe model fixes


def test_a_free_origin_is_off_without_rays():
    rng = np.random.default_rng(5)
    centre = np.array([0.0, 0.0, 3000.0])
    truth = _led_ring(rng, centre, n=6)
    data = _glossy_samples(rng, truth, centre, 0.0, 40.0, n=300)
    plain = light_fit.joint_fit(truth, data, fixed_mu=True)
    freed = light_fit.joint_fit(truth, data, fixed_mu=True, free_origin=True)
    np.testing.assert_allclose(freed.lights.positions_mm, plain.lights.positions_mm)
