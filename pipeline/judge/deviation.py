"""Signed deviation of the measured plate from its registered CAD target, per pixel.

Deviation sign
--------------
Positive where the measured surface lies on the side of the target that faces the cameras (the plate stands
proud of its target, towards the cameras), negative behind it. The camera-facing side is the side of the
target on which the left camera centre lies, taken at the plate centre (a plate seen whole by the camera has
the camera on one side of it everywhere).

The pose comes from :mod:`pipeline.judge.registration`, the target frame from :mod:`pipeline.judge.target_geometry`,
the verdict from the deviation map in :mod:`pipeline.judge.verdict`.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from pipeline.io import Target
from pipeline.judge.fits import check_grid
from pipeline.judge.registration import Registration
from pipeline.judge.target_geometry import check_target, mesh_grid
from pipeline.solvers import bounding_box


def _check_registration(registration: Registration) -> np.ndarray:
    """``registration.T_cam_target`` checked as a finite rigid (4, 4) transform."""
    if not isinstance(registration, Registration):
        raise TypeError(f"registration: expected a Registration, got {type(registration).__name__}")
    T = np.asarray(registration.T_cam_target, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(
            f"registration.T_cam_target: expected a finite (4, 4) matrix, got shape {T.shape}"
        )
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(
            "registration.T_cam_target: expected a rigid transform (rotation + translation)"
        )
    return T


def deviation_map(
    points_mm: npt.ArrayLike, mask: npt.ArrayLike, target: Target, registration: Registration
) -> np.ndarray:
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
    mesh (rasterised over its PCA plane at ``MESH_GRID_MM``, 10 mm, coarser for a mesh over 15 m;
    bilinear: :class:`pipeline.judge.target_geometry.MeshGrid`) times ``1/sqrt(1 + |grad h|^2)`` -- the normal
    distance to first order in the deviation.
    """
    tgt = check_target(target)
    T = _check_registration(registration)
    pts, m = check_grid(points_mm, mask, min_points=1)
    R, t = T[:3, :3], T[:3, 3]
    T_target_cam = np.hstack([R.T, (-R.T @ t)[:, None]])
    cam = T_target_cam[:, 3]  # camera centre in the target frame
    if tgt.shape != "mesh":
        # Analytic shapes: over the mask's bounding box (each pixel's value is its own), in bands of rows,
        # so the float64 temporaries stay in cache instead of allocating several (H, W, 3) arrays
        # (their page faults cost more than the arithmetic).
        dev = np.full(m.shape, np.nan, dtype=np.float32)
        box = bounding_box(m)
        if box is None:
            return dev
        rows, cols = box
        c0, c1 = cols.start, cols.stop
        band = max(1, _CHUNK // (c1 - c0))
        for r0 in range(rows.start, rows.stop, band):
            r1 = min(r0 + band, rows.stop)
            x = cv2.transform(pts[r0:r1, c0:c1], T_target_cam).reshape(-1, 3)
            dev[r0:r1, c0:c1] = _analytic_deviation(x, tgt, cam).reshape(r1 - r0, c1 - c0)
        dev[~m] = np.nan
        return dev
    # Mesh: camera frame -> plate coordinates of the mesh grid in one transform, in chunks as above.
    grid = mesh_grid(tgt)
    to_plate = grid.frame @ np.hstack(
        [T_target_cam[:, :3], (T_target_cam[:, 3] - grid.origin)[:, None]]
    )
    q_cam = grid.frame @ (cam - grid.origin)
    h0, _ = grid.sample(q_cam[None, :], filled=True)
    side = 1.0 if q_cam[2] > h0[0] else -1.0
    out = np.empty(m.size, dtype=np.float32)
    flat = pts.reshape(-1, 3)
    with np.errstate(invalid="ignore"):  # NaN points outside the mask
        for start in range(0, flat.shape[0], _MESH_CHUNK):
            q = cv2.transform(
                flat[start : start + _MESH_CHUNK].reshape(-1, 1, 3), to_plate
            ).reshape(-1, 3)
            h, slope = grid.sample(q)
            out[start : start + _MESH_CHUNK] = side * (q[:, 2] - h) * slope
    dev = out.reshape(m.shape)
    dev[~m] = np.nan
    return dev


_CHUNK = 1 << 16  # pixels per band of deviation_map's analytic shapes
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
            if Rt is None:
                raise ValueError(f"target.radius_mm: a {tgt.shape} needs its radius, got none")
            r2 = xx * xx + zz * zz if tgt.shape == "cylinder" else xx * xx + yy * yy + zz * zz
            num = r2 - 2.0 * Rt * zz
            outward = num / (np.sqrt(np.maximum(num + Rt * Rt, 0.0)) + Rt)
    # "outward" is the -z side at the plate centre; the camera is on it when its z < 0.
    return outward if cam[2] < 0 else -outward
