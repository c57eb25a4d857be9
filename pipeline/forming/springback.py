"""Elastic-plastic springback of a wide plate in pure bending (Gardiner 1957, plane strain).

Model
-----
A plate much wider than thick bends in plane strain (no strain along the bend's axis, i.e. along the
rolls). With von Mises' criterion and the plastic flow of an incompressible material the in-plane
yield stress and the elastic modulus are

    S  = 2 Y / sqrt(3)  ~ 1.155 Y          (plane-strain yield stress; Tresca gives S = Y)
    E' = E / (1 - nu^2)                     (plane-strain modulus)

(Marciniak, Duncan & Hu [2]_ sec. 6.2). An elastic-perfectly-plastic section of thickness ``t`` bent to
curvature ``k`` first yields at ``k_y = 2 S / (E' t)``. Per unit width, ``I = t^3 / 12``, and

    M(k) = E' I k                                 k <= k_y  (elastic)
    M(k) = M_p (1 - (k_y / k)^2 / 3),  M_p = S t^2 / 4    k >= k_y  (elastic core, plastic skins)

Unloading is elastic: the curvature drops by ``M / (E' I)``::

    1/R' = 1/R - M / (E' I)  =  k - 3 S / (E' t) (1 - (k_y / k)^2 / 3)          (k >= k_y)

which, with ``x = R S / (E' t)`` (R the loaded radius), is Gardiner's relation [1]_

    R / R' = 1 - 3 x + 4 x^3           (x <= 1/2; for x >= 1/2 the plate springs back flat: R' = inf)

Springback never exceeds the fully plastic value ``M_p / (E' I) = 3 S / (E' t) = 1.5 k_y``.

History
-------
Unloading from ``k_max`` leaves residual stresses of at most ``S / 2`` (the skins) and never reverse
yielding; reloading the same way is elastic until ``k_max`` and then follows the monotonic curve. So
the plate's shape after any sequence of same-direction passes is that after one pass to the largest
loaded curvature so far: a pass that does not load the plate beyond an earlier one leaves it as it was.

References
----------
.. [1] Gardiner, F. J., "The springback of metals", Transactions of the ASME 79 (1957) 1-9.
.. [2] Marciniak, Z., Duncan, J. L., Hu, S. J., "Mechanics of Sheet Metal Forming", 2nd ed.,
   Butterworth-Heinemann (2002), ch. 6 (bending of sheet: plane strain, elastic-perfectly-plastic moment,
   springback).
.. [3] Kalpakjian, S., Schmid, S. R., "Manufacturing Engineering and Technology", Pearson, sec. 16.5
   (springback), example "Estimating springback" (the uniaxial form of [1]_ with Y and E).
"""

from __future__ import annotations

import math
from typing import Literal, TypeAlias, cast

import numpy as np
import numpy.typing as npt
from scipy import optimize

#: A scalar in, a scalar out; an array in, an array out.
Floats: TypeAlias = float | npt.NDArray[np.float64]

#: Plane-strain yield stress over the uniaxial one, von Mises (Tresca: 1).
VON_MISES_PLANE_STRAIN = 2.0 / math.sqrt(3.0)


def _out(values: npt.NDArray[np.float64]) -> Floats:
    """A 0-d result as a scalar, any other as the array."""
    return cast(Floats, values[()])


def _check_positive(name: str, value: npt.ArrayLike) -> None:
    v = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise ValueError(f"{name}: expected positive finite values, got {value!r}")


def plane_strain_modulus(youngs_mpa: float, poisson: float) -> float:
    """``E' = E / (1 - nu^2)``, MPa."""
    _check_positive("youngs_mpa", youngs_mpa)
    if not 0.0 <= poisson < 0.5:
        raise ValueError(f"poisson: expected a number in [0, 0.5), got {poisson!r}")
    return youngs_mpa / (1.0 - poisson * poisson)


def plane_strain_yield(
    yield_mpa: npt.ArrayLike, criterion: Literal["von-mises", "tresca"] = "von-mises"
) -> Floats:
    """In-plane yield stress of a plate in plane strain, ``S``, MPa (``2 Y / sqrt(3)`` or ``Y``)."""
    _check_positive("yield_mpa", yield_mpa)
    if criterion == "von-mises":
        return _out(VON_MISES_PLANE_STRAIN * np.asarray(yield_mpa, dtype=np.float64))
    if criterion == "tresca":
        return _out(np.asarray(yield_mpa, dtype=np.float64))
    raise ValueError(f"criterion: expected 'von-mises' or 'tresca', got {criterion!r}")


def yield_curvature(
    yield_stress_mpa: npt.ArrayLike, modulus_mpa: npt.ArrayLike, thickness_mm: npt.ArrayLike
) -> Floats:
    """Curvature at first yield, ``k_y = 2 S / (E' t)``, 1/mm."""
    _check_positive("yield_stress_mpa", yield_stress_mpa)
    _check_positive("modulus_mpa", modulus_mpa)
    _check_positive("thickness_mm", thickness_mm)
    s = np.asarray(yield_stress_mpa, dtype=np.float64)
    return _out(2.0 * s / (np.asarray(modulus_mpa) * np.asarray(thickness_mm)))


def bending_moment(
    curvature: npt.ArrayLike,
    yield_stress_mpa: npt.ArrayLike,
    modulus_mpa: Floats,
    thickness_mm: Floats,
) -> Floats:
    """Elastic-perfectly-plastic bending moment per unit width, N mm / mm.

    Parameters
    ----------
    curvature : float or array_like
        Loaded curvature, 1/mm (>= 0).
    yield_stress_mpa : float or array_like
        The yield stress in the bending direction (``S`` in plane strain), MPa.
    modulus_mpa : float or ndarray
        The modulus (``E'`` in plane strain), MPa.
    thickness_mm : float or ndarray

    Returns
    -------
    float or ndarray
        ``E' I k`` below first yield, ``M_p (1 - (k_y / k)^2 / 3)`` above (module docstring).
    """
    k = np.asarray(curvature, dtype=np.float64)
    if np.any(np.isnan(k)) or np.any(k < 0):
        raise ValueError(f"curvature: expected non-negative curvatures, got {curvature!r}")
    s = np.asarray(yield_stress_mpa, dtype=np.float64)
    ky = yield_curvature(s, modulus_mpa, thickness_mm)
    t = thickness_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.where(
            k <= ky, modulus_mpa * t**3 / 12.0 * k, s * t * t / 4.0 * (1.0 - (ky / k) ** 2 / 3.0)
        )
    return _out(m)


def unloaded_curvature(
    loaded_curvature: npt.ArrayLike,
    yield_stress_mpa: npt.ArrayLike,
    modulus_mpa: Floats,
    thickness_mm: Floats,
) -> Floats:
    """Curvature after springback from a loaded curvature (Gardiner; 0 below first yield).

    Parameters
    ----------
    loaded_curvature : float or array_like
        1/mm, >= 0.
    yield_stress_mpa : float or array_like
        ``S`` (plane strain: :func:`plane_strain_yield`), MPa.
    modulus_mpa : float
        ``E'`` (plane strain: :func:`plane_strain_modulus`), MPa.
    thickness_mm : float

    Returns
    -------
    float or ndarray
        ``k - M(k) / (E' I)``, 1/mm; exactly 0 for ``k <= k_y``.
    """
    k = np.asarray(loaded_curvature, dtype=np.float64)
    m = bending_moment(k, yield_stress_mpa, modulus_mpa, thickness_mm)
    ku = k - m / (modulus_mpa * thickness_mm**3 / 12.0)
    return _out(np.maximum(ku, 0.0))


def gardiner_ratio(
    loaded_radius_mm: npt.ArrayLike,
    yield_stress_mpa: npt.ArrayLike,
    modulus_mpa: float,
    thickness_mm: float,
) -> Floats:
    """Gardiner's ``R / R' = 1 - 3 x + 4 x^3``, ``x = R S / (E' t)``; 0 (flat) for ``x >= 1/2``.

    The same relation as :func:`unloaded_curvature`, written as in [1]_ and [3]_; with uniaxial ``Y``
    and ``E`` it is the textbook's bending of a narrow strip.
    """
    _check_positive("loaded_radius_mm", loaded_radius_mm)
    x = (
        np.asarray(loaded_radius_mm, dtype=np.float64)
        * np.asarray(yield_stress_mpa)
        / (modulus_mpa * thickness_mm)
    )
    return _out(np.where(x >= 0.5, 0.0, 1.0 - 3.0 * x + 4.0 * x**3))


def loaded_curvature_for(
    unloaded: float, yield_stress_mpa: float, modulus_mpa: float, thickness_mm: float
) -> float:
    """The loaded curvature that springs back to ``unloaded`` (inverse of :func:`unloaded_curvature`), 1/mm.

    Parameters
    ----------
    unloaded : float
        Wanted curvature after springback, 1/mm, > 0.

    Returns
    -------
    float
        The root of ``k - 1.5 k_y + k_y^3 / (2 k^2) = unloaded`` in ``(k_y, unloaded + 1.5 k_y)``.
    """
    _check_positive("unloaded", unloaded)
    ky = float(yield_curvature(yield_stress_mpa, modulus_mpa, thickness_mm))

    def f(k: float) -> float:
        return k - 1.5 * ky + 0.5 * ky**3 / (k * k) - unloaded

    return float(optimize.brentq(f, ky, unloaded + 1.5 * ky, xtol=1e-16, rtol=1e-13))


def curvatures_after_passes(
    loaded_curvatures: npt.ArrayLike,
    yield_stress_mpa: npt.ArrayLike,
    modulus_mpa: float,
    thickness_mm: float,
    initial_loaded: float = 0.0,
) -> npt.NDArray[np.float64]:
    """The plate's curvature after each of a sequence of same-direction passes (the history rule).

    Parameters
    ----------
    loaded_curvatures : (n,) array_like
        Loaded curvature of each pass in order, 1/mm (>= 0).
    yield_stress_mpa, modulus_mpa, thickness_mm
        As in :func:`unloaded_curvature` (one plate: one yield stress).
    initial_loaded : float
        Largest loaded curvature the plate saw before these passes (0: flat from the mill).

    Returns
    -------
    (n,) ndarray
        ``unloaded_curvature(max(initial, k_1, ..., k_i))`` after pass i: a pass that does not load the
        plate beyond every earlier one leaves its shape unchanged (module docstring).
    """
    k = np.asarray(loaded_curvatures, dtype=np.float64).reshape(-1)
    peak = np.maximum.accumulate(np.maximum(k, initial_loaded)) if k.size else k
    after = unloaded_curvature(peak, yield_stress_mpa, modulus_mpa, thickness_mm)
    return np.asarray(after, dtype=np.float64).reshape(-1)
