"""D is never left without a peer's information: an empty join rebuilds D from L and the held
slots (issue 10)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agents.node import RobotNode
from deploy.base.build import belief_model, belief_rng
from estimator.distributed import DistributedBelief
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.slots import summarise
from estimator.summary import LocalSummary
from protocol.stack import Slot, Stack
from sim.loader import parse_scenario
from sim.sensors import Simulator
from tests.estimator.scenarios import fleet_text

STEPS = 6
# r1 at y = 0 and r2 at y = 2 both see object 1 (between them) and one object of their own.
SCENARIO = parse_scenario(
    fleet_text(
        "pair",
        STEPS,
        [0.0, 2.0],
        [(2.5, 1.0, -1.1, 1), (3.0, -1.0, 2.0, 2), (3.0, 3.0, -2.0, 1)],
        sensing=5.0,
    ).replace("prior = [0.5, 0.5]", "prior = [0.7, 0.3]"),
    "pair.toml",
)
CONFIG = BeliefConfig.paper(relinearize_skip=1, partial_relinearization=False)
SHARED = 1


def _local(robot: str, seed: int, frames: dict) -> HybridBelief:
    s = SCENARIO
    belief = HybridBelief(belief_model(s), {robot: s.robot(robot).start}, CONFIG)
    rng = belief_rng(seed, [robot])
    for f in frames[robot]:
        belief.step([f], rng)
    return belief


def _node(seed: int, config: BeliefConfig) -> RobotNode:
    """r1's node, its L and D drawing from the seeded streams of the study."""
    start, model = SCENARIO.robot("r1").start, belief_model(SCENARIO)
    return RobotNode("r1", start, model, belief_rng(seed, ["r1"]), belief_rng(seed, ["r1"]), config)


def _shifted(summary: LocalSummary, cls: int, delta: float) -> LocalSummary:
    """``summary`` with log φ of the realisations giving object SHARED class ``cls`` moved by
    ``delta``; with ``delta = -inf`` those realisations are left out."""
    col = summary.object_ids.index(SHARED)
    out = []
    for r in summary.realisations:
        if r.classes[col] == cls:
            if np.isinf(delta):
                continue
            r = dataclasses.replace(r, log_phi=r.log_phi + delta)
        out.append(r)
    return LocalSummary(summary.object_ids, tuple(out))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_empty_join_is_counted_and_d_equals_the_rebuild_from_l_and_held_slots(seed: int) -> None:
    s = SCENARIO
    frames = Simulator(s, seed).all_frames()
    summary = summarise(_local("r2", seed, frames))
    assert summary is not None and SHARED in summary.object_ids
    node = _node(seed, CONFIG)
    for f in frames["r1"][:-1]:
        node.on_frame(f)
    assert {0, 1} <= {h.classes[node.local.object_ids.index(SHARED)] for h in node.local.hypotheses}
    # v1 makes D drop class 1 of the shared object; v2 (its owner changed its mind) has only it.
    v1 = _shifted(_shifted(summary, 1, -60.0), 0, 0.0)
    v2 = _shifted(summary, 0, -np.inf)
    node.stack = Stack().with_slot(Slot("r2", 1, v1))
    first = node.integrate_pending()
    col = node.distributed.object_ids.index(SHARED)
    assert {h.classes[col] for h in node.distributed.hypotheses} == {0}
    assert first.empty_joins == first.rebuilds == 0
    node.stack = node.stack.with_slot(Slot("r2", 2, v2))
    stats = node.on_frame(frames["r1"][-1]).fusion
    assert (stats.empty_joins, stats.rebuilds) == (1, 1)
    assert (node.counters.empty_joins, node.counters.rebuilds) == (1, 1)
    assert node.distributed.stamps == {"r2": 2}

    # The reference: a D that never received anything equals L; it then integrates v2 alone.
    ref = DistributedBelief(belief_model(s), "r1", s.robot("r1").start, CONFIG)
    rng = belief_rng(seed, ["r1"])
    for f in frames["r1"]:
        ref.step([f], rng)
    ref.integrate([Slot("r2", 2, v2)])
    d = node.distributed
    assert d.object_ids == ref.object_ids
    got = {h.classes: h for h in d.hypotheses}
    want = {h.classes: h for h in ref.hypotheses}
    assert got.keys() == want.keys() and len(got) > 0
    for classes, h in want.items():
        g = got[classes]
        assert abs(g.log_weight - h.log_weight) < 1e-12
        for j in d.object_ids:
            key = object_key(j)
            np.testing.assert_allclose(g.pose(key), h.pose(key), atol=1e-9)
            np.testing.assert_allclose(
                g.isam.marginalCovariance(key), h.isam.marginalCovariance(key), atol=1e-9
            )
    assert node.distributed.step_of["r1"] == STEPS


@pytest.mark.parametrize("seed", [0, 1])
def test_a_rebuilt_d_keeps_re_linearising_the_semantic_evidence_of_l(seed: int) -> None:
    # With one continuous belief (the default) the weights re-linearise every detection's
    # evidence as the estimate moves (estimator.ledger): a rebuilt D must keep L's detections.
    s = SCENARIO
    config = BeliefConfig()
    frames = Simulator(s, seed).all_frames()
    node = _node(seed, config)
    for f in frames["r1"]:
        node.on_frame(f)
    node.rebuild()
    ledgers = [h.continuous.ledger for h in node.distributed.hypotheses]
    want = node.local.hypotheses[0].continuous.ledger
    assert want is not None and len(want.object_ids) > 0
    for got in ledgers:
        assert got is not None and got is not want  # a copy, not L's own
        assert got.object_ids == want.object_ids and got.robot_keys == want.robot_keys
        np.testing.assert_array_equal(got.applied, want.applied)
