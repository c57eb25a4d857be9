"""Geometry of a three-roll pyramid bender: top-roll displacement <-> loaded radius of the plate.

Derivation
----------
Frame: x horizontal across the rolls, y up, origin at the middle between the bottom rolls' axes, which lie
at ``(+-a, 0)`` with ``a = spacing / 2`` and radius ``r_b``. The top roll (radius ``r_t``) sits on the
symmetry axis. A flat plate of thickness ``t`` lies on the bottom rolls: its lower surface at ``y = r_b``,
its upper surface at ``y = r_b + t``; the top roll just touching it has its centre at
``y_0 = r_b + t + r_t``. The displacement ``d`` moves the top roll's centre down to ``y_0 - d``.

Loaded, the plate between the rolls is taken as a circular arc (the standard idealisation of continuous
roll bending: each section passes under the top roll at the same moment and takes the same curvature),
its mid-surface of radius ``R`` about a centre ``C = (0, c)`` above the plate (the plate sags under the
top roll: concave upwards). Then

- the top roll touches the *inner* (upper) surface, radius ``R - t/2``, at its lowest point: the roll
  lies inside that circle and on the axis, so its lowest point is the inner surface's lowest point,
  ``y = c - (R - t/2)``; the roll's centre is ``r_t`` above it;
- each bottom roll touches the *outer* (lower) surface, radius ``R + t/2``, from outside: the distance
  between the centres is ``rho = R + t/2 + r_b``, i.e. ``a^2 + c^2 = rho^2``, ``c = sqrt(rho^2 - a^2)``.

The displacement is the drop of the top roll's centre::

    d = (r_b + t + r_t) - (c - R + t/2 + r_t) = rho - sqrt(rho^2 - a^2)

``r_t`` cancels (the top roll moves with its own lowest point) and ``d`` is the sagitta of a circle of
radius ``rho`` over the half-chord ``a``. Its inverse, from ``(rho - d)^2 = rho^2 - a^2``::

    rho = (a^2 + d^2) / (2 d),        R = (a^2 + d^2) / (2 d) - r_b - t/2

For small ``d`` this is ``R ~ a^2 / (2 d) = L^2 / (8 d)`` (``L`` the spacing), the usual shop formula;
the exact form adds ``d/2 - r_b - t/2``. Limits: ``d < a`` (the contact points stay below the centre),
and the inner surface cannot be tighter than the top roll, ``R - t/2 > r_t``.

Rolls' force
------------
Cut the plate at the top roll and take one half: the bottom roll pushes it with ``N`` along the common
normal, i.e. along the line from the roll's centre through ``C`` (frictionless contact), at the angle
``phi`` from the vertical with ``sin(phi) = a / rho``. Vertically ``N cos(phi) = F / 2`` (``F`` the top
roll's force). The line of ``N`` passes through ``C``, a distance ``R sin(phi)`` from the mid-surface point
under the top roll, so the bending moment there is ``M = N R sin(phi) = (F / 2) R tan(phi)``::

    F = 2 M / (R tan(phi))       (small angles: F = 4 M / L, three-point bending)

All functions take and return mm (and N, N mm); they broadcast over numpy arrays.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .records import Machine
from .springback import Floats


def _check_thickness(thickness_mm: npt.ArrayLike) -> None:
    if not np.all(np.isfinite(thickness_mm)) or np.any(np.asarray(thickness_mm) <= 0):
        raise ValueError(
            f"thickness_mm: expected a positive finite thickness, got {thickness_mm!r}"
        )


def loaded_radius_mm(
    displacement_mm: npt.ArrayLike, machine: Machine, thickness_mm: float
) -> Floats:
    """Loaded mid-surface radius of the plate for a top-roll displacement.

    Parameters
    ----------
    displacement_mm : float or array_like
        Top-roll displacement from touching the flat plate, mm; in ``(0, max_displacement_mm)``.
    machine : Machine
    thickness_mm : float

    Returns
    -------
    float or ndarray
        ``R = (a^2 + d^2) / (2 d) - r_b - t/2`` (module docstring), mm.

    Raises
    ------
    ValueError
        A displacement outside ``(0, max_displacement_mm]`` (field ``displacement_mm``).
    """
    _check_thickness(thickness_mm)
    d = np.asarray(displacement_mm, dtype=np.float64)
    d_max = max_displacement_mm(machine, thickness_mm)
    if not np.all(np.isfinite(d)) or np.any(d <= 0) or np.any(d > d_max * (1 + 1e-12)):
        raise ValueError(
            f"displacement_mm: expected displacements in (0, {d_max:.1f}] mm for this machine "
            f"and thickness, got {displacement_mm!r}"
        )
    a = machine.half_span_mm
    r = (a * a + d * d) / (2 * d) - machine.bottom_roll_radius_mm - 0.5 * thickness_mm
    return float(r) if r.ndim == 0 else r


def displacement_for_radius_mm(
    radius_mm: npt.ArrayLike, machine: Machine, thickness_mm: float
) -> Floats:
    """Top-roll displacement that loads the plate's mid-surface to a radius (inverse of :func:`loaded_radius_mm`).

    Parameters
    ----------
    radius_mm : float or array_like
        Loaded mid-surface radius, mm; at least ``min_loaded_radius_mm`` (``inf``: the flat plate, 0).
    machine : Machine
    thickness_mm : float

    Returns
    -------
    float or ndarray
        ``d = rho - sqrt(rho^2 - a^2)`` with ``rho = R + t/2 + r_b``, mm.

    Raises
    ------
    ValueError
        A radius tighter than the machine can roll (field ``radius_mm``).
    """
    _check_thickness(thickness_mm)
    r = np.asarray(radius_mm, dtype=np.float64)
    r_min = min_loaded_radius_mm(machine, thickness_mm)
    if np.any(np.isnan(r)) or np.any(r < r_min * (1 - 1e-12)):
        raise ValueError(
            f"radius_mm: expected loaded radii of at least {r_min:.1f} mm on this machine, "
            f"got {radius_mm!r}"
        )
    a = machine.half_span_mm
    with np.errstate(invalid="ignore"):
        rho = r + 0.5 * thickness_mm + machine.bottom_roll_radius_mm
        # rho - sqrt(rho^2 - a^2) written without cancellation for large rho
        d = np.where(np.isinf(r), 0.0, a * a / (rho + np.sqrt(np.maximum(rho * rho - a * a, 0.0))))
    return float(d) if d.ndim == 0 else d


def max_displacement_mm(machine: Machine, thickness_mm: float) -> float:
    """Deepest displacement the circle model holds for: the inner surface wraps the top roll, or ``d = a``."""
    _check_thickness(thickness_mm)
    a = machine.half_span_mm
    rho = machine.top_roll_radius_mm + thickness_mm + machine.bottom_roll_radius_mm  # R = r_t + t/2
    return float(a if rho <= a else rho - np.sqrt(rho * rho - a * a))


def min_loaded_radius_mm(machine: Machine, thickness_mm: float) -> float:
    """Tightest loaded mid-surface radius of the circle model (at :func:`max_displacement_mm`)."""
    a = machine.half_span_mm
    d = max_displacement_mm(machine, thickness_mm)
    return float((a * a + d * d) / (2 * d) - machine.bottom_roll_radius_mm - 0.5 * thickness_mm)


def roll_force_n(
    moment_nmm: npt.ArrayLike, radius_mm: npt.ArrayLike, machine: Machine, thickness_mm: float
) -> Floats:
    """Top-roll force that holds a bending moment under the top roll (module docstring: ``2 M / (R tan(phi))``).

    Parameters
    ----------
    moment_nmm : float or array_like
        Bending moment over the plate's whole length along the rolls, N mm.
    radius_mm : float or array_like
        Loaded mid-surface radius, mm (``inf``: no force).
    machine : Machine
    thickness_mm : float

    Returns
    -------
    float or ndarray
        Force, N.
    """
    a = machine.half_span_mm
    r = np.asarray(radius_mm, dtype=np.float64)
    rho = r + 0.5 * thickness_mm + machine.bottom_roll_radius_mm
    with np.errstate(invalid="ignore", divide="ignore"):
        # 2 M / (R tan phi) = 2 M sqrt(rho^2 - a^2) / (R a); -> 2 M / a * (rho / R) as R -> inf (M -> 0 there)
        f = np.where(
            np.isinf(r),
            0.0,
            2.0 * np.asarray(moment_nmm) * np.sqrt(np.maximum(rho * rho - a * a, 0.0)) / (r * a),
        )
    return float(f) if f.ndim == 0 else f
