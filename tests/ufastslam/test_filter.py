"""The UFastSLAM filter: relations correcting the pose, resampling, association, modes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.ufastslam import (
    Observation,
    RelationConfig,
    UFastSLAM,
    UFastSLAMConfig,
    systematic_resample,
)
from estimator.ufastslam import unscented as ut
from estimator.ufastslam.models import inverse_observe, observe
from tests.tolerance import assert_close

STILL = np.zeros(2)
WALL = np.array([[4.0, -3.0], [4.0, 3.0]])  # two landmarks sharing x = 4


def z_of(pose: np.ndarray, landmark: np.ndarray) -> tuple[float, float]:
    z = observe(pose, landmark)
    return float(z[0]), float(z[1])


def heading_after_new_wall_landmark(source: str, seed: int = 0) -> float:
    """Landmark A is mapped precisely at its true place; every particle gets a 0.1 rad heading
    error; then the robot, truly at (0, 0, 0), sees landmark B (same x as A) for the first time."""
    config = UFastSLAMConfig(
        particles=200,
        control_std=(0.01, 0.2),
        measurement_std=(0.02, math.radians(0.2)),
        relations=RelationConfig(source=source),
    )
    slam = UFastSLAM(config, np.zeros(3))
    rng = np.random.default_rng(seed)
    truth = np.zeros(3)
    slam.step(STILL, [Observation(1, z_of(truth, WALL[0]), ("x:wall",))], rng)
    slam.mu[:, 0] = WALL[0]
    slam.sigma[:, 0] = 1e-4 * np.eye(2)
    slam.pose[:] = truth + np.array([0.0, 0.0, 0.1])
    slam.step(STILL, [Observation(2, z_of(truth, WALL[1]), ("x:wall",))], rng)
    return float(slam.pose_estimate()[2])


def test_same_x_relation_on_a_new_landmark_corrects_the_heading() -> None:
    corrected = heading_after_new_wall_landmark("labels")
    uncorrected = heading_after_new_wall_landmark("off")
    assert abs(corrected) < 0.02, corrected
    assert abs(uncorrected - 0.1) < 0.03, uncorrected


def test_new_landmark_relation_update_is_the_kalman_update_with_a_consider_state() -> None:
    """B joins an x group and a y group both anchored at A (a correlated Σ_A): the relations are
    linear, so B's map update must equal the Kalman update of its initial Gaussian by
    0 = B − A + n_s with A a consider state counted once, correlations included."""
    sigma_s = 0.05
    cfg = UFastSLAMConfig(particles=6, relations=RelationConfig(source="labels", std=sigma_s))
    slam = UFastSLAM(cfg, np.zeros(3))
    rng = np.random.default_rng(11)
    slam.step(STILL, [Observation(1, (3.0, 0.2), ("x:a", "y:b"))], rng)
    sigma_a = np.array([[0.04, 0.03], [0.03, 0.05]])
    slam.sigma[:, 0] = sigma_a
    z = (3.1, 0.25)
    slam.step(STILL, [Observation(2, z, ("x:a", "y:b"))], rng)

    def h_inv(noise: np.ndarray) -> np.ndarray:
        return inverse_observe(slam.pose[:, None, :], np.asarray(z) - noise)

    mu_obs, cov_obs = ut.transform(np.zeros(2), cfg.measurement_cov, h_inv)
    s = cov_obs + sigma_a + sigma_s**2 * np.eye(2)
    gain = cov_obs @ np.linalg.inv(s)
    nu = slam.mu[:, 0] - mu_obs
    assert_close(slam.mu[:, 1], mu_obs + np.einsum("nij,nj->ni", gain, nu), atol=1e-9)
    assert_close(slam.sigma[:, 1], cov_obs - gain @ cov_obs, atol=1e-9)


def test_threshold_detection_finds_the_same_relation() -> None:
    assert abs(heading_after_new_wall_landmark("threshold")) < 0.02


def test_relation_report_names_landmark_and_reference() -> None:
    slam = UFastSLAM(
        UFastSLAMConfig(particles=10, relations=RelationConfig(source="labels")), np.zeros(3)
    )
    rng = np.random.default_rng(0)
    slam.step(STILL, [Observation(7, z_of(np.zeros(3), WALL[0]), ("x:wall",))], rng)
    report = slam.step(STILL, [Observation(9, z_of(np.zeros(3), WALL[1]), ("x:wall",))], rng)
    assert [(r.kind, r.group, r.landmark, r.refs) for r in report.relations] == [
        ("x", "x:wall", 9, (7,))
    ]
    assert report.new_landmarks == (9,)
    assert slam.group_members() == [("x", "x:wall", [7, 9])]


def test_systematic_resample_copies_each_particle_floor_or_ceil_times() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = int(rng.integers(1, 60))
        w = rng.dirichlet(np.full(n, 0.3))
        counts = np.bincount(systematic_resample(w, rng), minlength=n)
        assert counts.sum() == n
        assert np.all(counts >= np.floor(n * w - 1e-9))
        assert np.all(counts <= np.ceil(n * w + 1e-9))


def test_systematic_resample_preserves_the_weighted_mean_in_expectation() -> None:
    rng = np.random.default_rng(2)
    n = 50
    values = rng.normal(0.0, 3.0, n)
    w = rng.dirichlet(np.ones(n))
    draws = np.array([values[systematic_resample(w, rng)].mean() for _ in range(4000)])
    target = float(w @ values)
    stderr = draws.std(ddof=1) / math.sqrt(len(draws))
    assert abs(draws.mean() - target) < 4 * stderr + 1e-12


def _filter_with_one_landmark(particles: int = 20) -> tuple[UFastSLAM, np.random.Generator]:
    slam = UFastSLAM(UFastSLAMConfig(particles=particles), np.zeros(3))
    rng = np.random.default_rng(3)
    slam.step(np.array([0.2, 0.0]), [Observation(1, (3.0, 0.2))], rng)
    return slam, rng


def test_resampling_never_aliases_particle_arrays() -> None:
    slam, rng = _filter_with_one_landmark()
    slam.log_w = np.full(20, -1e3)
    slam.log_w[5] = 0.0  # one particle takes all the weight: every particle becomes its copy
    before = {name: getattr(slam, name) for name in ("pose", "pose_cov", "mu", "sigma")}
    report = slam.step(np.array([0.2, 0.0]), [Observation(1, (2.9, 0.21))], rng)
    assert report.resampled
    for name, old in before.items():
        assert not np.shares_memory(getattr(slam, name), old), name
    # the copies are independent: changing one particle's landmark leaves the others alone
    assert_close(slam.mu[0, 0], slam.mu[1, 0])
    other = slam.mu[1, 0].copy()
    slam.mu[0, 0] += 1.0
    slam.sigma[0, 0] *= 2.0
    assert_close(slam.mu[1, 0], other)
    assert not np.shares_memory(slam.mu[0], slam.mu[1])


def test_weights_stay_normalised_and_resampling_resets_them() -> None:
    slam, rng = _filter_with_one_landmark()
    for k in range(10):
        report = slam.step(np.array([0.2, 0.0]), [Observation(1, (3.0 - 0.2 * k, 0.2))], rng)
        assert_close(slam.weights.sum(), 1.0)
        assert 1.0 <= report.n_eff <= 20.0 + 1e-9
        if report.resampled:
            assert_close(slam.weights, np.full(20, 1 / 20))


def test_steps_without_observations_accumulate_pose_covariance() -> None:
    slam = UFastSLAM(UFastSLAMConfig(particles=5), np.zeros(3))
    rng = np.random.default_rng(4)
    traces = []
    for _ in range(4):
        report = slam.step(np.array([0.4, 0.1]), [], rng)
        assert report.associations == () and not report.resampled
        traces.append(float(np.trace(slam.pose_cov[0])))
    assert traces == sorted(traces) and traces[0] > 0
    # identical particles stay identical until a measurement makes them sample
    assert_close(slam.pose[0], slam.pose[4])


def test_prediction_keeps_the_heading_around_pi() -> None:
    slam = UFastSLAM(
        UFastSLAMConfig(particles=3, control_std=(0.05, 0.3)), np.array([0.0, 0.0, math.pi - 0.01])
    )
    slam.step(np.array([0.0, 0.04]), [], np.random.default_rng(5))
    # π − 0.01 + 0.02 wraps to −π + 0.01; a naive mean of sigma points would land near 0
    assert_close(slam.pose[:, 2], -math.pi + 0.01, atol=1e-9)
    assert slam.pose_cov[0, 2, 2] == pytest.approx((0.3 * 0.5) ** 2, rel=1e-6)


def test_labels_without_labels_is_plain_ufastslam_bit_for_bit() -> None:
    def run(source: str) -> np.ndarray:
        cfg = UFastSLAMConfig(particles=15, relations=RelationConfig(source=source))
        slam = UFastSLAM(cfg, np.zeros(3))
        rng = np.random.default_rng(6)
        for k in range(8):
            slam.step(
                np.array([0.3, 0.05]),
                [Observation(1, (4.0 - 0.15 * k, 0.1 + 0.02 * k)), Observation(k + 2, (3.0, -0.3))],
                rng,
            )
        return np.concatenate([slam.pose.ravel(), slam.mu.ravel(), slam.log_w])

    np.testing.assert_array_equal(run("labels"), run("off"))


def test_nearest_neighbour_association_recovers_the_ids() -> None:
    landmarks = np.array([[3.0, 1.0], [4.0, -1.5], [6.0, 0.5]])
    cfg = UFastSLAMConfig(particles=20, association="nearest", measurement_std=(0.05, 0.01))
    slam = UFastSLAM(cfg, np.zeros(3))
    rng = np.random.default_rng(7)
    pose = np.zeros(3)
    first = None
    for _ in range(6):
        pose = pose + np.array([0.1, 0.0, 0.0])
        obs = [Observation(-1, z_of(pose, m)) for m in landmarks]
        report = slam.step(np.array([0.2, 0.0]), obs, rng)
        if first is None:
            first = report.associations
            assert len(set(first)) == 3 and report.new_landmarks == first
        else:
            assert report.associations == first and report.new_landmarks == ()
    _, xy = slam.map_estimate()
    assert_close(xy, landmarks, atol=0.1)


def test_every_mode_reapplies_relations_to_known_landmarks() -> None:
    """Both wall landmarks are first seen in the same step, so ONCE has no mapped reference for
    either and never relates them (exactly plain UFastSLAM); EVERY relates them at every later
    look and pulls them onto one x."""

    def x_gap(source: str, mode: str, seed: int) -> float:
        cfg = UFastSLAMConfig(particles=30, relations=RelationConfig(source=source, mode=mode))
        slam = UFastSLAM(cfg, np.zeros(3))
        rng = np.random.default_rng(seed)
        for _ in range(5):
            obs = [
                Observation(i + 1, z_of(np.zeros(3), m), ("x:wall",)) for i, m in enumerate(WALL)
            ]
            slam.step(STILL, obs, rng)
        _, xy = slam.map_estimate()
        return abs(float(xy[0, 0] - xy[1, 0]))

    seeds = range(5)
    off = np.array([x_gap("off", "once", s) for s in seeds])
    once = np.array([x_gap("labels", "once", s) for s in seeds])
    every = np.array([x_gap("labels", "every", s) for s in seeds])
    np.testing.assert_array_equal(once, off)
    assert np.all(every <= off)
    assert every.mean() < 0.3 * off.mean()


def test_close_measurements_are_rejected() -> None:
    slam = UFastSLAM(UFastSLAMConfig(particles=4, min_range=0.2), np.zeros(3))
    report = slam.step(
        STILL, [Observation(1, (0.1, 0.0)), Observation(2, (2.0, 0.0))], np.random.default_rng(9)
    )
    assert report.associations == (-1, 2)
    assert slam.landmark_ids == [2]


def test_a_landmark_new_twice_in_one_step_is_an_error() -> None:
    slam = UFastSLAM(UFastSLAMConfig(particles=4), np.zeros(3))
    with pytest.raises(ValueError, match="landmark 1 observed twice"):
        slam.step(
            STILL,
            [Observation(1, (2.0, 0.0)), Observation(1, (2.1, 0.0))],
            np.random.default_rng(10),
        )


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"particles": 0}, "particles must be ≥ 1"),
        ({"dt": 0.0}, "must be finite, > 0"),
        ({"control_std": (0.1, float("nan"))}, "must be finite, > 0"),
        ({"association": "greedy"}, "association 'greedy'"),
        ({"resample_threshold": 1.5}, "resample_threshold"),
    ],
)
def test_config_is_validated(kwargs: dict[str, object], fragment: str) -> None:
    with pytest.raises(ValueError) as info:
        UFastSLAMConfig(**kwargs)  # type: ignore[arg-type]
    assert fragment in str(info.value)


def test_step_rejects_bad_controls() -> None:
    slam = UFastSLAM(UFastSLAMConfig(particles=2), np.zeros(3))
    with pytest.raises(ValueError, match="control must be 2 finite numbers"):
        slam.step(np.array([0.1, np.inf]), [], np.random.default_rng(0))
    with pytest.raises(ValueError, match="start must be 3 finite numbers"):
        UFastSLAM(UFastSLAMConfig(particles=2), np.zeros(2))
