"""Fusion of the photometric and the stereo shape: stereo governs the low frequencies, the normals the detail.

Integrated normals are exact in their detail but carry any error of the light model as a smooth,
plate-wide bend (a light 3 m away treated as distant bends a 5 m radius by tens of percent; a light
bumped by a degree by half a percent). The stereo pair measures the same surface independently and
without that bias, but with more noise per pixel. So the fused surface is

    log z = log z_ps + c(u, v)

where ``c`` is the smooth part of ``log z_stereo - log z_ps``: a tensor-product cubic B-spline on a
coarse grid of knots, fitted robustly to the medians of that difference over small blocks of pixels
(a median per block drops stereo mismatches; Huber re-weighting drops bad blocks). Everything the
spline can represent -- scale, tilt, bend, twist, any shape error wider than about a knot spacing --
comes from the stereo pair; everything finer from the normals. The spline averages thousands of
stereo pixels per coefficient, so the stereo noise that reaches the surface is small, and a shape
feature that both see (a dent) is not in the difference at all. The knot spacing is chosen per
surface: the coarsest that explains the stereo pair as well as the finest (so correct normals keep
the shape, and only wrong ones hand it to the stereo pair).

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

import numba as nb
import numpy as np
import numpy.typing as npt

#: Finest knot spacing of the correction spline as a fraction of the plate's larger extent in the
#: image: at most, the stereo pair governs shape wider than about this.
KNOT_FRACTION = 1.0 / 16.0
#: Knot spacings tried, coarsest first (after a plane and a quadric in (u, v)).
KNOT_LADDER = (1.0 / 2.0, 1.0 / 4.0, 1.0 / 8.0, 1.0 / 16.0)
#: Shape disagreement (RMS, mm) below which the normals keep the shape (see fuse_low_frequencies): the
#: noise the finer rungs would fit is charged separately (NOISE_CORRELATION), so this only breaks
#: near-ties. Measured at 1224x1024: 0.25 left corner errors of 3-4 mm in place (small in RMS) with
#: LEDs refitted from nominal directions; 0.05 takes them out and still keeps exact normals' shape
#: (plane or quadric chosen with lights known).
RESOLVE_MM = 0.05
#: The polynomial rungs of the ladder: a plane (scale and tilt) and a quadric (and bend) in (u, v).
PLANE, QUADRIC = "plane", "quadric"
#: A rung of the ladder: the plane, the quadric, or a spline of a knot spacing (fraction of the extent).
Rung = str | float
_POLYNOMIAL: dict[Rung, int] = {PLANE: 3, QUADRIC: 6}
_DEGREE: dict[Rung, int] = {PLANE: 1, QUADRIC: 2}
#: The finer corrections of the ladder fit the stereo noise too: each coefficient takes the variance of
#: about this many blocks (noise correlated between neighbouring blocks) out of the residual.
NOISE_CORRELATION = 2.0
#: The difference is reduced to medians over square blocks of pixels; about this many blocks.
TARGET_BLOCKS = 12_000
#: Blocks are at least this wide (px): wider than the stereo matcher's window and the reach of its
#: smoothness term, so that the blocks' errors are roughly independent.
MIN_BLOCK_PX = 8
#: A block needs at least this fraction of its pixels with both depths to count.
MIN_BLOCK_FILL = 0.25
#: ... and the centroid of its samples within this fraction of its side from its centre (a block cut by
#: the surface's edge would put a steep difference at the wrong place).
MAX_CENTROID_OFFSET = 0.1
#: Huber threshold, in robust standard deviations of the block residuals.
HUBER_K = 2.0
#: Re-weighted passes of the robust fit.
IRLS_PASSES = 3
#: Weight of the second-difference penalty on the spline coefficients, relative to the data's total
#: weight per coefficient: bridges knot cells without stereo data, negligible where there is some.
SMOOTHING = 1e-6


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
        The 95th percentile over the surface of ``|c - plane| z`` (mm): the correction without its
        best-fit plane in (u, v), i.e. without a change of scale and tilt, which is no
        disagreement of shape.
    stereo_noise_mm : float
        Robust standard deviation of a stereo sample about the fused surface, mm (from the block
        medians' residuals, as if the noise were independent between samples).
    noise_floor_mm : float
        How much disagreement the stereo noise alone explains: 3 standard errors of the spline's
        value (the noise of the stereo samples of a knot cell, as if independent), mm.
    n_stereo : int
        Stereo pixels in the fit.
    knot_spacing_px : float or None
        Knot spacing of the correction chosen; None: a polynomial (see ``model``).
    model : {"plane", "quadric", "spline"}
        The correction chosen: scale and tilt; and bend; or a spline of ``knot_spacing_px``.
    """

    depth_mm: np.ndarray
    correction_mm: np.ndarray
    disagreement_mm: float
    stereo_noise_mm: float
    noise_floor_mm: float
    n_stereo: int
    knot_spacing_px: float | None
    model: str = "spline"


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
    resolve_mm : float or None
        The correction is chosen from a ladder: a plane in (u, v) (scale and tilt), a quadric (and
        bend), then splines of knot spacing 1/2, 1/4, ... of the extent down to ``knot_fraction``.
        Each rung is scored by its robust residual against the stereo pair plus what its
        coefficients would take out of pure noise (an information criterion); the best one is
        taken if it is the plane, else the coarsest from the quadric on whose score is within this
        RMS (mm) of the best: where the normals agree with the stereo pair to that, the stereo pair
        sets only scale, tilt and bend, and its noise does not reach the shape. None: the spline of
        ``knot_fraction`` (or, with too few stereo blocks for it, the finest rung they carry).

    Returns
    -------
    Fusion

    Raises
    ------
    ValueError
        Bad shapes, a photometric depth that is not finite and positive on the mask, too few
        stereo pixels for the coarsest correction.
    """
    z, zs, mask = _check_inputs(depth_ps_mm, stereo_depth_mm, mask, knot_fraction)
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    zb, zsb, mb = z[box], zs[box], mask[box]
    if np.any(mb & ~((zb > 0) & (zb < np.inf))):
        raise ValueError("depth_ps_mm: expected finite depths > 0 mm on the mask")
    sparse = max(1, int(np.sqrt(mb.size / 100_000)))
    z_typ = float(np.median(zb[::sparse, ::sparse][mb[::sparse, ::sparse]]))
    blocks = _Blocks.of(zb, zsb, mb)
    rung, grid, coef, _, sigma_pix = _chosen(
        _ladder_fits(blocks, mb.shape, knot_fraction, resolve_mm), blocks, resolve_mm, z_typ
    )
    fraction = rung if rung not in _POLYNOMIAL else None
    fused = np.full(z.shape, np.nan)
    correction = np.full(z.shape, np.nan, np.float32)
    _compose(zb, grid.evaluate(coef), mb, fused[box], correction[box])
    cells = max((grid.nv - 3) * (grid.nu - 3), 1) if fraction is not None else 1
    per_cell = max(float(blocks.samples.sum()) / cells, 1.0)
    return Fusion(
        depth_mm=fused,
        correction_mm=correction,
        disagreement_mm=_disagreement(zb, correction[box], mb),
        stereo_noise_mm=float(sigma_pix * z_typ),
        noise_floor_mm=float(3.0 * sigma_pix / np.sqrt(per_cell) * z_typ),
        n_stereo=int(blocks.n_pixels),
        knot_spacing_px=None if fraction is None else float(grid.spacing),
        model=rung if isinstance(rung, str) else "spline",
    )


def _check_inputs(
    depth_ps_mm: npt.ArrayLike,
    stereo_depth_mm: npt.ArrayLike,
    mask: npt.ArrayLike,
    knot_fraction: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arrays of :func:`fuse_low_frequencies` checked: photometric and stereo depth float64, mask."""
    z = np.asarray(depth_ps_mm, dtype=np.float64)
    zs = np.asarray(stereo_depth_mm, dtype=np.float64)
    m = np.asarray(mask)
    if z.ndim != 2 or zs.shape != z.shape or m.shape != z.shape or m.dtype != bool:
        raise ValueError(
            f"depth_ps_mm, stereo_depth_mm, mask: expected (H, W) arrays of one shape (mask bool), got "
            f"{z.shape}, {zs.shape}, {m.shape} {m.dtype}"
        )
    if not 0 < knot_fraction <= 1:
        raise ValueError(f"knot_fraction: expected in (0, 1], got {knot_fraction}")
    if not m.any():
        raise ValueError("mask: expected at least one surface pixel, got none")
    return z, zs, m


#: One fitted rung: (rung, grid, coefficients, robust RMS, per-pixel robust sd), log depth.
LadderFit = tuple[Rung, "_Grid", np.ndarray, float, float]


def _ladder_fits(
    blocks: _Blocks, shape: tuple[int, int], knot_fraction: float, resolve_mm: float | None
) -> list[LadderFit]:
    """The fits ``(rung, grid, coef, rms, sigma_pix)`` of every rung of the ladder that the blocks can carry
    (``resolve_mm`` None: only the spline of ``knot_fraction``, or the finest rung the blocks carry)."""
    extent = float(max(shape))

    def fit(rung: Rung) -> LadderFit | None:
        grid = _Grid.over(shape, extent * (1.0 if isinstance(rung, str) else rung))
        if blocks.n_used < 4 * _POLYNOMIAL.get(rung, grid.size):
            return None
        return (rung, grid, *_fit(grid, blocks, degree=_DEGREE.get(rung)))

    if resolve_mm is None:
        ladder: list[Rung] = [
            knot_fraction,
            *(f for f in KNOT_LADDER[::-1] if f > knot_fraction),
            QUADRIC,
            PLANE,
        ]
        for rung in ladder:
            fits = [f for f in (fit(rung),) if f is not None]
            if fits:
                break
    else:
        rungs: list[Rung] = [PLANE, QUADRIC, *(k for k in KNOT_LADDER if k >= knot_fraction)]
        fits = [f for f in map(fit, rungs) if f is not None]
    if not fits:
        raise ValueError(
            f"stereo_depth_mm: expected stereo depth over at least {4 * _POLYNOMIAL[PLANE]} blocks of {blocks.size} px of "
            f"the surface, got {blocks.n_used}"
        )
    return fits


def _chosen(
    fits: list[LadderFit], blocks: _Blocks, resolve_mm: float | None, z_typ: float
) -> LadderFit:
    """The fit taken: each is scored by its residual plus what its coefficients would take out of pure noise
    (an information criterion); the best if it is the plane, else the coarsest from the quadric on within
    ``resolve_mm`` RMS of the best score."""
    noise2 = min(f[3] for f in fits) ** 2
    slack = 0.0 if resolve_mm is None else (resolve_mm / z_typ) ** 2

    def score(f: LadderFit) -> float:
        return float(
            f[3] ** 2
            + 2.0 * NOISE_CORRELATION * noise2 * _POLYNOMIAL.get(f[0], f[1].size) / blocks.n_used
        )

    best = min(fits, key=score)
    # the slack applies between the bend and the finer corrections: the bend itself needs no more than
    # its score (a bent plate must get the stereo pair's radius)
    return (
        best
        if best[0] == PLANE
        else next(f for f in fits if f[0] != PLANE and score(f) <= score(best) + slack)
    )


def _disagreement(zb: np.ndarray, corr_b: np.ndarray, mb: np.ndarray) -> float:
    """Disagreement of shape (mm, 95th percentile): the log correction without its best plane in (u, v)
    (a scale and tilt), on every 4th pixel of the box."""
    r_i, c_i = np.nonzero(mb[::4, ::4])
    z_s = zb[::4, ::4][r_i, c_i]
    log_corr = np.log1p(corr_b[::4, ::4][r_i, c_i].astype(np.float64) / z_s)
    A = np.column_stack([np.ones(r_i.size), c_i, r_i]).astype(np.float64)
    plane, *_ = np.linalg.lstsq(A, log_corr, rcond=None)
    return float(np.percentile(np.abs(log_corr - A @ plane) * z_s, 95))


def smooth_stereo_depth(
    stereo_depth_mm: np.ndarray, mask: np.ndarray, *, knot_fraction: float = 1.0 / 8.0
) -> np.ndarray:
    """A complete, smooth surface through the stereo depth: (H, W) float64 mm on ``mask``, NaN elsewhere.

    The robust spline of :func:`fuse_low_frequencies` (``knot_fraction``, no ladder) fitted to
    ``log z_stereo`` itself: a starting surface for the near-field normals where the stereo pair
    has holes and noise.
    """
    ones = np.where(mask, 1.0, np.nan)
    return fuse_low_frequencies(
        ones, stereo_depth_mm, mask, knot_fraction=knot_fraction, resolve_mm=None
    ).depth_mm


@dataclass(frozen=True)
class _Blocks:
    """Medians of ``log z_stereo - log z_ps`` over b x b blocks of a box of pixels.

    ``value`` (nbv, nbu) float64 (0 where unused), ``count`` (nbv, nbu) pixels with both depths
    (0 where unused), ``samples`` how many of them the median was taken over (every ``stride``-th
    pixel), ``centre_r``/``centre_c`` block centres in box pixels.
    """

    size: int
    value: np.ndarray
    count: np.ndarray
    samples: np.ndarray
    centre_r: np.ndarray
    centre_c: np.ndarray

    @property
    def n_used(self) -> int:
        return int(np.count_nonzero(self.count))

    @property
    def n_pixels(self) -> int:
        return int(self.count.sum())

    @classmethod
    def of(cls, z: np.ndarray, zs: np.ndarray, mask: np.ndarray) -> _Blocks:
        h, w = mask.shape
        b = max(MIN_BLOCK_PX, int(round(np.sqrt(h * w / TARGET_BLOCKS))))
        stride = max(1, b // 4)  # a median of up to 16 samples per block is plenty
        k = -(-b // stride)  # samples per block side
        b = k * stride
        nbv, nbu = -(-h // b), -(-w // b)
        padded = np.full((nbv * b, nbu * b), np.inf)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.log(zs[::stride, ::stride]) - np.log(z[::stride, ::stride])
        padded[:h:stride, :w:stride] = np.where(
            mask[::stride, ::stride] & np.isfinite(r), r, np.inf
        )
        tiles = padded[::stride, ::stride].reshape(nbv, k, nbu, k)
        tiles = tiles.transpose(0, 2, 1, 3).reshape(nbv, nbu, k * k)  # type: ignore[assignment]  # numpy's stubs keep the 4-d shape type
        have = np.isfinite(tiles)
        count = have.sum(axis=2)
        # a block's median stands for its centre only if its samples are spread around the centre
        offsets = np.arange(k, dtype=np.float64) - (k - 1) / 2.0
        with np.errstate(invalid="ignore", divide="ignore"):
            off_r = (have.reshape(nbv, nbu, k, k).sum(axis=3) @ offsets) / count
            off_c = (have.reshape(nbv, nbu, k, k).sum(axis=2) @ offsets) / count
        centred = (np.abs(off_r) <= MAX_CENTROID_OFFSET * k) & (
            np.abs(off_c) <= MAX_CENTROID_OFFSET * k
        )
        tiles.sort(axis=2)  # +inf (no data) last
        lo = np.take_along_axis(tiles, np.maximum((count - 1) // 2, 0)[..., None], axis=2)[..., 0]
        hi = np.take_along_axis(tiles, np.maximum(count // 2, 0)[..., None], axis=2)[..., 0]
        med = 0.5 * (lo + hi)
        used = (count >= max(1, int(MIN_BLOCK_FILL * k * k))) & centred
        samples = np.where(used, count, 0).astype(np.float64)
        centre = (
            stride * (k - 1) / 2.0
        )  # the centre of a block's samples (every stride-th pixel from its corner)
        return cls(
            size=b,
            value=np.where(used, med, 0.0),
            count=samples * stride * stride,  # pixels the samples stand for
            samples=samples,
            centre_r=np.arange(nbv) * b + centre,
            centre_c=np.arange(nbu) * b + centre,
        )


class _Grid:
    """Uniform cubic B-splines over a box of pixels: ``nv x nu`` coefficients, knots ``spacing`` px apart."""

    def __init__(self, shape: tuple[int, int], spacing: float) -> None:
        self.shape = shape
        self.spacing = float(spacing)
        self.nv = int(np.ceil(shape[0] / self.spacing)) + 3
        self.nu = int(np.ceil(shape[1] / self.spacing)) + 3

    @classmethod
    def over(cls, shape: tuple[int, int], spacing: float) -> _Grid:
        return cls(shape, max(4.0, spacing))

    @property
    def size(self) -> int:
        return self.nv * self.nu

    def basis(self, x: np.ndarray, n: int) -> np.ndarray:
        """(len(x), n) dense cubic B-spline basis along one axis at pixel coordinates x (box pixels)."""
        t = np.asarray(x, dtype=np.float64) / self.spacing
        i = np.clip(np.floor(t).astype(np.int64), 0, n - 4)
        f = t - i
        w = (
            np.stack(
                [(1 - f) ** 3, 3 * f**3 - 6 * f**2 + 4, -3 * f**3 + 3 * f**2 + 3 * f + 1, f**3],
                axis=1,
            )
            / 6.0
        )
        B = np.zeros((t.size, n))
        for a in range(4):
            B[np.arange(t.size), i + a] = w[:, a]
        return B

    def evaluate(self, coef: np.ndarray) -> np.ndarray:
        """The spline on every pixel of the box: (H, W), separably."""
        Bv = self.basis(np.arange(self.shape[0]), self.nv)
        Bu = self.basis(np.arange(self.shape[1]), self.nu)
        values: np.ndarray = (Bv @ coef.reshape(self.nv, self.nu)) @ Bu.T
        return values

    def penalty(self) -> np.ndarray:
        """P^T P of the second differences of the coefficients along both grid directions (dense)."""

        def dtd(n: int) -> np.ndarray:
            d = np.diff(np.eye(n), 2, axis=0)
            return d.T @ d

        return np.kron(dtd(self.nv), np.eye(self.nu)) + np.kron(np.eye(self.nv), dtd(self.nu))


def _fit(grid: _Grid, blocks: _Blocks, *, degree: int | None) -> tuple[np.ndarray, float, float]:
    """Robust penalised least squares of the spline to the block medians (weights: pixel counts).

    With ``degree`` (1 or 2) the correction is a polynomial of that degree in (u, v) (scale and tilt;
    and bend).
    Returns the coefficients (nv * nu,), the robust weighted RMS of the block residuals and the
    per-pixel robust standard deviation (both in log depth).
    """
    Bv = grid.basis(blocks.centre_r, grid.nv)
    Bu = grid.basis(blocks.centre_c, grid.nu)
    R, W0 = blocks.value, blocks.count
    Q = None
    if degree is not None:
        # a polynomial in the coefficients' indices is one in (u, v): cubic B-splines reproduce it
        gv, gu = np.meshgrid(
            np.arange(grid.nv, dtype=np.float64),
            np.arange(grid.nu, dtype=np.float64),
            indexing="ij",
        )
        gv, gu = gv.ravel() - gv.mean(), gu.ravel() - gu.mean()
        Q = np.column_stack(
            [np.ones(grid.size), gv, gu, gv * gv, gv * gu, gu * gu][
                : _POLYNOMIAL[PLANE] if degree == 1 else _POLYNOMIAL[QUADRIC]
            ]
        )
    PtP = grid.penalty()
    lam = SMOOTHING * W0.sum() / grid.size
    w = W0.copy()
    coef = np.zeros(grid.size)
    rms = sigma_pix = 0.0
    for _ in range(IRLS_PASSES):
        # normal equations of sum_ij w_ij (R_ij - (Bv C Bu^T)_ij)^2, separably
        inner = Bu.T @ (w[:, :, None] * Bu[None])  # (nbv, nu, nu): Bu^T diag(w_i) Bu per block row
        outer = Bv[:, :, None] * Bv[:, None, :]  # (nbv, nv, nv)
        N = (outer.reshape(len(Bv), -1).T @ inner.reshape(len(Bv), -1)).reshape(
            grid.nv, grid.nv, grid.nu, grid.nu
        )
        N = N.transpose(0, 2, 1, 3).reshape(grid.size, grid.size)
        rhs = (Bv.T @ (w * R) @ Bu).ravel()
        if Q is not None:
            coef = Q @ np.linalg.solve(Q.T @ N @ Q, Q.T @ rhs)
        else:
            coef = np.linalg.solve(N + lam * PtP, rhs)
        res = R - (Bv @ coef.reshape(grid.nv, grid.nu)) @ Bu.T
        used = W0 > 0
        # per-sample units: a median of n samples ~ 1.25 sigma / sqrt(n)
        scaled = (res * np.sqrt(blocks.samples))[used] / 1.2533
        sigma_pix = 1.4826 * float(np.median(np.abs(scaled)))
        rms = float(
            np.sqrt(np.sum(W0[used] * res[used] ** 2 * (w[used] / W0[used])) / np.sum(w[used]))
        )
        if not sigma_pix > 0:
            break
        a = np.abs(res) * np.sqrt(W0) / (HUBER_K * sigma_pix)
        w = W0 * np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    return coef, rms, sigma_pix


@nb.njit(cache=True, parallel=True)
def _compose(
    z: np.ndarray, c: np.ndarray, mask: np.ndarray, fused: np.ndarray, correction: np.ndarray
) -> None:
    """fused = z exp(c) and correction = fused - z on the mask (left NaN elsewhere), in place."""
    h, w = mask.shape
    for i in nb.prange(h):
        for j in range(w):
            if mask[i, j]:
                f = z[i, j] * np.exp(c[i, j])
                fused[i, j] = f
                correction[i, j] = f - z[i, j]
