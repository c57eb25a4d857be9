"""The cell's lights: distant and point (near-field LED) lights, and what each casts on a surface.

A light is either *distant* (a unit direction, the same everywhere) or a *point light* at
``position_mm`` with an optional LED axis and beam profile ``mu``. The irradiance that light k
casts on a surface point X with unit normal n (left-camera frame, mm) is

    E_k(X, n) = e_k * a_k(X) * max(0, n . l_k(X))

with the unit vector ``l_k(X)`` from X towards the light and the attenuation

    a_k(X) = (1000 / |P_k - X|)^2 * max(0, cos theta_k)^mu_k        (point light)
    a_k(X) = 1                                                      (distant light)

where ``theta_k`` is the angle between the LED's axis and the ray P_k -> X. ``e_k`` is the
light's ``intensity``: for a point light the irradiance on a surface facing it 1000 mm away on
its axis (Queau et al. 2018's LED model; relative units, only ratios between lights matter).

References
----------
.. [1] Y. Queau, B. Durix, T. Wu, D. Cremers, F. Lauze, J.-D. Durou, "LED-based photometric
   stereo: modeling, calibration and numerical solution", J. Math. Imaging Vis. 60, 2018.
.. [2] R. Mecca, A. Wetzler, A. M. Bruckstein, R. Kimmel, "Near field photometric stereo with
   point light sources", SIAM J. Imaging Sci. 7(4), 2014.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numba
import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from pipeline.formats import CalibratedLight, Light

#: The irradiance of a point light is given at this distance (mm) from it.
REFERENCE_DISTANCE_MM = 1000.0
#: A point light closer than this (mm) to a camera's centre is inside the camera head.
CAMERA_HEAD_RADIUS_MM = 100.0


@dataclass(frozen=True)
class Lights:
    """N lights in the left-camera frame (OpenCV: x right, y down, z forward), mm.

    Attributes
    ----------
    directions : (N, 3) float64
        Unit vector from the surface towards a distant light; NaN rows for point lights.
    positions_mm : (N, 3) float64
        Position of a point light; NaN rows for distant lights.
    axes : (N, 3) float64
        Unit emission axis of a point light (its beam centre); NaN where none is given
        (isotropic: ``mu`` is then 0) and for distant lights.
    mu : (N,) float64
        LED beam profile exponent ``cos^mu`` (0: isotropic; 0 for distant lights).
    intensity : (N,) float64
        ``e_k`` > 0 (see the module docstring).
    """

    directions: np.ndarray
    positions_mm: np.ndarray
    axes: np.ndarray
    mu: np.ndarray
    intensity: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.intensity)
        for name in ("directions", "positions_mm", "axes"):
            value = getattr(self, name)
            if value.shape != (n, 3):
                raise ValueError(f"Lights.{name}: expected shape ({n}, 3), got {value.shape}")
        if self.mu.shape != (n,):
            raise ValueError(f"Lights.mu: expected shape ({n},), got {self.mu.shape}")
        distant = np.isfinite(self.directions).all(axis=1)
        point = np.isfinite(self.positions_mm).all(axis=1)
        if np.any(distant == point):
            k = int(np.flatnonzero(distant == point)[0])
            raise ValueError(f"Lights[{k}]: expected exactly one of a direction and a position")
        if not (np.all(np.isfinite(self.intensity)) and np.all(self.intensity > 0)):
            raise ValueError("Lights.intensity: expected finite intensities > 0")
        if not (np.all(np.isfinite(self.mu)) and np.all(self.mu >= 0)):
            raise ValueError("Lights.mu: expected finite exponents >= 0")
        no_axis = ~np.isfinite(self.axes).all(axis=1)
        if np.any(no_axis & (self.mu > 0)):
            k = int(np.flatnonzero(no_axis & (self.mu > 0))[0])
            raise ValueError(f"Lights[{k}]: mu > 0 needs an axis")

    # ------------------------------------------------------------------ construction

    @classmethod
    def distant(cls, directions: npt.ArrayLike, intensity: npt.ArrayLike | None = None) -> Lights:
        """Distant lights from (N, 3) unit directions (surface -> light) and (N,) intensities (default 1)."""
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        n = len(d)
        e = np.ones(n) if intensity is None else np.asarray(intensity, dtype=np.float64).reshape(n)
        nan = np.full((n, 3), np.nan)
        return cls(directions=d, positions_mm=nan, axes=nan.copy(), mu=np.zeros(n), intensity=e)

    @classmethod
    def points(
        cls,
        positions_mm: npt.ArrayLike,
        intensity: npt.ArrayLike | None = None,
        *,
        axes: npt.ArrayLike | None = None,
        mu: npt.ArrayLike | None = None,
    ) -> Lights:
        """Point lights at (N, 3) positions (mm), with optional (N, 3) unit axes and (N,) exponents."""
        p = np.asarray(positions_mm, dtype=np.float64).reshape(-1, 3)
        n = len(p)
        e = np.ones(n) if intensity is None else np.asarray(intensity, dtype=np.float64).reshape(n)
        a = (
            np.full((n, 3), np.nan)
            if axes is None
            else np.asarray(axes, dtype=np.float64).reshape(n, 3)
        )
        m = np.zeros(n) if mu is None else np.asarray(mu, dtype=np.float64).reshape(n)
        return cls(directions=np.full((n, 3), np.nan), positions_mm=p, axes=a, mu=m, intensity=e)

    @classmethod
    def from_documents(cls, lights: Sequence[Light | CalibratedLight]) -> Lights:
        """From the ``lights`` entries of a capture (``pipeline.formats.Light``) or a light calibration."""
        n = len(lights)
        out = {k: np.full((n, 3), np.nan) for k in ("directions", "positions_mm", "axes")}
        mu = np.zeros(n)
        intensity = np.ones(n)
        for k, light in enumerate(lights):
            direction = getattr(light, "direction", None)
            if direction is not None:
                d = np.asarray(direction, dtype=np.float64)
                out["directions"][k] = d / np.linalg.norm(d)
            else:
                out["positions_mm"][k] = light.position_mm
                if light.axis is not None:
                    a = np.asarray(light.axis, dtype=np.float64)
                    out["axes"][k] = a / np.linalg.norm(a)
                mu[k] = light.mu or 0.0
            intensity[k] = light.intensity
        return cls(mu=mu, intensity=intensity, **out)

    def documents(self) -> list[dict[str, list[float] | float]]:
        """The lights as ``lights[k]`` objects of a ``plate-capture/1`` (JSON-ready)."""
        docs = []
        doc: dict[str, list[float] | float]
        for k in range(self.n):
            if self.is_point[k]:
                doc = {"position_mm": [float(v) for v in self.positions_mm[k]]}
                if np.isfinite(self.axes[k]).all():
                    doc["axis"] = [float(v) for v in self.axes[k]]
                    doc["mu"] = float(self.mu[k])
            else:
                doc = {"direction": [float(v) for v in self.directions[k]]}
            doc["intensity"] = float(self.intensity[k])
            docs.append(doc)
        return docs

    # ------------------------------------------------------------------ properties

    @property
    def n(self) -> int:
        return len(self.intensity)

    @property
    def is_point(self) -> npt.NDArray[np.bool_]:
        """(N,) bool, True for point lights."""
        point: npt.NDArray[np.bool_] = np.isfinite(self.positions_mm).all(axis=1)
        return point

    @property
    def any_point(self) -> bool:
        return bool(self.is_point.any())

    def with_intensity(self, intensity: npt.ArrayLike) -> Lights:
        return Lights(
            self.directions,
            self.positions_mm,
            self.axes,
            self.mu,
            np.asarray(intensity, np.float64),
        )

    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arrays for compiled kernels: ``geometry`` (N, 3) float64 (position for point lights,
        direction for distant ones), ``axes`` (N, 3) (0 where none) and ``kind`` (N,) int64
        (1 point, 0 distant). ``mu`` is :attr:`mu`."""
        point = self.is_point
        geometry = np.where(point[:, None], self.positions_mm, self.directions)
        axes = np.where(np.isfinite(self.axes), self.axes, 0.0)
        return np.ascontiguousarray(geometry), np.ascontiguousarray(axes), point.astype(np.int64)

    # ------------------------------------------------------------------ geometry

    def directions_at(self, points_mm: np.ndarray) -> np.ndarray:
        """Unit vectors from surface points towards each light.

        Parameters
        ----------
        points_mm : (..., 3) float
            Surface points, left-camera frame, mm.

        Returns
        -------
        (N, ..., 3) float64
            ``l_k(X)``; a distant light's direction everywhere.
        """
        x = np.asarray(points_mm, dtype=np.float64)
        out = np.empty((self.n, *x.shape))
        for k in range(self.n):
            if self.is_point[k]:
                d = self.positions_mm[k] - x
                out[k] = d / np.linalg.norm(d, axis=-1, keepdims=True)
            else:
                out[k] = self.directions[k]
        return out

    def attenuation_at(self, points_mm: np.ndarray) -> np.ndarray:
        """The attenuation ``a_k(X)`` of every light at surface points (1 for distant lights).

        Parameters
        ----------
        points_mm : (..., 3) float
            Surface points, left-camera frame, mm.

        Returns
        -------
        (N, ...) float64
            ``(1000 / |P - X|)^2 * max(0, cos theta)^mu``, dimensionless.
        """
        x = np.asarray(points_mm, dtype=np.float64)
        out = np.ones((self.n, *x.shape[:-1]))
        for k in np.flatnonzero(self.is_point):
            d = x - self.positions_mm[k]  # light -> surface
            dist2 = np.einsum("...c,...c->...", d, d)
            att = REFERENCE_DISTANCE_MM**2 / dist2
            if self.mu[k] > 0:
                cos = np.einsum("...c,c->...", d, self.axes[k]) / np.sqrt(dist2)
                att = att * np.maximum(cos, 0.0) ** self.mu[k]
            out[k] = att
        return out

    def irradiance(self, points_mm: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """``e_k a_k(X) max(0, n . l_k(X))`` for every light: (N, ...) float64 (see the module docstring)."""
        n = np.asarray(normals, dtype=np.float64)
        shading = np.maximum(np.einsum("k...c,...c->k...", self.directions_at(points_mm), n), 0.0)
        irradiance: npt.NDArray[np.float64] = (
            self.intensity.reshape((-1,) + (1,) * (shading.ndim - 1))
            * self.attenuation_at(points_mm)
            * shading
        )
        return irradiance

    def nominal_directions(self, centre_mm: npt.ArrayLike) -> Lights:
        """Distant lights pointing where these lights are seen from ``centre_mm`` (3,), mm.

        Point lights become distant ones with the direction from the centre; the intensity is the
        irradiance they cast at the centre (so that images keep their relative brightness there).
        """
        c = np.asarray(centre_mm, dtype=np.float64).reshape(3)
        dirs = self.directions_at(c)
        att = self.attenuation_at(c)
        return Lights.distant(dirs, self.intensity * att)


@numba.njit(nogil=True, cache=True, inline="always")
def light_at(
    k: int,
    x0: float,
    x1: float,
    x2: float,
    geometry: npt.NDArray[np.float64],
    axes: npt.NDArray[np.float64],
    kind: npt.NDArray[np.int64],
    mu: npt.NDArray[np.float64],
) -> tuple[float, float, float, float]:
    """Light k seen from the surface point (x0, x1, x2) mm: its unit vector and its attenuation a_k
    (the documented model; ``geometry``, ``axes``, ``kind`` as :meth:`Lights.kernel_arrays`).

    Inlined into the kernels that call it, which keep their own floating-point flags.
    """
    if kind[k] == 1:
        d0, d1, d2 = geometry[k, 0] - x0, geometry[k, 1] - x1, geometry[k, 2] - x2
        dist2 = d0 * d0 + d1 * d1 + d2 * d2
        dist = np.sqrt(dist2)
        a = REFERENCE_DISTANCE_MM * REFERENCE_DISTANCE_MM / dist2
        if mu[k] > 0.0:
            cos = -(d0 * axes[k, 0] + d1 * axes[k, 1] + d2 * axes[k, 2]) / dist
            a *= max(cos, 0.0) ** mu[k]
        return d0 / dist, d1 / dist, d2 / dist, a
    return geometry[k, 0], geometry[k, 1], geometry[k, 2], 1.0


@numba.njit(nogil=True, cache=True, fastmath={"nsz", "arcp", "contract", "reassoc"})
def light_vectors_block(
    depth: npt.NDArray[np.floating[Any]],
    kinv: npt.NDArray[np.float64],
    geometry: npt.NDArray[np.float64],
    axes: npt.NDArray[np.float64],
    kind: npt.NDArray[np.int64],
    mu: npt.NDArray[np.float64],
    min_attenuation: float,
    i: int,
    j0: int,
    samples: npt.NDArray[np.float32],
    usable: npt.NDArray[np.float32],
    m: npt.NDArray[np.int64],
    L: npt.NDArray[np.float32],
) -> None:
    """Per pixel (i, j0 + j) of a row block: the light model from the surface point it sees.

    ``depth`` (H, W) mm and ``kinv`` (3, 3) give the point X = depth * K^-1 (u, v, 1); ``geometry``,
    ``axes``, ``kind`` as :meth:`Lights.kernel_arrays`, ``mu`` (N,). Writes the unit light vectors
    l_k(X) into ``L`` (N, 3, w) float32 and divides the samples (N, w) float32 by the attenuation
    a_k(X) in place; a sample whose attenuation is below ``min_attenuation`` of the pixel's largest
    becomes unusable (``usable`` 0, ``m`` (w,) counts it out). Pixels without a depth get L = 0.

    The model of :func:`light_at`, evaluated a light at a time over the block's pixels (loops the
    compiler vectorises; the beam's power ``cos^mu`` in single precision, 1e-7 relative), where a
    pixel at a time it took most of each near-field estimate (docs/figures.md, *Speed, end to end*).
    """
    n, w = samples.shape
    x0, x1, x2 = np.empty(w), np.empty(w), np.empty(w)
    seen = np.empty(w, np.bool_)
    v = float(i)
    for j in range(w):
        z = depth[i, j0 + j]
        seen[j] = z > 0.0
        z = z if seen[j] else 0.0
        u = float(j0 + j)
        x0[j] = z * (kinv[0, 0] * u + kinv[0, 1] * v + kinv[0, 2])
        x1[j] = z * (kinv[1, 0] * u + kinv[1, 1] * v + kinv[1, 2])
        x2[j] = z * (kinv[2, 0] * u + kinv[2, 1] * v + kinv[2, 2])
    att = np.empty((n, w))
    cos = np.empty(w, np.float32)
    for k in range(n):
        if kind[k] != 1:  # distant: its direction everywhere, no attenuation
            for j in range(w):
                L[k, 0, j], L[k, 1, j], L[k, 2, j] = geometry[k, 0], geometry[k, 1], geometry[k, 2]
                att[k, j] = 1.0
            continue
        g0, g1, g2 = geometry[k, 0], geometry[k, 1], geometry[k, 2]
        a0, a1, a2 = axes[k, 0], axes[k, 1], axes[k, 2]
        for j in range(w):
            d0, d1, d2 = g0 - x0[j], g1 - x1[j], g2 - x2[j]
            dist2 = d0 * d0 + d1 * d1 + d2 * d2
            inv = 1.0 / np.sqrt(dist2)
            L[k, 0, j], L[k, 1, j], L[k, 2, j] = d0 * inv, d1 * inv, d2 * inv
            att[k, j] = REFERENCE_DISTANCE_MM * REFERENCE_DISTANCE_MM / dist2
            cos[j] = max(-(d0 * a0 + d1 * a1 + d2 * a2) * inv, 0.0)
        if mu[k] > 0.0:
            power = np.float32(mu[k])
            for j in range(w):
                att[k, j] *= cos[j] ** power
    for j in range(w):
        if not seen[j]:
            L[:, :, j] = 0.0  # outside the mask: no samples are usable there
            continue
        a_max = 0.0
        for k in range(n):
            a_max = max(a_max, att[k, j])
        for k in range(n):
            if att[k, j] > min_attenuation * a_max:
                samples[k, j] = np.float32(samples[k, j] / att[k, j])
            elif usable[k, j] > 0:
                usable[k, j] = np.float32(0.0)
                samples[k, j] = np.float32(0.0)
                m[j] -= 1
