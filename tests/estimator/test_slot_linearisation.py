"""A slot's ξ taken at other poses than L's own (``estimator.slots.summarise(belief, at)``,
``BeliefConfig.slot_linearisation``): the owner's own factors linearised at its fused estimate,
every other variable eliminated. The same information, read where the receivers are."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.slots import linearisation_point, summarise
from estimator.summary import Xi
from sim.generate import generate_scenario
from sim.scenario import Scenario
from tests.estimator.stepwise import class_log_posteriors

# A window that acts within the run: L's graph then holds a root-shifted marginal factor too.
# The dense ξ: the one these tests read (a sparse one is made from it, estimator.sparse_xi).
CONFIGS = {
    "every pose": BeliefConfig(window=None, xi="dense"),
    "window 15": BeliefConfig(window=15, xi="dense"),
}


def _world(seed: int) -> Scenario:
    s = generate_scenario(2, 10, 3, 80 + seed, steps=50, area=10.0)
    return dataclasses.replace(s, class_prior=(0.5, 0.3, 0.2))


def _local(seed: int, config: BeliefConfig) -> HybridBelief:
    belief, _ = class_log_posteriors(_world(seed), seed, config, ["r1"])
    return belief


def _turned(
    values: gtsam.Values, start: int, angle: float, shift: tuple[float, float]
) -> gtsam.Values:
    """Every pose of ``values`` but the robot's ``start`` (held by its prior) moved by one rigid
    motion (what a fused estimate does to a drifted local map, to first order) and bent a
    little, pose by pose."""
    motion = gtsam.Pose2(shift[0], shift[1], angle)
    out = gtsam.Values()
    for i, key in enumerate(values.keys()):
        if key == start:
            out.insert(key, values.atPose2(key))
            continue
        bend = gtsam.Pose2(0.01 * np.sin(i), 0.01 * np.cos(i), 0.002 * np.sin(3 * i))
        out.insert(key, motion.compose(values.atPose2(key)).compose(bend))
    return out


def _mean(xi: Xi) -> np.ndarray:
    """ξ's mean as poses (n, 3): lin ⊕ Λ⁻¹η."""
    delta = np.linalg.solve(xi.info, xi.eta).reshape(-1, 3)
    out = [gtsam.Pose2(*p).retract(d) for p, d in zip(xi.lin, delta, strict=True)]
    return np.array([(p.x(), p.y(), p.theta()) for p in out])


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("seed", range(2))
def test_at_its_own_point_the_slot_is_the_one_from_the_bayes_tree(name: str, seed: int) -> None:
    belief = _local(seed, CONFIGS[name])
    reference = summarise(belief)
    assert reference is not None and reference.per_object is not None
    at = belief.hypotheses[0].continuous.isam.getLinearizationPoint()
    summary = summarise(belief, at)
    assert summary is not None and summary.per_object is not None
    a, b = reference.per_object.xi, summary.per_object.xi
    assert isinstance(a, Xi) and isinstance(b, Xi)
    np.testing.assert_allclose(b.lin, a.lin, rtol=0, atol=1e-12)
    scale = np.abs(a.info).max()
    np.testing.assert_allclose(b.info, a.info, rtol=0, atol=1e-9 * scale)
    # η = Λ δ̂: the Bayes tree reads δ̂ from iSAM2's Δ, which its wildfire threshold (10⁻³)
    # leaves partly stale; the batch elimination solves it. Measured up to 0.2 mm apart.
    np.testing.assert_allclose(_mean(b), _mean(a), rtol=0, atol=1e-3)
    assert np.abs(b.eta - a.eta).max() < 1e-2 * max(np.abs(a.eta).max(), 1.0)
    assert belief.slot_fit_refused == 0


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("seed", range(3))
def test_taken_elsewhere_the_slot_holds_the_same_information_about_where_l_is(
    name: str, seed: int
) -> None:
    belief = _local(seed, CONFIGS[name])
    h = belief.hypotheses[0].continuous
    estimate = h.isam.calculateEstimate()
    at = _turned(estimate, belief.pose_key("r1", 0), 0.05, (0.4, -0.3))
    summary = summarise(belief, at)
    assert summary is not None and summary.per_object is not None
    xi = summary.per_object.xi
    assert isinstance(xi, Xi)
    ids = summary.object_ids
    # Linearised where the fused estimate is ...
    for i, j in enumerate(ids):
        p = at.atPose2(object_key(j))
        np.testing.assert_allclose(xi.lin[i], (p.x(), p.y(), p.theta()), atol=1e-12)
    # ... its mean is still L's own (one Gauss-Newton step from 0.4 m and 3° away: the
    # residual is second order, measured below 2 mm) ...
    want = np.array([[*estimate.atPose2(object_key(j)).translation()] for j in ids])
    np.testing.assert_allclose(_mean(xi)[:, :2], want, rtol=0, atol=0.01)
    # ... and its information is L's factors' at those poses, priors divided out: the batch
    # marginal of L's graph, against which the objects' weak priors are taken off.
    graph = h.isam.getFactorsUnsafe()
    batch = gtsam.Marginals(graph, at)
    keys = gtsam.KeyVector([object_key(j) for j in ids])
    info = np.asarray(batch.jointMarginalInformation(keys).fullMatrix())
    prior = np.diag(1.0 / np.asarray(belief.config.object_prior_sigmas) ** 2)
    for i in range(len(ids)):
        info[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] -= prior
    np.testing.assert_allclose(xi.info, info, rtol=0, atol=1e-6 * np.abs(info).max())
    # Not the information at L's own point: the turn shows in Λ (the test can see a ξ that
    # ignored ``at``).
    own = summarise(belief)
    assert own is not None and own.per_object is not None
    assert np.abs(own.per_object.xi.info - xi.info).max() > 1e-4 * np.abs(info).max()


def test_an_estimate_that_l_cannot_fit_leaves_the_slot_at_ls_point_and_is_counted() -> None:
    belief = _local(0, CONFIGS["every pose"])
    h = belief.hypotheses[0].continuous
    reference = summarise(belief)
    assert reference is not None and reference.per_object is not None
    # A poisoned fused estimate: every object 40 m away, the robot where L has it.
    at = gtsam.Values()
    estimate = h.isam.calculateEstimate()
    for key in estimate.keys():  # noqa: SIM118 - gtsam.Values is not iterable
        p = estimate.atPose2(key)
        far = key in {object_key(j) for j in belief.object_ids}
        at.insert(key, gtsam.Pose2(p.x() + (40.0 if far else 0.0), p.y(), p.theta()))
    summary = summarise(belief, at)
    assert summary is not None and summary.per_object is not None
    np.testing.assert_array_equal(summary.per_object.xi.info, reference.per_object.xi.info)
    np.testing.assert_array_equal(summary.per_object.xi.lin, reference.per_object.xi.lin)
    assert belief.slot_fit_refused == 1
    assert belief.slot_fit > 100.0
    # An honest move (the small turn above) passes, and its excess per dimension is small.
    honest = _turned(estimate, belief.pose_key("r1", 0), 0.05, (0.4, -0.3))
    assert summarise(belief, honest) is not None
    assert belief.slot_fit_refused == 1
    assert 0.0 <= belief.slot_fit < 1.0


def test_only_a_per_object_fused_config_asks_for_a_point() -> None:
    fused = _local(0, BeliefConfig(window=None))
    point = linearisation_point(fused)
    assert point is not None and point.size() == fused.hypotheses[0].continuous.estimate.size()
    assert linearisation_point(_local(0, BeliefConfig(slot_linearisation="local"))) is None
    assert linearisation_point(_local(0, BeliefConfig.joint())) is None
    with pytest.raises(ValueError, match="slot_linearisation 'D'"):
        BeliefConfig(slot_linearisation="D")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 1e300])
def test_a_non_finite_or_absurd_fused_estimate_is_refused_and_the_slot_stays_finite(
    bad: float,
) -> None:
    belief = _local(0, CONFIGS["every pose"])
    estimate = belief.hypotheses[0].continuous.isam.calculateEstimate()
    at = gtsam.Values()
    for key in estimate.keys():  # noqa: SIM118 - gtsam.Values is not iterable
        p = estimate.atPose2(key)
        at.insert(key, gtsam.Pose2(bad, p.y(), p.theta()))
    summary = summarise(belief, at)
    assert summary is not None and summary.per_object is not None
    xi = summary.per_object.xi
    assert belief.slot_fit_refused == 1
    assert np.isfinite(xi.info).all() and np.isfinite(xi.eta).all() and np.isfinite(xi.lin).all()
