"""Curvature of the measured plate: its principal radii and a per-pixel principal-curvature map.

All points are in the left-camera frame (OpenCV: x right, y down, z forward), in mm. Sign convention:
a curvature or radius is **positive where the surface is convex towards the camera** and negative where
it is concave towards it. The radius of the target's own shape (``radius_mm`` of the result) comes from
the geometric fits of :mod:`pipeline.judge.fits`.

References
----------
.. [1] do Carmo, M., "Differential Geometry of Curves and Surfaces" (1976), sec. 3-3 -- shape operator of a graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from numpy.polynomial import legendre as leg
from scipy import ndimage

from pipeline.judge.fits import MAX_FIT_POINTS, check_grid, grid_sample, local_quadric, pca_frame

#: A principal direction whose sagitta over the plate, ``|k| L^2 / 8`` (L = plate extent along that
#: direction), is below this many mm counts as flat: its radius is reported as None.
FLAT_SAGITTA_MM = 0.5


@dataclass(frozen=True)
class CurvatureResult:
    """Principal curvatures of the measured surface.

    Attributes
    ----------
    principal_radii_mm : (float or None, float or None)
        ``(r1, r2)``, signed (+ convex towards the camera), ``|r1| <= |r2|``; None where the surface is flat
        in that direction (sagitta over the plate below ``flat_sagitta_mm``).
    principal_curvatures_per_mm : (float, float)
        ``(k1, k2)`` behind the radii, signed, ``|k1| >= |k2|`` (reported even when flat).
    principal_directions : (2, 3) float64
        Unit tangent directions of k1 and k2 at the plate centre, left-camera frame.
    curvature_map : (H, W, 2) float32
        Per-pixel principal curvatures ``(k1, k2)`` in 1/mm, signed, ``|k1| >= |k2|``; NaN outside the mask.
    polynomial_degree : int
        Total degree of the height polynomial the map comes from.
    fit_rms_mm : float
        RMS height residual of that polynomial, mm.
    """

    principal_radii_mm: tuple[float | None, float | None]
    principal_curvatures_per_mm: tuple[float, float]
    principal_directions: np.ndarray
    curvature_map: np.ndarray
    polynomial_degree: int
    fit_rms_mm: float


def _choose_degree(rho: float) -> int:
    """Polynomial degree for a height field whose worst ``|k| * half-extent`` is rho.

    The height of a circular arc, ``R (1 - sqrt(1 - (rho t)^2))`` on ``t in [-1, 1]``, has its singularity
    at ``t = 1/rho``; a Legendre series converges like ``r^-deg`` with ``r = 1/rho + sqrt(1/rho^2 - 1)``
    (Bernstein ellipse). Take the degree for ``r^-deg <= 1e-4``, even, between 4 and 12."""
    rho = min(max(rho, 1e-6), 0.95)
    r = 1.0 / rho + math.sqrt(1.0 / rho**2 - 1.0)
    deg = math.ceil(math.log(1e4) / math.log(r))
    deg += deg % 2
    return int(min(max(deg, 4), 12))


class _HeightPoly:
    """``h(x, y)`` as a total-degree Legendre polynomial on the normalised plate box."""

    def __init__(self, q: np.ndarray, deg: int) -> None:
        lo, hi = q[:, :2].min(axis=0), q[:, :2].max(axis=0)
        self.mid = (lo + hi) / 2
        self.half = np.maximum((hi - lo) / 2, 1e-9)
        self.deg = deg
        ii, jj = np.meshgrid(np.arange(deg + 1), np.arange(deg + 1), indexing="ij")
        self.keep = ((ii + jj) <= deg).ravel()
        xn, yn = self._norm(q[:, 0], q[:, 1])
        V = leg.legvander2d(xn, yn, [deg, deg])[:, self.keep]
        # Normal equations: Legendre columns on [-1, 1] are close to orthogonal, so V^T V is well conditioned
        # (far cheaper than an SVD least squares on 20 000 x 91).
        coef = np.linalg.solve(V.T @ V, V.T @ q[:, 2])
        C = np.zeros((deg + 1) ** 2)
        C[self.keep] = coef
        self.C = C.reshape(deg + 1, deg + 1)
        self.rms = float(np.sqrt(np.mean((V @ coef - q[:, 2]) ** 2)))
        sx, sy = 1.0 / self.half
        dx = leg.legder(self.C, 1, sx, axis=0)
        self.d = {
            "x": dx,
            "y": leg.legder(self.C, 1, sy, axis=1),
            "xx": leg.legder(self.C, 2, sx, axis=0),
            "xy": leg.legder(dx, 1, sy, axis=1),
            "yy": leg.legder(self.C, 2, sy, axis=1),
        }

    def _norm(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (x - self.mid[0]) / self.half[0], (y - self.mid[1]) / self.half[1]

    def tensor(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Second fundamental form in an orthonormal tangent basis (e1 along r_x), (M, 3): B11, B12, B22.
        Normal is the graph's upward normal (+h)."""
        xn, yn = self._norm(x, y)
        # the Legendre polynomials at the points once, each derivative a product with its coefficients
        # (legval2d's recurrence per derivative took 3-10 times as long; the same values to ~1e-15)
        vx, vy = leg.legvander(xn, self.deg), leg.legvander(yn, self.deg)

        def value(c: np.ndarray) -> np.ndarray:
            rows, cols = c.shape
            out: np.ndarray = np.einsum("mi,mi->m", vx[:, :rows] @ c, vy[:, :cols])
            return out

        hx, hy, hxx, hxy, hyy = (value(self.d[key]) for key in ("x", "y", "xx", "xy", "yy"))
        E, F, G = 1 + hx * hx, hx * hy, 1 + hy * hy
        w = np.sqrt(1 + hx * hx + hy * hy)
        L, M, N = hxx / w, hxy / w, hyy / w
        den = E * G - F * F
        a11 = 1 / np.sqrt(E)
        a22 = np.sqrt(E / den)
        a21 = -F / np.sqrt(E * den)
        b11 = a11 * a11 * L
        b12 = a11 * (a21 * L + a22 * M)
        b22 = a21 * a21 * L + 2 * a21 * a22 * M + a22 * a22 * N
        return np.stack([b11, b12, b22], axis=1)


def _eig_sym2(b: np.ndarray) -> np.ndarray:
    """Eigenvalues of symmetric 2x2 tensors (M, 3) -> (M, 2) ordered by decreasing magnitude."""
    mean = (b[:, 0] + b[:, 2]) / 2
    rad = np.sqrt(((b[:, 0] - b[:, 2]) / 2) ** 2 + b[:, 1] ** 2)
    lam = np.stack([mean + rad, mean - rad], axis=1)
    swap = np.abs(lam[:, 1]) > np.abs(lam[:, 0])
    lam[swap] = lam[swap][:, ::-1]
    return lam


def principal_curvatures(
    points_mm: npt.ArrayLike,
    mask: npt.ArrayLike,
    *,
    flat_sagitta_mm: float = FLAT_SAGITTA_MM,
    max_points: int = MAX_FIT_POINTS,
) -> CurvatureResult:
    """Principal radii and a per-pixel principal-curvature map of the measured surface.

    Parameters
    ----------
    points_mm : (H, W, 3) array_like of float
        Surface point of each pixel, left-camera frame, mm (ignored outside the mask).
    mask : (H, W) bool
        True where the point is valid; at least 50 valid pixels.
    flat_sagitta_mm : float
        A principal direction counts as flat (radius None) when ``|k| L^2 / 8 < flat_sagitta_mm``, L the
        plate's extent along it (mm). Default 0.5 mm: a quarter of the usual 2 mm tolerance.
    max_points : int
        The height polynomial is fitted on at most this many points (uniform subsample).

    Returns
    -------
    CurvatureResult
        Signed principal radii (+ convex towards the camera, ``|r1| <= |r2|``), curvatures, directions,
        and the (H, W, 2) float32 curvature map (1/mm, NaN outside the mask).

    Raises
    ------
    ValueError
        On bad shapes, dtypes, non-finite points in the mask, or a non-positive ``flat_sagitta_mm``.

    Notes
    -----
    The surface is written as a height field ``h(x, y)`` over its PCA plane and fitted by a Legendre
    polynomial of total degree 4..12 (chosen from a first quadric's curvature so the truncation error
    of a circular arc stays below ~1e-4 of the height). The exact shape operator of the graph (first and
    second fundamental forms, [1]) gives the curvature at every point -- not the vertex curvature of a
    parabola, which is what biases a global quadric. The plate's principal curvatures are the eigenvalues
    of the median of the per-point curvature tensor (expressed in a tangent basis aligned with the plate
    axes), so a sphere gives two equal radii without the bias of sorting noisy pairs. The map is evaluated
    on a grid of at most ~300 x 300 pixels and interpolated bilinearly to full size (it is a smooth
    polynomial field; its resolution is that of the polynomial, not of the pixels).
    """
    pts, m = check_grid(points_mm, mask, min_points=50)
    if not (math.isfinite(flat_sagitta_mm) and flat_sagitta_mm > 0):
        raise ValueError(
            f"flat_sagitta_mm: expected a positive number of mm, got {flat_sagitta_mm}"
        )
    sub = grid_sample(pts, m, max_points)
    c, frame, q, deg = _height_frame(sub)
    poly = _HeightPoly(q, deg)
    lam, directions, radii = _plate_curvature(poly, q, frame, flat_sagitta_mm)
    return CurvatureResult(
        principal_radii_mm=(radii[0], radii[1]),
        principal_curvatures_per_mm=(float(lam[0]), float(lam[1])),
        principal_directions=directions,
        curvature_map=_curvature_map(pts, m, c, frame, poly),
        polynomial_degree=deg,
        fit_rms_mm=poly.rms,
    )


def _height_frame(sub: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The plate frame of points (M, 3): centroid, rows (ex, ey, ez) with ez towards the camera and ex
    along a first quadric's strongest curvature, the points in it (M, 3), and the polynomial degree."""
    c, frame = pca_frame(sub)
    frame = frame * np.array([[1.0], [-1.0], [-1.0]])  # ez towards the camera, still right-handed
    q = (sub - c) @ frame.T
    a = local_quadric(q)
    evals, evecs = np.linalg.eigh(np.array([[2 * a[3], a[4]], [a[4], 2 * a[5]]]))
    # Turn x_p to the quadric's direction of strongest curvature: the tangent basis below (e1 along r_x)
    # then follows the principal directions, so their median tensor does not mix k1 into k2.
    i_max = int(np.argmax(np.abs(evals)))
    ex = evecs[0, i_max] * frame[0] + evecs[1, i_max] * frame[1]
    frame = np.stack([ex, np.cross(frame[2], ex), frame[2]])
    q = (sub - c) @ frame.T
    half = (q[:, :2].max(axis=0) - q[:, :2].min(axis=0)) / 2
    deg = _choose_degree(float(np.max(np.abs(evals)) * np.max(half)))
    return c, frame, q, deg


def _plate_curvature(
    poly: _HeightPoly, q: np.ndarray, frame: np.ndarray, flat_sagitta_mm: float
) -> tuple[np.ndarray, np.ndarray, list[float | None]]:
    """The plate's principal curvatures (2,), directions (2, 3) and radii (None where flat): the
    eigen-decomposition of the median curvature tensor over the points ``q`` (plate frame)."""
    # The graph normal points towards the camera, so a surface convex towards the camera has negative II;
    # flip to our sign convention.
    b = -poly.tensor(q[:, 0], q[:, 1])
    bm = np.median(b, axis=0)
    tens = np.array([[bm[0], bm[1]], [bm[1], bm[2]]])
    lam, vec = np.linalg.eigh(tens)
    order = np.argsort(-np.abs(lam))
    lam, vec = lam[order], vec[:, order]
    directions = vec.T @ frame[:2]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii: list[float | None] = []
    for i in range(2):
        proj = q[:, :2] @ vec[:, i]
        extent = float(proj.max() - proj.min())
        sag = abs(lam[i]) * extent**2 / 8
        radii.append(float(1.0 / lam[i]) if sag >= flat_sagitta_mm else None)
    return lam, directions, radii


def _curvature_map(
    pts: np.ndarray, m: np.ndarray, c: np.ndarray, frame: np.ndarray, poly: _HeightPoly
) -> np.ndarray:
    """The (H, W, 2) float32 per-pixel principal curvatures (1/mm), NaN outside the mask ``m``.

    Evaluated at every valid pixel of small grids; on large grids at every step-th pixel (step odd, at
    most ~300 x 300 samples) and interpolated bilinearly. With an odd step, sample j sits at pixel
    j*step + (step-1)/2, exactly where cv2.resize by the factor step puts source pixel j.
    """
    H, W = m.shape
    n_valid = int(np.count_nonzero(m))
    step = max(1, math.ceil(max(H, W) / 300))
    step += 1 - step % 2
    o = (step - 1) // 2
    coarse_mask = m[o::step, o::step]
    if n_valid <= 200_000 or not coarse_mask.any():
        qv = (pts[m] - c) @ frame.T
        kmap: np.ndarray = np.full((H, W, 2), np.nan, dtype=np.float32)
        kmap[m] = _eig_sym2(-poly.tensor(qv[:, 0], qv[:, 1]))
    else:
        qc = (pts[o::step, o::step][coarse_mask] - c) @ frame.T
        kmap_c = np.empty((*coarse_mask.shape, 2), dtype=np.float32)
        kmap_c[coarse_mask] = _eig_sym2(-poly.tensor(qc[:, 0], qc[:, 1]))
        if not coarse_mask.all():
            # Extend the smooth field nearest-neighbour outside the mask so the interpolation at the mask's
            # border stays defined; those pixels are set to NaN again below.
            _, (ri, ci) = ndimage.distance_transform_edt(~coarse_mask, return_indices=True)
            kmap_c = kmap_c[ri, ci]
        hc, wc = coarse_mask.shape
        kmap = cv2.resize(kmap_c, (wc * step, hc * step), interpolation=cv2.INTER_LINEAR)
        if kmap.shape[0] < H or kmap.shape[1] < W:
            kmap = np.pad(
                kmap,
                ((0, max(0, H - kmap.shape[0])), (0, max(0, W - kmap.shape[1])), (0, 0)),
                mode="edge",
            )
        kmap = kmap[:H, :W]
    # NaN off the mask a channel at a time (a masked copy broadcast over both took 2.5 times as long)
    nan = np.float32(np.nan)
    return np.asarray(cv2.merge([np.where(m, kmap[..., k], nan) for k in range(2)]))
