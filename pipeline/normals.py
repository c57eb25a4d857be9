"""Photometric normals: per-pixel Lambertian photometric stereo (stage 2 of the method).

One public function, :func:`estimate_normals`, turns N intensity-normalised images
taken under N known distant lights into a field of unit surface normals and albedo
in the left-camera frame, filling the holes (too few usable samples) by harmonic
interpolation and counting them.

References
----------
.. [1] R. J. Woodham, "Photometric method for determining surface orientation from
   multiple images", Optical Engineering 19(1), 1980.
.. [2] B. Shi et al., "A benchmark dataset and evaluation for non-Lambertian and
   uncalibrated photometric stereo" (DiLiGenT), CVPR 2016 / TPAMI 2019: the real
   data the robust estimator is checked on (``tests/realdata.py``).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .formats import UNIT_TOLERANCE, CaptureError
from .lights import light_vectors_block

METHODS = ("robust", "lstsq")

#: A per-pixel system sum_k l_k l_k^T is degenerate (lights nearly coplanar or too few)
#: when det(M) / (trace(M) / 3)^3 falls below this (1 for an isotropic set of lights,
#: 0 for coplanar ones). 1e-4 ~ a condition number of ~1e3 in the worst direction.
DEGENERATE_RATIO = 1e-4

# Robust estimator (method="robust"), see estimate_normals' Notes and _robust_block. Chosen
# on DiLiGenT cat/pot1/ball (8-bit crops, 96 lights) and on synthetic spheres and plates
# with 12-24 lights, shadows and specular lobes (tests/pipeline/test_normals.py).
#: Attached/cast shadow pre-screen: a sample darker than this fraction of the pixel's
#: reference intensity (its 90th-percentile sample) is left out of the first fit.
SHADOW_FRACTION = 0.2
SHADOW_REF_QUANTILE = 0.9
#: The brightest ``floor(TRIM_TOP_FRACTION * m)`` of a pixel's m samples are left out of
#: the first fit (specular highlights; 3 of 12 lights). The later fits pick their samples
#: afresh from all, so a good sample left out here comes back.
TRIM_TOP_FRACTION = 0.3
#: After a fit, samples with n.l <= COS_MIN are attached shadows (or grazing) and dropped.
COS_MIN = 0.05
#: Samples whose residual r = I - rho n.l lies outside (-OUTLIER_K, OUTLIER_K_HIGH) * scale
#: are dropped (r > 0: highlight; r < 0: cast shadow, interreflection deficit). scale =
#: 1.4826 * median |r| of the kept samples, at least SCALE_FLOOR * rho. A lower
#: OUTLIER_K_HIGH (with TRIM_TOP_FRACTION 0.5) halves the bias left by broad specular lobes
#: but costs ~40 % more noise on matte plates (measured on simulated plates): kept symmetric.
OUTLIER_K = 1.5
OUTLIER_K_HIGH = 1.5
SCALE_FLOOR = 0.01
#: Re-selections and re-fits after the first fit (a 3rd changes DiLiGenT and the synthetic
#: sphere tests by < 0.05 deg and costs ~30 % more time).
ROBUST_ITERATIONS = 2
#: A fit needs at least this many samples (3 unknowns).
_MIN_FIT = 3

# Per-pixel status codes of the estimators.
_OK, _FEW, _DEGENERATE, _BAD_FIT, _NONFINITE, _OUTSIDE = 0, 1, 2, 3, 4, 5


@dataclass(frozen=True)
class NormalField:
    """Per-pixel surface normals and albedo from photometric stereo.

    Attributes
    ----------
    normals : (H, W, 3) float32
        Unit normals in the left-camera frame (x right, y down, z forward), pointing
        out of the surface towards the camera (n_z < 0); NaN where ``mask`` is False.
    albedo : (H, W) float32
        rho, relative to the intensity-normalised images (I_k = rho max(0, n.l_k));
        NaN where ``mask`` is False; interpolated where ``filled``.
    mask : (H, W) bool
        Pixels that have a normal (estimated or filled).
    filled : (H, W) bool
        Pixels whose normal was interpolated from neighbours (too few usable samples,
        a degenerate light set, or an estimate facing away from the camera); a subset
        of ``mask``.
    n_filled : int
        ``filled.sum()``.
    specular : SpecularFit or None
        The specular lobe fitted (``method="robust"`` with ``view_dirs`` or ``camera_matrix``);
        None otherwise.
    """

    normals: np.ndarray
    albedo: np.ndarray
    mask: np.ndarray
    filled: np.ndarray
    n_filled: int
    specular: "SpecularFit | None" = None


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
        ``"lstsq"``: Woodham's least squares for b = rho n over all valid samples.
        ``"robust"``: the same model fitted to the samples left after rejecting attached
        and cast shadows and specular highlights (see Notes).
    min_samples : int
        A pixel with fewer usable samples than this (>= 3) is a hole, filled from its
        neighbours.
    view_dirs : (3,) float, optional
        A distant (orthographic) camera: the unit vector from the surface towards it,
        left-camera frame (v_z < 0), e.g. (0, 0, -1). With ``method="robust"`` it switches
        on the specular stage (see Notes); ``method="lstsq"`` ignores it (it is the plain
        Lambertian baseline).
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
        Bad shapes or dtypes, non-unit or non-finite lights, lights not on the camera
        side or not spanning 3D, unknown method, bad min_samples, non-finite images at
        used samples.
    CaptureError
        Not one mask pixel gave a normal (images dark, or inconsistent with the lights).

    Notes
    -----
    Least squares: per pixel, (sum_k v_k l_k l_k^T) b = sum_k v_k I_k l_k over its valid
    samples (v_k); pixels with all samples valid share one pseudo-inverse (one float32
    matrix product), the others solve their own 3x3 system (adjugate, compiled loop over
    pixels). rho = |b|, n = b / rho.

    Robust (per pixel; numba, a block of a row at a time, vectorised over its pixels):
    first fit without samples darker than
    SHADOW_FRACTION of the pixel's 90th-percentile sample (shadows) and without its
    brightest TRIM_TOP_FRACTION (highlights) -- or, if that leaves an ill-posed system,
    without the shadows only, or with all samples; then ROBUST_ITERATIONS times:
    keep the valid samples with n.l > COS_MIN and a residual within -OUTLIER_K ..
    +OUTLIER_K_HIGH robust scales (MAD), and refit. On DiLiGenT (8-bit crops, 96 lights) this gives
    mean angular errors ball 2.57, cat 6.42, pot1 7.55 deg against 4.41, 8.76, 9.83 for
    least squares (``benchmarks/bench_normals_realdata.py``). A pixel's estimate uses
    at least 3 samples. On clean Lambertian data the trimming costs ~10 % in noise, and
    where the errors are systematic rather than outliers (the UW grey sphere: nearly
    Lambertian, 12 clustered lights of limited accuracy) it is slightly worse than least
    squares (4.93 against 4.71 deg inside 0.9 R).

    Specular stage (``method="robust"`` with ``view_dirs`` or ``camera_matrix``): shiny coatings add a lobe
    around the mirror direction to every sample, I_k = rho n.l_k + s g(n.h_k) with the
    half vector h_k = normalize(l_k + v). For a ring of lights the lobe is, to first order
    in the normal, inside the span of the Lambertian model, so rejecting samples cannot
    remove it: it biases every normal smoothly (about 1 deg at a lobe as bright as the
    diffuse part), and the integrated surface gets the wrong curvature. This stage models it:
    the lobe's shape g(c) = max(0, c)^e is fitted globally (1-D search over LOBE_EXPONENTS
    on a subsample of pixels: the e whose per-pixel non-negative amplitude removes the most
    residual); if the lobe explains less than LOBE_MIN_F times what a free parameter takes
    out of pure noise the stage stops (matte: the robust estimate stands). Otherwise
    SPECULAR_ITERATIONS joint Gauss-Newton passes fit b = rho n per pixel and the amplitude
    s >= 0 pooled over SPECULAR_WINDOW-pixel boxes (a per-pixel s is not identifiable; the
    pooled normal equation of s has the pixel's b eliminated: Schur complement), on the lit
    samples with residuals within SPECULAR_K global noise scales (the first pass, before
    the lobe is known, keeps all bright ones). The exponent is searched again half way.
    On the simulated cylinder (R 5 m, 12 lights at 45 deg, lobe e = 40 at 0.4 of white) the
    smoothed normal bias falls from ~1 deg to ~0.01 deg. The fit is in ``NormalField.specular``.

    Orientation: with lights on the camera side (l_z < 0) and images consistent with
    them, every lit sample has n . l > 0, so the least-squares b has n_z < 0 without any
    sign flip. A pixel whose estimate still has n_z >= 0 (noise, a black pixel with
    rho = 0) is treated as a hole and filled, never flipped.

    Holes (fewer than ``min_samples`` usable samples, a degenerate light set, rho = 0 or
    n_z >= 0) are filled by a harmonic (discrete Laplace) interpolation of the three
    normal components and the albedo from the estimated 4-neighbours, then
    renormalised; they are flagged in ``filled`` and counted in ``n_filled``. A
    connected hole with no estimated pixel next to it cannot be filled: it is left out
    of ``mask`` and a ``RuntimeWarning`` says how many pixels that was.

    References
    ----------
    Woodham 1980 (see the module docstring).
    """
    images, light_dirs, mask, valid = _check_inputs(images, light_dirs, mask, valid, method, min_samples)
    view_map = _view_map(view_dirs, camera_matrix)
    specular = None
    if method == "lstsq":
        b, status = _lstsq(images, light_dirs, mask, valid, min_samples)
    else:
        b, status = _robust(images, light_dirs, mask, valid, min_samples)
        if view_map is not None:
            specular = _specular(images, valid, status, light_dirs, view_map, b)
    return _field_from_fit(b, status, mask, specular=specular)


def _field_from_fit(b, status, mask, *, specular) -> NormalField:
    """The NormalField of a per-pixel fit: b = rho n (3, H, W) float32 and status (H, W) int8 -> unit
    normals and albedo, holes (no estimate, or one facing away) filled from their neighbours."""
    h, w = mask.shape
    normals = np.empty((h, w, 3), dtype=np.float32)
    albedo = np.empty((h, w), dtype=np.float32)
    _finalize(b, status, normals, albedo)
    nonfinite = status == _NONFINITE
    if nonfinite.any():
        r, c = np.argwhere(nonfinite)[0]
        raise ValueError(
            f"images: expected finite values at the used samples (mask and valid), got NaN or inf "
            f"at {int(nonfinite.sum())} pixels, first at (row {r}, col {c})"
        )
    estimated = status == _OK
    if not estimated.any():
        raise CaptureError(
            f"images: no pixel of the mask ({int(mask.sum())} px) gave a normal "
            f"(too few usable samples, or images dark or inconsistent with the lights)"
        )
    holes = mask & ~estimated
    filled = _harmonic_fill(normals, albedo, estimated, holes)
    unfilled = holes & ~filled
    if unfilled.any():
        warnings.warn(
            f"estimate_normals: {int(unfilled.sum())} mask pixels in holes with no estimated "
            f"neighbour were left without a normal (excluded from the mask)",
            RuntimeWarning,
            stacklevel=3,
        )
    return NormalField(
        normals=normals,
        albedo=albedo,
        mask=estimated | filled,
        filled=filled,
        n_filled=int(filled.sum()),
        specular=specular,
    )


def drop_facing_away(field: NormalField, K: np.ndarray, *, min_cos: float = 0.02) -> tuple[NormalField, int]:
    """Treat normals that do not face their pixel's ray as holes and fill them.

    A normal can have n_z < 0 and still face away from a pixel near the image's edge, whose ray
    is tilted (noise, a saturated pixel, a light model that does not fit there); the integration
    needs ``n . r < 0`` for every pixel's ray ``r = K^-1 (u, v, 1)``.

    Parameters
    ----------
    field : NormalField
    K : (3, 3) float
        Intrinsics of the grid, pixels.
    min_cos : float
        A normal is kept when ``-n . r / |r| > min_cos`` (dimensionless; 0.02 ~ within 88.9 deg).

    Returns
    -------
    (NormalField, int)
        The field with those normals filled from their neighbours (``filled`` and ``n_filled``
        include them; pixels that cannot be filled leave the mask), and how many were dropped.
    """
    bad = np.empty(field.mask.shape, np.bool_)
    count = _facing_away(field.normals, field.mask, np.linalg.inv(np.asarray(K, dtype=np.float64)), float(min_cos), bad)
    if count == 0:
        return field, 0
    normals, albedo = field.normals.copy(), field.albedo.copy()
    known = field.mask & ~bad
    if not known.any():
        raise CaptureError(f"normals: every one of the {count} normals faces away from its camera ray")
    normals[bad] = np.nan
    filled_now = _harmonic_fill(normals, albedo, known, bad)
    mask = known | filled_now
    filled = (field.filled & known) | filled_now
    return replace(field, normals=normals, albedo=albedo, mask=mask, filled=filled,
                   n_filled=int(np.count_nonzero(filled))), count


@numba.njit(parallel=True, cache=True)
def _facing_away(normals, mask, kinv, min_cos, bad):
    """bad = mask pixels whose normal is not within acos(min_cos) of facing its ray (NaN: bad); returns the count."""
    h, w = mask.shape
    count = 0
    for i in numba.prange(h):
        for j in range(w):
            bad[i, j] = False
            if not mask[i, j]:
                continue
            r0 = kinv[0, 0] * j + kinv[0, 1] * i + kinv[0, 2]
            r1 = kinv[1, 0] * j + kinv[1, 1] * i + kinv[1, 2]
            r2 = kinv[2, 0] * j + kinv[2, 1] * i + kinv[2, 2]
            c = -(normals[i, j, 0] * r0 + normals[i, j, 1] * r1 + normals[i, j, 2] * r2) / np.sqrt(
                r0 * r0 + r1 * r1 + r2 * r2)
            if not c > min_cos:
                bad[i, j] = True
                count += 1
    return count


# --------------------------------------------------------------------------- checks


def _check_inputs(images, light_dirs, mask, valid, method, min_samples):
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    images = np.asarray(images)
    if images.ndim != 3:
        raise ValueError(f"images: expected shape (N, H, W), got {images.shape}")
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(f"images: expected a float array (intensity-normalised), got dtype {images.dtype}")
    n, h, w = images.shape
    light_dirs = np.asarray(light_dirs, dtype=np.float64)
    if light_dirs.shape != (n, 3):
        raise ValueError(f"light_dirs: expected shape ({n}, 3) to match {n} images, got {light_dirs.shape}")
    if not np.all(np.isfinite(light_dirs)):
        raise ValueError("light_dirs: expected finite numbers, got NaN or inf")
    lengths = np.linalg.norm(light_dirs, axis=1)
    bad = np.flatnonzero(np.abs(lengths - 1.0) > UNIT_TOLERANCE)
    if bad.size:
        raise ValueError(f"light_dirs[{bad[0]}]: expected a unit vector, got length {lengths[bad[0]]:.4f}")
    behind = np.flatnonzero(light_dirs[:, 2] >= 0)
    if behind.size:
        raise ValueError(
            f"light_dirs[{behind[0]}]: expected a light on the camera side (l_z < 0, OpenCV camera "
            f"frame, from surface to light), got {light_dirs[behind[0]].round(4).tolist()}"
        )
    if n < _MIN_FIT or np.linalg.matrix_rank(light_dirs, tol=1e-6) < 3:
        raise ValueError(f"light_dirs: expected at least 3 directions spanning 3D, got {n} of rank "
                         f"{np.linalg.matrix_rank(light_dirs, tol=1e-6)}")
    if isinstance(min_samples, bool) or not isinstance(min_samples, (int, np.integer)) or not _MIN_FIT <= min_samples <= n:
        raise ValueError(f"min_samples: expected an integer in [{_MIN_FIT}, {n}] (N images), got {min_samples!r}")
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise ValueError(f"mask: expected shape ({h}, {w}) to match images, got {mask.shape}")
    if mask.dtype != bool:
        raise ValueError(f"mask: expected a bool array, got dtype {mask.dtype}")
    if valid is not None:
        valid = np.asarray(valid)
        if valid.shape != images.shape:
            raise ValueError(f"valid: expected shape {images.shape} to match images, got {valid.shape}")
        if valid.dtype != bool:
            raise ValueError(f"valid: expected a bool array, got dtype {valid.dtype}")
    return images.astype(np.float32, copy=False), light_dirs, mask, valid


def _view_map(view_dirs, camera_matrix):
    """None, or A (3, 3) float64 with the view direction of pixel (u, v) = normalize(A (u, v, 1)).

    A distant camera v: A = [0 | 0 | v]; a pinhole camera K: A = -K^-1.
    """
    if view_dirs is not None and camera_matrix is not None:
        raise ValueError("view_dirs, camera_matrix: expected at most one of them, got both")
    if camera_matrix is not None:
        K = np.asarray(camera_matrix, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"camera_matrix: expected a finite (3, 3) matrix, got shape {K.shape}")
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == K[2, 0] == K[2, 1] == 0 and K[2, 2] == 1):
            raise ValueError(f"camera_matrix: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                             f"got {K.tolist()}")
        return -np.linalg.inv(K)
    if view_dirs is None:
        return None
    v = np.asarray(view_dirs)
    if v.shape != (3,):
        raise ValueError(f"view_dirs: expected shape (3,) (a distant camera; camera_matrix for a pinhole one), "
                         f"got {v.shape}")
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"view_dirs: expected a float array, got dtype {v.dtype}")
    if not np.all(np.isfinite(v)):
        raise ValueError("view_dirs: expected finite numbers, got NaN or inf")
    length = float(np.linalg.norm(v))
    if abs(length - 1.0) > UNIT_TOLERANCE:
        raise ValueError(f"view_dirs: expected a unit vector, got length {length:.4f}")
    if v[2] >= 0:
        raise ValueError("view_dirs: expected a vector from the surface towards the camera (v_z < 0), got v_z >= 0")
    A = np.zeros((3, 3))
    A[:, 2] = v
    return A


# --------------------------------------------------------------------------- least squares


def _lstsq(images, L, mask, valid, min_samples):
    """Woodham least squares. Returns b = rho n as (3, H, W) float32 and status (H, W) int8."""
    n, h, w = images.shape
    flat = images.reshape(n, h * w)
    # Pixels with all samples valid share one pseudo-inverse (the light set spans 3D, checked).
    # Computed over the whole frame: cheaper than gathering the mask when the plate fills it.
    b = (np.linalg.pinv(L).astype(np.float32) @ flat).reshape(3, h, w)
    status = np.where(mask, _OK, _OUTSIDE).astype(np.int8)
    if valid is not None:
        # Pixels with some invalid samples: their own normal equations, solved per pixel in
        # compiled code (numpy's batched solve over gathered pixels took ~1 s at 5 MP).
        _lstsq_partial_kernel(images, valid, mask, L, int(min_samples), b, status)
    return b, status


@numba.njit(parallel=True, cache=True)
def _lstsq_partial_kernel(images, valid, mask, L, min_samples, b, status):
    """Least squares over the valid samples of every mask pixel that has an invalid one.

    (sum_k v_k l_k l_k^T) b = sum_k v_k I_k l_k, solved by the adjugate; b (3, H, W) and
    status (H, W) are updated in place (_FEW / _DEGENERATE where it cannot be solved).
    """
    n, h, w = images.shape
    for i in numba.prange(h):
        for j in range(w):
            if not mask[i, j]:
                continue
            m = 0
            for k in range(n):
                m += valid[k, i, j]
            if m == n:
                continue  # all valid: the shared pseudo-inverse already gave b
            if m < min_samples:
                status[i, j] = _FEW
                continue
            m00 = m01 = m02 = m11 = m12 = m22 = 0.0
            r0 = r1 = r2 = 0.0
            for k in range(n):
                if valid[k, i, j]:
                    lx, ly, lz = L[k, 0], L[k, 1], L[k, 2]
                    x = images[k, i, j]
                    m00 += lx * lx
                    m01 += lx * ly
                    m02 += lx * lz
                    m11 += ly * ly
                    m12 += ly * lz
                    m22 += lz * lz
                    r0 += x * lx
                    r1 += x * ly
                    r2 += x * lz
            c00 = m11 * m22 - m12 * m12
            c01 = m02 * m12 - m01 * m22
            c02 = m01 * m12 - m02 * m11
            c11 = m00 * m22 - m02 * m02
            c12 = m01 * m02 - m00 * m12
            c22 = m00 * m11 - m01 * m01
            det = m00 * c00 + m01 * c01 + m02 * c02
            tr = (m00 + m11 + m22) / 3.0
            if not det > DEGENERATE_RATIO * tr * tr * tr:
                status[i, j] = _DEGENERATE
                continue
            b[0, i, j] = (c00 * r0 + c01 * r1 + c02 * r2) / det
            b[1, i, j] = (c01 * r0 + c11 * r1 + c12 * r2) / det
            b[2, i, j] = (c02 * r0 + c12 * r1 + c22 * r2) / det


@numba.njit(parallel=True, cache=True)
def _finalize(b, status, normals, albedo):
    """rho = |b|, n = b / rho into (H, W, 3) / (H, W); NaN where no estimate.

    A pixel with status OK whose b is not finite gets _NONFINITE; one with rho = 0 or
    n_z >= 0 (facing away from the camera: not a valid estimate) gets _BAD_FIT.
    """
    h, w = status.shape
    for i in numba.prange(h):
        for j in range(w):
            if status[i, j] == _OK:
                x, y, z = b[0, i, j], b[1, i, j], b[2, i, j]
                if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                    status[i, j] = _NONFINITE
                else:
                    rho = np.sqrt(x * x + y * y + z * z)
                    if rho > 0 and z < 0:
                        normals[i, j, 0] = x / rho
                        normals[i, j, 1] = y / rho
                        normals[i, j, 2] = z / rho
                        albedo[i, j] = rho
                        continue
                    status[i, j] = _BAD_FIT
            normals[i, j, 0] = np.nan
            normals[i, j, 1] = np.nan
            normals[i, j, 2] = np.nan
            albedo[i, j] = np.nan


# --------------------------------------------------------------------------- robust


def _robust(images, L, mask, valid, min_samples):
    """Robust per-pixel fit (numba). Returns b = rho n as (3, H, W) float32 and status (H, W) int8."""
    n, h, w = images.shape
    b = np.empty((3, h, w), dtype=np.float32)
    status = np.empty((h, w), dtype=np.int8)
    use_valid = valid is not None
    v = valid if use_valid else np.ones((1, 1, 1), dtype=bool)
    zeros = np.zeros((n, 3))
    _robust_kernel(
        np.ascontiguousarray(images), np.ascontiguousarray(v), use_valid, np.ascontiguousarray(mask),
        np.zeros((1, 1)), np.eye(3), np.ascontiguousarray(L, dtype=np.float64), zeros, np.zeros(n, np.int64),
        np.zeros(n), 0.0, int(min_samples), _robust_params(), _sorting_network(n), b, status,
    )
    return b, status


def _robust_params() -> np.ndarray:
    """The robust estimator's constants as the kernel's parameter vector."""
    return np.array(
        [SHADOW_FRACTION, SHADOW_REF_QUANTILE, TRIM_TOP_FRACTION, COS_MIN, OUTLIER_K, SCALE_FLOOR, ROBUST_ITERATIONS,
         OUTLIER_K_HIGH],
        dtype=np.float64,
    )


#: LLVM fast-math flags for the kernels: reassociation lets the loops over a row's pixels
#: vectorise; no "nnan"/"ninf", so NaN and inf checks keep their meaning.
_FASTMATH = {"nsz", "arcp", "contract", "reassoc"}
# float32 constants for the robust kernels (a float64 literal would promote a whole loop to float64)
_F32_ZERO, _F32_ONE, _F32_THIRD = np.float32(0.0), np.float32(1.0), np.float32(1.0 / 3.0)
_F32_INF = np.float32(np.inf)
_F32_MIN_FIT = np.float32(_MIN_FIT)
_F32_DEGENERATE = np.float32(DEGENERATE_RATIO)
_F32_MAD = np.float32(1.4826)  # median |r| -> standard deviation for Gaussian noise

# The robust kernel works on one image row at a time with every per-pixel quantity an
# array over the row's pixels, so that each step is a branch-free loop over pixels that
# LLVM vectorises (a per-pixel loop with data-dependent branches was ~10x slower).
# Order statistics use rank counting (n^2 compares per pixel, branch-free).


@numba.njit(cache=True, fastmath=_FASTMATH)
def _fit_row(samples, weight, L, b, ok):
    """Per pixel j of a row: weighted (0/1) least squares b[:, j] over the samples.

    samples, weight : (N, W) float32; L : (N, 3, W) float32, the light vector of each sample
    (the same for every pixel of a distant light, per pixel for a point light); b : (3, W)
    float32 out; ok : (W,) float32 out, 1 where the system has >= 3 samples and is well posed
    (see DEGENERATE_RATIO), else 0. Float32 throughout: twice the SIMD lanes of float64, and
    at most N = a few dozen unit-scale terms per sum.
    """
    n, w = samples.shape
    m00 = np.zeros(w, np.float32)
    m01 = np.zeros(w, np.float32)
    m02 = np.zeros(w, np.float32)
    m11 = np.zeros(w, np.float32)
    m12 = np.zeros(w, np.float32)
    m22 = np.zeros(w, np.float32)
    r0 = np.zeros(w, np.float32)
    r1 = np.zeros(w, np.float32)
    r2 = np.zeros(w, np.float32)
    cnt = np.zeros(w, np.float32)
    for k in range(n):
        lxk, lyk, lzk = L[k, 0], L[k, 1], L[k, 2]
        for j in range(w):
            lx, ly, lz = lxk[j], lyk[j], lzk[j]
            wk = weight[k, j]
            wi = wk * samples[k, j]
            wx, wy = wk * lx, wk * ly
            m00[j] += wx * lx
            m01[j] += wx * ly
            m02[j] += wx * lz
            m11[j] += wy * ly
            m12[j] += wy * lz
            m22[j] += wk * lz * lz
            r0[j] += wi * lx
            r1[j] += wi * ly
            r2[j] += wi * lz
            cnt[j] += wk
    for j in range(w):
        c00 = m11[j] * m22[j] - m12[j] * m12[j]
        c01 = m02[j] * m12[j] - m01[j] * m22[j]
        c02 = m01[j] * m12[j] - m02[j] * m11[j]
        c11 = m00[j] * m22[j] - m02[j] * m02[j]
        c12 = m01[j] * m02[j] - m00[j] * m12[j]
        c22 = m00[j] * m11[j] - m01[j] * m01[j]
        det = m00[j] * c00 + m01[j] * c01 + m02[j] * c02
        tr = (m00[j] + m11[j] + m22[j]) * _F32_THIRD
        good = cnt[j] >= _F32_MIN_FIT and det > _F32_DEGENERATE * tr * tr * tr
        inv = _F32_ONE / det if good else _F32_ZERO
        b[0, j] = (c00 * r0[j] + c01 * r1[j] + c02 * r2[j]) * inv
        b[1, j] = (c01 * r0[j] + c11 * r1[j] + c12 * r2[j]) * inv
        b[2, j] = (c02 * r0[j] + c12 * r1[j] + c22 * r2[j]) * inv
        ok[j] = _F32_ONE if good else _F32_ZERO


@functools.lru_cache(maxsize=16)
def _sorting_network(n: int) -> np.ndarray:
    """Compare-exchange pairs (C, 2) int64 of Batcher's odd-even merge sort for n keys."""
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            j = k % p
            while j <= n - 1 - k:
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
                j += 2 * k
            k //= 2
        p *= 2
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _sort_row(values, pairs):
    """Sort every column of values (N, W) in place with the sorting network ``pairs`` (branch-free)."""
    w = values.shape[1]
    for c in range(pairs.shape[0]):
        lo, hi = values[pairs[c, 0]], values[pairs[c, 1]]
        for j in range(w):
            x, y = lo[j], hi[j]
            lo[j] = np.minimum(x, y)
            hi[j] = np.maximum(x, y)


#: Pixels per work block of the robust kernel: a block's N x width scratch arrays should
#: stay in the L2 cache (N = 12: 256 px, ~12 kB per float32 array).
_BLOCK_SAMPLES = 3072


@numba.njit(parallel=True, cache=True)
def _robust_kernel(images, valid, use_valid, mask, depth, kinv, geometry, axes, kind, mu, min_attenuation,
                   min_samples, params, pairs, b_out, status):
    """Robust fit of every mask pixel; see estimate_normals' Notes. Fills b_out (3, H, W) with rho n and
    status (H, W) with a status code per pixel.

    The lights as :meth:`pipeline.lights.Lights.kernel_arrays` give them; with point lights, ``depth``
    (H, W) mm and ``kinv`` give each pixel's surface point (:func:`pipeline.lights.light_vectors_block`);
    with distant lights only, ``depth`` may be (1, 1) and is not read.
    """
    n, h, w = images.shape
    width = max(16, _BLOCK_SAMPLES // n)
    per_row = (w + width - 1) // width
    near = False
    for k in range(n):
        near = near or kind[k] == 1
    for t in numba.prange(h * per_row):
        i = t // per_row
        j0 = (t % per_row) * width
        j1 = min(j0 + width, w)
        if not mask[i, j0:j1].any():
            status[i, j0:j1] = _OUTSIDE
            continue
        samples, usable, m, finite = _load_block(images, valid, use_valid, mask, i, j0, j1)
        L = np.empty((n, 3, j1 - j0), np.float32)
        if near:
            light_vectors_block(depth, kinv, geometry, axes, kind, mu, min_attenuation, i, j0, samples, usable, m, L)
        else:
            for k in range(n):
                for c in range(3):
                    L[k, c, :] = geometry[k, c]
        _robust_block(samples, usable, m, finite, mask, L, min_samples, params, pairs, b_out, status, i, j0)


@numba.njit(cache=True, fastmath=_FASTMATH)
def _load_block(images, valid, use_valid, mask, i, j0, j1):
    """The samples of pixels (i, j0:j1): (N, w) float32 values (0 where unusable), (N, w) float32
    usability (1: a valid sample of a mask pixel), (w,) int64 counts and (w,) finiteness."""
    n = images.shape[0]
    w = j1 - j0
    samples = np.empty((n, w), np.float32)
    usable = np.empty((n, w), np.float32)
    m = np.zeros(w, np.int64)
    finite = np.ones(w, np.bool_)
    for k in range(n):
        for j in range(w):
            x = images[k, i, j0 + j]
            u = mask[i, j0 + j] and (not use_valid or valid[k, i, j0 + j])
            usable[k, j] = _F32_ONE if u else _F32_ZERO
            samples[k, j] = x if u else _F32_ZERO
            m[j] += 1 if u else 0
            if u and not np.isfinite(x):
                finite[j] = False
    return samples, usable, m, finite


@numba.njit(cache=True, fastmath=_FASTMATH)
def _robust_block(samples, usable, m, finite, mask, L, min_samples, params, pairs, b_out, status, i, j0):
    """The robust fit of the pixels (i, j0:j0 + w) of one row from their samples (N, w), usability
    (N, w), counts and finiteness (see _load_block) under light vectors L (N, 3, w)."""
    # params: float64 (8,); the per-sample work is float32 (L too), the per-pixel quantities float32
    shadow_fraction, trim_top, cos_min = np.float32(params[0]), params[2], np.float32(params[3])
    outlier_k, scale_floor, outlier_k_high = np.float32(params[4]), np.float32(params[5]), np.float32(params[7])
    ref_quantile = params[1]
    iterations = int(params[6])
    n, w = samples.shape
    ranked = np.empty((n, w), np.float32)  # scratch for order statistics (+inf = not counted)
    keep = np.empty((n, w), np.float32)
    trial = np.empty((n, w), np.float32)
    resid = np.empty((n, w), np.float32)
    for k in range(n):
        for j in range(w):
            ranked[k, j] = samples[k, j] if usable[k, j] > 0 else _F32_INF
    # shadow level and highlight cut from the pixel's order statistics
    _sort_row(ranked, pairs)  # unusable samples (+inf) sort last
    low = np.empty(w, np.float32)
    top = np.empty(w, np.float32)
    for j in range(w):
        mj = m[j]
        ref = ranked[int(ref_quantile * (mj - 1)), j] if mj > 0 else _F32_ZERO
        low[j] = shadow_fraction * ref
        n_top = int(trim_top * mj)
        top[j] = ranked[mj - n_top, j] if n_top > 0 else _F32_INF
    # first fit: without shadows and highlights; else without shadows; else all samples
    b = np.zeros((3, w), np.float32)
    ok = np.zeros(w, np.float32)
    cand = np.empty((3, w), np.float32)
    cand_ok = np.empty(w, np.float32)
    for attempt in range(3):
        for k in range(n):
            for j in range(w):
                x = samples[k, j]
                if attempt == 0:
                    inside = x > low[j] and x < top[j]
                elif attempt == 1:
                    inside = x > low[j]
                else:
                    inside = True
                # pixels already fitted keep their weights
                keep[k, j] = keep[k, j] if ok[j] > 0 else (usable[k, j] if inside else _F32_ZERO)
        _fit_row(samples, keep, L, cand, cand_ok)
        remaining = 0
        for j in range(w):
            if ok[j] == 0 and cand_ok[j] > 0:
                ok[j] = _F32_ONE
                b[0, j], b[1, j], b[2, j] = cand[0, j], cand[1, j], cand[2, j]
            remaining += 1 if (ok[j] == 0 and m[j] >= _MIN_FIT) else 0
        if remaining == 0:
            break
    # re-select the samples from the fit: lit (n.l > cos_min) and within +-k robust scales
    rho = np.empty(w, np.float32)
    scale = np.empty(w, np.float32)
    kth = np.empty(w, np.int64)
    accept = np.empty(w, dtype=np.bool_)
    for _ in range(iterations):
        for j in range(w):
            rho[j] = np.sqrt(b[0, j] * b[0, j] + b[1, j] * b[1, j] + b[2, j] * b[2, j])
            kth[j] = 0
        for k in range(n):
            lxk, lyk, lzk = L[k, 0], L[k, 1], L[k, 2]
            for j in range(w):
                d = b[0, j] * lxk[j] + b[1, j] * lyk[j] + b[2, j] * lzk[j]  # rho n.l
                r = samples[k, j] - d
                resid[k, j] = r
                lit = usable[k, j] > 0 and d > cos_min * rho[j]
                trial[k, j] = _F32_ONE if lit else _F32_ZERO
                counted = lit and keep[k, j] > 0
                ranked[k, j] = abs(r) if counted else _F32_INF
                kth[j] += 1 if counted else 0
        _sort_row(ranked, pairs)
        for j in range(w):
            scale[j] = ranked[kth[j] // 2, j]  # the (upper) median of |r|
        for j in range(w):
            scale[j] = max(_F32_MAD * scale[j], scale_floor * rho[j])
        for k in range(n):
            for j in range(w):
                r = resid[k, j]
                inlier = -outlier_k * scale[j] < r < outlier_k_high * scale[j]
                trial[k, j] = trial[k, j] if inlier else _F32_ZERO
        _fit_row(samples, trial, L, cand, cand_ok)
        for j in range(w):
            accept[j] = ok[j] > 0 and cand_ok[j] > 0 and rho[j] > 0 and kth[j] >= _MIN_FIT
            if accept[j]:
                b[0, j], b[1, j], b[2, j] = cand[0, j], cand[1, j], cand[2, j]
        for k in range(n):
            keep_k, trial_k = keep[k], trial[k]
            for j in range(w):
                keep_k[j] = trial_k[j] if accept[j] else keep_k[j]
    for j in range(w):
        if not mask[i, j0 + j]:
            status[i, j0 + j] = _OUTSIDE
        elif not finite[j]:
            status[i, j0 + j] = _NONFINITE
        elif m[j] < min_samples:
            status[i, j0 + j] = _FEW
        elif ok[j] == 0:
            status[i, j0 + j] = _DEGENERATE
        else:
            status[i, j0 + j] = _OK
        b_out[0, i, j0 + j] = b[0, j]
        b_out[1, i, j0 + j] = b[1, j]
        b_out[2, i, j0 + j] = b[2, j]


# --------------------------------------------------------------------------- hole filling


def _harmonic_fill(normals, albedo, known, holes):
    """Fill ``holes`` of the normals (H, W, 3) and albedo (H, W) in place by the discrete Laplace equation.

    Each hole pixel becomes the mean of its 4-neighbours that are known or holes; known
    pixels are Dirichlet data. The filled normals are renormalised (the harmonic mean of
    unit vectors with n_z < 0 has n_z < 0: maximum principle). Hole components with no
    known 4-neighbour are not filled. Returns the (H, W) bool mask of filled pixels.
    """
    filled = np.zeros_like(holes)
    if not holes.any():
        return filled
    # Work in the holes' bounding box grown by one pixel (the known neighbours).
    rows, cols = np.nonzero(holes)
    r0, r1 = max(rows.min() - 1, 0), min(rows.max() + 2, holes.shape[0])
    c0, c1 = max(cols.min() - 1, 0), min(cols.max() + 2, holes.shape[1])
    box = (slice(r0, r1), slice(c0, c1))
    hole_b, known_b = holes[box], known[box]
    labels, _ = ndi.label(hole_b)  # 4-connectivity
    touching = ndi.binary_dilation(known_b) & hole_b
    fill = hole_b & np.isin(labels, np.unique(labels[touching]))
    if not fill.any():
        return filled
    h, w = hole_b.shape
    values = np.concatenate([normals[box], albedo[box][..., None]], axis=-1).reshape(h * w, 4).astype(np.float64)
    fill_flat = np.flatnonzero(fill)
    index = np.full(h * w, -1, dtype=np.int64)
    index[fill_flat] = np.arange(fill_flat.size)
    rr, cc = np.divmod(fill_flat, w)
    known_flat = known_b.ravel()
    diag = np.zeros(fill_flat.size)
    rhs = np.zeros((fill_flat.size, 4))
    ii, jj = [], []
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = rr + dr, cc + dc
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        nb = np.where(inside, r * w + c, 0)
        nb_known = inside & known_flat[nb]
        nb_fill = inside & (index[nb] >= 0)
        diag += nb_known | nb_fill
        rhs[nb_known] += values[nb[nb_known]]
        ii.append(np.flatnonzero(nb_fill))
        jj.append(index[nb[nb_fill]])
    ii, jj = np.concatenate(ii), np.concatenate(jj)
    diag_idx = np.arange(fill_flat.size)
    A = sp.csc_matrix(
        (np.concatenate([diag, -np.ones(ii.size)]), (np.concatenate([diag_idx, ii]), np.concatenate([diag_idx, jj]))),
        shape=(fill_flat.size, fill_flat.size),
    )
    sol = np.asarray(spla.spsolve(A, rhs)).reshape(fill_flat.size, 4)
    n = sol[:, :3] / np.linalg.norm(sol[:, :3], axis=1, keepdims=True)
    at = (rr + r0, cc + c0)
    normals[at] = n
    albedo[at] = sol[:, 3]
    filled[at] = True
    return filled


# --------------------------------------------------------------------------- specular lobe

# Specular stage (method="robust" with view_dirs or camera_matrix), see estimate_normals' Notes.
#: Candidate lobe exponents e of g(c) = c^e, c = n.h (1-D search on the summed residual;
#: the minimum is refined by a parabola in log e). 2 ~ a very broad sheen, 1000 ~ a mirror-like glint.
LOBE_EXPONENTS = tuple(float(x) for x in np.geomspace(2.0, 1000.0, 28))
#: The search uses at most this many pixels (a regular subsample of the estimated ones).
LOBE_SEARCH_PIXELS = 40000
#: The lobe is modelled only when it explains this many times the residual that one extra
#: free parameter per pixel removes from pure noise (an F-ratio over the search pixels).
LOBE_MIN_F = 4.0
#: Side (px) of the box over which the specular amplitude s is pooled: s is a property of
#: the coating that varies slowly; one s per pixel is not identifiable (for a ring of lights
#: the lobe is, to first order, in the span of the Lambertian model).
SPECULAR_WINDOW = 31
#: Joint Gauss-Newton passes (normals per pixel, pooled amplitude).
SPECULAR_ITERATIONS = 4
#: In the specular stage a sample is used when lit (n.l > COS_MIN) and its residual is within
#: SPECULAR_K global noise scales (a cast shadow, an interreflection, a lobe of another shape).
SPECULAR_K = 3.0
#: A pixel the specular stage turns by more than this keeps its robust Lambertian estimate
#: (the stage corrects up to ~10 deg on the synthetic plates of the tests, ~1 deg on the simulated cell).
MAX_SPECULAR_TURN_DEG = 15.0
#: Samples of the lobe table over c in [0, 1].
_LOBE_TABLE = 4096


@dataclass(frozen=True)
class SpecularFit:
    """The specular lobe fitted by :func:`estimate_normals` (``method="robust"`` with a view direction).

    Attributes
    ----------
    modelled : bool
        False when the data showed no lobe worth modelling (matte: the Lambertian estimate stands).
    exponent : float
        Lobe exponent e of g(c) = max(0, c)^e, c = n . h_k, h_k = normalize(l_k + v) (NaN if not modelled).
    f_ratio : float
        Residual explained by the lobe over what one free parameter explains in pure noise (~1 without a lobe).
    amplitude_median : float
        Median over the estimated pixels of the pooled amplitude s (same units as the images).
    n_reverted : int
        Pixels the lobe turned by more than MAX_SPECULAR_TURN_DEG (or away from the camera):
        they keep the robust Lambertian estimate.
    """

    modelled: bool
    exponent: float
    f_ratio: float
    amplitude_median: float
    n_reverted: int = 0


def _lobe_tables(exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """g(c) = c^e and g'(c) = e c^(e-1) sampled at c = i / (_LOBE_TABLE - 1), float64 (_LOBE_TABLE + 1,) each
    (one guard entry for the interpolation at c = 1)."""
    c = np.linspace(0.0, 1.0, _LOBE_TABLE)
    g = c**exponent
    dg = exponent * c ** (exponent - 1.0)
    return np.append(g, g[-1]), np.append(dg, dg[-1])


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _lookup(table, c):
    """Linear interpolation of a lobe table at c (clamped to [0, 1]: the lobe is 0 for c <= 0)."""
    x = min(max(c, 0.0), 1.0) * (_LOBE_TABLE - 1)
    i = int(x)
    f = x - i
    return table[i] + f * (table[i + 1] - table[i])


@numba.njit(parallel=True, cache=True)
def _lobe_search_kernel(samples, usable, b, view, L, g_tables, cos_min, shadow_fraction, out):
    """Per search pixel p and lobe e: the residual the lobe removes from the Lambertian fit.

    samples, usable : (N, P); b : (3, P) current rho n; view : (P, 3); g_tables : (T+1, E), the
    lobe tables side by side (row t: every lobe at c = t / (T - 1)), so that one sample's
    interpolation weights serve all lobes in one contiguous loop.
    out : (P, E + 2): [:, e] reduction of the summed squared residual by s g_e (s >= 0),
    [:, E] the Lambertian residual, [:, E + 1] the number of samples used (0: pixel unusable).
    """
    n, p_count = samples.shape
    n_exp = g_tables.shape[1]
    for p in numba.prange(p_count):
        out[p, :] = 0.0
        rho = np.sqrt(b[0, p] ** 2 + b[1, p] ** 2 + b[2, p] ** 2)
        if not rho > 0:
            continue
        nx, ny, nz = b[0, p] / rho, b[1, p] / rho, b[2, p] / rho
        w = np.zeros(n)
        cs = np.zeros(n)
        m00 = m01 = m02 = m11 = m12 = m22 = r0 = r1 = r2 = cnt = 0.0
        for k in range(n):
            lx, ly, lz = L[k, 0], L[k, 1], L[k, 2]
            nl = nx * lx + ny * ly + nz * lz
            x = samples[k, p]
            if usable[k, p] and nl > cos_min and x > shadow_fraction * rho * nl:
                w[k] = 1.0
                m00 += lx * lx
                m01 += lx * ly
                m02 += lx * lz
                m11 += ly * ly
                m12 += ly * lz
                m22 += lz * lz
                r0 += x * lx
                r1 += x * ly
                r2 += x * lz
                cnt += 1.0
            hx, hy, hz = lx + view[p, 0], ly + view[p, 1], lz + view[p, 2]
            hn = np.sqrt(hx * hx + hy * hy + hz * hz)
            cs[k] = (nx * hx + ny * hy + nz * hz) / hn
        c00 = m11 * m22 - m12 * m12
        c01 = m02 * m12 - m01 * m22
        c02 = m01 * m12 - m02 * m11
        c11 = m00 * m22 - m02 * m02
        c12 = m01 * m02 - m00 * m12
        c22 = m00 * m11 - m01 * m01
        det = m00 * c00 + m01 * c01 + m02 * c02
        tr = (m00 + m11 + m22) / 3.0
        if cnt < _MIN_FIT + 2 or not det > DEGENERATE_RATIO * tr * tr * tr:
            continue
        b0 = (c00 * r0 + c01 * r1 + c02 * r2) / det
        b1 = (c01 * r0 + c11 * r1 + c12 * r2) / det
        b2 = (c02 * r0 + c12 * r1 + c22 * r2) / det
        sse = 0.0
        for k in range(n):
            r = samples[k, p] - (b0 * L[k, 0] + b1 * L[k, 1] + b2 * L[k, 2])
            sse += w[k] * r * r
        out[p, n_exp] = sse
        out[p, n_exp + 1] = cnt
        gi = np.zeros(n_exp)
        glx = np.zeros(n_exp)
        gly = np.zeros(n_exp)
        glz = np.zeros(n_exp)
        gg = np.zeros(n_exp)
        for k in range(n):
            if w[k] > 0:
                x = min(max(cs[k], 0.0), 1.0) * (_LOBE_TABLE - 1)  # as _lookup, for every lobe at once
                t = int(x)
                f = x - t
                lo, hi = g_tables[t], g_tables[t + 1]
                sk, lx, ly, lz = samples[k, p], L[k, 0], L[k, 1], L[k, 2]
                for e in range(n_exp):
                    g = lo[e] + f * (hi[e] - lo[e])
                    gi[e] += g * sk
                    glx[e] += g * lx
                    gly[e] += g * ly
                    glz[e] += g * lz
                    gg[e] += g * g
        for e in range(n_exp):
            a0 = (c00 * glx[e] + c01 * gly[e] + c02 * glz[e]) / det
            a1 = (c01 * glx[e] + c11 * gly[e] + c12 * glz[e]) / det
            a2 = (c02 * glx[e] + c12 * gly[e] + c22 * glz[e]) / det
            num = gi[e] - (a0 * r0 + a1 * r1 + a2 * r2)
            den = gg[e] - (a0 * glx[e] + a1 * gly[e] + a2 * glz[e])
            if den > 1e-12 * gg[e] and num > 0:  # s = num / den >= 0
                out[p, e] = num * num / den


@numba.njit(parallel=True, cache=True, fastmath=_FASTMATH, error_model="numpy")
def _specular_pass_kernel(images, valid, use_valid, fit, L, view_map, g_table, dg_table, b, s_map,
                          cos_min, lo, hi, db0, coef, num, den):
    """One joint Gauss-Newton linearisation of I_k = b.l_k + s g(n.h_k) at every pixel with fit True.

    b (3, H, W) = rho n and s_map (H, W) are the current estimate; lo < r_k < hi selects the samples;
    the view direction of pixel (i, j) is normalize(view_map (j, i, 1)).
    Out: db0 (3, H, W) the step in b with s fixed, coef (3, H, W) the change of that step per unit
    change of s, num / den (H, W) the pixel's normal equation for s with b eliminated (Schur
    complement): ds = num / den (0, 0 where the pixel has no well-posed system).
    """
    n, h, w = images.shape
    for i in numba.prange(h):
        for j in range(w):
            db0[0, i, j] = db0[1, i, j] = db0[2, i, j] = 0.0
            coef[0, i, j] = coef[1, i, j] = coef[2, i, j] = 0.0
            num[i, j] = 0.0
            den[i, j] = 0.0
            if not fit[i, j]:
                continue
            bx, by, bz = b[0, i, j], b[1, i, j], b[2, i, j]
            rho = np.sqrt(bx * bx + by * by + bz * bz)
            if not rho > 0:
                continue
            nx, ny, nz = bx / rho, by / rho, bz / rho
            vx = view_map[0, 0] * j + view_map[0, 1] * i + view_map[0, 2]
            vy = view_map[1, 0] * j + view_map[1, 1] * i + view_map[1, 2]
            vz = view_map[2, 0] * j + view_map[2, 1] * i + view_map[2, 2]
            vn = 1.0 / np.sqrt(vx * vx + vy * vy + vz * vz)
            vx, vy, vz = vx * vn, vy * vn, vz * vn
            s = s_map[i, j]
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            jr0 = jr1 = jr2 = jg0 = jg1 = jg2 = gr = gg = cnt = 0.0
            for k in range(n):
                if use_valid and not valid[k, i, j]:
                    continue
                lx, ly, lz = L[k, 0], L[k, 1], L[k, 2]
                nl = nx * lx + ny * ly + nz * lz
                if not nl > cos_min:
                    continue
                hx, hy, hz = lx + vx, ly + vy, lz + vz
                hn = 1.0 / np.sqrt(hx * hx + hy * hy + hz * hz)
                hx, hy, hz = hx * hn, hy * hn, hz * hn
                c = nx * hx + ny * hy + nz * hz
                g = _lookup(g_table, c)
                r = images[k, i, j] - (bx * lx + by * ly + bz * lz) - s * g
                if not (lo < r < hi):
                    continue
                t = s * _lookup(dg_table, c) / rho  # d(s g)/db = t (h - c n)
                j0 = lx + t * (hx - c * nx)
                j1 = ly + t * (hy - c * ny)
                j2 = lz + t * (hz - c * nz)
                a00 += j0 * j0
                a01 += j0 * j1
                a02 += j0 * j2
                a11 += j1 * j1
                a12 += j1 * j2
                a22 += j2 * j2
                jr0 += j0 * r
                jr1 += j1 * r
                jr2 += j2 * r
                jg0 += j0 * g
                jg1 += j1 * g
                jg2 += j2 * g
                gr += g * r
                gg += g * g
                cnt += 1.0
            c00 = a11 * a22 - a12 * a12
            c01 = a02 * a12 - a01 * a22
            c02 = a01 * a12 - a02 * a11
            c11 = a00 * a22 - a02 * a02
            c12 = a01 * a02 - a00 * a12
            c22 = a00 * a11 - a01 * a01
            det = a00 * c00 + a01 * c01 + a02 * c02
            tr = (a00 + a11 + a22) / 3.0
            if cnt < _MIN_FIT or not det > DEGENERATE_RATIO * tr * tr * tr:
                continue
            d0 = (c00 * jr0 + c01 * jr1 + c02 * jr2) / det
            d1 = (c01 * jr0 + c11 * jr1 + c12 * jr2) / det
            d2 = (c02 * jr0 + c12 * jr1 + c22 * jr2) / det
            e0 = (c00 * jg0 + c01 * jg1 + c02 * jg2) / det
            e1 = (c01 * jg0 + c11 * jg1 + c12 * jg2) / det
            e2 = (c02 * jg0 + c12 * jg1 + c22 * jg2) / det
            if not (np.isfinite(d0 + d1 + d2) and np.isfinite(e0 + e1 + e2) and abs(e0) + abs(e1) + abs(e2) < 1e6):
                continue  # overflow in float32: leave the pixel as it is
            db0[0, i, j], db0[1, i, j], db0[2, i, j] = d0, d1, d2
            coef[0, i, j], coef[1, i, j], coef[2, i, j] = e0, e1, e2
            if cnt > _MIN_FIT:
                num[i, j] = gr - (e0 * jr0 + e1 * jr1 + e2 * jr2)
                den[i, j] = max(gg - (e0 * jg0 + e1 * jg1 + e2 * jg2), 0.0)


def _specular(images, valid, status, L, view_map, b):
    """The specular stage: fit a lobe and refine b (3, H, W) float32 in place. Returns a SpecularFit.

    ``view_map`` (3, 3): the view direction of pixel (u, v) is normalize(view_map (u, v, 1)).
    """
    n, h, w = images.shape
    fit = status == _OK
    use_valid = valid is not None
    v = valid if use_valid else np.ones((1, 1, 1), dtype=bool)
    flat = np.flatnonzero(fit)
    sel = flat[:: max(1, flat.size // LOBE_SEARCH_PIXELS)]
    rows, cols = np.divmod(sel, w)

    def search():
        samples = images.reshape(n, h * w).take(sel, axis=1).astype(np.float64)
        usable = valid.reshape(n, h * w).take(sel, axis=1) if use_valid else np.ones(samples.shape, dtype=bool)
        pv = np.stack([cols, rows, np.ones(sel.size)], axis=1) @ view_map.T
        pv /= np.linalg.norm(pv, axis=1, keepdims=True)
        exps = np.array(LOBE_EXPONENTS)
        tables = np.stack([_lobe_tables(e)[0] for e in exps], axis=1)
        out = np.empty((sel.size, exps.size + 2))
        _lobe_search_kernel(samples, usable, b.reshape(3, h * w).take(sel, axis=1).astype(np.float64), pv, L, tables,
                            COS_MIN, SHADOW_FRACTION, out)
        used = out[:, -1] > 0
        if not used.any():
            return float("nan"), 0.0, float("nan")
        red = out[used, :-2].sum(axis=0)
        best = int(np.argmax(red))
        dof = (out[used, -1] - 4.0).sum()
        sigma2 = (out[used, -2].sum() - red[best]) / dof
        f_ratio = float(red[best] / sigma2 / used.sum()) if sigma2 > 0 else float("inf")
        log_e = np.log(exps[best])
        if 0 < best < exps.size - 1:  # parabola through the neighbours in log e
            y0, y1, y2 = red[best - 1], red[best], red[best + 1]
            curv = y0 - 2 * y1 + y2
            step = np.log(exps[best + 1]) - log_e
            if curv < 0:
                log_e += 0.5 * step * (y0 - y2) / curv
        return float(np.exp(log_e)), f_ratio, float(np.sqrt(max(sigma2, 0.0)))

    exponent, f_ratio, sigma = search()
    if not f_ratio >= LOBE_MIN_F:
        return SpecularFit(modelled=False, exponent=float("nan"), f_ratio=f_ratio, amplitude_median=0.0)
    b_start = b.copy()
    s = np.zeros((h, w), dtype=np.float32)
    db0 = np.empty((3, h, w), dtype=np.float32)
    coef = np.empty((3, h, w), dtype=np.float32)
    num = np.empty((h, w), dtype=np.float32)
    den = np.empty((h, w), dtype=np.float32)
    box = (SPECULAR_WINDOW, SPECULAR_WINDOW)
    for it in range(SPECULAR_ITERATIONS):
        if it == SPECULAR_ITERATIONS // 2:  # again, from the better normals; kept only if it is a clear lobe
            again = search()
            if again[1] >= LOBE_MIN_F and LOBE_EXPONENTS[0] < again[0] < LOBE_EXPONENTS[-1]:
                exponent, f_ratio, sigma = again
        g_table, dg_table = _lobe_tables(exponent)
        hi = np.inf if it == 0 else SPECULAR_K * sigma  # the first pass starts without the lobe
        _specular_pass_kernel(images, v, use_valid, fit, L, view_map, g_table, dg_table, b, s, COS_MIN,
                              -SPECULAR_K * sigma, hi, db0, coef, num, den)
        pooled_num = cv2.boxFilter(num, -1, box, normalize=False)
        pooled_den = cv2.boxFilter(den, -1, box, normalize=False)
        # a box with (almost) no information on s keeps its s
        ds = np.divide(pooled_num, pooled_den, out=np.zeros_like(num), where=pooled_den > 1e-6 * float(pooled_den.max()))
        s_new = np.maximum(s + ds, 0.0)  # the lobe adds light: s >= 0 (a constraint of the model)
        step = s_new - s
        np.add(b, db0 - coef * step, out=b, where=fit)  # b outside the fitted pixels is not defined
        s = s_new
    # a pixel the lobe turned by more than MAX_SPECULAR_TURN_DEG (or away from the camera) keeps
    # its Lambertian estimate: the lobe did not describe it (saturated peak, another material)
    with np.errstate(all="ignore"):  # NaN / inf compare False below: reverted; b outside fit is undefined
        b64, b0 = b.astype(np.float64), b_start.astype(np.float64)
        cos_turn = (b64 * b0).sum(axis=0) / np.sqrt((b64 * b64).sum(axis=0) * (b0 * b0).sum(axis=0))
    revert = fit & ~((cos_turn > np.cos(np.radians(MAX_SPECULAR_TURN_DEG))) & (b[2] < 0))
    b[:, revert] = b_start[:, revert]
    return SpecularFit(modelled=True, exponent=exponent, f_ratio=f_ratio, amplitude_median=float(np.median(s[fit])),
                       n_reverted=int(revert.sum()))
