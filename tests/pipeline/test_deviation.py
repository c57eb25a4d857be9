"""Registration, deviation sign, verdict and target surface against ray-cast analytic plates."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from pipeline.io import Target
from pipeline.judge.deviation import deviation_map
from pipeline.judge.registration import Registration, fitted_target_radius, register_to_target
from pipeline.judge.target_geometry import target_surface
from pipeline.judge.verdict import judge
from pipeline.stages import edge_band
from tests.pipeline.surfaces import cylinder, dented, plate_grid, saddle, sphere

PLATE_CENTRE = np.array([30.0, -20.0, 3000.0])  # where plate_grid puts the plate frame's origin


def target(shape, radius=None, tol=2.0, **kw):
    return Target(shape=shape, radius_mm=radius, size_mm=(3000.0, 3000.0), tolerance_mm=tol, **kw)


def pixel_area(mask):
    return 3000.0 * 3000.0 / mask.sum()  # the 3 m x 3 m plate over its pixels (mean), mm^2


def true_registration(shape, R_cp, sign):
    """T_cam_target of the generating plate: the plate frame for convex plates (centre at +z_p); for concave
    ones the target's +z is -z_p (its centre of curvature is towards the camera), y flipped to stay proper."""
    R = R_cp if sign > 0 or shape == "plane" else R_cp @ np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, PLATE_CENTRE
    return Registration(T_cam_target=T, shape=shape, rms_mm=0.0, convex_towards_camera=None)


def shape_height(shape, R, sign, offset_mm=0.0):
    """Height of the plate whose surface lies ``offset_mm`` towards the camera from the nominal one
    (concentric for cylinder and sphere, so the offset is exact along every normal)."""
    if shape == "plane":
        return lambda x, y: 0 * x - offset_mm
    Ro = R + sign * offset_mm
    if shape == "cylinder":
        return lambda x, y: sign * (R - np.sqrt(Ro * Ro - x * x))
    return lambda x, y: sign * (R - np.sqrt(Ro * Ro - x * x - y * y))


# --------------------------------------------------------------------------- analytic targets


@pytest.mark.parametrize("shape", ["plane", "cylinder", "sphere"])
@pytest.mark.parametrize("sign", [1, -1])
def test_registration_gives_noise_level_deviation(shape, sign):
    R = 5000.0
    rng = np.random.default_rng(31 + 2 * sign + len(shape))
    pts, m, _, R_cp = plate_grid(shape_height(shape, R, sign), noise_mm=0.2, rng=rng)
    tgt = target(shape, None if shape == "plane" else R)
    reg = register_to_target(pts, m, tgt)
    assert reg.T_cam_target.shape == (4, 4)
    if shape != "plane":
        assert reg.convex_towards_camera == (sign > 0)
        # the target's +z points to its centre of curvature: away from the camera for a convex plate
        assert np.sign(reg.T_cam_target[:3, 2] @ R_cp[:, 2]) == sign
    if shape == "cylinder":
        assert abs(reg.T_cam_target[:3, 1] @ R_cp[:, 1]) > math.cos(
            math.radians(0.1)
        )  # y = the axis
    dev = deviation_map(pts, m, tgt, reg)
    assert dev.dtype == np.float32 and dev.shape == m.shape
    assert np.isnan(dev[~m]).all() and np.isfinite(dev[m]).all()
    # The deviation is the 0.2 mm noise: mean ~0 (0.02 mm = 10 sigma of the mean), RMS 0.2 +- 25 %.
    assert abs(np.mean(dev[m])) < 0.02
    assert 0.15 < np.sqrt(np.mean(dev[m] ** 2)) < 0.25
    assert reg.rms_mm == pytest.approx(np.sqrt(np.mean(dev[m] ** 2)), rel=0.1)
    j = judge(dev, m, 2.0, pixel_area_mm2=pixel_area(m))
    assert j.verdict == "pass" and j.defects == () and j.within_tolerance_pct == 100.0


@pytest.mark.parametrize("shape", ["plane", "cylinder", "sphere"])
@pytest.mark.parametrize("sign", [1, -1])
def test_deviation_sign_with_known_pose(shape, sign):
    R = 3000.0
    pts, m, _, R_cp = plate_grid(shape_height(shape, R, sign, offset_mm=1.0))
    tgt = target(shape, None if shape == "plane" else R)
    dev = deviation_map(pts, m, tgt, true_registration(shape, R_cp, sign))
    # 1 mm towards the cameras, exactly along every normal: +1 mm (noise-free; float32 output).
    assert np.allclose(dev[m], 1.0, atol=1e-4)
    behind = deviation_map(
        *plate_grid(shape_height(shape, R, sign, offset_mm=-1.0))[:2],
        tgt,
        true_registration(shape, R_cp, sign),
    )
    assert np.allclose(behind[np.isfinite(behind)], -1.0, atol=1e-4)


def test_uniform_offset_is_absorbed_by_best_fit():
    # A rigid best fit cannot tell a plate shifted by 1 mm from one in place: the deviation after
    # registration is ~0 (the 1 mm shows only with a fixed pose, test above).
    R = 5000.0
    pts, m, _, _ = plate_grid(lambda x, y: cylinder(R)(x, y) - 1.0)
    tgt = target("cylinder", R)
    dev = deviation_map(pts, m, tgt, register_to_target(pts, m, tgt))
    assert np.max(np.abs(dev[m])) < 1e-3


def test_dent_fails_and_the_same_plate_without_it_passes():
    R = 5000.0
    tgt = target("cylinder", R, tol=2.0)
    plain, m0, _, _ = plate_grid(cylinder(R), noise_mm=0.2, rng=np.random.default_rng(8))
    dent, m1, xy, _ = plate_grid(
        dented(cylinder(R), depth_mm=6.0, radius_mm=100.0, at=(300.0, -200.0)),
        noise_mm=0.2,
        rng=np.random.default_rng(8),
    )
    j0 = judge(
        deviation_map(plain, m0, tgt, register_to_target(plain, m0, tgt)),
        m0,
        2.0,
        pixel_area_mm2=pixel_area(m0),
    )
    assert j0.verdict == "pass"
    dev = deviation_map(dent, m1, tgt, register_to_target(dent, m1, tgt))
    j1 = judge(dev, m1, 2.0, pixel_area_mm2=pixel_area(m1))
    assert j1.verdict == "fail" and len(j1.defects) == 1
    d = j1.defects[0]
    # The dent is pushed away from the cameras: negative, peak -6 mm +- noise and pixel sampling.
    assert -6.8 < d.peak_deviation_mm < -5.0
    # Out of tolerance where 6 (1 - q)^3 > 2: r < 64 mm, ~13 000 mm^2; pixels of ~19 mm: +- 50 %.
    assert 6_000 < d.area_mm2 < 20_000
    dist = np.where(m1, np.hypot(xy[..., 0] - 300.0, xy[..., 1] + 200.0), np.inf)
    row, col = np.unravel_index(np.argmin(dist), m1.shape)
    assert abs(d.centroid_px[0] - col) < 2 and abs(d.centroid_px[1] - row) < 2


def test_judge_rules_single_pixel_block_and_scatter():
    rng = np.random.default_rng(3)
    m = np.ones((100, 120), dtype=bool)
    m[:, :5] = False
    dev = rng.normal(0.0, 0.2, m.shape)
    area = 4.0  # mm^2 per pixel
    spike = dev.copy()
    spike[50, 60] = 10.0  # one noisy pixel: 4 mm^2 < 100 mm^2
    j = judge(spike, m, 2.0, pixel_area_mm2=area)
    assert j.verdict == "pass" and j.max_abs_mm == 10.0 and j.outside_area_mm2 == 4.0
    block = dev.copy()
    block[10:16, 20:26] = -3.0  # 36 px = 144 mm^2 >= 100 mm^2
    j = judge(block, m, 2.0, pixel_area_mm2=area)
    assert j.verdict == "fail" and len(j.defects) == 1
    assert j.defects[0].area_mm2 == 144.0 and j.defects[0].peak_deviation_mm == -3.0
    assert j.defects[0].centroid_px == (22.5, 12.5)
    # the reason in cm², singular for one region (issue 26)
    assert j.reasons[0] == "1 region out of the 2 mm tolerance over 1 cm² (largest 1.4 cm²)"
    scatter = dev.copy()
    pick = np.zeros(m.shape, dtype=bool)
    pick[::2, ::2] = (
        rng.random((50, 60)) < 0.3
    )  # isolated pixels: no region reaches 100 mm^2, ~7 % out
    scatter[pick] = 2.5
    j = judge(scatter, m, 2.0, pixel_area_mm2=area)
    assert j.defects == () and j.verdict == "fail" and "% of the area" in j.reasons[0]


def test_judge_statistics():
    m = np.ones((20, 20), dtype=bool)
    dev = np.full((20, 20), 0.5)
    dev[:2] = -1.5  # 40 of 400 pixels
    dev[5, 5] = np.nan  # not judged
    m[19, :] = False
    area = np.full((20, 20), 2.0)
    area[:2] = 6.0
    j = judge(dev, m, 1.0, pixel_area_mm2=area)
    a = np.abs(dev[m & np.isfinite(dev)])
    assert j.n_pixels == a.size == 379
    assert j.rms_mm == pytest.approx(np.sqrt(np.mean(a * a)))
    assert j.max_abs_mm == 1.5 and j.p95_mm == pytest.approx(np.percentile(a, 95))
    # area-weighted: 40 px x 6 mm^2 out of tolerance, 339 px x 2 mm^2 in
    assert j.within_tolerance_pct == pytest.approx(100 * 339 * 2 / (339 * 2 + 40 * 6))
    assert j.verdict == "fail"


# --------------------------------------------------------------------------- mesh targets


def _patch_mesh(height, half=1650.0, n=67):
    g = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(g, g)
    V = np.stack([gx.ravel(), gy.ravel(), height(gx, gy).ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])


@pytest.mark.parametrize(
    "name,height", [("cylinder", cylinder(4000.0, -1)), ("saddle", saddle(4000.0, 6000.0))]
)
def test_mesh_target_from_stl_registers(tmp_path, name, height):
    V, F = _patch_mesh(height)
    # The mesh in an arbitrary frame of its own, written as STL by trimesh and read back.
    R_mesh = Rotation.from_euler("zyx", [70, 40, -25], degrees=True).as_matrix()
    moved = V @ R_mesh.T + np.array([500.0, -2000.0, 800.0])
    path = tmp_path / "target.stl"
    trimesh.Trimesh(moved, F).export(path)
    loaded = trimesh.load(path)
    tgt = target(
        "mesh", mesh_vertices_mm=np.asarray(loaded.vertices), mesh_faces=np.asarray(loaded.faces)
    )
    pts, m, _, _ = plate_grid(height)
    reg = register_to_target(pts, m, tgt)
    dev = deviation_map(pts, m, tgt, reg)
    assert np.isfinite(dev[m]).all()
    # Registered to ~0.1 mm RMS: the mesh's 50 mm facets differ from the true surface by up to
    # 50^2 / (8 * 4000) = 0.08 mm, the rest is registration.
    assert np.sqrt(np.mean(dev[m] ** 2)) < 0.1
    assert reg.rms_mm < 0.1
    # Sign: the plate moved 1 mm towards the camera along z_p reads about +1 mm.
    pts1, m1, _, _ = plate_grid(lambda x, y: height(x, y) - 1.0)
    dev1 = deviation_map(pts1, m1, tgt, reg)
    assert 0.7 < np.nanmedian(dev1[m1]) < 1.1


# --------------------------------------------------------------------------- radius, target surface


def test_fitted_target_radius():
    rng = np.random.default_rng(12)
    pts, m, _, _ = plate_grid(cylinder(6000.0, -1), noise_mm=0.2, rng=rng)
    assert fitted_target_radius(pts, m, target("cylinder", 5000.0)) == pytest.approx(
        6000.0, rel=5e-4
    )
    pts, m, _, _ = plate_grid(sphere(7000.0), noise_mm=0.2, rng=rng)
    assert fitted_target_radius(pts, m, target("sphere", 7500.0)) == pytest.approx(7000.0, rel=5e-4)
    assert fitted_target_radius(pts, m, target("plane")) is None


@pytest.mark.parametrize("shape", ["plane", "cylinder", "sphere"])
def test_target_surface(shape):
    R = 2500.0
    V, F = target_surface(target(shape, None if shape == "plane" else R), spacing_mm=100.0)
    assert V.shape == (31 * 31, 3) and F.shape == (2 * 30 * 30, 3) and F.dtype == np.int64
    assert np.allclose(V[:, :2].min(axis=0), -1500) and np.allclose(V[:, :2].max(axis=0), 1500)
    x, y, z = V.T
    if shape == "plane":
        assert np.all(z == 0)
    elif shape == "cylinder":
        assert np.allclose(x * x + (z - R) ** 2, R * R)
    else:
        assert np.allclose(x * x + y * y + (z - R) ** 2, R * R)
    normals = trimesh.Trimesh(V, F, process=False).face_normals
    assert np.all(normals[:, 2] > 0)  # towards +z, the centre of curvature
    V2, F2 = target_surface(target("mesh", mesh_vertices_mm=V, mesh_faces=F))
    assert np.array_equal(V2, V) and np.array_equal(F2, F)


# --------------------------------------------------------------------------- bad input


def test_bad_inputs():
    pts, m, _, R_cp = plate_grid(cylinder(5000.0), shape=(40, 50))
    good = target("cylinder", 5000.0)
    with pytest.raises(TypeError, match=r"target: expected a pipeline.io.Target, got dict"):
        register_to_target(pts, m, {"shape": "cylinder"})
    with pytest.raises(ValueError, match=r"target.shape: expected one of"):
        register_to_target(pts, m, target("cone", 5.0))
    with pytest.raises(
        ValueError, match=r"target.radius_mm: expected a positive radius for a sphere, got None"
    ):
        register_to_target(pts, m, target("sphere"))
    with pytest.raises(ValueError, match=r"target.mesh_vertices_mm/mesh_faces: expected arrays"):
        register_to_target(pts, m, target("mesh"))
    with pytest.raises(ValueError, match=r"target.mesh_faces: expected \(F, 3\) indices below 3"):
        register_to_target(
            pts, m, target("mesh", mesh_vertices_mm=np.eye(3), mesh_faces=np.array([[0, 1, 3]]))
        )
    with pytest.raises(ValueError, match=r"mask: expected shape \(40, 50\)"):
        register_to_target(pts, m[:, :-1], good)
    reg = true_registration("cylinder", R_cp, 1)
    with pytest.raises(TypeError, match="registration: expected a Registration"):
        deviation_map(pts, m, good, np.eye(4))
    skew = Registration(
        T_cam_target=np.diag([2.0, 1, 1, 1]), shape="cylinder", rms_mm=0, convex_towards_camera=None
    )
    with pytest.raises(ValueError, match=r"registration.T_cam_target: expected a rigid transform"):
        deviation_map(pts, m, good, skew)
    dev = deviation_map(pts, m, good, reg)
    with pytest.raises(ValueError, match="tolerance_mm: expected a positive number of mm, got 0"):
        judge(dev, m, 0.0, pixel_area_mm2=1.0)
    with pytest.raises(ValueError, match=r"pixel_area_mm2: expected a number or shape \(40, 50\)"):
        judge(dev, m, 2.0, pixel_area_mm2=np.ones((3, 3)))
    with pytest.raises(ValueError, match="pixel_area_mm2: expected a positive area"):
        judge(dev, m, 2.0, pixel_area_mm2=-1.0)
    with pytest.raises(
        ValueError, match="deviation_mm: expected finite deviations inside the mask, got none"
    ):
        judge(np.full(m.shape, np.nan), m, 2.0, pixel_area_mm2=1.0)
    with pytest.raises(ValueError, match=r"mask: expected a bool array of shape \(40, 50\)"):
        judge(dev, m.astype(int), 2.0, pixel_area_mm2=1.0)
    with pytest.raises(ValueError, match="spacing_mm: expected a positive spacing"):
        target_surface(good, spacing_mm=0.0)
    with pytest.raises(ValueError, match="cannot span size_mm"):
        target_surface(target("cylinder", 1000.0))


# --------------------------------------------------------------------------- the edge band (issue 24)


def _plate_with_a_hole():
    """A 200 x 240 px plate (mask) with a round opening, noise-level deviation, 10 mm^2 per pixel."""
    rng = np.random.default_rng(17)
    h, w = 200, 240
    m = np.zeros((h, w), dtype=bool)
    m[20:180, 20:220] = True
    yy, xx = np.mgrid[0:h, 0:w]
    m &= np.hypot(xx - 160, yy - 100) > 25
    dev = np.where(m, rng.normal(0.0, 0.2, (h, w)), np.nan)
    return m, dev


def test_the_edge_band_is_left_out_by_geometry_whatever_its_deviation():
    """Mixed pixels along the outline and the opening are not judged; whether they are within
    tolerance or far out of it makes no difference to what is left out."""
    m, dev = _plate_with_a_hole()
    band = edge_band(m)
    bad = dev.copy()
    bad[20:23, 60:120] = -9.0  # a 3 px strip along the outline: the floor pulled in
    judged = m & ~band
    calm = judge(dev, judged, 2.0, pixel_area_mm2=10.0)
    wild = judge(bad, judged, 2.0, pixel_area_mm2=10.0)
    assert wild.verdict == calm.verdict == "pass" and wild.n_pixels == calm.n_pixels
    assert judge(bad, m, 2.0, pixel_area_mm2=10.0).verdict == "fail"  # judged with the band: fails


def test_a_bent_edge_still_fails():
    """A real edge defect reaches into the plate (here 30 px of a flange bent by up to 12 mm): judged
    beyond the band with its own depth."""
    m, dev = _plate_with_a_hole()
    bent = dev.copy()
    ramp = np.linspace(12.0, 2.5, 30)[None, :]
    bent[60:140, 190:220] = ramp[:, ::-1]  # deepest at the outline (column 219)
    j = judge(bent, m & ~edge_band(m), 2.0, pixel_area_mm2=10.0)
    assert j.verdict == "fail"
    assert j.defects[0].peak_deviation_mm == pytest.approx(12.0 - 3 * 9.5 / 29, abs=0.05)


def test_mesh_target_with_an_opening_registers(tmp_path):
    """A saddle is nearly itself turned over and by 90 deg (R1 ~ R2); with an opening cut in it only the true
    pose fits, and the coarse starts must not miss it (the simulator writes such targets, issue 17)."""
    from pipeline.io import load_target
    from pipeline.simulate import CaptureSpec, Cutout, PlateSpec, simulate_capture

    plate = PlateSpec(
        shape="saddle",
        radius_mm=6000.0,
        radius2_mm=8000.0,
        cutouts=(Cutout.circle(400.0, -300.0, 260.0),),
    )
    out = simulate_capture(
        tmp_path, plate=plate, capture=CaptureSpec(width=320, height=256, stereo=False), seed=3
    )
    truth = np.load(out / "truth.npz")
    h, w = truth["mask"].shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    points = truth["depth_mm"][..., None] * (
        np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(truth["K"]).T
    )
    tgt = load_target(out / "target.json")
    reg = register_to_target(points, truth["mask"], tgt)
    # the STL is in the plate frame: the registration is T_cam_plate
    R = reg.T_cam_target[:3, :3].T @ truth["T_cam_plate"][:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 0.2
    assert reg.rms_mm < 0.1
    dev = deviation_map(points, truth["mask"], tgt, registration=reg)
    assert np.nanmax(np.abs(dev)) < 0.5
