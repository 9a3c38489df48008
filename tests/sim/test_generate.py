"""Random world generator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.generate import generate_scenario
from sim.sensors import Simulator
from sim.world import World


def test_generate_scenario_is_reproducible_per_seed() -> None:
    a = generate_scenario(robots=3, objects=20, classes=4, seed=9)
    b = generate_scenario(robots=3, objects=20, classes=4, seed=9)
    c = generate_scenario(robots=3, objects=20, classes=4, seed=10)
    assert a == b
    assert a.objects != c.objects


@pytest.mark.parametrize(("robots", "objects", "classes"), [(1, 1, 2), (5, 100, 3), (10, 300, 6)])
def test_generate_scenario_sizes_and_bounds(robots: int, objects: int, classes: int) -> None:
    s = generate_scenario(robots=robots, objects=objects, classes=classes, seed=1, steps=80)
    assert (len(s.robots), len(s.objects), s.num_classes) == (robots, objects, classes)
    assert all(0 <= o.class_index < classes for o in s.objects)
    assert len(set(s.object_ids)) == objects and len(set(s.robot_ids)) == robots
    half = max(12.0, 4.0 * np.sqrt(objects)) / 2
    world = World(s)
    for traj in world.trajectories.values():
        assert traj.shape == (81, 3)
        # robots steer back near the border, so they never stray far outside the square
        assert np.max(np.abs(traj[:, :2])) < half + 2.0
    model = s.classifier.build()
    assert model.num_classes == classes


def test_generated_world_produces_detections() -> None:
    s = generate_scenario(robots=4, objects=60, classes=3, seed=2)
    frames = Simulator(s, 0).all_frames()
    assert sum(len(f.detections) for fs in frames.values() for f in fs) > 50


def test_generate_scenario_rejects_bad_sizes() -> None:
    with pytest.raises(ValueError):
        generate_scenario(robots=0, objects=5, classes=2, seed=0)
    with pytest.raises(ValueError):
        generate_scenario(robots=2, objects=5, classes=1, seed=0)


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_twins_are_near_of_another_class_and_leave_the_world_as_it_was(kind: str) -> None:
    base = generate_scenario(3, 12, 4, seed=8, steps=30, area=15.0, kind=kind)
    twinned = generate_scenario(3, 12, 4, seed=8, steps=30, area=15.0, kind=kind, twins=0.3)
    assert twinned.objects[:12] == base.objects and twinned.robots == base.robots
    assert twinned.classifier == base.classifier
    for o, t in zip(base.objects, twinned.objects[12:], strict=True):
        assert t.id == o.id + 12 and t.class_index != o.class_index
        assert math.dist(o.pose[:2], t.pose[:2]) == pytest.approx(0.3)
        if kind == "pose":
            assert 0 < abs(t.pose[2] - o.pose[2]) <= 0.1 or abs(t.pose[2] - o.pose[2]) > 6.1
        else:
            assert t.pose[2] == 0.0
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="twins"):
            generate_scenario(1, 2, 2, seed=1, twins=bad)
