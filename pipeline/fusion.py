"""Fusion of the photometric and the stereo shape: stereo governs the low frequencies, the normals the detail.

Integrated normals are exact in their detail but carry any error of the light model as a smooth,
plate-wide bend (a light 3 m away treated as distant bends a 5 m radius by tens of percent; a light
bumped by a degree by half a percent). The stereo pair measures the same surface independently and
without that bias, but with more noise per pixel. So the fused surface is

    log z = log z_ps + c(u, v)

where ``c`` is the smooth part of ``log z_stereo - log z_ps``: a tensor-product cubic B-spline on a
coarse grid of knots, fitted robustly (Huber IRLS) to the pixels where both exist. Everything the
spline can represent -- scale, tilt, bend, twist, any shape error wider than about a knot spacing --
comes from the stereo pair; everything finer from the normals. The spline averages thousands of
stereo pixels per coefficient, so the stereo noise that reaches the surface is small, and a shape
feature that both see (a dent) is not in the difference at all.

References
----------
.. [1] D. Nehab, S. Rusinkiewicz, J. Davis, R. Ramamoorthi, "Efficiently combining positions and
   normals for precise 3D geometry", SIGGRAPH 2005 (the same split of frequencies, there by a
   Gaussian low-pass of positions).
.. [2] P. Dierckx, "Curve and surface fitting with splines", Oxford, 1993 (penalised tensor-product
   B-splines).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

#: Finest knot spacing of the correction spline as a fraction of the plate's larger extent in the
#: image: at most, the stereo pair governs shape wider than about this.
KNOT_FRACTION = 1.0 / 16.0
#: Knot spacings tried, coarsest first (after a correction of scale and tilt only).
KNOT_LADDER = (1.0 / 2.0, 1.0 / 4.0, 1.0 / 8.0, 1.0 / 16.0)
#: Shape disagreement (RMS, mm) below which the normals keep the shape (see fuse_low_frequencies).
#: Measured at 1224x1024 on simulated plates whose normals are exact (lights known): the finest spline
#: explains ~0.15 mm RMS of the stereo pair's correlated noise more than scale and tilt do; with
#: near-field LEDs given as distant directions the coarse corrections leave 3-6 mm.
RESOLVE_MM = 0.25
#: At most this many stereo pixels enter the fit (a regular subsample).
MAX_FIT_PIXELS = 60_000
#: Huber threshold, in robust standard deviations of the stereo residual.
HUBER_K = 2.0
#: IRLS passes of the robust fit.
IRLS_PASSES = 4
#: Weight of the second-difference penalty on the spline coefficients, relative to the data's total
#: weight per coefficient: bridges knot cells without stereo data, negligible where there is some.
SMOOTHING = 1e-3


@dataclass(frozen=True)
class Fusion:
    """The fused surface and how far the two shapes disagreed.

    Attributes
    ----------
    depth_mm : (H, W) float64
        Fused depth along the left optical axis, mm; NaN outside the mask.
    correction_mm : (H, W) float32
        ``depth_mm - depth_ps`` (what the stereo pair changed), mm; NaN outside the mask.
    disagreement_mm : float
        The 95th percentile of ``|correction|`` after removing its best-fit plane in depth (a
        scale and tilt error is no disagreement of shape), mm.
    stereo_noise_mm : float
        Robust standard deviation of the stereo depth about the fused surface, mm (per pixel).
    noise_floor_mm : float
        How much disagreement the stereo noise alone explains: 3 standard errors of the spline's
        value (the noise over the stereo pixels of a knot cell, taken as independent), mm.
    n_stereo : int
        Stereo pixels in the fit.
    knot_spacing_px : float or None
        Knot spacing of the correction chosen; None: scale and tilt only.
    """

    depth_mm: np.ndarray
    correction_mm: np.ndarray
    disagreement_mm: float
    stereo_noise_mm: float
    noise_floor_mm: float
    n_stereo: int
    knot_spacing_px: float | None


def fuse_low_frequencies(
    depth_ps_mm: np.ndarray,
    stereo_depth_mm: np.ndarray,
    mask: np.ndarray,
    *,
    knot_fraction: float = KNOT_FRACTION,
    resolve_mm: float | None = RESOLVE_MM,
) -> Fusion:
    """Replace the low frequencies of a photometric surface by the stereo pair's.

    Parameters
    ----------
    depth_ps_mm : (H, W) float
        Depth integrated from the normals (mm along the optical axis), finite and > 0 on ``mask``.
    stereo_depth_mm : (H, W) float
        Stereo depth on the same grid (mm), NaN where unmatched.
    mask : (H, W) bool
        The surface's pixels.
    knot_fraction : float
        The finest knot spacing tried, as a fraction of the mask's larger extent (0 < . <= 1).
    resolve_mm : float
        The correction is the coarsest of a ladder -- scale and tilt only, then splines of knot
        spacing 1/2, 1/4, ... of the extent down to ``knot_fraction`` -- whose robust residual
        against the stereo pair exceeds the finest one's by less than this RMS (mm): where the
        normals agree with the stereo pair to that, the stereo pair only sets scale and tilt, and
        its noise does not reach the shape. None: always the spline of ``knot_fraction``.

    Returns
    -------
    Fusion

    Raises
    ------
    ValueError
        Bad shapes, a photometric depth that is not finite and positive on the mask, fewer stereo
        pixels than spline coefficients.
    """
    z = np.asarray(depth_ps_mm, dtype=np.float64)
    zs = np.asarray(stereo_depth_mm, dtype=np.float64)
    mask = np.asarray(mask)
    if z.ndim != 2 or zs.shape != z.shape or mask.shape != z.shape or mask.dtype != bool:
        raise ValueError(
            f"depth_ps_mm, stereo_depth_mm, mask: expected (H, W) arrays of one shape (mask bool), got "
            f"{z.shape}, {zs.shape}, {mask.shape} {mask.dtype}"
        )
    if not 0 < knot_fraction <= 1:
        raise ValueError(f"knot_fraction: expected in (0, 1], got {knot_fraction}")
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        raise ValueError("mask: expected at least one surface pixel, got none")
    zm = z[rows, cols]
    if not (np.all(np.isfinite(zm)) and np.all(zm > 0)):
        raise ValueError("depth_ps_mm: expected finite depths > 0 mm on the mask")
    both = mask & np.isfinite(zs) & (zs > 0)
    step = max(1, int(np.sqrt(np.count_nonzero(both) / MAX_FIT_PIXELS)))
    fr, fc = np.nonzero(both[::step, ::step])
    fr, fc = fr * step, fc * step
    r = np.log(zs[fr, fc]) - np.log(z[fr, fc])
    z_typ = float(np.median(zm))
    fits = []
    ladder = (None, *KNOT_LADDER) if resolve_mm is not None else (knot_fraction,)
    for fraction in ladder:
        if fraction is not None and fraction < knot_fraction:
            break
        grid = _Grid.around(rows, cols, fraction) if fraction is not None else _Grid.around(rows, cols, 1.0)
        if fr.size < 4 * grid.size:
            break
        fits.append((grid, fraction) + _robust_spline_fit(grid, fr, fc, r, plane_only=fraction is None))
    if not fits:
        raise ValueError(
            f"stereo_depth_mm: expected at least {4 * _Grid.around(rows, cols, 1.0).size} matched surface pixels to "
            f"fit the correction, got {fr.size} (subsampled by {step})"
        )
    # the coarsest correction that explains the stereo pair as well as the finest, up to resolve_mm RMS
    sigma_best = min(f[3] for f in fits)
    slack = 0.0 if resolve_mm is None else (resolve_mm / z_typ) ** 2
    grid, fraction, coef, sigma_log, se_log = next(f for f in fits if f[3] ** 2 <= sigma_best**2 + slack)
    c = grid.evaluate(coef, rows, cols)
    fused = np.full(z.shape, np.nan)
    fused[rows, cols] = zm * np.exp(c)
    correction = np.full(z.shape, np.nan, np.float32)
    corr = fused[rows, cols] - zm
    correction[rows, cols] = corr

    # disagreement of shape: the correction without its best plane in depth (scale and tilt)
    sub = slice(None, None, max(1, rows.size // 200_000))
    A = np.column_stack([np.ones(rows[sub].size), cols[sub], rows[sub]]).astype(np.float64)
    plane, *_ = np.linalg.lstsq(A, corr[sub], rcond=None)
    shape_part = corr[sub] - A @ plane
    return Fusion(
        depth_mm=fused,
        correction_mm=correction,
        disagreement_mm=float(np.percentile(np.abs(shape_part), 95)),
        stereo_noise_mm=float(sigma_log * z_typ),
        noise_floor_mm=float(3.0 * se_log * z_typ),
        n_stereo=int(fr.size),
        knot_spacing_px=None if fraction is None else float(grid.spacing),
    )


def smooth_stereo_depth(stereo_depth_mm: np.ndarray, mask: np.ndarray, *, knot_fraction: float = 1.0 / 8.0
                        ) -> np.ndarray:
    """A complete, smooth surface through the stereo depth: (H, W) float64 mm on ``mask``, NaN elsewhere.

    The robust spline of :func:`fuse_low_frequencies` (``knot_fraction``, no ladder) fitted to
    ``log z_stereo`` itself: a starting surface for the near-field normals where the stereo pair
    has holes and noise.
    """
    ones = np.where(mask, 1.0, np.nan)
    return fuse_low_frequencies(ones, stereo_depth_mm, mask, knot_fraction=knot_fraction, resolve_mm=None).depth_mm


class _Grid:
    """Uniform cubic B-splines over a box of pixels: ``nu x nv`` coefficients, knots ``spacing`` px apart."""

    def __init__(self, r0: float, c0: float, spacing: float, nv: int, nu: int):
        self.r0, self.c0, self.spacing, self.nv, self.nu = r0, c0, spacing, nv, nu

    @classmethod
    def around(cls, rows: np.ndarray, cols: np.ndarray, knot_fraction: float) -> "_Grid":
        r0, r1 = float(rows.min()), float(rows.max()) + 1.0
        c0, c1 = float(cols.min()), float(cols.max()) + 1.0
        spacing = max(4.0, knot_fraction * max(r1 - r0, c1 - c0))
        nv = int(np.ceil((r1 - r0) / spacing)) + 3
        nu = int(np.ceil((c1 - c0) / spacing)) + 3
        return cls(r0, c0, spacing, nv, nu)

    @property
    def size(self) -> int:
        return self.nv * self.nu

    def _basis(self, x: np.ndarray, x0: float) -> tuple[np.ndarray, np.ndarray]:
        """First coefficient index (M,) and the 4 weights (M, 4) of the cubic B-spline at x."""
        t = (np.asarray(x, dtype=np.float64) - x0) / self.spacing
        i = np.floor(t).astype(np.int64)
        f = t - i
        w = np.stack([(1 - f) ** 3, 3 * f**3 - 6 * f**2 + 4, -3 * f**3 + 3 * f**2 + 3 * f + 1, f**3], axis=1) / 6.0
        return i, w

    def design(self, rows: np.ndarray, cols: np.ndarray) -> sp.csr_matrix:
        """(M, nv * nu) sparse matrix of the tensor-product basis at the pixels."""
        iv, wv = self._basis(rows, self.r0)
        iu, wu = self._basis(cols, self.c0)
        m = rows.size
        idx = ((iv[:, None, None] + np.arange(4)[None, :, None]) * self.nu
               + (iu[:, None, None] + np.arange(4)[None, None, :])).reshape(m, 16)
        val = (wv[:, :, None] * wu[:, None, :]).reshape(m, 16)
        indptr = np.arange(0, 16 * m + 1, 16)
        return sp.csr_matrix((val.ravel(), idx.ravel(), indptr), shape=(m, self.size))

    def evaluate(self, coef: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The spline at the pixels (M,): evaluated separably on their bounding box, then indexed."""
        r_lo, r_hi = int(rows.min()), int(rows.max()) + 1
        c_lo, c_hi = int(cols.min()), int(cols.max()) + 1
        Bv = self._dense(np.arange(r_lo, r_hi), self.r0, self.nv)
        Bu = self._dense(np.arange(c_lo, c_hi), self.c0, self.nu)
        box = (Bv @ coef.reshape(self.nv, self.nu)) @ Bu.T
        return box[rows - r_lo, cols - c_lo]

    def _dense(self, x: np.ndarray, x0: float, n: int) -> np.ndarray:
        """(len(x), n) dense basis matrix along one axis."""
        i, w = self._basis(x, x0)
        B = np.zeros((x.size, n))
        for a in range(4):
            B[np.arange(x.size), i + a] = w[:, a]
        return B

    def penalty(self) -> sp.csr_matrix:
        """Second differences of the coefficients along both grid directions, stacked."""
        def d2(n):
            return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(n - 2, 0), n))
        Iv, Iu = sp.identity(self.nv), sp.identity(self.nu)
        return sp.vstack([sp.kron(d2(self.nv), Iu), sp.kron(Iv, d2(self.nu))]).tocsr()


def _robust_spline_fit(grid: _Grid, rows: np.ndarray, cols: np.ndarray, r: np.ndarray, *, plane_only: bool = False):
    """Huber-IRLS penalised least squares of the spline to r at the pixels (``plane_only``: the
    spline restricted to planes in (u, v), i.e. a scale and tilt of the depth).

    Returns the coefficients (nv * nu,), the robust standard deviation of the residuals and the
    typical standard error of the fitted spline value (both in the units of r).
    """
    A = grid.design(rows, cols)
    if plane_only:
        # a plane is a spline whose coefficients are a plane over the knot grid
        gv, gu = np.meshgrid(np.arange(grid.nv, dtype=np.float64), np.arange(grid.nu, dtype=np.float64), indexing="ij")
        Q = sp.csr_matrix(np.column_stack([np.ones(grid.size), gv.ravel(), gu.ravel()]))
        A = (A @ Q).tocsr()
    P = grid.penalty() if not plane_only else sp.csr_matrix((0, 3))
    PtP = (P.T @ P).tocsc()
    w = np.ones(r.size)
    coef = np.zeros(grid.size)
    sigma = 0.0
    lam = SMOOTHING * r.size / grid.size
    for _ in range(IRLS_PASSES):
        Aw = A.multiply(w[:, None]).tocsr()
        N = (A.T @ Aw).tocsc() + lam * PtP
        coef = spla.spsolve(N, Aw.T @ r)
        res = r - A @ coef
        sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        if not sigma > 0:
            break
        a = np.abs(res) / (HUBER_K * sigma)
        w = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    # standard error of a spline value: sigma / sqrt(samples per knot cell), as if independent
    cells = max((grid.nv - 3) * (grid.nu - 3), 1)
    se = sigma / np.sqrt(max(float(w.sum()) / cells, 1.0))
    if plane_only:
        coef = Q @ coef
    return coef, sigma, se
