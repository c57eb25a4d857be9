"""Registration of the measured plate to its CAD target: the best-fit pose of the target on the plate.

Plane, cylinder and sphere targets are fitted analytically (:mod:`pipeline.surface_fits`); a mesh target
by ICP then point-to-surface refinement on its height grid (:class:`pipeline.target_geometry.MeshGrid`).
The target frame is described in :mod:`pipeline.target_geometry`.

References
----------
.. [1] Besl, P. J., McKay, N. D., "A method for registration of 3-D shapes", IEEE TPAMI 14(2), 1992 (ICP).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .io import Target
from .solvers import robust_gauss_newton, robust_scale
from .surface_fits import (
    MAX_FIT_POINTS,
    check_grid,
    fit_curved,
    fit_cylinder,
    fit_sphere,
    grid_sample,
    pca_frame,
)
from .target_geometry import MeshGrid, check_target, mesh_grid

#: ICP for mesh targets: measured points used for the coarse alignment.
ICP_POINTS = 2000
#: ICP for mesh targets: coarse starts (in-plane turns, normal either way) refined by ICP, best scored first.
ICP_STARTS = 4


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


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _in_plane_x(points: np.ndarray, z: np.ndarray, size_mm) -> np.ndarray:
    """Target x axis: the measured plate's in-plane principal direction matching ``size_mm``, ``x_cam >= 0``."""
    _, frame = pca_frame(points)
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
    tgt = check_target(target)
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
        ``T_cam_target`` maps target-frame points into the camera frame (the frame: :mod:`pipeline.target_geometry`).

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
    its own PCA plane; the measured PCA frame is matched to the mesh's under in-plane turns every 30 deg,
    with the plate's normal either way (24 starts, scored by the mean distance of the points to the
    grid's); the ICP_STARTS best are refined by point-to-point ICP (``trimesh.registration.icp``)
    against points of that grid, and the one of lowest cost by robust Gauss-Newton on the
    point-to-surface distances.
    """
    tgt = check_target(target)
    pts, m = check_grid(points_mm, mask, min_points=50)
    sample = grid_sample(pts, m, MAX_FIT_POINTS)
    if tgt.shape == "mesh":
        return _register_mesh(sample, tgt)
    centroid = sample.mean(axis=0)
    if tgt.shape == "plane":
        n, p0, _, _, rms, _ = fit_curved(
            sample, cylinder=False, radius_mm=None, max_points=MAX_FIT_POINTS, curvature_per_mm=0.0
        )
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
    return Registration(
        T_cam_target=_pose(R, origin),
        shape=tgt.shape,
        rms_mm=float(rms),
        convex_towards_camera=convex,
        fitted_radius_mm=free_radius,
    )


def _register_mesh(sample: np.ndarray, target: Target) -> Registration:
    import trimesh  # heavy import, only for mesh targets

    grid = mesh_grid(target)
    jj, ii = np.nonzero(np.isfinite(grid.height))
    keep = np.linspace(0, len(jj) - 1, min(len(jj), 50_000)).round().astype(np.int64)
    jj, ii = jj[keep], ii[keep]
    q_nodes = np.stack(
        [grid.x0 + ii * grid.step, grid.y0 + jj * grid.step, grid.height[jj, ii]], axis=1
    )
    target_pts = q_nodes @ grid.frame + grid.origin  # target frame

    c_s, frame_s = pca_frame(sample)
    icp_pts = sample[
        np.linspace(0, len(sample) - 1, min(len(sample), ICP_POINTS)).round().astype(np.int64)
    ]
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
        T, _, cost = trimesh.registration.icp(
            icp_pts,
            target_pts,
            initial=T0,
            threshold=1e-7,
            max_iterations=20,
            reflection=False,
            scale=False,
        )
        if best is None or cost < best[1]:
            best = (T, cost)
    T_target_cam = _refine_mesh_pose(best[0], sample, grid)
    rms = _mesh_rms(T_target_cam, sample, grid)
    return Registration(
        T_cam_target=np.linalg.inv(T_target_cam),
        shape="mesh",
        rms_mm=rms,
        convex_towards_camera=None,
    )


def _mesh_residuals(
    T_target_cam: np.ndarray, pts: np.ndarray, grid: MeshGrid, *, filled: bool
) -> np.ndarray:
    x_t = pts @ T_target_cam[:3, :3].T + T_target_cam[:3, 3]
    q = (x_t - grid.origin) @ grid.frame.T
    h, s = grid.sample(q, filled=filled)
    return (q[:, 2] - h) * s


def _refine_mesh_pose(T0: np.ndarray, pts: np.ndarray, grid: MeshGrid) -> np.ndarray:
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
    f_scale = max(3.0 * robust_scale(fun(p)), 0.05)
    p, _ = robust_gauss_newton(fun, p, steps, f_scale, rtol=1e-9)
    f_scale = max(3.0 * robust_scale(fun(p)), 0.01)
    p, _ = robust_gauss_newton(fun, p, steps, f_scale, rtol=1e-9)
    return pose(p)


def _mesh_rms(T_target_cam: np.ndarray, pts: np.ndarray, grid: MeshGrid) -> float:
    r = _mesh_residuals(T_target_cam, pts, grid, filled=False)
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else math.nan
