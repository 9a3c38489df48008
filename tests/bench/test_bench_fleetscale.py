"""The fleet-scale benchmark's measures (bench/bench_fleetscale.py): the age of information,
the fitted slope and a small fleet's figures, checked on what they must find (never a time)."""

from __future__ import annotations

import numpy as np

from bench.bench_fleetscale import Point, aoi, costs, run_point, slope, world
from deploy.study.fleet import FleetStats


def _point(fused: np.ndarray, hops: np.ndarray, first: list[int]) -> Point:
    steps, n, _ = fused.shape
    empty = np.zeros((steps, n))
    return Point(n, 1.0, FleetStats(), empty, fused, hops, np.array(first), {}, 0, 0, 0.0)


def test_aoi_counts_the_steps_until_a_version_is_first_fused() -> None:
    # Robot 0's D holds robot 1's version k − 2 after step k; robot 1's D holds robot 0's
    # version 3 (its first: robot 0 knows no object before step 3) after step 4.
    fused = np.full((4, 2, 2), -1)
    fused[:, 0, 1] = [-1, -1, 1, 2]
    fused[:, 1, 0] = [-1, -1, -1, 3]
    hops = np.ones((4, 2, 2))
    hops[:, 1, 0] = 2.0  # from robot 1 to robot 0
    ages, by_hops, open_ = aoi(_point(fused, hops, [3, 1]))
    assert sorted(zip(ages.tolist(), by_hops.tolist(), strict=True)) == [
        (1, 1.0),  # robot 0's version 3, one hop to robot 1
        (2, 2.0),  # robot 1's versions 1 and 2, two hops to robot 0
        (2, 2.0),
    ]
    assert open_ == 3  # robot 1's versions 3 and 4 and robot 0's 4 are not fused by the end


def test_slope_is_the_exponent_of_a_power_law() -> None:
    sizes = [10, 25, 50, 100]
    b, per_robot = slope(sizes, [2.0 * n**1.5 for n in sizes])
    assert abs(b - 1.5) < 1e-9 and per_robot > 0
    b, per_robot = slope(sizes, [3.0 + 0.5 * n for n in sizes])
    assert abs(per_robot - 0.5) < 1e-9


def test_run_point_measures_every_robot_and_step_and_bounds_what_d_holds() -> None:
    s = world(6, seed=5, steps=8)
    full = run_point(s, 2)
    assert full.fused.shape == (8, 6, 6) and full.hops.shape == (8, 6, 6)
    assert len(full.stats.heard) == 8 * 6 == len(full.stats.gossip_s)
    assert sum(full.stats.heard) == full.stats.deliveries > 0
    assert full.sent.sum() == sum(full.stats.delivered_bytes)
    held = (full.fused >= 0).sum(axis=2)
    assert held.max() >= 2 and full.evicted == full.foreign == 0
    c = costs(full)
    assert c.heard > 0 and c.sent_kb > 0 and np.isfinite([c.local, c.d, c.gossip]).all()
    assert {"L robot", "D robot", "L object", "D object", "L objects", "D objects"} <= set(
        full.accuracy
    )
    # Room for one peer: no D ever fuses two, and the slots left out are counted.
    bound = run_point(s, 2, max_slots=2)
    assert (bound.fused >= 0).sum(axis=2).max() == 1
    assert bound.evicted + bound.foreign > 0
