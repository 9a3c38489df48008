"""Per-object class beliefs (``BeliefConfig.classes = "per_object"``, issue 40 items 1–2): against
exact enumeration of the joint realisations, per-object fusion against the centralized belief,
versioned down-dating of a slot's class log φ, and the slot summary.

Every world has a non-uniform class prior (a dropped or doubled P(c) shows), several seeds and
2–4 classes. Tolerances are measured maxima with a margin; each constant says what was measured.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng
from estimator.distributed import DistributedBelief, SlotError
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.models import SensorFrame
from estimator.slots import PHI_FLOOR, summarise
from estimator.summary import LocalSummary, ObjectClasses, Slot
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.exact_worlds import (
    NEAR_LINEAR,
    PRIORS,
    centralized_belief,
    distributed_belief,
    local_slot,
    no_pruning,
    prior_world,
)
from tests.tolerance import assert_close

PER_OBJECT = BeliefConfig(classes="per_object")

# (classes, objects, world seed): generated 2-robot worlds in an 8 m square, r1's belief over 40
# steps. Measured max |ΔP| against exact enumeration over these × seeds 0–1: 0.0034 (M = 2,
# world 1, seed 1), every other case ≤ 0.0009. The bar for dropping same-step coupling is
# 0.005.
EXACT_WORLDS = [(2, 6, 1), (3, 5, 2), (4, 4, 3), (2, 8, 4), (3, 6, 5)]
EXACT_TOL = 0.005


def _skewed(s: Scenario) -> Scenario:
    """``s`` with a non-uniform class prior (1 : … : 2)."""
    prior = np.linspace(1.0, 2.0, s.num_classes)
    return dataclasses.replace(s, class_prior=tuple(prior / prior.sum()))


@functools.cache
def _generated(m: int, objects: int, world: int) -> Scenario:
    return _skewed(generate_scenario(2, objects, m, world, steps=40, area=8.0))


def _run_local(
    s: Scenario, seed: int, config: BeliefConfig, robot: str = "r1"
) -> list[tuple[list[int], np.ndarray]]:
    belief = HybridBelief(belief_model(s), {robot: s.robot(robot).start}, config)
    rng = belief_rng(seed, [robot])
    out = []
    for f in Simulator(s, seed).all_frames()[robot]:
        belief.step([f], rng)
        out.append((list(belief.object_ids), belief.class_marginals().copy()))
    return out


@pytest.mark.parametrize(("m", "objects", "world"), EXACT_WORLDS)
@pytest.mark.parametrize("seed", range(2))
def test_per_object_marginals_equal_exact_enumeration_at_every_step(
    m: int, objects: int, world: int, seed: int
) -> None:
    s = _generated(m, objects, world)
    exact = _run_local(s, seed, no_pruning())
    ours = _run_local(s, seed, PER_OBJECT)
    worst = 0.0
    for k, ((ids_e, p_e), (ids_o, p_o)) in enumerate(zip(exact, ours, strict=True), start=1):
        assert ids_e == ids_o, f"step {k}: objects differ"
        if ids_e:
            assert_close(p_o.sum(axis=1), 1.0, atol=1e-12, what=f"step {k}: rows sum to 1")
            worst = max(worst, float(np.abs(p_e - p_o).max()))
    assert len(ours[-1][0]) >= 3, "the world must show a few objects"
    assert worst <= EXACT_TOL, f"max |ΔP| {worst:.4f} against exact enumeration"


def test_the_class_prior_enters_once() -> None:
    """Dropping or doubling the prior is seen: an object never detected has exactly the prior,
    and the posterior is softmax(log prior + L)."""
    s = _generated(3, 5, 2)
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, PER_OBJECT)
    rng = belief_rng(0, ["r1"])
    frames = Simulator(s, 0).all_frames()["r1"]
    for f in frames:
        belief.step([f], rng)
    log_post = np.log(np.asarray(s.class_prior))[None, :] + belief.log_evidence
    expected = np.exp(log_post - np.logaddexp.reduce(log_post, axis=1)[:, None])
    assert_close(belief.class_marginals(), expected, atol=1e-12)
    # Right after its first detection an object still shows the prior: a belief with a uniform
    # prior holds the same evidence and different marginals.
    first = next(k for k, f in enumerate(frames, start=1) if f.detections)
    beliefs = []
    for prior in (s.class_prior, tuple([1.0 / 3] * 3)):
        world = dataclasses.replace(s, class_prior=prior)
        b = HybridBelief(belief_model(world), {"r1": s.robot("r1").start}, PER_OBJECT)
        rng = belief_rng(0, ["r1"])
        for f in frames[:first]:
            b.step([f], rng)
        beliefs.append(b)
    assert_close(beliefs[0].log_evidence, beliefs[1].log_evidence, atol=1e-9)
    # log P0 − log P1 = log π0 − log π1 + a constant per object: the prior enters exactly once.
    ratio = np.log(beliefs[0].class_marginals()) - np.log(beliefs[1].class_marginals())
    moved = ratio - (np.log(np.asarray(s.class_prior)) - np.log(1.0 / 3))[None, :]
    assert_close(moved - moved.mean(axis=1, keepdims=True), 0.0, atol=1e-9)
    assert np.ptp(ratio, axis=1).min() > 0.5  # and the two priors do differ in the posterior


def test_a_per_object_belief_has_one_hypothesis_with_its_map_classes() -> None:
    s = _generated(4, 4, 3)
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, PER_OBJECT)
    rng = belief_rng(1, ["r1"])
    for f in Simulator(s, 1).all_frames()["r1"]:
        belief.step([f], rng)
    assert len(belief.hypotheses) == 1
    p = belief.class_marginals()
    assert belief.hypotheses[0].classes == tuple(np.argmax(p, axis=1).tolist())
    snap = belief.snapshot("r1")
    assert snap.class_probs is not None
    assert_close(snap.marginals(4), p, atol=0.0)
    assert snap.classes.shape == (1, len(belief.object_ids))


def test_per_object_needs_one_continuous_belief() -> None:
    with pytest.raises(ValueError, match="semantic_poses"):
        BeliefConfig(classes="per_object", semantic_poses=True)
    with pytest.raises(ValueError, match="classes"):
        BeliefConfig(classes="joint-ish")


# -- the slot ---------------------------------------------------------------------------------


def test_the_slot_carries_the_class_evidence_shifted_per_object() -> None:
    s = _generated(3, 6, 5)
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, PER_OBJECT)
    rng = belief_rng(0, ["r1"])
    for f in Simulator(s, 0).all_frames()["r1"]:
        belief.step([f], rng)
    summary = summarise(belief)
    assert summary is not None and summary.kind == "per_object"
    assert summary.per_object is not None and summary.realisations == ()
    phi = summary.per_object.log_phi
    assert phi.shape == (len(belief.object_ids), 3)
    assert not phi.flags.writeable
    assert_close(phi.max(axis=1), 0.0, atol=0.0)
    assert phi.min() >= PHI_FLOOR
    # The shift leaves every object's posterior as it was.
    log_post = np.log(np.asarray(s.class_prior))[None, :] + phi
    p = np.exp(log_post - np.logaddexp.reduce(log_post, axis=1)[:, None])
    assert_close(p, belief.class_marginals(), atol=1e-12)
    xis, which = summary.distinct_xi()
    assert xis == [summary.per_object.xi] and which == []


# -- fusion -----------------------------------------------------------------------------------

DISJOINT_YS = (0.0, 8.0, 16.0)


def _disjoint_world(classes: str) -> Scenario:
    """Three robots on lanes 8 m apart, each with objects of its own ahead (seen by it alone)."""
    prior = PRIORS[classes]
    m = len(prior)
    yaws = (0.4, -1.2, 2.0, -2.6, 1.1, -0.3)
    objects = [
        (2.0 + 0.8 * j, y + (0.3 if j == 0 else -0.5), yaws[(2 * i + j) % 6], 1 + (i + j) % m)
        for i, y in enumerate(DISJOINT_YS)
        for j in range(2)
    ]
    return prior_world(DISJOINT_YS, objects, prior, steps=6, noise_scale=NEAR_LINEAR, speed=0.5)


# D of r1 with the other robots' final slots against the centralized belief, both per object.
# Objects seen by one robot each: the class evidence of an object is evaluated on its observer's
# geometry in both, with different Monte Carlo draws. Measured over 2 priors × 3 seeds: max |ΔP|
# 0.0014, on posteriors whose most probable class holds 0.45–0.80.
FUSION_TOL = 0.01


@pytest.mark.parametrize("classes", ["two", "three"])
@pytest.mark.parametrize("seed", range(3))
def test_per_object_fusion_equals_the_centralized_per_object_belief(
    classes: str, seed: int
) -> None:
    s = _disjoint_world(classes)
    frames = Simulator(s, seed).all_frames()
    config = no_pruning(classes="per_object")
    central = centralized_belief(s, seed, frames, config)
    d = distributed_belief(s, "r1", seed, frames, config)
    stats = d.integrate([local_slot(s, r, seed, frames, config) for r in ("r2", "r3")])
    assert stats.integrated == ("r2", "r3") and stats.empty_joins == 0
    assert sorted(d.object_ids) == sorted(central.object_ids)
    pc = dict(zip(central.object_ids, central.class_marginals(), strict=True))
    pd = dict(zip(d.object_ids, d.class_marginals(), strict=True))
    worst = max(float(np.abs(pd[j] - pc[j]).max()) for j in pc)
    assert worst <= FUSION_TOL, f"max |ΔP| {worst:.4f}"
    # Without the other robots' slots D must be far from C on their objects.
    alone = distributed_belief(s, "r1", seed, frames, config)
    assert set(alone.object_ids) < set(central.object_ids)


def _versions(s: Scenario, seed: int, frames: dict[str, list[SensorFrame]]) -> list[Slot]:
    """r2's slot after 2, 4 and 6 steps."""
    config = no_pruning(classes="per_object")
    return [local_slot(s, "r2", seed, frames, config, steps) for steps in (2, 4, 6)]


@pytest.mark.parametrize("seed", range(3))
def test_versions_replace_each_other_and_double_counting_adds_them(seed: int) -> None:
    s = _disjoint_world("three")
    frames = Simulator(s, seed).all_frames()
    config = no_pruning(classes="per_object")
    versions = _versions(s, seed, frames)
    consistent = distributed_belief(s, "r1", seed, frames, config)
    doubled = distributed_belief(s, "r1", seed, frames, config, fusion="double_count")
    once = distributed_belief(s, "r1", seed, frames, config)
    for v in versions:
        consistent.integrate([v])
        doubled.integrate([v])
    once.integrate([versions[-1]])
    assert consistent.versions["r2"] == versions[-1].version
    # own + newest, to rounding: the older versions are divided out.
    assert_close(consistent.class_log_posterior(), once.class_log_posterior(), atol=1e-12)
    # Double counting holds the sum of the three versions.
    newest = versions[-1].summary
    assert newest.per_object is not None
    rows = [doubled.object_ids.index(j) for j in newest.object_ids]
    total = np.zeros_like(doubled.log_evidence)
    for v in versions:
        assert v.summary.per_object is not None
        for i, j in enumerate(v.summary.object_ids):
            total[doubled.object_ids.index(j)] += v.summary.per_object.log_phi[i]
    log_prior = np.log(np.asarray(s.class_prior))
    assert_close(
        doubled.class_log_posterior()[rows],
        (log_prior + doubled.log_evidence + total)[rows],
        atol=1e-9,
    )
    gap = np.abs(doubled.class_marginals() - consistent.class_marginals()).max()
    assert gap > 0.01, "double counting must differ from consistent fusion"


def test_an_old_version_is_not_integrated_again() -> None:
    s = _disjoint_world("two")
    frames = Simulator(s, 0).all_frames()
    versions = _versions(s, 0, frames)
    d = distributed_belief(s, "r1", 0, frames, no_pruning(classes="per_object"))
    d.integrate([versions[2]])
    before = d.class_log_posterior()
    assert d.integrate([versions[0]]).integrated == ()
    assert_close(d.class_log_posterior(), before, atol=0.0)


def test_a_slot_of_the_other_kind_is_refused() -> None:
    s = _disjoint_world("two")
    frames = Simulator(s, 0).all_frames()
    joint = local_slot(s, "r2", 0, frames, no_pruning())
    per_object = local_slot(s, "r2", 0, frames, no_pruning(classes="per_object"))
    d = distributed_belief(s, "r1", 0, frames, no_pruning(classes="per_object"))
    with pytest.raises(SlotError, match="classes 'table'"):
        d.integrate([joint])
    table_d = distributed_belief(s, "r1", 0, frames, no_pruning())
    with pytest.raises(SlotError, match="classes 'per_object'"):
        table_d.integrate([per_object])


def test_a_slot_whose_class_evidence_does_not_fit_is_refused() -> None:
    s = _disjoint_world("two")
    frames = Simulator(s, 0).all_frames()
    slot = local_slot(s, "r2", 0, frames, no_pruning(classes="per_object"))
    po = slot.summary.per_object
    assert po is not None
    d = distributed_belief(s, "r1", 0, frames, no_pruning(classes="per_object"))
    for bad in (po.log_phi[:, :1], np.full_like(po.log_phi, np.nan)):
        summary = LocalSummary(slot.summary.object_ids, (), ObjectClasses(bad, po.xi))
        with pytest.raises(SlotError, match="class log φ"):
            d.integrate([Slot("r2", slot.stamp, summary)])
    assert d.versions == {}


def test_a_rebuilt_per_object_belief_equals_one_that_integrated_the_same_slots() -> None:
    s = _disjoint_world("three")
    frames = Simulator(s, 1).all_frames()
    config = no_pruning(classes="per_object")
    slots = [local_slot(s, r, 1, frames, config) for r in ("r2", "r3")]
    d = distributed_belief(s, "r1", 1, frames, config)
    d.integrate(slots)
    rebuilt = distributed_belief(s, "r1", 1, frames, config)
    local = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, config)
    rng = belief_rng(1, ["r1"])
    for f in frames["r1"]:
        local.step([f], rng)
    stats = rebuilt.rebuild(local, slots)
    assert stats.rebuilds == 1
    assert rebuilt.object_ids == d.object_ids
    assert_close(rebuilt.class_log_posterior(), d.class_log_posterior(), atol=1e-9)


def test_distributed_belief_type_is_the_one_tested() -> None:
    assert issubclass(DistributedBelief, HybridBelief)
