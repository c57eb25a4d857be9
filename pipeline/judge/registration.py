"""Registration of the measured plate to its CAD target: the best-fit pose of the target on the plate.

Plane, cylinder and sphere targets are fitted analytically (:mod:`pipeline.judge.fits`); a mesh target
by ICP then point-to-surface refinement on its height grid (:class:`pipeline.judge.target_geometry.MeshGrid`).
The target frame is described in :mod:`pipeline.judge.target_geometry`.

References
----------
.. [1] Besl, P. J., McKay, N. D., "A method for registration of 3-D shapes", IEEE TPAMI 14(2), 1992 (ICP).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipeline.io import Target
from pipeline.judge.area import pixel_area_mm2
from pipeline.judge.fits import (
    MAX_FIT_POINTS,
    check_grid,
    fit_curved,
    fit_cylinder,
    fit_sphere,
    grid_sample,
    pca_frame,
)
from pipeline.judge.target_geometry import MeshGrid, check_target, mesh_grid
from pipeline.solvers import robust_gauss_newton, robust_scale

#: ICP for mesh targets: measured points used for the coarse alignment.
ICP_POINTS = 2000
#: ICP for mesh targets: coarse starts (in-plane turns, normal either way) refined by ICP, best scored first.
ICP_STARTS = 4
#: The footprint's extent: these percentiles of the plate's area along each in-surface axis (a rail's
#: stub past the edge, a few stray pixels, do not move it), from a histogram of bins this wide (mm).
FOOTPRINT_PERCENTILES = (0.5, 99.5)
FOOTPRINT_BIN_MM = 0.5
#: Moves of the frame to the footprint's middle (:func:`_footprint_frame`) at most, and the move (mm)
#: under which it stays.
FRAME_STEPS = 8
FRAME_STEP_TOL_MM = 0.1


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


def _in_plane_x(
    points: np.ndarray, z: np.ndarray, size_mm: tuple[float, float] | list[float]
) -> np.ndarray:
    """Target x axis in the plane normal to ``z``: along the side of the measured footprint's
    minimum-area rectangle that matches ``size_mm[0]`` (a square: the side nearer the camera's x),
    with ``x_cam >= 0``. The footprint's outline, unlike its principal direction, stays put when the
    plate is square or the camera sees one side with more pixels."""
    e1 = np.cross(z, [0.0, 1.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(z, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z, e1)
    uv = np.stack([points @ e1, points @ e2], axis=1).astype(np.float32)
    (_, _), (w, h), angle = cv2.minAreaRect(uv)
    t = np.deg2rad(angle)
    sides = [np.cos(t) * e1 + np.sin(t) * e2, -np.sin(t) * e1 + np.cos(t) * e2]
    lengths = [w, h]
    long_first = size_mm[0] >= size_mm[1]
    if abs(w - h) <= 0.05 * max(w, h) or abs(size_mm[0] - size_mm[1]) <= 0.05 * max(size_mm):
        x = max(sides, key=lambda d: abs(d[0]))  # square: the side nearer the camera's x
    else:
        i_long = int(np.argmax(lengths))
        x = sides[i_long] if long_first else sides[1 - i_long]
    facing: np.ndarray = -x if x[0] < 0 else x
    return facing


# --------------------------------------------------------------------------- registration


def fitted_target_radius(
    points_mm: npt.ArrayLike, mask: npt.ArrayLike, target: Target
) -> float | None:
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


def register_to_target(
    points_mm: npt.ArrayLike, mask: npt.ArrayLike, target: Target
) -> Registration:
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
        ``T_cam_target`` maps target-frame points into the camera frame (the frame: :mod:`pipeline.judge.target_geometry`).

    Raises
    ------
    ValueError, TypeError
        Bad grid, mask or target.

    Notes
    -----
    Plane, cylinder, sphere: a robust geometric fit of the shape with the target's radius fixed, started
    from the radius-free fit (its curvature picks convex or concave when it is at least half the target's;
    otherwise both are tried and the lower cost wins); the in-surface position is the measured plate's
    footprint's centre (the middle of its extent along the target's axes, not the pixels' centroid, which
    leans to the side nearer the camera) and the in-plane x axis its principal direction (these two do
    not change the deviation of a rotationally or translationally symmetric target). Mesh: the mesh is rasterised to a height grid over
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
    if tgt.shape == "plane":
        n, p0, _, _, rms, _ = fit_curved(
            sample, cylinder=False, radius_mm=None, max_points=MAX_FIT_POINTS, curvature_per_mm=0.0
        )
        fitted: tuple[np.ndarray, ...] = (n, p0)
        convex: bool | None = None
        k_free: float | None = None
    elif tgt.shape == "cylinder":
        cyl = fit_cylinder(sample, radius_mm=tgt.radius_mm)
        fitted = (cyl.axis, cyl.point_on_axis_mm)
        rms, convex, k_free = cyl.rms_mm, cyl.convex_towards_camera, cyl.free_curvature_per_mm
    else:  # sphere
        sph = fit_sphere(sample, radius_mm=tgt.radius_mm)
        fitted = (sph.center_mm,)
        rms, convex, k_free = sph.rms_mm, sph.convex_towards_camera, sph.free_curvature_per_mm
    x, z, origin = _footprint_frame(tgt, fitted, sample)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    free_radius = (
        None
        if convex is None or k_free is None
        else (abs(1.0 / k_free) if k_free != 0 else math.inf)
    )
    return Registration(
        T_cam_target=_pose(R, origin),
        shape=tgt.shape,
        rms_mm=float(rms),
        convex_towards_camera=convex,
        fitted_radius_mm=free_radius,
    )


def _frame_at(
    tgt: Target, fitted: tuple[np.ndarray, ...], sample: np.ndarray, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target axes x, z and origin on the fitted plane / cylinder / sphere nearest ``centre``."""
    if tgt.shape == "plane":
        z, p0 = fitted  # the fit's normal points away from the camera
        origin = p0 + ((centre - p0) - ((centre - p0) @ z) * z)
        return _in_plane_x(sample, z, tgt.size_mm), z, origin
    if tgt.shape == "cylinder":
        a, c = fitted
        v = (centre - c) - ((centre - c) @ a) * a
        v /= np.linalg.norm(v)
        origin = c + ((centre - c) @ a) * a + tgt.radius_mm * v
        x = np.cross(a, -v)  # the axis's sign is the fit's: x points to the camera's +x
        return (-x if x[0] < 0 else x), -v, origin
    (c,) = fitted
    v = (centre - c) / np.linalg.norm(centre - c)
    return _in_plane_x(sample, -v, tgt.size_mm), -v, c + tgt.radius_mm * v


def _footprint_frame(
    tgt: Target, fitted: tuple[np.ndarray, ...], sample: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The target's axes x, z and origin at the middle of the plate's footprint on the fitted shape.

    Started at the pixels' centroid, which leans towards the side nearer the camera (more pixels per
    mm^2 there), then moved to the middle of the footprint's extent along the frame's in-surface axes
    (:func:`_footprint_centre`, the points weighted by the plate's area their pixels see) until it
    stays (:data:`FRAME_STEPS` at most). On a curved shape the extent is measured along the tangent
    plane at the origin, and a plate's arc projects symmetrically onto it only from the arc's middle:
    one step left a plate rolled 15 deg about its axis 18 mm off its middle (3000 mm wide at 3 m, its
    true points, 5 mm pixels), and the pixels' own percentiles a plate tilted 20 deg 9 mm off.
    """
    x, z, origin = _frame_at(tgt, fitted, sample, sample.mean(axis=0))
    weight = _pixel_area_weights(tgt, fitted, sample)
    for _ in range(FRAME_STEPS):
        centre = _footprint_centre(sample, weight, origin, x, np.cross(z, x))
        x, z, moved = _frame_at(tgt, fitted, sample, centre)
        step = float(np.linalg.norm(moved - origin))
        origin = moved
        if step < FRAME_STEP_TOL_MM:
            break
    return x, z, origin


def _pixel_area_weights(
    tgt: Target, fitted: tuple[np.ndarray, ...], sample: np.ndarray
) -> np.ndarray:
    """Each point's share of the plate's area (up to the constant ``fx fy``): the area its pixel sees
    (:func:`pipeline.judge.area.pixel_area_mm2`) with the fitted shape's normal at the point."""
    if tgt.shape == "plane":
        n = np.broadcast_to(fitted[0], sample.shape)
    elif tgt.shape == "cylinder":
        a, c = fitted
        r = sample - c
        n = r - np.outer(r @ a, a)
    else:
        n = sample - fitted[0]
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    z = sample[:, 2]
    weight: np.ndarray = pixel_area_mm2(z[None], n[None], (sample / z[:, None])[None], np.eye(3))[0]
    return weight


def _footprint_centre(
    sample: np.ndarray, weight: np.ndarray, origin: np.ndarray, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """The middle of the points' extent along ``x`` and ``y`` from ``origin``: the
    :data:`FOOTPRINT_PERCENTILES` of the plate's area (the points weighted by ``weight``), so that the
    side nearer the camera, with more pixels per mm^2, does not draw its percentile nearer its edge
    than the far side's."""
    d = sample - origin
    lo_x, hi_x = _area_percentiles(d @ x, weight)
    lo_y, hi_y = _area_percentiles(d @ y, weight)
    centre: np.ndarray = origin + 0.5 * (lo_x + hi_x) * x + 0.5 * (lo_y + hi_y) * y
    return centre


def _area_percentiles(values: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """The :data:`FOOTPRINT_PERCENTILES` of ``values`` (mm) weighted by ``weight``, from their weighted
    histogram in :data:`FOOTPRINT_BIN_MM` bins (interpolated within the bin)."""
    lo = float(values.min())
    bins = ((values - lo) / FOOTPRINT_BIN_MM).astype(np.int64)
    cum = np.cumsum(np.bincount(bins, weights=weight))
    edges = lo + FOOTPRINT_BIN_MM * np.arange(1, cum.size + 1)
    lo_q, hi_q = np.interp(
        np.asarray(FOOTPRINT_PERCENTILES) / 100.0 * cum[-1],
        np.concatenate([[0.0], cum]),
        np.concatenate([[lo], edges]),
    )
    return float(lo_q), float(hi_q)


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
    best: tuple[np.ndarray, float] | None = None
    # ICP from the four best starts: a saddle turned upside down and by 90 deg is nearly itself (R1 ~ R2), and
    # such near-symmetric poses can score better before ICP than the true one
    for _, T0 in scored[:ICP_STARTS]:
        T, _, cost = trimesh.registration.icp(  # type: ignore[no-untyped-call]  # trimesh is untyped
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
    if best is None:
        raise ValueError(f"target: no start pose for the mesh among {len(scored)}")
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
    residuals: np.ndarray = (q[:, 2] - h) * s
    return residuals


def _refine_mesh_pose(T0: np.ndarray, pts: np.ndarray, grid: MeshGrid) -> np.ndarray:
    """Robust Gauss-Newton on point-to-surface distances over a small rotation (about the points' centroid)
    and translation. A cylinder or sphere can slide along itself at no cost, which could carry the plate off
    the mesh: two weak rows (0.01 per mm and point) hold the centroid's in-plane position from the ICP."""
    x0 = pts @ T0[:3, :3].T + T0[:3, 3]
    centre = x0.mean(axis=0)
    hold = 1e-2 * math.sqrt(pts.shape[0])

    def pose(p: np.ndarray) -> np.ndarray:
        Rs = Rotation.from_rotvec(p[:3]).as_matrix()
        R = Rs @ T0[:3, :3]
        t = Rs @ (T0[:3, 3] - centre) + centre + p[3:]
        return _pose(R, t)

    def fun(p: np.ndarray) -> np.ndarray:
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


def pixel_in_target_frame(
    points_mm: np.ndarray,
    mask: np.ndarray,
    pixel: tuple[float, float],
    T_cam_target: np.ndarray,
) -> tuple[float, float] | None:
    """``(x, y)`` in the target's frame, mm, of the measured point at ``pixel`` ``(u, v)``.

    The point is the one of the nearest pixel on ``mask`` with a finite position (a region's
    centroid may fall just off the plate, in an opening); None when the mask holds no point.
    """
    valid = mask & np.isfinite(points_mm).all(axis=-1)
    rows, cols = np.nonzero(valid)
    if rows.size == 0:
        return None
    u, v = pixel
    k = int(np.argmin((cols - u) ** 2 + (rows - v) ** 2))
    T = np.asarray(T_cam_target, dtype=np.float64)
    x = T[:3, :3].T @ (points_mm[rows[k], cols[k]] - T[:3, 3])
    return float(x[0]), float(x[1])
