"""Near-field photometric normals: point lights (LEDs) whose direction and irradiance vary over the plate.

Under a point light at P the image of a surface point X is

    I_k = rho * e_k * a_k(X) * max(0, n . l_k(X)),   l_k(X) = (P_k - X) / |P_k - X|

(:mod:`pipeline.lights`). Given X -- from the current estimate of the surface -- every pixel is
again a linear problem in b = rho n, with its own light vectors: the samples are divided by
``a_k(X)`` and fitted against ``l_k(X)`` with the same per-pixel estimators as distant lights
(:func:`pipeline.normals.estimate_normals`'s robust fit, or plain least squares). The surface
itself comes from integrating these normals, so the two are solved alternately
(:func:`pipeline.run.inspect` starts from the stereo depth and iterates until the depth stops
moving; Queau et al. 2018, section 4, and Mecca et al. 2014 solve the same coupled problem).

Distant lights may be mixed in: their direction is the same everywhere and ``a_k = 1``.

References
----------
.. [1] Y. Queau, B. Durix, T. Wu, D. Cremers, F. Lauze, J.-D. Durou, "LED-based photometric
   stereo: modeling, calibration and numerical solution", J. Math. Imaging Vis. 60, 2018.
.. [2] R. Mecca, A. Wetzler, A. M. Bruckstein, R. Kimmel, "Near field photometric stereo with
   point light sources", SIAM J. Imaging Sci. 7(4), 2014.
"""

from __future__ import annotations

import numba
import numpy as np

from .lights import REFERENCE_DISTANCE_MM, Lights
from .normals import (
    _BLOCK_SAMPLES,
    _F32_ZERO,
    _FASTMATH,
    _OUTSIDE,
    METHODS,
    NormalField,
    _field_from_fit,
    _load_block,
    _robust_block,
    _robust_params,
    _sorting_network,
)

#: The robust fit's parameters that make it plain least squares over the usable samples: no shadow
#: level, no highlight trim, no re-selection (see pipeline.normals._robust_params for the order).
_PLAIN_PARAMS = np.array([0.0, 0.9, 0.0, -np.inf, np.inf, 0.0, 0.0, np.inf])

#: A sample whose attenuation a_k(X) is below this fraction of the pixel's largest one is left out
#: (outside the LED's beam: its value is noise divided by almost nothing).
MIN_RELATIVE_ATTENUATION = 0.02


def estimate_normals_near(
    images: np.ndarray,
    lights: Lights,
    depth_mm: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    method: str = "robust",
    min_samples: int = 3,
) -> NormalField:
    """Estimate unit normals and albedo per pixel under point (and distant) lights.

    Parameters
    ----------
    images : (N, H, W) float32
        Left-camera images on the undistorted grid, dark-subtracted and divided by each light's
        intensity ``e_k`` (as :func:`pipeline.preprocess.preprocess` gives them), so that
        ``I_k = rho a_k(X) max(0, n . l_k(X))``.
    lights : Lights
        The N lights, left-camera frame, mm.
    depth_mm : (H, W) float
        Current estimate of the surface: depth along the optical axis (mm) of the point each
        pixel sees (``X = depth * K^-1 (u, v, 1)``); finite and > 0 on ``mask``.
    K : (3, 3) float
        Intrinsics of the undistorted left grid, pixels.
    mask : (H, W) bool
        Pixels to estimate.
    valid : (N, H, W) bool, optional
        Usable samples (False: saturated, shadowed); None = all.
    method : {"robust", "lstsq"}
        The per-pixel estimator (see :func:`pipeline.normals.estimate_normals`): the robust fit
        (shadows, highlights and outliers rejected), or least squares over the usable samples.
        The specular stage of distant lights is not applied.
    min_samples : int
        Fewer usable samples than this: a hole, filled from the neighbours.

    Returns
    -------
    NormalField
        ``normals`` (H, W, 3) float32, left-camera frame, towards the camera; ``albedo`` rho in
        the units of ``images``.

    Raises
    ------
    ValueError
        Bad shapes, a depth that is not finite and positive on the mask, unknown method.
    CaptureError
        Not one pixel gave a normal.

    Notes
    -----
    Samples of a pixel whose attenuation is below MIN_RELATIVE_ATTENUATION of its largest one
    are left out. The light vectors are computed per pixel inside the compiled kernel, a block of
    a row at a time; nothing of size (N, H, W) beyond the inputs is allocated.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    images = np.asarray(images)
    if images.ndim != 3 or images.dtype != np.float32:
        raise ValueError(f"images: expected a float32 array of shape (N, H, W), got {images.dtype} {images.shape}")
    n, h, w = images.shape
    if not isinstance(lights, Lights) or lights.n != n:
        raise ValueError(f"lights: expected Lights for {n} images, got {getattr(lights, 'n', type(lights).__name__)}")
    mask = np.asarray(mask)
    if mask.shape != (h, w) or mask.dtype != bool:
        raise ValueError(f"mask: expected a bool array of shape ({h}, {w}), got {mask.dtype} {mask.shape}")
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.shape != (h, w):
        raise ValueError(f"depth_mm: expected shape ({h}, {w}), got {depth.shape}")
    on = depth[mask]
    if not (np.all(np.isfinite(on)) and np.all(on > 0)):
        raise ValueError("depth_mm: expected finite depths > 0 mm on the mask")
    if isinstance(min_samples, bool) or not isinstance(min_samples, (int, np.integer)) or not 3 <= min_samples <= n:
        raise ValueError(f"min_samples: expected an integer in [3, {n}], got {min_samples!r}")
    if valid is not None:
        valid = np.asarray(valid)
        if valid.shape != images.shape or valid.dtype != bool:
            raise ValueError(f"valid: expected a bool array of shape {images.shape}, got {valid.dtype} {valid.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"K: expected a finite (3, 3) matrix, got shape {K.shape}")

    geometry, axes, kind = lights.kernel_arrays()
    use_valid = valid is not None
    v = valid if use_valid else np.ones((1, 1, 1), dtype=bool)
    b = np.empty((3, h, w), dtype=np.float32)
    status = np.empty((h, w), dtype=np.int8)
    params = _robust_params() if method == "robust" else _PLAIN_PARAMS
    _near_kernel(
        np.ascontiguousarray(images), np.ascontiguousarray(v), use_valid, np.ascontiguousarray(mask),
        np.ascontiguousarray(depth), np.linalg.inv(K), geometry, axes, kind, lights.mu.astype(np.float64),
        int(min_samples), params, _sorting_network(n), b, status,
    )
    return _field_from_fit(b, status, mask, specular=None)


@numba.njit(parallel=True, cache=True)
def _near_kernel(images, valid, use_valid, mask, depth, kinv, geometry, axes, kind, mu, min_samples, params, pairs,
                 b_out, status):
    n, h, w = images.shape
    width = max(16, _BLOCK_SAMPLES // n)
    per_row = (w + width - 1) // width
    for t in numba.prange(h * per_row):
        i = t // per_row
        j0 = (t % per_row) * width
        j1 = min(j0 + width, w)
        if not mask[i, j0:j1].any():
            status[i, j0:j1] = _OUTSIDE
            continue
        samples, usable, m, finite = _load_block(images, valid, use_valid, mask, i, j0, j1)
        L = np.empty((n, 3, j1 - j0), np.float32)
        _light_block(depth, kinv, geometry, axes, kind, mu, i, j0, samples, usable, m, L)
        _robust_block(samples, usable, m, finite, mask, L, min_samples, params, pairs, b_out, status, i, j0)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _light_block(depth, kinv, geometry, axes, kind, mu, i, j0, samples, usable, m, L):
    """Per pixel (i, j0 + j): unit light vectors into L (N, 3, w) and the samples divided by the
    attenuation in place; samples of too little attenuation become unusable (``m`` counts them out)."""
    n, w = samples.shape
    att = np.empty(n)
    ref2 = REFERENCE_DISTANCE_MM * REFERENCE_DISTANCE_MM
    for j in range(w):
        z = depth[i, j0 + j]
        if not (z > 0.0):
            continue  # outside the mask: no samples are usable there
        u = float(j0 + j)
        v = float(i)
        x0 = z * (kinv[0, 0] * u + kinv[0, 1] * v + kinv[0, 2])
        x1 = z * (kinv[1, 0] * u + kinv[1, 1] * v + kinv[1, 2])
        x2 = z * (kinv[2, 0] * u + kinv[2, 1] * v + kinv[2, 2])
        a_max = 0.0
        for k in range(n):
            if kind[k] == 1:
                d0, d1, d2 = geometry[k, 0] - x0, geometry[k, 1] - x1, geometry[k, 2] - x2
                dist2 = d0 * d0 + d1 * d1 + d2 * d2
                dist = np.sqrt(dist2)
                a = ref2 / dist2
                if mu[k] > 0.0:
                    cos = -(d0 * axes[k, 0] + d1 * axes[k, 1] + d2 * axes[k, 2]) / dist
                    a *= max(cos, 0.0) ** mu[k]
                L[k, 0, j], L[k, 1, j], L[k, 2, j] = d0 / dist, d1 / dist, d2 / dist
            else:
                a = 1.0
                L[k, 0, j], L[k, 1, j], L[k, 2, j] = geometry[k, 0], geometry[k, 1], geometry[k, 2]
            att[k] = a
            a_max = max(a_max, a)
        for k in range(n):
            if att[k] > MIN_RELATIVE_ATTENUATION * a_max:
                samples[k, j] = np.float32(samples[k, j] / att[k])
            elif usable[k, j] > 0:
                usable[k, j] = _F32_ZERO
                samples[k, j] = _F32_ZERO
                m[j] -= 1
