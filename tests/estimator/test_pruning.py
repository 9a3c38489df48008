"""Hypothesis management: the pruning rules and object-by-object branching (issue 10)."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.special import logsumexp

from estimator.hybrid import BeliefConfig, BeliefModel, HybridBelief, _Beam, _Evidence
from estimator.models import GaussianNoise
from estimator.models.classifier import AliasedClassifier
from estimator.pruning import (
    PruningRule,
    _heaviest_first,
    _least_own_marginal,
    _support,
    class_marginals,
    match_marginals,
    select,
)
from estimator.weights import SampledEvidence

MARGINAL = PruningRule("marginal", 150.0, 1e-4, 300)
RATIO = PruningRule("ratio", 150.0, 1e-4, 300)


def _weights(lw: np.ndarray) -> np.ndarray:
    w = np.exp(lw - lw.max())
    return w / w.sum()


@pytest.mark.parametrize("seed", range(6))
def test_support_is_the_heaviest_carrier_first_of_equal_weights(seed: int) -> None:
    """The protected rows are, for each (object, class) with marginal ≥ floor, the heaviest row
    carrying it, the first of equal weights (ties are common: copies of one weight); a class no
    row carries protects nothing, even with floor 0."""
    rng = np.random.default_rng(seed)
    k, n, m = (60, 5, 4) if seed < 3 else (700, 5, 4)  # 700: rows are visited in several blocks
    w = rng.choice([0.0, 1e-9, 0.05, 0.05, 0.2, 1.0], k)  # repeated weights, some zero
    w /= w.sum()
    classes = rng.integers(0, m - 2, (k, n))  # class m − 1 is carried by no row
    light = np.argsort(w, kind="stable")[: k // 20]
    classes[light, 0] = m - 2  # class m − 2 of object 0: only among the lightest rows
    if k > 64:  # class m − 2 of object 1: the 65th heaviest row (first of the second block)
        ranked = np.argsort(-w, kind="stable")
        classes[ranked[[64, -1]], 1] = m - 2
    floor = [0.0, 1e-4, 0.02][seed % 3]
    marg = class_marginals(w, classes, m)
    expected = np.zeros(k, dtype=bool)
    for j in range(n):
        for i in range(m):
            carriers = [r for r in range(k) if classes[r, j] == i]
            if marg[j, i] >= floor and marg[j, i] > 0:
                best = max(w[r] for r in carriers)
                expected[min(r for r in carriers if w[r] == best)] = True
    assert np.array_equal(_support(w, classes, marg, floor), expected)


@pytest.mark.parametrize("seed", range(4))
def test_heaviest_first_is_the_prefix_of_the_stable_sort(seed: int) -> None:
    """Ties (copies of one weight, zeros) straddle the cut: they are ranked by index."""
    rng = np.random.default_rng(seed)
    k = [1, 63, 700, 5000][seed]
    w = rng.choice([0.0, 1e-9, 0.05, 0.05, 0.2, 1.0], k) * rng.choice([1.0, 1.0, 1.0 + 1e-12], k)
    ranked = np.argsort(-w, kind="stable")
    for count in {1, 2, 63, 64, 65, 192, k - 1, k, k + 5} - {0, -1}:
        assert np.array_equal(_heaviest_first(w, count), ranked[:count]), count


@pytest.mark.parametrize("seed", range(4))
def test_least_own_marginal_is_the_row_minimum_of_the_marginals_of_its_classes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k, n, m = [(1, 1, 2), (50, 7, 3), (900, 40, 4), (300, 2, 5)][seed]
    classes = rng.integers(0, m, (k, n)).astype([np.int64, np.int8][seed % 2])
    w = _weights(rng.normal(0.0, 5.0, k))
    marg = class_marginals(w, classes, m)
    expected = [min(marg[j, classes[r, j]] for j in range(n)) for r in range(k)]
    assert np.array_equal(_least_own_marginal(marg, classes), expected)


@pytest.mark.parametrize("seed", range(5))
def test_select_marginal_keeps_a_carrier_of_every_class_above_the_floor(seed: int) -> None:
    rng = np.random.default_rng(seed)
    lw = rng.normal(0.0, 6.0, 400)
    classes = rng.integers(0, 3, (400, 6))
    kept = select(lw, classes, 3, MARGINAL)
    marg = class_marginals(_weights(lw), classes, 3)
    for j in range(6):
        for i in range(3):
            if marg[j, i] >= 1e-4:
                assert np.any(classes[kept, j] == i), (j, i, marg[j, i])


def test_select_ratio_loses_a_class_the_marginal_rule_keeps_with_its_marginal() -> None:
    # Object 0's class 1 is carried only by realisations that also hold an unlikely class of
    # object 1: each is below w_max/150, together they make P(c_0 = 1) ≈ 0.17.
    lw = np.log(np.array([1.0] + [0.005] * 40))
    classes = np.zeros((41, 2), dtype=np.int64)
    classes[1:, 0] = 1
    classes[1:, 1] = np.arange(40) % 2
    marg = class_marginals(_weights(lw), classes, 2)
    assert marg[0, 1] > 0.15
    assert not np.any(classes[select(lw, classes, 2, RATIO), 0] == 1)
    kept = select(lw, classes, 2, MARGINAL)
    assert np.any(classes[kept, 0] == 1)
    matched = match_marginals(lw[kept], classes[kept], marg)
    np.testing.assert_allclose(class_marginals(np.exp(matched), classes[kept], 2), marg, atol=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_match_marginals_is_the_least_change_that_restores_every_marginal(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m, n = 3, 4
    classes = np.array(list(itertools.product(range(m), repeat=n)), dtype=np.int64)
    lw = rng.normal(0.0, 2.0, len(classes))
    target = class_marginals(_weights(lw), classes, m)
    kept = rng.choice(len(classes), 30, replace=False)
    kept = np.union1d(kept, [int(np.argmax(lw))])
    got = np.exp(match_marginals(lw[kept], classes[kept], target))
    assert abs(got.sum() - 1.0) < 1e-12
    np.testing.assert_allclose(class_marginals(got, classes[kept], m), target, atol=1e-6)
    # the I-projection multiplies the weights by a product of per-(object, class) factors:
    # log(got / w) is additive over the objects' classes
    ratio = np.log(got) - np.log(_weights(lw[kept]))
    design = np.concatenate([classes[kept] == i for i in range(m)], axis=1).astype(float)
    fit, *_ = np.linalg.lstsq(np.c_[design, np.ones(len(kept))], ratio, rcond=None)
    np.testing.assert_allclose(np.c_[design, np.ones(len(kept))] @ fit, ratio, atol=1e-6)
    # already matching marginals: nothing changes
    again = np.exp(match_marginals(np.log(got), classes[kept], target))
    np.testing.assert_allclose(again, got, atol=1e-6)


def test_match_marginals_leaves_unsupported_classes_at_zero() -> None:
    classes = np.array([[0, 0], [0, 1], [1, 0]])
    target = np.array([[0.5, 0.5], [0.6, 0.4]])
    got = np.exp(match_marginals(np.log([0.5, 0.3, 0.2]), classes, target))
    np.testing.assert_allclose(class_marginals(got, classes, 2), target, atol=1e-6)
    np.testing.assert_allclose(got, [0.1, 0.4, 0.5], atol=1e-6)
    only_zero = np.exp(match_marginals(np.log([0.6, 0.4]), classes[:2], target))
    np.testing.assert_allclose(
        class_marginals(only_zero, classes[:2], 2), [[1, 0], [0.6, 0.4]], atol=1e-6
    )


def test_select_drops_non_finite_and_keeps_the_heaviest() -> None:
    lw = np.array([-np.inf, 0.0, np.nan, -1.0])
    classes = np.array([[0], [1], [0], [0]])
    kept = select(lw, classes, 2, MARGINAL)
    assert list(kept) == [1, 3]
    assert len(select(np.full(3, -np.inf), classes[:3], 2, MARGINAL)) == 0


# -- branching -------------------------------------------------------------------------------


def _belief(prior: tuple[float, ...], config: BeliefConfig) -> HybridBelief:
    m = len(prior)
    classifier = AliasedClassifier(tuple((c + 1) % m for c in range(m)), (0.0,) * m, np.eye(m))
    model = BeliefModel(
        m, prior, classifier, GaussianNoise((0.003, 0.003, 0.001)), GaussianNoise((0.1, 0.1, 0.01))
    )
    return HybridBelief(model, {"r1": (0.0, 0.0, 0.0)}, config)


def _synthetic_step(
    belief: HybridBelief, rng: np.random.Generator, parents: int, old: int, new: list[int]
) -> tuple[list[SimpleNamespace], list[SampledEvidence], list, list[int]]:
    """Fake parents (classes of ``old`` known objects), detections of the old objects and of the
    new object ids ``new`` (object ids may repeat: several detections of one new object), and
    random per-sample evidence."""
    m = belief.model.num_classes
    belief.object_ids = list(range(100, 100 + old))
    belief._object_index = {j: i for i, j in enumerate(belief.object_ids)}
    hyps = [
        SimpleNamespace(
            classes=tuple(int(c) for c in rng.integers(0, m, old)),
            log_weight=float(rng.normal(0, 1)),
        )
        for _ in range(parents)
    ]
    ids = [*belief.object_ids, *new]
    detections = [(None, SimpleNamespace(object_id=j)) for j in ids]
    samples = 64
    evidence = [
        SampledEvidence(rng.normal(0, 0.3, samples), rng.normal(-1.0, 1.5, (samples, len(ids), m)))
        for _ in hyps
    ]
    return hyps, evidence, detections, list(dict.fromkeys(new))


def _branch(
    belief: HybridBelief,
    hyps: list[SimpleNamespace],
    evidence: list[SampledEvidence],
    detections: list,
    new_ids: list[int],
) -> _Beam:
    base = np.stack([ev.base for ev in evidence])
    log_lik = np.stack([ev.log_lik for ev in evidence])
    own = np.arange(len(hyps))  # every parent its own continuous belief
    classes = belief._classes_of(hyps)  # type: ignore[arg-type]
    reduced = _Evidence(*belief._reduce(classes, own, base, log_lik, detections, new_ids), own)
    return belief._branch(hyps, reduced, new_ids)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("prior", "new", "seed"),
    [
        ((0.8, 0.2), [1, 2, 3], 0),
        ((0.6, 0.3, 0.1), [1, 2, 2, 3], 1),  # object 2 seen twice in the step
        ((0.6, 0.3, 0.1), [5, 4], 2),
    ],
)
def test_branch_without_pruning_equals_enumeration(
    prior: tuple[float, ...], new: list[int], seed: int
) -> None:
    belief = _belief(prior, BeliefConfig.exact())
    rng = np.random.default_rng(seed)
    hyps, evidence, detections, new_ids = _synthetic_step(belief, rng, 3, 2, new)
    beam = _branch(belief, hyps, evidence, detections, new_ids)
    m = len(prior)
    log_prior = np.log(prior)
    expected = {}
    for p, (h, ev) in enumerate(zip(hyps, evidence, strict=True)):
        for combo in itertools.product(range(m), repeat=len(new_ids)):
            cls = dict(zip(new_ids, combo, strict=True))
            det_classes = [
                h.classes[belief._object_index[d.object_id]]
                if d.object_id in belief._object_index
                else cls[d.object_id]
                for _, d in detections
            ]
            lw = h.log_weight + sum(log_prior[c] for c in combo)
            lw += float(ev.log_means(np.array([det_classes]))[0])
            expected[(p, combo)] = lw
    got = {
        (int(p), tuple(int(c) for c in cls)): float(lw)
        for p, cls, lw in zip(beam.parent, beam.classes, beam.log_weight, strict=True)
    }
    assert got.keys() == expected.keys()
    for key, lw in expected.items():
        assert math.isclose(got[key], lw, rel_tol=0, abs_tol=1e-9), key


def test_branch_partial_weight_is_the_sum_of_its_completions() -> None:
    belief = _belief((0.6, 0.3, 0.1), BeliefConfig.exact())
    rng = np.random.default_rng(7)
    hyps, evidence, detections, new_ids = _synthetic_step(belief, rng, 2, 1, [1, 2])
    full = _branch(belief, hyps, evidence, detections, new_ids)
    # Σ over object 2's classes of the children's weights = the weight with object 2 summed out
    # under its prior, evaluated directly on the same samples.
    for p, ev in enumerate(evidence):
        for c1 in range(3):
            rows = (full.parent == p) & (full.classes[:, 0] == c1)
            total = logsumexp(full.log_weight[rows])
            old = hyps[p].classes[0]
            log_lik = ev.log_lik
            per_sample = (
                ev.base
                + log_lik[:, 0, old]
                + log_lik[:, 1, c1]
                + logsumexp(np.log([0.6, 0.3, 0.1]) + log_lik[:, 2, :], axis=1)
            )
            direct = hyps[p].log_weight + np.log([0.6, 0.3, 0.1][c1])
            direct += logsumexp(per_sample) - np.log(len(per_sample))
            assert math.isclose(total, direct, abs_tol=1e-9)


def test_branch_cost_grows_linearly_with_new_objects() -> None:
    belief = _belief((0.1,) * 10, BeliefConfig())
    rng = np.random.default_rng(0)
    hyps, evidence, detections, new_ids = _synthetic_step(belief, rng, 1, 0, list(range(1, 21)))
    beam = _branch(belief, hyps, evidence, detections, new_ids)
    cap = belief.cap
    assert len(beam.parent) <= cap
    # each of the 20 objects extends at most `cap` partial children by 10 classes
    assert beam.weighed <= 1 + 20 * cap * 10
    assert beam.classes.shape[1] == 20


@pytest.mark.parametrize("seed", range(6))
def test_branch_with_the_ratio_rule_keeps_what_enumeration_then_pruning_keeps(seed: int) -> None:
    # Pruning between objects compares partial children with a full child, so it never drops a
    # completion the final ratio rule keeps: the result is that of enumerating every child first.
    rng = np.random.default_rng(seed)
    prior = (0.5, 0.3, 0.2)
    exact = _belief(prior, BeliefConfig.exact())
    hyps, evidence, detections, new_ids = _synthetic_step(exact, rng, 2, 1, [1, 2, 3, 4, 5])
    full = _branch(exact, hyps, evidence, detections, new_ids)
    best = full.log_weight.max()
    expected = {
        (int(p), tuple(int(c) for c in cls))
        for p, cls, lw in zip(full.parent, full.classes, full.log_weight, strict=True)
        if lw >= best - np.log(150.0)
    }
    paper = _belief(prior, BeliefConfig.paper(max_hypotheses=10_000))
    paper.object_ids, paper._object_index = exact.object_ids, exact._object_index
    beam = _branch(paper, hyps, evidence, detections, new_ids)
    got = {
        (int(p), tuple(int(c) for c in cls))
        for p, cls in zip(beam.parent, beam.classes, strict=True)
    }
    assert got == expected
    assert beam.weighed <= full.weighed


@pytest.mark.parametrize("seed", range(4))
def test_class_marginals_sum_the_weights_of_every_objects_classes(seed: int) -> None:
    """Against the per-class definition P(c_j = i) = Σ_k w_k [c_kj = i], on non-uniform weights;
    an object with a class no realisation carries has a zero there."""
    rng = np.random.default_rng(seed)
    classes = rng.integers(0, 3, (40, 7))
    classes[:, 2] = np.where(classes[:, 2] == 1, 0, classes[:, 2])  # object 2 never class 1
    w = rng.dirichlet(np.full(40, 0.5))
    want = np.array([[w[classes[:, j] == i].sum() for i in range(4)] for j in range(7)])
    got = class_marginals(w, classes, 4)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    assert got[2, 1] == 0.0 and (got[:, 3] == 0.0).all()
    assert class_marginals(w[:0], classes[:0], 4).shape == (7, 4)


def test_select_never_keeps_a_non_finite_weight_even_as_the_only_carrier_of_a_class() -> None:
    """A -inf or NaN log-weight never survives: not by the marginal rule (a class no finite row
    carries has marginal 0, and weight 0 is not below 0 / marginal_ratio), nor as a carrier."""
    classes = np.array([[0], [1], [1]])
    for bad in (-np.inf, np.nan):
        kept = select(np.array([0.0, bad, bad]), classes, 2, MARGINAL)
        assert kept.tolist() == [0], bad


def test_the_cap_keeps_the_protected_carrier_of_a_class_before_heavier_rows() -> None:
    """Over max_hypotheses, the heaviest row goes first, then the protected carriers of classes
    at or above class_floor, then by weight: a light sole carrier of a class survives the cap."""
    rule = PruningRule("marginal", 1e4, 1e-4, 2)
    kept = select(np.array([0.0, -0.1, -5.0]), np.array([[0], [0], [1]]), 2, rule)
    assert kept.tolist() == [0, 2]
