"""A slot's ξ and log φ (Eq. 18, design doc §4) against independent batch maths.

The object prior is strong here (σ = 0.5 m, 0.5 rad): with the default 100 m prior, dividing it
out or not changes Λ by 1e-4 and no comparison could tell.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from deploy.base.build import belief_model
from estimator.factors import diagonal_noise, object_key, pose_key, semantic_factor
from estimator.hybrid import BeliefConfig, BeliefModel, Hypothesis
from estimator.models import SensorFrame, viewpoint
from estimator.slots import EIGEN_FLOOR, _floor_eigenvalues, summarise
from sim.sensors import Simulator
from tests.estimator.exact_worlds import PRIORS, local_belief, no_pruning, prior_world
from tests.tolerance import assert_close

STRONG_PRIOR = (0.5, 0.5, 0.5)
# Three objects ahead of one robot, seen from different sides, one per class.
OBJECTS = [
    (2.0, 0.3, 0.4, 1),
    (2.8, -0.6, 1.2, 2),
    (3.5, 0.8, -0.5, 3),
]
# ξ is the Schur complement at the hypothesis' own linearisation point, so it agrees with the batch
# computation to rounding, amplified by the 1 mm start prior: measured ≤ 1.5e-10 of max |Λ| for Λ
# and η, ≤ 8e-11 m for the mean (6 worlds × 8–27 realisations). Not dividing the prior out moves
# Λ by 1/σ² = 4, i.e. 7 % of max |Λ|.
XI_RTOL = 1e-8
MEAN_ATOL = 1e-9


def _objects(classes: str) -> list[tuple[float, float, float, int]]:
    m = len(PRIORS[classes])
    return [(x, y, yaw, 1 + (c - 1) % m) for x, y, yaw, c in OBJECTS]


def _batch_xi(
    model: BeliefModel,
    start: np.ndarray,
    frames: list[SensorFrame],
    h: Hypothesis,
    object_ids: tuple[int, ...],
    config: BeliefConfig,
    with_object_priors: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """(Λ, η) over the objects: the whole batch graph of ``h``'s realisation (its semantic
    factors only with ``config.semantic_poses``) linearised at ``h``'s linearisation point, robot
    poses eliminated by a numpy Schur complement."""
    graph = gtsam.NonlinearFactorGraph()
    start_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(config.start_prior_sigmas))
    graph.add(gtsam.PriorFactorPose2(pose_key(0, 0), gtsam.Pose2(*start), start_noise))
    odometry, geometric = (
        diagonal_noise(model.odometry_noise),
        diagonal_noise(model.geometric_noise),
    )
    lin = h.isam.getLinearizationPoint()
    classes = dict(zip(object_ids, h.classes, strict=True))
    for f in frames:
        xk = pose_key(0, f.k)
        graph.add(
            gtsam.BetweenFactorPose2(pose_key(0, f.k - 1), xk, gtsam.Pose2(*f.odometry), odometry)
        )
        for d in f.detections:
            oj = object_key(d.object_id)
            graph.add(gtsam.BetweenFactorPose2(xk, oj, gtsam.Pose2(*d.z_geo), geometric))
            if not config.semantic_poses:
                continue
            x, o = lin.atPose2(xk), lin.atPose2(oj)
            psi0 = float(viewpoint([x.x(), x.y(), x.theta()], [o.x(), o.y(), o.theta()]))
            graph.add(
                semantic_factor(model.classifier, classes[d.object_id], d.z_sem, xk, oj, psi0)
            )
    if with_object_priors:
        prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(config.object_prior_sigmas))
        for j in object_ids:
            centre = gtsam.Pose2(*h.object_priors[j])
            graph.add(gtsam.PriorFactorPose2(object_key(j), centre, prior_noise))
    ordering = gtsam.Ordering()
    for j in object_ids:
        ordering.push_back(object_key(j))
    for k in range(len(frames) + 1):
        ordering.push_back(pose_key(0, k))
    info, eta = graph.linearize(lin).hessian(ordering)
    n = 3 * len(object_ids)
    h_oo, h_or, h_rr = info[:n, :n], info[:n, n:], info[n:, n:]
    schur = h_oo - h_or @ np.linalg.solve(h_rr, h_or.T)
    return schur, eta[:n] - h_or @ np.linalg.solve(h_rr, eta[n:])


@pytest.mark.parametrize("semantic_poses", [False, True], ids=["shared", "per-realisation"])
@pytest.mark.parametrize("classes", ["two", "three"])
@pytest.mark.parametrize("seed", range(3))
def test_summarise_xi_is_the_batch_schur_complement_without_object_priors(
    classes: str, seed: int, semantic_poses: bool
) -> None:
    s = prior_world([0.0], _objects(classes), PRIORS[classes], steps=8)
    config = no_pruning(object_prior_sigmas=STRONG_PRIOR, semantic_poses=semantic_poses)
    frames = Simulator(s, seed).all_frames()
    belief = local_belief(s, "r1", seed, frames, config)
    summary = summarise(belief)
    assert summary is not None
    m = len(PRIORS[classes])
    assert summary.object_ids == tuple(belief.object_ids) and len(summary.object_ids) == 3
    assert len(summary.realisations) == len(belief.hypotheses) == m**3
    model, start = belief_model(s), np.array(s.robot("r1").start)
    prior_info = 1.0 / STRONG_PRIOR[0] ** 2
    frames_r1 = list(frames["r1"])
    # One ξ for every realisation when they share a continuous belief, one each otherwise.
    xis, _ = summary.distinct_xi()
    assert len(xis) == (m**3 if semantic_poses else 1)
    for h, real in zip(belief.hypotheses, summary.realisations, strict=True):
        what = f"realisation {h.classes}"
        assert real.classes == h.classes, what
        lin = h.isam.getLinearizationPoint()
        expected_lin = [
            [p.x(), p.y(), p.theta()]
            for p in (lin.atPose2(object_key(j)) for j in summary.object_ids)
        ]
        assert_close(real.lin, expected_lin, what=what)
        info, eta = _batch_xi(model, start, frames_r1, h, summary.object_ids, config, False)
        scale = float(np.abs(info).max())
        assert_close(real.info, info, rtol=0.0, atol=XI_RTOL * scale, what=f"Λ of {what}")
        assert_close(real.eta, eta, rtol=0.0, atol=XI_RTOL * scale, what=f"η of {what}")
        assert_close(
            np.linalg.solve(real.info, real.eta),
            np.linalg.solve(info, eta),
            rtol=0.0,
            atol=MEAN_ATOL,
            what=f"mean of {what}",
        )
        # Not vacuous: the prior is a visible part of the joint that iSAM2 holds.
        with_prior, _ = _batch_xi(model, start, frames_r1, h, summary.object_ids, config, True)
        assert np.abs(np.diag(with_prior - real.info)).min() > 0.99 * prior_info, what


@pytest.mark.parametrize("classes", ["two", "three"])
def test_summarise_log_phi_divides_the_class_prior_out_of_every_weight(classes: str) -> None:
    s = prior_world([0.0], _objects(classes), PRIORS[classes], steps=4)
    frames = Simulator(s, 0).all_frames()
    belief = local_belief(s, "r1", 0, frames, no_pruning())
    summary = summarise(belief)
    assert summary is not None
    log_prior = np.log(PRIORS[classes])
    for h, real in zip(belief.hypotheses, summary.realisations, strict=True):
        expected = h.log_weight - sum(log_prior[c] for c in h.classes)
        assert math.isclose(real.log_phi, expected, rel_tol=0.0, abs_tol=1e-12), h.classes
    # Not vacuous: with a non-uniform prior the division differs between realisations.
    phi = np.array([r.log_phi for r in summary.realisations])
    lw = np.array([h.log_weight for h in belief.hypotheses])
    assert np.ptp(phi - lw) > 1.0


def test_a_xi_left_improper_by_the_prior_division_is_floored_to_a_proper_gaussian() -> None:
    """Dividing out the object prior of a barely constrained object can leave Λ with a
    non-positive eigenvalue: every eigenvalue is raised to EIGEN_FLOOR × the largest (the
    eigenvectors kept); a Λ already above the floor is only symmetrised."""
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    info = (q * np.array([4.0, 1.0, -1e-3])) @ q.T
    floored = _floor_eigenvalues(info)
    vals, vecs = np.linalg.eigh(floored)
    np.testing.assert_allclose(vals, [EIGEN_FLOOR * 4.0, 1.0, 4.0], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(abs(vecs.T @ q), np.eye(3)[[2, 1, 0]], atol=1e-6)
    proper = (q * np.array([4.0, 1.0, 0.5])) @ q.T
    np.testing.assert_array_equal(_floor_eigenvalues(proper), 0.5 * (proper + proper.T))
