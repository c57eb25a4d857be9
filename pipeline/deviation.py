"""Registration of the measured plate to its CAD target, signed deviation, and the pass/fail verdict.

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

Deviation sign
--------------
Positive where the measured surface lies on the side of the target that faces the cameras (the plate stands
proud of its target, towards the cameras), negative behind it. The camera-facing side is the side of the
target on which the left camera centre lies, taken at the plate centre (a plate seen whole by the camera has
the camera on one side of it everywhere).

References
----------
.. [1] Besl, P. J., McKay, N. D., "A method for registration of 3-D shapes", IEEE TPAMI 14(2), 1992 (ICP).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .solvers import robust_gauss_newton as _robust_gauss_newton
from .solvers import robust_scale as _robust_scale
from .surface_fits import MAX_FIT_POINTS, check_grid, fit_cylinder, fit_sphere, grid_sample
from .surface_fits import fit_curved as _fit_curved
from .surface_fits import pca_frame as _pca_frame
from .io import Target

#: Default smallest out-of-tolerance region (mm^2) that fails a plate: 100 mm^2 = 1 cm^2, i.e. tens of
#: pixels at 1.2-3.5 mm/pixel, far more than a noisy pixel, far less than a real dent (a 6 mm dent of
#: radius 100 mm is out of a 2 mm tolerance over ~13 000 mm^2).
MIN_DEFECT_AREA_MM2 = 100.0
#: Default largest share (%) of the measured area allowed out of tolerance in total, scattered or not.
MAX_OUTSIDE_PCT = 1.0
#: Mesh targets: spacing (mm) of the height grid the mesh is rasterised to. Bilinear interpolation of a
#: surface of radius R at spacing g errs by ~g^2 / (8 R): 0.006 mm at R 2 m.
MESH_GRID_MM = 10.0
#: ICP for mesh targets: measured points used for the coarse alignment.
ICP_POINTS = 2000
#: ICP for mesh targets: coarse starts (in-plane turns, normal either way) refined by ICP, best scored first.
ICP_STARTS = 4

_SHAPES = ("plane", "cylinder", "sphere", "mesh")


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Registration:
    """Best-fit pose of the target on the measured plate.

    Attributes
    ----------
    T_cam_target : (4, 4) float64
        Maps target-frame points (mm) into the left-camera frame (mm): ``X_cam = R @ X_target + t``.
    shape : str
        The target's shape type.
    rms_mm : float
        RMS orthogonal distance of the measured points used in the fit to the registered target, mm.
    convex_towards_camera : bool or None
        For cylinder and sphere targets: whether the fit chose the plate convex towards the cameras.
    fitted_radius_mm : float or None
        For cylinder and sphere targets: the radius of the radius-free fit of the same shape made on the
        way (equal to :func:`fitted_target_radius` on the same grid; ``inf`` for an exactly flat fit).
        None for plane and mesh targets.
    """

    T_cam_target: np.ndarray
    shape: str
    rms_mm: float
    convex_towards_camera: bool | None
    fitted_radius_mm: float | None = None


@dataclass(frozen=True)
class DefectRegion:
    """A connected region (8-neighbour) of pixels out of tolerance.

    Attributes
    ----------
    centroid_px : (float, float)
        ``(u, v)`` = (column, row) of the region's centroid, pixels.
    area_mm2 : float
        Surface area of the region, mm^2.
    peak_deviation_mm : float
        Signed deviation of largest magnitude in the region, mm.
    n_pixels : int
    """

    centroid_px: tuple[float, float]
    area_mm2: float
    peak_deviation_mm: float
    n_pixels: int


@dataclass(frozen=True)
class EdgeArtefacts:
    """How :func:`judge` tells segmentation artefacts at the plate's edge from edge defects (issue 17).

    An out-of-tolerance region is an *edge artefact*, excluded from the verdict and the statistics,
    when all three hold:

    - it touches the measured mask's boundary (an outline or an opening; not the image frame);
    - it is thin along that boundary: ``share`` of its pixels lie within ``max_depth_px`` of it (mixed
      pixels and what the integration makes of them; a bent edge or a flange reaches further in);
    - what lies beside it is floor-like: the median of ``step_mm`` over its pixels is at least
      ``min_step_mm`` (``+inf``, a dark background, counts as a step; NaN, unknown, does not count).

    Attributes
    ----------
    step_mm : (H, W) array_like of float
        Depth step from the plate to its surroundings near the boundary, mm, positive behind the plate
        (``pipeline.segmentation.Segmentation.surroundings_step_mm``); NaN where unknown.
    min_step_mm : float
        Least step (mm) typical of the floor or the supports beside the plate.
    max_depth_px : float
        How far into the plate (px) an artefact reaches.
    share : float
        Share of the region's pixels that must lie within ``max_depth_px`` of the boundary (0..1].
    """

    step_mm: np.ndarray
    min_step_mm: float = 100.0
    max_depth_px: float = 6.0
    share: float = 0.9

    def __post_init__(self) -> None:
        step = np.asarray(self.step_mm, dtype=np.float32)
        if step.ndim != 2:
            raise ValueError(f"EdgeArtefacts.step_mm: expected an (H, W) array, got shape {step.shape}")
        object.__setattr__(self, "step_mm", step)
        if not (math.isfinite(self.min_step_mm) and self.min_step_mm > 0):
            raise ValueError(f"EdgeArtefacts.min_step_mm: expected a step > 0 mm, got {self.min_step_mm}")
        if not (math.isfinite(self.max_depth_px) and self.max_depth_px > 0):
            raise ValueError(f"EdgeArtefacts.max_depth_px: expected > 0 px, got {self.max_depth_px}")
        if not 0 < self.share <= 1:
            raise ValueError(f"EdgeArtefacts.share: expected in (0, 1], got {self.share}")


@dataclass(frozen=True)
class ExcludedRegion:
    """An out-of-tolerance region left out of the verdict, and why.

    Attributes
    ----------
    centroid_px : (float, float)
        ``(u, v)`` of its centroid, pixels.
    area_mm2 : float
    peak_deviation_mm : float
        Signed deviation of largest magnitude in it, mm.
    n_pixels : int
    reason : str
    """

    centroid_px: tuple[float, float]
    area_mm2: float
    peak_deviation_mm: float
    n_pixels: int
    reason: str


@dataclass(frozen=True)
class Judgement:
    """Deviation statistics and the verdict (see :func:`judge` for the rule).

    Attributes
    ----------
    rms_mm, max_abs_mm, p95_mm : float
        RMS, maximum and 95th percentile of ``|deviation|`` over the judged pixels, mm.
    within_tolerance_pct : float
        Share of the judged surface area with ``|deviation| <= tolerance_mm``, percent.
    verdict : {"pass", "fail"}
    defects : tuple of DefectRegion
        Out-of-tolerance regions of at least ``min_defect_area_mm2``, largest first.
    outside_area_mm2 : float
        Total out-of-tolerance area, mm^2 (regions of any size).
    n_pixels : int
        Pixels judged (in the mask, with a finite deviation).
    reasons : tuple of str
        Why the plate failed (empty when it passed).
    excluded : tuple of ExcludedRegion
        Out-of-tolerance regions left out of the verdict and of every statistic above (only with
        ``edge_artefacts``), each with its reason.
    """

    rms_mm: float
    max_abs_mm: float
    p95_mm: float
    within_tolerance_pct: float
    verdict: str
    defects: tuple[DefectRegion, ...]
    outside_area_mm2: float
    n_pixels: int
    reasons: tuple[str, ...]
    excluded: tuple[ExcludedRegion, ...] = ()


# --------------------------------------------------------------------------- checks and helpers


def _check_target(target) -> Target:
    if not isinstance(target, Target):
        raise TypeError(f"target: expected a pipeline.io.Target, got {type(target).__name__}")
    if target.shape not in _SHAPES:
        raise ValueError(f"target.shape: expected one of {_SHAPES}, got {target.shape!r}")
    if target.shape in ("cylinder", "sphere"):
        r = target.radius_mm
        if r is None or not math.isfinite(r) or r <= 0:
            raise ValueError(f"target.radius_mm: expected a positive radius for a {target.shape}, got {r}")
    if target.shape == "mesh":
        v, f = target.mesh_vertices_mm, target.mesh_faces
        if v is None or f is None:
            raise ValueError("target.mesh_vertices_mm/mesh_faces: expected arrays for a mesh target, got None")
        v, f = np.asarray(v), np.asarray(f)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3 or not np.all(np.isfinite(v)):
            raise ValueError(f"target.mesh_vertices_mm: expected finite (V, 3) with V >= 3, got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1 or f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError(f"target.mesh_faces: expected (F, 3) indices below {v.shape[0]}, got shape {f.shape}")
    size = tuple(target.size_mm)
    if len(size) != 2 or not all(math.isfinite(s) and s > 0 for s in size):
        raise ValueError(f"target.size_mm: expected two positive sizes in mm, got {target.size_mm}")
    return target


def _check_registration(registration) -> np.ndarray:
    if not isinstance(registration, Registration):
        raise TypeError(f"registration: expected a Registration, got {type(registration).__name__}")
    T = np.asarray(registration.T_cam_target, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"registration.T_cam_target: expected a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("registration.T_cam_target: expected a rigid transform (rotation + translation)")
    return T


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _in_plane_x(points: np.ndarray, z: np.ndarray, size_mm) -> np.ndarray:
    """Target x axis: the measured plate's in-plane principal direction matching ``size_mm``, ``x_cam >= 0``."""
    _, frame = _pca_frame(points)
    major = frame[0] - (frame[0] @ z) * z
    major /= np.linalg.norm(major)
    x = major if size_mm[0] >= size_mm[1] else np.cross(z, major)
    return -x if x[0] < 0 else x


# --------------------------------------------------------------------------- registration


def fitted_target_radius(points_mm, mask, target) -> float | None:
    """Radius of the target's own shape fitted, radius free, to the measured surface (``radius_mm`` of the result).

    Parameters
    ----------
    points_mm : (H, W, 3) array_like of float
        Surface points, left-camera frame, mm.
    mask : (H, W) bool
    target : pipeline.io.Target

    Returns
    -------
    float or None
        Unsigned cylinder radius (cylinder target) or sphere radius (sphere target), mm; ``inf`` for an
        exactly flat fit; None for plane and mesh targets.
    """
    tgt = _check_target(target)
    pts, m = check_grid(points_mm, mask, min_points=50)
    if tgt.shape == "cylinder":
        return fit_cylinder(grid_sample(pts, m, MAX_FIT_POINTS)).radius_mm
    if tgt.shape == "sphere":
        return fit_sphere(grid_sample(pts, m, MAX_FIT_POINTS)).radius_mm
    return None


def register_to_target(points_mm, mask, target) -> Registration:
    """Best-fit rigid registration of the measured surface to the target.

    Parameters
    ----------
    points_mm : (H, W, 3) array_like of float
        Surface point of each pixel, left-camera frame, mm (ignored outside the mask).
    mask : (H, W) bool
        True where valid; at least 50 valid pixels.
    target : pipeline.io.Target

    Returns
    -------
    Registration
        ``T_cam_target`` maps target-frame points into the camera frame (module docstring for the frame).

    Raises
    ------
    ValueError, TypeError
        Bad grid, mask or target.

    Notes
    -----
    Plane, cylinder, sphere: a robust geometric fit of the shape with the target's radius fixed, started
    from the radius-free fit (its curvature picks convex or concave when it is at least half the target's;
    otherwise both are tried and the lower cost wins); the in-surface position is the measured plate's
    centroid and the in-plane x axis its principal direction (these two do not change the deviation of a
    rotationally or translationally symmetric target). Mesh: the mesh is rasterised to a height grid over
    its own PCA plane; the measured and mesh PCA frames are matched under the 4 proper axis flips (and
    with x and y swapped); the two starts closest to the mesh are refined by point-to-point ICP
    (``trimesh.registration.icp``) against points of that grid, the better one then refined by robust Gauss-Newton on the point-to-surface distances.
    """
    tgt = _check_target(target)
    pts, m = check_grid(points_mm, mask, min_points=50)
    sample = grid_sample(pts, m, MAX_FIT_POINTS)
    if tgt.shape == "mesh":
        return _register_mesh(sample, tgt)
    centroid = sample.mean(axis=0)
    if tgt.shape == "plane":
        n, p0, _, _, rms, _ = _fit_curved(sample, cylinder=False, radius_mm=None, max_points=MAX_FIT_POINTS,
                                       curvature_per_mm=0.0)
        z = n  # the fit's normal points away from the camera
        origin = p0 + ((centroid - p0) - ((centroid - p0) @ z) * z)
        x = _in_plane_x(sample, z, tgt.size_mm)
        convex = None
    elif tgt.shape == "cylinder":
        fit = fit_cylinder(sample, radius_mm=tgt.radius_mm)
        a, c = fit.axis, fit.point_on_axis_mm
        v = (centroid - c) - ((centroid - c) @ a) * a
        v /= np.linalg.norm(v)
        origin = c + ((centroid - c) @ a) * a + tgt.radius_mm * v
        z = -v
        y = a
        x = np.cross(y, z)
        rms, convex, k_free = fit.rms_mm, fit.convex_towards_camera, fit.free_curvature_per_mm
    else:  # sphere
        fit = fit_sphere(sample, radius_mm=tgt.radius_mm)
        v = centroid - fit.center_mm
        v /= np.linalg.norm(v)
        origin = fit.center_mm + tgt.radius_mm * v
        z = -v
        x = _in_plane_x(sample, z, tgt.size_mm)
        rms, convex, k_free = fit.rms_mm, fit.convex_towards_camera, fit.free_curvature_per_mm
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    free_radius = None if convex is None else (abs(1.0 / k_free) if k_free != 0 else math.inf)
    return Registration(T_cam_target=_pose(R, origin), shape=tgt.shape, rms_mm=float(rms),
                        convex_towards_camera=convex, fitted_radius_mm=free_radius)


# --------------------------------------------------------------------------- mesh targets


@dataclass(frozen=True)
class _MeshGrid:
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
        mx, my = mx.reshape(rows, cols), my.reshape(rows, cols)  # cv2.remap wants both sizes < 32767
        grid = self.height_filled if filled else self.height
        border = cv2.BORDER_REPLICATE if filled else cv2.BORDER_CONSTANT
        h = cv2.remap(grid, mx, my, cv2.INTER_LINEAR, borderMode=border, borderValue=float("nan"))
        s = cv2.remap(self.slope_factor, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return h.ravel()[:n].astype(np.float64), s.ravel()[:n].astype(np.float64)


def _rasterise(q_vertices: np.ndarray, faces: np.ndarray, step: float):
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
            det = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (cc[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
            ok = np.abs(det) > 1e-12
            det = np.where(ok, det, 1.0)
            l1 = ((px - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (cc[:, 0] - a[:, 0]) * (py - a[:, 1])) / det
            l2 = ((b[:, 0] - a[:, 0]) * (py - a[:, 1]) - (px - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
            l0 = 1 - l1 - l2
            inside = ok & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
            z = l0 * a[:, 2] + l1 * b[:, 2] + l2 * cc[:, 2]
            height[jj[inside], ii[inside]] = z[inside]
        chunk_start = chunk_end
    return lo, height


#: The last mesh target rasterised and its grid: registration and deviation map of one inspection
#: rasterise the same target (one entry: a service inspects one plate at a time).
_last_grid: tuple[Target, _MeshGrid] | None = None


def _mesh_grid(target: Target) -> _MeshGrid:
    global _last_grid
    last = _last_grid
    if last is not None and last[0] is target:
        return last[1]
    grid = _rasterised_grid(target)
    _last_grid = (target, grid)
    return grid


def _rasterised_grid(target: Target) -> _MeshGrid:
    v = np.asarray(target.mesh_vertices_mm, dtype=np.float64)
    f = np.asarray(target.mesh_faces, dtype=np.int64)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not np.any(area > 0):
        raise ValueError("target.mesh_faces: expected triangles of non-zero area, got only degenerate ones")
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
        raise ValueError("target.mesh_faces: the mesh covers no grid node; it is not a plate-like surface")
    filled = height
    holes = np.isnan(height)
    if holes.any():
        _, (rj, ri) = ndimage.distance_transform_edt(holes, return_indices=True)
        filled = height[rj, ri]
    gy, gx = np.gradient(filled, step)
    slope = 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)
    return _MeshGrid(origin=origin, frame=frame, x0=float(lo[0]), y0=float(lo[1]), step=step,
                     height=height.astype(np.float32), slope_factor=slope.astype(np.float32),
                     height_filled=filled.astype(np.float32))


def _register_mesh(sample: np.ndarray, target: Target) -> Registration:
    import trimesh  # heavy import, only for mesh targets

    grid = _mesh_grid(target)
    jj, ii = np.nonzero(np.isfinite(grid.height))
    keep = np.linspace(0, len(jj) - 1, min(len(jj), 50_000)).round().astype(np.int64)
    jj, ii = jj[keep], ii[keep]
    q_nodes = np.stack([grid.x0 + ii * grid.step, grid.y0 + jj * grid.step, grid.height[jj, ii]], axis=1)
    target_pts = q_nodes @ grid.frame + grid.origin  # target frame

    c_s, frame_s = _pca_frame(sample)
    icp_pts = sample[np.linspace(0, len(sample) - 1, min(len(sample), ICP_POINTS)).round().astype(np.int64)]
    # Mesh PCA frame's z is the least-spread axis; the measured frame's z is too (pointing away from camera).
    # In the plane, PCA's axes are ill-defined for a squarish plate (and turned by an opening differently in
    # the mesh's area weighting and the camera's pixel sampling): in-plane turns every 30 deg, each with
    # the plate's normal either way.
    starts = []
    for flip in (np.eye(3), np.diag([1.0, -1.0, -1.0])):
        for turn in np.radians(np.arange(0.0, 360.0, 30.0)):
            c, s_ = math.cos(turn), math.sin(turn)
            starts.append(np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ flip)
    tree = cKDTree(target_pts)
    scored = []
    for M in starts:
        R0 = grid.frame.T @ M @ frame_s  # camera -> target
        T0 = _pose(R0, grid.origin - R0 @ c_s)
        dist, _ = tree.query(icp_pts @ R0.T + T0[:3, 3])
        scored.append((float(np.mean(dist)), T0))
    scored.sort(key=lambda item: item[0])
    best = None
    # ICP from the four best starts: a saddle turned upside down and by 90 deg is nearly itself (R1 ~ R2), and
    # such near-symmetric poses can score better before ICP than the true one
    for _, T0 in scored[:ICP_STARTS]:
        T, _, cost = trimesh.registration.icp(icp_pts, target_pts, initial=T0, threshold=1e-7,
                                              max_iterations=20, reflection=False, scale=False)
        if best is None or cost < best[1]:
            best = (T, cost)
    T_target_cam = _refine_mesh_pose(best[0], sample, grid)
    rms = _mesh_rms(T_target_cam, sample, grid)
    return Registration(T_cam_target=np.linalg.inv(T_target_cam), shape="mesh", rms_mm=rms,
                        convex_towards_camera=None)


def _mesh_residuals(T_target_cam: np.ndarray, pts: np.ndarray, grid: _MeshGrid, *, filled: bool) -> np.ndarray:
    x_t = pts @ T_target_cam[:3, :3].T + T_target_cam[:3, 3]
    q = (x_t - grid.origin) @ grid.frame.T
    h, s = grid.sample(q, filled=filled)
    return (q[:, 2] - h) * s


def _refine_mesh_pose(T0: np.ndarray, pts: np.ndarray, grid: _MeshGrid) -> np.ndarray:
    """Robust Gauss-Newton on point-to-surface distances over a small rotation (about the points' centroid)
    and translation. A cylinder or sphere can slide along itself at no cost, which could carry the plate off
    the mesh: two weak rows (0.01 per mm and point) hold the centroid's in-plane position from the ICP."""
    x0 = pts @ T0[:3, :3].T + T0[:3, 3]
    centre = x0.mean(axis=0)
    hold = 1e-2 * math.sqrt(pts.shape[0])

    def pose(p):
        Rs = Rotation.from_rotvec(p[:3]).as_matrix()
        R = Rs @ T0[:3, :3]
        t = Rs @ (T0[:3, 3] - centre) + centre + p[3:]
        return _pose(R, t)

    def fun(p):
        r = _mesh_residuals(pose(p), pts, grid, filled=True)
        return np.concatenate([r, hold * (grid.frame[:2] @ p[3:])])

    # Steps large against the float32 height grid's resolution: 1e-4 rad moves a plate edge 0.15 mm.
    steps = np.array([1e-4, 1e-4, 1e-4, 0.1, 0.1, 0.1])
    p = np.zeros(6)
    f_scale = max(3.0 * _robust_scale(fun(p)), 0.05)
    p, _ = _robust_gauss_newton(fun, p, steps, f_scale, rtol=1e-9)
    f_scale = max(3.0 * _robust_scale(fun(p)), 0.01)
    p, _ = _robust_gauss_newton(fun, p, steps, f_scale, rtol=1e-9)
    return pose(p)


def _mesh_rms(T_target_cam: np.ndarray, pts: np.ndarray, grid: _MeshGrid) -> float:
    r = _mesh_residuals(T_target_cam, pts, grid, filled=False)
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else math.nan


# --------------------------------------------------------------------------- deviation


def deviation_map(points_mm, mask, target, registration) -> np.ndarray:
    """Signed deviation of the measured surface from the registered target, per pixel.

    Parameters
    ----------
    points_mm : (H, W, 3) array_like of float
        Surface points, left-camera frame, mm.
    mask : (H, W) bool
    target : pipeline.io.Target
    registration : Registration
        From :func:`register_to_target` (or any rigid ``T_cam_target``).

    Returns
    -------
    (H, W) float32
        Signed orthogonal distance to the target surface, mm: **positive where the measured surface lies
        on the side of the target that faces the cameras**, negative behind it. NaN outside the mask and,
        for mesh targets, where the point falls outside the mesh's footprint.

    Notes
    -----
    Plane, cylinder and sphere: exact distances in the target frame. Mesh: the height difference to the
    mesh (rasterised to a 5 mm grid over its PCA plane, bilinear) times ``1/sqrt(1 + |grad h|^2)`` --
    the normal distance to first order in the deviation.
    """
    tgt = _check_target(target)
    T = _check_registration(registration)
    pts, m = check_grid(points_mm, mask, min_points=1)
    R, t = T[:3, :3], T[:3, 3]
    T_target_cam = np.hstack([R.T, (-R.T @ t)[:, None]])
    cam = T_target_cam[:, 3]  # camera centre in the target frame
    if tgt.shape != "mesh":
        # Analytic shapes: in chunks of pixels, so the float64 temporaries stay in cache instead of
        # allocating several (H, W, 3) arrays (their page faults cost more than the arithmetic).
        out = np.empty(m.size, dtype=np.float32)
        flat = pts.reshape(-1, 3)
        for start in range(0, flat.shape[0], _CHUNK):
            x = cv2.transform(flat[start : start + _CHUNK].reshape(-1, 1, 3), T_target_cam).reshape(-1, 3)
            out[start : start + _CHUNK] = _analytic_deviation(x, tgt, cam)
        out = out.reshape(m.shape)
        out[~m] = np.nan
        return out
    # Mesh: camera frame -> plate coordinates of the mesh grid in one transform, in chunks as above.
    grid = _mesh_grid(tgt)
    to_plate = grid.frame @ np.hstack([T_target_cam[:, :3], (T_target_cam[:, 3] - grid.origin)[:, None]])
    q_cam = grid.frame @ (cam - grid.origin)
    h0, _ = grid.sample(q_cam[None, :], filled=True)
    side = 1.0 if q_cam[2] > h0[0] else -1.0
    out = np.empty(m.size, dtype=np.float32)
    flat = pts.reshape(-1, 3)
    with np.errstate(invalid="ignore"):  # NaN points outside the mask
        for start in range(0, flat.shape[0], _MESH_CHUNK):
            q = cv2.transform(flat[start : start + _MESH_CHUNK].reshape(-1, 1, 3), to_plate).reshape(-1, 3)
            h, slope = grid.sample(q)
            out[start : start + _MESH_CHUNK] = side * (q[:, 2] - h) * slope
    out = out.reshape(m.shape)
    out[~m] = np.nan
    return out


_CHUNK = 1 << 16  # pixels per chunk of deviation_map's analytic shapes
_MESH_CHUNK = 1 << 18  # and of mesh targets (each chunk samples the grid with cv2.remap)


def _analytic_deviation(x: np.ndarray, tgt: Target, cam: np.ndarray) -> np.ndarray:
    """Signed deviation (mm, + on the camera's side) of target-frame points (N, 3) from a plane, cylinder or sphere."""
    Rt = tgt.radius_mm
    xx, yy, zz = x[:, 0], x[:, 1], x[:, 2]
    with np.errstate(invalid="ignore"):
        if tgt.shape == "plane":
            outward = -zz
        else:
            # |p - c| - R = (|p|^2 - 2 R z) / (|p - c| + R) for c = (0, 0, R): no cancellation at large R
            r2 = xx * xx + zz * zz if tgt.shape == "cylinder" else xx * xx + yy * yy + zz * zz
            num = r2 - 2.0 * Rt * zz
            outward = num / (np.sqrt(np.maximum(num + Rt * Rt, 0.0)) + Rt)
    # "outward" is the -z side at the plate centre; the camera is on it when its z < 0.
    return outward if cam[2] < 0 else -outward


# --------------------------------------------------------------------------- verdict


def judge(deviation_mm, mask, tolerance_mm: float, *, pixel_area_mm2, min_defect_area_mm2: float = MIN_DEFECT_AREA_MM2,
          max_outside_pct: float = MAX_OUTSIDE_PCT, edge_artefacts: EdgeArtefacts | None = None) -> Judgement:
    """Deviation statistics and the pass/fail verdict of a plate.

    Parameters
    ----------
    deviation_mm : (H, W) array_like of float
        Signed deviation, mm (from :func:`deviation_map`); NaN pixels are not judged.
    mask : (H, W) bool
        Measured pixels.
    tolerance_mm : float
        Allowed ``|deviation|``, mm, > 0.
    pixel_area_mm2 : float or (H, W) array_like of float
        Surface area one pixel covers, mm^2 (one value, or per pixel).
    min_defect_area_mm2 : float
        Smallest connected out-of-tolerance region that fails the plate, mm^2 (default 100 mm^2).
    max_outside_pct : float
        Largest share of the judged area allowed out of tolerance in total, percent (default 1 %).
    edge_artefacts : EdgeArtefacts, optional
        Leave out-of-tolerance regions that are segmentation artefacts at the plate's edge (see
        :class:`EdgeArtefacts`) out of the verdict and the statistics, each listed in
        ``Judgement.excluded`` with its reason. None (default): every region is judged.

    Returns
    -------
    Judgement

    Raises
    ------
    ValueError
        Bad shapes, non-positive tolerance or areas, or no pixel with a finite deviation in the mask.

    Notes
    -----
    Rule: the plate **fails** when some 8-connected region of pixels with ``|deviation| > tolerance_mm``
    covers at least ``min_defect_area_mm2``, or when the out-of-tolerance pixels together cover more than
    ``max_outside_pct`` of the judged area; otherwise it passes. So isolated noisy pixels do not fail a
    good plate, while a real local defect (a dent, a kink) or a plate wrong all over does. Statistics are
    over the judged pixels (mask and finite deviation); ``within_tolerance_pct`` is area-weighted.
    """
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if dev.ndim != 2:
        raise ValueError(f"deviation_mm: expected shape (H, W), got {dev.shape}")
    m = np.asarray(mask)
    if m.dtype != np.bool_ or m.shape != dev.shape:
        raise ValueError(f"mask: expected a bool array of shape {dev.shape}, got {m.dtype} {m.shape}")
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"tolerance_mm: expected a positive number of mm, got {tolerance_mm}")
    if not (math.isfinite(min_defect_area_mm2) and min_defect_area_mm2 > 0):
        raise ValueError(f"min_defect_area_mm2: expected a positive area in mm^2, got {min_defect_area_mm2}")
    if not (math.isfinite(max_outside_pct) and 0 <= max_outside_pct <= 100):
        raise ValueError(f"max_outside_pct: expected a percentage in [0, 100], got {max_outside_pct}")
    area = np.asarray(pixel_area_mm2, dtype=np.float64)
    if area.ndim == 0:
        if not (math.isfinite(float(area)) and area > 0):
            raise ValueError(f"pixel_area_mm2: expected a positive area in mm^2, got {float(area)}")
    elif area.shape != dev.shape:
        raise ValueError(f"pixel_area_mm2: expected a number or shape {dev.shape}, got shape {area.shape}")
    judged = m & np.isfinite(dev)
    excluded: tuple[ExcludedRegion, ...] = ()
    if edge_artefacts is not None:
        if not isinstance(edge_artefacts, EdgeArtefacts):
            raise TypeError(f"edge_artefacts: expected an EdgeArtefacts or None, got {type(edge_artefacts).__name__}")
        if edge_artefacts.step_mm.shape != dev.shape:
            raise ValueError(
                f"edge_artefacts.step_mm: expected shape {dev.shape} to match deviation_mm, got {edge_artefacts.step_mm.shape}"
            )
        left_out, excluded = _edge_artefacts(dev, m, judged, tolerance_mm, area, edge_artefacts)
        judged &= ~left_out
    n = int(np.count_nonzero(judged))
    if n == 0:
        raise ValueError("deviation_mm: expected finite deviations inside the mask, got none")
    area_judged = area[judged] if area.ndim == 2 else None
    if area_judged is not None and not np.all(np.isfinite(area_judged) & (area_judged > 0)):
        raise ValueError("pixel_area_mm2: expected positive finite areas at every judged pixel")

    a = np.abs(dev[judged])
    rms = float(np.sqrt(np.mean(a * a)))
    max_abs = float(a.max())
    p95 = float(np.percentile(a, 95))
    w = np.full(n, float(area)) if area.ndim == 0 else area_judged
    outside = a > tolerance_mm
    total_area = float(w.sum())
    outside_area = float(w[outside].sum())
    within_pct = 100.0 * (1.0 - outside_area / total_area)

    defects: list[DefectRegion] = []
    if outside.any():
        out_map = np.zeros(dev.shape, dtype=bool)
        out_map[judged] = outside
        labels, n_lab = ndimage.label(out_map, structure=np.ones((3, 3), dtype=bool))
        rows, cols = np.nonzero(out_map)  # few pixels: per-region sums by bincount over them only
        lab = labels[rows, cols]
        px_area = np.full(lab.size, float(area)) if area.ndim == 0 else area[rows, cols]
        reg_area = np.bincount(lab, weights=px_area, minlength=n_lab + 1)
        reg_count = np.bincount(lab, minlength=n_lab + 1)
        reg_row = np.bincount(lab, weights=rows, minlength=n_lab + 1)
        reg_col = np.bincount(lab, weights=cols, minlength=n_lab + 1)
        vals = dev[rows, cols]
        for k in np.nonzero(reg_area >= min_defect_area_mm2)[0]:
            if k == 0:
                continue
            v = vals[lab == k]
            peak = float(v[np.argmax(np.abs(v))])
            defects.append(DefectRegion(centroid_px=(float(reg_col[k] / reg_count[k]), float(reg_row[k] / reg_count[k])),
                                        area_mm2=float(reg_area[k]), peak_deviation_mm=peak, n_pixels=int(reg_count[k])))
        defects.sort(key=lambda d: -d.area_mm2)
    reasons = []
    if defects:
        reasons.append(f"{len(defects)} region(s) out of the {tolerance_mm:g} mm tolerance over "
                       f"{min_defect_area_mm2:g} mm^2 (largest {defects[0].area_mm2:.0f} mm^2)")
    if 100.0 - within_pct > max_outside_pct:
        reasons.append(f"{100.0 - within_pct:.2f} % of the area out of tolerance (over {max_outside_pct:g} %)")
    return Judgement(rms_mm=rms, max_abs_mm=max_abs, p95_mm=p95, within_tolerance_pct=within_pct,
                     verdict="fail" if reasons else "pass", defects=tuple(defects), outside_area_mm2=outside_area,
                     n_pixels=n, reasons=tuple(reasons), excluded=excluded)


def _edge_artefacts(dev: np.ndarray, mask: np.ndarray, judged: np.ndarray, tolerance_mm: float, area: np.ndarray,
                    rule: EdgeArtefacts) -> tuple[np.ndarray, tuple[ExcludedRegion, ...]]:
    """The pixels of out-of-tolerance regions that are edge artefacts under ``rule``, and those regions."""
    out_map = judged & (np.abs(np.where(judged, dev, 0.0)) > tolerance_mm)
    if not out_map.any():
        return np.zeros_like(mask), ()
    # distance (px) to the mask's boundary; beyond the image frame counts as inside (the plate goes on)
    pad = int(math.ceil(rule.max_depth_px)) + 2
    framed = cv2.copyMakeBorder(mask.view(np.uint8), pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    depth_px = cv2.distanceTransform(framed, cv2.DIST_L2, 3)[pad:-pad, pad:-pad]
    labels, n_lab = ndimage.label(out_map, structure=np.ones((3, 3), dtype=bool))
    rows, cols = np.nonzero(out_map)
    lab = labels[rows, cols]
    d = depth_px[rows, cols]
    step = rule.step_mm[rows, cols]
    touches = np.bincount(lab, weights=(d <= 1.5).astype(np.float64), minlength=n_lab + 1) > 0
    count = np.bincount(lab, minlength=n_lab + 1)
    shallow = np.bincount(lab, weights=(d <= rule.max_depth_px).astype(np.float64), minlength=n_lab + 1)
    thin = shallow >= rule.share * np.maximum(count, 1)
    # median of the step over the region's pixels where it is known (inf included) >= min_step_mm
    known = ~np.isnan(step)
    n_known = np.bincount(lab[known], minlength=n_lab + 1)
    n_deep = np.bincount(lab[known], weights=(step[known] >= rule.min_step_mm).astype(np.float64), minlength=n_lab + 1)
    floorish = (n_known > 0) & (n_deep > 0.5 * n_known)
    artefact = touches & thin & floorish
    artefact[0] = False
    if not artefact.any():
        return np.zeros_like(mask), ()
    px_area = np.full(lab.size, float(area)) if area.ndim == 0 else area[rows, cols]
    reg_area = np.bincount(lab, weights=px_area, minlength=n_lab + 1)
    reg_row = np.bincount(lab, weights=rows, minlength=n_lab + 1)
    reg_col = np.bincount(lab, weights=cols, minlength=n_lab + 1)
    vals = dev[rows, cols]
    regions = []
    for k in np.nonzero(artefact)[0]:
        v = vals[lab == k]
        steps = step[(lab == k) & known]
        typical = float(np.median(steps))
        beside = "dark surroundings without stereo depth" if math.isinf(typical) else f"surroundings {typical:.0f} mm behind"
        regions.append(ExcludedRegion(
            centroid_px=(float(reg_col[k] / count[k]), float(reg_row[k] / count[k])), area_mm2=float(reg_area[k]),
            peak_deviation_mm=float(v[np.argmax(np.abs(v))]), n_pixels=int(count[k]),
            reason=(f"edge artefact: along the plate's edge, within {rule.max_depth_px:g} px of it, beside "
                    f"{beside}: pixels that mix plate and surroundings, not a forming defect"),
        ))
    regions.sort(key=lambda r: -r.area_mm2)
    return artefact[labels] & out_map, tuple(regions)


# --------------------------------------------------------------------------- target surface for display


def target_surface(target, *, spacing_mm: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
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
    tgt = _check_target(target)
    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected a positive spacing in mm, got {spacing_mm}")
    if tgt.shape == "mesh":
        return np.asarray(tgt.mesh_vertices_mm, dtype=np.float64).copy(), np.asarray(tgt.mesh_faces, dtype=np.int64).copy()
    sx, sy = tgt.size_mm
    nx = max(2, int(math.ceil(sx / spacing_mm)) + 1)
    ny = max(2, int(math.ceil(sy / spacing_mm)) + 1)
    gx, gy = np.meshgrid(np.linspace(-sx / 2, sx / 2, nx), np.linspace(-sy / 2, sy / 2, ny))
    if tgt.shape == "plane":
        gz = np.zeros_like(gx)
    else:
        Rt = tgt.radius_mm
        r2 = gx * gx if tgt.shape == "cylinder" else gx * gx + gy * gy
        if np.any(r2 >= Rt * Rt):
            raise ValueError(f"target.radius_mm: a {tgt.shape} of radius {Rt} mm cannot span size_mm {tgt.size_mm}")
        gz = Rt - np.sqrt(Rt * Rt - r2)
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([b, d, c], axis=1)]).astype(np.int64)
    return vertices, faces
