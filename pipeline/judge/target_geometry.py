"""The CAD target's geometry: its frame, its checks, its surface as a mesh, and a mesh target as a height grid.

Target frame (the target's own frame; ``Registration.T_cam_target`` maps it into the left-camera frame)
-------------------------------------------------------------------------------------------------------
For ``plane``, ``cylinder`` and ``sphere`` targets: origin at the plate centre, on the surface; x along
``size_mm[0]``; y along ``size_mm[1]`` (the cylinder axis); z the plate normal at the centre. The surface is

- plane: ``z = 0``, with +z pointing away from the cameras after registration;
- cylinder: ``x^2 + (z - R)^2 = R^2`` (axis ``{(0, t, R)}``), i.e. ``z = R - sqrt(R^2 - x^2)``;
- sphere: ``x^2 + y^2 + (z - R)^2 = R^2``, i.e. ``z = R - sqrt(R^2 - x^2 - y^2)``.

So the centre of curvature is at ``(0, 0, +R)``: +z points from the surface towards its concave side. A plate
convex towards the cameras is registered with +z pointing away from them, a concave one with +z towards
them (the fit decides). ``size_mm`` is the extent projected on the xy plane (not the arc length), as in
the simulator. For ``mesh`` targets the target frame is the mesh file's own frame, whatever it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from pipeline.io import Target

#: Mesh targets: spacing (mm) of the height grid the mesh is rasterised to. Bilinear interpolation of a
#: surface of radius R at spacing g errs by ~g^2 / (8 R): 0.006 mm at R 2 m.
MESH_GRID_MM = 10.0

_SHAPES = ("plane", "cylinder", "sphere", "mesh")


def check_target(target: Target) -> Target:
    """The target checked for what registration and deviation need (shape, radius, mesh arrays, size)."""
    if not isinstance(target, Target):
        raise TypeError(f"target: expected a pipeline.io.Target, got {type(target).__name__}")
    if target.shape not in _SHAPES:
        raise ValueError(f"target.shape: expected one of {_SHAPES}, got {target.shape!r}")
    if target.shape in ("cylinder", "sphere"):
        r = target.radius_mm
        if r is None or not math.isfinite(r) or r <= 0:
            raise ValueError(
                f"target.radius_mm: expected a positive radius for a {target.shape}, got {r}"
            )
    if target.shape == "mesh":
        v, f = target.mesh_vertices_mm, target.mesh_faces
        if v is None or f is None:
            raise ValueError(
                "target.mesh_vertices_mm/mesh_faces: expected arrays for a mesh target, got None"
            )
        v, f = np.asarray(v), np.asarray(f)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3 or not np.all(np.isfinite(v)):
            raise ValueError(
                f"target.mesh_vertices_mm: expected finite (V, 3) with V >= 3, got shape {v.shape}"
            )
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1 or f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError(
                f"target.mesh_faces: expected (F, 3) indices below {v.shape[0]}, got shape {f.shape}"
            )
    size = tuple(target.size_mm)
    if len(size) != 2 or not all(math.isfinite(s) and s > 0 for s in size):
        raise ValueError(f"target.size_mm: expected two positive sizes in mm, got {target.size_mm}")
    return target


def target_surface(target: Target, *, spacing_mm: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """The target surface as a triangle mesh in the target frame (for the 3D view).

    Parameters
    ----------
    target : pipeline.io.Target
    spacing_mm : float
        Grid spacing of the generated mesh for plane/cylinder/sphere, mm (mesh targets are returned as given).

    Returns
    -------
    vertices : (V, 3) float64
        Target frame (module docstring), mm; map to the camera with ``Registration.T_cam_target``.
    faces : (F, 3) int64
        Counter-clockwise seen from +z: face normals point to +z (towards the centre of curvature).
    """
    tgt = check_target(target)
    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected a positive spacing in mm, got {spacing_mm}")
    if tgt.shape == "mesh":
        return np.asarray(tgt.mesh_vertices_mm, dtype=np.float64).copy(), np.asarray(
            tgt.mesh_faces, dtype=np.int64
        ).copy()
    sx, sy = tgt.size_mm
    nx = max(2, int(math.ceil(sx / spacing_mm)) + 1)
    ny = max(2, int(math.ceil(sy / spacing_mm)) + 1)
    gx, gy = np.meshgrid(np.linspace(-sx / 2, sx / 2, nx), np.linspace(-sy / 2, sy / 2, ny))
    if tgt.shape == "plane":
        gz = np.zeros_like(gx)
    else:
        Rt = tgt.radius_mm
        if Rt is None:
            raise ValueError(f"target.radius_mm: a {tgt.shape} needs its radius, got none")
        r2 = gx * gx if tgt.shape == "cylinder" else gx * gx + gy * gy
        if np.any(r2 >= Rt * Rt):
            raise ValueError(
                f"target.radius_mm: a {tgt.shape} of radius {Rt} mm cannot span size_mm {tgt.size_mm}"
            )
        gz = Rt - np.sqrt(Rt * Rt - r2)
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([b, d, c], axis=1)]).astype(
        np.int64
    )
    return vertices, faces


def target_area_mm2(target: Target) -> float:
    """Surface area of a target plate, mm^2: what a complete segmentation of it would measure.

    Parameters
    ----------
    target : pipeline.io.Target

    Returns
    -------
    float
        Mesh: the sum of its triangles' areas (its outline and openings included). Plane: the
        product of ``size_mm``. Cylinder: arc length across the axis times the length,
        ``2 R asin(sx / 2R) sy``. Sphere: the cap over the ``size_mm`` rectangle (midpoint rule
        on a 400 x 400 grid, relative error < 1e-5).

    Notes
    -----
    A parametric target has no outline: its area is its size's rectangle on the surface. The
    measured area is reported against it (details.json); missing metal is never a defect.
    """
    if not isinstance(target, Target):
        raise TypeError(f"target: expected a pipeline.io.Target, got {type(target).__name__}")
    if target.shape == "mesh":
        v = np.asarray(target.mesh_vertices_mm, dtype=np.float64)
        tri = v[np.asarray(target.mesh_faces, dtype=np.int64)]
        return float(
            0.5
            * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        )
    sx, sy = (float(v) for v in target.size_mm)
    if target.shape == "plane":
        return sx * sy
    if target.radius_mm is None:
        raise ValueError(f"target.radius_mm: a {target.shape} needs its radius, got none")
    R = float(target.radius_mm)
    if target.shape == "cylinder":
        return 2.0 * R * math.asin(min(1.0, sx / (2.0 * R))) * sy
    n = 400
    x = (np.arange(n) + 0.5) / n * sx - sx / 2
    y = (np.arange(n) + 0.5) / n * sy - sy / 2
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    if np.any(r2 >= R * R):
        raise ValueError(
            f"target.radius_mm: a sphere of radius {R} mm cannot span size_mm {target.size_mm}"
        )
    return float((R / np.sqrt(R * R - r2)).sum() * (sx / n) * (sy / n))


@dataclass(frozen=True)
class MeshGrid:
    """A mesh target as a height field over its PCA plane.

    ``frame`` rows (ex, ey, ez) and ``origin`` give plate coordinates ``q = frame @ (X_target - origin)``;
    the surface is ``q_z = h(q_x, q_y)`` with ``h`` sampled at ``x0 + i * step``, ``y0 + j * step``
    (``height[j, i]``, NaN off the mesh); ``slope_factor = 1 / sqrt(1 + |grad h|^2)``.
    """

    origin: np.ndarray
    frame: np.ndarray
    x0: float
    y0: float
    step: float
    height: np.ndarray
    slope_factor: np.ndarray
    height_filled: np.ndarray

    def sample(self, q: np.ndarray, *, filled: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear height and slope factor at plate coordinates (M, 3); NaN off the mesh unless filled."""
        n = q.shape[0]
        cols = 4096 if n > 4096 else max(n, 1)
        rows = -(-n // cols)
        mx = np.zeros(rows * cols, dtype=np.float32)
        my = np.zeros(rows * cols, dtype=np.float32)
        mx[:n] = (q[:, 0] - self.x0) / self.step
        my[:n] = (q[:, 1] - self.y0) / self.step
        mx, my = (
            mx.reshape(rows, cols),
            my.reshape(rows, cols),
        )  # cv2.remap wants both sizes < 32767
        grid = self.height_filled if filled else self.height
        border = cv2.BORDER_REPLICATE if filled else cv2.BORDER_CONSTANT
        h = cv2.remap(grid, mx, my, cv2.INTER_LINEAR, borderMode=border, borderValue=float("nan"))
        s = cv2.remap(self.slope_factor, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return h.ravel()[:n].astype(np.float64), s.ravel()[:n].astype(np.float64)


def _rasterise(
    q_vertices: np.ndarray, faces: np.ndarray, step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Heights of a triangle mesh (plate coordinates) on a regular grid by barycentric interpolation."""
    lo = q_vertices[:, :2].min(axis=0)
    hi = q_vertices[:, :2].max(axis=0)
    nx = int(math.floor((hi[0] - lo[0]) / step)) + 1
    ny = int(math.floor((hi[1] - lo[1]) / step)) + 1
    height = np.full((ny, nx), np.nan)
    tri = q_vertices[faces]  # (F, 3, 3)
    i0 = np.ceil((tri[:, :, 0].min(axis=1) - lo[0]) / step - 1e-9).astype(np.int64)
    i1 = np.floor((tri[:, :, 0].max(axis=1) - lo[0]) / step + 1e-9).astype(np.int64)
    j0 = np.ceil((tri[:, :, 1].min(axis=1) - lo[1]) / step - 1e-9).astype(np.int64)
    j1 = np.floor((tri[:, :, 1].max(axis=1) - lo[1]) / step + 1e-9).astype(np.int64)
    cnt_i = np.maximum(i1 - i0 + 1, 0)
    cnt_j = np.maximum(j1 - j0 + 1, 0)
    # Process triangles in chunks so the candidate (triangle, node) pairs stay small in memory.
    chunk_start = 0
    counts = cnt_i * cnt_j
    cum = np.cumsum(counts)
    while chunk_start < len(faces):
        base = cum[chunk_start - 1] if chunk_start else 0
        chunk_end = int(np.searchsorted(cum, base + 2_000_000, side="right"))
        chunk_end = max(chunk_end, chunk_start + 1)
        sl = slice(chunk_start, chunk_end)
        c = counts[sl]
        if c.sum():
            f_idx = np.repeat(np.arange(chunk_start, chunk_end), c)
            k = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
            ii = i0[f_idx] + k % cnt_i[f_idx]
            jj = j0[f_idx] + k // cnt_i[f_idx]
            px = lo[0] + ii * step
            py = lo[1] + jj * step
            a, b, cc = tri[f_idx, 0], tri[f_idx, 1], tri[f_idx, 2]
            det = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (cc[:, 0] - a[:, 0]) * (
                b[:, 1] - a[:, 1]
            )
            ok = np.abs(det) > 1e-12
            det = np.where(ok, det, 1.0)
            l1 = (
                (px - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (cc[:, 0] - a[:, 0]) * (py - a[:, 1])
            ) / det
            l2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
            l0 = 1 - l1 - l2
            inside = ok & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
            z = l0 * a[:, 2] + l1 * b[:, 2] + l2 * cc[:, 2]
            height[jj[inside], ii[inside]] = z[inside]
        chunk_start = chunk_end
    return lo, height


#: The last mesh target rasterised and its grid: registration and deviation map of one inspection
#: rasterise the same target (one entry: a service inspects one plate at a time).
_last_grid: tuple[Target, MeshGrid] | None = None


def mesh_grid(target: Target) -> MeshGrid:
    """The mesh target as a height grid (rasterised once per target object; see :data:`_last_grid`)."""
    global _last_grid
    last = _last_grid
    if last is not None and last[0] is target:
        return last[1]
    grid = _rasterised_grid(target)
    _last_grid = (target, grid)
    return grid


def _rasterised_grid(target: Target) -> MeshGrid:
    """Rasterise a mesh target over its area-weighted PCA plane at MESH_GRID_MM (coarser for a mesh over 15 m)."""
    v = np.asarray(target.mesh_vertices_mm, dtype=np.float64)
    f = np.asarray(target.mesh_faces, dtype=np.int64)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not np.any(area > 0):
        raise ValueError(
            "target.mesh_faces: expected triangles of non-zero area, got only degenerate ones"
        )
    centres = tri.mean(axis=1)
    origin = (centres * area[:, None]).sum(axis=0) / area.sum()
    d = centres - origin
    cov = (d * area[:, None]).T @ d
    _, evecs = np.linalg.eigh(cov)
    frame = np.stack([evecs[:, 2], evecs[:, 1], np.cross(evecs[:, 2], evecs[:, 1])])
    q = (v - origin) @ frame.T
    extent = float(np.max(q[:, :2].max(axis=0) - q[:, :2].min(axis=0)))
    step = max(MESH_GRID_MM, extent / 1500.0)
    lo, height = _rasterise(q, f, step)
    if np.isnan(height).all():
        raise ValueError(
            "target.mesh_faces: the mesh covers no grid node; it is not a plate-like surface"
        )
    filled = height
    holes = np.isnan(height)
    if holes.any():
        _, (rj, ri) = ndimage.distance_transform_edt(holes, return_indices=True)
        filled = height[rj, ri]
    gy, gx = np.gradient(filled, step)
    slope = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    return MeshGrid(
        origin=origin,
        frame=frame,
        x0=float(lo[0]),
        y0=float(lo[1]),
        step=step,
        height=height.astype(np.float32),
        slope_factor=slope.astype(np.float32),
        height_filled=filled.astype(np.float32),
    )
