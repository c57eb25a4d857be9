"""The plate among its surroundings: which pixels of the left undistorted grid see the plate.

Brightness alone cannot tell a plate from a shop floor, supports or a conveyor that the same lights
make as bright; geometry can. The stereo pair puts the plate and everything around it at depths
hundreds of millimetres apart, so the plate is found as the near, smooth sheet of the stereo depth:

1. *Candidates* (:func:`candidate_mask`): pixels that are not dark (brightest photometric sample at
   least ``dark_fraction`` of the image's bright level). A dark conveyor is excluded here; a lit floor
   is not. This is also the region the stereo pair should be matched over.
2. *Surface*: a smooth surface, inverse depth ``1/z`` as a polynomial in the normalised image
   coordinates ``(x, y) = K^-1 (u, v, 1)`` (exact for a plane; a curved plate at 3 m is within a few
   millimetres at degree 4), is fitted robustly to the stereo depth. The fit starts on the nearest
   candidates (the plate lies above the floor and the supports) and grows: each round keeps the
   largest connected set of candidates within ``depth_band_mm`` of the current surface and refits.
3. *Plate*: the largest 8-connected set of candidates whose stereo depth lies within the band, less
   the parts narrower than ``support_width_mm`` whose depth leaves the smooth surface: supports that
   reach out beside the plate at its depth (a rail under its edge). Where such a support met the
   plate, the edge band is widened to a quarter of that width.
4. *Holes stay holes*: a region enclosed by the plate is filled only if at most a quarter of it shows
   depth off the plate or darkness, and it is a small dropout (at most ``max_dropout_mm2``) or, given
   photometric normals, its normals follow the fitted surface (median within ``DROPOUT_NORMAL_DEG``);
   anything showing what lies behind is an opening and stays out of the mask, as does a larger
   unmatched area without agreeing normals. Nothing is ever filled across a depth step: a filled
   region has no stereo depth of its own (see :meth:`Segmentation.stereo_prior`).
5. *The rim*: pixels the stereo pair could not match next to the plate (its matching windows
   straddle the edge) are added only where darkness bounds them within ``reach_px`` (a dark
   background makes the edge sharp); next to a lit floor they stay out (there the unmatched strip is
   mostly the floor hidden from the right camera).
6. *Edge band*: the plate's pixels within ``edge_px`` of its boundary (outline and openings; the
   image frame does not count) mix plate and surroundings in the photometric images; they are
   excluded from the mask and counted. Given photometric normals, pixels a little further in whose
   normal leaves the fitted surface's by more than ``EDGE_NORMAL_DEG`` join the band (the stereo
   matcher smears the plate's depth a few pixels onto what lies beside it).
7. *Surroundings step*: along the boundary, the depth of what lies beside the plate relative to the
   plate's surface, for telling segmentation artefacts at the edge from real edge defects
   (:func:`pipeline.verdict.judge`).

Without a usable stereo depth (no pair, or too little matched) the plate is the largest candidate
component with small holes filled (the dark-background case), and the result says so.

Conventions: images ``[row, col]``, pixel ``(u, v) = (col, row)``; depth ``z`` in mm along the left
camera's optical axis on the left undistorted grid (``X = z K^-1 (u, v, 1)``), NaN where unmatched;
areas in mm^2 on the fitted surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

#: Default depth band (mm) about the fitted surface within which a pixel can belong to the plate. The
#: floor and the supports lie hundreds of millimetres behind the plate; a real bent edge or dent tens of
#: millimetres off the smooth fit stays inside (so a forming defect is measured and judged, not cut away).
DEPTH_BAND_MM = 50.0
#: Default width (px) of the edge band excluded along the plate's outline and openings.
EDGE_PX = 2
#: Default largest unmatched region (mm^2) inside the plate that is filled as a stereo dropout.
MAX_DROPOUT_MM2 = 1500.0
#: Default width (mm) under which a part of the matched plate that leaves the smooth surface is taken for a
#: support reaching out beside the plate (rails and blocks are 100-200 mm wide).
SUPPORT_WIDTH_MM = 250.0
#: A narrow part is a support when PROTRUSION_SHARE of its pixels have a stereo depth farther from the smooth
#: surface than this (mm) or five times the fit's RMS: a support's flat top parts from a curved plate's
#: continuation.
PROTRUSION_RESIDUAL_MM = 8.0
PROTRUSION_SHARE = 0.3
#: Default share of the image's bright level (95th percentile of the brightest sample) below which a
#: pixel is dark: painted and rusty steel (albedo 0.25-0.7) stays above it, a dark conveyor (~0.05)
#: below, even when a lit floor's painted lines set the bright level.
DARK_FRACTION = 0.2
#: Dark specks of at most this many pixels enclosed by bright ones are not dark (a rust pore, noise):
#: the stereo matcher would otherwise make a hole of its window's size around each.
DARK_SPECK_PX = 9
#: A larger unmatched area inside the plate is filled when the median angle between its photometric
#: normals and the fitted surface's is at most this (deg): the stereo pair missed plate there.
DROPOUT_NORMAL_DEG = 3.0
#: A dropout may hold at most this share of pixels with off-plate depth or darkness.
DROPOUT_MAX_OFF_SHARE = 0.25
#: Near the boundary (``edge_px`` + this many px) a pixel whose photometric normal is more than
#: EDGE_NORMAL_DEG from the fitted surface's is not measured: a bent edge turns its normal by far less
#: over its first pixels, a support's side by ~90 deg.
EDGE_NORMAL_ZONE_PX = 3
EDGE_NORMAL_DEG = 35.0
#: Polynomial degree of the final surface fit (in inverse depth over normalised image coordinates).
SURFACE_DEGREE = 4
#: Samples used for the surface fit (a regular stride over the image).
FIT_SAMPLES = 20_000
#: The surface fit starts on the nearest candidates: this share of them (by depth).
SEED_SHARE = 0.25
#: Least share of the candidates with a stereo depth for a geometric segmentation.
MIN_MATCHED_SHARE = 0.1
#: plain_outline / plain_depth: the shares of the brightness mask's area that may be dark inside it (an opening), lit
#: outside it (a floor, supports) and off its smooth surface in depth. Measured at 1224x1024: plain
#: plates 0 dark inside, 0.06-0.4 % lit outside (more with LEDs); a 60 mm round hole 0.13 % dark
#: inside; a lit floor 34-400 % lit outside.
PLAIN_OPENING_SHARE = 0.0005
PLAIN_LIT_SHARE = 0.02
PLAIN_OFF_SURFACE_SHARE = 0.002
#: ... lit pixels within this many pixels of the mask are its own (mixed) edge.
PLAIN_MARGIN_PX = 5


@dataclass(frozen=True)
class Segmentation:
    """Where the plate is on the left undistorted grid, and what was left out.

    Attributes
    ----------
    mask : (H, W) bool
        The plate's pixels to measure (edge band excluded).
    edge_band : (H, W) bool
        Plate pixels within ``edge_px`` of the plate's outline or of an opening, excluded from
        ``mask`` because they may mix plate and surroundings.
    holes : (H, W) bool
        Regions enclosed by the plate that are not measured: openings (depth behind the plate or
        dark) and areas the stereo pair could not match that are too large to fill.
    surface_depth_mm : (H, W) float32
        Depth of the fitted smooth surface (mm, every pixel; NaN where it does not face the camera
        or in brightness-only mode).
    surroundings_step_mm : (H, W) float32
        At plate pixels (``mask | edge_band``) within ``step_zone_px`` of the plate's boundary: the
        stereo depth of the nearest pixel beside the plate that has one, minus the fitted surface's
        depth here (mm; positive when the surroundings lie behind the plate, away from the cameras);
        ``+inf`` where darkness (no depth: a dark background) is nearer; NaN elsewhere and where
        neither is near (a wide unmatched strip).
    pixel_area_mm2 : (H, W) float32
        Area of the fitted surface one pixel sees, mm^2 (NaN in brightness-only mode).
    plate_area_mm2, edge_band_area_mm2, holes_area_mm2, filled_area_mm2 : float
        Areas on the fitted surface (NaN in brightness-only mode), mm^2: the mask, the edge band, the
        holes kept, and the unmatched areas filled (dropouts, or with agreeing normals).
    n_mask, n_edge_band, n_holes, n_hole_pixels, n_off_depth, n_dark, n_unmatched : int
        Pixels in the mask and edge band; openings and unmatched
        regions kept as holes (count and pixels); candidate pixels whose stereo depth lies off the
        plate's surface; dark pixels; candidate pixels without stereo depth.
    fit_rms_mm : float
        Robust RMS (1.4826 MAD) of the stereo depth about the fitted surface over the plate, mm
        (NaN in brightness-only mode).
    depth_band_mm : float
        The band used.
    method : {"stereo", "brightness"}
    reasons : tuple of str
        What the segmentation decided that the operator should be able to read (fallbacks, holes
        kept, dropouts filled, edge band, area against the target's).
    """

    mask: np.ndarray
    edge_band: np.ndarray
    holes: np.ndarray
    surface_depth_mm: np.ndarray
    surroundings_step_mm: np.ndarray
    pixel_area_mm2: np.ndarray
    plate_area_mm2: float
    edge_band_area_mm2: float
    holes_area_mm2: float
    filled_area_mm2: float
    n_mask: int
    n_edge_band: int
    n_holes: int
    n_hole_pixels: int
    n_off_depth: int
    n_dark: int
    n_unmatched: int
    fit_rms_mm: float
    depth_band_mm: float
    method: str
    reasons: tuple[str, ...]

    def stereo_prior(self, depth_mm) -> np.ndarray:
        """The stereo depth to fuse with the normals: ``depth_mm`` (H, W) where the mask is and the depth lies
        within the band of the plate's surface, NaN elsewhere (mm; so a filled dropout, an edge band or a
        stray match of the floor never pulls the surface)."""
        d = np.asarray(depth_mm, dtype=np.float32)
        if d.shape != self.mask.shape:
            raise ValueError(f"depth_mm: expected shape {self.mask.shape}, got {d.shape}")
        if self.method != "stereo":
            return np.where(self.mask, d, np.float32(np.nan))
        with np.errstate(invalid="ignore"):
            near = np.abs(d - self.surface_depth_mm) < self.depth_band_mm
        return np.where(self.mask & near, d, np.float32(np.nan))

    @property
    def region(self) -> np.ndarray:
        """(H, W) bool: every pixel segmented as plate, ``mask | edge_band``."""
        return self.mask | self.edge_band

    def area_ratio(self, target_area_mm2: float) -> float:
        """Segmented plate area (mask and edge band) over the target's area (dimensionless)."""
        if not (math.isfinite(target_area_mm2) and target_area_mm2 > 0):
            raise ValueError(f"target_area_mm2: expected a positive area in mm^2, got {target_area_mm2}")
        return (self.plate_area_mm2 + self.edge_band_area_mm2) / target_area_mm2


# --------------------------------------------------------------------------- checks


def _image(name: str, value, shape: tuple[int, int] | None = None) -> np.ndarray:
    arr = np.asarray(value)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected an (H, W) array, got shape {arr.shape}")
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape} to match brightness, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name}: expected real numbers, got dtype {arr.dtype}")
    return arr


def _bool_image(name: str, value, shape: tuple[int, int]) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype != np.bool_ or arr.shape != shape:
        raise ValueError(f"{name}: expected a bool array of shape {shape}, got {arr.dtype} {arr.shape}")
    return arr


def _camera_matrix(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"camera_matrix: expected a (3, 3) K with fx, fy > 0, got {np.asarray(K).tolist()}")
    return K


# --------------------------------------------------------------------------- candidates


def candidate_mask(brightness, *, seen=None, dark_fraction: float = DARK_FRACTION) -> np.ndarray:
    """Pixels bright enough to be the plate: not dark against the image's bright level.

    Parameters
    ----------
    brightness : (H, W) array_like of float
        Brightest photometric sample per pixel (any linear unit, e.g. fractions of full scale after
        dark subtraction and intensity normalisation); NaN counts as dark.
    seen : (H, W) bool, optional
        Pixels that have samples at all (False where the undistorted ray leaves the raw image).
    dark_fraction : float
        A pixel is dark below ``dark_fraction`` times the 95th percentile of the (lightly smoothed)
        brightness over the seen pixels (dimensionless, 0..1).

    Returns
    -------
    (H, W) bool
        True where a pixel may be the plate. Over a dark conveyor this is the plate; over a lit floor
        it is most of the image. Meant both for :func:`segment_plate` and as the region the stereo
        pair is matched over (``mask`` of :func:`pipeline.stereo.stereo_depth`).

    Raises
    ------
    ValueError
        Bad shapes or ``dark_fraction``, or no light at all.
    """
    b = _image("brightness", brightness).astype(np.float32)
    shape = b.shape
    ok = np.ones(shape, bool) if seen is None else _bool_image("seen", seen, shape)
    if not (math.isfinite(dark_fraction) and 0 < dark_fraction < 1):
        raise ValueError(f"dark_fraction: expected a share in (0, 1), got {dark_fraction}")
    b = np.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0)
    # smooth the grain so that single dark texels of a rusty plate are not called dark
    smooth = cv2.GaussianBlur(b, (0, 0), 1.0)
    step = max(1, int(math.sqrt(b.size / 200_000)))  # the level from ~200k pixels: as good, and cheaper
    lit = smooth[::step, ::step][ok[::step, ::step]]
    level = float(np.percentile(lit, 95)) if lit.size else 0.0
    if not level > 0:
        raise ValueError("brightness: expected some light on the seen pixels, got none above zero")
    bright = ok & (smooth >= dark_fraction * level)
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~bright).view(np.uint8), connectivity=4)
    speck = stats[:, cv2.CC_STAT_AREA] <= DARK_SPECK_PX
    speck[0] = False  # label 0: the bright pixels
    return (bright | speck[labels]) & ok


# --------------------------------------------------------------------------- surface fit


def _normalised_coords(K: np.ndarray, shape: tuple[int, int], stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    u = np.arange(0, w, stride, dtype=np.float64)
    v = np.arange(0, h, stride, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    x = Kinv[0, 0] * u[None, :] + Kinv[0, 1] * v[:, None] + Kinv[0, 2]
    y = np.broadcast_to(Kinv[1, 1] * v[:, None] + Kinv[1, 2], x.shape)
    return x, y


def _design(x: np.ndarray, y: np.ndarray, degree: int, scale: tuple[float, float, float, float]) -> np.ndarray:
    """Monomials ``xs^i ys^j`` (i + j <= degree) of the centred, scaled coordinates, (M, T)."""
    xs = (x - scale[0]) / scale[1]
    ys = (y - scale[2]) / scale[3]
    cols = [xs**i * ys**j for d in range(degree + 1) for i in range(d, -1, -1) for j in [d - i]]
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


def _largest_component(mask: np.ndarray, connectivity: int = 8) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=connectivity)
    if n <= 1:
        return np.zeros_like(mask)
    return labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))


@dataclass(frozen=True)
class _Surface:
    coef: np.ndarray
    degree: int
    scale: tuple[float, float, float, float]
    rms_mm: float

    def depth(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = _design(x, y, self.degree, self.scale) @ self.coef
            return np.where(inv > 0, 1.0 / inv, np.nan)


def _fit_surface(depth: np.ndarray, candidates: np.ndarray, K: np.ndarray, band_mm: float) -> _Surface | None:
    """Grow a robust smooth fit from the nearest candidates (see the module docstring); None if too few."""
    h, w = depth.shape
    stride = max(1, int(round(math.sqrt(h * w / FIT_SAMPLES))))
    z = depth[::stride, ::stride].astype(np.float64)
    cand = candidates[::stride, ::stride] & np.isfinite(z) & (z > 0)
    if np.count_nonzero(cand) < 50:
        return None
    x, y = _normalised_coords(K, (h, w), stride)
    x, y = x[: z.shape[0], : z.shape[1]], y[: z.shape[0], : z.shape[1]]
    xs, ys = x[cand], y[cand]
    scale = (float(xs.mean()), float(xs.std()) + 1e-9, float(ys.mean()), float(ys.std()) + 1e-9)
    zc = z[cand]
    wc = 1.0 / zc
    monomials = _design(xs, ys, SURFACE_DEGREE, scale)  # columns ordered by total degree
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
        new = _largest_component(grid)[cand]
        if degree == SURFACE_DEGREE and np.array_equal(new, inliers):
            break
        inliers = new
        if np.count_nonzero(inliers) < 50:
            return None
    r = r[inliers]
    rms = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return _Surface(coef=coef, degree=degree, scale=scale, rms_mm=rms)


def _protrusions(core: np.ndarray, residual: np.ndarray, mm_per_px: float, width_mm: float,
                 max_residual_mm: float) -> np.ndarray:
    """(H, W) bool: the parts of ``core`` narrower than ``width_mm`` (removed by an opening with a disc
    of that diameter) of which ``PROTRUSION_SHARE`` have ``|residual|`` (mm) over ``max_residual_mm``.

    The opening runs on the mask reduced so the disc is ~15 px across (a plate is smooth at that scale);
    the slivers that the reduction adds along straight edges follow the surface and are kept."""
    if width_mm <= 0 or not math.isfinite(mm_per_px) or mm_per_px <= 0:
        return np.zeros_like(core)
    h, w = core.shape
    d_px = width_mm / mm_per_px
    f = max(1, int(d_px // 15))
    small = cv2.resize(core.astype(np.float32), (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA) > 0.5
    k = max(3, int(round(d_px / f)) | 1)
    opened = cv2.morphologyEx(small.view(np.uint8), cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    back = cv2.resize(opened, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    parts = core & ~back
    if not parts.any():
        return parts
    n, labels = cv2.connectedComponents(parts.view(np.uint8), connectivity=8)
    res = np.abs(residual[parts])
    ok = np.isfinite(res)
    lab = labels[parts][ok]
    # a support's part holds the plate's edge strip next to it too (the reduced opening's slivers), whose depth
    # follows the surface: a part is a support when a good share of it (not necessarily half) leaves it
    above = np.bincount(lab, weights=(res[ok] > max_residual_mm).astype(np.float64), minlength=n)
    counted = np.bincount(lab, minlength=n)
    out = above > PROTRUSION_SHARE * counted
    out[0] = False
    return out[labels] & parts


def _wide_parts(parts: np.ndarray, min_half_width_px: float) -> np.ndarray:
    """The connected components of ``parts`` (8-neighbour) at least ``2 min_half_width_px`` wide somewhere
    (slivers along an edge are not)."""
    if not parts.any():
        return parts
    inside = cv2.distanceTransform(parts.view(np.uint8), cv2.DIST_L2, 3)
    n, labels = cv2.connectedComponents(parts.view(np.uint8), connectivity=8)
    widest = np.zeros(n, np.float32)
    np.maximum.at(widest, labels[parts], inside[parts])
    wide = widest >= min_half_width_px
    wide[0] = False
    return wide[labels]


def _on_full_grid(values: np.ndarray, shape: tuple[int, int], step: int) -> np.ndarray:
    """Bilinear upsampling of values (float) sampled at pixels ``(step i, step j)`` to the (H, W) grid."""
    h, w = shape
    map_x = np.broadcast_to((np.arange(w, dtype=np.float32) / step)[None, :], (h, w))
    map_y = np.broadcast_to((np.arange(h, dtype=np.float32) / step)[:, None], (h, w))
    return cv2.remap(values.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _coarse_coords(K: np.ndarray, shape: tuple[int, int], step: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates at pixels ``(step i, step j)`` covering the (H, W) grid (last sample at or
    beyond the last pixel)."""
    h, w = shape
    grid = (step * (-(-(h - 1) // step)) + 1, step * (-(-(w - 1) // step)) + 1)
    return _normalised_coords(K, grid, step)


def _surface_depth(surface: _Surface, K: np.ndarray, shape: tuple[int, int], step: int = 8) -> np.ndarray:
    """(H, W) float32 depth (mm) of the fitted surface: evaluated every ``step`` pixels, bilinear between
    (a surface of degree 4 over the image is smooth at that scale: the interpolation errs by micrometres)."""
    x, y = _coarse_coords(K, shape, step)
    return _on_full_grid(surface.depth(x, y), shape, step)


@dataclass(frozen=True)
class _Geometry:
    """The fitted surface's area per pixel (mm^2) and unit normal (towards the camera), every ``step`` px."""

    area: np.ndarray  # (h', w') float64
    normal: np.ndarray  # (h', w', 3) float64
    step: int

    def area_full(self, shape: tuple[int, int]) -> np.ndarray:
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
        map_x, map_y = map_x.reshape(height, width), map_y.reshape(height, width)
        comps = [cv2.remap(self.normal[..., i].astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE).ravel()[:m] for i in range(3)]
        n = np.stack(comps, axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _geometry(surface: _Surface, K: np.ndarray, shape: tuple[int, int], step: int = 16) -> _Geometry:
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
    return _Geometry(area=norm / (K[0, 0] * K[1, 1]), normal=n, step=step)


def _nearest(outside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (px, L2 5x5 mask) from each pixel to the nearest ``outside`` pixel, and that pixel's flat index."""
    src = (~outside).view(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    zeros = np.flatnonzero(outside.ravel())
    if zeros.size == 0:
        return np.full(outside.shape, np.inf, np.float32), np.zeros(outside.shape, np.intp)
    return dist, zeros[np.clip(labels - 1, 0, zeros.size - 1)]


# --------------------------------------------------------------------------- segmentation


def plain_outline(bright_mask, candidates) -> bool:
    """Whether the plate looks alone in the image: nothing lit around the brightness mask, no opening in it.

    The usual cell: a plate over a dark conveyor. Then the stereo pair and the normals need only the
    brightness mask, and :func:`plain_depth` decides from the stereo depth whether the mask is one sheet.

    Parameters
    ----------
    bright_mask : (H, W) bool
        The brightness mask (:func:`pipeline.preprocess.plate_mask`: Otsu, holes filled, eroded).
    candidates : (H, W) bool
        :func:`candidate_mask`.

    Returns
    -------
    bool
        True when at most PLAIN_OPENING_SHARE of the mask's area is dark inside it (an opening) and at
        most PLAIN_LIT_SHARE is lit outside it beyond PLAIN_MARGIN_PX (a floor, supports).
    """
    mask = _bool_image("bright_mask", bright_mask, np.shape(bright_mask))
    cand = _bool_image("candidates", candidates, mask.shape)
    n = int(np.count_nonzero(mask))
    if n == 0 or np.count_nonzero(mask & ~cand) > PLAIN_OPENING_SHARE * n:
        return False
    size = 2 * PLAIN_MARGIN_PX + 1
    grown = cv2.dilate(mask.view(np.uint8), np.ones((size, size), np.uint8)).view(bool)
    return bool(np.count_nonzero(cand & ~grown) <= PLAIN_LIT_SHARE * n)


def plain_depth(bright_mask, depth_mm, camera_matrix, *, depth_band_mm: float = DEPTH_BAND_MM) -> bool:
    """Whether the stereo depth over the brightness mask is one smooth sheet (no floor taken in).

    Parameters
    ----------
    bright_mask : (H, W) bool
        The brightness mask.
    depth_mm : (H, W) float
        Stereo depth (mm, NaN where unmatched).
    camera_matrix : (3, 3) float
        Intrinsics of the grid, pixels.
    depth_band_mm : float
        Half width of the band around the fitted smooth surface that counts as the plate, mm.

    Returns
    -------
    bool
        True when at most PLAIN_OFF_SURFACE_SHARE of the matched mask pixels lie off the smooth
        surface fitted to them. With :func:`plain_outline`, the brightness mask is then the plate
        and :func:`segment_plate` (~0.5 s at 2448 x 2048) is not needed.
    """
    mask = _bool_image("bright_mask", bright_mask, np.shape(bright_mask))
    depth = np.asarray(depth_mm, dtype=np.float64)
    K = _camera_matrix(camera_matrix)
    surface = _fit_surface(depth, mask, K, depth_band_mm)
    if surface is None:
        return False
    stride = max(1, int(round(math.sqrt(depth.size / FIT_SAMPLES))))
    z = depth[::stride, ::stride]
    inside = mask[::stride, ::stride] & np.isfinite(z) & (z > 0)
    x, y = _normalised_coords(K, depth.shape, stride)
    x, y = x[: z.shape[0], : z.shape[1]], y[: z.shape[0], : z.shape[1]]
    X = _design(x[inside], y[inside], surface.degree, surface.scale)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.abs(z[inside] - 1.0 / (X @ surface.coef)) > depth_band_mm
    return bool(np.count_nonzero(off) <= PLAIN_OFF_SURFACE_SHARE * max(np.count_nonzero(inside), 1))


def segment_plate(
    brightness,
    depth_mm,
    camera_matrix,
    *,
    seen=None,
    candidates=None,
    normals=None,
    depth_band_mm: float = DEPTH_BAND_MM,
    edge_px: int = EDGE_PX,
    depth_scale_px: int = 1,
    max_dropout_mm2: float = MAX_DROPOUT_MM2,
    reach_px: int = 4,
    support_width_mm: float = SUPPORT_WIDTH_MM,
    step_zone_px: int = 8,
    target_area_mm2: float | None = None,
    dark_fraction: float = DARK_FRACTION,
) -> Segmentation:
    """Segment the plate from its surroundings by the stereo depth, brightness only as a first guess.

    Parameters
    ----------
    brightness : (H, W) array_like of float
        Brightest photometric sample per pixel on the left undistorted grid (any linear unit), as
        preprocessing computes it.
    depth_mm : (H, W) array_like of float or None
        Stereo depth, mm along the left optical axis, on the same grid; NaN where unmatched. It must
        cover the surroundings too (match the pair over :func:`candidate_mask`, not over a plate mask).
        None: brightness only.
    camera_matrix : (3, 3) array_like
        K of the left undistorted grid (pixels).
    seen : (H, W) bool, optional
        Pixels that have photometric samples (False outside the raw image's undistorted footprint).
    candidates : (H, W) bool, optional
        The pixels that may be plate (default :func:`candidate_mask` of ``brightness``).
    normals : (H, W, 3) array_like of float, optional
        Photometric unit normals (left camera frame, towards the camera; NaN where unknown), e.g.
        :func:`pipeline.normals.estimate_normals` over the candidates. Near the boundary (within
        ``edge_px + EDGE_NORMAL_ZONE_PX``) a pixel whose normal is more than ``EDGE_NORMAL_DEG`` from
        the fitted surface's is left out of the mask (into the edge band): the side of a support,
        or a pixel that mixes plate and surroundings, which the stereo matcher smeared to the
        plate's depth. A bent edge turns its normals by far less over its first pixels.
    depth_band_mm : float
        Largest distance (mm, along the optical axis) of a plate pixel's stereo depth from the fitted
        smooth surface.
    edge_px : int
        Width of the edge band, pixels (>= 0), for a stereo depth matched at this grid's resolution.
    depth_scale_px : int
        The stereo depth was matched on this grid reduced this many times (``pipeline.run`` matches a
        pair wider than 1600 px reduced): the matcher's smearing across an edge grows with it, so the
        edge band and the zone of the normals check are this many times wider (>= 1).
    max_dropout_mm2 : float
        Largest unmatched region inside the plate filled as a stereo dropout, mm^2 (>= 0).
    reach_px : int
        Unmatched rim pixels up to this far (px) from the matched plate are plate when darkness
        bounds them (a dark background).
    support_width_mm : float
        Parts of the matched plate narrower than this (mm; a morphological opening by a disc of this
        diameter removes them) whose stereo depth leaves the smooth surface (``PROTRUSION_SHARE`` of
        them farther than ``max(PROTRUSION_RESIDUAL_MM, 5 fit_rms_mm)``) are supports or clutter
        reaching out beside the plate at its depth, not plate; 0 disables this.
    step_zone_px : int
        Width (px) of the zone along the plate's boundary where ``surroundings_step_mm`` is given.
    target_area_mm2 : float, optional
        The target's area (mm^2): the segmented area is compared with it (a reason when they differ by
        more than 5 % over or 10 % under).
    dark_fraction : float
        See :func:`candidate_mask`.

    Returns
    -------
    Segmentation

    Raises
    ------
    ValueError
        Bad shapes, dtypes or option values.
    pipeline.formats.CaptureError
        No plate found: no candidate pixels, or none connected to the fitted surface.

    Notes
    -----
    See the module docstring for the steps. A plate pixel is never decided by brightness against a
    lit floor; brightness only excludes the dark and bounds the rim against a dark background.
    """
    from .formats import CaptureError

    b = _image("brightness", brightness).astype(np.float32)
    shape = b.shape
    K = _camera_matrix(camera_matrix)
    ok = np.ones(shape, bool) if seen is None else _bool_image("seen", seen, shape)
    if depth_mm is not None:
        depth = _image("depth_mm", depth_mm, shape).astype(np.float32)
    else:
        depth = None
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != shape + (3,):
            raise ValueError(f"normals: expected shape {shape + (3,)} to match brightness, got {normals.shape}")
    for name, value in (("depth_band_mm", depth_band_mm), ("max_dropout_mm2", max_dropout_mm2),
                        ("support_width_mm", support_width_mm)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name}: expected a finite value >= 0, got {value}")
    if depth_band_mm <= 0:
        raise ValueError(f"depth_band_mm: expected a band > 0 mm, got {depth_band_mm}")
    for name, value in (("edge_px", edge_px), ("reach_px", reach_px), ("step_zone_px", step_zone_px)):
        if not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name}: expected an integer >= 0, got {value!r}")
    if not isinstance(depth_scale_px, (int, np.integer)) or depth_scale_px < 1:
        raise ValueError(f"depth_scale_px: expected an integer >= 1, got {depth_scale_px!r}")
    edge_px = int(edge_px) * int(depth_scale_px)
    if target_area_mm2 is not None and not (math.isfinite(target_area_mm2) and target_area_mm2 > 0):
        raise ValueError(f"target_area_mm2: expected a positive area in mm^2 or None, got {target_area_mm2}")
    cand = candidate_mask(b, seen=ok, dark_fraction=dark_fraction) if candidates is None else (
        _bool_image("candidates", candidates, shape) & ok)
    if not cand.any():
        raise CaptureError("photometric images: no plate found (no pixel brighter than the dark background)")
    dark = ok & ~cand
    reasons: list[str] = []

    finite = np.zeros(shape, bool) if depth is None else (np.isfinite(depth) & (depth > 0) & ok)
    matched_share = np.count_nonzero(finite & cand) / np.count_nonzero(cand)
    if depth is None:
        reasons.append("no stereo depth: the plate was told from its surroundings by brightness only")
    elif matched_share < MIN_MATCHED_SHARE:
        reasons.append(
            f"stereo depth on {100 * matched_share:.1f} % of the bright pixels (under {100 * MIN_MATCHED_SHARE:.0f} %): "
            "the plate was told from its surroundings by brightness only"
        )
    else:
        s = int(depth_scale_px)
        params = dict(depth_band_mm=float(depth_band_mm), max_dropout_mm2=float(max_dropout_mm2), reach_px=int(reach_px),
                      support_width_mm=float(support_width_mm), step_zone_px=int(step_zone_px))
        if s == 1:
            parts = _classify(b, depth, K, ok, cand, normals, **params)
        else:
            # the depth has the resolution of a grid s times coarser: decide there (s^2 times less work),
            # then bring the decisions back and draw the edge band on this grid
            K_s = np.diag([1.0 / s, 1.0 / s, 1.0]) @ K
            parts = _classify(b[::s, ::s], depth[::s, ::s], K_s, ok[::s, ::s], cand[::s, ::s],
                              None if normals is None else normals[::s, ::s], **params)
            if parts is not None:
                parts = parts.upsampled(s, shape)
        if parts is None:
            reasons.append("no smooth surface fits the stereo depth: brightness only")
        else:
            return _finish(parts, b, depth, K, ok, cand, dark, normals, reasons, edge_px=edge_px,
                           depth_scale_px=s, depth_band_mm=float(depth_band_mm), max_dropout_mm2=float(max_dropout_mm2),
                           support_width_mm=float(support_width_mm), target_area_mm2=target_area_mm2)
    return _by_brightness(cand, dark, ok, reasons, edge_px=edge_px)


@dataclass(frozen=True)
class _Parts:
    """What the geometric segmentation decided, on its grid (internal)."""

    surface: _Surface
    region: np.ndarray  # (H, W) bool: plate, before the edge band
    holes: np.ndarray  # (H, W) bool
    feet: np.ndarray  # (H, W) bool: wide supports removed beside the plate
    step: np.ndarray  # (H, W) float32, see Segmentation.surroundings_step_mm
    mm_per_px: float  # on this grid
    n_holes: int
    largest_hole_mm2: float
    filled_mm2: float  # small dropouts filled
    filled_by_normals_mm2: float  # larger unmatched areas filled, their normals agreeing
    largest_by_normals_mm2: float
    protrusions_mm2: float  # supports removed
    px_scale: int = 1  # pixels of the final grid per pixel of this one, along each axis

    def upsampled(self, s: int, shape: tuple[int, int]) -> "_Parts":
        """The decisions on a grid ``s`` times finer of ``shape`` (coarse pixel i covers s i .. s i + s - 1)."""
        h, w = shape

        def up(a: np.ndarray) -> np.ndarray:
            src = a.view(np.uint8) if a.dtype == np.bool_ else a
            big = cv2.resize(src, (a.shape[1] * s, a.shape[0] * s), interpolation=cv2.INTER_NEAREST)
            out = np.zeros((h, w), src.dtype) if a.dtype == np.bool_ else np.full((h, w), np.nan, a.dtype)
            out[: min(h, big.shape[0]), : min(w, big.shape[1])] = big[:h, :w]
            return out.view(np.bool_) if a.dtype == np.bool_ else out

        return replace(self, region=up(self.region), holes=up(self.holes), feet=up(self.feet), step=up(self.step),
                       mm_per_px=self.mm_per_px / s, px_scale=s)


def _classify(b, depth, K, ok, cand, normals, *, depth_band_mm: float, max_dropout_mm2: float, reach_px: int,
              support_width_mm: float, step_zone_px: int) -> _Parts | None:
    """Steps 2-5 and 7 of the module docstring on the given grid; None if no smooth surface fits."""
    from .formats import CaptureError

    shape = b.shape
    dark = ok & ~cand
    finite = np.isfinite(depth) & (depth > 0) & ok
    surface = _fit_surface(depth, cand & finite, K, depth_band_mm)
    if surface is None:
        return None
    z_fit = _surface_depth(surface, K, shape)
    residual = depth - z_fit  # NaN where unmatched
    with np.errstate(invalid="ignore"):
        near = finite & cand & (np.abs(residual) < depth_band_mm)
        off = finite & ~near  # matched, off the plate's surface (or a dark pixel with depth)
    core = _largest_component(near)
    if not core.any():
        raise CaptureError("stereo: no plate found (no matched pixels near the fitted surface)")
    geometry = _geometry(surface, K, shape)
    area = geometry.area_full(shape)
    mm_per_px = math.sqrt(float(np.nanmedian(area[core])))
    protrusions = _protrusions(core, residual, mm_per_px, support_width_mm, max(PROTRUSION_RESIDUAL_MM, 5.0 * surface.rms_mm))
    if protrusions.any():
        core &= ~protrusions
        core = _largest_component(core)
    feet = _wide_parts(protrusions, max(1.5, support_width_mm / mm_per_px / 20))
    unknown = ok & cand & ~finite

    # ---- enclosed regions: small dropouts are filled, openings and large unmatched areas stay holes
    n_lab, labels = cv2.connectedComponents((~core).view(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    inner = np.ones(n_lab, bool)
    inner[border] = False
    inner[0] = False  # label 0 is the core
    lab = labels.ravel()
    count = np.bincount(lab, minlength=n_lab)
    n_offish = np.bincount(lab, weights=(off | dark | ~ok).ravel().astype(np.float64), minlength=n_lab)
    area_lab = np.bincount(lab, weights=np.nan_to_num(area, nan=0.0).ravel().astype(np.float64), minlength=n_lab)
    no_depth_behind = inner & (n_offish <= DROPOUT_MAX_OFF_SHARE * count)
    fill = no_depth_behind & (area_lab <= max_dropout_mm2)
    larger = no_depth_behind & ~fill
    by_normals = np.zeros(n_lab, bool)
    if normals is not None and larger.any():
        # a larger unmatched area is plate if its photometric normals follow the plate's surface: with no
        # stereo depth in it, filling it lets no depth step into the solve, only normals that agree
        rows, cols = np.nonzero(larger[labels])
        cos = np.einsum("mc,mc->m", np.asarray(normals[rows, cols], np.float32), geometry.normals_at(rows, cols))
        agree = np.nan_to_num(cos, nan=-1.0) >= math.cos(math.radians(DROPOUT_NORMAL_DEG))
        n_agree = np.bincount(labels[rows, cols], weights=agree.astype(np.float64), minlength=n_lab)
        by_normals = larger & (n_agree > 0.5 * count)
        fill |= by_normals
    hole_lab = inner & ~fill
    holes = hole_lab[labels]
    region = core | fill[labels]

    # ---- the rim: unmatched pixels next to the plate that darkness bounds (a dark background); a pixel
    # mostly dark (under half the plate's median brightness, unsmoothed) is not taken
    kernel = np.ones((3, 3), np.uint8)
    near_dark = cv2.distanceTransform((~dark).view(np.uint8), cv2.DIST_L2, 3) <= reach_px + 1
    lit = b >= 0.5 * float(np.median(b[::4, ::4][core[::4, ::4]]))
    reachable = (unknown & near_dark & lit & ~holes).view(np.uint8)
    grown = region.view(np.uint8).copy()
    for _ in range(reach_px):
        grown = cv2.dilate(grown, kernel) & (reachable | grown)
    region = grown.astype(bool)

    # ---- the step to the surroundings along the boundary, for telling edge artefacts from defects
    # (the nearest surroundings with a depth, unless darkness - no depth, a dark background - is nearer)
    outside = ~region
    zone = region & (cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, 3) <= step_zone_px)
    dist_off, nearest_off = _nearest(off & outside)
    dist_dark = cv2.distanceTransform((~((dark | ~lit | ~ok) & outside)).view(np.uint8), cv2.DIST_L2, 3)
    reach = step_zone_px + 2 * reach_px + 4  # past the unmatched strip beside the plate
    step = np.full(shape, np.nan, np.float32)
    use_off = zone & (dist_off <= np.minimum(dist_dark, reach))
    step[zone & ~use_off & (dist_dark <= reach)] = np.inf
    step[use_off] = depth.ravel()[nearest_off[use_off]] - z_fit[use_off]

    small = fill & ~by_normals
    return _Parts(surface=surface, region=region, holes=holes, feet=feet, step=step, mm_per_px=mm_per_px,
                  n_holes=int(np.count_nonzero(hole_lab)),
                  largest_hole_mm2=float(area_lab[hole_lab].max()) if hole_lab.any() else 0.0,
                  filled_mm2=float(area_lab[small].sum()), filled_by_normals_mm2=float(area_lab[by_normals].sum()),
                  largest_by_normals_mm2=float(area_lab[by_normals].max()) if by_normals.any() else 0.0,
                  protrusions_mm2=float(np.nansum(area[protrusions])))


def _finish(parts: _Parts, b, depth, K, ok, cand, dark, normals, reasons: list[str], *, edge_px: int,
            depth_scale_px: int, depth_band_mm: float, max_dropout_mm2: float, support_width_mm: float,
            target_area_mm2: float | None) -> Segmentation:
    """Step 6 (edge band, normals check) on the full grid, areas and counts, the result."""
    shape = b.shape
    surface, region = parts.surface, parts.region
    z_fit = _surface_depth(surface, K, shape)
    geometry = _geometry(surface, K, shape)
    area = geometry.area_full(shape)
    finite = np.isfinite(depth) & (depth > 0) & ok
    with np.errstate(invalid="ignore"):
        off = finite & cand & ~(np.abs(depth - z_fit) < depth_band_mm)

    # ---- the edge band: plate pixels within edge_px of the outline or of a hole (not of the image frame)
    if edge_px > 0:
        k = 2 * edge_px + 1
        padded = cv2.copyMakeBorder(region.view(np.uint8), edge_px, edge_px, edge_px, edge_px, cv2.BORDER_REPLICATE)
        inner_region = cv2.erode(padded, np.ones((k, k), np.uint8))[edge_px:-edge_px, edge_px:-edge_px].astype(bool)
    else:
        inner_region = region
    mask = inner_region & ok
    if parts.feet.any():
        # where a support met the plate, its foot may be left at the plate's edge: a wider band there
        foot_px = max(edge_px, int(math.ceil(support_width_mm / parts.mm_per_px / 4)))
        mask &= cv2.distanceTransform((~parts.feet).view(np.uint8), cv2.DIST_L2, 3) > foot_px
    n_normal_off = 0
    if normals is not None:
        zone_px = edge_px + EDGE_NORMAL_ZONE_PX * depth_scale_px
        zone = mask & (cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, 3) <= zone_px)
        rows, cols = np.nonzero(zone)
        cos = np.einsum("mc,mc->m", np.asarray(normals[rows, cols], np.float32), geometry.normals_at(rows, cols))
        turned = np.nan_to_num(cos, nan=1.0) < math.cos(math.radians(EDGE_NORMAL_DEG))
        n_normal_off = int(np.count_nonzero(turned))
        mask[rows[turned], cols[turned]] = False
    edge_band = region & ~mask
    step = np.where(region, parts.step, np.float32(np.nan)).astype(np.float32)

    holes = parts.holes
    plate_area = float(np.nansum(area[mask]))
    band_area = float(np.nansum(area[edge_band]))
    holes_area = float(np.nansum(area[holes]))
    if parts.protrusions_mm2:
        reasons.append(
            f"{parts.protrusions_mm2:.0f} mm^2 of narrow parts at the plate's depth that leave its smooth surface "
            f"(supports reaching out beside the plate) excluded"
        )
    if parts.n_holes:
        reasons.append(
            f"{parts.n_holes} region(s) inside the plate kept as holes, not measured ({holes_area:.0f} mm^2, largest "
            f"{parts.largest_hole_mm2:.0f} mm^2): openings or areas without stereo depth, never filled across a depth step"
        )
    if parts.filled_mm2:
        reasons.append(
            f"{parts.filled_mm2:.0f} mm^2 of stereo dropouts inside the plate filled (each at most {max_dropout_mm2:g} mm^2)"
        )
    if parts.filled_by_normals_mm2:
        reasons.append(
            f"{parts.filled_by_normals_mm2:.0f} mm^2 of larger areas without stereo depth filled (largest "
            f"{parts.largest_by_normals_mm2:.0f} mm^2): their photometric normals follow the plate's surface within "
            f"{DROPOUT_NORMAL_DEG:g} deg"
        )
    if n_normal_off:
        reasons.append(
            f"{n_normal_off} px near the edge whose photometric normals leave the plate's surface by over "
            f"{EDGE_NORMAL_DEG:g} deg put in the edge band (a support's side, or plate and surroundings mixed)"
        )
    if edge_band.any():
        reasons.append(
            f"edge band of {int(np.count_nonzero(edge_band))} px ({band_area:.0f} mm^2) along the outline and the "
            f"openings excluded: those pixels mix plate and surroundings"
        )
    if target_area_mm2 is not None:
        ratio = (plate_area + band_area) / target_area_mm2
        if ratio > 1.05:
            reasons.append(
                f"segmented area {plate_area + band_area:.0f} mm^2 is {100 * (ratio - 1):.1f} % over the target's "
                f"{target_area_mm2:.0f} mm^2: surroundings at the plate's depth may be included"
            )
        elif ratio < 0.9:
            reasons.append(
                f"segmented area {plate_area + band_area:.0f} mm^2 is {100 * (1 - ratio):.1f} % under the target's "
                f"{target_area_mm2:.0f} mm^2 (openings, plate partly out of view, or unmatched areas)"
            )
    return Segmentation(
        mask=mask,
        edge_band=edge_band,
        holes=holes,
        surface_depth_mm=z_fit,
        surroundings_step_mm=step,
        pixel_area_mm2=area,
        plate_area_mm2=plate_area,
        edge_band_area_mm2=band_area,
        holes_area_mm2=holes_area,
        filled_area_mm2=parts.filled_mm2 + parts.filled_by_normals_mm2,
        n_mask=int(np.count_nonzero(mask)),
        n_edge_band=int(np.count_nonzero(edge_band)),
        n_holes=parts.n_holes,
        n_hole_pixels=int(np.count_nonzero(holes)),
        n_off_depth=int(np.count_nonzero(off)),
        n_dark=int(np.count_nonzero(dark)),
        n_unmatched=int(np.count_nonzero(ok & cand & ~finite)),
        fit_rms_mm=surface.rms_mm,
        depth_band_mm=depth_band_mm,
        method="stereo",
        reasons=tuple(reasons),
    )


def _by_brightness(cand: np.ndarray, dark: np.ndarray, ok: np.ndarray, reasons: list[str], *,
                   edge_px: int) -> Segmentation:
    """The plate as the largest candidate component, holes of a few pixels filled (no depth to judge by)."""
    from .formats import CaptureError

    shape = cand.shape
    opened = cv2.morphologyEx(cand.view(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8)).astype(bool)
    core = _largest_component(opened)
    if not core.any():
        raise CaptureError("photometric images: no plate found (no region brighter than the background)")
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats((~core).view(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    # without depth only specks can be told from openings: at most 0.05 % of the plate
    small = stats[:, cv2.CC_STAT_AREA] <= max(4, int(5e-4 * np.count_nonzero(core)))
    small[border] = False
    small[0] = False
    inner = np.ones(n_lab, bool)
    inner[border] = False
    inner[0] = False
    filled = small[labels]
    holes = (inner & ~small)[labels]
    region = core | filled
    if edge_px > 0:
        k = 2 * edge_px + 1
        padded = cv2.copyMakeBorder(region.view(np.uint8), edge_px, edge_px, edge_px, edge_px, cv2.BORDER_REPLICATE)
        mask = cv2.erode(padded, np.ones((k, k), np.uint8))[edge_px:-edge_px, edge_px:-edge_px].astype(bool) & ok
    else:
        mask = region & ok
    edge_band = region & ~mask
    nan = np.full(shape, np.nan, np.float32)
    n_holes = int(np.count_nonzero(inner & ~small))
    if n_holes:
        reasons.append(f"{n_holes} dark region(s) inside the plate kept as holes, not measured")
    return Segmentation(
        mask=mask, edge_band=edge_band, holes=holes, surface_depth_mm=nan, surroundings_step_mm=nan.copy(),
        pixel_area_mm2=nan.copy(), plate_area_mm2=math.nan, edge_band_area_mm2=math.nan, holes_area_mm2=math.nan,
        filled_area_mm2=math.nan,
        n_mask=int(np.count_nonzero(mask)), n_edge_band=int(np.count_nonzero(edge_band)),
        n_holes=n_holes, n_hole_pixels=int(np.count_nonzero(holes)),
        n_off_depth=0, n_dark=int(np.count_nonzero(dark)), n_unmatched=int(np.count_nonzero(cand)),
        fit_rms_mm=math.nan, depth_band_mm=math.nan, method="brightness", reasons=tuple(reasons),
    )


def target_area_mm2(target) -> float:
    """Surface area of a target plate, mm^2: what a complete segmentation of it would measure.

    Parameters
    ----------
    target : pipeline.io.Target

    Returns
    -------
    float
        Mesh: the sum of its triangles' areas (its outline and openings included). Plane: the
        product of ``size_mm``. Cylinder: arc length across the axis times the length,
        ``2 R asin(sx / 2R) sy``. Sphere: the cap over the ``size_mm`` rectangle (midpoint rule
        on a 400 x 400 grid, relative error < 1e-5).

    Notes
    -----
    A parametric target has no outline: its area is its size's rectangle on the surface. The
    measured area is reported against it (details.json); missing metal is never a defect.
    """
    from .io import Target

    if not isinstance(target, Target):
        raise TypeError(f"target: expected a pipeline.io.Target, got {type(target).__name__}")
    if target.shape == "mesh":
        v = np.asarray(target.mesh_vertices_mm, dtype=np.float64)
        tri = v[np.asarray(target.mesh_faces, dtype=np.int64)]
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    sx, sy = (float(v) for v in target.size_mm)
    if target.shape == "plane":
        return sx * sy
    R = float(target.radius_mm)
    if target.shape == "cylinder":
        return 2.0 * R * math.asin(min(1.0, sx / (2.0 * R))) * sy
    n = 400
    x = (np.arange(n) + 0.5) / n * sx - sx / 2
    y = (np.arange(n) + 0.5) / n * sy - sy / 2
    r2 = x[None, :] ** 2 + y[:, None] ** 2
    if np.any(r2 >= R * R):
        raise ValueError(f"target.radius_mm: a sphere of radius {R} mm cannot span size_mm {target.size_mm}")
    return float((R / np.sqrt(R * R - r2)).sum() * (sx / n) * (sy / n))
