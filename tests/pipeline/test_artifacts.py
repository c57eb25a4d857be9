"""Result artifacts: PLY surface and target, deviation and normal PNGs, depth .npy."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import trimesh

from pipeline.artifacts import (
    COLOUR_STOPS,
    deviation_colormap,
    save_depth,
    write_deviation_png,
    write_normals_png,
    write_surface_ply,
    write_target_ply,
    write_uncertainty,
)

GREY = (128, 128, 128)


def _grid(h: int, w: int, *, z_mm: float = 3000.0, step_mm: float = 5.0, seed: int = 0):
    """Points of a gently curved sheet on an (h, w) pixel grid, x along columns, y along rows, mm."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) * step_mm, (v - h / 2) * step_mm
    z = z_mm + (x**2 + y**2) / 20000.0 + rng.normal(0, 0.01, (h, w))
    return np.stack([x, y, z], axis=-1)


def _read_ply(path):
    mesh = trimesh.load(path, process=False, force="mesh")
    raw = mesh.metadata["_ply_raw"]["vertex"]["data"]
    return mesh, raw


# --------------------------------------------------------------------------- colour map


def test_colormap_stops_saturation_and_nan():
    limit = 4.0
    dev = np.array([[-limit, -limit / 2, 0.0, limit / 2, limit], [-9.0, 9.0, np.nan, -3.0, 1.0]])
    rgb = deviation_colormap(dev, limit_mm=limit)
    assert rgb.shape == (2, 5, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[0], COLOUR_STOPS)
    np.testing.assert_array_equal(rgb[1, 0], COLOUR_STOPS[0])  # saturated blue below -limit
    np.testing.assert_array_equal(rgb[1, 1], COLOUR_STOPS[-1])  # saturated red above +limit
    np.testing.assert_array_equal(rgb[1, 2], GREY)
    # -3 mm = t -0.75: halfway between the first two stops (linear in RGB, rounded).
    expected = np.rint((np.array(COLOUR_STOPS[0]) + np.array(COLOUR_STOPS[1])) / 2)
    np.testing.assert_array_equal(rgb[1, 3], expected)
    # Blue below, red above: the sign convention.
    assert rgb[1, 4, 0] > rgb[1, 4, 2] and rgb[0, 1, 2] > rgb[0, 1, 0]


@pytest.mark.parametrize("limit", [0.0, -1.0, math.inf, math.nan, None])
def test_colormap_bad_limit(limit):
    with pytest.raises(ValueError, match="limit_mm: expected a positive finite number"):
        deviation_colormap(np.zeros((2, 2)), limit_mm=limit)


def test_colormap_rejects_infinite_deviation():
    with pytest.raises(
        ValueError, match="deviation_mm: expected finite values or NaN, got 1 infinite"
    ):
        deviation_colormap(np.array([0.0, np.inf]), limit_mm=1.0)


def test_colormap_is_the_tables_nearest_step():
    # each deviation takes the table's step nearest to it (ties to even), clipped to the ends: the
    # compiled pass against the same arithmetic written in numpy, on every half step of the table
    # (the ties), strided views and shapes of any rank
    from pipeline.artifacts.colours import _COLOUR_LUT

    size = len(_COLOUR_LUT) - 1
    rng = np.random.default_rng(5)
    for limit in (4.0, 0.7):
        dev = rng.normal(0.0, limit, (300, 400))
        dev[rng.random(dev.shape) < 0.1] = np.nan
        half_steps = ((np.arange(-size, size + 1) + 0.5) / ((size - 1) / 2) - 1.0) * limit
        dev.ravel()[: half_steps.size] = half_steps
        index = np.clip(np.rint((dev / limit + 1.0) * (0.5 * (size - 1))), 0, size - 1)
        index[np.isnan(dev)] = size
        expected = _COLOUR_LUT[index.astype(np.intp)]
        np.testing.assert_array_equal(deviation_colormap(dev, limit_mm=limit), expected)
        np.testing.assert_array_equal(
            deviation_colormap(dev[::3, ::2], limit_mm=limit), expected[::3, ::2]
        )
    assert deviation_colormap(0.0, limit_mm=1.0).tolist() == [247, 247, 247]


# --------------------------------------------------------------------------- surface PLY


def test_surface_ply_round_trip(tmp_path):
    h, w = 12, 16
    pts = _grid(h, w)
    dev = np.linspace(-3, 3, h * w).reshape(h, w)
    path = tmp_path / "surface.ply"
    write_surface_ply(path, pts, np.ones((h, w), bool), dev, tolerance_mm=1.5)
    mesh, raw = _read_ply(path)
    assert len(mesh.vertices) == h * w and len(mesh.faces) == 2 * (h - 1) * (w - 1)
    # float32 storage: 3000 mm carries ~2.4e-4 mm resolution.
    np.testing.assert_allclose(mesh.vertices, pts.reshape(-1, 3), atol=5e-4)
    np.testing.assert_allclose(raw["deviation_mm"], dev.ravel(), atol=1e-6)
    colours = np.stack([raw["red"], raw["green"], raw["blue"]], axis=1)
    np.testing.assert_array_equal(colours, deviation_colormap(dev.ravel(), limit_mm=3.0))
    # Faces wound towards the cameras (-z), like the surface normals.
    assert np.all(mesh.face_normals[:, 2] < 0)
    assert "left camera frame" in path.read_bytes()[:600].decode("ascii", "replace")


def test_surface_ply_masked_cells(tmp_path):
    h, w = 10, 14
    rng = np.random.default_rng(5)
    mask = rng.random((h, w)) > 0.25
    pts = _grid(h, w)
    pts[2, 3] = np.nan  # a non-finite point inside the mask is not measured
    mask[2, 3] = True
    write_surface_ply(tmp_path / "s.ply", pts, mask, np.zeros((h, w)))
    mesh, _ = _read_ply(tmp_path / "s.ply")
    # Brute force: cells whose four corners are valid, and the corners they use.
    valid = mask & np.isfinite(pts).all(axis=-1)
    cells = [
        (r, c) for r in range(h - 1) for c in range(w - 1) if valid[r : r + 2, c : c + 2].all()
    ]
    used = {(r + dr, c + dc) for r, c in cells for dr in (0, 1) for dc in (0, 1)}
    assert len(mesh.faces) == 2 * len(cells) and len(mesh.vertices) == len(used)
    expected = np.array([pts[r, c] for r, c in sorted(used)])
    got = mesh.vertices[np.lexsort((mesh.vertices[:, 0], mesh.vertices[:, 1]))]
    np.testing.assert_allclose(
        got, expected[np.lexsort((expected[:, 0], expected[:, 1]))], atol=5e-4
    )
    assert np.all(np.isfinite(mesh.vertices))


def test_surface_ply_decimation_stride(tmp_path):
    h, w, budget = 100, 130, 1000
    pts = _grid(h, w)
    write_surface_ply(
        tmp_path / "s.ply", pts, np.ones((h, w), bool), np.zeros((h, w)), max_vertices=budget
    )
    mesh, _ = _read_ply(tmp_path / "s.ply")
    stride = next(s for s in range(1, 100) if math.ceil(h / s) * math.ceil(w / s) <= budget)
    assert len(mesh.vertices) == math.ceil(h / stride) * math.ceil(w / stride) <= budget
    np.testing.assert_allclose(mesh.vertices, pts[::stride, ::stride].reshape(-1, 3), atol=5e-4)


def test_surface_ply_nan_deviation_is_grey(tmp_path):
    h, w = 6, 7
    dev = np.full((h, w), 0.5)
    dev[0, 0] = np.nan
    write_surface_ply(tmp_path / "s.ply", _grid(h, w), np.ones((h, w), bool), dev, limit_mm=1.0)
    _, raw = _read_ply(tmp_path / "s.ply")
    assert np.isnan(raw["deviation_mm"][0])
    assert (raw["red"][0], raw["green"][0], raw["blue"][0]) == GREY


def test_surface_ply_bad_inputs(tmp_path):
    pts, mask, dev = _grid(5, 6), np.ones((5, 6), bool), np.zeros((5, 6))
    p = tmp_path / "s.ply"
    with pytest.raises(ValueError, match=r"points_mm: expected shape \(H, W, 3\), got \(5, 6\)"):
        write_surface_ply(p, pts[..., 0], mask, dev)
    with pytest.raises(ValueError, match=r"mask: expected shape \(5, 6\), got \(6, 5\)"):
        write_surface_ply(p, pts, mask.T, dev)
    with pytest.raises(ValueError, match="mask: expected a bool array, got float64"):
        write_surface_ply(p, pts, mask.astype(float), dev)
    with pytest.raises(ValueError, match=r"deviation_mm: expected shape \(5, 6\)"):
        write_surface_ply(p, pts, mask, dev[:4])
    with pytest.raises(ValueError, match="max_vertices: expected an integer >= 3, got 2"):
        write_surface_ply(p, pts, mask, dev, max_vertices=2)
    checker = (np.indices((5, 6)).sum(axis=0) % 2).astype(bool)
    with pytest.raises(ValueError, match="mask: no 2x2 cell with four valid corners"):
        write_surface_ply(p, pts, checker, dev)


# --------------------------------------------------------------------------- target PLY


def test_target_ply_moved_into_camera_frame(tmp_path):
    box = trimesh.creation.box(extents=(300.0, 200.0, 10.0))
    angle = 0.3
    T = np.eye(4)
    T[:3, :3] = [
        [math.cos(angle), -math.sin(angle), 0],
        [math.sin(angle), math.cos(angle), 0],
        [0, 0, 1],
    ]
    T[:3, 3] = [10.0, -20.0, 3000.0]
    write_target_ply(tmp_path / "t.ply", box.vertices, box.faces, T)
    mesh, _ = _read_ply(tmp_path / "t.ply")
    np.testing.assert_allclose(mesh.vertices, box.vertices @ T[:3, :3].T + T[:3, 3], atol=5e-4)
    np.testing.assert_array_equal(mesh.faces, box.faces)
    bad = T.copy()
    bad[0, 0] = 2.0
    with pytest.raises(ValueError, match="T_cam_target: expected a rigid transform"):
        write_target_ply(tmp_path / "t.ply", box.vertices, box.faces, bad)
    with pytest.raises(ValueError, match=r"faces: expected indices in \[0, 7\]"):
        write_target_ply(tmp_path / "t.ply", box.vertices, box.faces + 1, T)


# --------------------------------------------------------------------------- deviation PNG


def _read_rgb(path):
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert bgr is not None and bgr.dtype == np.uint8 and bgr.ndim == 3
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def test_deviation_png_size_and_colours(tmp_path):
    tol = 1.5  # default limit 3 mm: +/- tolerance on the light stops
    h, w = 60, 80
    values = [-3.0, -tol, 0.0, tol, 3.0, 7.0, np.nan]
    dev = np.zeros((h, w))
    for i, val in enumerate(values):
        dev[:, i * 10 : (i + 1) * 10] = val
    mask = np.ones((h, w), bool)
    mask[:, 70:] = False  # the last 10 columns are not measured
    path = tmp_path / "deviation.png"
    write_deviation_png(path, dev, mask, tolerance_mm=tol)
    rgb = _read_rgb(path)
    k = math.ceil(540 / h)  # documented enlargement of small maps
    assert rgb.shape[0] == max(k * h, 540) and rgb.shape[1] > k * w
    expected = [*COLOUR_STOPS, COLOUR_STOPS[-1], GREY, GREY]
    for i, colour in enumerate(expected):
        centre = rgb[k * h // 2, k * (i * 10 + 5)]
        np.testing.assert_array_equal(
            centre, colour, err_msg=f"block {i} ({values[i] if i < 7 else 'masked'})"
        )
    # The map region is exactly the colour map, enlarged by k (nearest neighbour).
    np.testing.assert_array_equal(
        rgb[::k, : w * k : k][:h], deviation_colormap(np.where(mask, dev, np.nan), limit_mm=3.0)
    )
    # The panel holds black text and the colour bar from red to blue. The bar's end rows are
    # under its black frame, the next ones are 1/(bar height) inside the ends: allow 4 units.
    panel = rgb[:, k * w :].astype(int)
    assert np.any(np.all(panel == 0, axis=-1))
    for stop in (COLOUR_STOPS[0], COLOUR_STOPS[-1]):
        assert np.any(np.abs(panel - stop).max(axis=-1) <= 4), stop


def test_deviation_png_large_map_keeps_resolution(tmp_path):
    h, w = 600, 700
    dev = np.tile(np.linspace(-2, 2, w), (h, 1))
    write_deviation_png(
        tmp_path / "d.png", dev, np.ones((h, w), bool), tolerance_mm=1.0, limit_mm=2.0
    )
    rgb = _read_rgb(tmp_path / "d.png")
    assert rgb.shape[0] == h and rgb.shape[1] > w
    np.testing.assert_array_equal(rgb[:, :w], deviation_colormap(dev, limit_mm=2.0))


def test_deviation_png_bad_inputs(tmp_path):
    dev, mask = np.zeros((8, 9)), np.ones((8, 9), bool)
    with pytest.raises(ValueError, match="tolerance_mm: expected a positive finite number"):
        write_deviation_png(tmp_path / "d.png", dev, mask, tolerance_mm=0.0)
    with pytest.raises(ValueError, match="limit_mm: expected a positive finite number"):
        write_deviation_png(tmp_path / "d.png", dev, mask, tolerance_mm=1.0, limit_mm=-2.0)
    with pytest.raises(ValueError, match=r"deviation_mm: expected shape \(H, W\), got \(72,\)"):
        write_deviation_png(tmp_path / "d.png", dev.ravel(), mask, tolerance_mm=1.0)
    with pytest.raises(OSError, match="cannot write the image"):
        write_deviation_png(tmp_path / "missing_dir" / "d.png", dev, mask, tolerance_mm=1.0)


# --------------------------------------------------------------------------- normals PNG, depth


def test_normals_png_mapping(tmp_path):
    n = np.zeros((4, 5, 3))
    n[...] = (0.0, 0.0, -1.0)  # facing the cameras
    n[0, 0] = (1.0, 0.0, 0.0)  # tilted to +x
    n[0, 1] = (0.0, -1.0, 0.0)  # tilted up (-y)
    n[0, 2] = (0.6, 0.0, -0.8)
    mask = np.ones((4, 5), bool)
    mask[3, 4] = False
    n[3, 4] = np.nan  # outside the mask anything goes
    write_normals_png(tmp_path / "n.png", n, mask)
    rgb = _read_rgb(tmp_path / "n.png")
    assert rgb.shape == (4, 5, 3)
    np.testing.assert_array_equal(rgb[1, 1], (128, 128, 255))
    np.testing.assert_array_equal(rgb[0, 0], (255, 128, 128))
    np.testing.assert_array_equal(rgb[0, 1], (128, 255, 128))
    np.testing.assert_array_equal(rgb[0, 2], np.rint([1.6 * 127.5, 127.5, 1.8 * 127.5]))
    np.testing.assert_array_equal(rgb[3, 4], (0, 0, 0))


def test_uncertainty_map_is_viridis_up_to_a_quarter_of_the_tolerance(tmp_path):
    # uncertainty.png: OpenCV's viridis at the level 255 * U / (tolerance / 4), saturating there; grey off
    # the judged points; uncertainty.npy the values on them, NaN elsewhere
    u = np.array([[0.0, 0.25, 0.5], [1.0, np.nan, 0.1]], np.float32)
    mask = np.array([[True, True, True], [True, False, True]])
    write_uncertainty(tmp_path, u, mask, tolerance_mm=2.0)
    rgb = _read_rgb(tmp_path / "uncertainty.png")
    levels = np.array([[0, 127, 255], [255, 0, 51]], np.uint8)
    viridis = cv2.cvtColor(cv2.applyColorMap(levels, cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(rgb[mask], viridis[mask])
    np.testing.assert_array_equal(rgb[1, 1], GREY)
    np.testing.assert_array_equal(np.load(tmp_path / "uncertainty.npy"), np.where(mask, u, np.nan))


def test_normals_png_bad_inputs(tmp_path):
    n = np.zeros((3, 3, 3))
    n[..., 2] = -1.0
    mask = np.ones((3, 3), bool)
    bad = n.copy()
    bad[1, 1] = (0.0, 0.0, -1.1)
    with pytest.raises(ValueError, match="normals: expected unit vectors inside the mask"):
        write_normals_png(tmp_path / "n.png", bad, mask)
    bad[1, 1] = np.nan
    with pytest.raises(
        ValueError, match="normals: expected finite values inside the mask, got 1 non-finite"
    ):
        write_normals_png(tmp_path / "n.png", bad, mask)
    with pytest.raises(ValueError, match=r"normals: expected shape \(H, W, 3\)"):
        write_normals_png(tmp_path / "n.png", n[..., :2], mask)


def test_save_depth_round_trip(tmp_path):
    depth = np.full((5, 6), 3000.25)
    depth[0, :] = np.nan
    path = tmp_path / "depth.npy"
    save_depth(path, depth)
    got = np.load(path)
    assert got.dtype == np.float32 and got.shape == (5, 6)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(depth))
    np.testing.assert_allclose(got[1:], depth[1:], rtol=1e-7)
    save_depth(tmp_path / "plain", depth)  # written as named, no suffix added
    assert (tmp_path / "plain").is_file()
    with pytest.raises(ValueError, match="depth_mm: expected finite values or NaN, got 1 infinite"):
        save_depth(path, np.where(np.arange(30).reshape(5, 6) == 3, np.inf, 1.0))
    with pytest.raises(ValueError, match=r"depth_mm: expected a float array of shape \(H, W\)"):
        save_depth(path, np.zeros(4))


def test_surface_ply_reads_back_and_refuses_what_it_cannot_show(tmp_path):
    from pipeline.artifacts.ply import read_surface_ply, write_surface_ply

    h, w = 20, 30
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    points = np.dstack([xx * 10.0, yy * 10.0, np.full((h, w), 2000.0)])
    dev = (xx - 15.0) * 0.1
    write_surface_ply(tmp_path / "surface.ply", points, np.ones((h, w), bool), dev)
    vertices, faces, deviation = read_surface_ply(tmp_path / "surface.ply")
    assert vertices.shape[1] == 3 and faces.shape[1] == 3 and faces.max() < len(vertices)
    assert deviation.shape == (len(vertices),)
    # every vertex carries the deviation of its grid point
    cols = np.rint(vertices[:, 0] / 10.0).astype(int)
    np.testing.assert_allclose(deviation, (cols - 15.0) * 0.1, atol=1e-5)

    (tmp_path / "notes.ply").write_text("not a mesh\n")
    with pytest.raises(ValueError, match=r"notes.ply: not a readable PLY"):
        read_surface_ply(tmp_path / "notes.ply")
    quads = "\n".join(
        [
            "ply",
            "format ascii 1.0",
            "element vertex 4",
            "property float x",
            "property float y",
            "property float z",
            "property float quality",
            "element face 1",
            "property list uchar int vertex_indices",
            "end_header",
            "0 0 0 0",
            "1 0 0 0",
            "1 1 0 0",
            "0 1 0 0",
            "4 0 1 2 3",
        ]
    )
    (tmp_path / "quads.ply").write_text(quads + "\n")
    with pytest.raises(ValueError, match=r"quads.ply: face: expected triangles only"):
        read_surface_ply(tmp_path / "quads.ply")
