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
feature that both see (a dent) is not in the difference at all.

The correction is chosen by the evidence (a lack-of-fit test): from a plane in (u, v) (scale and
tilt, always the stereo pair's), a quadric (and bend) and splines of finer knots, the coarsest rung
that the finest one does not beat by more than the stereo noise explains. When the test takes the
finest spline, it is estimated as a smoother: its second-difference penalty a prior on the
correction's roughness whose weight the data set (REML, :func:`_penalised`), so that its knot cells
at the outline or in a thin part of the mask, which few stereo blocks hold, follow the plate inside
as far as those blocks are weak instead of their correlated stereo error (bench_lights case 11, the
plate's edge beside a glare-lit conveyor). When the test takes a coarser spline, its coefficients
whose basis the blocks barely reach (the ring of knots beyond the outline, a corner of the mask's
bounding box) are held to the fit's quadric by a prior whose variance the well-held ones set
(:func:`_held_to_quadric`), instead of the free extrapolation of a few rim blocks (the sweep's
glossy cells, seeds 92 and 99, whose stereo pair carries highlights at the rim). The noise is
measured on the data: the robust spread of the finest rung's block residuals and their
correlation between neighbouring blocks (a stereo matcher's errors are correlated over its window
and smoothness term), which inflates what pure noise takes out of the residual. So exact normals
keep their shape (and their noise is all that reaches it), while wrong lights, whose bend the
stereo pair proves, hand the plate's overall shape to it. The fit's covariance gives the
correction's own standard deviation at every pixel and the bend's, for the uncertainty
(:mod:`pipeline.judge.uncertainty`).

References
----------
.. [1] D. Nehab, S. Rusinkiewicz, J. Davis, R. Ramamoorthi, "Efficiently combining positions and
   normals for precise 3D geometry", SIGGRAPH 2005 (the same split of frequencies, there by a
   Gaussian low-pass of positions).
.. [2] P. Dierckx, "Curve and surface fitting with splines", Oxford, 1993 (penalised tensor-product
   B-splines).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numba as nb
import numpy as np
import numpy.typing as npt
from scipy import linalg, optimize, special

from pipeline.solvers import bounding_box, percentile

#: Finest knot spacing of the correction spline as a fraction of the plate's larger extent in the
#: image: at most, the stereo pair governs shape wider than about this.
KNOT_FRACTION = 1.0 / 16.0
#: Knot spacings tried, coarsest first (after a plane and a quadric in (u, v)).
KNOT_LADDER = (1.0 / 2.0, 1.0 / 4.0, 1.0 / 8.0, 1.0 / 16.0)
#: Threads that fit the ladder's rungs (each fit is independent: the same fits on any number).
LADDER_WORKERS = 2
#: Significance level of the lack-of-fit test that lets a finer correction in (see :func:`_chosen`): a
#: coarser rung is kept unless the finest explains the stereo pair better than noise would with
#: probability 1 - SIGNIFICANCE.
SIGNIFICANCE = 1e-3
#: Largest neighbour correlation of the block residuals taken from the data (beyond it the
#: inflation of the noise would grow without bound).
MAX_NEIGHBOUR_CORRELATION = 0.9
#: The polynomial rungs of the ladder: a plane (scale and tilt) and a quadric (and bend) in (u, v).
PLANE, QUADRIC = "plane", "quadric"
#: A rung of the ladder: the plane, the quadric, or a spline of a knot spacing (fraction of the extent).
Rung = str | float
_POLYNOMIAL: dict[Rung, int] = {PLANE: 3, QUADRIC: 6}
_DEGREE: dict[Rung, int] = {PLANE: 1, QUADRIC: 2}
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
#: Weight of the second-difference penalty on the spline coefficients of a rung of fixed size (and of
#: the finest rung's first pass), relative to the data's total weight per coefficient: bridges knot
#: cells without stereo data, negligible where there is some. The finest spline, once chosen, is
#: estimated with the data's own weight (REML, :func:`_penalised`).
SMOOTHING = 1e-6


@dataclass(frozen=True)
class Fusion:
    """The fused surface, how far the two shapes disagreed, and how sure the correction is.

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
        medians' residuals of the finest rung, as if the noise were independent between samples).
    noise_floor_mm : float
        How much disagreement the stereo noise alone explains: 3 standard deviations of the chosen
        correction's value beyond its plane, as the disagreement is (``correction_sd_mm``: its
        covariance, the noise's correlation included), 95th percentile over the surface, mm; 0 for a
        plane.
    n_stereo : int
        Stereo pixels in the fit.
    knot_spacing_px : float or None
        Knot spacing of the correction chosen; None: a polynomial (see ``model``).
    model : {"plane", "quadric", "spline"}
        The correction chosen: scale and tilt; and bend; or a spline of ``knot_spacing_px``.
    noise_inflation : float
        How much the block residuals' correlation between neighbours inflates the variance of a
        smooth fit over pure, independent noise (1: independent), measured on the data.
    evidence : dict
        The lack-of-fit test per rung tried: ``{rung: [statistic, threshold]}`` (chi-square, its
        quantile at 1 - :data:`SIGNIFICANCE`); the rung chosen is the coarsest whose statistic is
        within its threshold.
    correction_sd_mm : (H, W) float32 or None
        Standard deviation of the chosen correction at every pixel from the stereo noise (its fit's
        covariance), beyond the least-squares plane in (u, v) through the correction's error over the
        mask (a rigid registration takes up scale and tilt), mm; NaN outside the mask.
    model_sd_mm : (H, W) float32 or None
        How far the next finer rung's correction lies from the chosen one at every pixel, mm (NaN
        outside the mask; None when the finest was chosen): the structure the lack-of-fit test did
        not let in, both what the stereo pair could not prove (a shape error of the normals below its
        noise's reach) and that rung's own noise. The uncertainty counts it as the model's part.
    bend_cov : (3, 3) float64 or None
        Covariance of the quadric correction's second derivatives ``(d2/du2, d2/dudv, d2/dv2)`` of
        log depth at the plate's centre, per px^2 squared: how well the stereo pair fixes the bend,
        whichever rung was chosen (the radius's uncertainty).
    """

    depth_mm: np.ndarray
    correction_mm: np.ndarray
    disagreement_mm: float
    stereo_noise_mm: float
    noise_floor_mm: float
    n_stereo: int
    knot_spacing_px: float | None
    model: str = "spline"
    noise_inflation: float = 1.0
    evidence: dict[str, list[float]] = field(default_factory=dict)
    correction_sd_mm: np.ndarray | None = None
    bend_cov: np.ndarray | None = None
    model_sd_mm: np.ndarray | None = None


def fuse_low_frequencies(
    depth_ps_mm: np.ndarray,
    stereo_depth_mm: np.ndarray,
    mask: np.ndarray,
    *,
    knot_fraction: float = KNOT_FRACTION,
    select: bool = True,
    coarsest: Rung = PLANE,
) -> Fusion:
    """Replace the low frequencies of a photometric surface by what the stereo pair proves of them.

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
    select : bool
        True: the correction is chosen from a ladder, a plane in (u, v) (scale and tilt), a quadric
        (and bend), then splines of knot spacing 1/2, 1/4, ... of the extent down to
        ``knot_fraction``, by a lack-of-fit test (:func:`_chosen`): the coarsest rung that the
        finest does not beat beyond the measured stereo noise. False: the spline of
        ``knot_fraction`` (or, with too few stereo blocks for it, the finest rung they carry).
    coarsest : {"plane", "quadric"}
        With ``select``: the coarsest rung the test may take. :data:`QUADRIC`: the stereo pair sets
        the bend whatever the test says, for normals whose bend is not to be trusted (fitted with a
        specular lobe: :func:`pipeline.surface.reconstruct.with_lobe`). The evidence of every rung
        is reported all the same.

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
    box = bounding_box(mask)
    assert box is not None  # _check_inputs refuses an empty mask
    zb, zsb, mb = z[box], zs[box], mask[box]
    if np.any(mb & ~((zb > 0) & (zb < np.inf))):
        raise ValueError("depth_ps_mm: expected finite depths > 0 mm on the mask")
    sparse = max(1, int(np.sqrt(mb.size / 100_000)))
    z_typ = float(np.median(zb[::sparse, ::sparse][mb[::sparse, ::sparse]]))
    blocks = _Blocks.of(zb, zsb, mb)
    fits = _ladder_fits(blocks, mb.shape, knot_fraction, select)
    chosen, inflation, evidence = _chosen(fits, blocks, coarsest) if select else (fits[0], 1.0, {})
    index = next(i for i, f in enumerate(fits) if f is chosen)
    finest = index == len(fits) - 1
    if select and finest and chosen.basis is None:  # the finest spline: estimated as a smoother
        chosen = _fit(
            chosen.grid, blocks, rung=chosen.rung, n_params=chosen.grid.size, smoother=True
        )
    fraction = chosen.rung if chosen.rung not in _POLYNOMIAL else None
    sigma_pix = fits[-1].sigma_pix if select else chosen.sigma_pix  # the finest rung's: the noise
    scale2 = _noise_variance(sigma_pix, blocks) * inflation
    finer = None if finest else fits[index + 1]
    if select and not finest and chosen.basis is None:
        # a coarser spline: its coefficients that no block holds are not left to free extrapolation
        chosen = _held_to_quadric(chosen, blocks, scale2)
    with ThreadPoolExecutor(max_workers=1) as pool:
        # the maps of the correction's uncertainty on a worker, beside the fused depth
        maps = pool.submit(_uncertainty_maps, chosen, finer, scale2, zb, mb, box, z.shape, select)
        fused = np.full(z.shape, np.nan)
        correction = np.full(z.shape, np.nan, np.float32)
        _compose(zb, chosen.grid.evaluate(chosen.coef), mb, fused[box], correction[box])
        disagreement = _disagreement(zb, correction[box], mb)
        sd, model, noise_floor = maps.result()
    quadric = next((f for f in fits if f.rung == QUADRIC), None)
    return Fusion(
        depth_mm=fused,
        correction_mm=correction,
        disagreement_mm=disagreement,
        stereo_noise_mm=float(sigma_pix * z_typ),
        noise_floor_mm=noise_floor,
        n_stereo=int(blocks.n_pixels),
        knot_spacing_px=None if fraction is None else float(chosen.grid.spacing),
        model=chosen.rung if isinstance(chosen.rung, str) else "spline",
        noise_inflation=float(inflation),
        evidence=evidence,
        correction_sd_mm=sd,
        bend_cov=None if quadric is None or not select else _bend_cov(quadric, scale2),
        model_sd_mm=model,
    )


def _uncertainty_maps(
    chosen: _Fitted,
    finer: _Fitted | None,
    scale2: float,
    zb: np.ndarray,
    mb: np.ndarray,
    box: tuple[slice, slice],
    shape: tuple[int, ...],
    select: bool,
) -> tuple[np.ndarray | None, np.ndarray | None, float]:
    """:attr:`Fusion.correction_sd_mm`, :attr:`Fusion.model_sd_mm` (None without ``select``, the latter
    also when the finest rung was chosen) and the noise floor (mm) of the chosen correction: its
    standard deviation and its difference from the next finer rung, mm, on the mask (``mb`` on the
    box ``box`` of a grid of ``shape``)."""
    if not select:
        return None, None, 0.0
    sd = np.full(shape, np.nan, np.float32)
    sd[box] = np.where(mb, _value_sd(chosen, scale2, mb) * zb, np.nan)
    model = None
    if finer is not None:
        model = np.full(shape, np.nan, np.float32)
        model[box] = np.where(mb, _difference(finer, chosen) * zb, np.nan)
    return sd, model, float(3.0 * _nan_p95(sd[box][mb]))


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


@dataclass(frozen=True)
class _Fitted:
    """One rung of the ladder fitted to the blocks (log depth).

    ``coef`` the spline coefficients; ``sigma_pix`` the per-sample robust standard deviation;
    ``residual`` (nbv, nbu) the block residuals; ``normal``
    the normal equations' matrix of the last pass (with the penalty), ``inverse`` its inverse when the
    penalised fit had it at hand (None: computed when needed), ``basis`` the polynomial basis in
    coefficient space (None for a spline); ``n_params`` the free parameters (a penalised spline's
    effective degrees of freedom).
    """

    rung: Rung
    grid: _Grid
    coef: np.ndarray
    sigma_pix: float
    residual: np.ndarray
    normal: np.ndarray
    inverse: np.ndarray | None
    basis: np.ndarray | None
    n_params: float


def _ladder_fits(
    blocks: _Blocks, shape: tuple[int, int], knot_fraction: float, select: bool
) -> list[_Fitted]:
    """The fits of every rung of the ladder that the blocks can carry, coarsest first (``select`` False:
    only the spline of ``knot_fraction``, or the finest rung the blocks carry)."""
    extent = float(max(shape))

    def fit(rung: Rung) -> _Fitted | None:
        grid = _Grid.over(shape, extent * (1.0 if isinstance(rung, str) else rung))
        n_params = _POLYNOMIAL.get(rung, grid.size)
        if blocks.n_used < 4 * n_params:
            return None
        return _fit(grid, blocks, rung=rung, n_params=n_params)

    if not select:
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
        # independent fits, mostly LAPACK and numpy's loops (the GIL released): two at a time
        with ThreadPoolExecutor(max_workers=LADDER_WORKERS) as pool:
            fits = [f for f in pool.map(fit, rungs) if f is not None]
    if not fits:
        raise ValueError(
            f"stereo_depth_mm: expected stereo depth over at least {4 * _POLYNOMIAL[PLANE]} blocks of {blocks.size} px of "
            f"the surface, got {blocks.n_used}"
        )
    return fits


def _chosen(
    fits: list[_Fitted], blocks: _Blocks, coarsest: Rung = PLANE
) -> tuple[_Fitted, float, dict[str, list[float]]]:
    """The rung taken by a lack-of-fit test against the finest, the noise inflation and the evidence
    (rungs coarser than ``coarsest`` are tested but never taken).

    Under pure noise, the drop of the standardised residual sum from a rung with ``p`` parameters to
    the finest (``p_f``) is chi-square with ``p_f - p`` degrees of freedom, once divided by the
    noise variance (the finest rung's residual sum over its ``n - p_f`` degrees of freedom, residuals
    clipped at one robust scale for all rungs) and by the inflation that the residuals' correlation
    between neighbouring blocks brings (measured on the finest rung's residuals). The coarsest rung whose drop is within the
    ``1 - SIGNIFICANCE`` quantile is taken: a finer correction enters only where the stereo pair
    proves it.
    """
    finest = fits[-1]
    inflation = _noise_inflation(finest.residual, blocks)
    used = blocks.count > 0
    root_n = np.sqrt(blocks.samples[used]) / 1.2533
    # one clip for every rung (the finest's robust scale), so that the sums compare
    clip = HUBER_K * max(finest.sigma_pix, 1e-12)

    def rss(f: _Fitted) -> float:
        return float(np.sum(np.minimum(np.abs(f.residual[used] * root_n), clip) ** 2))

    rss_finest = rss(finest)
    dof_noise = max(int(np.count_nonzero(used)) - finest.n_params, 1)
    noise2 = rss_finest / dof_noise * inflation
    evidence: dict[str, list[float]] = {}
    chosen = finest
    allowed = coarsest == PLANE or coarsest not in [f.rung for f in fits]
    for f in fits[:-1]:
        allowed = allowed or f.rung == coarsest
        dof = finest.n_params - f.n_params
        statistic = (rss(f) - rss_finest) / noise2 if noise2 > 0 else np.inf
        threshold = 2.0 * float(special.gammaincinv(dof / 2.0, 1.0 - SIGNIFICANCE))  # chi2 quantile
        evidence[_rung_name(f.rung)] = [round(float(statistic), 1), round(threshold, 1)]
        if statistic <= threshold and chosen is finest and allowed:
            chosen = f
    evidence[_rung_name(finest.rung)] = [0.0, 0.0]
    return chosen, inflation, evidence


def _rung_name(rung: Rung) -> str:
    return rung if isinstance(rung, str) else f"spline 1/{round(1.0 / rung)}"


def _noise_inflation(residual: np.ndarray, blocks: _Blocks) -> float:
    """Variance inflation of a smooth fit by the correlation of neighbouring block residuals.

    The standardised residuals' correlation between horizontal and between vertical neighbours
    (both blocks used), taken as a first-order autoregression along each axis: a smooth function's
    fit then sees ``(1 + r) / (1 - r)`` times the independent noise's variance per axis.
    """
    used = blocks.count > 0
    s = residual * np.sqrt(blocks.samples)
    scale = 1.4826 * float(np.median(np.abs(s[used]))) if used.any() else 0.0
    if not scale > 0:
        return 1.0
    s = np.where(used, np.clip(s / scale, -HUBER_K * 2, HUBER_K * 2), 0.0)
    factor = 1.0
    for a, b, both in (
        (s[:, 1:], s[:, :-1], used[:, 1:] & used[:, :-1]),
        (s[1:, :], s[:-1, :], used[1:, :] & used[:-1, :]),
    ):
        if np.count_nonzero(both) < 10:
            continue
        x, y = a[both], b[both]
        r = float(np.sum(x * y) / np.sqrt(np.sum(x * x) * np.sum(y * y)))
        r = min(max(r, 0.0), MAX_NEIGHBOUR_CORRELATION)
        factor *= (1.0 + r) / (1.0 - r)
    return factor


def _noise_variance(sigma_pix: float, blocks: _Blocks) -> float:
    """The variance (log depth squared) that scales ``normal^-1`` into the coefficients' covariance.

    A block's residual has variance ``(1.2533 sigma)^2 / samples`` (a median's efficiency) and the fit
    weighs it by ``samples * stride^2`` (its pixels): the weighted least squares' covariance is
    ``stride^2 (1.2533 sigma)^2 normal^-1``.
    """
    stride2 = float(np.mean(blocks.count[blocks.count > 0] / blocks.samples[blocks.count > 0]))
    return stride2 * (1.2533 * sigma_pix) ** 2


def _coef_cov(f: _Fitted, scale2: float) -> np.ndarray:
    """Covariance of a fit's spline coefficients (``scale2``: :func:`_noise_variance` times the inflation)."""
    if f.basis is not None:
        Q = f.basis
        inner = np.linalg.pinv(Q.T @ f.normal @ Q)
        cov: np.ndarray = scale2 * (Q @ inner @ Q.T)
        return cov
    inverse = f.inverse if f.inverse is not None else np.linalg.pinv(f.normal)
    cov_spline: np.ndarray = scale2 * inverse
    return cov_spline


def _value_sd(f: _Fitted, scale2: float, mask: np.ndarray) -> np.ndarray:
    """Standard deviation of a fit's value at every pixel of its box (log depth) beyond a plane in (u, v),
    from its covariance, computed on every 8th pixel and interpolated.

    The deviation is read after a rigid registration to the target, which takes up any error of scale
    and tilt: what remains of the correction's error at a pixel is its value less the least-squares
    plane through its values over the surface ``mask`` (the box's pixels). With ``c`` the coefficients'
    error (covariance ``C``), ``b(x)`` a pixel's basis row and ``a(x) = (1, u, v)``, the plane's
    coefficients are ``G c`` with ``G = (A^T A)^-1 A^T B`` over the sampled surface, and the residual
    ``(b(x) - a(x)^T G) c`` has the variance
    ``b C b^T - 2 b (C G^T) a + a^T (G C G^T) a``. A plane rung's error is such a plane: nothing remains.
    """
    cov = _coef_cov(f, scale2)
    grid = f.grid
    h, w = grid.shape
    rv, ru = _samples(h), _samples(w)
    Bv, Bu = grid.basis(rv, grid.nv), grid.basis(ru, grid.nu)
    # var(v, u) = sum_{ab,cd} Bv[v,a] Bu[u,b] C[ab,cd] Bv[v,c] Bu[u,d]
    C = cov.reshape(grid.nv, grid.nu, grid.nv, grid.nu)
    tmp = np.einsum("va,abcd->vbcd", Bv, C, optimize=True)
    tmp = np.einsum("vc,vbcd->vbd", Bv, tmp, optimize=True)
    var = np.einsum("ub,vbd,ud->vu", Bu, tmp, Bu, optimize=True)
    m = mask[np.ix_(rv.astype(np.int64).clip(max=h - 1), ru.astype(np.int64).clip(max=w - 1))]
    m = m.astype(np.float64)
    if m.sum() >= 3:
        # the plane's functions on the sampled grid, centred and scaled (well conditioned)
        vv = (rv - rv.mean()) / max(float(h), 1.0)
        uu = (ru - ru.mean()) / max(float(w), 1.0)
        planes = (
            np.ones(m.shape),
            np.broadcast_to(uu, m.shape),
            np.broadcast_to(vv[:, None], m.shape),
        )
        At_B = np.stack([(Bv.T @ (m * fk) @ Bu).ravel() for fk in planes])  # (3, p)
        AtA = np.array([[np.sum(m * fi * fj) for fj in planes] for fi in planes])
        G = np.linalg.solve(AtA, At_B)  # (3, p)
        D = cov @ G.T  # (p, 3): cov(c, plane coefficients)
        E = G @ D  # (3, 3): the plane coefficients' covariance
        cross = sum(planes[k] * ((Bv @ D[:, k].reshape(grid.nv, grid.nu)) @ Bu.T) for k in range(3))
        quad = sum(planes[i] * planes[j] * E[i, j] for i in range(3) for j in range(3))
        var = var - 2.0 * cross + quad
    return _on_pixels(np.sqrt(np.clip(var, 0.0, None)), h, w)


def _difference(finer: _Fitted, chosen: _Fitted) -> np.ndarray:
    """|finer - chosen| (log depth) at every pixel of their box, computed on every 8th pixel and
    interpolated (both are smooth on the scale of the finer rung's knots)."""
    h, w = chosen.grid.shape
    rv, ru = _samples(h), _samples(w)

    def sampled(f: _Fitted) -> np.ndarray:
        g = f.grid
        values: np.ndarray = (g.basis(rv, g.nv) @ f.coef.reshape(g.nv, g.nu)) @ g.basis(ru, g.nu).T
        return values

    return _on_pixels(np.abs(sampled(finer) - sampled(chosen)), h, w)


#: The maps of the correction's uncertainty are computed on every this many pixels and interpolated.
_MAP_STEP = 8


def _samples(n: int) -> np.ndarray:
    """Pixel positions along an axis of ``n`` pixels at which the maps are computed: the centres of
    :data:`_MAP_STEP`-pixel cells, where :func:`_on_pixels`' bilinear enlargement puts them."""
    return np.arange(-(-n // _MAP_STEP)) * _MAP_STEP + (_MAP_STEP - 1) / 2.0


def _on_pixels(values: np.ndarray, h: int, w: int) -> np.ndarray:
    """Values at :func:`_samples` positions brought to every pixel of an (h, w) box, float32 (bilinear;
    the outer half cells keep their nearest sample's value)."""
    rows, cols = values.shape
    full: np.ndarray = cv2.resize(
        values.astype(np.float32),
        (cols * _MAP_STEP, rows * _MAP_STEP),
        interpolation=cv2.INTER_LINEAR,
    )
    return full[:h, :w]


def _bend_cov(quadric: _Fitted, scale2: float) -> np.ndarray:
    """Covariance of the quadric's second derivatives of log depth ``(uu, uv, vv)`` per px^2 (see Fusion)."""
    cov = _coef_cov(quadric, scale2)
    grid = quadric.grid
    h, w = grid.shape
    c_v, c_u, d = (h - 1) / 2.0, (w - 1) / 2.0, max(h, w) / 4.0
    # second differences of the spline's value at the centre, as linear maps of the coefficients
    pts = {
        (dv, du): np.kron(
            grid.basis(np.array([c_v + dv * d]), grid.nv),
            grid.basis(np.array([c_u + du * d]), grid.nu),
        )[0]
        for dv in (-1, 0, 1)
        for du in (-1, 0, 1)
    }
    G = np.stack(
        [
            (pts[(0, 1)] - 2 * pts[(0, 0)] + pts[(0, -1)]) / d**2,
            (pts[(1, 1)] - pts[(1, -1)] - pts[(-1, 1)] + pts[(-1, -1)]) / (4 * d**2),
            (pts[(1, 0)] - 2 * pts[(0, 0)] + pts[(-1, 0)]) / d**2,
        ]
    )
    bend: np.ndarray = G @ cov @ G.T
    return bend


def _nan_p95(values: np.ndarray) -> float:
    """``np.nanpercentile(values, 95)`` of a 1-D sample (its finite values' 95th percentile, the same to the bit)."""
    finite = values[~np.isnan(values)]
    return float(percentile(finite, 95)) if finite.size else float("nan")


def _disagreement(zb: np.ndarray, corr_b: np.ndarray, mb: np.ndarray) -> float:
    """Disagreement of shape (mm, 95th percentile): the log correction without its best plane in (u, v)
    (a scale and tilt), on every 4th pixel of the box."""
    r_i, c_i = np.nonzero(mb[::4, ::4])
    z_s = zb[::4, ::4][r_i, c_i]
    log_corr = np.log1p(corr_b[::4, ::4][r_i, c_i].astype(np.float64) / z_s)
    A = np.column_stack([np.ones(r_i.size), c_i, r_i]).astype(np.float64)
    plane, *_ = np.linalg.lstsq(A, log_corr, rcond=None)
    return float(percentile(np.abs(log_corr - A @ plane) * z_s, 95))


def correction_basis(
    model: str,
    knot_spacing_px: float | None,
    rows: np.ndarray,
    cols: np.ndarray,
    shape: tuple[int, int],
) -> np.ndarray:
    """(P, k): the freedom of a correction (a :class:`Fusion`'s ``model`` and ``knot_spacing_px``) at
    pixels (``rows``, ``cols``) of the surface's bounding box (``shape`` px; box coordinates): a plane
    or a quadric in (u, v), or the cubic splines of its knot spacing over the box. Whatever change of
    the photometric log depth lies in their span, the stereo pair's correction takes out (the
    uncertainty's lobe part; a spline estimated with a prior, :func:`_penalised` and
    :func:`_held_to_quadric`, takes out a little less).
    """
    if knot_spacing_px is not None:
        grid = _Grid.over(shape, knot_spacing_px)
        Bv = grid.basis(np.asarray(rows, np.float64), grid.nv)
        Bu = grid.basis(np.asarray(cols, np.float64), grid.nu)
        splines: np.ndarray = (Bv[:, :, None] * Bu[:, None, :]).reshape(len(Bv), -1)
        return splines
    scale = max(float(max(shape)), 1.0)
    v, u = np.asarray(rows, np.float64) / scale, np.asarray(cols, np.float64) / scale
    return _monomials(v, u, _POLYNOMIAL[QUADRIC if model == QUADRIC else PLANE])


def smooth_stereo_depth(
    stereo_depth_mm: np.ndarray,
    mask: np.ndarray,
    *,
    knot_fraction: float = 1.0 / 8.0,
) -> np.ndarray:
    """A complete, smooth surface through the stereo depth: (H, W) float64 mm on ``mask``, NaN elsewhere.

    The robust spline of :func:`fuse_low_frequencies` (``knot_fraction``, no ladder) fitted to
    ``log z_stereo`` itself: a starting surface for the near-field normals, and for the lobe's
    measurement, where the stereo pair has holes and noise.
    """
    ones = np.where(mask, 1.0, np.nan)
    return fuse_low_frequencies(
        ones, stereo_depth_mm, mask, knot_fraction=knot_fraction, select=False
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


def _fit(
    grid: _Grid, blocks: _Blocks, *, rung: Rung, n_params: int, smoother: bool = False
) -> _Fitted:
    """Robust penalised least squares of the spline to the block medians (weights: pixel counts).

    For the polynomial rungs the correction is a polynomial of degree 1 (scale and tilt) or 2 (and
    bend) in (u, v).
    """
    Bv = grid.basis(blocks.centre_r, grid.nv)
    Bu = grid.basis(blocks.centre_c, grid.nu)
    R, W0 = blocks.value, blocks.count
    Q = _polynomial_basis(grid, _DEGREE[rung]) if rung in _DEGREE else None
    PtP = grid.penalty()
    lam = SMOOTHING * W0.sum() / grid.size  # before the noise is known: a bridge over empty cells
    w = W0.copy()
    used = W0 > 0
    coef = np.zeros(grid.size)
    res = R.copy()
    sigma_pix = 0.0
    N = np.eye(grid.size)
    inverse: np.ndarray | None = None
    edf = float(n_params)
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
            noise = sigma_pix if smoother else 0.0  # a fixed rung: the bridge over empty cells only
            coef, N, inverse, edf = _penalised(N, rhs, PtP, lam, noise, res, blocks)
        res = R - (Bv @ coef.reshape(grid.nv, grid.nu)) @ Bu.T
        # per-sample units: a median of n samples ~ 1.25 sigma / sqrt(n)
        scaled = (res * np.sqrt(blocks.samples))[used] / 1.2533
        sigma_pix = 1.4826 * float(np.median(np.abs(scaled)))
        if not sigma_pix > 0:
            break
        a = np.abs(res) * np.sqrt(W0) / (HUBER_K * sigma_pix)
        w = W0 * np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    return _Fitted(
        rung=rung,
        grid=grid,
        coef=coef,
        sigma_pix=sigma_pix,
        residual=np.where(used, res, 0.0),
        normal=N,
        inverse=inverse,
        basis=Q,
        n_params=edf,
    )


def _held_to_quadric(f: _Fitted, blocks: _Blocks, scale2: float) -> _Fitted:
    """A spline rung of fixed size with a prior on its coefficients' departure from its quadric.

    The ladder's fits are least squares (the lack-of-fit test compares them), so a coefficient
    whose basis the blocks barely reach (the ring of knots beyond the mask's outline, a corner of
    its bounding box) takes whatever a few rim blocks and the cubic's continuation give it, with a
    standard deviation of many mm, and the correction there is free extrapolation. Here the
    departures ``d`` of the coefficients from the fit's own quadric (its projection in the
    metric of the normal matrix: the weighted least-squares quadric of the same blocks) are taken
    as independent with variance ``tau^2`` (empirical Bayes: ``tau^2`` from the departures
    themselves, each weighted by how well it is known, Paule-Mandel [4]_). A coefficient that the
    blocks fix better than that spread (its least-squares variance below ``tau^2``) keeps its
    least-squares value: the prior there would only shrink what the stereo pair proves (the bend of
    near-field lights given by their directions grows towards the rim). One that they fix worse is
    its posterior mean under the prior: held to the quadric as far as the blocks are weak, with a
    posterior variance of ``tau^2`` at most, the correction's standard deviation there.

    References
    ----------
    .. [4] R. C. Paule, J. Mandel, "Consensus values and weighting factors", J. Res. Natl. Bur.
       Stand. 87 (1982) 377-385.
    """
    grid = f.grid
    N = f.normal
    Qc = _polynomial_basis(grid, 2)
    prior = Qc @ np.linalg.solve(Qc.T @ N @ Qc, Qc.T @ (N @ f.coef))
    departure = f.coef - prior
    var = np.clip(np.diag(_coef_cov(f, scale2)), 0.0, None)  # the fit's inverse, when it has one
    tau2 = _between_variance(departure, var, dof=grid.size - Qc.shape[1])
    # the prior only where it knows more than the data: a coefficient the blocks fix better than
    # the departures spread keeps its least-squares value
    A = N + np.diag(np.where(var > tau2, scale2 / tau2, 0.0))
    inverse = np.linalg.inv(A)
    coef = prior + inverse @ (N @ departure)
    Bv = grid.basis(blocks.centre_r, grid.nv)
    Bu = grid.basis(blocks.centre_c, grid.nu)
    residual = blocks.value - (Bv @ coef.reshape(grid.nv, grid.nu)) @ Bu.T
    return _Fitted(
        rung=f.rung,
        grid=grid,
        coef=coef,
        sigma_pix=f.sigma_pix,
        residual=np.where(blocks.count > 0, residual, 0.0),
        normal=A,
        inverse=inverse,
        basis=None,
        n_params=float(np.trace(inverse @ N)),
    )


def _between_variance(values: np.ndarray, var: np.ndarray, *, dof: int) -> float:
    """``tau^2`` of ``values ~ N(0, var + tau^2)`` by the Paule-Mandel moment equation
    ``sum(values^2 / (var + tau^2)) = dof`` (a value far less sure than ``tau^2`` weighs little;
    ``dof``: the values' count less the parameters fitted before them), solved by Brent's method. At
    least the smallest positive ``var`` over the values' count (no departure beyond the noise: held to
    the quadric)."""
    n = max(dof, 1)
    floor = float(np.min(var[var > 0])) / values.size if np.any(var > 0) else 1e-30
    squares = values**2

    def excess(tau2: float) -> float:  # falls as tau^2 grows
        return float(np.sum(squares / (var + tau2))) - n

    if excess(floor) <= 0.0:
        return floor
    # at hi the sum is below sum(values^2) / hi < 1 <= n
    hi = float(np.sum(squares)) + floor
    return float(optimize.brentq(excess, floor, hi, xtol=1e-9 * floor, rtol=1e-12))


def _penalised(
    N: np.ndarray,
    rhs: np.ndarray,
    PtP: np.ndarray,
    lam: float,
    sigma_pix: float,
    res: np.ndarray,
    blocks: _Blocks,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """One pass of the spline's penalised fit: coefficients, normal matrix with the penalty, its inverse
    (None in the first pass), effective degrees of freedom.

    The second-difference penalty is a prior on the correction's roughness: the coefficients' second
    differences independent with variance ``tau^2``, so its weight is ``s^2 / tau^2`` (``s^2`` the
    block noise per unit weight, :func:`_noise_variance` times the residuals' :func:`_noise_inflation`,
    from the previous pass). ``tau^2`` is not set but estimated from the data by REML, i.e. the weight
    that maximises the marginal likelihood of the block medians [3]_: a plate whose low frequencies
    the stereo pair proves rough gets a small one, and a coefficient that many blocks hold follows
    them whatever it is, while one that few blocks hold (a knot cell at the outline, a thin part of
    the mask) is drawn to the smooth continuation of its neighbours by as much as its data are weak
    against that prior, instead of following a few blocks' correlated stereo error. In the first
    pass (no noise measured yet), and for the ladder's fits (``sigma_pix`` 0: the lack-of-fit test
    compares nested least squares; only the finest spline, once the test takes it, is estimated so,
    see :func:`fuse_low_frequencies`), the weight is ``lam`` (:data:`SMOOTHING`), a bridge over knot
    cells without data and nothing more.

    With ``A = N + k PtP`` (``k`` balances the two's traces) and the generalised eigenvectors ``V``
    (``V^T A V = I``, ``V^T k PtP V = diag(g)``, ``0 <= g <= 1``), every weight ``mu k`` is
    diagonal: ``(N + mu k PtP)^-1 = V diag(1 / (1 + (mu - 1) g)) V^T``, so the REML criterion is
    searched over ``mu`` at no further factorisation.

    References
    ----------
    .. [3] S. N. Wood, "Generalized additive models", 2nd ed., CRC, 2017, sec. 6.2 (smoothing
       parameters by REML; a penalty as a Gaussian prior on the coefficients).
    """
    scale2 = (
        _noise_variance(sigma_pix, blocks) * _noise_inflation(res, blocks) if sigma_pix > 0 else 0.0
    )
    if not scale2 > 0:
        normal = N + lam * PtP
        return np.linalg.solve(normal, rhs), normal, None, float(PtP.shape[0])
    k = float(np.trace(N) / np.trace(PtP))
    try:
        g, V = linalg.eigh(k * PtP, N + k * PtP)
    except linalg.LinAlgError:  # data too sparse for the penalty's null space: no prior fitted
        normal = N + lam * PtP
        return np.linalg.solve(normal, rhs), normal, None, float(PtP.shape[0])
    g = np.clip(g, 0.0, 1.0)
    b2 = (V.T @ rhs) ** 2
    # the penalty's rank: all but its null space, the bilinear terms (1, u, v, uv)
    rank = int(np.count_nonzero(g > _PENALTY_NULL))
    mu = _PENALTY_GRID[:, None]
    d = 1.0 + (mu - 1.0) * g[None, :]
    # -2 log marginal likelihood (REML) up to a constant, per weight
    criterion = (
        -rank * np.log(mu[:, 0]) + np.log(d).sum(axis=1) - (b2[None, :] / d).sum(axis=1) / scale2
    )
    best = _PENALTY_GRID[int(np.argmin(criterion))]
    d_best = 1.0 + (best - 1.0) * g
    coef = V @ ((V.T @ rhs) / d_best)
    edf = float(np.sum((1.0 - g) / d_best))  # trace of the hat matrix
    inverse = (V / d_best) @ V.T  # (N + best k PtP)^-1, for the coefficients' covariance
    return coef, N + best * k * PtP, inverse, edf


#: Weights of the penalty searched (times the trace balance k, see :func:`_penalised`): from none to
#: far beyond any data, 0.05 decade apart (the criterion is flat on that scale near its minimum).
_PENALTY_GRID = np.logspace(-8.0, 10.0, 361)
#: Generalised eigenvalues below this are the penalty's null space (round-off of exact zeros).
_PENALTY_NULL = 1e-9


def _polynomial_basis(grid: _Grid, degree: int) -> np.ndarray:
    """(size, 3 or 6): spline coefficients of a polynomial of ``degree`` (1 or 2) in (u, v).

    A polynomial in the coefficients' indices is one in (u, v): cubic B-splines reproduce it.
    """
    gv, gu = np.meshgrid(
        np.arange(grid.nv, dtype=np.float64),
        np.arange(grid.nu, dtype=np.float64),
        indexing="ij",
    )
    gv, gu = gv.ravel() - gv.mean(), gu.ravel() - gu.mean()
    return _monomials(gv, gu, _POLYNOMIAL[PLANE] if degree == 1 else _POLYNOMIAL[QUADRIC])


def _monomials(v: np.ndarray, u: np.ndarray, count: int) -> np.ndarray:
    """(len(v), count): the first ``count`` of 1, v, u, v^2, v u, u^2 (a plane's 3, a quadric's 6)."""
    columns = [np.ones(v.size), v, u, v * v, v * u, u * u]
    return np.column_stack(columns[:count])


@nb.njit(nogil=True, cache=True)
def _compose(
    z: np.ndarray, c: np.ndarray, mask: np.ndarray, fused: np.ndarray, correction: np.ndarray
) -> None:
    """fused = z exp(c) and correction = fused - z on the mask (left NaN elsewhere), in place.

    Serial and without the GIL, so that any thread may fuse
    (:func:`pipeline.surface.reconstruct.stereo_lobe` smooths the stereo depth on a worker, beside the
    main thread's parallel kernels)."""
    h, w = mask.shape
    for i in range(h):
        for j in range(w):
            if mask[i, j]:
                f = z[i, j] * np.exp(c[i, j])
                fused[i, j] = f
                correction[i, j] = f - z[i, j]
