"""Synthetic surfaces for the pipeline's tests and benchmarks: analytic plates seen by a pinhole camera,
and an independent least-squares integration to check the solver against.

Plates for the curvature and deviation stages: a height field ``h(x_p, y_p)`` in a plate frame (z_p away
from the camera) posed tilted in front of a pinhole camera at ~3000 mm; every pixel's ray is intersected
with the surface (Newton along the ray), so the points form a real camera grid (:func:`plate_grid`).
Plates for the integration: ray-traced normals, mask and depth (:func:`render_cylinder`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation

#: Tilt of the plate (Euler xyz, deg) relative to facing the camera: off-axis and rotated in-plane.
TILT_DEG = (8.0, -5.0, 20.0)


def plate_grid(
    height,
    *,
    shape=(128, 160),
    size_mm=(3000.0, 3000.0),
    distance_mm=3000.0,
    tilt_deg=TILT_DEG,
    noise_mm=0.0,
    rng=None,
):
    """Ray-cast a plate ``z_p = height(x_p, y_p)`` (mm, z_p away from the camera) into a camera grid.

    Returns
    -------
    points : (H, W, 3) float64, left-camera frame, mm; NaN outside the plate.
    mask : (H, W) bool, pixels whose ray meets the plate inside ``|x_p| <= size/2``, ``|y_p| <= size/2``.
    xy : (H, W, 2) float64, plate-frame (x_p, y_p) of each pixel's hit, mm.
    R_cam_plate : (3, 3) float64; the plate centre is at ``(30, -20, distance_mm)``.
    """
    H, W = shape
    f = (W / 2) * distance_mm / (0.6 * max(size_mm))  # the plate fills ~5/6 of the width
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    R = Rotation.from_euler("xyz", tilt_deg, degrees=True).as_matrix()
    t = np.array([30.0, -20.0, distance_mm])
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    n = R[:, 2]
    s = (t @ n) / (rays @ n)  # start on the plane z_p = 0

    def g(s):
        p = (s[..., None] * rays - t) @ R
        with np.errstate(invalid="ignore"):
            return p[..., 2] - height(p[..., 0], p[..., 1]), p

    for _ in range(50):
        g0, _ = g(s)
        if np.nanmax(np.abs(g0)) < 1e-10:
            break
        g1, _ = g(s + 1e-3)
        s = s - g0 / ((g1 - g0) / 1e-3)
    g0, p = g(s)
    mask = (
        (np.abs(p[..., 0]) <= size_mm[0] / 2)
        & (np.abs(p[..., 1]) <= size_mm[1] / 2)
        & (np.abs(g0) < 1e-6)
    )
    if noise_mm:
        s = s + rng.normal(0.0, noise_mm, s.shape) / np.linalg.norm(rays, axis=-1)
    points = s[..., None] * rays
    points[~mask] = np.nan
    return points, mask, p[..., :2], R


def cylinder(R, sign=1):
    """Cylinder with its axis along y_p; sign +1 convex towards the camera (centre behind the plate)."""
    return lambda x, y: sign * (R - np.sqrt(R * R - x * x))


def sphere(R, sign=1):
    return lambda x, y: sign * (R - np.sqrt(R * R - x * x - y * y))


def saddle(R1, R2):
    """Convex towards the camera along x_p (radius R1), concave along y_p (radius R2)."""
    return lambda x, y: (R1 - np.sqrt(R1 * R1 - x * x)) - (R2 - np.sqrt(R2 * R2 - y * y))


def dented(height, depth_mm=6.0, radius_mm=100.0, at=(300.0, -200.0)):
    """Adds a smooth dent ``depth (1 - r^2/rho^2)^3`` pushed away from the camera."""

    def h(x, y):
        q = ((x - at[0]) ** 2 + (y - at[1]) ** 2) / radius_mm**2
        return height(x, y) + depth_mm * np.where(q < 1, 1 - q, 0.0) ** 3

    return h


# ------------------------------------------------------------------------------ integration


def rotation_xy(ax_rad: float, ay_rad: float) -> np.ndarray:
    """R = Rx(ax) @ Ry(ay)."""
    cx, sx, cy, sy = np.cos(ax_rad), np.sin(ax_rad), np.cos(ay_rad), np.sin(ay_rad)
    rx = np.array([[1.0, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1.0, 0], [-sy, 0, cy]])
    return rx @ ry


def plate_camera(width: int, height: int, f_px: float) -> np.ndarray:
    """K with fx != fy and a principal point off the centre."""
    return np.array(
        [[f_px, 0.0, width / 2 + 3.3], [0.0, 1.013 * f_px, height / 2 - 2.1], [0.0, 0.0, 1.0]]
    )


def render_cylinder(
    K,
    hw,
    *,
    radius_mm=5000.0,
    plate_mm=(3000.0, 3000.0),
    distance_mm=3000.0,
    tilt_rad=(0.05, 0.08),
    convex=False,
):
    """Ray-trace a cylindrical plate (axis along the plate's second axis).

    The plate frame is the camera frame at zero tilt, its origin on the surface at the plate centre,
    ``distance_mm`` in front of the camera: ``X_cam = R_cam_plate X_plate + (0, 0, distance_mm)``.

    Returns
    -------
    normals : (H, W, 3) float64, unit, towards the camera; mask : (H, W) bool (the plate);
    depth_mm : (H, W) float64, z of the hit point, NaN off the plate.
    """
    h, w = hw
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    r_cam_plate = rotation_xy(*tilt_rad)
    s = -1.0 if convex else 1.0  # axis behind (concave towards camera) or in front of the plate
    a = rays @ r_cam_plate  # ray directions in the plate frame
    c = r_cam_plate.T @ np.array([0.0, 0.0, distance_mm])  # X_plate = lam * a - c
    cz = c[2] + s * radius_mm
    qa = a[..., 0] ** 2 + a[..., 2] ** 2
    qb = -2.0 * (a[..., 0] * c[0] + a[..., 2] * cz)
    qc = c[0] ** 2 + cz**2 - radius_mm**2
    disc = qb * qb - 4.0 * qa * qc
    root = np.sqrt(np.maximum(disc, 0.0))
    big = -0.5 * (qb + np.sign(qb) * root)
    lam1, lam2 = big / qa, qc / big
    near1 = np.abs(lam1 * a[..., 2] - c[2]) < np.abs(lam2 * a[..., 2] - c[2])
    lam = np.where(near1, lam1, lam2)  # the sheet through the plate origin
    xp = lam[..., None] * a - c
    grad = np.stack([xp[..., 0], np.zeros_like(lam), xp[..., 2] - s * radius_mm], -1)
    n = grad @ r_cam_plate.T
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n *= -np.sign(np.sum(n * rays, -1))[..., None]
    mask = (
        (disc > 0)
        & (np.abs(xp[..., 0]) <= plate_mm[0] / 2)
        & (np.abs(xp[..., 1]) <= plate_mm[1] / 2)
    )
    return n, mask, np.where(mask, lam * rays[..., 2], np.nan)


def sparse_least_squares(n, mask, K, log_prior=None, weight=0.0):
    """Independent reference: the equations written out as a sparse matrix, solved directly."""
    h, w = mask.shape
    kinv = np.linalg.inv(K)
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ kinv.T
    nr = np.sum(n * rays, -1)
    gu = -(n @ kinv[:, 0]) / nr
    gv = -(n @ kinv[:, 1]) / nr
    index = -np.ones((h, w), int)
    index[mask] = np.arange(mask.sum())
    rows, cols, vals, rhs = [], [], [], []
    eq = 0
    for a_sl, b_sl, g in (
        ((slice(None), slice(0, -1)), (slice(None), slice(1, None)), gu),
        ((slice(0, -1), slice(None)), (slice(1, None), slice(None)), gv),
    ):
        both = mask[a_sl] & mask[b_sl]
        ia, ib = index[a_sl][both], index[b_sl][both]
        m = ia.size
        rows += [np.arange(eq, eq + m)] * 2
        cols += [ib, ia]
        vals += [np.ones(m), -np.ones(m)]
        rhs.append(0.5 * (g[a_sl][both] + g[b_sl][both]))
        eq += m
    if log_prior is not None:
        known = mask & np.isfinite(log_prior)
        m = int(known.sum())
        rows.append(np.arange(eq, eq + m))
        cols.append(index[known])
        vals.append(np.full(m, np.sqrt(weight)))
        rhs.append(np.sqrt(weight) * log_prior[known])
        eq += m
    a = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(eq, int(mask.sum())),
    )
    x = scipy.sparse.linalg.spsolve((a.T @ a).tocsc(), a.T @ np.concatenate(rhs))
    out = np.full((h, w), np.nan)
    out[mask] = x
    return out
