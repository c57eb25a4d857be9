"""The specular lobe under point lights: measured on the stereo pair's surface, fitted with the normals.

A glossy coating adds a lobe around each light's mirror direction to every sample:

    I_k = a_k(X) * (rho n . l_k(X) + s g(n . h_k(X))),   g(c) = max(0, c)^e,
    h_k = normalize(l_k + v)   (v: towards the camera)

Under a ring of LEDs close to the plate, every light's half vector lies within ~25 deg of the normal
over the middle of the plate, so every sample there carries some lobe: rejecting samples cannot
remove it (the robust Lambertian fit was 1.6 deg off in the median, 11 deg at the 95th percentile
on the simulated 18-LED cell, worst on dark paint where the lobe outweighs the diffuse light), and
a fit of normals and lobe started from those Lambertian normals settles in the wrong minimum there
(the lobe's own gradient outweighs the diffuse term's). Two things make it well posed:

1. The lobe's shape (e) and strength (s) are properties of the coating, one pair for the plate.
   They are measured on the stereo pair's smooth surface, whose normals owe nothing to the
   photometric model: on a subsample of pixels, ``I_k / a_k = b . l_k + s_j g_e(n_stereo . h_k)``
   is linear in (b, s_j) for each candidate e (:data:`~pipeline.surface.normals.specular.LOBE_EXPONENTS`);
   the e with the least residual is taken, refined between its neighbours on that grid (a
   golden-section search: the grid's steps are 26 %, and a broad lobe read at 15.9 for 15 bent the
   normals by twice what noise does), and s is the median of the s_j. The lobe is modelled
   only when it takes out LOBE_MIN_F times what one free parameter per pixel takes out of noise
   (the F-ratio of the distant lights' specular stage): a matte plate skips this stage (the test
   runs first on ~PRETEST_PIXELS of the pixels, where a matte plate, F about 1, stops).
2. Per pixel, b = rho n is fitted by Gauss-Newton on all the lit samples with the lobe's
   derivative in the Jacobian, started from the stereo surface's normal (a few degrees from the
   truth at most). A pixel that ends more than MAX_SPECULAR_TURN_DEG from that start, or whose
   system is ill posed, keeps the robust Lambertian estimate.

The samples' residuals are then cut at SPECULAR_K global noise scales (a cast shadow, a lobe of
another shape) and the fit repeated. On the simulated 18-LED glare cell (seed 0) the normals'
error falls from 1.6 / 12.5 deg (median / p95) to 0.2 / 1.1 deg.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from pipeline.lights.model import Lights, light_at
from pipeline.surface.normals.field import OK, OUTSIDE, NormalField, field_from_fit
from pipeline.surface.normals.robust import COS_MIN
from pipeline.surface.normals.solve3 import DEGENERATE_RATIO, MIN_FIT, adjugate3, adjugate_times
from pipeline.surface.normals.specular import (
    LOBE_EXPONENTS,
    LOBE_MIN_F,
    MAX_SPECULAR_TURN_DEG,
    SPECULAR_K,
    SpecularFit,
)

Arr = npt.NDArray[Any]

#: The lobe is modelled when it explains this many times what one free parameter per pixel takes out
#: of noise: the threshold of the distant lights' specular stage.
MIN_F = LOBE_MIN_F
#: The lobe is measured on at most this many pixels (a regular subsample of the plate).
LOBE_SEARCH_PIXELS = 8000
#: The F-test is first run on about this many of those pixels (a regular subsample): a matte plate
#: stops there.
PRETEST_PIXELS = 1000
#: Golden-section steps refining the exponent between the grid's neighbours of its best one (the
#: grid's steps are 26 %; a broad lobe measured at 15.9 for the simulator's 15 bent the normals by
#: 0.9 deg in the median against 0.4 with the exact exponent): the bracket shrinks to 0.2 %.
EXPONENT_STEPS = 10
#: The lobe's own uncertainty (:func:`_lobe_spread`) treats the sampled pixels of one cell of an
#: ``n x n`` grid over the plate's larger extent as one cluster: the stereo surface the lobe is
#: measured on is a spline of knots 1/8 of the extent (:func:`pipeline.surface.fusion.smooth_stereo_depth`),
#: so its normals' errors are shared within a knot cell, not between cells.
LOBE_CLUSTERS_PER_SIDE = 8
#: Step in log exponent of the finite differences of the lobe fit's residual (its curvature).
LOG_EXPONENT_STEP = 0.02
#: Gauss-Newton passes per pixel before and after the residual cut.
GN_ITERATIONS = 4
#: As for the near-field Lambertian fit: samples of a light that lights the pixel less than this
#: fraction of its best-lit light are left out (outside the LED's beam).
MIN_RELATIVE_ATTENUATION = 0.02


@dataclass(frozen=True)
class Lobe:
    """The coating's lobe measured on the stereo surface: ``s * max(0, n . h)^e`` per unit irradiance.

    ``log_exponent_sd`` and ``amplitude_sd`` are the standard uncertainties of ``ln e`` and of ``s``
    from the fit itself, ``correlation`` theirs (:func:`_lobe_spread`). None where not measured (a
    lobe of another fit).
    """

    exponent: float
    amplitude: float
    f_ratio: float
    log_exponent_sd: float | None = None
    amplitude_sd: float | None = None
    correlation: float = 0.0


def surface_normals(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) float64 of a depth map (central differences of its 3-D points), towards
    the camera; NaN where a neighbour has no depth."""
    h, w = depth_mm.shape
    vv, uu = np.mgrid[:h, :w]
    rays = np.einsum(
        "ij,jhw->hwi", np.linalg.inv(K), np.stack([uu, vv, np.ones_like(uu)]).astype(np.float64)
    )
    points = rays * depth_mm[..., None]
    n = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    return _orient(n, points)


def surface_normals_at(depth_mm: np.ndarray, K: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """:func:`surface_normals` at the flat pixel indices ``idx`` only, (P, 3): the same central
    differences (one-sided at the image's border), computed on the pixels' 3 x 3 neighbourhoods."""
    h, w = depth_mm.shape
    i, j = np.divmod(idx, w)
    di = np.arange(-1, 2)
    ii = np.clip(i[:, None] + di, 0, h - 1)  # (P, 3): up, centre, down
    jj = np.clip(j[:, None] + di, 0, w - 1)  # (P, 3): left, centre, right
    rows = np.broadcast_to(ii[:, :, None], (idx.size, 3, 3))
    cols = np.broadcast_to(jj[:, None, :], (idx.size, 3, 3))
    pts = _points(depth_mm[rows, cols], K, cols, rows)  # (P, 3, 3, 3)
    d_u = (pts[:, 1, 2] - pts[:, 1, 0]) / (jj[:, 2] - jj[:, 0])[:, None]
    d_v = (pts[:, 2, 1] - pts[:, 0, 1]) / (ii[:, 2] - ii[:, 0])[:, None]
    return _orient(np.cross(d_u, d_v), pts[:, 1, 1])


def _points(depth: np.ndarray, K: np.ndarray, uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
    """The 3-D points (P, 3, 3, 3) of pixels (uu, vv) (P, 3, 3) at depths ``depth``."""
    uvw = np.stack([uu, vv, np.ones_like(uu)]).astype(np.float64)
    points: np.ndarray = np.einsum("ij,jpab->pabi", np.linalg.inv(K), uvw) * depth[..., None]
    return points


def _orient(n: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unit ``n`` turned towards the camera (NaN where undefined)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    flip = np.einsum("...c,...c->...", n, points) > 0
    return np.where(flip[..., None], -n, n)


def _normals_defined(depth_mm: np.ndarray) -> np.ndarray:
    """Where :func:`surface_normals` can be finite: the pixel's left/right and up/down neighbours
    (itself at the border) have a depth."""
    f = np.isfinite(depth_mm)
    pad = np.pad(f, 1, mode="edge")
    defined: np.ndarray = pad[1:-1, :-2] & pad[1:-1, 2:] & pad[:-2, 1:-1] & pad[2:, 1:-1]
    return defined


def measure_lobe(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    depth_mm: np.ndarray,
    normals: np.ndarray | None,
    mask: np.ndarray,
    K: np.ndarray,
    *,
    start_mm: np.ndarray | None = None,
    gain: np.ndarray | None = None,
    refine: bool = True,
) -> Lobe:
    """The lobe's exponent and amplitude from the images on a known surface (see the module docstring).

    ``depth_mm`` gives each pixel's point, ``normals`` (H, W, 3) its normal (the stereo pair's); both
    finite on ``mask``. With ``normals=None`` they are those of the depth map ``start_mm``
    (:func:`surface_normals`), computed at the sampled pixels only. ``gain`` (N,): the images
    times it are those divided by ``lights``' intensities (images divided by other lights'). Returns
    the lobe with its F-ratio (about 1 for a matte plate). ``refine=False``: the exponent stays on
    the grid of LOBE_EXPONENTS (a start for a fit that fits the exponent itself).

    The test runs first on about PRETEST_PIXELS of the sampled pixels: a plate whose lobe explains
    less than MIN_F / 2 there (a matte one: F about 1) is answered from that subsample
    (:func:`matte_lobe`); any other is measured on all of them, so that the lobe of a glossy plate is
    the same as without the pretest.
    """
    sampled = _lobe_samples(depth_mm, normals, mask, K, start_mm)
    if sampled is None:
        return Lobe(float("nan"), 0.0, 0.0)
    idx, n_all = sampled
    quick = _pretest(images, valid, lights, depth_mm, idx, n_all, mask.shape[1], K, gain, refine)
    if quick.f_ratio < MIN_F / 2:
        return quick
    return _lobe_on(images, valid, lights, depth_mm, n_all, idx, mask.shape[1], K, gain, refine)


def matte_lobe(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    depth_mm: np.ndarray,
    mask: np.ndarray,
    K: np.ndarray,
    *,
    start_mm: np.ndarray,
) -> Lobe | None:
    """:func:`measure_lobe`'s pretest alone (the normals those of ``start_mm``): the lobe when the plate is
    matte there (F under MIN_F / 2), else None (measure it on every sampled pixel). No parallel kernel:
    it may run on a worker beside the depth solve."""
    sampled = _lobe_samples(depth_mm, None, mask, K, start_mm)
    if sampled is None:
        return None
    idx, n_all = sampled
    quick = _pretest(images, valid, lights, depth_mm, idx, n_all, mask.shape[1], K, None, True)
    return quick if quick.f_ratio < MIN_F / 2 else None


def _lobe_samples(
    depth_mm: np.ndarray,
    normals: np.ndarray | None,
    mask: np.ndarray,
    K: np.ndarray,
    start_mm: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`measure_lobe`'s pixels (flat indices, about LOBE_SEARCH_PIXELS of the usable ones) and their
    normals (P, 3); None with fewer than 100 usable pixels."""
    if normals is not None:
        finite_n = np.all(np.isfinite(normals), axis=-1)
    elif start_mm is not None:
        finite_n = _normals_defined(start_mm)
    else:
        raise ValueError("normals: expected the normals or start_mm, got neither")
    ok_px = mask & np.isfinite(depth_mm) & finite_n
    idx = np.flatnonzero(ok_px.ravel())
    if idx.size < 100:
        return None
    idx = idx[:: max(1, idx.size // LOBE_SEARCH_PIXELS)]
    if normals is not None:
        return idx, normals.reshape(-1, 3)[idx]
    assert start_mm is not None
    n_all = surface_normals_at(start_mm, K, idx)
    finite = np.all(np.isfinite(n_all), axis=-1)  # a degenerate neighbourhood: none in practice
    return idx[finite], n_all[finite]


def _pretest(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    depth_mm: np.ndarray,
    idx: np.ndarray,
    n_all: np.ndarray,
    w: int,
    K: np.ndarray,
    gain: np.ndarray | None,
    refine: bool,
) -> Lobe:
    """The lobe on about PRETEST_PIXELS of the sampled pixels ``idx`` (normals ``n_all``)."""
    sub = slice(None, None, max(1, idx.size // PRETEST_PIXELS))
    return _lobe_on(images, valid, lights, depth_mm, n_all[sub], idx[sub], w, K, gain, refine)


def _lobe_on(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    depth_mm: np.ndarray,
    n: np.ndarray,
    idx: np.ndarray,
    w: int,
    K: np.ndarray,
    gain: np.ndarray | None = None,
    refine: bool = True,
) -> Lobe:
    """:func:`measure_lobe` on the flat pixels ``idx`` of normals ``n`` (P, 3)."""
    uv1 = np.stack([idx % w, idx // w, np.ones(idx.size)]).astype(np.float64)
    x = (np.linalg.inv(K) @ uv1).T * depth_mm.ravel()[idx, None]
    n_img = images.shape[0]
    raw = images.reshape(n_img, -1)[:, idx].astype(np.float64)
    if gain is not None:
        raw *= np.asarray(gain, np.float64)[:, None]
    use = None if valid is None else valid.reshape(n_img, -1)[:, idx]
    return lobe_of(raw, use, lights, x, n, refine=refine)


def lobe_on_samples(
    intensity: np.ndarray, points: np.ndarray, normals: np.ndarray, lights: Lights
) -> Lobe:
    """The lobe measured like :func:`measure_lobe` on samples (P, N) of points and normals (P, 3)
    under ``lights`` (sample blocks of :mod:`pipeline.lights.refinement`, whose values carry the
    lights' intensities)."""
    raw = intensity.T / lights.intensity[:, None]
    return lobe_of(raw, None, lights, points, normals)


def lobe_cosines(lv: np.ndarray, x: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``max(0, n . h_k)`` (N, P): the cosine the lobe is raised to at points ``x`` (P, 3, camera frame,
    mm) with normals ``n`` (P, 3), ``h_k`` the half vector of the light direction ``lv`` (N, P, 3)
    and the view towards the camera."""
    view = -x / np.linalg.norm(x, axis=-1, keepdims=True)
    half = lv + view[None]
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    c: np.ndarray = np.maximum(np.einsum("kpc,pc->kp", half, n), 0.0)
    return c


def lobe_of(
    raw: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    x: np.ndarray,
    n: np.ndarray,
    *,
    refine: bool = True,
) -> Lobe:
    """The lobe of values ``raw`` (N, P) (divided by the lights' intensities) at points ``x`` and
    normals ``n`` (P, 3): per point ``raw_k / a_k = b . l_k + s_p g_e(n . h_k)`` for each exponent,
    the exponent of least residual (on LOBE_EXPONENTS, then refined between the best one's
    neighbours unless ``refine`` is False) and the median amplitude, with the F-ratio against b
    alone."""
    lv = lights.directions_at(x)  # (N, P, 3)
    att = lights.attenuation_at(x)  # (N, P)
    c = lobe_cosines(lv, x, n)
    nl = np.einsum("kpc,pc->kp", lv, n)
    use = (nl > COS_MIN) & (att > MIN_RELATIVE_ATTENUATION * att.max(axis=0)) & np.isfinite(raw)
    if valid is not None:
        use &= valid
    wt = use.astype(np.float64)
    y = np.where(use, raw / np.where(use, att, 1.0), 0.0)

    def fit(cols: np.ndarray) -> tuple[np.ndarray, float]:
        sol, res = _weighted_fits(cols, y, wt)
        return sol, float(np.sum(res * res))

    def with_lobe(e: float) -> tuple[float, float]:
        sol, r = fit(np.concatenate([lv, (c**e)[..., None]], axis=-1))
        return r, float(np.median(sol[:, 3]))

    _, r_lambert = fit(lv)
    grid = [with_lobe(e) for e in LOBE_EXPONENTS]
    i = int(np.argmin([r for r, _ in grid]))
    r, s = grid[i]
    e = LOBE_EXPONENTS[i]
    if refine and np.isfinite(r):
        r, e, s = _refine_exponent(
            with_lobe,
            LOBE_EXPONENTS[max(i - 1, 0)],
            LOBE_EXPONENTS[min(i + 1, len(LOBE_EXPONENTS) - 1)],
            (r, e, s),
        )
    p = x.shape[0]
    dof = max(float(wt.sum()) - 4 * p, 1.0)
    f_ratio = ((r_lambert - r) / p) / max(r / dof, 1e-30)
    if not (f_ratio >= MIN_F and np.isfinite(e)):  # no lobe to model: nothing to qualify
        return Lobe(float(e), max(s, 0.0), float(f_ratio))
    sd_log_e, sd_s, corr = _lobe_spread(lv, c, y, wt, x, float(e))
    return Lobe(float(e), max(s, 0.0), float(f_ratio), sd_log_e, sd_s, corr)


def _lobe_spread(
    lv: np.ndarray, c: np.ndarray, y: np.ndarray, wt: np.ndarray, x: np.ndarray, e: float
) -> tuple[float, float, float]:
    """Standard uncertainties of the lobe's ``ln e`` and median amplitude ``s`` from the fit of
    :func:`lobe_of` (its arrays: light directions ``lv`` (N, P, 3), ``c = n . h`` (N, P), values ``y``
    and weights ``wt`` (N, P), points ``x`` (P, 3)), and their correlation.

    A delete-one-cluster jackknife, linearised: the stereo normals the lobe is measured on share
    their errors within a knot cell, so the pixels of a cell (:data:`LOBE_CLUSTERS_PER_SIDE` per
    side of the plate's larger extent) are left out together, never one by one (independent
    residuals would understate the spread). The exponent minimises the residual sum
    ``R(ln e)`` (every pixel's ``b`` and ``s_p`` fitted); without cluster ``k`` it moves by
    ``g_k / R''`` (``g_k``: the cluster's share of ``dR / d ln e``, which sums to 0 at the minimum;
    the cluster-robust sandwich). The amplitude is then the median of the other clusters' ``s_p``
    at that exponent (``s_p`` to first order in it).
    """
    h = LOG_EXPONENT_STEP
    (r_lo, s_lo), (r_0, s_0), (r_hi, s_hi) = (
        _pixel_fit(lv, c, y, wt, e * float(np.exp(d))) for d in (-h, 0.0, h)
    )
    curvature = float(np.sum(r_hi - 2.0 * r_0 + r_lo)) / h**2
    lo, hi = x[:, :2].min(axis=0), x[:, :2].max(axis=0)
    cell = max(float(np.max(hi - lo)) / LOBE_CLUSTERS_PER_SIDE, 1e-9)
    ij = np.minimum(((x[:, :2] - lo) / cell).astype(np.int64), LOBE_CLUSTERS_PER_SIDE - 1)
    _, cluster = np.unique(ij[:, 0] * LOBE_CLUSTERS_PER_SIDE + ij[:, 1], return_inverse=True)
    n_cl = int(cluster.max()) + 1
    if n_cl < 2 or not curvature > 0:
        return float("inf"), float("inf"), 0.0
    d_log_e = np.bincount(cluster, (r_hi - r_lo) / (2.0 * h), minlength=n_cl) / curvature
    slope = (s_hi - s_lo) / (2.0 * h)
    d_s = np.array(
        [np.median((s_0 + d_log_e[k] * slope)[cluster != k]) for k in range(n_cl)]
    ) - float(np.median(s_0))
    theta = np.stack([d_log_e, d_s], axis=1)
    theta -= theta.mean(axis=0)
    cov = (n_cl - 1) / n_cl * theta.T @ theta
    sd = np.sqrt(np.diag(cov))
    corr = float(cov[0, 1] / (sd[0] * sd[1])) if sd[0] * sd[1] > 0 else 0.0
    return float(sd[0]), float(sd[1]), corr


def _pixel_fit(
    lv: np.ndarray, c: np.ndarray, y: np.ndarray, wt: np.ndarray, e: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the least-squares fit of ``y = b . l + s_p c^e`` (weights ``wt``): its residual sum
    of squares and ``s_p`` (P,) each (the fit of :func:`lobe_of` at one exponent, pixel by pixel)."""
    sol, res = _weighted_fits(np.concatenate([lv, (c**e)[..., None]], axis=-1), y, wt)
    return np.sum(res * res, axis=0), sol[:, 3]


def _weighted_fits(
    cols: np.ndarray, y: np.ndarray, wt: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel's weighted least squares ``y_kp ~ cols_kp . sol_p`` (weights ``wt`` (N, P)): the
    solutions (P, k) and the weighted residuals (N, P)."""
    m = np.einsum("kpi,kpj,kp->pij", cols, cols, wt) + 1e-12 * np.eye(cols.shape[-1])
    rhs = np.einsum("kpi,kp,kp->pi", cols, y, wt)
    sol: np.ndarray = np.linalg.solve(m, rhs[..., None])[..., 0]
    res: np.ndarray = (y - np.einsum("kpi,pi->kp", cols, sol)) * wt
    return sol, res


def _refine_exponent(
    with_lobe: Any, lo: float, hi: float, best: tuple[float, float, float]
) -> tuple[float, float, float]:
    """The exponent of least residual between the grid's neighbours ``lo`` and ``hi`` of its best
    exponent: golden-section search on log e (EXPONENT_STEPS steps). ``with_lobe(e)`` returns the
    residual and the amplitude; ``best`` (residual, exponent, amplitude) is the grid's, kept unless
    beaten."""
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = np.log(lo), np.log(hi)
    x1, x2 = b - golden * (b - a), a + golden * (b - a)
    f1, f2 = with_lobe(float(np.exp(x1))), with_lobe(float(np.exp(x2)))
    for _ in range(EXPONENT_STEPS):
        for x, (r, s) in ((x1, f1), (x2, f2)):
            if r < best[0]:
                best = (r, float(np.exp(x)), s)
        if f1[0] < f2[0]:
            b, x2, f2 = x2, x1, f1
            x1 = b - golden * (b - a)
            f1 = with_lobe(float(np.exp(x1)))
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + golden * (b - a)
            f2 = with_lobe(float(np.exp(x2)))
    for x, (r, s) in ((x1, f1), (x2, f2)):
        if r < best[0]:
            best = (r, float(np.exp(x)), s)
    return best


def fit_with_lobe(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    depth_mm: np.ndarray,
    start_normals: np.ndarray,
    K: np.ndarray,
    lobe: Lobe,
    fallback: NormalField,
    noise: float,
) -> tuple[NormalField, int]:
    """Normals fitted with the lobe per pixel from the stereo surface's normals (module docstring).

    ``fallback``: the robust Lambertian field on the same pixels, kept where the fit fails or turns
    more than MAX_SPECULAR_TURN_DEG from its start. Returns the field (with a SpecularFit) and the
    number of pixels that kept the fallback.
    """
    h, w = images.shape[1:]
    mask = fallback.mask
    start = np.where(np.isfinite(start_normals), start_normals, fallback.normals)
    depth = np.where(mask & np.isfinite(depth_mm), depth_mm, 0.0)
    b = np.zeros((3, h, w), np.float64)
    rms = np.full((h, w), np.nan)
    good = np.zeros((h, w), np.bool_)
    args = _kernel_args(
        images, valid, lights, mask, depth, start, np.linalg.inv(K), lobe.exponent, lobe.amplitude
    )
    _lobe_kernel(*args, np.inf, False, b, rms, good)
    scale = max(float(np.nanmedian(rms[good])) if good.any() else 0.0, noise)
    _lobe_kernel(*args, SPECULAR_K * scale, True, b, rms, good)
    bn = np.linalg.norm(b, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = b / bn
    turn = np.degrees(np.arccos(np.clip(np.einsum("chw,hwc->hw", n, start), -1.0, 1.0)))
    take = good & mask & np.isfinite(turn) & (turn <= MAX_SPECULAR_TURN_DEG) & (n[2] < 0)
    estimated = mask & ~fallback.filled
    reverted = int(np.sum(estimated & ~take))
    out = np.where(
        take[None], b, np.moveaxis(fallback.normals * fallback.albedo[..., None], -1, 0)
    ).astype(np.float32)
    status = np.where(take | estimated, OK, OUTSIDE).astype(np.int8)
    fit = SpecularFit(
        modelled=True,
        exponent=lobe.exponent,
        f_ratio=lobe.f_ratio,
        amplitude_median=lobe.amplitude,
        n_reverted=reverted,
        log_exponent_sd=lobe.log_exponent_sd,
        amplitude_sd=lobe.amplitude_sd,
        lobe_correlation=lobe.correlation,
    )
    return field_from_fit(out, status, mask, specular=fit), reverted


def normals_with_lobe(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    depth_mm: np.ndarray,
    start_normals: np.ndarray,
    kinv: np.ndarray,
    exponent: float,
    amplitude: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, W, 3) fitted with a given lobe from ``start_normals`` on the pixels where
    ``depth_mm`` is finite, and where the fit converged (H, W): the Gauss-Newton of
    :func:`fit_with_lobe` without its residual cut, on any grid (``kinv`` maps its pixel (u, v, 1) to
    a ray; a subsampled grid's is ``K^-1 diag(step, step, 1)``). For the uncertainty: the normals'
    change when the lobe's parameters move (:mod:`pipeline.judge.uncertainty`).
    """
    h, w = depth_mm.shape
    mask = np.isfinite(depth_mm) & np.all(np.isfinite(start_normals), axis=-1)
    b = np.zeros((3, h, w), np.float64)
    good = np.zeros((h, w), np.bool_)
    start = np.where(mask[..., None], start_normals, 0.0)
    depth = np.where(mask, depth_mm, 0.0)
    args = _kernel_args(images, valid, lights, mask, depth, start, kinv, exponent, amplitude)
    _lobe_kernel(*args, np.inf, False, b, np.full((h, w), np.nan), good)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.moveaxis(b / np.linalg.norm(b, axis=0), 0, -1)
    return n, good & mask


#: :func:`_lobe_kernel`'s arguments up to its iterations (:func:`_kernel_args`).
_KernelArgs = tuple[Arr, Arr, bool, Arr, Arr, Arr, Arr, Arr, Arr, Arr, Arr, float, float, int]


def _kernel_args(
    images: np.ndarray,
    valid: np.ndarray | None,
    lights: Lights,
    mask: np.ndarray,
    depth_mm: np.ndarray,
    start_normals: np.ndarray,
    kinv: np.ndarray,
    exponent: float,
    amplitude: float,
) -> _KernelArgs:
    """The leading arguments of :func:`_lobe_kernel` (through its iterations), in the dtypes and
    layouts it is compiled for: ``depth_mm`` (H, W) and ``start_normals`` (H, W, 3) finite on
    ``mask``; ``kinv`` the grid's pixel to ray."""
    geometry, axes, kind = lights.kernel_arrays()
    return (
        np.ascontiguousarray(images),
        np.ascontiguousarray(valid) if valid is not None else np.ones((1, 1, 1), dtype=bool),
        valid is not None,
        np.ascontiguousarray(mask),
        np.ascontiguousarray(depth_mm, dtype=np.float64),
        np.ascontiguousarray(kinv, dtype=np.float64),
        geometry,
        axes,
        kind,
        lights.mu.astype(np.float64),
        np.ascontiguousarray(start_normals, dtype=np.float64),
        float(amplitude),
        float(exponent),
        GN_ITERATIONS,
    )


@numba.njit(parallel=True, cache=True)
def _lobe_kernel(
    images: Arr,
    valid: Arr,
    use_valid: bool,
    mask: Arr,
    depth: Arr,
    kinv: Arr,
    geometry: Arr,
    axes: Arr,
    kind: Arr,
    mu: Arr,
    start: Arr,
    s: float,
    e: float,
    iterations: int,
    cut: float,
    from_b: bool,
    b: Arr,
    rms: Arr,
    good: Arr,
) -> None:
    """Gauss-Newton per mask pixel of ``I_k / a_k = b . l_k + s max(0, n . h_k)^e`` (n = b / |b|).

    Starts from ``b`` when ``from_b`` (and the pixel converged before), else from ``start`` (H, W, 3)
    with the albedo fitted to it. Samples whose residual times a_k exceeds ``cut`` are left out.
    Writes b (3, H, W), the RMS of a_k * residual over the used samples, and ``good``.
    """
    n_img, h, w = images.shape
    for i in numba.prange(h):
        lv = np.empty((n_img, 3))
        hv = np.empty((n_img, 3))
        y = np.empty(n_img)
        att = np.empty(n_img)
        use = np.empty(n_img, np.bool_)
        for j in range(w):
            z = depth[i, j]
            if not mask[i, j] or not (z > 0.0):
                good[i, j] = False
                continue
            u, vv = float(j), float(i)
            x0 = z * (kinv[0, 0] * u + kinv[0, 1] * vv + kinv[0, 2])
            x1 = z * (kinv[1, 0] * u + kinv[1, 1] * vv + kinv[1, 2])
            x2 = z * (kinv[2, 0] * u + kinv[2, 1] * vv + kinv[2, 2])
            xn = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            v0, v1, v2 = -x0 / xn, -x1 / xn, -x2 / xn
            a_max = 0.0
            for k in range(n_img):
                l0, l1, l2, a = light_at(k, x0, x1, x2, geometry, axes, kind, mu)
                lv[k, 0], lv[k, 1], lv[k, 2] = l0, l1, l2
                h0, h1, h2 = l0 + v0, l1 + v1, l2 + v2
                hn = np.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
                hv[k, 0], hv[k, 1], hv[k, 2] = h0 / hn, h1 / hn, h2 / hn
                att[k] = a
                a_max = max(a_max, a)
            for k in range(n_img):
                x = images[k, i, j]
                ok = att[k] > MIN_RELATIVE_ATTENUATION * a_max and np.isfinite(x)
                if use_valid:
                    ok = ok and valid[k, i, j]
                use[k] = ok
                y[k] = x / att[k] if ok else 0.0
            if from_b and good[i, j]:
                b0, b1, b2 = b[0, i, j], b[1, i, j], b[2, i, j]
            else:
                n0, n1, n2 = start[i, j, 0], start[i, j, 1], start[i, j, 2]
                num = 0.0
                den = 0.0
                for k in range(n_img):
                    nl = n0 * lv[k, 0] + n1 * lv[k, 1] + n2 * lv[k, 2]
                    if use[k] and nl > COS_MIN:
                        c = max(n0 * hv[k, 0] + n1 * hv[k, 1] + n2 * hv[k, 2], 0.0)
                        num += (y[k] - s * c**e) * nl
                        den += nl * nl
                rho = num / den if den > 0.0 else 0.0
                b0, b1, b2 = rho * n0, rho * n1, rho * n2
            converged = rho_ok = True
            ss = 0.0
            cnt = 0
            for _ in range(iterations):
                bn = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
                if not (bn > 0.0):
                    rho_ok = False
                    break
                n0, n1, n2 = b0 / bn, b1 / bn, b2 / bn
                m00 = m01 = m02 = m11 = m12 = m22 = 0.0
                r0 = r1 = r2 = 0.0
                ss = 0.0
                cnt = 0
                for k in range(n_img):
                    if not use[k]:
                        continue
                    nl = n0 * lv[k, 0] + n1 * lv[k, 1] + n2 * lv[k, 2]
                    if nl <= COS_MIN:
                        continue
                    c = max(n0 * hv[k, 0] + n1 * hv[k, 1] + n2 * hv[k, 2], 0.0)
                    ce1 = c ** (e - 1.0) if c > 0.0 else 0.0  # one power per sample
                    g = s * ce1 * c
                    gp = s * e * ce1
                    r = y[k] - (b0 * lv[k, 0] + b1 * lv[k, 1] + b2 * lv[k, 2]) - g
                    if abs(r) * att[k] > cut:
                        continue
                    f = gp / bn
                    j0 = lv[k, 0] + f * (hv[k, 0] - c * n0)
                    j1 = lv[k, 1] + f * (hv[k, 1] - c * n1)
                    j2 = lv[k, 2] + f * (hv[k, 2] - c * n2)
                    m00 += j0 * j0
                    m01 += j0 * j1
                    m02 += j0 * j2
                    m11 += j1 * j1
                    m12 += j1 * j2
                    m22 += j2 * j2
                    r0 += j0 * r
                    r1 += j1 * r
                    r2 += j2 * r
                    ss += (r * att[k]) ** 2
                    cnt += 1
                c00, c01, c02, c11, c12, c22, det = adjugate3(m00, m01, m02, m11, m12, m22)
                tr = (m00 + m11 + m22) / 3.0
                if cnt < MIN_FIT or not det > DEGENERATE_RATIO * tr * tr * tr:
                    converged = False
                    break
                d0, d1, d2 = adjugate_times(c00, c01, c02, c11, c12, c22, r0, r1, r2)
                b0 += d0 / det
                b1 += d1 / det
                b2 += d2 / det
            ok_px = converged and rho_ok and np.isfinite(b0 + b1 + b2)
            good[i, j] = ok_px
            b[0, i, j], b[1, i, j], b[2, i, j] = b0, b1, b2
            rms[i, j] = np.sqrt(ss / cnt) if ok_px and cnt > 0 else np.nan
