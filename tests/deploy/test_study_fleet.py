"""The in-process fleet's per-step measures (deploy/study/fleet.py, ``FleetStats``): the clock
times what the fleet does and changes nothing of it, and every timed section is counted where
it belongs."""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable

import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng, link_model_for, make_nodes
from deploy.study.fleet import FleetStats, linked_pairs, run_fleet
from estimator.hybrid import BeliefConfig
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator

STEPS = 8


def _world() -> Scenario:
    # 6 robots in a 14 m square, 10 m range: several hops at times, every robot heard by some.
    return generate_scenario(6, 12, 3, seed=21, steps=STEPS, area=14.0)


def _run(
    gossip: str, clock: Callable[[], float] = time.perf_counter
) -> tuple[FleetStats, dict[str, tuple[object, ...]]]:
    s = _world()
    frames = Simulator(s, 3).all_frames()
    nodes = make_nodes(s, belief_model(s), BeliefConfig(), lambda r: belief_rng(3, [r]))
    stats = run_fleet(nodes, frames, link_model_for(s), STEPS, gossip=gossip, clock=clock)
    estimates: dict[str, tuple[object, ...]] = {}
    for r, node in nodes.items():
        snap = node.distributed.snapshot(r)
        estimates[r] = (
            snap.robot_pose,
            snap.object_ids,
            snap.object_pose,
            snap.object_cov,
            snap.weights,
        )
    return stats, estimates


def _ticks() -> Callable[[], float]:
    """A clock that moves one second at every reading: a timed section without readings
    inside lasts exactly 1 s."""
    counter = itertools.count()
    return lambda: float(next(counter))


@pytest.mark.parametrize("gossip", ["delta", "full"])
def test_run_fleet_clock_times_without_changing_the_fleet(gossip: str) -> None:
    wall, by_wall = _run(gossip)
    ticked, by_ticks = _run(gossip, _ticks())
    assert wall.delivered_bytes == ticked.delivered_bytes and wall.deliveries > 0
    assert wall.heard == ticked.heard
    for r, estimate in by_wall.items():
        for a, b in zip(estimate, by_ticks[r], strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b)), r


@pytest.mark.parametrize("gossip", ["delta", "full"])
def test_run_fleet_counts_each_timed_section_where_it_belongs(gossip: str) -> None:
    s = _world()
    stats, _ = _run(gossip, _ticks())
    robots = s.robot_ids
    shape = (STEPS, len(robots))
    heard = np.reshape(stats.heard, shape)
    # Every robot with a link at step k sends once (one section) and decodes every stack it
    # hears (one section each); D's fusion, L's step and D's step are one section each.
    frames = Simulator(s, 3).all_frames()
    links = link_model_for(s)
    senders = np.array(
        [[r in {a for a, _ in linked_pairs(robots, frames, links, k)} for r in robots]
         for k in range(1, STEPS + 1)]
    )  # fmt: skip
    assert heard.sum() == stats.deliveries > 0
    assert np.array_equal(np.reshape(stats.gossip_s, shape), senders + heard)
    digests = np.reshape(stats.digest_s, shape)
    assert np.all(digests == (1.0 if gossip == "delta" else 0.0))
    for phase in (stats.fusion_s, stats.local_s, stats.distributed_s):
        assert phase == [1.0] * len(robots) * STEPS


def test_linked_pairs_are_the_robots_in_range() -> None:
    s = _world()
    frames = Simulator(s, 3).all_frames()
    pairs = linked_pairs(s.robot_ids, frames, link_model_for(s), 4)
    pos = {r: frames[r][3].true_pose[:2] for r in s.robot_ids}
    expected = {
        (a, b)
        for a in s.robot_ids
        for b in s.robot_ids
        if a != b and math.dist(pos[a], pos[b]) <= (s.communication.range or 10.0)
    }
    assert set(pairs) == expected and len(pairs) == len(expected) > 0


def test_a_fleet_larger_than_a_stack_keeps_every_stack_within_the_wire() -> None:
    """70 robots in one another's range, more than a stack's 64 slots (docs/distributed.md,
    "How many robots a D holds"): every robot holds 63 peers' slots, every stack it sends is
    one a peer accepts, and D fuses what the stack holds."""
    s = generate_scenario(70, 24, 3, seed=4, steps=3, area=6.0, comm_range=20.0)
    frames = Simulator(s, 1).all_frames()
    nodes = make_nodes(s, belief_model(s), BeliefConfig(), lambda r: belief_rng(1, [r]))
    stats = run_fleet(nodes, frames, link_model_for(s), s.steps)
    cap = next(iter(nodes.values())).limits.max_slots
    assert cap == 64 and stats.deliveries > 0
    for r, node in nodes.items():
        c = node.counters
        assert c.invalid == c.own_slot_invalid == 0, r
        assert len(node.current_stack()) <= cap
        peers = {slot.owner for slot in node.stack} - {r}
        assert set(node.distributed.versions) == peers, r
    assert max(len(n.distributed.versions) for n in nodes.values()) == cap - 1
