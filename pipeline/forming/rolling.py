"""One pass of a plate through the bender: displacement -> loaded curvature -> curvature after springback.

Joins :mod:`.bender` (geometry, force) and :mod:`.springback` (Gardiner, history) with the two things the
nominal model does not know:

- the plate's **yield factor** ``f``: its effective yield stress is ``f`` times the nominal one (the
  nominal yield is a guaranteed minimum; mill plates are typically 5-35 % above it). It also absorbs
  what the elastic-perfectly-plastic model leaves out (hardening, Bauschinger, the arc idealisation).
- the machine's **displacement gain** ``g`` (dimensionless, nominally 1): how far the plate is really
  pushed per mm the top roll's reading moves. It absorbs what the ideal three-point geometry leaves out
  (the plate between the rolls is not one circular arc, contact points move round the rolls, a worn roll
  or a reading's scale), which scale with the displacement rather than with the force.
- the machine's **compliance** ``c`` (mm per MN): the frame and rolls give under the bending force, so the
  plate sees the displacement ``g d - c F``. ``F`` depends on the loaded curvature (it holds the plate's
  moment, :func:`.bender.roll_force_n`), so the loaded curvature solves ``k = k_geom(g d - c F(k))``, found
  by fixed-point iteration: a contraction while ``c dF/dd < 1``; ``dF/dd`` is at most the plate's elastic
  three-point stiffness ``48 E' I b / L^3`` (0.1 MN/mm for 30 mm x 12 m on a 1.4 m span) and nearly 0 once
  the plate yields through.

Everything is vectorised over passes (:class:`PassSetup` holds one row per pass) for the fits of
:mod:`.learning` and the simulator of :mod:`.campaign`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from . import springback
from .records import Machine, PlateRecord

#: Fixed-point iterations of the compliance loop; stops earlier once the curvature moves < 1e-14 / mm.
_MAX_ITER = 60


@dataclass(frozen=True)
class PassSetup:
    """Machine and plate constants of a set of passes, one row per pass (all 1-D arrays, mm, MPa).

    Attributes
    ----------
    half_span_mm, bottom_roll_radius_mm : ndarray
        The machine's.
    thickness_mm, length_mm, modulus_mpa, yield_mpa : ndarray
        The plate's: thickness, length along the rolls, plane-strain modulus ``E'`` and plane-strain
        *nominal* yield stress ``S`` (von Mises).
    """

    half_span_mm: npt.NDArray[np.float64]
    bottom_roll_radius_mm: npt.NDArray[np.float64]
    thickness_mm: npt.NDArray[np.float64]
    length_mm: npt.NDArray[np.float64]
    modulus_mpa: npt.NDArray[np.float64]
    yield_mpa: npt.NDArray[np.float64]

    @classmethod
    def of(cls, machines: Sequence[Machine], plates: Sequence[PlateRecord]) -> PassSetup:
        """Rows for ``(machines[i], plates[i])``, the machine and the plate of pass i."""
        if len(machines) != len(plates):
            raise ValueError(
                f"plates: expected one per machine ({len(machines)}), got {len(plates)}"
            )
        mats = [p.target.material for p in plates]
        return cls(
            np.array([m.half_span_mm for m in machines], dtype=np.float64),
            np.array([m.bottom_roll_radius_mm for m in machines], dtype=np.float64),
            np.array([m.thickness_mm for m in mats], dtype=np.float64),
            np.array([p.target.length_mm for p in plates], dtype=np.float64),
            np.array(
                [springback.plane_strain_modulus(m.youngs_mpa, m.poisson) for m in mats],
                dtype=np.float64,
            ),
            np.array([springback.plane_strain_yield(m.yield_mpa) for m in mats], dtype=np.float64),
        )

    def geometric_curvature(self, displacement_mm: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Loaded mid-surface curvature of the rigid machine, ``1/R = 2 d / (a^2 + d^2 - 2 d (r_b + t/2))``.

        :func:`.bender.loaded_radius_mm` inverted without its checks (0 for ``d <= 0``).
        """
        d: npt.NDArray[np.float64] = np.maximum(np.asarray(displacement_mm, dtype=np.float64), 0.0)
        a = self.half_span_mm
        return (
            2.0
            * d
            / (a * a + d * d - 2.0 * d * (self.bottom_roll_radius_mm + 0.5 * self.thickness_mm))
        )

    def force_n(
        self, curvature: npt.ArrayLike, yield_factor: npt.ArrayLike
    ) -> npt.NDArray[np.float64]:
        """Top-roll force at a loaded curvature, N (:func:`.bender.roll_force_n` in curvature form)."""
        k = np.asarray(curvature, dtype=np.float64)
        s = self.yield_mpa * np.asarray(yield_factor, dtype=np.float64)
        m = springback.bending_moment(k, s, self.modulus_mpa, self.thickness_mm) * self.length_mm
        a = self.half_span_mm
        # 2 M sqrt(rho^2 - a^2) / (R a) with rho = R + t/2 + r_b, multiplied through by k = 1/R
        root = np.sqrt(
            np.maximum(
                (1.0 + k * (0.5 * self.thickness_mm + self.bottom_roll_radius_mm)) ** 2
                - (k * a) ** 2,
                0.0,
            )
        )
        return 2.0 * m * root / a

    def loaded_curvature(
        self,
        displacement_mm: npt.ArrayLike,
        yield_factor: npt.ArrayLike,
        compliance_mm_per_mn: npt.ArrayLike,
        gain: npt.ArrayLike = 1.0,
    ) -> npt.NDArray[np.float64]:
        """Loaded mid-surface curvature with the machine's gain and give, 1/mm (module docstring)."""
        d = np.asarray(displacement_mm, dtype=np.float64) * np.asarray(gain, dtype=np.float64)
        c = 1e-6 * np.asarray(compliance_mm_per_mn, dtype=np.float64)
        k = self.geometric_curvature(d)
        for _ in range(_MAX_ITER):
            k_new = self.geometric_curvature(d - c * self.force_n(k, yield_factor))
            done = np.max(np.abs(k_new - k), initial=0.0) < 1e-14
            k = k_new
            if done:
                break
        return k

    def unloaded_curvature(
        self, peak_loaded_curvature: npt.ArrayLike, yield_factor: npt.ArrayLike
    ) -> npt.NDArray[np.float64]:
        """Curvature after springback from the largest loaded curvature so far, 1/mm."""
        s = self.yield_mpa * np.asarray(yield_factor, dtype=np.float64)
        return np.asarray(
            springback.unloaded_curvature(
                peak_loaded_curvature, s, self.modulus_mpa, self.thickness_mm
            ),
            dtype=np.float64,
        )


def plate_curvatures(
    plate: PlateRecord,
    machines: Mapping[str, Machine],
    *,
    yield_factor: float,
    compliance_mm_per_mn: Mapping[str, float],
    gain: Mapping[str, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Loaded and unloaded mid-surface curvature after each of a plate's passes (history rule included).

    Parameters
    ----------
    plate : PlateRecord
    machines : mapping of machine id to Machine
        Every machine the plate's passes name.
    yield_factor : float
        The plate's effective yield over its nominal yield.
    compliance_mm_per_mn : mapping of machine id to float
        Each machine's compliance.
    gain : mapping of machine id to float, optional
        Each machine's displacement gain (default 1).

    Returns
    -------
    loaded, unloaded : (n_passes,) ndarray
        1/mm. ``unloaded[i]`` springs back from the largest of ``loaded[:i + 1]``.
    """
    if not plate.passes:
        return np.zeros(0), np.zeros(0)
    missing = [p.machine_id for p in plate.passes if p.machine_id not in machines]
    if missing:
        raise ValueError(f"machine_id: no machine {missing[0]!r} among {sorted(machines)}")
    setup = PassSetup.of(
        [machines[p.machine_id] for p in plate.passes], [plate] * len(plate.passes)
    )
    d = np.array([p.top_roll_displacement_mm for p in plate.passes])
    c = np.array([compliance_mm_per_mn[p.machine_id] for p in plate.passes])
    g = np.array([(gain or {}).get(p.machine_id, 1.0) for p in plate.passes])
    loaded = setup.loaded_curvature(d, yield_factor, c, g)
    return loaded, setup.unloaded_curvature(np.maximum.accumulate(loaded), yield_factor)
