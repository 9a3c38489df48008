"""The in-process fleet: N RobotNodes, an in-memory transport and a link model, in lock-step.

At the start of step k every robot receives the stacks its linked peers had at the end of step
k − 1 (relay is one hop per step, as in the paper's table), then every robot processes its frame.
The run is deterministic: same scenario, seed and link model, same result.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from agents.links import LinkModel
from agents.node import NodeCounters, RobotNode
from deploy.base.build import COMM_MODES, link_model_for, make_nodes
from estimator.models import SensorFrame

# Built in deploy.base.build; kept importable from here for the callers written before it.
__all__ = [
    "COMM_MODES",
    "FleetStats",
    "StepCallback",
    "link_model_for",
    "make_nodes",
    "run_fleet",
    "run_fleets",
]

StepCallback = Callable[[str, int, RobotNode, float, float], None]


@dataclass(slots=True)
class FleetStats:
    """Per-run figures: bytes of every delivered stack, deliveries, and per robot step (in the
    order ``on_step`` sees them) the empty joins and rebuilds of D's fusion (``FusionStats``);
    ``refused`` the stacks and slots the fleet's nodes refused over the run (``NodeCounters``:
    invalid stacks, slots that contradict the model, own slots outside the wire's limits), none
    in an honest fleet whose limits fit its beliefs."""

    delivered_bytes: list[int] = field(default_factory=list)
    deliveries: int = 0
    empty_joins: list[int] = field(default_factory=list)
    rebuilds: list[int] = field(default_factory=list)
    refused: int = 0


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
    callbacks = None if on_step is None else [on_step]
    return run_fleets([nodes], frames, links, steps, callbacks)[0]


def run_fleets(
    fleets: Sequence[Mapping[str, RobotNode]],
    frames: Mapping[str, Sequence[SensorFrame]],
    links: LinkModel,
    steps: int,
    on_step: Sequence[StepCallback] | None = None,
    before_step: Callable[[int], None] | None = None,
) -> list[FleetStats]:
    """Several fleets over the same frames and links in one lock-step loop, so that fleets whose
    nodes share a :class:`LocalTrack` per robot step each L once. ``before_step(k)`` runs after
    the deliveries of step k and before any robot steps (e.g. to step shared tracks itself)."""
    stats = [FleetStats() for _ in fleets]
    for k in range(1, steps + 1):
        # Every fleet delivers before any robot steps: a shared L must not run ahead of a stack.
        for i, nodes in enumerate(fleets):
            _deliver(nodes, frames, links, k, stats[i])
        if before_step is not None:
            before_step(k)
        for i, nodes in enumerate(fleets):
            _advance(nodes, frames, k, stats[i], None if on_step is None else on_step[i])
    for st, nodes in zip(stats, fleets, strict=True):
        st.refused = sum(_refused(node.counters) for node in nodes.values())
    return stats


def _refused(c: NodeCounters) -> int:
    return c.invalid + c.rejected_slots + c.foreign_slots + c.own_slot_invalid


def _deliver(
    nodes: Mapping[str, RobotNode],
    frames: Mapping[str, Sequence[SensorFrame]],
    links: LinkModel,
    k: int,
    stats: FleetStats,
) -> None:
    robots = list(nodes)
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


def _advance(
    nodes: Mapping[str, RobotNode],
    frames: Mapping[str, Sequence[SensorFrame]],
    k: int,
    stats: FleetStats,
    on_step: StepCallback | None,
) -> None:
    for r in nodes:
        t0 = time.perf_counter()
        fused = nodes[r].integrate_pending()
        t1 = time.perf_counter()
        # on_frame integrates again; nothing is left by then, but count whatever it reports.
        again = nodes[r].on_frame(frames[r][k - 1]).fusion
        t2 = time.perf_counter()
        stats.empty_joins.append(fused.empty_joins + again.empty_joins)
        stats.rebuilds.append(fused.rebuilds + again.rebuilds)
        if on_step is not None:
            on_step(r, k, nodes[r], 1e3 * (t1 - t0), 1e3 * (t2 - t0))
