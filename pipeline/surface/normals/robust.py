"""The robust per-pixel estimator: Lambertian least squares on the samples left after rejecting
shadows, highlights and outliers (``method="robust"``, the default).

Per pixel (compiled, a block of a row at a time, vectorised over its pixels): a first fit without
the samples darker than SHADOW_FRACTION of the pixel's 90th-percentile sample (shadows) and without
its brightest TRIM_TOP_FRACTION (highlights) -- or, if that leaves an ill-posed system, without the
shadows only, or with all samples; then ROBUST_ITERATIONS times: keep the valid samples with
n.l > COS_MIN and a residual within -OUTLIER_K .. +OUTLIER_K_HIGH robust scales (MAD), and refit.
A pixel's estimate uses at least 3 samples. Its accuracy on real data (DiLiGenT, against least
squares) is in docs/figures.md (*Real data*; ``benchmarks/bench_normals_realdata.py``). On clean
Lambertian data the trimming costs ~10 % in noise, and where the errors are systematic rather than
outliers (the UW grey sphere: nearly Lambertian, 12 clustered lights of limited accuracy) it is
slightly worse than least squares.

The same kernel serves point lights (:func:`pipeline.lights.nearfield.estimate_normals_near`): the light
vectors of a block are then computed per pixel from the current surface
(:func:`pipeline.lights.model.light_vectors_block`).

Kept as one module (~510 lines, a tenth of them the typed signatures of its kernels, one argument per
line): the kernels call each other and numba compiles them together.
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from pipeline.lights.model import light_vectors_block
from pipeline.surface.normals.field import DEGENERATE, FEW, NONFINITE, OK, OUTSIDE
from pipeline.surface.normals.noise import image_noise
from pipeline.surface.normals.solve3 import DEGENERATE_RATIO, MIN_FIT

#: An array argument of the kernels (their dtypes are set by the callers).
Arr = npt.NDArray[Any]

# Constants chosen on DiLiGenT cat/pot1/ball (8-bit crops, 96 lights) and on synthetic spheres
# and plates with 12-24 lights, shadows and specular lobes (tests/pipeline/test_normals.py).
#: Attached/cast shadow pre-screen: a sample darker than this fraction of the pixel's
#: reference intensity (its 90th-percentile sample) is left out of the first fit.
SHADOW_FRACTION = 0.2
SHADOW_REF_QUANTILE = 0.9
#: The brightest ``floor(TRIM_TOP_FRACTION * m)`` of a pixel's m samples are left out of
#: the first fit (specular highlights; 3 of 12 lights). The later fits pick their samples
#: afresh from all, so a good sample left out here comes back.
TRIM_TOP_FRACTION = 0.3
#: After a fit, samples with n.l <= COS_MIN are attached shadows (or grazing) and dropped.
COS_MIN = 0.05
#: Samples whose residual r = I - rho n.l lies outside (-OUTLIER_K, OUTLIER_K_HIGH) * scale
#: are dropped (r > 0: highlight; r < 0: cast shadow, interreflection deficit). scale =
#: 1.4826 * median |r| of the kept samples, at least SCALE_FLOOR * rho. A lower
#: OUTLIER_K_HIGH (with TRIM_TOP_FRACTION 0.5) halves the bias left by broad specular lobes
#: but costs ~40 % more noise on matte plates (measured on simulated plates): kept symmetric.
OUTLIER_K = 1.5
OUTLIER_K_HIGH = 1.5
SCALE_FLOOR = 0.01
#: ... and at least this many times the images' own noise (measured on the plate, see
#: :func:`pipeline.surface.normals.noise.image_noise`): a residual within what the sensor's noise explains
#: is no outlier. Without
#: it, trimming at 1.5 robust scales of a few samples' residuals cuts pure noise asymmetrically,
#: and the normals' error is then no longer zero-mean but bends the integrated plate smoothly
#: (measured on simulated plates, 12 lights, 0.4 % noise: deviation p95 0.11 mm against 0.04 mm
#: for least squares once the stereo pair no longer hides it).
NOISE_SCALES = 2.0
#: Re-selections and re-fits after the first fit (a 3rd changes DiLiGenT and the synthetic
#: sphere tests by < 0.05 deg and costs ~30 % more time).
ROBUST_ITERATIONS = 2

#: LLVM fast-math flags for the kernels: reassociation lets the loops over a row's pixels
#: vectorise; no "nnan"/"ninf", so NaN and inf checks keep their meaning.
FASTMATH = {"nsz", "arcp", "contract", "reassoc"}
# float32 constants for the robust kernels (a float64 literal would promote a whole loop to float64)
_F32_ZERO, _F32_ONE, _F32_THIRD = np.float32(0.0), np.float32(1.0), np.float32(1.0 / 3.0)
_F32_INF = np.float32(np.inf)
_F32_MIN_FIT = np.float32(MIN_FIT)
_F32_DEGENERATE = np.float32(DEGENERATE_RATIO)
_F32_MAD = np.float32(1.4826)  # median |r| -> standard deviation for Gaussian noise

#: Samples per work block of the robust kernel (N lights x width pixels). Each block allocates its
#: scratch arrays (about ten), and every thread allocates from the process's one malloc arena
#: (:data:`pipeline.parallel.MALLOC_ARENAS`): with blocks of 256 px (N = 12) the two threads
#: contended for it, and the kernel alone took 72-170 ms at 1224x1024 (12 lights, two threads,
#: after ``configure_process``) against 49-51 ms with 1024 px, the same to the bit (94 against
#: 87 ms on one thread). A block's arrays stay within the L2 cache (N = 12: 48 kB per float32 array).
_BLOCK_SAMPLES = 12288

# The robust kernel works on one block of an image row at a time with every per-pixel quantity
# an array over the block's pixels, so that each step is a branch-free loop over pixels that
# LLVM vectorises (a per-pixel loop with data-dependent branches was ~10x slower).
# Order statistics come from a sorting network (branch-free compare-exchanges).


def robust(
    images: np.ndarray, L: np.ndarray, mask: np.ndarray, valid: np.ndarray | None, min_samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """The robust fit of every mask pixel under distant lights (see the module docstring).

    Parameters
    ----------
    images : (N, H, W) float32
        Intensity-normalised images (checked by :func:`pipeline.surface.normals.estimate_normals`).
    L : (N, 3) float64
        Unit light directions.
    mask : (H, W) bool
    valid : (N, H, W) bool or None
        Usable samples; None: all.
    min_samples : int
        Fewer usable samples than this: status :data:`~pipeline.surface.normals.field.FEW`.

    Returns
    -------
    b : (3, H, W) float32
        rho n.
    status : (H, W) int8
        Status codes of :mod:`pipeline.surface.normals.field`.
    """
    n, h, w = images.shape
    b = np.empty((3, h, w), dtype=np.float32)
    status = np.empty((h, w), dtype=np.int8)
    use_valid = valid is not None
    v = valid if use_valid else np.ones((1, 1, 1), dtype=bool)
    zeros = np.zeros((n, 3))
    robust_kernel(
        np.ascontiguousarray(images),
        np.ascontiguousarray(v),
        use_valid,
        np.ascontiguousarray(mask),
        np.zeros((1, 1)),
        np.eye(3),
        np.ascontiguousarray(L, dtype=np.float64),
        zeros,
        np.zeros(n, np.int64),
        np.zeros(n),
        0.0,
        int(min_samples),
        robust_params(float(np.median(image_noise(images, mask)))),
        sorting_network(n),
        b,
        status,
    )
    return b, status


def robust_params(noise: float = 0.0) -> np.ndarray:
    """The robust estimator's constants as the kernel's parameter vector (9,) float64, in this order:
    SHADOW_FRACTION, SHADOW_REF_QUANTILE, TRIM_TOP_FRACTION, COS_MIN, OUTLIER_K, SCALE_FLOOR,
    ROBUST_ITERATIONS, OUTLIER_K_HIGH, and the absolute floor of the robust scale
    ``NOISE_SCALES * noise`` (``noise``: the images' noise, :func:`pipeline.surface.normals.noise.image_noise`)."""
    return np.array(
        [
            SHADOW_FRACTION,
            SHADOW_REF_QUANTILE,
            TRIM_TOP_FRACTION,
            COS_MIN,
            OUTLIER_K,
            SCALE_FLOOR,
            ROBUST_ITERATIONS,
            OUTLIER_K_HIGH,
            NOISE_SCALES * noise,
        ],
        dtype=np.float64,
    )


@functools.lru_cache(maxsize=16)
def sorting_network(n: int) -> np.ndarray:
    """Compare-exchange pairs (C, 2) int64 of Batcher's odd-even merge sort for n keys."""
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            j = k % p
            while j <= n - 1 - k:
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
                j += 2 * k
            k //= 2
        p *= 2
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@numba.njit(parallel=True, cache=True)
def robust_kernel(
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
    min_attenuation: float,
    min_samples: int,
    params: Arr,
    pairs: Arr,
    b_out: Arr,
    status: Arr,
) -> None:
    """Robust fit of every mask pixel (see the module docstring). Fills b_out (3, H, W) with rho n and
    status (H, W) with a status code per pixel.

    The lights as :meth:`pipeline.lights.model.Lights.kernel_arrays` give them; with point lights, ``depth``
    (H, W) mm and ``kinv`` give each pixel's surface point (:func:`pipeline.lights.model.light_vectors_block`);
    with distant lights only, ``depth`` may be (1, 1) and is not read. ``params``: :func:`robust_params`
    (or other constants in that order); ``pairs``: :func:`sorting_network` of N.
    """
    n, h, w = images.shape
    width = max(16, _BLOCK_SAMPLES // n)
    per_row = (w + width - 1) // width
    near = False
    for k in range(n):
        near = near or kind[k] == 1
    for t in numba.prange(h * per_row):
        i = t // per_row
        j0 = (t % per_row) * width
        j1 = min(j0 + width, w)
        if not mask[i, j0:j1].any():
            status[i, j0:j1] = OUTSIDE
            continue
        samples, usable, m, finite = _load_block(images, valid, use_valid, mask, i, j0, j1)
        L = np.empty((n, 3, j1 - j0), np.float32)
        if near:
            light_vectors_block(
                depth, kinv, geometry, axes, kind, mu, min_attenuation, i, j0, samples, usable, m, L
            )
        else:
            for k in range(n):
                for c in range(3):
                    L[k, c, :] = geometry[k, c]
        _robust_block(
            samples, usable, m, finite, mask, L, min_samples, params, pairs, b_out, status, i, j0
        )


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _load_block(
    images: Arr, valid: Arr, use_valid: bool, mask: Arr, i: int, j0: int, j1: int
) -> tuple[Arr, Arr, Arr, Arr]:
    """The samples of pixels (i, j0:j1): (N, w) float32 values (0 where unusable), (N, w) float32
    usability (1: a valid sample of a mask pixel), (w,) int64 counts and (w,) finiteness."""
    n = images.shape[0]
    w = j1 - j0
    samples = np.empty((n, w), np.float32)
    usable = np.empty((n, w), np.float32)
    m = np.zeros(w, np.int64)
    finite = np.ones(w, np.bool_)
    for k in range(n):
        for j in range(w):
            x = images[k, i, j0 + j]
            u = mask[i, j0 + j] and (not use_valid or valid[k, i, j0 + j])
            usable[k, j] = _F32_ONE if u else _F32_ZERO
            samples[k, j] = x if u else _F32_ZERO
            m[j] += 1 if u else 0
            if u and not np.isfinite(x):
                finite[j] = False
    return samples, usable, m, finite


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _robust_block(
    samples: Arr,
    usable: Arr,
    m: Arr,
    finite: Arr,
    mask: Arr,
    L: Arr,
    min_samples: int,
    params: Arr,
    pairs: Arr,
    b_out: Arr,
    status: Arr,
    i: int,
    j0: int,
) -> None:
    """The robust fit of the pixels (i, j0:j0 + w) of one row from their samples (N, w), usability
    (N, w), counts and finiteness (see _load_block) under light vectors L (N, 3, w)."""
    # params: float64 (9,); the per-sample work is float32 (L too), the per-pixel quantities float32
    shadow_fraction, trim_top, cos_min = np.float32(params[0]), params[2], np.float32(params[3])
    outlier_k, scale_floor, outlier_k_high, noise_floor = (
        np.float32(params[4]),
        np.float32(params[5]),
        np.float32(params[7]),
        np.float32(params[8]),
    )
    ref_quantile = params[1]
    iterations = int(params[6])
    n, w = samples.shape
    ranked = np.empty((n, w), np.float32)  # scratch for order statistics (+inf = not counted)
    keep = np.empty((n, w), np.float32)
    low, top = _trim_levels(
        samples, usable, m, ranked, pairs, shadow_fraction, ref_quantile, trim_top
    )
    b, ok = _first_fit(samples, usable, m, L, low, top, keep)
    _refit(
        samples,
        usable,
        L,
        pairs,
        iterations,
        cos_min,
        outlier_k,
        outlier_k_high,
        scale_floor,
        noise_floor,
        b,
        ok,
        keep,
        ranked,
    )
    for j in range(w):
        if not mask[i, j0 + j]:
            status[i, j0 + j] = OUTSIDE
        elif not finite[j]:
            status[i, j0 + j] = NONFINITE
        elif m[j] < min_samples:
            status[i, j0 + j] = FEW
        elif ok[j] == 0:
            status[i, j0 + j] = DEGENERATE
        else:
            status[i, j0 + j] = OK
        b_out[0, i, j0 + j] = b[0, j]
        b_out[1, i, j0 + j] = b[1, j]
        b_out[2, i, j0 + j] = b[2, j]


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _trim_levels(
    samples: Arr,
    usable: Arr,
    m: Arr,
    ranked: Arr,
    pairs: Arr,
    shadow_fraction: float | np.floating[Any],
    ref_quantile: float,
    trim_top: float,
) -> tuple[Arr, Arr]:
    """Per pixel of a block: the shadow level ``low`` and the highlight cut ``top`` (w,) float32 from
    its order statistics (``ranked`` (N, w) is scratch)."""
    n, w = samples.shape
    for k in range(n):
        for j in range(w):
            ranked[k, j] = samples[k, j] if usable[k, j] > 0 else _F32_INF
    _sort_row(ranked, pairs)  # unusable samples (+inf) sort last
    low = np.empty(w, np.float32)
    top = np.empty(w, np.float32)
    for j in range(w):
        mj = m[j]
        ref = ranked[int(ref_quantile * (mj - 1)), j] if mj > 0 else _F32_ZERO
        low[j] = shadow_fraction * ref
        n_top = int(trim_top * mj)
        top[j] = ranked[mj - n_top, j] if n_top > 0 else _F32_INF
    return low, top


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _first_fit(
    samples: Arr, usable: Arr, m: Arr, L: Arr, low: Arr, top: Arr, keep: Arr
) -> tuple[Arr, Arr]:
    """The first fit of a block: without shadows and highlights; else without shadows; else all samples.

    Returns b (3, w) float32 and ok (w,) float32 (1: fitted); ``keep`` (N, w) receives the weights
    of each pixel's fit.
    """
    n, w = samples.shape
    b = np.zeros((3, w), np.float32)
    ok = np.zeros(w, np.float32)
    cand = np.empty((3, w), np.float32)
    cand_ok = np.empty(w, np.float32)
    for attempt in range(3):
        for k in range(n):
            for j in range(w):
                x = samples[k, j]
                if attempt == 0:
                    inside = x > low[j] and x < top[j]
                elif attempt == 1:
                    inside = x > low[j]
                else:
                    inside = True
                # pixels already fitted keep their weights
                keep[k, j] = keep[k, j] if ok[j] > 0 else (usable[k, j] if inside else _F32_ZERO)
        _fit_row(samples, keep, L, cand, cand_ok)
        remaining = 0
        for j in range(w):
            if ok[j] == 0 and cand_ok[j] > 0:
                ok[j] = _F32_ONE
                b[0, j], b[1, j], b[2, j] = cand[0, j], cand[1, j], cand[2, j]
            remaining += 1 if (ok[j] == 0 and m[j] >= MIN_FIT) else 0
        if remaining == 0:
            break
    return b, ok


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _refit(
    samples: Arr,
    usable: Arr,
    L: Arr,
    pairs: Arr,
    iterations: int,
    cos_min: float | np.floating[Any],
    outlier_k: float | np.floating[Any],
    outlier_k_high: float | np.floating[Any],
    scale_floor: float | np.floating[Any],
    noise_floor: float | np.floating[Any],
    b: Arr,
    ok: Arr,
    keep: Arr,
    ranked: Arr,
) -> None:
    """``iterations`` re-selections and refits of a block, in place on b (3, w) and keep (N, w): each
    keeps the samples lit (n.l > cos_min) and within -outlier_k .. +outlier_k_high robust scales of
    the current fit (``ranked`` (N, w) is scratch)."""
    n, w = samples.shape
    trial = np.empty((n, w), np.float32)
    resid = np.empty((n, w), np.float32)
    cand = np.empty((3, w), np.float32)
    cand_ok = np.empty(w, np.float32)
    rho = np.empty(w, np.float32)
    scale = np.empty(w, np.float32)
    kth = np.empty(w, np.int64)
    accept = np.empty(w, dtype=np.bool_)
    for _ in range(iterations):
        for j in range(w):
            rho[j] = np.sqrt(b[0, j] * b[0, j] + b[1, j] * b[1, j] + b[2, j] * b[2, j])
            kth[j] = 0
        for k in range(n):
            lxk, lyk, lzk = L[k, 0], L[k, 1], L[k, 2]
            for j in range(w):
                d = b[0, j] * lxk[j] + b[1, j] * lyk[j] + b[2, j] * lzk[j]  # rho n.l
                r = samples[k, j] - d
                resid[k, j] = r
                lit = usable[k, j] > 0 and d > cos_min * rho[j]
                trial[k, j] = _F32_ONE if lit else _F32_ZERO
                counted = lit and keep[k, j] > 0
                ranked[k, j] = abs(r) if counted else _F32_INF
                kth[j] += 1 if counted else 0
        _sort_row(ranked, pairs)
        for j in range(w):
            scale[j] = ranked[kth[j] // 2, j]  # the (upper) median of |r|
        for j in range(w):
            scale[j] = max(_F32_MAD * scale[j], scale_floor * rho[j], noise_floor)
        for k in range(n):
            for j in range(w):
                r = resid[k, j]
                inlier = -outlier_k * scale[j] < r < outlier_k_high * scale[j]
                trial[k, j] = trial[k, j] if inlier else _F32_ZERO
        _fit_row(samples, trial, L, cand, cand_ok)
        for j in range(w):
            accept[j] = ok[j] > 0 and cand_ok[j] > 0 and rho[j] > 0 and kth[j] >= MIN_FIT
            if accept[j]:
                b[0, j], b[1, j], b[2, j] = cand[0, j], cand[1, j], cand[2, j]
        for k in range(n):
            keep_k, trial_k = keep[k], trial[k]
            for j in range(w):
                keep_k[j] = trial_k[j] if accept[j] else keep_k[j]


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _fit_row(samples: Arr, weight: Arr, L: Arr, b: Arr, ok: Arr) -> None:
    """Per pixel j of a block: weighted (0/1) least squares b[:, j] over the samples.

    samples, weight : (N, W) float32; L : (N, 3, W) float32, the light vector of each sample
    (the same for every pixel of a distant light, per pixel for a point light); b : (3, W)
    float32 out; ok : (W,) float32 out, 1 where the system has >= 3 samples and is well posed
    (see DEGENERATE_RATIO), else 0. Float32 throughout: twice the SIMD lanes of float64, and
    at most N = a few dozen unit-scale terms per sum.
    """
    n, w = samples.shape
    m00 = np.zeros(w, np.float32)
    m01 = np.zeros(w, np.float32)
    m02 = np.zeros(w, np.float32)
    m11 = np.zeros(w, np.float32)
    m12 = np.zeros(w, np.float32)
    m22 = np.zeros(w, np.float32)
    r0 = np.zeros(w, np.float32)
    r1 = np.zeros(w, np.float32)
    r2 = np.zeros(w, np.float32)
    cnt = np.zeros(w, np.float32)
    for k in range(n):
        lxk, lyk, lzk = L[k, 0], L[k, 1], L[k, 2]
        for j in range(w):
            lx, ly, lz = lxk[j], lyk[j], lzk[j]
            wk = weight[k, j]
            wi = wk * samples[k, j]
            wx, wy = wk * lx, wk * ly
            m00[j] += wx * lx
            m01[j] += wx * ly
            m02[j] += wx * lz
            m11[j] += wy * ly
            m12[j] += wy * lz
            m22[j] += wk * lz * lz
            r0[j] += wi * lx
            r1[j] += wi * ly
            r2[j] += wi * lz
            cnt[j] += wk
    # The adjugate solve of pipeline.surface.normals.solve3, written out: through the helper LLVM compiles
    # this loop over a block's pixels differently (the last bit of some solutions changes, and with
    # it which samples later fits keep), so the vectorised float32 loop stays as it is.
    for j in range(w):
        c00 = m11[j] * m22[j] - m12[j] * m12[j]
        c01 = m02[j] * m12[j] - m01[j] * m22[j]
        c02 = m01[j] * m12[j] - m02[j] * m11[j]
        c11 = m00[j] * m22[j] - m02[j] * m02[j]
        c12 = m01[j] * m02[j] - m00[j] * m12[j]
        c22 = m00[j] * m11[j] - m01[j] * m01[j]
        det = m00[j] * c00 + m01[j] * c01 + m02[j] * c02
        tr = (m00[j] + m11[j] + m22[j]) * _F32_THIRD
        good = cnt[j] >= _F32_MIN_FIT and det > _F32_DEGENERATE * tr * tr * tr
        inv = _F32_ONE / det if good else _F32_ZERO
        b[0, j] = (c00 * r0[j] + c01 * r1[j] + c02 * r2[j]) * inv
        b[1, j] = (c01 * r0[j] + c11 * r1[j] + c12 * r2[j]) * inv
        b[2, j] = (c02 * r0[j] + c12 * r1[j] + c22 * r2[j]) * inv
        ok[j] = _F32_ONE if good else _F32_ZERO


@numba.njit(nogil=True, cache=True, fastmath=FASTMATH)
def _sort_row(values: Arr, pairs: Arr) -> None:
    """Sort every column of values (N, W) in place with the sorting network ``pairs`` (branch-free)."""
    w = values.shape[1]
    for c in range(pairs.shape[0]):
        lo, hi = values[pairs[c, 0]], values[pairs[c, 1]]
        for j in range(w):
            x, y = lo[j], hi[j]
            lo[j] = np.minimum(x, y)
            hi[j] = np.maximum(x, y)
