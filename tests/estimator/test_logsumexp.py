"""estimator.logsumexp gives scipy.special.logsumexp's results to the bit, on the shapes and axes
the estimator uses and on the edge cases (ties, −inf, +inf, NaN, empty, all −inf)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import logsumexp as scipy_logsumexp

from estimator.logsumexp import logsumexp


def _same(a: object, b: object) -> bool:
    x, y = np.asarray(a), np.asarray(b)
    return x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()


@pytest.mark.parametrize("seed", range(6))
def test_equal_to_scipy_to_the_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for shape, axis in (
        ((40,), None),
        ((7, 30), 1),
        ((30, 7), 0),
        ((5, 6, 9), 2),
        ((4, 3, 5), None),
        ((300, 500), 1),  # a belief's parents × samples (numpy sums these in blocks)
        ((60, 3, 500), 2),
    ):
        a = rng.standard_normal(shape) * 10.0 ** rng.integers(-3, 4)
        a[rng.random(shape) < 0.1] = -np.inf
        flat = a.reshape(-1)
        flat[rng.integers(0, flat.size, 3)] = flat.max()  # ties at the maximum
        got, want = logsumexp(a, axis=axis), scipy_logsumexp(a, axis=axis)
        assert _same(got, want), (shape, axis)


@pytest.mark.parametrize(
    "a",
    [
        [-np.inf, -np.inf],
        [np.inf, 1.0],
        [np.inf, -np.inf],
        [np.nan, 1.0],
        [1e308, 1e308],
        [-1e308, 0.0],
        [0.0],
        [],
        [[1.0, -np.inf], [-np.inf, -np.inf]],
    ],
)
def test_edge_cases_equal_to_scipy(a: list[float]) -> None:
    for axis in (None, -1):
        assert _same(logsumexp(np.array(a), axis=axis), scipy_logsumexp(np.array(a), axis=axis))
