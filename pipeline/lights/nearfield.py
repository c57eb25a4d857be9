"""Near-field photometric normals: point lights (LEDs) whose direction and irradiance vary over the plate.

Under a point light at P the image of a surface point X is

    I_k = rho * e_k * a_k(X) * max(0, n . l_k(X)),   l_k(X) = (P_k - X) / |P_k - X|

(:mod:`pipeline.lights.model`). Given X -- from the current estimate of the surface -- every pixel is
again a linear problem in b = rho n, with its own light vectors: the samples are divided by
``a_k(X)`` and fitted against ``l_k(X)`` with the same per-pixel estimators as distant lights
(:func:`pipeline.surface.normals.estimate_normals`'s robust fit, or plain least squares). The surface
itself comes from integrating these normals, so the two are solved alternately
(:func:`pipeline.surface.reconstruct.near_field_surface` starts from the stereo depth and iterates until the
depth stops moving; Queau et al. 2018, section 4, and Mecca et al. 2014 solve the same coupled problem).

Distant lights may be mixed in: their direction is the same everywhere and ``a_k = 1``.

References
----------
.. [1] Y. Queau, B. Durix, T. Wu, D. Cremers, F. Lauze, J.-D. Durou, "LED-based photometric
   stereo: modeling, calibration and numerical solution", J. Math. Imaging Vis. 60, 2018.
.. [2] R. Mecca, A. Wetzler, A. M. Bruckstein, R. Kimmel, "Near field photometric stereo with
   point light sources", SIAM J. Imaging Sci. 7(4), 2014.
"""

from __future__ import annotations

import numpy as np

from pipeline.lights.model import Lights
from pipeline.surface.normals import METHODS, NormalField
from pipeline.surface.normals.field import field_from_fit
from pipeline.surface.normals.noise import image_noise
from pipeline.surface.normals.robust import robust_kernel, robust_params, sorting_network

#: The robust fit's parameters that make it plain least squares over the usable samples: no shadow
#: level, no highlight trim, no re-selection (see pipeline.surface.normals.robust.robust_params for the order).
_PLAIN_PARAMS = np.array([0.0, 0.9, 0.0, -np.inf, np.inf, 0.0, 0.0, np.inf, 0.0])

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
    noise: float | None = None,
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
        The per-pixel estimator (see :func:`pipeline.surface.normals.estimate_normals`): the robust fit
        (shadows, highlights and outliers rejected), or least squares over the usable samples.
        The specular stage of distant lights is not applied.
    min_samples : int
        Fewer usable samples than this: a hole, filled from the neighbours.

    noise : float, optional
        The images' noise (their units), the robust estimator's scale floor; default: measured here
        (:func:`pipeline.surface.normals.noise.image_noise`). The alternation of :mod:`pipeline.surface.reconstruct`
        measures it once for all its estimates.
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
    are left out. The light vectors are computed per pixel inside the compiled kernel
    (:func:`pipeline.lights.model.light_vectors_block`), a block of a row at a time; nothing of size
    (N, H, W) beyond the inputs is allocated.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    images = np.asarray(images)
    if images.ndim != 3 or images.dtype != np.float32:
        raise ValueError(
            f"images: expected a float32 array of shape (N, H, W), got {images.dtype} {images.shape}"
        )
    n, h, w = images.shape
    if not isinstance(lights, Lights) or lights.n != n:
        raise ValueError(
            f"lights: expected Lights for {n} images, got {getattr(lights, 'n', type(lights).__name__)}"
        )
    mask = np.asarray(mask)
    if mask.shape != (h, w) or mask.dtype != bool:
        raise ValueError(
            f"mask: expected a bool array of shape ({h}, {w}), got {mask.dtype} {mask.shape}"
        )
    depth = np.asarray(depth_mm, dtype=np.float64)
    if depth.shape != (h, w):
        raise ValueError(f"depth_mm: expected shape ({h}, {w}), got {depth.shape}")
    on = depth[mask]
    if not (np.all(np.isfinite(on)) and np.all(on > 0)):
        raise ValueError("depth_mm: expected finite depths > 0 mm on the mask")
    if (
        isinstance(min_samples, bool)
        or not isinstance(min_samples, (int, np.integer))
        or not 3 <= min_samples <= n
    ):
        raise ValueError(f"min_samples: expected an integer in [3, {n}], got {min_samples!r}")
    if valid is not None:
        valid = np.asarray(valid)
        if valid.shape != images.shape or valid.dtype != bool:
            raise ValueError(
                f"valid: expected a bool array of shape {images.shape}, got {valid.dtype} {valid.shape}"
            )
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"K: expected a finite (3, 3) matrix, got shape {K.shape}")

    geometry, axes, kind = lights.kernel_arrays()
    use_valid = valid is not None
    v = valid if use_valid else np.ones((1, 1, 1), dtype=bool)
    b = np.empty((3, h, w), dtype=np.float32)
    status = np.empty((h, w), dtype=np.int8)
    if method == "robust" and noise is None:
        noise = float(np.median(image_noise(images, mask)))
    params = robust_params(noise or 0.0) if method == "robust" else _PLAIN_PARAMS
    robust_kernel(
        np.ascontiguousarray(images),
        np.ascontiguousarray(v),
        use_valid,
        np.ascontiguousarray(mask),
        np.ascontiguousarray(depth),
        np.linalg.inv(K),
        geometry,
        axes,
        kind,
        lights.mu.astype(np.float64),
        float(MIN_RELATIVE_ATTENUATION),
        int(min_samples),
        params,
        sorting_network(n),
        b,
        status,
    )
    return field_from_fit(b, status, mask, specular=None)
