"""The semantic factor: analytic Jacobians and its normalised log-likelihood."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative21, numericalDerivative22

from estimator.factors import (
    object_key,
    pose_key,
    semantic_error,
    semantic_factor,
    semantic_log_normaliser,
    viewpoint_with_jacobians,
)
from estimator.models import AliasedClassifier, ClassifierModel, paper_classifier, viewpoint
from tests.tolerance import assert_close


def _array(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


MODELS: list[ClassifierModel] = [
    paper_classifier(),
    AliasedClassifier.random(4, np.random.default_rng(3), noise_std=0.4),
]


def _random_cases(n: int = 25) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(11)
    cases = []
    while len(cases) < n:
        x, o = rng.uniform(-4, 4, 3), rng.uniform(-4, 4, 3)
        x[2] = rng.uniform(-np.pi, np.pi)
        o[2] = rng.uniform(-np.pi, np.pi)
        if np.hypot(*(x[:2] - o[:2])) > 0.3:
            cases.append((x, o, rng.normal(0.4, 0.3, 4)))
    return cases


@pytest.mark.parametrize("model", MODELS, ids=["paper", "aliased4"])
def test_semantic_error_jacobians_match_numerical_derivatives(model: ClassifierModel) -> None:
    for x, o, z in _random_cases():
        zc = z[: model.dim]
        for c in range(model.num_classes):

            def err(
                xp: gtsam.Pose2, op: gtsam.Pose2, c: int = c, zc: np.ndarray = zc
            ) -> np.ndarray:
                return semantic_error(model, c, zc, _array(xp), _array(op))[0]

            _, jx, jo = semantic_error(model, c, zc, x, o)
            nx = numericalDerivative21(err, gtsam.Pose2(*x), gtsam.Pose2(*o))
            no = numericalDerivative22(err, gtsam.Pose2(*x), gtsam.Pose2(*o))
            assert_close(jx, nx, rtol=0, atol=1e-7, what="d error / d x")
            assert_close(jo, no, rtol=0, atol=1e-7, what="d error / d o")


def test_viewpoint_with_jacobians_matches_vectorised_viewpoint() -> None:
    for x, o, _ in _random_cases():
        psi, _, _ = viewpoint_with_jacobians(x, o)
        assert_close(psi, viewpoint(x, o), atol=1e-12)


@pytest.mark.parametrize("model", MODELS, ids=["paper", "aliased4"])
def test_semantic_factor_linearisation_is_the_whitened_analytic_jacobian(
    model: ClassifierModel,
) -> None:
    """The factor's (specialised) callback against the generic model maths, for every class."""
    xk, oj = pose_key(0, 3), object_key(7)
    r = gtsam.noiseModel.Gaussian.Covariance(model.cov(0, 0.0)).R()  # Rᵀ R = Σ⁻¹
    for x, o, z in _random_cases(5):
        values = gtsam.Values()
        values.insert(xk, gtsam.Pose2(*x))
        values.insert(oj, gtsam.Pose2(*o))
        for c in range(model.num_classes):
            factor = semantic_factor(model, c, z[: model.dim], xk, oj, float(viewpoint(x, o)))
            a, b = factor.linearize(values).jacobian()
            err, jx, jo = semantic_error(model, c, z[: model.dim], x, o)
            assert_close(a, r @ np.hstack([jx, jo]), atol=1e-9)
            assert_close(b, -(r @ err), atol=1e-9)


@pytest.mark.parametrize("model", MODELS, ids=["paper", "aliased4"])
def test_semantic_log_likelihood_equals_minus_factor_error_minus_log_normaliser(
    model: ClassifierModel,
) -> None:
    xk, oj = pose_key(1, 2), object_key(4)
    for x, o, z in _random_cases(10):
        values = gtsam.Values()
        values.insert(xk, gtsam.Pose2(*x))
        values.insert(oj, gtsam.Pose2(*o))
        psi = float(viewpoint(x, o))
        for c in range(model.num_classes):
            factor = semantic_factor(model, c, z[: model.dim], xk, oj, psi)
            expected = model.log_likelihood(z[: model.dim], c, psi)
            got = -factor.error(values) + semantic_log_normaliser(model, c, psi)
            assert_close(got, expected, atol=1e-10)


def test_pose_keys_are_distinct_per_robot_and_step() -> None:
    keys = {pose_key(slot, k) for slot in range(5) for k in range(100)}
    assert len(keys) == 500
    assert not keys & {object_key(j) for j in range(100)}
