"""Photometric normals under distant lights: :func:`estimate_normals`, the estimators' one entry point."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from pipeline.camera import check_camera_matrix
from pipeline.formats import UNIT_TOLERANCE
from pipeline.surface.normals.field import NormalField, field_from_fit
from pipeline.surface.normals.lstsq import lstsq
from pipeline.surface.normals.robust import robust
from pipeline.surface.normals.solve3 import MIN_FIT
from pipeline.surface.normals.specular import specular

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

METHODS = ("robust", "lstsq")


def estimate_normals(
    images: np.ndarray,
    light_dirs: np.ndarray,
    mask: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    method: str = "robust",
    min_samples: int = 3,
    view_dirs: np.ndarray | None = None,
    camera_matrix: np.ndarray | None = None,
) -> NormalField:
    """Estimate unit normals and albedo per pixel from N images under N distant lights.

    Parameters
    ----------
    images : (N, H, W) float32
        Left-camera images, dark-subtracted, undistorted and divided by each light's
        intensity, so that I_k = rho * max(0, n . l_k) + noise. Must be finite where used.
    light_dirs : (N, 3) float
        Unit vectors (|l| within 1e-3 of 1) in the left-camera frame, from the surface
        towards light k; every light on the camera side (l_z < 0).
    mask : (H, W) bool
        Plate pixels to estimate.
    valid : (N, H, W) bool, optional
        Usable samples (False = saturated, shadowed or known bad); None = all usable.
        Unusable samples may hold any value, NaN included.
    method : {"robust", "lstsq"}
        ``"lstsq"``: Woodham's least squares for b = rho n over all valid samples. ``"robust"``:
        the same model on the samples left after rejecting shadows and highlights (see Notes).
    min_samples : int
        A pixel with fewer usable samples than this (>= 3) is a hole, filled from its neighbours.
    view_dirs : (3,) float, optional
        A distant (orthographic) camera: the unit vector from the surface towards it, left-camera
        frame (v_z < 0), e.g. (0, 0, -1). With ``method="robust"`` it switches on the specular
        stage (see Notes); ``method="lstsq"`` ignores it (the plain Lambertian baseline).
    camera_matrix : (3, 3) float, optional
        A pinhole camera instead (the undistorted grid's K): the view direction of pixel
        (u, v) is ``-normalize(K^-1 (u, v, 1))``, computed where the specular stage needs
        it. At most one of ``view_dirs`` and ``camera_matrix``; neither = no specular model.

    Returns
    -------
    NormalField

    Raises
    ------
    ValueError
        Bad shapes or dtypes, non-unit or non-finite lights, lights not on the camera side or not
        spanning 3D, unknown method, bad min_samples, non-finite images at used samples.
    CaptureError
        Not one mask pixel gave a normal (images dark, or inconsistent with the lights).

    Notes
    -----
    The estimators: least squares (:mod:`pipeline.surface.normals.lstsq`), robust (:mod:`pipeline.surface.normals.robust`)
    and the specular stage (:mod:`pipeline.surface.normals.specular`; its fit in ``NormalField.specular``).

    Orientation: with lights on the camera side (l_z < 0) and images consistent with them, every lit
    sample has n . l > 0, so b = rho n has n_z < 0 without any sign flip. An estimate that still has
    n_z >= 0 (noise, a black pixel with rho = 0) is a hole, never flipped.

    Holes (fewer than ``min_samples`` usable samples, a degenerate light set, rho = 0 or n_z >= 0)
    are filled from the estimated 4-neighbours (:func:`pipeline.surface.normals.fill.harmonic_fill`),
    flagged in ``filled`` and counted in ``n_filled``. A connected hole with no estimated pixel next
    to it is left out of ``mask`` and a ``RuntimeWarning`` says how many pixels that was.

    References
    ----------
    Woodham 1980 (see :mod:`pipeline.surface.normals`).
    """
    images, light_dirs, mask, valid = _check_inputs(
        images, light_dirs, mask, valid, method, min_samples
    )
    view_map = _view_map(view_dirs, camera_matrix)
    fitted = None
    if method == "lstsq":
        b, status = lstsq(images, light_dirs, mask, valid, min_samples)
    else:
        b, status = robust(images, light_dirs, mask, valid, min_samples)
        if view_map is not None:
            fitted = specular(images, valid, status, light_dirs, view_map, b)
    return field_from_fit(b, status, mask, specular=fitted)


def _check_inputs(
    images: npt.ArrayLike,
    light_dirs: npt.ArrayLike,
    mask: npt.ArrayLike | None,
    valid: npt.ArrayLike | None,
    method: str,
    min_samples: int,
) -> tuple[Arr, Arr, Arr, Arr | None]:
    """The inputs of :func:`estimate_normals` checked: (images float32, light_dirs float64, mask, valid)."""
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    images = np.asarray(images)
    if images.ndim != 3:
        raise ValueError(f"images: expected shape (N, H, W), got {images.shape}")
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(
            f"images: expected a float array (intensity-normalised), got dtype {images.dtype}"
        )
    n, h, w = images.shape
    light_dirs = np.asarray(light_dirs, dtype=np.float64)
    if light_dirs.shape != (n, 3):
        raise ValueError(
            f"light_dirs: expected shape ({n}, 3) to match {n} images, got {light_dirs.shape}"
        )
    if not np.all(np.isfinite(light_dirs)):
        raise ValueError("light_dirs: expected finite numbers, got NaN or inf")
    lengths = np.linalg.norm(light_dirs, axis=1)
    bad = np.flatnonzero(np.abs(lengths - 1.0) > UNIT_TOLERANCE)
    if bad.size:
        raise ValueError(
            f"light_dirs[{bad[0]}]: expected a unit vector, got length {lengths[bad[0]]:.4f}"
        )
    behind = np.flatnonzero(light_dirs[:, 2] >= 0)
    if behind.size:
        raise ValueError(
            f"light_dirs[{behind[0]}]: expected a light on the camera side (l_z < 0, OpenCV camera "
            f"frame, from surface to light), got {light_dirs[behind[0]].round(4).tolist()}"
        )
    if n < MIN_FIT or np.linalg.matrix_rank(light_dirs, tol=1e-6) < 3:
        raise ValueError(
            f"light_dirs: expected at least 3 directions spanning 3D, got {n} of rank "
            f"{np.linalg.matrix_rank(light_dirs, tol=1e-6)}"
        )
    if (
        isinstance(min_samples, bool)
        or not isinstance(min_samples, (int, np.integer))
        or not MIN_FIT <= min_samples <= n
    ):
        raise ValueError(
            f"min_samples: expected an integer in [{MIN_FIT}, {n}] (N images), got {min_samples!r}"
        )
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise ValueError(f"mask: expected shape ({h}, {w}) to match images, got {mask.shape}")
    if mask.dtype != bool:
        raise ValueError(f"mask: expected a bool array, got dtype {mask.dtype}")
    if valid is not None:
        valid = np.asarray(valid)
        if valid.shape != images.shape:
            raise ValueError(
                f"valid: expected shape {images.shape} to match images, got {valid.shape}"
            )
        if valid.dtype != bool:
            raise ValueError(f"valid: expected a bool array, got dtype {valid.dtype}")
    return images.astype(np.float32, copy=False), light_dirs, mask, valid


def _view_map(view_dirs: npt.ArrayLike | None, camera_matrix: npt.ArrayLike | None) -> Arr | None:
    """None, or A (3, 3) float64 with the view direction of pixel (u, v) = normalize(A (u, v, 1)).

    A distant camera v: A = [0 | 0 | v]; a pinhole camera K: A = -K^-1.
    """
    if view_dirs is not None and camera_matrix is not None:
        raise ValueError("view_dirs, camera_matrix: expected at most one of them, got both")
    if camera_matrix is not None:
        K = check_camera_matrix(camera_matrix, "camera_matrix")
        inverse: np.ndarray = -np.linalg.inv(K)
        return inverse
    if view_dirs is None:
        return None
    v = np.asarray(view_dirs)
    if v.shape != (3,):
        raise ValueError(
            f"view_dirs: expected shape (3,) (a distant camera; camera_matrix for a pinhole one), "
            f"got {v.shape}"
        )
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"view_dirs: expected a float array, got dtype {v.dtype}")
    if not np.all(np.isfinite(v)):
        raise ValueError("view_dirs: expected finite numbers, got NaN or inf")
    length = float(np.linalg.norm(v))
    if abs(length - 1.0) > UNIT_TOLERANCE:
        raise ValueError(f"view_dirs: expected a unit vector, got length {length:.4f}")
    if v[2] >= 0:
        raise ValueError(
            "view_dirs: expected a vector from the surface towards the camera (v_z < 0), got v_z >= 0"
        )
    A = np.zeros((3, 3))
    A[:, 2] = v
    return A
