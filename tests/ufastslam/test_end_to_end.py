"""Seeded end to end on `rectangle` (the paper's experiment 1): 20 seeds, 50 particles."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.study.ufastslam import dead_reckoning, filter_config, run_filter
from sim.ufastslam import load_world, simulate

SEEDS = range(20)
PARTICLES = 50


@pytest.mark.slow
def test_rectangle_semantic_beats_ufastslam_beats_dead_reckoning() -> None:
    world = load_world("rectangle")
    plain_cfg = filter_config(world, PARTICLES, "off")
    oracle_cfg = filter_config(world, PARTICLES, "labels")
    odometry, plain, semantic = [], [], []
    for seed in SEEDS:
        run = simulate(world, seed)
        odometry.append(dead_reckoning(world, run).pose_rmse)
        plain.append(run_filter(world, run, plain_cfg).pose_rmse)
        oracle = run_filter(world, run, oracle_cfg)
        assert oracle.relations_false == 0 and oracle.relations_true > 0
        semantic.append(oracle.pose_rmse)
    odometry_a, plain_a, semantic_a = np.array(odometry), np.array(plain), np.array(semantic)
    report = (
        f"odometry {odometry_a.round(3)}\nplain {plain_a.round(3)}\nsemantic {semantic_a.round(3)}"
    )
    # the paper's claim: relations found when landmarks are first seen correct the drift
    assert np.sum(semantic_a < plain_a) >= 16, report
    # and UFastSLAM itself improves on the odometry it is fed
    assert plain_a.mean() < odometry_a.mean(), report
    assert np.sum(plain_a < odometry_a) >= 16, report
