"""Link models (proximity, schedule, seeded random loss, conjunction) and the scenario's
communication as a link model, against the ground-truth world."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from agents.links import AllOf, Proximity, RandomDrop, Schedule
from deploy.study.fleet import link_model_for
from sim.loader import load_scenario
from sim.scenario import Scenario
from sim.world import World

ORIGIN = (0.0, 0.0)
ROBOTS = ("r1", "r2", "r3")
PAIRS = [(a, b) for a, b in itertools.permutations(ROBOTS, 2)]


class _Fixed:
    """A link model with a fixed answer, to test the conjunction on its own."""

    def __init__(self, answer: bool) -> None:
        self.answer = answer

    def allowed(self, sender, receiver, k, sender_pos, receiver_pos) -> bool:
        return self.answer


# -- Proximity ---------------------------------------------------------------------------------


def test_proximity_allows_up_to_range_inclusive() -> None:
    link = Proximity(10.0)
    assert link.allowed("r1", "r2", 1, ORIGIN, (6.0, 8.0))  # exactly 10 m
    assert link.allowed("r1", "r2", 1, ORIGIN, (3.0, 4.0))
    assert link.allowed("r1", "r2", 1, (1.0, 1.0), (1.0, 1.0))


def test_proximity_excludes_beyond_range() -> None:
    link = Proximity(10.0)
    assert not link.allowed("r1", "r2", 1, ORIGIN, (6.0, 8.0 + 1e-9))
    assert not link.allowed("r1", "r2", 1, ORIGIN, (0.0, -10.5))


def test_proximity_ignores_heading_component() -> None:
    link = Proximity(5.0)
    assert link.allowed("r1", "r2", 1, (0.0, 0.0, 3.0), (3.0, 4.0, -2.0))


def test_proximity_is_symmetric() -> None:
    rng = np.random.default_rng(7)
    link = Proximity(4.0)
    for _ in range(200):
        a, b = rng.uniform(-5.0, 5.0, size=(2, 2))
        assert link.allowed("r1", "r2", 3, a, b) == link.allowed("r2", "r1", 3, b, a)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_proximity_rejects_non_positive_range(bad: float) -> None:
    with pytest.raises(ValueError, match="range"):
        Proximity(bad)


# -- Schedule ----------------------------------------------------------------------------------


def test_schedule_step_bounds_are_inclusive() -> None:
    link = Schedule(((5, 8, "r1", "r2"),))
    allowed = [k for k in range(0, 12) if link.allowed("r1", "r2", k, ORIGIN, ORIGIN)]
    assert allowed == [5, 6, 7, 8]


def test_schedule_edges_are_undirected() -> None:
    link = Schedule(((1, 3, "r2", "r1"),))
    for k in range(1, 4):
        assert link.allowed("r1", "r2", k, ORIGIN, ORIGIN)
        assert link.allowed("r2", "r1", k, ORIGIN, ORIGIN)


def test_schedule_allows_only_listed_pairs() -> None:
    link = Schedule(((1, 10, "r1", "r2"), (4, 6, "r2", "r3")))
    for k in range(1, 11):
        got = {(a, b) for a, b in PAIRS if link.allowed(a, b, k, ORIGIN, ORIGIN)}
        expected = {("r1", "r2"), ("r2", "r1")}
        if 4 <= k <= 6:
            expected |= {("r2", "r3"), ("r3", "r2")}
        assert got == expected, k
    assert not link.allowed("r1", "r1", 2, ORIGIN, ORIGIN)


def test_schedule_ignores_positions() -> None:
    link = Schedule(((1, 1, "r1", "r2"),))
    assert link.allowed("r1", "r2", 1, ORIGIN, (1e6, -1e6))


def test_schedule_empty_allows_nothing() -> None:
    link = Schedule(())
    assert not any(link.allowed(a, b, k, ORIGIN, ORIGIN) for a, b in PAIRS for k in range(5))


# -- RandomDrop --------------------------------------------------------------------------------


def _draws(link: RandomDrop, steps: range) -> list[bool]:
    return [link.allowed(a, b, k, ORIGIN, ORIGIN) for k in steps for a, b in PAIRS]


def test_random_drop_p0_never_drops() -> None:
    assert all(_draws(RandomDrop(0.0, 11), range(1, 301)))


def test_random_drop_p1_always_drops() -> None:
    assert not any(_draws(RandomDrop(1.0, 11), range(1, 301)))


@pytest.mark.parametrize("p", [0.1, 0.5, 0.85])
def test_random_drop_empirical_rate_matches_p(p: float) -> None:
    draws = np.array(_draws(RandomDrop(p, 2024), range(1, 1001)))
    n = len(draws)
    dropped = 1.0 - draws.mean()
    stderr = math.sqrt(p * (1.0 - p) / n)
    assert abs(dropped - p) < 5.0 * stderr, (dropped, p, n)


def test_random_drop_is_deterministic_and_order_independent() -> None:
    link = RandomDrop(0.4, 99)
    keys = [(a, b, k) for k in range(1, 41) for a, b in PAIRS]
    forward = {key: link.allowed(key[0], key[1], key[2], ORIGIN, ORIGIN) for key in keys}
    order = np.random.default_rng(5).permutation(len(keys))
    fresh = RandomDrop(0.4, 99)
    shuffled = {}
    for i in order:
        a, b, k = keys[i]
        shuffled[keys[i]] = fresh.allowed(a, b, k, (3.0, 1.0), (-2.0, 7.0))
    assert shuffled == forward
    assert 0 < sum(forward.values()) < len(keys)


def test_random_drop_directions_are_independent_draws() -> None:
    link = RandomDrop(0.5, 3)
    fwd = [link.allowed("r1", "r2", k, ORIGIN, ORIGIN) for k in range(1, 201)]
    back = [link.allowed("r2", "r1", k, ORIGIN, ORIGIN) for k in range(1, 201)]
    assert fwd != back


def test_random_drop_different_seeds_differ() -> None:
    steps = range(1, 201)
    assert _draws(RandomDrop(0.5, 1), steps) != _draws(RandomDrop(0.5, 2), steps)


@pytest.mark.parametrize("bad", [-0.01, 1.01, math.nan])
def test_random_drop_rejects_p_outside_unit_interval(bad: float) -> None:
    with pytest.raises(ValueError, match="probability"):
        RandomDrop(bad, 0)


# -- AllOf -------------------------------------------------------------------------------------


@pytest.mark.parametrize("answers", list(itertools.product([False, True], repeat=3)))
def test_all_of_is_the_conjunction(answers: tuple[bool, ...]) -> None:
    link = AllOf(tuple(_Fixed(a) for a in answers))
    assert link.allowed("r1", "r2", 1, ORIGIN, ORIGIN) == all(answers)


def test_all_of_combines_schedule_and_range() -> None:
    link = AllOf((Schedule(((1, 5, "r1", "r2"),)), Proximity(2.0)))
    assert link.allowed("r1", "r2", 3, ORIGIN, (1.0, 1.0))
    assert not link.allowed("r1", "r2", 3, ORIGIN, (3.0, 0.0))  # out of range
    assert not link.allowed("r1", "r2", 6, ORIGIN, (1.0, 1.0))  # out of schedule
    assert not link.allowed("r1", "r3", 3, ORIGIN, (1.0, 1.0))  # not listed


def test_all_of_empty_allows_everything() -> None:
    assert AllOf(()).allowed("r1", "r2", 1, ORIGIN, (1e9, 0.0))


# -- the scenario's communication ----------------------------------------------------------------


def _allowed_pairs(s: Scenario, link, world: World, k: int) -> set[tuple[str, str]]:
    """Pairs (a, b), a before b in scenario order, the link model allows at step k (both ways
    checked: a link model of the paper's world must be symmetric)."""
    traj = world.trajectories
    out = set()
    for a, b in itertools.combinations(s.robot_ids, 2):
        ab = link.allowed(a, b, k, traj[a][k], traj[b][k])
        ba = link.allowed(b, a, k, traj[b][k], traj[a][k])
        assert ab == ba, (a, b, k)
        if ab:
            out.add((a, b))
    return out


@pytest.mark.parametrize(
    ("comm", "world_source"),
    [(None, "paper"), ("schedule", "paper"), ("range", "paper:comm10")],
)
def test_link_model_for_paper_reproduces_world_links(comm: str | None, world_source: str) -> None:
    s = load_scenario("paper")
    link = link_model_for(s, comm)
    world = World(load_scenario(world_source))
    truth = World(s)
    seen = set()
    for k in range(1, s.steps + 1):
        got = _allowed_pairs(s, link, truth, k)
        assert got == world.links(k), k
        seen.add(frozenset(got))
    assert len(seen) > 1  # the links change over the run: the comparison is not vacuous


def test_link_model_for_paper_both_mode_reproduces_world_links() -> None:
    s = load_scenario("paper")
    world = World(load_scenario("paper", overrides={"communication.mode": "both"}))
    link = link_model_for(s, "both")
    truth = World(s)
    for k in range(1, s.steps + 1):
        assert _allowed_pairs(s, link, truth, k) == world.links(k), k


def test_link_model_for_drop_only_removes_links() -> None:
    s = load_scenario("paper")
    base = link_model_for(s)
    lossy = link_model_for(s, drop=0.5, seed=4)
    traj = World(s).trajectories
    kept = lost = 0
    for k in range(1, s.steps + 1):
        for a, b in itertools.permutations(s.robot_ids, 2):
            args = (a, b, k, traj[a][k], traj[b][k])
            if lossy.allowed(*args):
                assert base.allowed(*args)
                kept += 1
            elif base.allowed(*args):
                lost += 1
    assert kept > 0 and lost > 0
    assert not any(
        link_model_for(s, drop=1.0).allowed(a, b, k, traj[a][k], traj[b][k])
        for k in range(1, s.steps + 1)
        for a, b in itertools.permutations(s.robot_ids, 2)
    )


def test_link_model_for_rejects_unknown_mode() -> None:
    with pytest.raises(ValueError, match="communication mode"):
        link_model_for(load_scenario("paper"), "telepathy")
