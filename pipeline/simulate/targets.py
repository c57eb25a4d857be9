"""The nominal target a simulated capture is written with: analytic, or a mesh for other outlines and openings."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..formats import TARGET_FORMAT, TargetFile
from .geometry import inside_outline, outline_polygon, plate_height, plate_region
from .scene import PlateSpec

if TYPE_CHECKING:
    import trimesh


def target_object(plate: PlateSpec, tolerance_mm: float, out: Path) -> dict[str, Any]:
    """The ``plate-target/1`` object of the nominal plate (no dents); writes ``target.stl`` for a saddle
    and for a plate with a non-rectangular outline or with openings (see :func:`plate_mesh`)."""
    if plate.outline != "rectangle" or plate.cutouts:
        # the analytic shapes know only a size: the outline and the openings need a mesh
        plate_mesh(plate).export(out / "target.stl")
        shape: dict[str, Any] = {"type": "mesh", "file": "target.stl"}
    elif plate.shape == "plane":
        shape = {"type": "plane"}
    elif plate.shape in ("cylinder", "sphere"):
        shape = {"type": plate.shape, "radius_mm": float(plate.curved_radius_mm)}
    else:
        _saddle_mesh(plate).export(out / "target.stl")
        shape = {"type": "mesh", "file": "target.stl"}
    obj = {
        "format": TARGET_FORMAT,
        "shape": shape,
        "size_mm": list(plate.size_mm),
        "tolerance_mm": float(tolerance_mm),
    }
    TargetFile.model_validate(obj)
    return obj


def plate_mesh(plate: PlateSpec, *, spacing_mm: float = 50.0) -> trimesh.Trimesh:
    """The nominal plate (its shape without dents) over its outline, openings cut out, as a triangle mesh.

    Parameters
    ----------
    plate : PlateSpec
    spacing_mm : float
        Spacing of the interior vertices, mm; the outline and the openings' edges are sampled at half
        of it (a chord of a 100 mm radius opening then errs by < 0.8 mm from the arc).

    Returns
    -------
    trimesh.Trimesh
        Vertices in the plate frame (mm, z_p = nominal height ``plate_height``), faces with normals
        towards -z_p (the cameras). Boundary-conforming: a Delaunay triangulation of the edge samples
        and an interior grid, keeping the triangles whose centroid lies on the plate.
    """
    import trimesh
    from scipy.spatial import Delaunay, cKDTree

    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected > 0, got {spacing_mm}")
    nominal = PlateSpec(
        shape=plate.shape,
        radius_mm=plate.radius_mm,
        radius2_mm=plate.radius2_mm,
        convex=plate.convex,
        size_mm=plate.size_mm,
        outline=plate.outline,
        cutouts=plate.cutouts,
    )
    edge_step = spacing_mm / 2
    outline = outline_polygon(plate, step_mm=edge_step)
    edges = [
        outline[~np.any([c.signed_distance(*outline.T) < 0 for c in plate.cutouts], axis=0)]
        if plate.cutouts
        else outline
    ]
    for cut in plate.cutouts:
        ring = cut.boundary(edge_step)
        edges.append(ring[inside_outline(plate, ring[:, 0], ring[:, 1])])
    boundary = np.concatenate(edges)
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    gx, gy = np.meshgrid(
        np.arange(-half_w, half_w + 1e-9, spacing_mm), np.arange(-half_h, half_h + 1e-9, spacing_mm)
    )
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    grid = grid[plate_region(nominal, grid[:, 0], grid[:, 1])]
    near_edge, _ = cKDTree(boundary).query(grid)
    points = np.concatenate([boundary, grid[near_edge >= 0.4 * spacing_mm]])
    tri = Delaunay(points).simplices
    # a triangle bridging an opening or a concave stretch of the outline has its centroid off the plate
    centroid = points[tri].mean(axis=1)
    tri = tri[plate_region(nominal, centroid[:, 0], centroid[:, 1])]
    # faces counter-clockwise seen from -z_p (the cameras' side): clockwise in (x_p, y_p)
    a, b, c = (points[tri[:, i]] for i in range(3))
    ccw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]) > 0
    tri[ccw] = tri[ccw][:, ::-1]
    used = np.unique(tri)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(used.size)
    xy = points[used]
    z, _, _ = plate_height(nominal, xy[:, 0], xy[:, 1])
    return trimesh.Trimesh(vertices=np.column_stack([xy, z]), faces=remap[tri], process=False)


def _saddle_mesh(plate: PlateSpec, n: int = 61) -> trimesh.Trimesh:
    """Nominal saddle as a triangle mesh in the plate frame (mm), ``n x n`` vertices."""
    import trimesh

    nominal = PlateSpec(
        shape=plate.shape,
        radius_mm=plate.radius_mm,
        radius2_mm=plate.radius2_mm,
        convex=plate.convex,
        size_mm=plate.size_mm,
    )
    xs = np.linspace(-plate.size_mm[0] / 2, plate.size_mm[0] / 2, n)
    ys = np.linspace(-plate.size_mm[1] / 2, plate.size_mm[1] / 2, n)
    gx, gy = np.meshgrid(xs, ys)
    gz, _, _ = plate_height(nominal, gx, gy)
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
