"""Percentiles of large 1-D samples, to the bit ``np.percentile``'s, by one partition per order statistic.

``np.percentile`` (linear interpolation) partitions its input at several indices at once: the two
order statistics around each percentile and also the first and the last element, which it needs to
find NaN. On the pipeline's samples (0.2-0.7 million values: a stereo window's grey levels, the
deviation and uncertainty maps over a plate) that partition is several times slower than a single
partition at the lower order statistic followed by the minimum of what lies above it. The values,
the interpolation and the result's type are numpy's own (``tests/pipeline/test_order.py`` compares
them bit for bit); an input with NaN goes to ``np.percentile`` itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt


def percentile(a: npt.ArrayLike, q: float | Sequence[float]) -> Any:
    """``np.percentile(a, q)`` of the values of ``a`` (flattened), the default linear method.

    Parameters
    ----------
    a : array_like of float
        The sample (any shape; its values are taken flattened). Not modified.
    q : float or sequence of float
        Percentiles in [0, 100].

    Returns
    -------
    numpy scalar or array
        Exactly what ``np.percentile(a, q)`` returns: its value, dtype and type.
    """
    arr = np.asarray(a).ravel()
    n = arr.size
    if n == 0 or not np.issubdtype(arr.dtype, np.floating) or np.isnan(arr.max()):
        return np.percentile(arr, q)  # numpy's errors and its NaN handling
    weak_q = type(q) in (int, float)  # numpy's weak promotion of a Python scalar
    fraction = np.asanyarray(np.true_divide(q, 100))
    if np.any(fraction < 0) or np.any(fraction > 1):
        return np.percentile(arr, q)  # numpy's error
    virtual = np.asanyarray((n - 1) * fraction)
    below = np.floor(virtual)
    below = np.where(virtual >= n - 1, n - 1, below).astype(np.intp)
    above = np.minimum(below + 1, n - 1)
    values = _order_statistics(arr, np.unique(below))
    previous = np.asarray([values[int(k)] for k in below.ravel()], arr.dtype).reshape(below.shape)
    following = np.asarray([values[int(k)] for k in above.ravel()], arr.dtype).reshape(above.shape)
    # numpy's gamma: the virtual index less the lower one (-1 past the end, where both values agree)
    lower = np.where(virtual >= n - 1, -1, below)
    gamma: Any = np.asanyarray(virtual - lower, dtype=virtual.dtype)
    if weak_q:
        gamma = float(gamma)
    return _lerp(previous, following, gamma)


def _order_statistics(arr: np.ndarray, ks: np.ndarray) -> dict[int, Any]:
    """The ``k``-th and ``k + 1``-th smallest values of ``arr`` for each ``k`` of ``ks`` (one partition
    each: the ``k + 1``-th is the smallest of what lies above the ``k``-th; of the tail beyond a
    threshold only when ``k`` lies in a short tail, see :func:`_in_tail`)."""
    n = arr.size
    values: dict[int, Any] = {}
    for k in ks:
        k = int(k)
        pair = _in_tail(arr, k)
        if pair is not None:
            values.update(pair)
            continue
        part = np.partition(arr, k)
        values[k] = part[k]
        if k + 1 < n:
            values[k + 1] = part[k + 1 :].min()
    return values


#: A sample of at least this many values whose order statistic lies in a tail of at most
#: 1 / TAIL_SHARE of it is partitioned only beyond a threshold (:func:`_in_tail`).
TAIL_MIN_SIZE = 50_000
TAIL_SHARE = 8
#: Every this many-th value is the subsample the threshold is taken from.
TAIL_STRIDE = 16


def _in_tail(arr: np.ndarray, k: int) -> dict[int, Any] | None:
    """The ``k``-th and ``k + 1``-th smallest values of ``arr`` when ``k`` lies in one of its short tails,
    found among the values beyond a threshold only; None when it does not (or the threshold missed).

    The threshold is an order statistic of every :data:`TAIL_STRIDE`-th value, set a few standard
    deviations of its rank deeper than the tail: the values beyond it (one comparison over the
    sample) hold the two sought, which is checked by counting them before they are taken, so that the
    values are the very ones of a partition of the whole sample (a threshold that missed, on a sample
    ordered against the stride, falls back to that partition)."""
    n = arr.size
    upper = 2 * k >= n
    # the values from the k-th up, or from the smallest to the (k+1)-th
    tail = n - k if upper else k + 2
    if n < TAIL_MIN_SIZE or TAIL_SHARE * tail > n:
        return None
    sample = arr[::TAIL_STRIDE]
    m = sample.size
    expected = tail * m / n
    want = min(m - 1, int(expected + 4.0 * np.sqrt(expected)) + 8)
    if upper:
        t = np.partition(sample, m - 1 - want)[m - 1 - want]
        beyond = arr[arr >= t]
        j = k - (n - beyond.size)  # the values under t come first
        if j < 0:
            return None
    else:
        t = np.partition(sample, want)[want]
        beyond = arr[arr <= t]
        j = k
        if beyond.size < k + 2:
            return None
    part = np.partition(beyond, j)
    pair = {k: part[j]}
    if k + 1 < n:
        pair[k + 1] = part[j + 1 :].min()
    return pair


def _lerp(a: np.ndarray, b: np.ndarray, t: Any) -> Any:
    """numpy's interpolation between the order statistics (``numpy.lib._function_base_impl._lerp``): from
    the nearer end, so that ``t`` 0 and 1 give ``a`` and ``b`` exactly."""
    diff = b - a
    result = np.add(a, diff * t, out=...)
    np.subtract(
        b,
        diff * (1 - t),
        out=result,
        where=np.asarray(t) >= 0.5,
        casting="unsafe",
        dtype=type(result.dtype),
    )
    return result[()] if result.ndim == 0 else result
