"""The paper's reconstructed world (design doc §9) and the world's geometry helpers."""

from __future__ import annotations

import numpy as np
import pytest

from sim.loader import load_scenario
from sim.world import World, in_view, integrate
from tests.tolerance import assert_close


@pytest.fixture(scope="module")
def paper() -> World:
    return World(load_scenario("paper"))


def test_paper_first_observations_at_steps_1_3_1(paper: World) -> None:
    assert [paper.first_sighting(r) for r in ("r1", "r2", "r3")] == [1, 3, 1]


@pytest.mark.parametrize(
    ("robot", "k", "known"),
    [("r2", 15, [2, 4]), ("r3", 20, [2, 3, 4, 12]), ("r2", 25, [2, 3, 4, 11, 15])],
)
def test_paper_locally_known_objects(paper: World, robot: str, k: int, known: list[int]) -> None:
    assert paper.known_objects(robot, k) == known


def test_paper_r1_first_within_10m_of_r2_and_r3_at_step_13(paper: World) -> None:
    for other in ("r2", "r3"):
        within = [k for k in range(1, 61) if paper.distance("r1", other, k) <= 10.0]
        assert within[0] == 13, other


def test_paper_schedule_links(paper: World) -> None:
    assert paper.links(5) == set()
    assert paper.links(6) == {("r2", "r3")}
    assert paper.links(12) == {("r2", "r3")}
    assert paper.links(13) == {("r1", "r2"), ("r1", "r3"), ("r2", "r3")}
    assert paper.links(60) == paper.links(13)


def test_paper_comm10_variant_links_r1_from_step_13() -> None:
    world = World(load_scenario("paper", ["comm10"]))
    joined = [k for k in range(1, 61) if ("r1", "r2") in world.links(k)]
    assert joined[0] == 13


def test_paper_sense10_variant_sees_more_objects(paper: World) -> None:
    wide = World(load_scenario("paper:sense10"))
    for r in ("r1", "r2", "r3"):
        assert set(paper.known_objects(r, 60)) <= set(wide.known_objects(r, 60))
    assert len(wide.known_objects("r2", 15)) > len(paper.known_objects("r2", 15))


def test_integrate_constant_turn_closes_a_circle() -> None:
    n = 40
    actions = np.tile([0.25, 0.0, 2 * np.pi / n], (n, 1))
    poses = integrate(np.array([1.0, 2.0, 0.3]), actions)
    assert poses.shape == (n + 1, 3)
    assert_close(poses[-1, :2], [1.0, 2.0], atol=1e-9)


def test_in_view_range_and_bearing_limits() -> None:
    pose = np.array([0.0, 0.0, np.pi / 2])
    pts = np.array([[0.0, 3.0], [0.0, 3.6], [3.0, 0.0], [-2.0, 2.1], [-2.0, 1.9]])
    # straight ahead, too far, 90° off, just inside 45°... (bearing 43.6°), just outside (46.5°)
    assert in_view(pose, pts, np.radians(45.0), 3.5).tolist() == [True, False, False, True, False]


def test_visibility_row_zero_is_empty(paper: World) -> None:
    for r in ("r1", "r2", "r3"):
        assert not paper.visibility[r][0].any()
