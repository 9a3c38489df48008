"""The study's methods share what they may and nothing else."""

from __future__ import annotations

import dataclasses

import numpy as np

from deploy.study.runner import run_single
from estimator.hybrid import BeliefConfig
from estimator.metrics import CROSS_METRICS
from sim.loader import load_scenario
from sim.scenario import Scenario


def _paper(steps: int) -> Scenario:
    s = load_scenario("paper")
    robots = tuple(dataclasses.replace(r, actions=r.actions[:steps]) for r in s.robots)
    return dataclasses.replace(s, steps=steps, robots=robots)


def test_methods_give_the_same_metrics_alone_or_together() -> None:
    # Together, local, distributed and double_count share one L per robot; alone, each builds
    # its own. L depends only on the robot's own data, so every metric must be identical.
    # (The metrics against another belief, CROSS_METRICS, exist only where the other runs.)
    s = _paper(16)
    together = run_single(s, ["local", "distributed", "double_count"], 3, BeliefConfig())
    for method in ("local", "distributed", "double_count"):
        alone = run_single(s, [method], 3, BeliefConfig())
        for metric, values in alone.metrics[method].items():
            if metric in CROSS_METRICS:
                assert np.isnan(values).all(), (method, metric)
                continue
            np.testing.assert_array_equal(
                values, together.metrics[method][metric], err_msg=f"{method}/{metric}"
            )
    # with local beside them the fleets are also scored on L's objects
    for method in ("distributed", "double_count"):
        assert np.isfinite(together.metrics[method]["class_log_loss_local_objects"]).any()


def test_distributed_beats_local_after_the_robots_meet() -> None:
    s = _paper(30)
    result = run_single(
        s, ["local", "distributed", "double_count", "centralized"], 1, BeliefConfig()
    )
    msde = {m: np.nanmean(result.metrics[m]["msde"][:, -1]) for m in result.metrics}
    assert msde["distributed"] < msde["local"]
    assert result.stack_bytes["distributed"] and min(result.stack_bytes["distributed"]) > 0
    # double counting claims more certainty about the objects than the centralized reference
    det = {m: np.nanmean(result.metrics[m]["object_sqrt_det"][:, -1]) for m in result.metrics}
    assert det["double_count"] < det["centralized"] <= det["distributed"] * 1.05
