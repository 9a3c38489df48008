"""The weight integral (design doc §3): closed-form geometric evidence, the per-assignment Monte
Carlo mean, and agreement of the default estimator with the paper's literal one."""

from __future__ import annotations

import itertools
import math

import gtsam
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from estimator.factors import diagonal_noise, object_key, pose_key
from estimator.models import paper_classifier, se2, viewpoint
from estimator.models.noise import PAPER_GEOMETRIC
from estimator.weights import (
    InvolvedGaussian,
    SemanticTerms,
    assignment_log_means,
    geo_conditioned,
    geo_conditioned_batch,
    geo_conditioned_samples,
    paper_mc,
    sampled_viewpoints,
)
from tests.tolerance import assert_close

# Robot pose and object pose of the one-detection examples; ψ ≈ 69°, where the paper model
# separates the classes well.
ROBOT = np.array([0.4, -0.3, 0.2])
OBJECT = np.array([2.0, 0.5, 2.4])
GEO_COV = PAPER_GEOMETRIC.cov
GEO_LOG_NORM = -0.5 * float(np.linalg.slogdet(2.0 * np.pi * GEO_COV)[1])
BOTH_CLASSES = np.array([[0], [1]], dtype=np.int64)
NO_DETECTIONS = np.zeros((1, 0), dtype=np.int64)
MODEL = paper_classifier()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(271828)


def _no_semantics() -> SemanticTerms:
    empty = np.zeros(0, dtype=np.int64)
    return SemanticTerms(empty, empty, np.zeros((0, 2)))


def _random_spd(n: int, rng: np.random.Generator) -> np.ndarray:
    a = rng.standard_normal((n, n))
    return a @ a.T + n * np.eye(n)


def _random_linear_case(
    n: int, m: int, rng: np.random.Generator
) -> tuple[InvolvedGaussian, np.ndarray]:
    """Random Λ (n, n), whitened J (m, n) and b (m,); also returns S = J Λ⁻¹ Jᵀ + I."""
    info = _random_spd(n, rng)
    jac = rng.standard_normal((m, n))
    rhs = rng.standard_normal(m)
    lin = rng.uniform(-2.0, 2.0, (n // 3, 3))
    g = InvolvedGaussian(lin, info, jac, rhs, (m // 3) * GEO_LOG_NORM)
    return g, jac @ np.linalg.solve(info, jac.T) + np.eye(m)


def _one_detection(
    robot: np.ndarray,
    obj: np.ndarray,
    z_geo: np.ndarray,
    info: np.ndarray,
) -> InvolvedGaussian:
    """The involved Gaussian of one robot pose seeing one object, built as HybridBelief does:
    the whitened linearised BetweenFactorPose2 at the linearisation point (robot, object)."""
    xk, oj = pose_key(0, 1), object_key(7)
    values = gtsam.Values()
    values.insert(xk, gtsam.Pose2(*robot))
    values.insert(oj, gtsam.Pose2(*obj))
    factor = gtsam.BetweenFactorPose2(xk, oj, gtsam.Pose2(*z_geo), diagonal_noise(PAPER_GEOMETRIC))
    jac, rhs = factor.linearize(values).jacobian()
    return InvolvedGaussian(np.array([robot, obj]), info, jac, rhs, GEO_LOG_NORM)


def _one_semantic_term(z_sem: np.ndarray) -> SemanticTerms:
    return SemanticTerms(np.array([0]), np.array([1]), z_sem[None, :])


@pytest.mark.parametrize(("n", "m"), [(6, 3), (9, 6)])
def test_geo_conditioned_geometric_evidence_matches_dense_gaussian(
    n: int, m: int, rng: np.random.Generator
) -> None:
    g, s = _random_linear_case(n, m, rng)
    assignments = np.zeros((3, 0), dtype=np.int64)
    got = geo_conditioned(g, _no_semantics(), assignments, MODEL, 10, rng)
    # ∫ exp(−½‖Jδ − b‖²) N(δ; 0, Λ⁻¹) dδ = (2π)^{m/2} N(b; 0, S): the whitened factors carry no
    # 2π, their normaliser is geo_log_norm.
    dense = multivariate_normal.logpdf(g.rhs, np.zeros(m), s)
    expected = dense + 0.5 * m * math.log(2.0 * math.pi) + g.geo_log_norm
    assert got.shape == (3,)
    assert_close(got, np.full(3, expected), what="log P(Z_geo)")


@pytest.mark.parametrize(("n", "m"), [(6, 3), (9, 6)])
def test_geo_conditioned_geometric_evidence_is_unwhitened_innovation_density(
    n: int, m: int, rng: np.random.Generator
) -> None:
    # Linear-Gaussian check in measurement units: residual r ~ N(0, H Λ⁻¹ Hᵀ + Σ_geo).
    info = _random_spd(n, rng)
    h = rng.standard_normal((m, n))
    r = rng.standard_normal(m)
    sigma = np.kron(np.eye(m // 3), GEO_COV)
    whiten = np.linalg.inv(np.linalg.cholesky(sigma))
    lin = np.zeros((n // 3, 3))
    g = InvolvedGaussian(lin, info, whiten @ h, whiten @ r, (m // 3) * GEO_LOG_NORM)
    got = geo_conditioned(g, _no_semantics(), NO_DETECTIONS, MODEL, 1, rng)
    innovation = h @ np.linalg.solve(info, h.T) + sigma
    assert_close(got, [multivariate_normal.logpdf(r, np.zeros(m), innovation)], what="log P(z)")


def _direct_log_means(log_lik: np.ndarray, assignments: np.ndarray) -> np.ndarray:
    s, d_count, _ = log_lik.shape
    out = []
    for row in assignments:
        per_sample = [sum(log_lik[i, d, row[d]] for d in range(d_count)) for i in range(s)]
        out.append(math.log(sum(math.exp(v) for v in per_sample) / s))
    return np.array(out)


def test_assignment_log_means_matches_direct_loop(rng: np.random.Generator) -> None:
    log_lik = rng.normal(-1.0, 1.5, (40, 3, 2))
    assignments = np.array(list(itertools.product(range(2), repeat=3)), dtype=np.int64)
    got = assignment_log_means(log_lik, assignments)
    assert_close(got, _direct_log_means(log_lik, assignments), what="log mean Π_d P(z_d | c)")


def test_assignment_log_means_repeated_class_columns(rng: np.random.Generator) -> None:
    # Two detections of one object share its class; assignments need not be all combinations.
    log_lik = rng.normal(0.0, 1.0, (25, 2, 3))
    assignments = np.array([[0, 0], [2, 2], [1, 1]], dtype=np.int64)
    got = assignment_log_means(log_lik, assignments)
    assert_close(got, _direct_log_means(log_lik, assignments))


def test_assignment_log_means_no_detections_is_zero() -> None:
    log_lik = np.zeros((17, 0, 2))
    assignments = np.zeros((4, 0), dtype=np.int64)
    got = assignment_log_means(log_lik, assignments)
    assert_close(got, _direct_log_means(log_lik, assignments))
    assert_close(got, np.zeros(4))


def test_assignment_log_means_stable_for_tiny_likelihoods() -> None:
    log_lik = np.full((10, 2, 2), -800.0)
    log_lik[:5, :, 1] = -801.0
    got = assignment_log_means(log_lik, np.array([[0, 0], [1, 1]], dtype=np.int64))
    expected_1 = -1600.0 + math.log(0.5 + 0.5 * math.exp(-2.0))
    assert_close(got, [-1600.0, expected_1], what="no underflow")


GeoTerms = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _well_conditioned_case() -> tuple[InvolvedGaussian, SemanticTerms, GeoTerms]:
    """One detection with a tight prior (σ = 0.05) on both involved poses; class 0 generated
    z_sem."""
    rel = se2.between(ROBOT, OBJECT)
    z_geo = rel + np.array([0.2, -0.3, 0.1])
    g = _one_detection(ROBOT, OBJECT, z_geo, np.eye(6) / 0.05**2)
    z_sem = MODEL.mean(0, float(viewpoint(ROBOT, OBJECT))) + np.array([0.1, -0.2])
    terms = _one_semantic_term(z_sem)
    geo_terms = (terms.robot_var, terms.object_var, z_geo[None, :], GEO_COV)
    return g, terms, geo_terms


def test_geo_conditioned_agrees_with_paper_mc_on_tight_prior() -> None:
    g, terms, geo_terms = _well_conditioned_case()
    rng = np.random.default_rng(1729)
    ours = geo_conditioned(g, terms, BOTH_CLASSES, MODEL, 20_000, rng)
    literal = paper_mc(g, terms, geo_terms, BOTH_CLASSES, MODEL, 200_000, rng)
    # Over five seeds the two estimators differ by ≤ 3e-3 (MC error plus linearisation); the
    # tolerance leaves a wide margin. Class 0 generated z_sem, so its log-odds are large.
    assert ours[0] - ours[1] > 3.0
    assert_close(ours[0] - ours[1], literal[0] - literal[1], atol=0.02, rtol=0, what="log-odds")
    assert_close(ours, literal, atol=0.02, rtol=0, what="Δlog w with geometric normalisation")


def test_paper_mc_without_semantics_matches_closed_form() -> None:
    # paper_mc is exact in its nonlinear geometry; with a tight prior the linearised closed form
    # of geo_conditioned is within Monte Carlo error of it.
    g, _, geo_terms = _well_conditioned_case()
    rng = np.random.default_rng(99)
    literal = paper_mc(g, _no_semantics(), geo_terms, NO_DETECTIONS, MODEL, 200_000, rng)
    closed = geo_conditioned(g, _no_semantics(), NO_DETECTIONS, MODEL, 1, rng)
    assert_close(literal, closed, atol=0.02, rtol=0, what="log P(Z_geo)")


def _newly_seen_object(rng: np.random.Generator) -> tuple[InvolvedGaussian, SemanticTerms]:
    """A robot with a tight pose prior sees an object whose only prior is the weak one centred on
    the first-measurement initial value (design doc §1–2)."""
    z_geo = se2.between(ROBOT, OBJECT)
    lin_object = se2.compose(ROBOT, z_geo)
    info = np.diag(
        np.concatenate([np.full(3, 1e-3**-2), np.array([100.0, 100.0, math.pi]) ** -2.0])
    )
    g = _one_detection(ROBOT, lin_object, z_geo, info)
    z_sem = MODEL.mean(1, float(viewpoint(ROBOT, OBJECT))) + 0.1 * rng.standard_normal(2)
    return g, _one_semantic_term(z_sem)


def test_geo_conditioned_finite_for_newly_seen_object(rng: np.random.Generator) -> None:
    g, terms = _newly_seen_object(rng)
    got = geo_conditioned(g, terms, BOTH_CLASSES, MODEL, 1000, rng)
    assert got.shape == (2,)
    assert np.all(np.isfinite(got))
    # The geometric evidence of a weakly known object is tiny (the object could be anywhere) but
    # common to both classes; class 1 generated z_sem.
    assert got[1] > got[0]


def test_geo_conditioned_low_variance_for_newly_seen_object(rng: np.random.Generator) -> None:
    # The default estimator samples the geometry-conditioned posterior, so its class log-odds for
    # a new object are stable across seeds (paper_mc's are not, design doc §3).
    g, terms = _newly_seen_object(rng)
    odds = []
    for seed in (1, 2, 3):
        w = geo_conditioned(g, terms, BOTH_CLASSES, MODEL, 1000, np.random.default_rng(seed))
        odds.append(w[1] - w[0])
    assert_close(odds, np.full(3, np.mean(odds)), atol=0.05, rtol=0, what="log-odds by seed")


def test_sampled_viewpoints_equal_the_viewpoints_of_retracted_poses(
    rng: np.random.Generator,
) -> None:
    """The fused ψ of the weight integral against se2.retract then viewpoint, over headings all
    round the circle, rotations beyond ±π and rotations at, below and just above the
    small-angle switch of the exponential map."""
    lin = np.concatenate(
        [rng.uniform(-8.0, 8.0, (3, 5, 2)), rng.uniform(-7.0, 7.0, (3, 5, 1))], axis=2
    )
    delta = rng.normal(0.0, 0.4, (3, 200, 5, 3))
    delta[..., 2] *= rng.choice([1.0, 10.0], size=delta.shape[:-1])
    delta[0, :6, 1, 2] = [0.0, 1e-9, -1e-9, 0.99e-6, 1.01e-6, -1.01e-6]
    robot_var, object_var = np.array([0, 0, 3, 3, 0]), np.array([1, 2, 4, 2, 4])
    poses = se2.retract(lin[:, None], delta)
    expected = viewpoint(poses[:, :, robot_var], poses[:, :, object_var])
    got = sampled_viewpoints(lin, delta, robot_var, object_var)
    assert got.shape == (3, 200, 5)
    assert np.abs(np.angle(np.exp(1j * (got - expected)))).max() < 1e-12


def test_geo_conditioned_batch_equals_one_parent_at_a_time() -> None:
    """The vectorised evidence of several parents: what a single-parent call gives each of them
    with the same draws (two detections of two objects, parents at different poses)."""
    rng = np.random.default_rng(5)
    gs = []
    for p in range(3):
        robot = ROBOT + 0.3 * p * np.array([1.0, -0.5, 0.4])
        obj2 = OBJECT + np.array([1.0, -2.0, -1.0])
        info = _random_spd(9, rng)
        g1 = _one_detection(robot, OBJECT, se2.between(robot, OBJECT), info[:6, :6])
        g2 = _one_detection(robot, obj2, se2.between(robot, obj2) + 0.05, info[:6, :6])
        jac = np.zeros((6, 9))
        jac[:3, :6] = g1.jac
        jac[3:, :3], jac[3:, 6:] = g2.jac[:, :3], g2.jac[:, 3:]
        lin = np.array([robot, OBJECT, obj2])
        gs.append(
            InvolvedGaussian(lin, info, jac, np.concatenate([g1.rhs, g2.rhs]), 2 * GEO_LOG_NORM)
        )
    terms = SemanticTerms(np.array([0, 0]), np.array([1, 2]), np.array([[0.3, 0.7], [0.8, 0.1]]))
    eps = np.random.default_rng(9).standard_normal((300, 9))
    base, log_lik = geo_conditioned_batch(gs, terms, MODEL, eps)
    singles = [geo_conditioned_samples(g, terms, MODEL, 300, np.random.default_rng(9)) for g in gs]
    assert_close(base, np.stack([s.base for s in singles]), rtol=1e-9)
    assert_close(log_lik, np.stack([s.log_lik for s in singles]), rtol=1e-9, atol=1e-9)
