"""``BeliefConfig.window``: robot poses older than a window are marginalised, objects are kept
(``estimator.smoother``), so a step and the belief's memory stop growing with the mission."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng
from estimator.distributed import DistributedBelief
from estimator.factors import object_key, pose_key
from estimator.hybrid import POSE_WINDOW, BeliefConfig, HybridBelief
from estimator.ledger import SemanticLedger
from estimator.models.classifier import all_log_likelihoods
from estimator.slots import summarise
from estimator.smoother import WindowedISAM2, marginal_covariances, pose_step, pose_steps
from estimator.summary import Slot
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.stepwise import class_log_posteriors

WINDOW = 15


def _world(seed: int, steps: int = 90) -> Scenario:
    s = generate_scenario(2, 10, 3, 60 + seed, steps=steps, area=10.0)
    return dataclasses.replace(s, class_prior=(0.5, 0.3, 0.2))


def _run(s: Scenario, seed: int, config: BeliefConfig) -> tuple[HybridBelief, list[np.ndarray]]:
    return class_log_posteriors(s, seed, config, ["r1"])


def _object_positions(belief: HybridBelief) -> np.ndarray:
    h = belief.hypotheses[0]
    return np.array([h.pose(object_key(j))[:2] for j in sorted(belief.object_ids)])


def test_pose_keys_say_their_step() -> None:
    keys = [pose_key(0, 0), pose_key(0, 17), pose_key(3, 250)]
    assert [pose_step(k) for k in keys] == [0, 17, 250]
    assert pose_step(object_key(17)) is None
    assert pose_steps(keys).tolist() == [0, 17, 250]


@pytest.mark.parametrize("seed", range(2))
def test_a_window_longer_than_the_mission_is_the_full_smoother(seed: int) -> None:
    s = _world(seed, steps=30)
    full, full_classes = _run(s, seed, BeliefConfig(window=None))
    windowed, windowed_classes = _run(s, seed, BeliefConfig(window=40))
    for a, b in zip(full_classes, windowed_classes, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(_object_positions(full), _object_positions(windowed), atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_the_window_keeps_its_poses_and_every_object_and_stays_near_the_full_smoother(
    seed: int,
) -> None:
    s = _world(seed)
    full, full_classes = _run(s, seed, BeliefConfig(window=None))
    windowed, windowed_classes = _run(s, seed, BeliefConfig(window=WINDOW))
    cont = windowed.hypotheses[0].continuous
    assert isinstance(cont.isam, WindowedISAM2)
    estimate = cont.estimate
    keys = [int(k) for k in estimate.keys()]  # noqa: SIM118 - gtsam.Values is not iterable
    steps = [pose_step(k) for k in keys]
    kept = sorted({st for st in steps if st is not None})
    oldest = cont.isam.oldest_kept()
    assert s.steps - 2 * WINDOW < oldest <= s.steps - WINDOW
    assert kept == list(range(oldest, s.steps + 1))
    assert cont.isam.rebuilds == s.steps // WINDOW - 1
    assert sum(st is None for st in steps) == len(windowed.object_ids)
    # The ledger holds only the detections of the kept poses: its memory is the window's.
    ledger = cont.ledger
    assert ledger is not None
    assert (pose_steps(ledger.robot_key_array()) >= oldest).all()
    assert 0 < len(ledger.robot_keys) < len(full.hypotheses[0].continuous.ledger.robot_keys)
    # Marginalised poses no longer move with later loop closures, and their detections'
    # evidence is final. Measured (seeds 0-4, a 10 m world, a window of 15 steps): objects at
    # most 6.6 cm from the full smoother's (part of it the full smoother's own linearisation
    # lag, which a rebuild resolves), a class probability at most 0.058 off at any step.
    gap = np.abs(_object_positions(full) - _object_positions(windowed)).max()
    assert gap < 0.1
    dp = max(
        np.abs(_probs(a) - _probs(b)).max()
        for a, b in zip(full_classes, windowed_classes, strict=True)
    )
    assert dp < 0.1


def _probs(log_posterior: np.ndarray) -> np.ndarray:
    return np.exp(log_posterior - np.logaddexp.reduce(log_posterior, axis=1, keepdims=True))


@pytest.mark.parametrize("seed", range(2))
def test_marginalising_keeps_the_kept_variables_marginal_at_the_fixed_point(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At iSAM2's fixed point (relinearised at every update), a rebuild changes neither the
    estimate nor the joint marginal of the objects and the latest pose: the marginal factor
    carries exactly what the old poses knew. A rebuild that dropped it, or linearised it
    elsewhere, would move both."""
    s = _world(seed)
    exact = BeliefConfig(
        window=WINDOW,
        relinearize_threshold=1e-9,
        relinearize_skip=1,
        partial_relinearization=False,
        extra_updates=3,
    )
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, exact)
    seen: list[tuple[float, float]] = []
    marginalise = WindowedISAM2._marginalise

    def checked(self: WindowedISAM2, oldest: int) -> None:
        keys = [object_key(j) for j in sorted(belief.object_ids)] + [belief.pose_key("r1")]
        before = self.isam.calculateEstimate()
        cov0 = self.isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        marginalise(self, oldest)
        after = self.isam.calculateEstimate()
        cov1 = self.isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        shift = max(
            float(np.abs(before.atPose2(k).localCoordinates(after.atPose2(k))).max()) for k in keys
        )
        seen.append((shift, float(np.abs(cov1 - cov0).max() / np.abs(cov0).max())))

    monkeypatch.setattr(WindowedISAM2, "_marginalise", checked)
    rng = belief_rng(seed, ["r1"])
    for f in Simulator(s, seed).all_frames()["r1"]:
        belief.step([f], rng)
    assert len(seen) == s.steps // WINDOW - 1
    # measured: shifts ≤ 1e-6 m, covariances ≤ 2.2e-7 relative
    assert max(shift for shift, _ in seen) < 1e-5
    assert max(cov for _, cov in seen) < 1e-5


@pytest.mark.parametrize("seed", range(2))
def test_a_window_over_several_robots_keeps_each_ones_last_poses(seed: int) -> None:
    """A centralized belief: both robots' old poses go at each rebuild (GTSAM's
    marginalizeLeaves refused this when two robots' old poses shared a clique)."""
    s = _world(seed)
    full, _ = class_log_posteriors(s, seed, BeliefConfig(window=None))
    windowed, _ = class_log_posteriors(s, seed, BeliefConfig(window=WINDOW))
    cont = windowed.hypotheses[0].continuous
    assert isinstance(cont.isam, WindowedISAM2)
    oldest = cont.isam.oldest_kept()
    assert oldest > 0
    keys = [int(k) for k in cont.estimate.keys()]  # noqa: SIM118 - gtsam.Values is not iterable
    for r in s.robot_ids:
        kept = [k for k in keys if k in {windowed.pose_key(r, t) for t in range(s.steps + 1)}]
        assert sorted(pose_step(k) for k in kept) == list(range(oldest, s.steps + 1))
    gap = np.abs(_object_positions(full) - _object_positions(windowed)).max()
    assert gap < 0.1  # measured 0.016 and 0.048 m (seeds 0, 1)


def test_a_windowed_distributed_belief_fuses_and_summarises() -> None:
    s = _world(0)
    robots = s.robot_ids
    model = belief_model(s)
    config = BeliefConfig(window=WINDOW)
    frames = Simulator(s, 0).all_frames()
    local = {r: HybridBelief(model, {r: s.robot(r).start}, config) for r in robots}
    d = DistributedBelief(model, "r1", s.robot("r1").start, config)
    full_d = DistributedBelief(model, "r1", s.robot("r1").start, BeliefConfig(window=None))
    rngs = {r: belief_rng(0, [r]) for r in robots}
    rng_d, rng_full = belief_rng(1, ["r1"]), belief_rng(1, ["r1"])
    for k in range(s.steps):
        for r in robots:
            local[r].step([frames[r][k]], rngs[r])
        d.step([frames["r1"][k]], rng_d)
        full_d.step([frames["r1"][k]], rng_full)
        summary = summarise(local["r2"])
        if summary is not None:
            slot = Slot("r2", k + 1, summary)
            d.integrate([slot])
            full_d.integrate([slot])
    assert d.versions["r2"] == (0, s.steps)
    assert sorted(d.object_ids) == sorted(full_d.object_ids)
    gap = np.abs(_object_positions(d) - _object_positions(full_d)).max()
    assert gap < 0.05  # measured 0.020 m (seed 0)
    assert summarise(d) is not None


def test_window_is_checked() -> None:
    with pytest.raises(ValueError, match="window"):
        BeliefConfig(window=0)
    with pytest.raises(ValueError, match="per_object"):
        BeliefConfig.joint(window=10)
    with pytest.raises(ValueError, match="window"):
        WindowedISAM2(gtsam.ISAM2Params(), 0)
    smoother = WindowedISAM2(gtsam.ISAM2Params(), 5)
    graph = gtsam.NonlinearFactorGraph()
    unit = gtsam.noiseModel.Unit.Create(3)
    graph.add(gtsam.PriorFactorPose2(pose_key(0, 0), gtsam.Pose2(), unit))
    values = gtsam.Values()
    values.insert(pose_key(0, 0), gtsam.Pose2())
    assert smoother.update(graph, values).getNewFactorsIndices() == [0]
    with pytest.raises(ValueError, match=r"factors \[7\] are not held"):
        smoother.update(remove=[7])


def test_the_ledger_retires_what_it_is_told_and_keeps_the_rest() -> None:
    s = _world(0, steps=10)
    model = belief_model(s).classifier
    ledger = SemanticLedger()
    assert ledger.robot_key_array().size == 0
    ledger.retire(np.zeros(0, dtype=bool))  # an empty ledger has nothing to retire
    rng = np.random.default_rng(3)
    for i in range(6):
        ledger.add(pose_key(0, i), i % 3, rng.random(model.dim))
    estimate = gtsam.Values()
    for i in range(6):
        estimate.insert(pose_key(0, i), gtsam.Pose2(i, 0.5 * i, 0.1 * i))
    for j in range(3):
        estimate.insert(object_key(j), gtsam.Pose2(2.0 + j, 1.0, 0.3 * j))
    index = {0: 0, 1: 1, 2: 2}
    ledger.refresh(estimate, model, index)
    keep = np.array([False, True, False, True, True, True])
    ledger.retire(keep)
    assert ledger.robot_keys == [pose_key(0, i) for i in (1, 3, 4, 5)]
    assert ledger.object_ids == [1, 0, 1, 2]
    psi = ledger.psi.copy()
    expected = all_log_likelihoods(model, np.stack(ledger.scores), psi[None, :])[0]
    np.testing.assert_allclose(ledger.applied, expected)
    # Nothing moved: a refresh of the kept detections changes nothing.
    assert not ledger.refresh(estimate, model, index).any()
    ledger.add(pose_key(0, 6), 0, rng.random(model.dim))
    with pytest.raises(ValueError, match="reference"):
        ledger.retire(np.array([True, True, True, True, False]))


def test_a_windowed_snapshot_reads_each_objects_covariance_from_one_joint_marginal() -> None:
    s = _world(1)
    windowed, _ = _run(s, 1, BeliefConfig(window=WINDOW))
    cont = windowed.hypotheses[0].continuous
    assert isinstance(cont.isam, WindowedISAM2) and cont.isam.rebuilds > 0
    keys = [object_key(j) for j in windowed.object_ids]
    one_by_one = np.array([cont.isam.marginalCovariance(k) for k in keys])
    np.testing.assert_allclose(marginal_covariances(cont.isam, keys), one_by_one, atol=1e-12)
    np.testing.assert_allclose(windowed.snapshot("r1").object_cov[0], one_by_one, atol=1e-12)
    assert marginal_covariances(cont.isam, []).shape == (0, 3, 3)


def test_per_object_beliefs_keep_a_window_by_default_and_joint_ones_every_pose() -> None:
    assert BeliefConfig().window == POSE_WINDOW
    for joint in (BeliefConfig.joint(), BeliefConfig.paper(), BeliefConfig.exact()):
        assert joint.window is None
    assert BeliefConfig(classes="joint").window is None
    assert BeliefConfig(classes="joint", semantic_poses=True).window is None
    with pytest.raises(ValueError, match="joint classes keep every pose"):
        BeliefConfig(classes="joint", window=50)
    with pytest.raises(ValueError, match="window_marginal 'exact'"):
        BeliefConfig(window_marginal="exact")


def test_a_copied_windowed_belief_steps_on_its_own() -> None:
    s = _world(2)
    belief, _ = _run(s, 2, BeliefConfig(window=WINDOW))
    cont = belief.hypotheses[0].continuous
    twin = cont.copy()
    assert isinstance(twin.isam, WindowedISAM2) and twin.isam is not cont.isam
    assert (twin.isam.oldest_kept(), twin.isam.rebuilds) == (
        cont.isam.oldest_kept(),
        cont.isam.rebuilds,
    )
    key = object_key(belief.object_ids[0])
    before = cont.isam.calculateEstimatePose2(key)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        gtsam.PriorFactorPose2(key, gtsam.Pose2(50.0, 50.0, 0.0), gtsam.noiseModel.Unit.Create(3))
    )
    twin.isam.update(graph)
    moved = twin.isam.calculateEstimatePose2(key)
    assert np.hypot(moved.x() - before.x(), moved.y() - before.y()) > 1.0
    assert cont.isam.calculateEstimatePose2(key).equals(before, 1e-12)


def test_a_windowed_belief_replays_bit_for_bit() -> None:
    """An agent rolls a failed step back by replaying its journal into fresh beliefs: the
    rebuilds and their root-shifted marginals must come out the same every time."""
    s = _world(3)
    first, first_classes = _run(s, 3, BeliefConfig(window=WINDOW))
    again, again_classes = _run(s, 3, BeliefConfig(window=WINDOW))
    assert first.hypotheses[0].continuous.isam.rebuilds > 1
    for a, b in zip(first_classes, again_classes, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(_object_positions(first), _object_positions(again))


def test_a_windowed_belief_refuses_a_robot_a_window_behind_the_others() -> None:
    # The window marginalises every pose older than the newest step less a window: a robot that
    # far behind would lose the pose its next frame continues, and iSAM2 would fail on a missing
    # key some steps later. The belief says so at the step that would leave it behind.
    s = _world(0)
    model = belief_model(s)
    frames = Simulator(s, 0).all_frames()
    lead, lag = s.robot_ids[:2]
    belief = HybridBelief(
        model, {r: s.robot(r).start for r in (lead, lag)}, BeliefConfig(window=WINDOW)
    )
    rng = belief_rng(0, [lead, lag])
    for k in range(WINDOW):
        belief.step([frames[lead][k]], rng)
    with pytest.raises(ValueError, match=rf"{lag!r} would be {WINDOW + 1} steps behind {lead!r}"):
        belief.step([frames[lead][WINDOW]], rng)
    assert belief.step_of[lead] == WINDOW  # refused before anything changed
    belief.step([frames[lead][WINDOW], frames[lag][0]], rng)  # the laggard catches up: fine
    free = HybridBelief(
        model, {r: s.robot(r).start for r in (lead, lag)}, BeliefConfig(window=None)
    )
    for k in range(WINDOW + 2):
        free.step([frames[lead][k]], rng)  # without a window every pose stays: no bound
