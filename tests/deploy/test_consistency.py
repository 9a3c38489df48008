"""Consistency over Monte Carlo runs (issue 4): the distributed belief's ANEES lies inside the χ²
bounds, double counting's above. Twenty runs of the paper's first 30 steps here; the full
100-run, 60-step study runs in ``make bench``.

Double counting runs on the first eight of those seeds, against the χ² bounds of eight runs (which
are wider, so the claim is no weaker): its ANEES is far beyond them — measured on these seeds,
object ANEES 15.9 / 19.4 / 25.1 per robot against an upper bound of 3.6 on the first eight
(18.0 / 23.5 / 24.3 on all twenty), robot ANEES 8.1 on average against 4.9. The beliefs are
scored at the last step only, the one the assertions read."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from deploy.study.runner import run_study
from estimator.hybrid import BeliefConfig
from estimator.metrics import chi2_bounds
from sim.loader import load_scenario

RUNS = 20
DOUBLE_COUNT_RUNS = 8
STEPS = 30
# Two processes of its own when the test runs alone; one under pytest-xdist, whose other worker
# already keeps the second core busy (two more would only make every test of the suite wait).
JOBS = 1 if "PYTEST_XDIST_WORKER" in os.environ else 2


@pytest.mark.slow
def test_distributed_is_consistent_and_double_counting_is_not() -> None:
    s = load_scenario("paper")
    robots = tuple(dataclasses.replace(r, actions=r.actions[:STEPS]) for r in s.robots)
    s = dataclasses.replace(s, steps=STEPS, robots=robots)
    seeds = list(range(100, 100 + RUNS))
    results = {
        method: run_study(s, [method], seeds[:runs], BeliefConfig(), JOBS, None, scored={STEPS})
        for method, runs in (("distributed", RUNS), ("double_count", DOUBLE_COUNT_RUNS))
    }

    def anees(method: str, metric: str) -> np.ndarray:
        """Per robot, the mean over runs at the last step."""
        return np.nanmean([r.metrics[method][metric][:, -1] for r in results[method]], axis=0)

    lo3, hi3 = chi2_bounds(3, RUNS)
    lo2, hi2 = chi2_bounds(2, RUNS)
    robot = anees("distributed", "robot_nees")
    objects = anees("distributed", "object_nees")
    assert np.all((lo3 <= robot) & (robot <= hi3)), (robot, (lo3, hi3))
    assert np.all((lo2 <= objects) & (objects <= hi2)), (objects, (lo2, hi2))
    _, hi3 = chi2_bounds(3, DOUBLE_COUNT_RUNS)
    _, hi2 = chi2_bounds(2, DOUBLE_COUNT_RUNS)
    assert np.all(anees("double_count", "object_nees") > hi2), anees("double_count", "object_nees")
    assert np.mean(anees("double_count", "robot_nees")) > hi3
