"""The belief gate (estimator.gate; issue 43, finding 2): the information bound from the sensor
model and the two-stage Mahalanobis test against the receiver's belief, on numbers chosen so that
a dropped term or a flipped sign changes the verdict."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from estimator.gate import (
    EVIDENCE_TERMS,
    GateSettings,
    Held,
    Implausible,
    _local,
    _mean_and_marginals,
    check_classes,
    check_summary,
    check_xi,
    evidence_per_detection,
    gate_threshold,
    per_detection_bound,
)
from estimator.models import ClassifierModel, se2
from estimator.models.classifier import AliasedClassifier
from estimator.sparse_xi import SparseXi
from estimator.summary import LocalSummary, ObjectClasses, Realisation
from estimator.xi import Xi
from tests.estimator.test_learned_model import random_model

LIN = np.array([[1.0, 2.0, 0.3]])
LAMBDA = np.array([[40.0, 6.0, 1.0], [6.0, 90.0, -2.0], [1.0, -2.0, 250.0]])
DELTA0 = np.array([0.5, -0.4, 0.2])  # the slot's mean, away from its linearisation point
COV_D = np.array([[0.05, 0.01, 0.0], [0.01, 0.03, 0.002], [0.0, 0.002, 0.01]])
SETTINGS = GateSettings()


def _xi() -> Xi:
    return Xi(LIN, LAMBDA, LAMBDA @ DELTA0)


def _held_at(offset: np.ndarray, calls: list[int] | None = None) -> Held:
    """The receiver's belief: object 7 at the slot's mean moved by ``offset`` (tangent), with
    covariance COV_D."""
    pose = se2.retract(LIN[0], DELTA0 + offset)[None]

    def covariances(ids):  # type: ignore[no-untyped-def]
        if calls is not None:
            calls.append(len(ids))
        return np.array([COV_D for _ in ids])

    return Held({7: 0}, pose, covariances)


def _offset(d2: float) -> np.ndarray:
    """An offset whose d² against Σ_s + Σ_D is ``d2``."""
    u = np.array([1.0, -2.0, 0.5])
    total = np.linalg.inv(LAMBDA) + COV_D
    return u * np.sqrt(d2 / (u @ np.linalg.solve(total, u)))


def test_threshold_is_chi2_with_three_degrees() -> None:
    assert gate_threshold(1e-9) == pytest.approx(44.84, abs=0.01)
    assert gate_threshold(1e-3) == pytest.approx(16.27, abs=0.01)


@pytest.mark.parametrize("d2, passes", [(40.0, True), (50.0, False)])
def test_the_gate_adds_both_covariances_and_measures_from_the_slot_mean(
    d2: float, passes: bool
) -> None:
    offset = _offset(d2)
    # The first stage (the slot's covariance alone) cannot pass either case: the receiver's
    # covariance decides, so dropping it would refuse the honest case.
    assert offset @ LAMBDA @ offset > gate_threshold(1e-9)
    calls: list[int] = []
    held = _held_at(offset, calls)
    if passes:
        check_xi("r2", (7,), _xi(), 100, held, 10.0, SETTINGS)
    else:
        with pytest.raises(Implausible, match="object 7 lies at Mahalanobis d² 50"):
            check_xi("r2", (7,), _xi(), 100, held, 10.0, SETTINGS)
    assert calls == [1]  # Σ_D asked for, once, for the one suspect object


def test_an_object_near_the_slot_mean_never_needs_the_receivers_covariance() -> None:
    calls: list[int] = []
    check_xi("r2", (7,), _xi(), 100, _held_at(np.array([0.02, 0.01, 0.0]), calls), 10.0, SETTINGS)
    assert calls == []


def test_the_gate_measures_from_the_slot_mean_not_its_linearisation_point() -> None:
    far = 5.0 * DELTA0  # d² ≈ 250 between the slot's mean and its linearisation point
    slot = Xi(LIN, LAMBDA, LAMBDA @ far)
    at_mean = Held({7: 0}, se2.retract(LIN[0], far)[None], lambda ids: np.array([COV_D]))
    check_xi("r2", (7,), slot, 100, at_mean, 10.0, SETTINGS)
    at_lin = Held({7: 0}, LIN.copy(), lambda ids: np.array([COV_D]))
    with pytest.raises(Implausible, match="Mahalanobis"):
        check_xi("r2", (7,), slot, 100, at_lin, 10.0, SETTINGS)


def test_objects_the_receiver_does_not_hold_pass_on_the_bound_alone() -> None:
    far = Held({8: 0}, np.array([[9000.0, 0.0, 0.0]]), lambda ids: np.array([COV_D]))
    check_xi("r2", (7,), _xi(), 100, far, 10.0, SETTINGS)


def test_information_bound_follows_the_steps_of_detections() -> None:
    # λmax(Λ) ≈ 250.3: above 2 × 12 × 10 = 240, below 2 × 13 × 10 = 260.
    with pytest.raises(Implausible, match=r"object 7 has information λmax 250"):
        check_xi("r2", (7,), _xi(), 12, None, 10.0, SETTINGS)
    check_xi("r2", (7,), _xi(), 13, None, 10.0, SETTINGS)
    check_xi("r2", (7,), _xi(), 12, None, 0.0, SETTINGS)  # no bound: semantic poses
    off = GateSettings(information_margin=0.0)
    check_xi("r2", (7,), _xi(), 1, None, 10.0, off)
    with pytest.raises(ValueError):
        GateSettings(information_margin=0.5)


def test_a_poisoned_slot_at_the_wire_cap_is_refused_either_way() -> None:
    poison = Xi(LIN + np.array([9000.0, 0.0, 0.0]), 1e9 * np.eye(3), np.zeros(3))
    with pytest.raises(Implausible, match="information"):
        check_xi("r3", (7,), poison, 13, _held_at(np.zeros(3)), 10.0, SETTINGS)
    no_bound = GateSettings(information_margin=0.0)
    with pytest.raises(Implausible, match="Mahalanobis"):
        check_xi("r3", (7,), poison, 13, _held_at(np.zeros(3)), 10.0, no_bound)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sparse_and_dense_solves_agree(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 5
    a = rng.normal(size=(3 * n, 3 * n))
    dense = a @ a.T + 3 * n * np.eye(3 * n)
    edges = np.array([[0, 1], [1, 2], [1, 3], [3, 4]])
    keep = np.zeros((n, n), bool)
    keep[np.arange(n), np.arange(n)] = True
    keep[edges[:, 0], edges[:, 1]] = keep[edges[:, 1], edges[:, 0]] = True
    blocks = dense.reshape(n, 3, n, 3).transpose(0, 2, 1, 3) * keep[:, :, None, None]
    lam = blocks.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    eta = rng.normal(size=3 * n)
    lin = rng.normal(size=(n, 3))
    sparse = SparseXi(
        lin,
        blocks[np.arange(n), np.arange(n)],
        edges,
        blocks[edges[:, 0], edges[:, 1]],
        eta,
    )
    d_s, m_s = _mean_and_marginals(sparse)
    d_d, m_d = _mean_and_marginals(Xi(lin, lam, eta))
    inv = np.linalg.inv(lam)
    assert np.allclose(d_s, d_d) and np.allclose(m_s, m_d)
    assert np.allclose(d_d.ravel(), inv @ eta)
    assert np.allclose(m_d[2], inv[6:9, 6:9])


def test_the_gates_local_coordinates_are_se2s() -> None:
    rng = np.random.default_rng(4)
    p = rng.normal(size=(40, 3)) * [5.0, 5.0, 3.0]
    q = np.concatenate([rng.normal(size=(20, 3)) * [5.0, 5.0, 3.0], p[:20] + 1e-9])
    assert np.allclose(_local(p, q), se2.local(p, q), rtol=0, atol=1e-12)


@pytest.mark.parametrize("d2, passes", [(40.0, True), (50.0, False)])
def test_the_slots_own_marginal_decides_when_the_receiver_is_certain(
    d2: float, passes: bool
) -> None:
    """Σ_D ≈ 0: the second stage (the slot's marginal alone) must pass the 40 and the third
    refuse the 50 — a wrong marginal in the second stage shows here."""
    tiny = 1e-9 * np.eye(3)
    u = np.array([1.0, -2.0, 0.5])
    calls: list[int] = []

    def covariances(ids):  # type: ignore[no-untyped-def]
        calls.append(len(ids))
        return np.array([tiny for _ in ids])

    # Two objects, correlated: the marginal of object 7 differs from its conditional block.
    lam2 = np.zeros((6, 6))
    lam2[:3, :3], lam2[3:, 3:] = LAMBDA, 2.0 * LAMBDA
    lam2[:3, 3:] = lam2[3:, :3] = -0.9 * LAMBDA
    lin2 = np.vstack([LIN, LIN + np.array([3.0, 0.0, 0.0])])
    slot = Xi(lin2, lam2, lam2 @ np.concatenate([DELTA0, np.zeros(3)]))
    sigma7 = np.linalg.inv(lam2)[:3, :3]
    offset = u * np.sqrt(d2 / (u @ np.linalg.solve(sigma7, u)))
    held = Held({7: 0}, se2.retract(LIN[0], DELTA0 + offset)[None], covariances)
    assert offset @ lam2[:3, :3] @ offset > gate_threshold(1e-9)  # the first stage cannot pass
    if passes:
        check_xi("r2", (7, 8), slot, 100, held, 10.0, SETTINGS)
        assert calls == []  # passed on the slot's own marginal
    else:
        with pytest.raises(Implausible, match="d² 50"):
            check_xi("r2", (7, 8), slot, 100, held, 10.0, SETTINGS)
        assert calls == [1]


def _largest_separation(model: ClassifierModel, rng: np.random.Generator, draws: int) -> float:
    """The largest |log P(z|a,ψ) − log P(z|b,ψ)| seen over scores on the edge of the plausible
    set (χ²_dim's 10⁻⁹ quantile around a random class at a random viewpoint ψ₀), each weighed
    at a random ψ: the worst the class-evidence bound has to cover."""
    g = float(chi2.isf(1e-9, model.dim))
    worst = 0.0
    for _ in range(draws):
        c = int(rng.integers(model.num_classes))
        psi0, psi = rng.uniform(0, 2 * np.pi, 2)
        u = rng.normal(size=model.dim)
        chol = np.linalg.cholesky(np.asarray(model.cov(c, psi0)))
        z = np.asarray(model.mean(c, psi0)) + np.sqrt(g) * chol @ (u / np.linalg.norm(u))
        ll = np.array([float(model.log_likelihood(z, a, psi)) for a in range(model.num_classes)])
        worst = max(worst, float(ll.max() - ll.min()))
    return worst


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_detections_class_evidence_stays_within_b(seed: int) -> None:
    """B covers every plausible score vector, for the aliased model and a learned one whose
    covariance changes with the viewpoint, and is not loose beyond a small factor."""
    rng = np.random.default_rng(seed)
    for model in (AliasedClassifier.random(4, rng), random_model(rng)):
        bound = evidence_per_detection(model, 1e-9)
        seen = _largest_separation(model, rng, 400)
        assert seen <= bound, (seen, bound)
        assert bound <= 8.0 * seen, (seen, bound)


class _TwoLevels:
    """A one-dimensional score: class 0 around 0, class 1 around ``gap``, noise σ, at every ψ."""

    num_classes, dim = 2, 1

    def __init__(self, gap: float, sigma: float) -> None:
        self.gap, self.sigma = gap, sigma

    def mean(self, c: int, psi: np.ndarray) -> np.ndarray:
        return np.full((*np.shape(psi), 1), c * self.gap)

    def cov(self, c: int, psi: np.ndarray) -> np.ndarray:
        return np.full((*np.shape(psi), 1, 1), self.sigma**2)


def test_b_is_tight_where_the_triangle_inequality_is() -> None:
    """Two well-separated levels: the plausible scores reach √g σ beyond either level, and there
    one detection separates the classes by (gap² + 2 gap √g σ) / 2σ² exactly; B is within 1 %."""
    model, g = _TwoLevels(10.0, 0.1), float(chi2.isf(1e-9, 1))
    exact = (100.0 + 2 * 10.0 * np.sqrt(g) * 0.1) / (2 * 0.01)
    bound = per_detection_bound(model, 1e-9)  # type: ignore[arg-type]
    assert exact <= bound <= 1.01 * exact, (exact, bound)


def test_b_grows_with_the_plausible_set_and_the_noise() -> None:
    sharp = AliasedClassifier.random(4, np.random.default_rng(5), noise_std=0.2)
    noisy = AliasedClassifier.random(4, np.random.default_rng(5), noise_std=0.4)
    assert evidence_per_detection(sharp, 1e-9) > evidence_per_detection(sharp, 1e-3)
    # Sharper scores tell classes apart more per detection.
    assert evidence_per_detection(sharp, 1e-9) > evidence_per_detection(noisy, 1e-9)


def _per_object(spans: list[float]) -> LocalSummary:
    """Objects 11, 12, … whose log φ span ``spans`` between their classes (non-uniform rows)."""
    rows = np.array([[0.3 * s, s, 0.0, 0.7 * s] for s in spans]) - 5.0
    n = len(spans)
    xi = Xi(np.zeros((n, 3)), np.eye(3 * n), np.zeros(3 * n))
    return LocalSummary(tuple(range(11, 11 + n)), (), ObjectClasses(rows, xi))


def test_class_evidence_bound_follows_the_steps_of_detections() -> None:
    b, margin, stamp = 5.0, 2.0, 10
    bound = margin * EVIDENCE_TERMS * stamp * b  # 300
    assert bound == 300.0
    check_classes("r2", _per_object([1.0, 299.0]), stamp, b, margin)
    with pytest.raises(Implausible, match=r"object 12 has class evidence spanning 301 nats"):
        check_classes("r2", _per_object([1.0, 301.0]), stamp, b, margin)
    # One step later the same evidence is within what 11 steps can give.
    check_classes("r2", _per_object([1.0, 301.0]), stamp + 1, b, margin)
    check_classes("r2", _per_object([1e5]), stamp, 0.0, margin)  # B = 0: not applied
    with pytest.raises(Implausible, match="object 11"):
        check_classes("r2", _per_object([np.nan]), stamp, b, margin)


def test_a_tables_bound_is_n_times_an_objects() -> None:
    xi = Xi(np.zeros((2, 3)), np.eye(6), np.zeros(6))
    reals = lambda top: (  # noqa: E731
        Realisation((0, 1), 0.0, xi),
        Realisation((1, 1), -top, xi),
    )
    # 2 objects, stamp 10, B 5, margin 2: 600 nats between realisations.
    check_classes("r2", LocalSummary((4, 5), reals(599.0)), 10, 5.0, 2.0)
    with pytest.raises(Implausible, match="table has class evidence spanning 601"):
        check_classes("r2", LocalSummary((4, 5), reals(601.0)), 10, 5.0, 2.0)


def test_check_summary_applies_the_class_bound_before_the_geometry() -> None:
    summary = _per_object([1e4])
    with pytest.raises(Implausible, match="class evidence"):
        check_summary("r2", summary, 10, None, 0.0, SETTINGS, per_detection=5.0)
    check_summary("r2", summary, 10, None, 0.0, SETTINGS)  # per_detection 0: not applied
