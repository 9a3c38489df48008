"""The distributed belief: exact fusion, no double counting under relay, order and idempotence,
and the downdate variants."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agents.links import Schedule
from deploy.base.build import belief_model, belief_rng
from deploy.study.fleet import make_nodes, run_fleet
from estimator.distributed import DistributedBelief
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief, Hypothesis
from estimator.metrics import world_position_cov
from estimator.models import GaussianNoise
from estimator.slots import summarise
from estimator.summary import Slot
from sim.generate import generate_scenario
from sim.loader import load_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator

# The fusion algebra is exact at a common linearisation point. iSAM2's default lazy relinearisation
# (relinearize_skip = 10, and the partial relinearisation check that skips subtrees) leaves
# iterates up to ~2 mm from that point whatever the fusion does, so the exactness tests check
# every variable at every update to test the fusion, not the iterate.
EXACT = BeliefConfig.joint(relinearize_skip=1, partial_relinearization=False)
NO_PRUNING = BeliefConfig.joint(
    prune_ratio=1e9,
    max_hypotheses=5000,
    robot_budget=None,
    relinearize_skip=1,
    partial_relinearization=False,
)


def _truncate(s: Scenario, steps: int) -> Scenario:
    robots = tuple(dataclasses.replace(r, actions=r.actions[:steps]) for r in s.robots)
    return dataclasses.replace(s, steps=steps, robots=robots)


def _scaled_noise(s: Scenario, scale: float = 0.1) -> Scenario:
    odometry = GaussianNoise(tuple(v * scale for v in s.odometry_noise.variances))  # type: ignore[arg-type]
    geometric = GaussianNoise(tuple(v * scale for v in s.geometric_noise.variances))  # type: ignore[arg-type]
    return dataclasses.replace(s, odometry_noise=odometry, geometric_noise=geometric)


def _near_linear_paper(steps: int) -> Scenario:
    s = load_scenario(
        "paper",
        overrides={
            "noise.odometry_var": [0.0003, 0.0003, 0.0001],
            "noise.geometric_var": [0.01, 0.01, 0.001],
        },
    )
    return _truncate(s, steps)


def _local(s: Scenario, robot: str, seed: int, frames: dict, config: BeliefConfig) -> HybridBelief:
    belief = HybridBelief(belief_model(s), {robot: s.robot(robot).start}, config)
    rng = belief_rng(seed, [robot])
    for f in frames[robot]:
        belief.step([f], rng)
    return belief


def _centralized(s: Scenario, seed: int, frames: dict, config: BeliefConfig) -> HybridBelief:
    robots = s.robot_ids
    belief = HybridBelief(belief_model(s), {r: s.robot(r).start for r in robots}, config)
    rng = belief_rng(seed, robots)
    for k in range(s.steps):
        belief.step([frames[r][k] for r in robots], rng)
    return belief


def _distributed(
    s: Scenario, robot: str, seed: int, frames: dict, config: BeliefConfig, **kw: str
) -> DistributedBelief:
    d = DistributedBelief(belief_model(s), robot, s.robot(robot).start, config, **kw)
    rng = belief_rng(seed, [robot])
    for f in frames[robot]:
        d.step([f], rng)
    return d


def _matching(belief: HybridBelief, classes_by_id: dict[int, int]) -> Hypothesis:
    """The hypothesis of ``belief`` that agrees with ``classes_by_id`` on every object."""
    for h in belief.hypotheses:
        if all(h.classes[i] == classes_by_id[j] for i, j in enumerate(belief.object_ids)):
            return h
    raise AssertionError("no hypothesis with the reference classes")


def _position_cov(h: Hypothesis, j: int) -> np.ndarray:
    key = object_key(j)
    return world_position_cov(h.pose(key), h.isam.marginalCovariance(key))


def test_fusing_every_latest_slot_reproduces_the_centralized_marginal() -> None:
    s = _near_linear_paper(30)
    seed = 1
    frames = Simulator(s, seed).all_frames()
    config = EXACT
    central = _centralized(s, seed, frames, config)
    d = _distributed(s, "r1", seed, frames, config)
    slots = [Slot(r, s.steps, summarise(_local(s, r, seed, frames, config))) for r in ("r2", "r3")]
    d.integrate(slots)
    assert sorted(d.object_ids) == sorted(central.object_ids)
    ref = central.map_hypothesis()
    classes = dict(zip(central.object_ids, ref.classes, strict=True))
    h = _matching(d, classes)
    for j in central.object_ids:
        key = object_key(j)
        assert np.hypot(*(h.pose(key)[:2] - ref.pose(key)[:2])) < 1e-3, j
        cd, cc = h.isam.marginalCovariance(key), ref.isam.marginalCovariance(key)
        np.testing.assert_allclose(np.diag(cd), np.diag(cc), rtol=0.02, err_msg=str(j))


def test_downdate_by_anti_factor_equals_removal() -> None:
    s = _near_linear_paper(24)
    seed = 2
    frames = Simulator(s, seed).all_frames()
    config = BeliefConfig.joint()
    early = _truncate(s, 16)
    early_frames = {r: fs[:16] for r, fs in frames.items()}
    v1 = Slot("r2", 16, summarise(_local(early, "r2", seed, early_frames, config)))
    v2 = Slot("r2", 24, summarise(_local(s, "r2", seed, frames, config)))
    results = []
    for downdate in ("remove", "anti"):
        d = _distributed(early, "r3", seed, early_frames, config, downdate=downdate)
        d.integrate([v1])
        d.integrate([v2])
        results.append(d)
    a, b = results
    assert [h.classes for h in a.hypotheses] == [h.classes for h in b.hypotheses]
    np.testing.assert_allclose(a.weights(), b.weights(), atol=1e-9)
    for ha, hb in zip(a.hypotheses, b.hypotheses, strict=True):
        for j in a.object_ids:
            np.testing.assert_allclose(ha.pose(object_key(j)), hb.pose(object_key(j)), atol=1e-6)
            np.testing.assert_allclose(
                _position_cov(ha, j), _position_cov(hb, j), rtol=1e-5, atol=1e-12
            )


def test_integration_order_does_not_matter_before_pruning() -> None:
    s = _truncate(load_scenario("paper"), 25)
    seed = 3
    frames = Simulator(s, seed).all_frames()
    slots = {
        r: Slot(r, 25, summarise(_local(s, r, seed, frames, NO_PRUNING))) for r in ("r2", "r3")
    }
    beliefs = []
    for order in (("r2", "r3"), ("r3", "r2")):
        d = _distributed(s, "r1", seed, frames, NO_PRUNING)
        d.integrate([slots[r] for r in order])
        beliefs.append(d)
    a, b = beliefs
    assert sorted(a.object_ids) == sorted(b.object_ids)
    assert len(a.hypotheses) == len(b.hypotheses)
    pa, pb = a.class_marginals(), b.class_marginals()
    for i, j in enumerate(a.object_ids):
        np.testing.assert_allclose(pa[i], pb[b.object_ids.index(j)], atol=1e-12)
    # Weights and classes are bookkeeping and agree to rounding; the poses are iSAM2 iterates whose
    # factor order differs, equal up to its relinearisation threshold (1e-3).
    ha, hb = a.map_hypothesis(), b.map_hypothesis()
    assert ha.classes == tuple(hb.classes[b.object_ids.index(j)] for j in a.object_ids)
    for j in a.object_ids:
        np.testing.assert_allclose(ha.pose(object_key(j)), hb.pose(object_key(j)), atol=1e-3)


def test_integrating_the_same_version_twice_changes_nothing() -> None:
    s = _truncate(load_scenario("paper"), 20)
    seed = 4
    frames = Simulator(s, seed).all_frames()
    slot = Slot("r3", 20, summarise(_local(s, "r3", seed, frames, BeliefConfig.joint())))
    d = _distributed(s, "r2", seed, frames, BeliefConfig.joint())
    first = d.integrate([slot])
    weights, ids = d.weights().copy(), list(d.object_ids)
    second = d.integrate([slot])
    assert first.integrated == ("r3",) and second.integrated == ()
    assert d.object_ids == ids
    np.testing.assert_array_equal(d.weights(), weights)
    assert not d.wants("r3", (0, 19)) and not d.wants("r2", (0, 99))
    assert d.wants("r3", (0, 21)) and d.wants("r3", (1, 1))  # a later epoch, lower stamp


def _min_cov_ratio(d: HybridBelief, central: HybridBelief) -> dict[int, float]:
    """Per object: the smallest eigenvalue of Σ_C^-½ Σ_D Σ_C^-½ (≥ 1 ⇔ D no more certain)."""
    ref = central.map_hypothesis()
    h = d.map_hypothesis()
    out = {}
    for j in d.object_ids:
        if j not in central.object_ids:
            continue
        cc, cd = _position_cov(ref, j), _position_cov(h, j)
        w = np.linalg.cholesky(np.linalg.inv(cc))
        out[j] = float(np.linalg.eigvalsh(w.T @ cd @ w)[0])
    return out


@pytest.mark.parametrize("topology", ["ring", "chain"])
def test_relayed_information_is_never_counted_twice(topology: str) -> None:
    # Near-linear regime (noise ×0.1), as for exact fusion: at nominal noise the ξ factors are
    # first order about their owners' linearisation points, which moves covariances by up to ~3 %
    # either way; double counting shrinks them by an order of magnitude.
    s = _scaled_noise(
        generate_scenario(robots=4, objects=10, classes=2, seed=7, steps=24, area=12.0)
    )
    seed = 5
    frames = Simulator(s, seed).all_frames()
    ids = s.robot_ids
    pairs = [(ids[i], ids[i + 1]) for i in range(3)] + (
        [(ids[3], ids[0])] if topology == "ring" else []
    )
    links = Schedule(tuple((1, s.steps, a, b) for a, b in pairs))
    model = belief_model(s)
    central = _centralized(s, seed, frames, BeliefConfig.joint())
    ratios = {}
    for fusion in ("consistent", "double_count"):
        nodes = make_nodes(s, model, BeliefConfig.joint(), lambda r: belief_rng(seed, [r]), fusion)
        run_fleet(nodes, frames, links, s.steps)
        ratios[fusion] = {r: _min_cov_ratio(n.distributed, central) for r, n in nodes.items()}
    for r, per_object in ratios["consistent"].items():
        assert per_object, r
        assert min(per_object.values()) >= 0.98, (r, per_object)
    overconfident = [
        v for per_object in ratios["double_count"].values() for v in per_object.values()
    ]
    assert np.median(overconfident) < 0.9, overconfident


def test_a_budgeted_distributed_belief_grows_its_budget_with_the_robots_it_holds() -> None:
    # BeliefConfig.robot_budget: D keeps at most budget × (1 + robots whose slots it holds).
    s = _truncate(load_scenario("paper"), 20)
    config = BeliefConfig.joint(robot_budget=3)
    nodes = make_nodes(s, belief_model(s), config, lambda r: belief_rng(4, [r]))
    frames = Simulator(s, 4).all_frames()
    most: dict[str, int] = {}

    def on_step(robot: str, k: int, node, fused_ms: float, ms: float) -> None:  # type: ignore[no-untyped-def]
        d = node.distributed
        assert d.information_sources() == 1 + len(d.stamps)
        assert len(d.hypotheses) <= 3 * d.information_sources()
        assert len(node.local.hypotheses) <= 3
        most[robot] = max(most.get(robot, 0), len(d.hypotheses))

    run_fleet(nodes, frames, Schedule(((1, 20, "r1", "r2"), (1, 20, "r2", "r3"))), 20, on_step)
    assert max(most.values()) > 3  # D outgrew a single robot's budget once it held slots


def test_a_fusion_builds_at_most_max_join_pairs_from_the_heaviest_hypotheses() -> None:
    """BeliefConfig.max_join bounds the (hypothesis, realisation) pairs a fusion builds for a
    slot before anything is built; the lightest hypotheses are left out first, so the most
    probable hypothesis is that of the unbounded fusion."""
    s = _truncate(load_scenario("paper"), 12)
    frames = Simulator(s, 2).all_frames()
    config = BeliefConfig.joint()
    slots = [Slot(r, s.steps, summarise(_local(s, r, 2, frames, config))) for r in ("r2", "r3")]
    fused = {}
    for most in (250_000, 20):
        d = _distributed(s, "r1", 2, frames, dataclasses.replace(config, max_join=most))
        stats = d.integrate(slots)
        classes = dict(zip(d.object_ids, d.map_hypothesis().classes, strict=True))
        fused[most] = (stats.candidates, classes)
    assert fused[20][0] <= 20 < fused[250_000][0]
    assert fused[20][1] == fused[250_000][1]
