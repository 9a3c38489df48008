"""The in-process fleet: N RobotNodes, an in-memory transport and a link model, in lock-step.

At the start of step k every robot receives the stacks its linked peers had at the end of step
k − 1 (relay is one hop per step, as in the paper's table), then every robot processes its frame.
The run is deterministic: same scenario, seed and link model, same result.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from agents.links import AllOf, LinkModel, Proximity, RandomDrop, Schedule
from agents.node import RobotNode
from estimator.hybrid import BeliefConfig, BeliefModel
from estimator.models import SensorFrame
from sim.scenario import Scenario

COMM_MODES = ("schedule", "range", "both")

StepCallback = Callable[[str, int, RobotNode, float, float], None]


def link_model_for(
    scenario: Scenario, comm: str | None = None, drop: float = 0.0, seed: int = 0
) -> LinkModel:
    """The scenario's communication as a link model; ``comm`` overrides its mode, ``drop`` adds
    seeded random loss."""
    c = scenario.communication
    mode = comm or c.mode
    if mode not in COMM_MODES:
        raise ValueError(f"communication mode {mode!r} (known: {', '.join(COMM_MODES)})")
    schedule = Schedule(tuple((e.first, e.last, e.a, e.b) for e in c.schedule))
    proximity = Proximity(c.range if c.range is not None else 10.0)
    model: LinkModel
    if mode == "schedule":
        model = schedule
    elif mode == "range":
        model = proximity
    else:
        model = AllOf((schedule, proximity))
    if drop > 0.0:
        model = AllOf((model, RandomDrop(drop, seed)))
    return model


@dataclass(slots=True)
class FleetStats:
    """Per-run transport figures: bytes of every delivered stack, deliveries per step."""

    delivered_bytes: list[int] = field(default_factory=list)
    deliveries: int = 0


def run_fleet(
    nodes: Mapping[str, RobotNode],
    frames: Mapping[str, Sequence[SensorFrame]],
    links: LinkModel,
    steps: int,
    on_step: StepCallback | None = None,
) -> FleetStats:
    """Drive ``nodes`` through ``steps`` lock-step rounds; ``on_step(robot, k, node, fusion_ms,
    step_ms)`` is called after every robot step with the wall times of the fusion into D and of
    the whole step (fusion included) in ms."""
    robots = list(nodes)
    stats = FleetStats()
    for k in range(1, steps + 1):
        positions = {r: frames[r][k - 1].true_pose for r in robots}
        deliveries = [
            (sender, receiver)
            for receiver in robots
            for sender in robots
            if sender != receiver
            and links.allowed(sender, receiver, k, positions[sender], positions[receiver])
        ]
        # Every stack is taken before any is delivered: what peers had at the end of step k − 1.
        outgoing = {s: nodes[s].outgoing() for s in sorted({s for s, _ in deliveries})}
        for sender, receiver in deliveries:
            data = outgoing[sender]
            if data is None:
                continue
            nodes[receiver].on_stack(data)
            nodes[sender].mark_sent(len(data))
            stats.delivered_bytes.append(len(data))
            stats.deliveries += 1
        for r in robots:
            t0 = time.perf_counter()
            nodes[r].integrate_pending()
            t1 = time.perf_counter()
            nodes[r].on_frame(frames[r][k - 1])
            t2 = time.perf_counter()
            if on_step is not None:
                on_step(r, k, nodes[r], 1e3 * (t1 - t0), 1e3 * (t2 - t0))
    return stats


def make_nodes(
    scenario: Scenario,
    model: BeliefModel,
    config: BeliefConfig,
    rng_for: Callable[[str], np.random.Generator],
    fusion: str = "consistent",
    downdate: str = "remove",
) -> dict[str, RobotNode]:
    """One node per robot of the scenario; ``rng_for(robot)`` builds a fresh generator, called
    twice per robot so that L and D draw identical streams."""
    return {
        r.id: RobotNode(
            r.id,
            r.start,
            model,
            rng_for(r.id),
            rng_for(r.id),
            config,
            fusion,
            downdate,
        )
        for r in scenario.robots
    }
