"""Evaluation metrics (design doc §8) on hand-computed cases."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest

from estimator.hybrid import BeliefSnapshot
from estimator.metrics import (
    ECE_BINS,
    METRICS,
    NEES_VARIANCE_FLOOR,
    calibration_stats,
    chi2_bound,
    chi2_bounds,
    class_comparison,
    class_ece,
    class_log_loss,
    ece_from_stats,
    evaluate,
    evaluate_calibration,
    mixture_position_nees,
    msde,
    nees,
    pose_nees,
    with_truth,
    world_pose_nees,
    world_position_cov,
)
from estimator.pruning import class_marginals
from tests.tolerance import assert_close

NO_CLASSES = np.zeros(0, dtype=np.int64)


def _rot(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def test_msde_two_objects_two_classes() -> None:
    prob = np.array([[0.8, 0.2], [0.3, 0.7]])
    # object 0 (true 0): ((1 − 0.8)² + 0.2²)/2 = 0.04; object 1 (true 0): (0.7² + 0.7²)/2 = 0.49
    assert_close(msde(prob, np.array([0, 0])), (0.04 + 0.49) / 2)


def test_msde_three_classes() -> None:
    prob = np.array([[0.5, 0.3, 0.2]])
    assert_close(msde(prob, np.array([2])), (0.25 + 0.09 + 0.64) / 3)


def test_msde_certain_and_correct_is_zero() -> None:
    assert msde(np.array([[0.0, 1.0], [1.0, 0.0]]), np.array([1, 0])) == 0.0


def test_msde_no_objects_is_nan() -> None:
    assert math.isnan(msde(np.zeros((0, 2)), NO_CLASSES))


def test_class_log_loss_mean_of_true_class_surprise() -> None:
    prob = np.array([[0.8, 0.2], [0.3, 0.7]])
    assert_close(class_log_loss(prob, np.array([0, 1])), -(math.log(0.8) + math.log(0.7)) / 2)


def test_class_log_loss_clips_pruned_true_class() -> None:
    prob = np.array([[1.0, 0.0]])
    assert_close(class_log_loss(prob, np.array([1])), -math.log(1e-12))


def test_class_log_loss_no_objects_is_nan() -> None:
    assert math.isnan(class_log_loss(np.zeros((0, 2)), NO_CLASSES))


def test_class_ece_calibrated_marginals_give_zero() -> None:
    # P(c = 1) = 0.7 for ten objects of which seven are class 1: bin 7 holds ten 0.7s with seven
    # hits, bin 3 ten 0.3s with three.
    prob = np.tile([0.7, 0.3], (10, 1))
    assert_close(class_ece(prob, np.array([0] * 7 + [1] * 3)), 0.0)
    assert class_ece(np.array([[0.0, 1.0], [1.0, 0.0]]), np.array([1, 0])) == 0.0


def test_class_ece_overconfident_weights_bins_by_count() -> None:
    # Four objects at P(c = 1) = 0.9, two of them class 1, and one certain and right. Bin 9 holds
    # 0.9 × 4 and 1.0 (Σp = 4.6, 3 hits), bin 1 the four 0.1s (Σp = 0.4, 2 hits), bin 0 the 0.0
    # (no hit): ECE = (5/10)|0.92 − 0.6| + (4/10)|0.1 − 0.5| + (1/10)·0 = 0.32. Unweighted bins
    # would give 0.24, one bin of everything 0.
    prob = np.array([[0.9, 0.1]] * 4 + [[1.0, 0.0]])
    assert_close(class_ece(prob, np.array([0, 0, 1, 1, 0])), 0.32)


def test_class_ece_every_class_counts() -> None:
    # Three classes: 0.6 (hit), 0.3 and 0.1 (misses) → (|0.6 − 1| + 0.3 + 0.1) / 3.
    assert_close(class_ece(np.array([[0.6, 0.3, 0.1]]), np.array([0])), 0.8 / 3)


def test_class_ece_no_objects_is_nan() -> None:
    assert math.isnan(class_ece(np.zeros((0, 2)), NO_CLASSES))


def test_calibration_stats_bin_edges() -> None:
    # A bin is closed below and open above, the last one also holds 1.0.
    prob = np.array([[0.0, 0.1, 0.9], [1.0, 0.0999, 0.3], [0.7, 0.2, 0.19999]])
    stats = calibration_stats(prob, np.array([2, 0, 0]))
    assert stats.shape == (3, ECE_BINS)
    # bins of 0.0 0.1 0.9 / 1.0 0.0999 0.3 / 0.7 0.2 0.19999
    expected = np.zeros((3, ECE_BINS))
    expected[0, [0, 1, 2, 3, 7, 9]] = (2, 2, 1, 1, 1, 2)
    expected[1, [0, 1, 2, 3, 7, 9]] = (0.0999, 0.29999, 0.2, 0.3, 0.7, 1.9)
    # the true classes' marginals: 0.9 (object 0, class 3), 1.0 and 0.7 (objects 1, 2, class 1)
    expected[2, [7, 9]] = (1, 2)
    assert_close(stats, expected)


def test_calibration_stats_pool_by_summing() -> None:
    # Pooled statistics are those of all objects together; the pooled ECE is not the mean of
    # the parts' ECEs (the parts hold different numbers of marginals).
    a_prob, a_true = np.array([[0.9, 0.1]]), np.array([0])
    b_prob, b_true = np.array([[0.9, 0.1]] * 3), np.array([1, 1, 1])
    a, b = calibration_stats(a_prob, a_true), calibration_stats(b_prob, b_true)
    both = calibration_stats(np.vstack([a_prob, b_prob]), np.concatenate([a_true, b_true]))
    assert_close(a + b, both)
    # bins 9 and 1 each hold four marginals with one and three hits: (|3.6 − 1| + |0.4 − 3|)/8
    assert_close(ece_from_stats(a + b), 5.2 / 8)
    assert_close(class_ece(a_prob, a_true), 0.1)
    assert_close(class_ece(b_prob, b_true), 0.9)


def test_ece_from_stats_vectorises_and_empty_is_nan() -> None:
    stats = np.stack([calibration_stats(np.array([[0.9, 0.1]]), np.array([1])), np.zeros((3, 10))])
    got = ece_from_stats(stats)
    assert got.shape == (2,)
    assert_close(got[0], 0.9)
    assert math.isnan(got[1])


def test_class_marginals_sum_weights_per_class() -> None:
    weights = np.array([0.5, 0.3, 0.2])
    classes = np.array([[0, 1], [1, 1], [0, 0]], dtype=np.int64)
    expected = np.array([[0.7, 0.3], [0.2, 0.8]])
    assert_close(class_marginals(weights, classes, 2), expected)


def test_class_marginals_unused_class_has_zero_probability() -> None:
    got = class_marginals(np.array([0.4, 0.6]), np.array([[0], [2]], dtype=np.int64), 3)
    assert_close(got, [[0.4, 0.0, 0.6]])


def test_world_position_cov_rotates_body_frame_quarter_turn() -> None:
    cov = np.diag([4.0, 1.0, 0.5])
    got = world_position_cov(np.array([3.0, -1.0, math.pi / 2]), cov)
    assert_close(got, np.diag([1.0, 4.0]), atol=1e-12)


def test_world_position_cov_eighth_turn_and_stacks() -> None:
    cov = np.diag([4.0, 1.0, 0.5])
    poses = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 4]]])  # (1, 2, 3)
    got = world_position_cov(poses, np.broadcast_to(cov, (1, 2, 3, 3)))
    assert got.shape == (1, 2, 2, 2)
    assert_close(got[0, 0], np.diag([4.0, 1.0]), atol=1e-12)
    # R diag(4, 1) Rᵀ at 45°: ½[[4 + 1, 4 − 1], [4 − 1, 4 + 1]]
    assert_close(got[0, 1], [[2.5, 1.5], [1.5, 2.5]], atol=1e-12)


def test_nees_full_covariance_and_batches() -> None:
    a = np.array([[0.3, 0.05, 0.01], [0.0, 0.2, 0.02], [0.0, 0.0, 0.1]])
    cov = a @ a.T
    e = np.array([0.1, -0.2, 0.05])
    expected = float(e @ np.linalg.inv(cov) @ e)
    assert_close(nees(e, cov), expected)
    # the floored form is the same number while Σ is well above the floor
    assert_close(nees(e, cov, NEES_VARIANCE_FLOOR), expected)
    batch = nees(np.stack([e, 2 * e]), np.stack([cov, cov]), NEES_VARIANCE_FLOOR)
    assert_close(batch, [expected, 4 * expected])


def test_nees_floor_lifts_a_singular_covariance() -> None:
    e = np.array([0.0, 1e-3])
    cov = np.diag([1.0, 0.0])
    assert_close(nees(e, cov, floor=1e-8), 1e-6 / 1e-8)
    with pytest.raises(np.linalg.LinAlgError):
        nees(e, cov)


def test_world_pose_nees_is_a_world_frame_vector_error() -> None:
    cov = np.diag([0.04, 0.01, 0.0025])
    assert_close(world_pose_nees(np.zeros(3), cov, np.array([0.2, 0.1, 0.05])), 3.0)
    # the error is not rotated into the estimate's frame, unlike pose_nees
    facing_y = np.array([0.0, 0.0, math.pi / 2])
    assert_close(world_pose_nees(facing_y, cov, np.array([0.2, 0.0, math.pi / 2])), 1.0)
    # θ is wrapped: 2π − 0.05 away is 0.05 away
    assert_close(
        world_pose_nees(np.array([0, 0, np.pi - 0.02]), cov, np.array([0, 0, -np.pi + 0.03])), 1.0
    )
    # a collapsed particle set (P = 0) is overconfident, not an error
    assert world_pose_nees(np.zeros(3), np.zeros((3, 3)), np.array([0.1, 0.0, 0.0])) > 1e9


def test_pose_nees_translation_seen_from_rotated_estimate() -> None:
    # The estimate faces +y, so a truth 1 m further along +y is 1 m ahead in the body frame.
    estimate = np.array([0.0, 0.0, math.pi / 2])
    truth = np.array([0.0, 1.0, math.pi / 2])
    cov = np.diag([0.5, 2.0, 0.1])
    assert_close(pose_nees(estimate, cov, truth), 1.0**2 / 0.5)


def test_pose_nees_heading_error() -> None:
    estimate = np.array([1.0, 2.0, 0.3])
    cov = np.diag([1.0, 1.0, 0.01])
    truth = np.array([1.0, 2.0, 0.5])
    assert_close(pose_nees(estimate, cov, truth), 0.2**2 / 0.01)


def test_pose_nees_matches_gtsam_logmap_with_full_covariance() -> None:
    estimate = np.array([1.0, -0.5, 0.4])
    truth = np.array([1.3, -0.2, 0.9])
    a = np.array([[0.3, 0.05, 0.01], [0.0, 0.2, 0.02], [0.0, 0.0, 0.1]])
    cov = a @ a.T
    e = gtsam.Pose2.Logmap(gtsam.Pose2(*estimate).between(gtsam.Pose2(*truth)))
    # By hand: between = (R(0.4)ᵀ(0.3, 0.3), 0.5); Logmap with (θ/2)cot(θ/2).
    t = _rot(0.4).T @ np.array([0.3, 0.3])
    half = 0.25
    k = half / math.tan(half)
    by_hand = np.array([k * t[0] + half * t[1], -half * t[0] + k * t[1], 0.5])
    assert_close(e, by_hand)
    assert_close(pose_nees(estimate, cov, truth), by_hand @ np.linalg.solve(cov, by_hand))


def test_pose_nees_broadcasts_over_hypotheses() -> None:
    estimate = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 2]])
    cov = np.broadcast_to(np.eye(3), (2, 3, 3))
    truth = np.array([1.0, 0.0, 0.0])
    # Second: truth is 1 m to the right (−y body) and −90° in heading.
    e2 = gtsam.Pose2.Logmap(gtsam.Pose2(*estimate[1]).between(gtsam.Pose2(*truth)))
    assert_close(pose_nees(estimate, cov, truth), [1.0, float(e2 @ e2)])


def test_mixture_position_nees_one_component_is_plain_nees() -> None:
    pose = np.array([[1.0, 1.0, 0.3]])
    cov = np.array([[[0.4, 0.1, 0.0], [0.1, 0.2, 0.0], [0.0, 0.0, 0.05]]])
    truth = np.array([1.5, 0.6])
    world = _rot(0.3) @ cov[0, :2, :2] @ _rot(0.3).T
    e = truth - pose[0, :2]
    got = mixture_position_nees(np.array([1.0]), pose, cov, truth)
    assert_close(got, e @ np.linalg.solve(world, e))


@pytest.mark.parametrize(
    ("truth", "expected"),
    [
        # mean (3, 0); spread 0.25·3² + 0.75·1² = 3 along x; total diag(4, 1)
        ((3.0, 2.0), 2.0**2 / 1.0),
        ((5.0, 0.0), 2.0**2 / 4.0),
        ((1.0, 1.0), 2.0**2 / 4.0 + 1.0),
    ],
)
def test_mixture_position_nees_two_components_include_spread(
    truth: tuple[float, float], expected: float
) -> None:
    weights = np.array([0.25, 0.75])
    pose = np.array([[0.0, 0.0, 0.7], [4.0, 0.0, -1.1]])
    # Isotropic position covariance: the rotation to the world frame leaves it unchanged.
    cov = np.broadcast_to(np.diag([1.0, 1.0, 0.3]), (2, 3, 3))
    assert_close(mixture_position_nees(weights, pose, cov, np.array(truth)), expected)


def test_mixture_position_nees_per_object() -> None:
    weights = np.array([0.5, 0.5])
    pose = np.array([[[0.0, 0.0, 0.0], [5.0, 5.0, 0.0]], [[2.0, 0.0, 0.0], [5.0, 5.0, 0.0]]])
    cov = np.broadcast_to(np.eye(3), (2, 2, 3, 3))
    truth = np.array([[1.0, 1.0], [6.0, 5.0]])
    # object 0: mean (1, 0), total diag(2, 1), e = (0, 1); object 1: no spread, e = (1, 0)
    assert_close(mixture_position_nees(weights, pose, cov, truth), [1.0, 1.0])


def test_chi2_bounds_match_design_doc() -> None:
    assert_close(chi2_bounds(3, 100), (2.54, 3.50), atol=0.005, rtol=0, what="d = 3, N = 100")
    assert_close(chi2_bounds(2, 100), (1.63, 2.41), atol=0.005, rtol=0, what="d = 2, N = 100")


def test_chi2_bound_is_the_one_sided_quantile() -> None:
    # the χ² table: 11.345 (3 dof, 99 %), 5.991 (2 dof, 95 %), 6.635 (1 dof, 99 %)
    assert_close(chi2_bound(3), 11.345, atol=5e-4, rtol=0)
    assert_close(chi2_bound(2, 0.95), 5.991, atol=5e-4, rtol=0)
    assert_close(chi2_bound(1, 0.99), 6.635, atol=5e-4, rtol=0)
    # one run: the two-sided ANEES band's upper end is the one-sided bound at 1 − (1 − p)/2
    assert_close(chi2_bounds(3, 1, 0.98)[1], chi2_bound(3, 0.99))


def _snapshot() -> BeliefSnapshot:
    """Two hypotheses over objects 4 and 9: the heavier says classes (0, 1), the other (1, 1)."""
    a = np.array([[0.2, 0.03, 0.01], [0.0, 0.1, -0.02], [0.0, 0.0, 0.05]])
    return BeliefSnapshot(
        object_ids=(4, 9),
        weights=np.array([0.75, 0.25]),
        classes=np.array([[0, 1], [1, 1]], dtype=np.int64),
        robot_pose=np.array([[1.0, 2.0, 0.5], [1.3, 1.8, 0.7]]),
        robot_cov=np.array([a @ a.T, np.diag([0.09, 0.04, 0.01])]),
        object_pose=np.array(
            [[[3.0, 1.0, 0.0], [-2.0, 4.0, 1.0]], [[3.5, 1.0, 0.2], [-2.0, 4.5, 1.2]]]
        ),
        object_cov=np.array(
            [
                [np.diag([0.04, 0.01, 0.01]), np.diag([0.09, 0.16, 0.02])],
                [np.diag([0.25, 0.04, 0.01]), np.diag([0.01, 0.01, 0.01])],
            ]
        ),
    )


TRUE_POSE = np.array([1.1, 2.1, 0.55])
TRUE_OBJECTS = {
    4: (np.array([3.2, 0.8, 0.1]), 0),
    9: (np.array([-2.1, 4.2, 1.1]), 1),
    11: (np.array([0.0, 0.0, 0.0]), 0),
}


def _body_position_nees(pose: np.ndarray, cov: np.ndarray, truth_xy: np.ndarray) -> float:
    """World-position NEES computed in the body frame: e_body = Rᵀ e_world against Σ_xy."""
    e_body = _rot(pose[2]).T @ (truth_xy - pose[:2])
    return float(e_body @ np.linalg.solve(cov[:2, :2], e_body))


def _mixture_by_loop(
    w: np.ndarray, poses: np.ndarray, covs: np.ndarray, truth: np.ndarray
) -> float:
    mean = sum(wi * p[:2] for wi, p in zip(w, poses, strict=True))
    total = np.zeros((2, 2))
    for wi, p, c in zip(w, poses, covs, strict=True):
        d = p[:2] - mean
        total += wi * (_rot(p[2]) @ c[:2, :2] @ _rot(p[2]).T + np.outer(d, d))
    e = truth - mean
    return float(e @ np.linalg.solve(total, e))


def _expected_metrics(snap: BeliefSnapshot) -> dict[str, float]:
    w = snap.weights
    truth = [TRUE_OBJECTS[j] for j in snap.object_ids]
    # P(c_4 = 0) = 0.75, P(c_9 = 1) = 1
    prob = [[0.75, 0.25], [0.0, 1.0]]
    sq = [
        sum((float(i == c) - prob[j][i]) ** 2 for i in range(2)) / 2
        for j, (_, c) in enumerate(truth)
    ]
    e_top = gtsam.Pose2.Logmap(gtsam.Pose2(*snap.robot_pose[0]).between(gtsam.Pose2(*TRUE_POSE)))
    object_err = [
        sum(w[h] * math.dist(snap.object_pose[h, j, :2], truth[j][0][:2]) for h in range(2))
        for j in range(2)
    ]
    object_det = [
        sum(w[h] * math.sqrt(np.linalg.det(snap.object_cov[h, j, :2, :2])) for h in range(2))
        for j in range(2)
    ]
    return {
        "hypotheses": 2.0,
        "msde": sum(sq) / 2,
        "class_log_loss": -(math.log(0.75) + math.log(1.0)) / 2,
        # marginals 0.75 (hit), 0.25, 0.0 (misses), 1.0 (hit) in bins 7, 2, 0, 9
        "class_ece": (0.25 + 0.25 + 0.0 + 0.0) / 4,
        "robot_error": sum(
            w[h] * math.dist(snap.robot_pose[h, :2], TRUE_POSE[:2]) for h in range(2)
        ),
        "object_error": sum(object_err) / 2,
        "robot_sqrt_det": sum(
            w[h] * math.sqrt(np.linalg.det(snap.robot_cov[h, :2, :2])) for h in range(2)
        ),
        "object_sqrt_det": sum(object_det) / 2,
        "robot_nees": float(e_top @ np.linalg.solve(snap.robot_cov[0], e_top)),
        "object_nees": sum(
            _body_position_nees(snap.object_pose[0, j], snap.object_cov[0, j], truth[j][0][:2])
            for j in range(2)
        )
        / 2,
        "robot_nees_mixture": _mixture_by_loop(w, snap.robot_pose, snap.robot_cov, TRUE_POSE[:2]),
        "object_nees_mixture": sum(
            _mixture_by_loop(w, snap.object_pose[:, j], snap.object_cov[:, j], truth[j][0][:2])
            for j in range(2)
        )
        / 2,
    }


def test_evaluate_two_hypotheses_two_objects() -> None:
    snap = _snapshot()
    got = evaluate(snap, 2, TRUE_POSE, TRUE_OBJECTS)
    expected = _expected_metrics(snap)
    assert set(got) == set(METRICS) == set(expected)
    for key in METRICS:
        assert_close(got[key], expected[key], what=key)


def test_evaluate_top_hypothesis_follows_weights() -> None:
    snap = _snapshot()
    swapped = BeliefSnapshot(
        snap.object_ids,
        snap.weights[::-1].copy(),
        snap.classes[::-1].copy(),
        snap.robot_pose[::-1].copy(),
        snap.robot_cov[::-1].copy(),
        snap.object_pose[::-1].copy(),
        snap.object_cov[::-1].copy(),
    )
    got = evaluate(swapped, 2, TRUE_POSE, TRUE_OBJECTS)
    expected = _expected_metrics(snap)
    for key in METRICS:
        assert_close(got[key], expected[key], what=key)


def test_evaluate_no_objects_gives_nan_object_metrics() -> None:
    snap = _snapshot()
    empty = BeliefSnapshot(
        (),
        snap.weights,
        np.zeros((2, 0), dtype=np.int64),
        snap.robot_pose,
        snap.robot_cov,
        np.zeros((2, 0, 3)),
        np.zeros((2, 0, 3, 3)),
    )
    got = evaluate(empty, 2, TRUE_POSE, TRUE_OBJECTS)
    expected = _expected_metrics(snap)
    assert set(got) == set(METRICS)
    object_keys = {
        "msde",
        "class_log_loss",
        "class_ece",
        "object_error",
        "object_sqrt_det",
        "object_nees",
        "object_nees_mixture",
    }
    for key in METRICS:
        if key in object_keys:
            assert math.isnan(got[key]), key
        else:
            assert_close(got[key], expected[key], what=key)


def test_evaluate_calibration_is_the_poolable_class_ece() -> None:
    snap = _snapshot()
    stats = evaluate_calibration(snap, 2, TRUE_OBJECTS)
    expected = np.zeros((3, ECE_BINS))
    expected[:, 7] = (1, 0.75, 1)
    expected[:, 2] = (1, 0.25, 0)
    expected[:, 0] = (1, 0.0, 0)
    expected[:, 9] = (1, 1.0, 1)
    assert_close(stats, expected)
    assert_close(ece_from_stats(stats), evaluate(snap, 2, TRUE_POSE, TRUE_OBJECTS)["class_ece"])


def test_evaluate_calibration_no_objects_is_zero() -> None:
    snap = _snapshot()
    empty = BeliefSnapshot(
        (),
        snap.weights,
        np.zeros((2, 0), dtype=np.int64),
        snap.robot_pose,
        snap.robot_cov,
        np.zeros((2, 0, 3)),
        np.zeros((2, 0, 3, 3)),
    )
    assert_close(evaluate_calibration(empty, 2, TRUE_OBJECTS), np.zeros((3, ECE_BINS)))


def test_an_object_the_world_does_not_have_is_left_out_of_the_object_metrics() -> None:
    """A phantom (a forged slot or frame put it in the belief) has no truth to measure it by:
    the metrics are those of the belief without it, never a crash of the scorer."""
    snap = _snapshot()
    truth = {4: TRUE_OBJECTS[4]}  # object 9 is a phantom here
    alone = BeliefSnapshot(
        object_ids=(4,),
        weights=snap.weights,
        classes=snap.classes[:, :1],
        robot_pose=snap.robot_pose,
        robot_cov=snap.robot_cov,
        object_pose=snap.object_pose[:, :1],
        object_cov=snap.object_cov[:, :1],
    )
    got = evaluate(snap, 2, TRUE_POSE, truth)
    want = evaluate(alone, 2, TRUE_POSE, truth)
    assert got.keys() == want.keys()
    for name in got:
        assert_close(got[name], want[name], what=name)
    assert got["object_error"] != evaluate(snap, 2, TRUE_POSE, TRUE_OBJECTS)["object_error"]
    assert_close(evaluate_calibration(snap, 2, truth), evaluate_calibration(alone, 2, truth))


def _per_object_snapshot() -> BeliefSnapshot:
    """The heavier hypothesis of :func:`_snapshot` alone, as a belief with per-object class
    marginals (0.6, 0.4) for object 4 and (0.3, 0.7) for object 9. Its classes (0, 1), weight 1,
    would say both are certain and right: a metric from them, not from ``class_probs``, differs."""
    snap = _snapshot()
    return BeliefSnapshot(
        object_ids=snap.object_ids,
        weights=np.array([1.0]),
        classes=snap.classes[:1],
        robot_pose=snap.robot_pose[:1],
        robot_cov=snap.robot_cov[:1],
        object_pose=snap.object_pose[:1],
        object_cov=snap.object_cov[:1],
        class_probs=np.array([[0.6, 0.4], [0.3, 0.7]]),
    )


def test_evaluate_scores_the_per_object_class_marginals() -> None:
    snap = _per_object_snapshot()
    got = evaluate(snap, 2, TRUE_POSE, TRUE_OBJECTS)
    # object 4 (true 0): ((1 − 0.6)² + 0.4²)/2 = 0.16; object 9 (true 1): (0.3² + 0.3²)/2 = 0.09
    assert_close(got["msde"], (0.16 + 0.09) / 2)
    assert_close(got["class_log_loss"], -(math.log(0.6) + math.log(0.7)) / 2)
    # 0.6 (hit), 0.4 (miss), 0.3 (miss), 0.7 (hit): |0.6 − 1| + 0.4 + 0.3 + |0.7 − 1| over 4
    assert_close(got["class_ece"], (0.4 + 0.4 + 0.3 + 0.3) / 4)
    # the rest is the one hypothesis' own, as without class marginals
    table = dataclasses.replace(snap, class_probs=None)
    plain = evaluate(table, 2, TRUE_POSE, TRUE_OBJECTS)
    assert (plain["msde"], plain["class_log_loss"], plain["class_ece"]) == (0.0, 0.0, 0.0)
    for key in set(METRICS) - {"msde", "class_log_loss", "class_ece"}:
        assert got[key] == plain[key], key
    stats = evaluate_calibration(snap, 2, TRUE_OBJECTS)
    expected = np.zeros((3, ECE_BINS))
    expected[:, 6] = (1, 0.6, 1)
    expected[:, 4] = (1, 0.4, 0)
    expected[:, 3] = (1, 0.3, 0)
    expected[:, 7] = (1, 0.7, 1)
    assert_close(stats, expected)
    assert_close(ece_from_stats(stats), got["class_ece"])


def test_a_phantom_is_left_out_of_the_per_object_class_marginals_too() -> None:
    snap = _per_object_snapshot()
    truth = {4: TRUE_OBJECTS[4]}  # object 9 is a phantom here
    kept = with_truth(snap, truth)
    assert kept.object_ids == (4,) and kept.class_probs is not None
    assert_close(kept.class_probs, [[0.6, 0.4]])
    assert with_truth(dataclasses.replace(snap, class_probs=None), truth).class_probs is None
    got = evaluate(snap, 2, TRUE_POSE, truth)
    assert_close(got["msde"], 0.16)
    assert_close(got["class_log_loss"], -math.log(0.6))
    assert_close(got["class_ece"], (0.4 + 0.4) / 2)
    stats = evaluate_calibration(snap, 2, truth)
    assert_close(stats[0].sum(), 2.0)
    assert_close(ece_from_stats(stats), got["class_ece"])


def test_per_object_class_marginals_of_no_object_give_nan_and_zero_stats() -> None:
    snap = _per_object_snapshot()
    empty = BeliefSnapshot(
        (),
        snap.weights,
        np.zeros((1, 0), dtype=np.int64),
        snap.robot_pose,
        snap.robot_cov,
        np.zeros((1, 0, 3)),
        np.zeros((1, 0, 3, 3)),
        class_probs=np.zeros((0, 2)),
    )
    got = evaluate(empty, 2, TRUE_POSE, TRUE_OBJECTS)
    assert math.isnan(got["msde"]) and math.isnan(got["class_ece"])
    assert_close(evaluate_calibration(empty, 2, TRUE_OBJECTS), np.zeros((3, ECE_BINS)))


def test_class_comparison_scores_both_beliefs_on_the_objects_both_know_only() -> None:
    # mine knows 3, 7, 9; theirs 9, 3, 5 (another order): shared 3 and 9
    prob = np.array([[0.9, 0.1], [0.2, 0.8], [0.35, 0.65]])
    other = np.array([[0.6, 0.4], [0.7, 0.3], [0.5, 0.5]])
    truth = {3: 0, 5: 1, 7: 1, 9: 1}
    gap, mine, theirs = class_comparison([3, 7, 9], prob, [9, 3, 5], other, truth)
    # object 3: |0.9 − 0.7| = 0.2; object 9: |0.35 − 0.6| = 0.25 (not 7's 0.8 against anything)
    assert gap == pytest.approx(0.25)
    assert mine == pytest.approx(-(np.log(0.9) + np.log(0.65)) / 2)
    assert theirs == pytest.approx(-(np.log(0.7) + np.log(0.4)) / 2)
    # swapped roles: the same gap, the log-losses swap
    assert class_comparison([9, 3, 5], other, [3, 7, 9], prob, truth) == pytest.approx(
        (gap, theirs, mine)
    )
    assert all(np.isnan(class_comparison([7], prob[1:2], [5], other[2:], truth)))
