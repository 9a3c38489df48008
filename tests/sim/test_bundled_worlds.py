"""The bundled test worlds `lanes` and `rendezvous` and their `short` variants: the geometry and
communication each was designed for (docs/scenarios.md, "The bundled test worlds")."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest

from estimator.models.classifier import viewpoint
from sim.loader import bundled_names, load_scenario
from sim.world import World
from tests.tolerance import assert_close

LANES = ("lanes", "lanes:short")
RENDEZVOUS = ("rendezvous", "rendezvous:short")
LANE_IDS = ("r1", "r2", "r3", "r4", "r5")
CHAIN = {("r1", "r2"), ("r2", "r3"), ("r3", "r4"), ("r4", "r5")}
# first step at which any two robots of the rendezvous worlds are within radio range
MEETING = {"rendezvous": 43, "rendezvous:short": 14}
MAX_NEW_OBJECTS_PER_STEP = 4


@pytest.fixture(scope="module", params=[*LANES, *RENDEZVOUS])
def any_world(request: pytest.FixtureRequest) -> tuple[str, World]:
    return request.param, World(load_scenario(request.param))


@pytest.fixture(scope="module", params=LANES)
def lanes(request: pytest.FixtureRequest) -> World:
    return World(load_scenario(request.param))


@pytest.fixture(scope="module", params=RENDEZVOUS)
def rendezvous(request: pytest.FixtureRequest) -> tuple[str, World]:
    return request.param, World(load_scenario(request.param))


def _link_steps(world: World) -> dict[int, set[tuple[str, str]]]:
    """Step k → the pairs that may talk at k, for the steps at which some pair may."""
    out = {}
    for k in range(1, world.scenario.steps + 1):
        if links := world.links(k):
            out[k] = links
    return out


def _connected(ids: tuple[str, ...], links: set[tuple[str, str]]) -> bool:
    reached, frontier = {ids[0]}, [ids[0]]
    while frontier:
        a = frontier.pop()
        for pair in links:
            if a in pair:
                b = pair[1] if pair[0] == a else pair[0]
                if b not in reached:
                    reached.add(b)
                    frontier.append(b)
    return reached == set(ids)


def test_bundled_names_list_the_test_worlds() -> None:
    assert {"lanes", "paper", "rendezvous"} <= set(bundled_names())


def test_bundled_worlds_short_variant_has_15_to_20_steps(any_world: tuple[str, World]) -> None:
    name, world = any_world
    steps = world.scenario.steps
    assert 15 <= steps <= 20 if name.endswith(":short") else 50 <= steps <= 60


def test_bundled_worlds_at_most_4_objects_first_seen_by_a_robot_in_one_step(
    any_world: tuple[str, World],
) -> None:
    _, world = any_world
    for r in world.scenario.robot_ids:
        seen = world.visibility[r]
        first = [
            int(np.flatnonzero(seen[:, j])[0]) for j in range(seen.shape[1]) if seen[:, j].any()
        ]
        busiest = max(Counter(first).values(), default=0)
        assert busiest <= MAX_NEW_OBJECTS_PER_STEP, (r, Counter(first))


def test_lanes_five_robots_three_aliased_classes_non_uniform_prior(lanes: World) -> None:
    s = lanes.scenario
    assert s.robot_ids == LANE_IDS
    assert s.num_classes == 3
    assert s.classifier.model == "aliased"
    assert all(a != c for c, a in enumerate(s.classifier.alias))
    assert len(set(s.class_prior)) > 1
    assert 12 <= len(s.objects) <= 16
    assert set(s.object_classes()) == {0, 1, 2}


def test_lanes_robots_drive_straight_lanes_5m_apart(lanes: World) -> None:
    traj = np.stack([lanes.trajectories[r] for r in LANE_IDS])  # (5, steps + 1, 3)
    assert_close(traj[:, :, 2], 0.0, what="headings")
    assert_close(traj[:, :, 1] - traj[:, :1, 1], 0.0, what="each robot stays in its lane")
    assert_close(np.diff(traj[:, :, 1], axis=0), 5.0, what="lane spacing")
    assert_close(np.diff(traj[:, :, 0], axis=0), 0.0, what="side by side")


def test_lanes_links_are_exactly_the_chain_of_neighbours_at_every_step(lanes: World) -> None:
    links = _link_steps(lanes)
    assert sorted(links) == list(range(1, lanes.scenario.steps + 1))
    for k, pairs in links.items():
        assert pairs == CHAIN, k


def test_lanes_neighbours_share_objects_seen_from_different_viewpoints(lanes: World) -> None:
    poses = lanes.object_poses
    for a, b in sorted(CHAIN):
        va, vb = lanes.visibility[a], lanes.visibility[b]
        shared = np.flatnonzero(va.any(axis=0) & vb.any(axis=0))
        assert len(shared) >= 1, (a, b)
        # the mean viewpoints (unit vectors) of the two robots differ by more than 45°
        spread = []
        for j in shared:
            mean_a, mean_b = (
                np.exp(
                    1j * viewpoint(lanes.trajectories[r][lanes.visibility[r][:, j]], poses[j])
                ).mean()
                for r in (a, b)
            )
            spread.append(abs(np.angle(mean_a / mean_b)))
        assert max(spread) > np.pi / 4, (a, b, spread)


def test_rendezvous_four_robots_two_or_three_classes(rendezvous: tuple[str, World]) -> None:
    _, world = rendezvous
    assert len(world.scenario.robots) == 4
    assert world.scenario.num_classes in (2, 3)
    assert world.scenario.communication.mode == "range"


def test_rendezvous_no_link_before_the_meeting_and_connected_at_the_end(
    rendezvous: tuple[str, World],
) -> None:
    name, world = rendezvous
    links = _link_steps(world)
    steps = world.scenario.steps
    assert min(links) == MEETING[name]
    assert steps - MEETING[name] + 1 <= 18, "the meeting is late in the run"
    assert _connected(world.scenario.robot_ids, links[steps])
    # once in range, the robots stay in range to the end
    for pair in set().union(*links.values()):
        ks = [k for k, pairs in links.items() if pair in pairs]
        assert ks == list(range(ks[0], steps + 1)), pair


def test_rendezvous_full_world_every_pair_in_range_at_the_last_step() -> None:
    world = World(load_scenario("rendezvous"))
    ids = world.scenario.robot_ids
    assert world.links(world.scenario.steps) == set(itertools.combinations(ids, 2))


def test_rendezvous_every_robot_sees_objects_before_the_meeting(
    rendezvous: tuple[str, World],
) -> None:
    name, world = rendezvous
    for r in world.scenario.robot_ids:
        assert world.known_objects(r, MEETING[name] - 1), r
