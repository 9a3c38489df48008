"""``estimator.smoother.relative_marginal``: the window's marginal on poses, re-expressed relative
to one of its variables, equals the linear marginal at its linearisation point, has the right
Jacobians elsewhere, and a rigid motion of all its variables does not pull them back."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from estimator import relative_marginal as smoother
from estimator.factors import object_key, pose_key
from estimator.relative_marginal import relative_marginal


def _keys() -> list[int]:
    return [object_key(3), pose_key(0, 5), object_key(7), object_key(9)]


def _values(keys: list[int], rng: np.random.Generator, scale: float = 5.0) -> gtsam.Values:
    values = gtsam.Values()
    for k in keys:
        values.insert(k, gtsam.Pose2(*rng.normal(size=3) * [scale, scale, 1.0]))
    return values


def _dense(keys: list[int], rng: np.random.Generator) -> gtsam.JacobianFactor:
    """A dense Gaussian over ``keys`` with absolute information (a random marginal)."""
    graph = gtsam.GaussianFactorGraph()
    unit = gtsam.noiseModel.Unit.Create(6)
    for i, a in enumerate(keys):
        for b in keys[i + 1 :]:
            ai, bi, r = rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), rng.normal(size=6)
            graph.push_back(gtsam.JacobianFactor(a, ai, b, bi, r, unit))
    return gtsam.JacobianFactor(graph)


def _relative_only(
    keys: list[int], values: gtsam.Values, rng: np.random.Generator
) -> gtsam.GaussianFactor:
    """The marginal of relative measurements alone (a chain of between factors, linearised
    at ``values`` away from their measurements): it holds no absolute information."""
    graph = gtsam.NonlinearFactorGraph()
    sigmas = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.2, 0.05]))
    for a, b in zip(keys, keys[1:] + keys[:1], strict=True):
        z = values.atPose2(a).between(values.atPose2(b)).retract(rng.normal(size=3) * 0.1)
        graph.add(gtsam.BetweenFactorPose2(a, b, z, sigmas))
    return gtsam.JacobianFactor(graph.linearize(values))


def _info(factor: gtsam.GaussianFactor, keys: list[int]) -> np.ndarray:
    ordered = gtsam.GaussianFactorGraph()
    ordered.push_back(factor)
    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    return ordered.augmentedHessian(ordering)


@pytest.mark.parametrize("seed", range(3))
def test_it_is_the_linear_marginal_at_its_linearisation_point(seed: int) -> None:
    rng = np.random.default_rng(seed)
    keys = _keys()
    estimate = _values(keys, rng)
    g = _dense(keys, rng)
    factor = relative_marginal(g, estimate)
    assert factor is not None
    # Information and information vector: the whole augmented Hessian but its constant.
    n = 3 * len(keys)
    want, got = _info(g, keys), _info(factor.linearize(estimate), keys)
    np.testing.assert_allclose(got[:n, :], want[:n, :], atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("seed", range(3))
def test_its_jacobians_are_its_errors_derivatives_away_from_the_linearisation_point(
    seed: int,
) -> None:
    rng = np.random.default_rng(10 + seed)
    keys = _keys()
    estimate = _values(keys, rng)
    factor = relative_marginal(_dense(keys, rng), estimate)
    assert factor is not None
    keys = [int(k) for k in factor.keys()]  # noqa: SIM118 - not iterable
    moved = gtsam.Values()
    for k in keys:
        moved.insert(k, estimate.atPose2(k).retract(rng.normal(size=3) * 0.4))
    jac = factor.linearize(moved).augmentedJacobian()[:, :-1]
    e0 = factor.unwhitenedError(moved)
    numeric = np.zeros_like(jac)
    for i, k in enumerate(keys):
        for d in range(3):
            step = np.zeros(3)
            step[d] = 1e-6
            v = gtsam.Values(moved)
            v.update(k, moved.atPose2(k).compose(gtsam.Pose2.Expmap(step)))
            numeric[:, 3 * i + d] = (factor.unwhitenedError(v) - e0) / 1e-6
    np.testing.assert_allclose(jac, numeric, atol=1e-4 * np.abs(jac).max())


@pytest.mark.parametrize("seed", range(3))
def test_a_rigid_motion_of_a_deformed_map_costs_what_the_deformation_costs(seed: int) -> None:
    """A later loop closure turns the old map and bends it a little. What relative measurements
    knew about old poses says nothing about where the map is, so the turn must cost nothing:
    the relative factor's error is the bend's alone. A linear factor's local coordinates mix
    the turn into the bend (second-order cross terms, of the size of the bend itself)."""
    rng = np.random.default_rng(20 + seed)
    keys = _keys()
    estimate = _values(keys, rng)
    g = _relative_only(keys, estimate, rng)
    factor = relative_marginal(g, estimate)
    assert factor is not None
    linear = gtsam.LinearContainerFactor(g, estimate)
    bent = gtsam.Values()
    for k in keys:
        bent.insert(k, estimate.atPose2(k).retract(rng.normal(size=3) * [0.3, 0.3, 0.1]))
    turn = gtsam.Pose2(*rng.normal(size=3) * [3.0, 3.0, 0.0] + [0.0, 0.0, 2.0])
    turned = gtsam.Values()
    for k in keys:
        turned.insert(k, turn.compose(bent.atPose2(k)))
    assert factor.error(bent) > 1.0  # the bend costs
    assert factor.error(turned) == pytest.approx(factor.error(bent), rel=1e-9)
    assert abs(linear.error(turned) - linear.error(bent)) > 0.1 * linear.error(
        bent
    )  # measured 16-117 %


def test_a_marginal_without_information_is_no_factor() -> None:
    keys = _keys()[:2]
    estimate = _values(keys, np.random.default_rng(0))
    empty = gtsam.JacobianFactor(
        keys[0],
        np.zeros((3, 3)),
        keys[1],
        np.zeros((3, 3)),
        np.zeros(3),
        gtsam.noiseModel.Unit.Create(3),
    )
    assert relative_marginal(empty, estimate) is None


def test_its_pose_arithmetic_is_gtsams() -> None:
    """The factor evaluates every key at once in numpy; each piece equals GTSAM's Pose2, also
    at angles near 0 and near ±π."""
    rng = np.random.default_rng(3)
    poses = rng.normal(size=(40, 3)) * [4.0, 4.0, 2.0]
    poses[:5, 2] = [0.0, 1e-12, -3e-6, np.pi - 1e-9, -np.pi + 1e-7]
    poses[:, 2] = smoother._wrap(poses[:, 2])
    others = np.roll(poses, 1, axis=0)
    gp = [gtsam.Pose2(*p) for p in poses]
    go = [gtsam.Pose2(*p) for p in others]
    np.testing.assert_allclose(
        smoother._inverse(poses), [smoother._xyt(p.inverse()) for p in gp], atol=1e-12
    )
    got = smoother._compose(poses, others)
    want = np.array([smoother._xyt(p.compose(o)) for p, o in zip(gp, go, strict=True)])
    np.testing.assert_allclose(got[:, :2], want[:, :2], atol=1e-12)
    np.testing.assert_allclose(smoother._wrap(got[:, 2] - want[:, 2]), 0.0, atol=1e-12)
    np.testing.assert_allclose(smoother._adjoint(poses), [p.AdjointMap() for p in gp], atol=1e-12)
    np.testing.assert_allclose(
        smoother._logmap(poses), [gtsam.Pose2.Logmap(p) for p in gp], atol=1e-9
    )
    tangents = smoother._logmap(poses)
    np.testing.assert_allclose(
        smoother._logmap_derivative(tangents),
        [gtsam.Pose2.LogmapDerivative(v) for v in tangents],
        atol=1e-9,
    )
