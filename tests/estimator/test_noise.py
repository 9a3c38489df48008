"""Tangent-space Gaussian noise on Pose2: validation, covariance of the draws, body-frame axes."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from estimator.models import GaussianNoise, se2
from estimator.models.noise import PAPER_GEOMETRIC, PAPER_ODOMETRY
from tests.tolerance import assert_angles_close, assert_close

SAMPLES = 20_000
# Statistical checks allow this many standard errors of the estimate.
Z = 5.0


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-20, 20, (n, 2)), rng.uniform(-np.pi, np.pi, n)])


def _assert_covariance(samples: np.ndarray, variances: np.ndarray, what: str) -> None:
    """Zero-mean samples (n, d) have covariance diag(variances), within Z standard errors:
    σ/√n for a mean, σ²√(2/(n−1)) for a variance, σ_iσ_j/√n for a covariance."""
    n = len(samples)
    sigma = np.sqrt(variances)
    mean = samples.mean(axis=0)
    cov = np.cov(samples, rowvar=False)
    assert np.all(np.abs(mean) <= Z * sigma / math.sqrt(n)), f"{what}: mean {mean}"
    var_se = variances * math.sqrt(2.0 / (n - 1))
    assert np.all(np.abs(np.diag(cov) - variances) <= Z * var_se), (
        f"{what}: variances {np.diag(cov)}, expected {variances}"
    )
    off = cov - np.diag(np.diag(cov))
    assert np.all(np.abs(off) <= Z * np.outer(sigma, sigma) / math.sqrt(n)), (
        f"{what}: covariances {off}"
    )


@pytest.mark.parametrize(
    "variances",
    [
        (0.0, 1.0, 1.0),
        (1.0, -0.1, 1.0),
        (1.0, 1.0, math.nan),
        (math.inf, 1.0, 1.0),
        (1.0,),  # two (bearing, range) or three (x, y, θ)
        (0.0, 1.0),
        (1.0, 1.0, 1.0, 1.0),
    ],
)
def test_gaussian_noise_rejects_bad_variances(variances: tuple[float, ...]) -> None:
    with pytest.raises(ValueError, match="variances"):
        GaussianNoise(variances)  # type: ignore[arg-type]


def test_gaussian_noise_exposes_sigmas_and_covariance() -> None:
    noise = GaussianNoise((0.04, 0.09, 0.01))
    assert_close(noise.sigmas, [0.2, 0.3, 0.1], what="sigmas")
    assert_close(noise.cov, np.diag([0.04, 0.09, 0.01]), what="cov")


def test_paper_noise_models_match_design_doc() -> None:
    assert PAPER_ODOMETRY.variances == (0.003, 0.003, 0.001)
    assert PAPER_GEOMETRIC.variances == (0.1, 0.1, 0.01)


def test_corrupt_with_zero_draws_returns_truth() -> None:
    truth = _random_poses(np.random.default_rng(1), 10)
    out = PAPER_GEOMETRIC.corrupt(truth, np.zeros((10, 3)))
    assert_close(out[:, :2], truth[:, :2], what="x, y")
    assert_angles_close(out[:, 2], truth[:, 2], what="θ")


def test_corrupt_matches_gtsam_retract() -> None:
    rng = np.random.default_rng(2)
    noise = GaussianNoise((0.04, 0.09, 0.01))
    truth, draws = _random_poses(rng, 50), rng.standard_normal((50, 3))
    out = noise.corrupt(truth, draws)
    for t, d, o in zip(truth, draws, out, strict=True):
        expected = gtsam.Pose2(*map(float, t)).retract(d * noise.sigmas)
        assert_close(o[:2], [expected.x(), expected.y()], what="x, y")
        assert_angles_close(o[2], expected.theta(), what="θ")


@pytest.mark.parametrize(
    "variances", [PAPER_ODOMETRY.variances, PAPER_GEOMETRIC.variances, (0.5, 0.02, 0.2)]
)
def test_sample_has_configured_tangent_covariance(variances: tuple[float, float, float]) -> None:
    rng = np.random.default_rng(20240611)
    noise = GaussianNoise(variances)
    truth = _random_poses(rng, SAMPLES)
    measured = noise.sample(truth, rng)
    _assert_covariance(se2.local(truth, measured), np.array(variances), "local(truth, sample)")


def test_corrupt_has_configured_tangent_covariance() -> None:
    rng = np.random.default_rng(99)
    noise = GaussianNoise((0.5, 0.02, 0.2))
    truth = np.broadcast_to(np.array([3.0, -1.0, 2.5]), (SAMPLES, 3))
    measured = noise.corrupt(truth, rng.standard_normal((SAMPLES, 3)))
    _assert_covariance(se2.local(truth, measured), np.array(noise.variances), "local(truth, z)")


def test_corrupt_applies_noise_in_body_frame() -> None:
    noise = GaussianNoise((0.04, 0.09, 0.01))
    truth = np.array([1.0, 2.0, math.pi / 2])
    # Body x of a pose facing world +y is world +y; body y is world −x.
    assert_close(noise.corrupt(truth, np.array([1.0, 0.0, 0.0])), [1.0, 2.2, math.pi / 2])
    assert_close(noise.corrupt(truth, np.array([0.0, 1.0, 0.0])), [0.7, 2.0, math.pi / 2])


def test_sample_x_noise_of_quarter_turned_pose_is_along_world_y() -> None:
    rng = np.random.default_rng(5)
    noise = GaussianNoise((0.04, 1e-10, 1e-10))
    truth = np.array([1.0, 2.0, math.pi / 2])
    measured = noise.sample(np.broadcast_to(truth, (SAMPLES, 3)), rng)
    shift = measured[:, :2] - truth[:2]
    var_x, var_y = shift.var(axis=0)
    assert var_x < 1e-8, f"world x variance {var_x}, expected ~1e-10"
    assert abs(var_y - 0.04) <= Z * 0.04 * math.sqrt(2.0 / (SAMPLES - 1)), (
        f"world y variance {var_y}"
    )


def test_sample_keeps_shape() -> None:
    rng = np.random.default_rng(6)
    assert PAPER_ODOMETRY.sample(np.zeros(3), rng).shape == (3,)
    assert PAPER_ODOMETRY.sample(np.zeros((4, 5, 3)), rng).shape == (4, 5, 3)


def test_sample_is_reproducible_from_seed() -> None:
    truth = _random_poses(np.random.default_rng(7), 100)
    a = PAPER_GEOMETRIC.sample(truth, np.random.default_rng(8))
    b = PAPER_GEOMETRIC.sample(truth, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)


def test_sample_equals_corrupt_with_the_same_draws() -> None:
    truth = _random_poses(np.random.default_rng(9), 100)
    draws = np.random.default_rng(10).standard_normal(truth.shape)
    sampled = PAPER_GEOMETRIC.sample(truth, np.random.default_rng(10))
    assert_close(sampled, PAPER_GEOMETRIC.corrupt(truth, draws), what="sample vs corrupt")
