"""The in-process fleet: N RobotNodes, an in-memory transport and a link model, in lock-step.

At the start of step k every robot receives the stacks its linked peers had at the end of step
k − 1 (relay is one hop per step, as in the paper's table), then every robot processes its frame.
The run is deterministic: same scenario, seed and link model, same result.

What a stack carries (``gossip``): ``delta``, the default, is the lock-step agents' protocol
(``agents.gossip.DeltaGossip``, strict): every robot publishes its round stack to the whole fleet
(a lock-step launch does: every agent reads every digest, and merges only the stacks of the
senders its order names), with the held slots some peer lacks by its latest digest. ``full``
sends every held slot (the fleet before issue 42, bit for bit). Both deliver every slot version
that can change a receiver, and in both only a robot that sends rebuilds its own slot, so D is
the same bit for bit; only the bytes differ (docs/architecture.md, "The study's gossip").
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from agents.gossip import DeltaGossip
from agents.links import LinkModel
from agents.node import NodeCounters, RobotNode
from deploy.base.build import COMM_MODES, link_model_for, make_nodes
from estimator.models import SensorFrame

# Built in deploy.base.build; kept importable from here for the callers written before it.
__all__ = [
    "COMM_MODES",
    "GOSSIP_MODES",
    "FleetStats",
    "StepCallback",
    "link_model_for",
    "linked_pairs",
    "make_nodes",
    "run_fleet",
    "run_fleets",
]

StepCallback = Callable[[str, int, RobotNode, float, float], None]
GOSSIP_MODES = ("delta", "full")


@dataclass(slots=True)
class FleetStats:
    """Per-run figures: bytes of every delivered stack, deliveries, and per robot step (in the
    order ``on_step`` sees them) the empty joins and rebuilds of D's fusion (``FusionStats``);
    ``refused`` the stacks and slots the fleet's nodes refused over the run (``NodeCounters``:
    invalid stacks, slots that contradict the model, own slots outside the wire's limits), none
    in an honest fleet whose limits fit its beliefs.

    Per robot step too, in seconds by the run's ``clock``: the three phases of its step
    (``fusion_s`` into D, L's step ``local_s``, D's step ``distributed_s``; ``StepReport``),
    ``gossip_s`` the stacks of the deliveries before it (its own stack encoded, once, and every
    stack it received decoded and merged), ``digest_s`` the digests of the whole fleet noted by
    its delta-gossip policy (0 with full stacks), and ``heard`` the stacks it received then."""

    delivered_bytes: list[int] = field(default_factory=list)
    deliveries: int = 0
    empty_joins: list[int] = field(default_factory=list)
    rebuilds: list[int] = field(default_factory=list)
    refused: int = 0
    fusion_s: list[float] = field(default_factory=list)
    local_s: list[float] = field(default_factory=list)
    distributed_s: list[float] = field(default_factory=list)
    gossip_s: list[float] = field(default_factory=list)
    digest_s: list[float] = field(default_factory=list)
    heard: list[int] = field(default_factory=list)


@dataclass(slots=True)
class _Gossiped:
    """One robot's share of one step's deliveries (seconds by the run's clock)."""

    gossip_s: float = 0.0
    digest_s: float = 0.0
    heard: int = 0


def run_fleet(
    nodes: Mapping[str, RobotNode],
    frames: Mapping[str, Sequence[SensorFrame]],
    links: LinkModel,
    steps: int,
    on_step: StepCallback | None = None,
    gossip: str = "delta",
    clock: Callable[[], float] = time.perf_counter,
) -> FleetStats:
    """Drive ``nodes`` through ``steps`` lock-step rounds; ``on_step(robot, k, node, fusion_ms,
    step_ms)`` is called after every robot step with the times of the fusion into D and of
    the whole step (fusion included) in ms, by ``clock`` (seconds; default the wall clock,
    ``time.process_time`` for CPU time): it times, never changes, what the fleet does."""
    callbacks = None if on_step is None else [on_step]
    return run_fleets([nodes], frames, links, steps, callbacks, gossip=gossip, clock=clock)[0]


def run_fleets(
    fleets: Sequence[Mapping[str, RobotNode]],
    frames: Mapping[str, Sequence[SensorFrame]],
    links: LinkModel,
    steps: int,
    on_step: Sequence[StepCallback] | None = None,
    before_step: Callable[[int], None] | None = None,
    gossip: str = "delta",
    clock: Callable[[], float] = time.perf_counter,
) -> list[FleetStats]:
    """Several fleets over the same frames and links in one lock-step loop, so that fleets whose
    nodes share a :class:`LocalTrack` per robot step each L once. ``before_step(k)`` runs after
    the deliveries of step k and before any robot steps (e.g. to step shared tracks itself).
    ``gossip``: what a stack carries (module docstring); ``clock``: see :func:`run_fleet`."""
    if gossip not in GOSSIP_MODES:
        raise ValueError(f"gossip {gossip!r} (known: {', '.join(GOSSIP_MODES)})")
    stats = [FleetStats() for _ in fleets]
    policies = [_policies(nodes) if gossip == "delta" else None for nodes in fleets]
    for k in range(1, steps + 1):
        # Every fleet delivers before any robot steps: a shared L must not run ahead of a stack.
        gossiped = [
            _deliver(nodes, frames, links, k, stats[i], policies[i], clock)
            for i, nodes in enumerate(fleets)
        ]
        if before_step is not None:
            before_step(k)
        for i, nodes in enumerate(fleets):
            callback = None if on_step is None else on_step[i]
            _advance(nodes, frames, k, stats[i], callback, gossiped[i], clock)
    for st, nodes in zip(stats, fleets, strict=True):
        st.refused = sum(_refused(node.counters) for node in nodes.values())
    return stats


def _refused(c: NodeCounters) -> int:
    return c.invalid + c.rejected_slots + c.foreign_slots + c.own_slot_invalid


def _policies(nodes: Mapping[str, RobotNode]) -> dict[str, DeltaGossip]:
    """Each robot's lock-step gossip policy, over the fleet as its roster."""
    roster = frozenset(nodes)
    return {
        r: DeltaGossip(r, 1.0, True, False, roster, node.limits.max_slots)
        for r, node in nodes.items()
    }


def _outgoing(
    nodes: Mapping[str, RobotNode],
    senders: Sequence[str],
    policies: dict[str, DeltaGossip],
    k: int,
    clock: Callable[[], float],
    gossiped: dict[str, _Gossiped],
) -> dict[str, bytes | None]:
    """Delta gossip: every robot's round stack (the held slots some peer lacks by its latest
    digest; None while it holds nothing, as a full stack), then every robot notes every other's
    digest (the versions it held when it sent), as every lock-step agent reads every stack."""
    held = {r: _digest(node) for r, node in nodes.items()}
    out: dict[str, bytes | None] = {}
    for s in senders:
        t0 = clock()
        chosen = policies[s].select(held[s], k, unsent=False) if held[s] else None
        out[s] = None if chosen is None else nodes[s].encoded_delta(chosen)
        gossiped[s].gossip_s += clock() - t0
    # Each policy notes the digests in the senders' order, whichever robot notes first.
    for r, policy in policies.items():
        t0 = clock()
        for sender, have in held.items():
            if r != sender:
                policy.note_digest(sender, have, frozenset(), k)
        gossiped[r].digest_s += clock() - t0
    return out


def _digest(node: RobotNode) -> dict[str, tuple[int, int]]:
    """The versions ``node``'s stack holds, its own slot's as ``current_stack`` would make it —
    (epoch, step) once L knows an object — without rebuilding that slot: only a robot that sends
    rebuilds it, as in a full-stack fleet (so the two give the same slots, and the same D, bit
    for bit; a lock-step agent, which publishes every round, rebuilds it every step)."""
    have = node.stack.versions()
    if node.local.object_ids:
        have[node.robot] = (node.epoch, node.k)
    return have


def linked_pairs(
    robots: Sequence[str], frames: Mapping[str, Sequence[SensorFrame]], links: LinkModel, k: int
) -> list[tuple[str, str]]:
    """The (sender, receiver) pairs ``links`` allows at step k, by the robots' true positions
    then, receiver by receiver in the order of ``robots``: the deliveries of step k."""
    positions = {r: frames[r][k - 1].true_pose for r in robots}
    return [
        (sender, receiver)
        for receiver in robots
        for sender in robots
        if sender != receiver
        and links.allowed(sender, receiver, k, positions[sender], positions[receiver])
    ]


def _deliver(
    nodes: Mapping[str, RobotNode],
    frames: Mapping[str, Sequence[SensorFrame]],
    links: LinkModel,
    k: int,
    stats: FleetStats,
    policies: dict[str, DeltaGossip] | None,
    clock: Callable[[], float],
) -> dict[str, _Gossiped]:
    deliveries = linked_pairs(list(nodes), frames, links, k)
    gossiped = {r: _Gossiped() for r in nodes}
    # Every stack is taken before any is delivered: what peers had at the end of step k − 1.
    senders = sorted({s for s, _ in deliveries})
    if policies is None:
        outgoing = {}
        for s in senders:
            t0 = clock()
            outgoing[s] = nodes[s].outgoing()
            gossiped[s].gossip_s += clock() - t0
    else:
        outgoing = _outgoing(nodes, senders, policies, k, clock, gossiped)
    for sender, receiver in deliveries:
        data = outgoing[sender]
        if data is None:
            continue
        t0 = clock()
        nodes[receiver].receive(data, sender)
        gossiped[receiver].gossip_s += clock() - t0
        gossiped[receiver].heard += 1
        nodes[sender].mark_sent(len(data))
        stats.delivered_bytes.append(len(data))
        stats.deliveries += 1
    return gossiped


def _advance(
    nodes: Mapping[str, RobotNode],
    frames: Mapping[str, Sequence[SensorFrame]],
    k: int,
    stats: FleetStats,
    on_step: StepCallback | None,
    gossiped: Mapping[str, _Gossiped],
    clock: Callable[[], float],
) -> None:
    for r in nodes:
        done = nodes[r].on_frame(frames[r][k - 1], clock=clock)
        stats.empty_joins.append(done.fusion.empty_joins)
        stats.rebuilds.append(done.fusion.rebuilds)
        stats.fusion_s.append(done.fusion_s)
        stats.local_s.append(done.local_s)
        stats.distributed_s.append(done.distributed_s)
        stats.gossip_s.append(gossiped[r].gossip_s)
        stats.digest_s.append(gossiped[r].digest_s)
        stats.heard.append(gossiped[r].heard)
        if on_step is not None:
            whole = done.fusion_s + done.local_s + done.distributed_s
            on_step(r, k, nodes[r], 1e3 * done.fusion_s, 1e3 * whole)
