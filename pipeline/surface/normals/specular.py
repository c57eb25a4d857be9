"""The specular stage: a lobe fitted on glossy plates, and the normals refined under it.

Used by :func:`pipeline.surface.normals.estimate_normals` with ``method="robust"`` and a view direction
(``view_dirs`` or ``camera_matrix``). Shiny coatings add a lobe around the mirror direction to every
sample, I_k = rho n.l_k + s g(n.h_k) with the half vector h_k = normalize(l_k + v). For a ring of
lights the lobe is, to first order in the normal, inside the span of the Lambertian model, so
rejecting samples cannot remove it: it biases every normal smoothly (about 1 deg at a lobe as bright
as the diffuse part), and the integrated surface gets the wrong curvature. This stage models it:
the lobe's shape g(c) = max(0, c)^e is fitted globally (1-D search over LOBE_EXPONENTS on a
subsample of pixels: the e whose per-pixel non-negative amplitude removes the most residual); if
the lobe explains less than LOBE_MIN_F times what a free parameter takes out of pure noise the
stage stops (matte: the robust estimate stands; the test runs first on ~LOBE_PRETEST_PIXELS of the
pixels, where a matte plate, F about 1, stops). Otherwise SPECULAR_ITERATIONS joint Gauss-Newton
passes fit b = rho n per pixel and the amplitude s >= 0 pooled over SPECULAR_WINDOW-pixel boxes (a
per-pixel s is not identifiable; the pooled normal equation of s has the pixel's b eliminated:
Schur complement), on the lit samples with residuals within SPECULAR_K global noise scales (the
first pass, before the lobe is known, keeps all bright ones). The exponent is searched again half
way. On the simulated cylinder (R 5 m, 12 lights at 45 deg, lobe e = 40 at 0.4 of white) the
smoothed normal bias falls from ~1 deg to ~0.01 deg.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt

from .field import OK
from .robust import COS_MIN, FASTMATH, SHADOW_FRACTION
from .solve3 import DEGENERATE_RATIO, MIN_FIT, adjugate3, adjugate_times

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

#: Candidate lobe exponents e of g(c) = c^e, c = n.h (1-D search on the summed residual;
#: the minimum is refined by a parabola in log e). 2 ~ a very broad sheen, 1000 ~ a mirror-like glint.
LOBE_EXPONENTS = tuple(float(x) for x in np.geomspace(2.0, 1000.0, 28))
#: The search uses at most this many pixels (a regular subsample of the estimated ones).
LOBE_SEARCH_PIXELS = 40000
#: The F-test is first run on about this many of those pixels (a regular subsample of them), where a
#: matte plate stops: its F-ratio, about 1, is then read within a few hundredths (a mean over
#: thousands of pixels), so one below half of LOBE_MIN_F cannot reach LOBE_MIN_F on all of them.
LOBE_PRETEST_PIXELS = 5000
#: The lobe is modelled only when it explains this many times the residual that one extra
#: free parameter per pixel removes from pure noise (an F-ratio over the search pixels).
LOBE_MIN_F = 4.0
#: Side (px) of the box over which the specular amplitude s is pooled: s is a property of
#: the coating that varies slowly; one s per pixel is not identifiable (for a ring of lights
#: the lobe is, to first order, in the span of the Lambertian model).
SPECULAR_WINDOW = 31
#: Joint Gauss-Newton passes (normals per pixel, pooled amplitude).
SPECULAR_ITERATIONS = 4
#: In the specular stage a sample is used when lit (n.l > COS_MIN) and its residual is within
#: SPECULAR_K global noise scales (a cast shadow, an interreflection, a lobe of another shape).
SPECULAR_K = 3.0
#: A pixel the specular stage turns by more than this keeps its robust Lambertian estimate
#: (the stage corrects up to ~10 deg on the synthetic plates of the tests, ~1 deg on the simulated cell).
MAX_SPECULAR_TURN_DEG = 15.0
#: Samples of the lobe table over c in [0, 1].
_LOBE_TABLE = 4096


@dataclass(frozen=True)
class SpecularFit:
    """The specular lobe fitted by :func:`estimate_normals` (``method="robust"`` with a view direction).

    Attributes
    ----------
    modelled : bool
        False when the data showed no lobe worth modelling (matte: the Lambertian estimate stands).
    exponent : float
        Lobe exponent e of g(c) = max(0, c)^e, c = n . h_k, h_k = normalize(l_k + v) (NaN if not modelled).
    f_ratio : float
        Residual explained by the lobe over what one free parameter explains in pure noise (~1 without a lobe).
    amplitude_median : float
        Median over the estimated pixels of the pooled amplitude s (same units as the images).
    n_reverted : int
        Pixels the lobe turned by more than MAX_SPECULAR_TURN_DEG (or away from the camera):
        they keep the robust Lambertian estimate.
    log_exponent_sd, amplitude_sd : float or None
        Standard uncertainties of ``ln e`` and of the amplitude from the lobe's own fit, where it was
        measured once for the plate (:func:`pipeline.lights.glare.lobe_of`, near-field LEDs); None
        for this stage's lobe. The uncertainty propagates them through the normals
        (:mod:`pipeline.judge.uncertainty`).
    lobe_correlation : float
        The correlation of those two (the fit's amplitude follows its exponent).
    """

    modelled: bool
    exponent: float
    f_ratio: float
    amplitude_median: float
    n_reverted: int = 0
    log_exponent_sd: float | None = None
    amplitude_sd: float | None = None
    lobe_correlation: float = 0.0


def _lobe_tables(exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """g(c) = c^e and g'(c) = e c^(e-1) sampled at c = i / (_LOBE_TABLE - 1), float64 (_LOBE_TABLE + 1,) each
    (one guard entry for the interpolation at c = 1)."""
    c = np.linspace(0.0, 1.0, _LOBE_TABLE)
    g = c**exponent
    dg = exponent * c ** (exponent - 1.0)
    return np.append(g, g[-1]), np.append(dg, dg[-1])


@functools.cache
def _search_tables() -> np.ndarray:
    """The lobe tables g of every exponent in LOBE_EXPONENTS, (_LOBE_TABLE + 1, E) float64, read-only:
    made once a process (every plate's search reads them)."""
    tables = np.stack([_lobe_tables(e)[0] for e in LOBE_EXPONENTS], axis=1)
    tables.flags.writeable = False
    return tables


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH, inline="always")
def _lookup(table: Arr, c: float) -> float:
    """Linear interpolation of a lobe table at c (clamped to [0, 1]: the lobe is 0 for c <= 0)."""
    x = min(max(c, 0.0), 1.0) * (_LOBE_TABLE - 1)
    i = int(x)
    f = x - i
    value: float = table[i] + f * (table[i + 1] - table[i])
    return value


def specular(
    images: np.ndarray,
    valid: np.ndarray | None,
    status: np.ndarray,
    L: np.ndarray,
    view_map: np.ndarray,
    b: np.ndarray,
) -> SpecularFit:
    """The specular stage (see the module docstring): fit a lobe and refine b in place.

    Parameters
    ----------
    images : (N, H, W) float32
    valid : (N, H, W) bool or None
    status : (H, W) int8
        The robust fit's status codes: the stage works on its estimated pixels.
    L : (N, 3) float64
        Unit light directions.
    view_map : (3, 3) float64
        The view direction of pixel (u, v) is normalize(view_map (u, v, 1)).
    b : (3, H, W) float32
        rho n of the robust fit, refined in place.

    Returns
    -------
    SpecularFit
    """
    w = images.shape[2]
    fit = status == OK
    flat = np.flatnonzero(fit)
    sel = flat[:: max(1, flat.size // LOBE_SEARCH_PIXELS)]
    pretest = sel[:: max(1, sel.size // LOBE_PRETEST_PIXELS)]
    exponent, f_ratio, sigma = _lobe_search(images, valid, b, pretest, w, view_map, L)
    if f_ratio >= LOBE_MIN_F / 2 and pretest.size < sel.size:
        exponent, f_ratio, sigma = _lobe_search(images, valid, b, sel, w, view_map, L)
    if not f_ratio >= LOBE_MIN_F:
        return SpecularFit(
            modelled=False, exponent=float("nan"), f_ratio=f_ratio, amplitude_median=0.0
        )
    b_start = b.copy()
    s, exponent, f_ratio = _joint_fit(
        images, valid, fit, sel, L, view_map, b, exponent, f_ratio, sigma
    )
    n_reverted = _revert_turned(b, b_start, fit)
    return SpecularFit(
        modelled=True,
        exponent=exponent,
        f_ratio=f_ratio,
        amplitude_median=float(np.median(s[fit])),
        n_reverted=n_reverted,
    )


def _lobe_search(
    images: Arr, valid: Arr | None, b: Arr, sel: Arr, w: int, view_map: Arr, L: Arr
) -> tuple[float, float, float]:
    """The lobe exponent over the search pixels ``sel`` (flat indices into rows of width ``w``).

    Returns (exponent, F-ratio, noise sigma): the exponent refined by a parabola in log e; NaN,
    0, NaN when no search pixel can be used.
    """
    n, h = images.shape[:2]
    rows, cols = np.divmod(sel, w)
    samples = images.reshape(n, h * w).take(sel, axis=1).astype(np.float64)
    usable = (
        valid.reshape(n, h * w).take(sel, axis=1)
        if valid is not None
        else np.ones(samples.shape, dtype=bool)
    )
    pv = np.stack([cols, rows, np.ones(sel.size)], axis=1) @ view_map.T
    pv /= np.linalg.norm(pv, axis=1, keepdims=True)
    exps = np.array(LOBE_EXPONENTS)
    tables = _search_tables()
    out = np.empty((sel.size, exps.size + 2))
    _lobe_search_kernel(
        samples,
        usable,
        b.reshape(3, h * w).take(sel, axis=1).astype(np.float64),
        pv,
        L,
        tables,
        COS_MIN,
        SHADOW_FRACTION,
        out,
    )
    used = out[:, -1] > 0
    if not used.any():
        return float("nan"), 0.0, float("nan")
    red = out[used, :-2].sum(axis=0)
    best = int(np.argmax(red))
    dof = (out[used, -1] - 4.0).sum()
    sigma2 = (out[used, -2].sum() - red[best]) / dof
    f_ratio = float(red[best] / sigma2 / used.sum()) if sigma2 > 0 else float("inf")
    log_e = np.log(exps[best])
    if 0 < best < exps.size - 1:  # parabola through the neighbours in log e
        y0, y1, y2 = red[best - 1], red[best], red[best + 1]
        curv = y0 - 2 * y1 + y2
        step = np.log(exps[best + 1]) - log_e
        if curv < 0:
            log_e += 0.5 * step * (y0 - y2) / curv
    return float(np.exp(log_e)), f_ratio, float(np.sqrt(max(sigma2, 0.0)))


def _joint_fit(
    images: Arr,
    valid: Arr | None,
    fit: Arr,
    sel: Arr,
    L: Arr,
    view_map: Arr,
    b: Arr,
    exponent: float,
    f_ratio: float,
    sigma: float,
) -> tuple[Arr, float, float]:
    """SPECULAR_ITERATIONS joint Gauss-Newton passes over b (in place) and the pooled amplitude.

    Returns the amplitude s (H, W) float32 and the exponent and F-ratio in use at the end (the
    exponent is searched again half way, and kept only if the lobe is clear).
    """
    _n, h, w = images.shape
    use_valid = valid is not None
    v = valid if valid is not None else np.ones((1, 1, 1), dtype=bool)
    s = np.zeros((h, w), dtype=np.float32)
    db0 = np.empty((3, h, w), dtype=np.float32)
    coef = np.empty((3, h, w), dtype=np.float32)
    num = np.empty((h, w), dtype=np.float32)
    den = np.empty((h, w), dtype=np.float32)
    box = (SPECULAR_WINDOW, SPECULAR_WINDOW)
    for it in range(SPECULAR_ITERATIONS):
        if (
            it == SPECULAR_ITERATIONS // 2
        ):  # again, from the better normals; kept only if it is a clear lobe
            again = _lobe_search(images, valid, b, sel, w, view_map, L)
            if again[1] >= LOBE_MIN_F and LOBE_EXPONENTS[0] < again[0] < LOBE_EXPONENTS[-1]:
                exponent, f_ratio, sigma = again
        g_table, dg_table = _lobe_tables(exponent)
        hi = np.inf if it == 0 else SPECULAR_K * sigma  # the first pass starts without the lobe
        _specular_pass_kernel(
            images,
            v,
            use_valid,
            fit,
            L,
            view_map,
            g_table,
            dg_table,
            b,
            s,
            COS_MIN,
            -SPECULAR_K * sigma,
            hi,
            db0,
            coef,
            num,
            den,
        )
        pooled_num = cv2.boxFilter(num, -1, box, normalize=False)
        pooled_den = cv2.boxFilter(den, -1, box, normalize=False)
        # a box with (almost) no information on s keeps its s
        ds = np.divide(
            pooled_num,
            pooled_den,
            out=np.zeros_like(num),
            where=pooled_den > 1e-6 * float(pooled_den.max()),
        )
        s_new = np.maximum(s + ds, 0.0)  # the lobe adds light: s >= 0 (a constraint of the model)
        step = s_new - s
        np.add(b, db0 - coef * step, out=b, where=fit)  # b outside the fitted pixels is not defined
        s = s_new
    return s, exponent, f_ratio


def _revert_turned(b: Arr, b_start: Arr, fit: Arr) -> int:
    """Pixels the lobe turned by more than MAX_SPECULAR_TURN_DEG (or away from the camera) get their
    Lambertian estimate back: the lobe did not describe them (saturated peak, another material).
    Returns how many."""
    with np.errstate(
        all="ignore"
    ):  # NaN / inf compare False below: reverted; b outside fit is undefined
        b64, b0 = b.astype(np.float64), b_start.astype(np.float64)
        cos_turn = (b64 * b0).sum(axis=0) / np.sqrt((b64 * b64).sum(axis=0) * (b0 * b0).sum(axis=0))
    revert = fit & ~((cos_turn > np.cos(np.radians(MAX_SPECULAR_TURN_DEG))) & (b[2] < 0))
    b[:, revert] = b_start[:, revert]
    return int(revert.sum())


@numba.njit(parallel=True, cache=True)
def _lobe_search_kernel(
    samples: Arr,
    usable: Arr,
    b: Arr,
    view: Arr,
    L: Arr,
    g_tables: Arr,
    cos_min: float,
    shadow_fraction: float,
    out: Arr,
) -> None:
    """Per search pixel p and lobe e: the residual the lobe removes from the Lambertian fit.

    samples, usable : (N, P); b : (3, P) current rho n; view : (P, 3); g_tables : (T+1, E), the
    lobe tables side by side (row t: every lobe at c = t / (T - 1)), so that one sample's
    interpolation weights serve all lobes in one contiguous loop.
    out : (P, E + 2): [:, e] reduction of the summed squared residual by s g_e (s >= 0),
    [:, E] the Lambertian residual, [:, E + 1] the number of samples used (0: pixel unusable).
    """
    n, p_count = samples.shape
    n_exp = g_tables.shape[1]
    for p in numba.prange(p_count):
        out[p, :] = 0.0
        rho = np.sqrt(b[0, p] ** 2 + b[1, p] ** 2 + b[2, p] ** 2)
        if not rho > 0:
            continue
        nx, ny, nz = b[0, p] / rho, b[1, p] / rho, b[2, p] / rho
        w = np.zeros(n)
        cs = np.zeros(n)
        m00 = m01 = m02 = m11 = m12 = m22 = r0 = r1 = r2 = cnt = 0.0
        for k in range(n):
            lx, ly, lz = L[k, 0], L[k, 1], L[k, 2]
            nl = nx * lx + ny * ly + nz * lz
            x = samples[k, p]
            if usable[k, p] and nl > cos_min and x > shadow_fraction * rho * nl:
                w[k] = 1.0
                m00 += lx * lx
                m01 += lx * ly
                m02 += lx * lz
                m11 += ly * ly
                m12 += ly * lz
                m22 += lz * lz
                r0 += x * lx
                r1 += x * ly
                r2 += x * lz
                cnt += 1.0
            hx, hy, hz = lx + view[p, 0], ly + view[p, 1], lz + view[p, 2]
            hn = np.sqrt(hx * hx + hy * hy + hz * hz)
            cs[k] = (nx * hx + ny * hy + nz * hz) / hn
        c00, c01, c02, c11, c12, c22, det = adjugate3(m00, m01, m02, m11, m12, m22)
        tr = (m00 + m11 + m22) / 3.0
        if cnt < MIN_FIT + 2 or not det > DEGENERATE_RATIO * tr * tr * tr:
            continue
        b0, b1, b2 = adjugate_times(c00, c01, c02, c11, c12, c22, r0, r1, r2)
        b0, b1, b2 = b0 / det, b1 / det, b2 / det
        sse = 0.0
        for k in range(n):
            r = samples[k, p] - (b0 * L[k, 0] + b1 * L[k, 1] + b2 * L[k, 2])
            sse += w[k] * r * r
        out[p, n_exp] = sse
        out[p, n_exp + 1] = cnt
        gi = np.zeros(n_exp)
        glx = np.zeros(n_exp)
        gly = np.zeros(n_exp)
        glz = np.zeros(n_exp)
        gg = np.zeros(n_exp)
        for k in range(n):
            if w[k] > 0:
                x = min(max(cs[k], 0.0), 1.0) * (
                    _LOBE_TABLE - 1
                )  # as _lookup, for every lobe at once
                t = int(x)
                f = x - t
                lo, hi = g_tables[t], g_tables[t + 1]
                sk, lx, ly, lz = samples[k, p], L[k, 0], L[k, 1], L[k, 2]
                for e in range(n_exp):
                    g = lo[e] + f * (hi[e] - lo[e])
                    gi[e] += g * sk
                    glx[e] += g * lx
                    gly[e] += g * ly
                    glz[e] += g * lz
                    gg[e] += g * g
        for e in range(n_exp):
            a0, a1, a2 = adjugate_times(c00, c01, c02, c11, c12, c22, glx[e], gly[e], glz[e])
            a0, a1, a2 = a0 / det, a1 / det, a2 / det
            num = gi[e] - (a0 * r0 + a1 * r1 + a2 * r2)
            den = gg[e] - (a0 * glx[e] + a1 * gly[e] + a2 * glz[e])
            if den > 1e-12 * gg[e] and num > 0:  # s = num / den >= 0
                out[p, e] = num * num / den


@numba.njit(parallel=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def _specular_pass_kernel(
    images: Arr,
    valid: Arr,
    use_valid: bool,
    fit: Arr,
    L: Arr,
    view_map: Arr,
    g_table: Arr,
    dg_table: Arr,
    b: Arr,
    s_map: Arr,
    cos_min: float,
    lo: float,
    hi: float,
    db0: Arr,
    coef: Arr,
    num: Arr,
    den: Arr,
) -> None:
    """One joint Gauss-Newton linearisation of I_k = b.l_k + s g(n.h_k) at every pixel with fit True.

    b (3, H, W) = rho n and s_map (H, W) are the current estimate; lo < r_k < hi selects the samples;
    the view direction of pixel (i, j) is normalize(view_map (j, i, 1)).
    Out: db0 (3, H, W) the step in b with s fixed, coef (3, H, W) the change of that step per unit
    change of s, num / den (H, W) the pixel's normal equation for s with b eliminated (Schur
    complement): ds = num / den (0, 0 where the pixel has no well-posed system).
    """
    n, h, w = images.shape
    for i in numba.prange(h):
        for j in range(w):
            db0[0, i, j] = db0[1, i, j] = db0[2, i, j] = 0.0
            coef[0, i, j] = coef[1, i, j] = coef[2, i, j] = 0.0
            num[i, j] = 0.0
            den[i, j] = 0.0
            if not fit[i, j]:
                continue
            bx, by, bz = b[0, i, j], b[1, i, j], b[2, i, j]
            rho = np.sqrt(bx * bx + by * by + bz * bz)
            if not rho > 0:
                continue
            nx, ny, nz = bx / rho, by / rho, bz / rho
            vx = view_map[0, 0] * j + view_map[0, 1] * i + view_map[0, 2]
            vy = view_map[1, 0] * j + view_map[1, 1] * i + view_map[1, 2]
            vz = view_map[2, 0] * j + view_map[2, 1] * i + view_map[2, 2]
            vn = 1.0 / np.sqrt(vx * vx + vy * vy + vz * vz)
            vx, vy, vz = vx * vn, vy * vn, vz * vn
            s = s_map[i, j]
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            jr0 = jr1 = jr2 = jg0 = jg1 = jg2 = gr = gg = cnt = 0.0
            for k in range(n):
                if use_valid and not valid[k, i, j]:
                    continue
                lx, ly, lz = L[k, 0], L[k, 1], L[k, 2]
                nl = nx * lx + ny * ly + nz * lz
                if not nl > cos_min:
                    continue
                hx, hy, hz = lx + vx, ly + vy, lz + vz
                hn = 1.0 / np.sqrt(hx * hx + hy * hy + hz * hz)
                hx, hy, hz = hx * hn, hy * hn, hz * hn
                c = nx * hx + ny * hy + nz * hz
                g = _lookup(g_table, c)
                r = images[k, i, j] - (bx * lx + by * ly + bz * lz) - s * g
                if not (lo < r < hi):
                    continue
                t = s * _lookup(dg_table, c) / rho  # d(s g)/db = t (h - c n)
                j0 = lx + t * (hx - c * nx)
                j1 = ly + t * (hy - c * ny)
                j2 = lz + t * (hz - c * nz)
                a00 += j0 * j0
                a01 += j0 * j1
                a02 += j0 * j2
                a11 += j1 * j1
                a12 += j1 * j2
                a22 += j2 * j2
                jr0 += j0 * r
                jr1 += j1 * r
                jr2 += j2 * r
                jg0 += j0 * g
                jg1 += j1 * g
                jg2 += j2 * g
                gr += g * r
                gg += g * g
                cnt += 1.0
            c00, c01, c02, c11, c12, c22, det = adjugate3(a00, a01, a02, a11, a12, a22)
            tr = (a00 + a11 + a22) / 3.0
            if cnt < MIN_FIT or not det > DEGENERATE_RATIO * tr * tr * tr:
                continue
            d0, d1, d2 = adjugate_times(c00, c01, c02, c11, c12, c22, jr0, jr1, jr2)
            d0, d1, d2 = d0 / det, d1 / det, d2 / det
            e0, e1, e2 = adjugate_times(c00, c01, c02, c11, c12, c22, jg0, jg1, jg2)
            e0, e1, e2 = e0 / det, e1 / det, e2 / det
            if not (
                np.isfinite(d0 + d1 + d2)
                and np.isfinite(e0 + e1 + e2)
                and abs(e0) + abs(e1) + abs(e2) < 1e6
            ):
                continue  # overflow in float32: leave the pixel as it is
            db0[0, i, j], db0[1, i, j], db0[2, i, j] = d0, d1, d2
            coef[0, i, j], coef[1, i, j], coef[2, i, j] = e0, e1, e2
            if cnt > MIN_FIT:
                num[i, j] = gr - (e0 * jr0 + e1 * jr1 + e2 * jr2)
                den[i, j] = max(gg - (e0 * jg0 + e1 * jg1 + e2 * jg2), 0.0)
