"""Step 2: the smooth surface, inverse depth as a polynomial in normalised image coordinates, fitted robustly
to the stereo depth from the nearest candidates outwards; its depth, area per pixel and normals on the grid."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.solvers import labelled

#: Default depth band (mm) about the fitted surface within which a pixel can belong to the plate. The
#: floor and the supports lie hundreds of millimetres behind the plate; a real bent edge or dent tens of
#: millimetres off the smooth fit stays inside (so a forming defect is measured and judged, not cut away).
DEPTH_BAND_MM = 50.0
#: Polynomial degree of the final surface fit (in inverse depth over normalised image coordinates).
SURFACE_DEGREE = 4
#: Samples used for the surface fit (a regular stride over the image).
FIT_SAMPLES = 20_000
#: The surface fit starts on the nearest candidates: this share of them (by depth).
SEED_SHARE = 0.25


def normalised_coords(
    K: np.ndarray, shape: tuple[int, int], stride: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image coordinates ``(x, y)`` of ``K^-1 (u, v, 1)`` at every ``stride``-th pixel of a (H, W) grid."""
    h, w = shape
    u = np.arange(0, w, stride, dtype=np.float64)
    v = np.arange(0, h, stride, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    x = Kinv[0, 0] * u[None, :] + Kinv[0, 1] * v[:, None] + Kinv[0, 2]
    y = np.broadcast_to(Kinv[1, 1] * v[:, None] + Kinv[1, 2], x.shape)
    return x, y


def _powers(v: np.ndarray, degree: int) -> list[np.ndarray]:
    """``v^0 .. v^degree`` by repeated products: numpy's ``v**k`` (k >= 3) of a negative base takes a slow
    scalar path, and a product differs from it only in the last bit."""
    powers = [np.ones_like(v), v]
    for _ in range(2, degree + 1):
        powers.append(powers[-1] * v)
    return powers[: degree + 1]


def design(
    x: np.ndarray, y: np.ndarray, degree: int, scale: tuple[float, float, float, float]
) -> np.ndarray:
    """Monomials ``xs^i ys^j`` (i + j <= degree) of the centred, scaled coordinates, (M, T)."""
    xs = (x - scale[0]) / scale[1]
    ys = (y - scale[2]) / scale[3]
    px, py = _powers(xs, degree), _powers(ys, degree)
    cols = [px[i] * py[d - i] for d in range(degree + 1) for i in range(d, -1, -1)]
    return np.stack(cols, axis=-1)


def _robust_fit(X: np.ndarray, w_obs: np.ndarray, z: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Coefficients of inverse depth by least squares with Huber weights on the depth residual (mm)."""
    weights = np.ones(len(w_obs))
    coef = np.zeros(X.shape[1])
    for i in range(iterations):
        Xw = X * weights[:, None]
        # normal equations: the coordinates are centred and scaled, so X^T W X stays well conditioned
        coef = np.linalg.solve(Xw.T @ X, Xw.T @ w_obs)
        if i == iterations - 1:
            break
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.abs(z - 1.0 / (X @ coef))
        r = np.nan_to_num(r, nan=1e9)
        scale = max(1.4826 * float(np.median(r)), 0.5)
        weights = np.minimum(1.0, 1.345 * scale / np.maximum(r, 1e-12))
    return coef


def largest_component(mask: np.ndarray, connectivity: int = 8) -> np.ndarray:
    """The largest connected component of ``mask`` (all False when it is empty)."""
    n, labels, areas = labelled(mask, connectivity=connectivity)
    if n <= 1:
        return np.zeros_like(mask)
    largest: np.ndarray = labels == 1 + int(np.argmax(areas[1:]))
    return largest


@dataclass(frozen=True)
class Surface:
    """A fitted smooth surface: inverse depth as a polynomial of ``degree`` in the scaled normalised
    coordinates (see :func:`design`), and the robust RMS (mm) of the depth about it."""

    coef: np.ndarray
    degree: int
    scale: tuple[float, float, float, float]
    rms_mm: float

    def depth(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth (mm) at normalised coordinates; NaN where the surface does not face the camera."""
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = design(x, y, self.degree, self.scale) @ self.coef
            return np.where(inv > 0, 1.0 / inv, np.nan)


def fit_surface(
    depth: np.ndarray, candidates: np.ndarray, K: np.ndarray, band_mm: float
) -> Surface | None:
    """Grow a robust smooth fit from the nearest candidates (see the module docstring); None if too few."""
    h, w = depth.shape
    stride = max(1, int(round(math.sqrt(h * w / FIT_SAMPLES))))
    z = depth[::stride, ::stride].astype(np.float64)
    cand = candidates[::stride, ::stride] & np.isfinite(z) & (z > 0)
    if np.count_nonzero(cand) < 50:
        return None
    x, y = normalised_coords(K, (h, w), stride)
    x, y = x[: z.shape[0], : z.shape[1]], y[: z.shape[0], : z.shape[1]]
    xs, ys = x[cand], y[cand]
    scale = (float(xs.mean()), float(xs.std()) + 1e-9, float(ys.mean()), float(ys.std()) + 1e-9)
    zc = z[cand]
    wc = 1.0 / zc
    monomials = design(xs, ys, SURFACE_DEGREE, scale)  # columns ordered by total degree
    inliers = zc <= np.quantile(zc, SEED_SHARE)
    degree, coef, r = 1, None, None
    for it in range(8):
        degree = 2 if it < 2 else (3 if it < 4 else SURFACE_DEGREE)
        if np.count_nonzero(inliers) < 3 * (degree + 1) * (degree + 2):
            degree = 1
        X = monomials[:, : (degree + 1) * (degree + 2) // 2]
        coef = _robust_fit(X[inliers], wc[inliers], zc[inliers])
        with np.errstate(divide="ignore", invalid="ignore"):
            r = zc - 1.0 / (X @ coef)
        near = np.abs(np.nan_to_num(r, nan=np.inf)) < band_mm
        grid = np.zeros(z.shape, bool)
        grid[cand] = near
        new = largest_component(grid)[cand]
        if degree == SURFACE_DEGREE and np.array_equal(new, inliers):
            break
        inliers = new
        if np.count_nonzero(inliers) < 50:
            return None
    if coef is None or r is None:
        return None
    r = r[inliers]
    rms = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return Surface(coef=coef, degree=degree, scale=scale, rms_mm=rms)


def _on_full_grid(values: np.ndarray, shape: tuple[int, int], step: int) -> np.ndarray:
    """Bilinear upsampling of values (float) sampled at pixels ``(step i, step j)`` to the (H, W) grid."""
    h, w = shape
    map_x = np.broadcast_to((np.arange(w, dtype=np.float32) / step)[None, :], (h, w))
    map_y = np.broadcast_to((np.arange(h, dtype=np.float32) / step)[:, None], (h, w))
    return cv2.remap(
        values.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def _coarse_coords(
    K: np.ndarray, shape: tuple[int, int], step: int
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates at pixels ``(step i, step j)`` covering the (H, W) grid (last sample at or
    beyond the last pixel)."""
    h, w = shape
    grid = (step * (-(-(h - 1) // step)) + 1, step * (-(-(w - 1) // step)) + 1)
    return normalised_coords(K, grid, step)


def surface_depth(
    surface: Surface, K: np.ndarray, shape: tuple[int, int], step: int = 8
) -> np.ndarray:
    """(H, W) float32 depth (mm) of the fitted surface: evaluated every ``step`` pixels, bilinear between
    (a surface of degree 4 over the image is smooth at that scale: the interpolation errs by micrometres)."""
    x, y = _coarse_coords(K, shape, step)
    return _on_full_grid(surface.depth(x, y), shape, step)


@dataclass(frozen=True)
class Geometry:
    """The fitted surface's area per pixel (mm^2) and unit normal (towards the camera), every ``step`` px."""

    area: np.ndarray  # (h', w') float64
    normal: np.ndarray  # (h', w', 3) float64
    step: int

    def area_full(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) float32 area per pixel (mm^2) on the full grid (bilinear)."""
        return _on_full_grid(self.area, shape, self.step)

    def normals_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(M, 3) float32 normals at pixels (bilinear on the coarse grid)."""
        m = rows.size
        width = min(max(m, 1), 4096)  # cv2.remap wants both sizes < 32767
        height = -(-m // width) if m else 1
        map_x = np.zeros(width * height, np.float32)
        map_y = np.zeros(width * height, np.float32)
        map_x[:m] = cols / self.step
        map_y[:m] = rows / self.step
        grid_x, grid_y = map_x.reshape(height, width), map_y.reshape(height, width)
        comps = [
            cv2.remap(
                self.normal[..., i].astype(np.float32),
                grid_x,
                grid_y,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            ).ravel()[:m]
            for i in range(3)
        ]
        n = np.stack(comps, axis=-1)
        unit: np.ndarray = n / np.linalg.norm(n, axis=-1, keepdims=True)
        return unit


def surface_geometry(
    surface: Surface, K: np.ndarray, shape: tuple[int, int], step: int = 16
) -> Geometry:
    """Area per pixel and normals of the fitted surface from its analytic-by-differences derivatives.

    With ``P = z(x, y) (x, y, 1)``: ``dP/dx = z_x (x, y, 1) + z (1, 0, 0)``, likewise for y; a pixel spans
    ``dx = 1/fx``, ``dy = 1/fy`` (skew neglected), so its area is ``|dP/dx x dP/dy| / (fx fy)``."""
    x, y = _coarse_coords(K, shape, step)
    d = 1e-4
    z = surface.depth(x, y)
    zx = (surface.depth(x + d, y) - surface.depth(x - d, y)) / (2 * d)
    zy = (surface.depth(x, y + d) - surface.depth(x, y - d)) / (2 * d)
    a = np.stack([zx * x + z, zx * y, zx], axis=-1)
    b = np.stack([zy * x, zy * y + z, zy], axis=-1)
    n = np.cross(a, b)
    norm = np.linalg.norm(n, axis=-1)
    n = n / norm[..., None]
    n = np.where(n[..., 2:3] > 0, -n, n)  # towards the camera: n_z < 0
    return Geometry(area=norm / (K[0, 0] * K[1, 1]), normal=n, step=step)
