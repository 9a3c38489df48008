"""HybridBelief.class_matrix(): built once per set of realisations, and always the classes of the
hypotheses it stands for — after every step of L and D and every fusion into D (a step and a
fusion leave theirs as they make them, from arrays, not from the hypotheses' tuples)."""

from __future__ import annotations

import numpy as np
import pytest

from agents.node import RobotNode
from deploy.base.build import belief_model, belief_rng
from deploy.study.fleet import link_model_for, make_nodes, run_fleet
from estimator.hybrid import BeliefConfig, HybridBelief
from sim.generate import generate_scenario
from sim.sensors import Simulator


def _from_tuples(belief: HybridBelief) -> np.ndarray:
    rows = [h.classes for h in belief.hypotheses]
    return np.array(rows, dtype=np.int64).reshape(len(rows), len(belief.object_ids))


@pytest.mark.parametrize("seed", [0, 5])
def test_class_matrix_is_the_hypotheses_classes_after_every_step_and_fusion(seed: int) -> None:
    s = generate_scenario(4, 12, 3, seed=20 + seed, steps=14)
    frames = Simulator(s, seed).all_frames()
    config = BeliefConfig.joint()
    nodes = make_nodes(s, belief_model(s), config, lambda r: belief_rng(seed, [r]), "consistent")
    checked = {"L": 0, "D": 0, "fused": 0}

    def check(robot: str, k: int, node: RobotNode, fusion_ms: float, step_ms: float) -> None:
        for name, belief in (("L", node.local), ("D", node.distributed)):
            cached = belief._class_rows
            matrix = belief.class_matrix()
            assert np.array_equal(matrix, _from_tuples(belief)), (robot, k, name)
            assert not matrix.flags.writeable
            if belief.object_ids:
                # Left by the step or the fusion that made these hypotheses, not rebuilt here.
                assert cached is not None and cached[1] is matrix, (robot, k, name)
                checked[name] += 1
        checked["fused"] += len(node.distributed.versions) > 0

    run_fleet(nodes, frames, link_model_for(s), s.steps, check)
    assert checked["L"] > 20 and checked["D"] > 20 and checked["fused"] > 20, checked
