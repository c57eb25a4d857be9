"""pipeline.solvers.order.percentile: numpy's percentile to the bit, faster on large samples."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.solvers.order import percentile

QS = (
    95,
    95.0,
    0.5,
    99.5,
    0,
    100,
    50,
    [0.5, 99.5],
    [5.0, 95.0],
    (25, 50, 75),
    np.array([1.0, 99.0]),
)


def _same(expected, got) -> bool:
    e, g = np.asarray(expected), np.asarray(got)
    return type(expected) is type(got) and e.dtype == g.dtype and np.array_equal(e, g)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_percentile_is_numpys_to_the_bit(dtype):
    rng = np.random.default_rng(7)
    for trial in range(400):
        n = int(rng.integers(1, 3000))
        a = (rng.normal(size=n) * rng.uniform(0.01, 100.0)).astype(dtype)
        if trial % 5 == 0:
            a = np.round(a, 1)  # ties
        for q in QS:
            assert _same(np.percentile(a, q), percentile(a, q)), (n, q)


def test_nan_integers_empty_and_bad_q_are_numpys():
    a = np.array([3.0, np.nan, 1.0, 2.0], np.float32)
    assert np.isnan(percentile(a, 50)) and np.isnan(np.percentile(a, 50))
    ints = np.arange(10)
    assert _same(np.percentile(ints, [10, 90]), percentile(ints, [10, 90]))
    with pytest.raises(ValueError):
        percentile(np.arange(5.0), 101)
    with pytest.raises(IndexError):
        percentile(np.array([], np.float64), 50)


def test_the_input_is_left_as_it_was():
    a = np.random.default_rng(1).normal(size=(40, 50))
    before = a.copy()
    percentile(a, [5, 95])
    assert np.array_equal(a, before)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_large_samples_tails_are_numpys_to_the_bit(dtype):
    """Samples large enough for the tail's threshold (pipeline.solvers.order._in_tail): random, with
    ties, sorted both ways and constant (a threshold that misses falls back to the whole partition)."""
    rng = np.random.default_rng(11)
    n = 120_001
    normal = rng.normal(size=n).astype(dtype)
    samples = [
        normal,
        np.round(normal, 1),
        np.sort(normal),
        np.sort(normal)[::-1].copy(),
        np.full(n, 2.5, dtype),
        rng.exponential(size=(300, 401)).astype(dtype),
    ]
    for a in samples:
        for q in (95, 99.5, 0.5, 5.0, [0.5, 99.5], 99.999, 0.001, 50, 100, 0):
            assert _same(np.percentile(a, q), percentile(a, q)), q
