"""The scaled unscented transform: exact for linear maps, equal to the Kalman update for a linear
measurement, angle-aware around ±π, and robust square roots."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.models.se2 import wrap_angle
from estimator.ufastslam import unscented as ut
from tests.tolerance import assert_angles_close, assert_close

PARAMS = [
    ut.UTParams(),
    ut.UTParams(alpha=0.5, beta=2.0, kappa=1.0),
    ut.UTParams(alpha=1.0, kappa=3.0),
]


def random_gaussians(rng: np.random.Generator, batch: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(batch, n) means and (batch, n, n) well-conditioned correlated covariances."""
    mean = rng.normal(0.0, 2.0, (batch, n))
    a = rng.normal(0.0, 1.0, (batch, n, n))
    return mean, a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(n)


@pytest.mark.parametrize("params", PARAMS)
def test_sigma_weights_sum_to_one(params: ut.UTParams) -> None:
    for n in (1, 3, 5, 9):
        w = ut.sigma_weights(n, params)
        assert_close(w.mean.sum(), 1.0)
        assert len(w.mean) == len(w.cov) == 2 * n + 1


def test_default_weights_are_non_negative() -> None:
    # α = 1, β = 2, κ = 0 (design doc §4): no negative weight, so every UT covariance is PSD
    for n in (2, 3, 5, 7, 11):
        w = ut.sigma_weights(n)
        assert np.all(w.mean >= 0) and np.all(w.cov >= 0)


@pytest.mark.parametrize("params", PARAMS)
def test_transform_is_exact_for_linear_maps(params: ut.UTParams) -> None:
    rng = np.random.default_rng(1)
    mean, cov = random_gaussians(rng, 7, 5)
    a = rng.normal(0.0, 1.0, (3, 5))
    b = rng.normal(0.0, 1.0, 3)

    y_mean, y_cov = ut.transform(mean, cov, lambda x: x @ a.T + b, params)

    assert_close(y_mean, mean @ a.T + b, rtol=1e-10, atol=1e-10)
    assert_close(y_cov, a @ cov @ a.T, rtol=1e-10, atol=1e-10)


def test_sigma_points_reproduce_mean_and_covariance() -> None:
    rng = np.random.default_rng(2)
    mean, cov = random_gaussians(rng, 4, 3)
    chi = ut.sigma_points(mean, cov)
    w = ut.sigma_weights(3)
    assert chi.shape == (4, 7, 3)
    m = np.einsum("s,bsi->bi", w.mean, chi)
    dev = chi - m[:, None, :]
    assert_close(m, mean)
    assert_close(np.einsum("s,bsi,bsj->bij", w.cov, dev, dev), cov, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("params", PARAMS)
def test_update_equals_kalman_update_for_a_linear_measurement(params: ut.UTParams) -> None:
    """Augmented state [x (3); consider c (2)], correlated prior, y = H a + v: the UT update of
    x equals the Kalman update's x-block, mean, covariance and log-likelihood."""
    rng = np.random.default_rng(3)
    batch, n, n_upd, m = 6, 5, 3, 4
    mean, cov = random_gaussians(rng, batch, n)
    h = rng.normal(0.0, 1.0, (m, n))
    r = np.diag(rng.uniform(0.1, 0.5, m))
    y = rng.normal(0.0, 3.0, (batch, m))

    res = ut.update(mean, cov, lambda a: a @ h.T, y, r, n_upd, params)

    s = h @ cov @ h.T + r
    k = cov @ h.T @ np.linalg.inv(s)
    nu = y - mean @ h.T
    kalman_mean = mean + np.einsum("bij,bj->bi", k, nu)
    kalman_cov = cov - k @ s @ np.swapaxes(k, -1, -2)
    ll = np.array(
        [
            -0.5 * nu[i] @ np.linalg.solve(s[i], nu[i])
            - 0.5 * np.log(np.linalg.det(2 * np.pi * s[i]))
            for i in range(batch)
        ]
    )
    assert_close(res.mean, kalman_mean[:, :n_upd], rtol=1e-9, atol=1e-9)
    assert_close(res.cov, kalman_cov[:, :n_upd, :n_upd], rtol=1e-9, atol=1e-9)
    assert_close(res.log_likelihood, ll, rtol=1e-9, atol=1e-9)


def test_update_broadcasts_measurement_and_noise_over_the_batch() -> None:
    rng = np.random.default_rng(4)
    mean, cov = random_gaussians(rng, 5, 2)
    one = ut.update(mean, cov, lambda a: a, np.array([0.3, -0.2]), 0.2 * np.eye(2), 2)
    for i in range(5):
        single = ut.update(mean[i], cov[i], lambda a: a, np.array([0.3, -0.2]), 0.2 * np.eye(2), 2)
        assert_close(one.mean[i], single.mean)
        assert_close(one.cov[i], single.cov)
        assert_close(one.log_likelihood[i], single.log_likelihood)


def test_angle_aware_mean_around_pi() -> None:
    """Headings of 3.13 rad: sigma points straddle ±π and wrap; the angle-aware mean is right
    where the naive one is not."""
    mean = np.array([3.13])
    cov = np.array([[0.05**2]])

    aware, aware_cov = ut.transform(mean, cov, wrap_angle, angular=(0,))
    naive, _ = ut.transform(mean, cov, wrap_angle)

    assert_angles_close(aware, [3.13], atol=1e-12)
    assert_close(aware_cov, cov, rtol=1e-9)
    assert abs(float(wrap_angle(naive[0] - 3.13))) > 1.0


def test_weighted_mean_of_headings_matches_circular_mean() -> None:
    rng = np.random.default_rng(5)
    headings = wrap_angle(np.pi + rng.normal(0.0, 0.05, 50))  # on both sides of ±π
    w = rng.uniform(0.5, 1.5, 50)
    w /= w.sum()

    aware = ut.weighted_mean(headings[:, None], w, angular=(0,))
    naive = w @ headings

    circular = np.arctan2(w @ np.sin(headings), w @ np.cos(headings))
    assert_angles_close(aware[0], circular, atol=1e-4)
    assert abs(float(wrap_angle(naive - circular))) > 1.0


def test_update_wraps_a_bearing_innovation() -> None:
    """A bearing measured at −3.1 rad while 3.1 is predicted is a 0.083 rad innovation, not 6.2."""
    mean = np.array([3.1])
    cov = np.array([[0.01]])
    res = ut.update(
        mean, cov, lambda a: wrap_angle(a), np.array([-3.1]), np.array([[0.01]]), 1, angular=(0,)
    )
    assert_angles_close(res.mean, [3.1 + 0.5 * (2 * np.pi - 6.2)], atol=1e-9)


def test_psd_sqrt_handles_zero_and_indefinite_matrices() -> None:
    zero = np.zeros((3, 3))
    root = ut.psd_sqrt(zero)
    assert np.all(np.isfinite(root))
    assert_close(root @ root.T, zero, atol=1e-10)
    indefinite = np.array([[[1.0, 0.0], [0.0, -1e-3]], [[2.0, 0.5], [0.5, 1.0]]])
    roots = ut.psd_sqrt(indefinite)
    assert_close(roots[0] @ roots[0].T, np.diag([1.0, 0.0]), atol=1e-9)
    assert_close(roots[1] @ roots[1].T, indefinite[1], atol=1e-9)


def test_params_are_validated() -> None:
    with pytest.raises(ValueError, match="alpha"):
        ut.UTParams(alpha=0.0)
    with pytest.raises(ValueError, match="n \\+ λ"):
        ut.sigma_weights(3, ut.UTParams(alpha=1.0, kappa=-3.0))
