"""The join of D's hypotheses with a slot's realisations finds its matches by sorted keys
(``estimator.distributed._fits``): the same (row, realisation) pairs in the same order as the
table of every comparison (``_fits_by_table``), which it replaced."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.distributed import _fits, _fits_by_table


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_by_key_equal_the_table_of_comparisons(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(400):
        rows, reals, shared = rng.integers(0, 60), rng.integers(0, 40), rng.integers(0, 7)
        classes = int(rng.integers(1, 6))
        parent = rng.integers(0, classes, size=(rows, shared))
        real = rng.integers(0, classes, size=(reals, shared))
        got, want = _fits(parent.astype(np.int8), real), _fits_by_table(parent, real)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype == np.int64
            np.testing.assert_array_equal(g, w)


def test_edge_cases_of_the_keyed_join() -> None:
    parent = np.array([[0, 1], [1, 1], [0, 1]])
    real = np.array([[0, 1], [1, 0], [0, 1]])
    rows, cols = _fits(parent, real)
    assert rows.tolist() == [0, 0, 2, 2] and cols.tolist() == [0, 2, 0, 2]
    # Nothing shared: every pair, row by row.
    rows, cols = _fits(np.zeros((2, 0), dtype=int), np.zeros((3, 0), dtype=int))
    assert rows.tolist() == [0, 0, 0, 1, 1, 1] and cols.tolist() == [0, 1, 2, 0, 1, 2]
    # No rows, no realisations.
    for p, r in ((np.zeros((0, 2), int), real), (parent, np.zeros((0, 2), int))):
        assert [x.tolist() for x in _fits(p, r)] == [[], []]
    # Keys that would not fit 62 bits (many shared objects of many classes): the table.
    wide = np.random.default_rng(5).integers(0, 300, size=(30, 9))
    real = np.concatenate([wide[::3], wide[:2] + 1])
    for g, w in zip(_fits(wide, real), _fits_by_table(wide, real), strict=True):
        np.testing.assert_array_equal(g, w)
    # There keys would wrap: 12 objects of 64 classes take 72 bits, and the last object's digit
    # 64**11 = 2**66 is 0 modulo 2**64, so tuples that differ only there would match.
    parent = np.zeros((2, 12), dtype=np.int64)
    parent[0, 11], parent[1] = 1, 63
    assert [x.tolist() for x in _fits(parent, np.zeros((1, 12), dtype=np.int64))] == [[], []]
