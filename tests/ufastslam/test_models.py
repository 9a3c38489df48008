"""Motion, observation and relation residuals of Semantic UFastSLAM."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.ufastslam.models import (
    inverse_observe,
    motion,
    observe,
    observe_jacobians,
    relation_residual,
)
from tests.tolerance import assert_angles_close, assert_close


def test_observe_and_inverse_observe_round_trip() -> None:
    rng = np.random.default_rng(0)
    poses = np.column_stack([rng.uniform(-5, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)])
    landmarks = rng.uniform(-10, 10, (20, 2))
    z = observe(poses, landmarks)
    assert np.all(np.abs(z[:, 1]) <= np.pi)
    assert_close(inverse_observe(poses, z), landmarks)


def test_observe_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(1)
    pose = np.array([0.5, -1.0, 2.9])
    landmark = np.array([-2.0, 1.5])
    h_x, h_m = observe_jacobians(pose, landmark)
    eps = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        diff = observe(pose + d, landmark) - observe(pose - d, landmark)
        assert_close(h_x[:, i], diff / (2 * eps), rtol=1e-6, atol=1e-8)
    for i in range(2):
        d = np.zeros(2)
        d[i] = eps
        diff = observe(pose, landmark + d) - observe(pose, landmark - d)
        assert_close(h_m[:, i], diff / (2 * eps), rtol=1e-6, atol=1e-8)
    batch_x, _ = observe_jacobians(rng.normal(size=(4, 5, 3)), rng.normal(size=(4, 5, 2)))
    assert batch_x.shape == (4, 5, 2, 3)


def test_observe_range_and_bearing() -> None:
    z = observe(np.array([1.0, 1.0, math.pi / 2]), np.array([1.0, 3.0]))
    assert_close(z, [2.0, 0.0], atol=1e-12)
    z = observe(np.array([0.0, 0.0, math.pi - 0.1]), np.array([-1.0, -0.2]))
    # the bearing is wrapped: atan2(−0.2, −1) − (π − 0.1) is just past −π
    assert_angles_close(z[1], math.atan2(-0.2, -1.0) - (math.pi - 0.1))
    assert -math.pi <= z[1] < math.pi


def test_motion_midpoint_discretisation() -> None:
    p = motion(np.array([1.0, 2.0, 0.3]), np.array([0.4, 0.2]), 0.5)
    a = 0.3 + 0.05
    assert_close(p, [1.0 + 0.2 * math.cos(a), 2.0 + 0.2 * math.sin(a), 0.4])


def test_motion_broadcasts_over_particles_and_sigma_points() -> None:
    poses = np.zeros((4, 7, 3))
    controls = np.ones((4, 7, 2))
    assert motion(poses, controls, 0.5).shape == (4, 7, 3)
    assert motion(poses, np.array([0.4, 0.0]), 0.5).shape == (4, 7, 3)


def test_relation_residuals() -> None:
    m = np.array([2.0, 5.0])
    assert_close(relation_residual("x", m, np.array([[1.5, -3.0]])), 0.5)
    assert_close(relation_residual("y", m, np.array([[9.0, 4.0]])), 1.0)
    # the line y = x through (0, 0) and (1, 1): (2, 5) lies 3/√2 m to its left
    line = np.array([[0.0, 0.0], [1.0, 1.0]])
    assert_close(relation_residual("col", m, line), 3.0 / math.sqrt(2.0))
    assert_close(relation_residual("col", np.array([4.0, 4.0]), line), 0.0, atol=1e-12)
    # metres, whatever the baseline's length
    assert_close(relation_residual("col", m, 10.0 * line), 3.0 / math.sqrt(2.0))


def test_relation_residual_rejects_unknown_kinds() -> None:
    with pytest.raises(ValueError, match="unknown relation kind 'z'"):
        relation_residual("z", np.zeros(2), np.zeros((1, 2)))
