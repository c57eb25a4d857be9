"""The normal field: what every estimator gives, and how its holes become normals.

A per-pixel fit leaves ``b = rho n`` (3, H, W) and a status per pixel (:data:`OK` or why not);
:func:`field_from_fit` turns them into unit normals and albedo and fills the holes from the
neighbours (:func:`pipeline.surface.normals.fill.harmonic_fill`). :func:`drop_facing_away` treats normals
that face away from their camera ray as holes too.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numba
import numpy as np
import numpy.typing as npt

from pipeline.formats import CaptureError
from pipeline.surface.normals.fill import harmonic_fill

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

if TYPE_CHECKING:
    from pipeline.surface.normals.specular import SpecularFit

#: Per-pixel status codes of the estimators: estimated; too few usable samples; a degenerate
#: system; an estimate facing away (rho = 0 or n_z >= 0); not finite; outside the mask.
OK, FEW, DEGENERATE, BAD_FIT, NONFINITE, OUTSIDE = 0, 1, 2, 3, 4, 5


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
    specular: SpecularFit | None = None


def field_from_fit(
    b: np.ndarray, status: np.ndarray, mask: np.ndarray, *, specular: SpecularFit | None
) -> NormalField:
    """The normal field of a per-pixel fit: unit normals and albedo, holes filled from their neighbours.

    Parameters
    ----------
    b : (3, H, W) float32
        rho n per pixel.
    status : (H, W) int8
        :data:`OK` or why a pixel has no estimate; a pixel whose estimate faces away from the
        camera (rho = 0 or n_z >= 0) is set to :data:`BAD_FIT` here and filled like a hole.
    mask : (H, W) bool
        The pixels that should have a normal.
    specular : SpecularFit or None
        Stored in the field.

    Returns
    -------
    NormalField

    Raises
    ------
    ValueError
        A used sample was not finite (status :data:`NONFINITE`).
    CaptureError
        Not one pixel was estimated.
    """
    h, w = mask.shape
    normals = np.empty((h, w, 3), dtype=np.float32)
    albedo = np.empty((h, w), dtype=np.float32)
    _finalize(b, status, normals, albedo)
    nonfinite = status == NONFINITE
    if nonfinite.any():
        r, c = np.argwhere(nonfinite)[0]
        raise ValueError(
            f"images: expected finite values at the used samples (mask and valid), got NaN or inf "
            f"at {int(nonfinite.sum())} pixels, first at (row {r}, col {c})"
        )
    estimated = status == OK
    if not estimated.any():
        raise CaptureError(
            f"images: no pixel of the mask ({int(mask.sum())} px) gave a normal "
            f"(too few usable samples, or images dark or inconsistent with the lights)"
        )
    holes = mask & ~estimated
    filled = harmonic_fill(normals, albedo, estimated, holes)
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


def drop_facing_away(
    field: NormalField, K: np.ndarray, *, min_cos: float = 0.02
) -> tuple[NormalField, int]:
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
    count = _facing_away(
        field.normals,
        field.mask,
        np.linalg.inv(np.asarray(K, dtype=np.float64)),
        float(min_cos),
        bad,
    )
    if count == 0:
        return field, 0
    normals, albedo = field.normals.copy(), field.albedo.copy()
    known = field.mask & ~bad
    if not known.any():
        raise CaptureError(
            f"normals: every one of the {count} normals faces away from its camera ray"
        )
    normals[bad] = np.nan
    filled_now = harmonic_fill(normals, albedo, known, bad)
    mask = known | filled_now
    filled = (field.filled & known) | filled_now
    return replace(
        field,
        normals=normals,
        albedo=albedo,
        mask=mask,
        filled=filled,
        n_filled=int(np.count_nonzero(filled)),
    ), count


@numba.njit(parallel=True, cache=True)
def _facing_away(normals: Arr, mask: Arr, kinv: Arr, min_cos: float, bad: Arr) -> int:
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
                r0 * r0 + r1 * r1 + r2 * r2
            )
            if not c > min_cos:
                bad[i, j] = True
                count += 1
    return count


@numba.njit(parallel=True, cache=True)
def _finalize(b: Arr, status: Arr, normals: Arr, albedo: Arr) -> None:
    """rho = |b|, n = b / rho into (H, W, 3) / (H, W); NaN where no estimate.

    A pixel with status OK whose b is not finite gets NONFINITE; one with rho = 0 or
    n_z >= 0 (facing away from the camera: not a valid estimate) gets BAD_FIT.
    """
    h, w = status.shape
    for i in numba.prange(h):
        for j in range(w):
            if status[i, j] == OK:
                x, y, z = b[0, i, j], b[1, i, j], b[2, i, j]
                if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                    status[i, j] = NONFINITE
                else:
                    rho = np.sqrt(x * x + y * y + z * z)
                    if rho > 0 and z < 0:
                        normals[i, j, 0] = x / rho
                        normals[i, j, 1] = y / rho
                        normals[i, j, 2] = z / rho
                        albedo[i, j] = rho
                        continue
                    status[i, j] = BAD_FIT
            normals[i, j, 0] = np.nan
            normals[i, j, 1] = np.nan
            normals[i, j, 2] = np.nan
            albedo[i, j] = np.nan
