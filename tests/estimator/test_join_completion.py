"""The join completes a truncated slot for D's rows that no realisation matches (issue 10).

A slot carries its owner's heaviest class realisations; a row of D whose combination of the
shared objects the slot does not carry is joined with the slot's nearest realisations, log φ
moved by the slot's own per-object class evidence (``estimator.distributed._nearest``). On a
slot whose φ is a product over objects the completed log φ is that product's value, up to the
mass the truncation left out.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from estimator.distributed import _nearest


def _product_slot(
    seed: int, num_objects: int, num_classes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every class realisation of ``num_objects`` objects with a product log φ of non-uniform
    per-object factors: realisations (R, n), log φ (R,), factors (n, M)."""
    rng = np.random.default_rng(seed)
    factors = rng.normal(0.0, 1.5, (num_objects, num_classes))
    real = np.array(list(itertools.product(range(num_classes), repeat=num_objects)))
    log_phi = factors[np.arange(num_objects)[None, :], real].sum(axis=1)
    return real, log_phi, factors


@pytest.mark.parametrize(("seed", "num_classes"), [(0, 2), (1, 3), (2, 3), (3, 2)])
def test_a_row_the_slot_does_not_carry_gets_the_product_log_phi(
    seed: int, num_classes: int
) -> None:
    real, log_phi, _ = _product_slot(seed, 4, num_classes)
    # Leave out the lightest realisation: D holds exactly that combination.
    missing = int(np.argmin(log_phi))
    kept = np.delete(np.arange(len(real)), missing)
    parent = real[missing][None, :]
    rows, cols, phi = _nearest(
        parent, real[kept], np.zeros((len(kept), 0), dtype=np.int64), log_phi[kept], np.array([0])
    )
    assert list(rows) == [0] and len(cols) == 1  # one child: no object is new to D
    # The only error: the sum of φ over the carriers of its class of object j lacks its own φ,
    # which takes −log(1 − φ*/Σ_{c_j = c*_j} φ) off the estimate through object j.
    carriers = [np.logaddexp.reduce(log_phi[real[:, j] == real[missing, j]]) for j in range(4)]
    bound = max(-np.log1p(-np.exp(log_phi[missing] - c)) for c in carriers)
    assert 0 < phi[0] - log_phi[missing] + bound <= bound + 1e-12, (phi[0], log_phi[missing])
    # Its nearest realisations differ from it in one object.
    assert int(np.sum(real[kept][cols[0]] != real[missing])) == 1


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_nearest_realisations_with_different_new_classes_make_different_children(seed: int) -> None:
    # Objects 0..2 are shared with D, object 3 is new to it; the slot lacks the lightest
    # combination of the shared objects (with either class of object 3), D holds it.
    real, log_phi, factors = _product_slot(seed, 4, 2)
    shared, fresh = real[:, :3], real[:, 3:]
    combos = np.unique(shared, axis=0)
    weight = [np.logaddexp.reduce(log_phi[np.all(shared == c, axis=1)]) for c in combos]
    target = combos[int(np.argmin(weight))]
    carried = ~np.all(shared == target, axis=1)
    rows, cols, phi = _nearest(
        target[None, :], shared[carried], fresh[carried], log_phi[carried], np.array([0])
    )
    assert list(rows) == [0, 0]
    assert sorted(int(fresh[carried][c, 0]) for c in cols) == [0, 1]
    left_out = float(np.logaddexp.reduce(log_phi[~carried]))
    carriers = [np.logaddexp.reduce(log_phi[shared[:, j] == target[j]]) for j in range(3)]
    bound = max(-np.log1p(-np.exp(left_out - c)) for c in carriers)
    for c, p in zip(cols, phi, strict=True):
        exact = factors[[0, 1, 2], target].sum() + factors[3, int(fresh[carried][c, 0])]
        # Each child is the mean of its nearest realisations' estimates, each short by what the
        # carriers of one of its classes lack (the left-out realisations).
        assert -bound - 1e-12 <= p - exact <= 1e-12, (p, exact, bound)


def test_a_class_the_slot_does_not_carry_is_not_completed() -> None:
    real, log_phi, _ = _product_slot(4, 3, 2)
    no_class_1 = real[:, 0] == 0  # the slot rules class 1 of object 0 out
    parent = np.array([[1, 0, 0]])
    rows, cols, phi = _nearest(
        parent,
        real[no_class_1],
        np.zeros((int(no_class_1.sum()), 0), dtype=np.int64),
        log_phi[no_class_1],
        np.array([0]),
    )
    assert len(rows) == len(cols) == len(phi) == 0
