"""Beliefs probed at every step, for the tests that follow them step by step (issue 10).

The centralized belief and an in-process fleet's local and distributed beliefs are each reduced by
a ``probe`` right after every step (class marginals, true-class probabilities, object means), so
that a test keeps small arrays per step instead of whole beliefs with their iSAM2 copies.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from agents.links import LinkModel
from agents.node import RobotNode
from deploy.base.build import belief_model, belief_rng
from deploy.study.fleet import make_nodes, run_fleet
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.models import GaussianNoise, SensorFrame
from sim.scenario import Scenario

T = TypeVar("T")
Array = NDArray[np.float64]
Frames = Mapping[str, Sequence[SensorFrame]]


@dataclass(frozen=True, slots=True)
class FleetSteps(Generic[T]):
    """``probe`` of every robot's L and D after each of its steps: ``local[robot][k − 1]``."""

    local: dict[str, list[T]]
    distributed: dict[str, list[T]]
    max_local_hypotheses: int
    max_distributed_hypotheses: int


def marginals_by_id(belief: HybridBelief) -> dict[int, Array]:
    """P(c_j = i) (M,) per object id."""
    p = belief.class_marginals()
    return {j: p[i] for i, j in enumerate(belief.object_ids)}


def mean_positions_by_id(belief: HybridBelief) -> dict[int, Array]:
    """Per object id, its position (2,) averaged over the hypotheses with their weights."""
    w = belief.weights()
    return {
        j: w @ np.array([h.pose(object_key(j))[:2] for h in belief.hypotheses])
        for j in belief.object_ids
    }


def centralized_steps(
    s: Scenario,
    seed: int,
    frames: Frames,
    config: BeliefConfig,
    probe: Callable[[HybridBelief], T],
) -> tuple[list[T], int]:
    """``probe`` of the centralized belief after every step (index k − 1) and the largest number
    of hypotheses it held."""
    robots = s.robot_ids
    belief = HybridBelief(belief_model(s), {r: s.robot(r).start for r in robots}, config)
    rng = belief_rng(seed, robots)
    out, most = [], 0
    for k in range(s.steps):
        belief.step([frames[r][k] for r in robots], rng)
        out.append(probe(belief))
        most = max(most, len(belief.hypotheses))
    return out, most


def fleet_steps(
    s: Scenario,
    seed: int,
    frames: Frames,
    config: BeliefConfig,
    links: LinkModel,
    probe: Callable[[HybridBelief], T],
) -> FleetSteps[T]:
    """Run the in-process fleet (consistent fusion) and ``probe`` every robot's L and D after
    each of its steps."""
    nodes = make_nodes(s, belief_model(s), config, lambda r: belief_rng(seed, [r]))
    local: dict[str, list[T]] = {r: [] for r in s.robot_ids}
    distributed: dict[str, list[T]] = {r: [] for r in s.robot_ids}
    most = [0, 0]

    def on_step(robot: str, k: int, node: RobotNode, *_: float) -> None:
        assert len(local[robot]) == k - 1, (robot, k)
        local[robot].append(probe(node.local))
        distributed[robot].append(probe(node.distributed))
        most[0] = max(most[0], len(node.local.hypotheses))
        most[1] = max(most[1], len(node.distributed.hypotheses))

    run_fleet(nodes, frames, links, s.steps, on_step)
    return FleetSteps(local, distributed, most[0], most[1])


def truncate(s: Scenario, steps: int) -> Scenario:
    """The scenario's first ``steps`` steps."""
    robots = tuple(dataclasses.replace(r, actions=r.actions[:steps]) for r in s.robots)
    return dataclasses.replace(s, steps=steps, robots=robots)


def scaled_noise(s: Scenario, scale: float) -> Scenario:
    """Odometry and geometric variances × ``scale`` (the classifier's noise is unchanged)."""
    odometry = GaussianNoise(tuple(v * scale for v in s.odometry_noise.variances))  # type: ignore[arg-type]
    geometric = GaussianNoise(tuple(v * scale for v in s.geometric_noise.variances))  # type: ignore[arg-type]
    return dataclasses.replace(s, odometry_noise=odometry, geometric_noise=geometric)


def quiet_after(frames: Frames, last: int) -> dict[str, list[SensorFrame]]:
    """The frames with no detections after step ``last`` (odometry unchanged)."""
    return {
        r: [f if f.k <= last else dataclasses.replace(f, detections=()) for f in fs]
        for r, fs in frames.items()
    }


def class_log_posteriors(
    s: Scenario, seed: int, config: BeliefConfig, robots: Sequence[str] | None = None
) -> tuple[HybridBelief, list[Array]]:
    """One belief over ``robots`` (default: all of ``s``'s) stepped through seed ``seed``'s
    frames, and its class log-posterior (n, M) after every step."""
    from sim.sensors import Simulator

    robots = list(s.robot_ids if robots is None else robots)
    belief = HybridBelief(belief_model(s), {r: s.robot(r).start for r in robots}, config)
    rng = belief_rng(seed, robots)
    frames = Simulator(s, seed).all_frames()
    out = []
    for k in range(s.steps):
        belief.step([frames[r][k] for r in robots], rng)
        out.append(belief.class_log_posterior().copy())
    return belief, out
