"""deploy.base.build: a belief built from a robot model file equals the scenario's, and one node
built alone (as an agent builds it) steps exactly like the same robot's node of the in-process
fleet."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agents.node import RobotNode
from deploy.base.build import belief_model, belief_rng, link_model_for, make_node, make_nodes
from deploy.study.fleet import run_fleet
from estimator.hybrid import BeliefConfig, BeliefModel
from estimator.snapshot import BeliefSnapshot
from sim.loader import bundled_names, load_scenario
from sim.robot_model import dump_robot_model, load_robot_model
from sim.sensors import Simulator

SEED = 4
STEPS = 8  # r2 and r3 talk from k = 6 in the paper's table: D fuses a peer's slot twice


def _assert_same_belief_model(a: BeliefModel, b: BeliefModel) -> None:
    assert a.num_classes == b.num_classes
    assert a.class_prior == b.class_prior
    assert a.odometry_noise == b.odometry_noise
    assert a.geometric_noise == b.geometric_noise
    assert type(a.classifier) is type(b.classifier)
    assert a.classifier.alias == b.classifier.alias
    assert a.classifier.best_view == b.classifier.best_view
    np.testing.assert_array_equal(a.classifier.sqrt_info, b.classifier.sqrt_info)


@pytest.mark.parametrize("source", [*bundled_names(), "paper:experiment"])
def test_belief_model_from_model_file_equals_the_scenarios(source: str, tmp_path: Path) -> None:
    s = load_scenario(source)
    path = tmp_path / "model.toml"
    path.write_text(dump_robot_model(s.robot_model()), encoding="utf-8")
    _assert_same_belief_model(belief_model(load_robot_model(path)), belief_model(s))


def test_belief_model_takes_every_field_of_the_robot_model() -> None:
    s = load_scenario("lanes")
    built = belief_model(s.robot_model())
    assert built.num_classes == 3
    assert built.class_prior == (0.5, 0.3, 0.2)
    assert built.odometry_noise.variances == (0.003, 0.003, 0.001)
    assert built.geometric_noise.variances == (0.1, 0.1, 0.01)
    assert built.classifier.alias == (1, 0, 0)
    np.testing.assert_array_equal(built.classifier.sqrt_info, np.eye(3) / 0.35)


Record = tuple[str, int, bytes | None, BeliefSnapshot]


def _run(nodes: dict[str, RobotNode]) -> list[Record]:
    """Every robot's encoded stack (built from L) and snapshot of D after each of its steps on
    the paper world, seed SEED."""
    s = load_scenario("paper")
    frames = Simulator(s, SEED).all_frames()
    out: list[Record] = []

    def record(robot: str, k: int, node: RobotNode, _fused: float, _ms: float) -> None:
        out.append((robot, k, node.outgoing(), node.distributed.snapshot(robot)))

    stats = run_fleet(nodes, frames, link_model_for(s), STEPS, record)
    assert stats.deliveries > 0
    return out


def test_make_node_steps_exactly_like_the_node_of_make_nodes() -> None:
    s = load_scenario("paper")
    model, config = belief_model(s), BeliefConfig()
    fleet = make_nodes(s, model, config, lambda r: belief_rng(SEED, [r]))
    alone = {r.id: make_node(r.id, r.start, model, SEED, config) for r in s.robots}
    expected = _run(fleet)
    assert all(data is not None for _, k, data, _ in expected if k == STEPS)
    got = _run(alone)
    assert [(r, k, data) for r, k, data, _ in got] == [(r, k, data) for r, k, data, _ in expected]
    for (r, k, _, snap), (_, _, _, ref) in zip(got, expected, strict=True):
        assert snap.object_ids == ref.object_ids, (r, k)
        for name in ("weights", "classes", "robot_pose", "robot_cov", "object_pose", "object_cov"):
            np.testing.assert_array_equal(getattr(snap, name), getattr(ref, name), f"{r} {k}")
