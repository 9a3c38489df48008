"""The asyncio agent over the in-memory transport, in one event loop: lock-step rounds merge exactly
the peers the conductor ordered (and so repeat the in-process runner), a realtime simulated agent
obeys the simulator's links (and only a simulated agent does), invalid input is counted and
logged rate-limited while the agent lives on, and a journal replay rebuilds the very belief.

The world: three robots 10 m apart driving along +x, each with two objects just ahead of it (seen
from k = 1), talking along a chain r1–r2–r3 (never r1–r3).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np
import pytest

from agents.control import (
    NeedFrames,
    Status,
    StepOrder,
    Stop,
    decode_control,
    encode_control,
)
from agents.core import CoreSettings
from agents.journal import Journal
from agents.links import Schedule
from agents.node import RobotNode
from agents.runtime import Agent, new_agent
from agents.transport import Inbox, Keys, MemoryBus, MemoryTransport
from deploy.base.build import belief_model, belief_rng, make_node, make_nodes
from deploy.launch import conductor as conductor_module
from deploy.launch.conductor import Conductor, ConductorError
from deploy.study.fleet import run_fleet
from estimator.hybrid import BeliefConfig, BeliefSnapshot
from estimator.models import Detection, SensorFrame
from protocol.codec import StackMessage, encode
from protocol.estimate import EstimateMessage, decode_estimate, encode_estimate
from protocol.frames import encode_frame
from protocol.stack import Stack
from sim.loader import parse_scenario
from sim.sensors import Simulator
from tests.estimator.scenarios import fleet_text, objects_ahead
from tests.tolerance import assert_close

STEPS = 8
SEED = 5
ROBOTS = ("r1", "r2", "r3")
_YS = [10.0 * i for i in range(len(ROBOTS))]
_TEXT = fleet_text(
    "chain3",
    STEPS,
    _YS,
    objects_ahead(_YS),
    description="three robots 10 m apart, two objects each",
    half_angle_deg=50.0,
    sensing=3.5,
    communication=(
        f'mode = "schedule"\nschedule = [[1, {STEPS}, "r1", "r2"], [1, {STEPS}, "r2", "r3"]]'
    ),
)
SCENARIO = parse_scenario(_TEXT, "chain3.toml")
CHAIN = Schedule(((1, STEPS, "r1", "r2"), (1, STEPS, "r2", "r3")))
KEYS = Keys("rt")
QUIET = 60.0  # a gossip period longer than any test: only steps publish stacks


@pytest.fixture(scope="module")
def frames() -> dict[str, list[SensorFrame]]:
    return Simulator(SCENARIO, SEED).all_frames()


def _nodes() -> dict[str, RobotNode]:
    """One node per robot, seeded exactly as `semfleet agent` and the in-process runner do."""
    model = belief_model(SCENARIO)
    return make_nodes(SCENARIO, model, BeliefConfig(), lambda r: belief_rng(SEED, [r]))


def _factory(robot: str) -> Callable[[], RobotNode]:
    """The node of ``robot`` at step 0, as `semfleet agent` builds it."""
    model = belief_model(SCENARIO)
    start = SCENARIO.robot(robot).start
    return lambda: make_node(robot, start, model, SEED, BeliefConfig())


def _agent(
    robot: str,
    bus: MemoryBus,
    mode: str,
    journal: Journal | None = None,
    gossip_period: float = QUIET,
    clock: Callable[[], float] | None = None,
    simulation: bool = False,
    listen_in_range: bool = False,
) -> Agent:
    settings = CoreSettings(
        mode=mode,
        gossip_period=gossip_period,
        retry_period=0.05,
        simulation=simulation,
        listen_in_range=listen_in_range,
    )
    extra = {} if clock is None else {"clock": clock}
    return new_agent(_factory(robot), KEYS, MemoryTransport(bus), settings, journal, **extra)


@contextlib.asynccontextmanager
async def _running(*agents: Agent) -> AsyncIterator[list[asyncio.Task[None]]]:
    """The agents' run() as tasks, once their transports are open; stopped and awaited at the end
    (a crash fails the test)."""
    tasks = [asyncio.create_task(a.run()) for a in agents]
    try:
        await _until(
            lambda: all(
                isinstance(a.transport, MemoryTransport) and a.transport.is_open for a in agents
            )
        )
        yield tasks
    finally:
        for a in agents:
            a.stop("test over")
        await asyncio.wait_for(asyncio.gather(*tasks), 10)


def _stepped(agent: Agent, k: int) -> bool:
    """Step k done and published: the worker has rebuilt the own slot (the node is read from
    the test's thread while the worker may be mid-step)."""
    return agent.node.k == k and agent.node.stack.stamps().get(agent.robot) == k


async def _until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.005)


def assert_same_snapshot(a: BeliefSnapshot, b: BeliefSnapshot, what: str) -> None:
    assert a.object_ids == b.object_ids, what
    np.testing.assert_array_equal(a.classes, b.classes, err_msg=what)
    for name in ("weights", "robot_pose", "robot_cov", "object_pose", "object_cov"):
        assert_close(getattr(a, name), getattr(b, name), what=f"{what}: {name}")
    assert (a.class_probs is None) == (b.class_probs is None), f"{what}: class_probs"
    if a.class_probs is not None and b.class_probs is not None:
        assert_close(a.class_probs, b.class_probs, what=f"{what}: class_probs")


# --------------------------------------------------------------------------- lock-step fleet


@dataclass
class LockstepRun:
    estimates: dict[tuple[str, int], EstimateMessage]
    stamps: dict[str, dict[str, int]]  # each agent's stack at the end
    journals: Path


async def _lockstep_fleet(
    frames: dict[str, list[SensorFrame]], journals: Path
) -> tuple[dict[tuple[str, int], EstimateMessage], dict[str, dict[str, int]]]:
    bus = MemoryBus()
    conductor = Conductor(
        SCENARIO, frames, ROBOTS, MemoryTransport(bus), KEYS, CHAIN, keep_estimates=True
    )
    await conductor.open()
    agents = []
    for r in ROBOTS:
        journal, records = Journal.open(journals / f"{r}.log", {"robot": r, "seed": SEED})
        assert records == []
        # The timer re-sends stacks an agent that opened later missed (as over Zenoh).
        agents.append(_agent(r, bus, "lockstep", journal=journal, gossip_period=0.05))
    async with _running(*agents) as tasks:
        await conductor.wait_alive(10)
        await conductor.run_lockstep(STEPS, step_timeout=30)
        assert not any(t.done() for t in tasks)
        conductor.stop_agents()
        await asyncio.wait_for(asyncio.gather(*tasks), 10)
    assert {a.stop_reason for a in agents} == {"run complete"}
    stamps = {a.robot: a.node.current_stack().stamps() for a in agents}
    return conductor.collected.estimates, stamps


@pytest.fixture(scope="module")
def lockstep_run(
    frames: dict[str, list[SensorFrame]], tmp_path_factory: pytest.TempPathFactory
) -> LockstepRun:
    journals = tmp_path_factory.mktemp("journals")
    estimates, stamps = asyncio.run(_lockstep_fleet(frames, journals))
    return LockstepRun(estimates, stamps, journals)


@pytest.fixture(scope="module")
def reference(frames: dict[str, list[SensorFrame]]) -> dict[tuple[str, int], dict[str, object]]:
    """The in-process runner over the same link model: snapshots of L and D after every step."""
    snaps: dict[tuple[str, int], dict[str, object]] = {}

    def record(robot: str, k: int, node: RobotNode, _fused: float, _ms: float) -> None:
        snaps[(robot, k)] = {
            "distributed": node.distributed.snapshot(robot),
            "local": node.local.snapshot(robot),
            "stamps": node.current_stack().stamps(),
        }

    run_fleet(_nodes(), frames, CHAIN, STEPS, record)
    return snaps


def test_agent_lockstep_fleet_repeats_the_in_process_runner(
    lockstep_run: LockstepRun, reference: dict[tuple[str, int], dict[str, object]]
) -> None:
    for r in ROBOTS:
        for k in range(1, STEPS + 1):
            est = lockstep_run.estimates[(r, k)]
            for belief in ("distributed", "local"):
                ref = reference[(r, k)][belief]
                assert isinstance(ref, BeliefSnapshot)
                assert_same_snapshot(est.beliefs[belief], ref, f"{r} k={k} {belief}")
        assert lockstep_run.stamps[r] == reference[(r, STEPS)]["stamps"]
    # Relay along the chain: r3 holds r1's slot, one round behind r2's copy of it.
    assert lockstep_run.stamps["r3"]["r1"] == STEPS - 2
    # D gained from the peers: r3's distributed belief maps r1's objects, its local one does not.
    final = lockstep_run.estimates[("r3", STEPS)].beliefs
    assert {1, 2} <= set(final["distributed"].object_ids)
    assert not {1, 2} & set(final["local"].object_ids)


@pytest.mark.asyncio
async def test_agent_lockstep_round_merges_exactly_the_ordered_peers(
    frames: dict[str, list[SensorFrame]],
) -> None:
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    peers = _nodes()
    del peers["r3"]
    agent = _agent("r3", bus, "lockstep")

    def order(k: int, senders: tuple[str, ...]) -> None:
        world.publish(KEYS.ctl("step"), encode_control(StepOrder(k, {"r3": senders})))
        world.publish(KEYS.frames("r3"), encode_frame(frames["r3"][k - 1]))

    def gossip(robot: str) -> None:
        world.publish(KEYS.stack(robot), peers[robot].encoded_stack())

    async with _running(agent) as (task,):
        order(1, ())
        await _until(lambda: _stepped(agent, 1))
        for node in peers.values():
            node.on_frame(frames[node.robot][0])
        order(2, ("r1", "r2"))
        gossip("r2")
        await asyncio.sleep(0.3)  # r1's stack of round 1 is missing: the agent must wait
        assert agent.node.k == 1
        assert agent.node.stack.stamps() == {"r3": 1}
        gossip("r1")
        await _until(lambda: _stepped(agent, 2))
        assert agent.node.stack.stamps() == {"r1": 1, "r2": 1, "r3": 2}
        for node in peers.values():
            node.on_frame(frames[node.robot][1])
        gossip("r1")  # round 2 of r1 arrives, but round 3 orders r2 only
        gossip("r2")
        order(3, ("r2",))
        await _until(lambda: _stepped(agent, 3))
        assert agent.node.stack.stamps() == {"r1": 1, "r2": 2, "r3": 3}
        assert agent.counters.frames_processed == 3
        assert not task.done()


# --------------------------------------------------------------------------- realtime


def _stack_from(node: RobotNode) -> bytes:
    return encode(StackMessage(node.robot, None, node.current_stack(), node.k))


def _links(k: int, links: dict[str, tuple[str, ...]]) -> bytes:
    return encode_control(StepOrder(k, links))


@pytest.mark.asyncio
async def test_simulated_agent_hears_whom_the_simulator_says_and_counts_the_rest(
    frames: dict[str, list[SensorFrame]],
) -> None:
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    peer = _nodes()["r2"]
    peer.on_frame(frames["r2"][0])
    agent = _agent("r1", bus, "realtime", simulation=True)
    async with _running(agent) as (task,):
        world.publish(KEYS.stack("r2"), _stack_from(peer))  # no links yet: nobody is heard
        await _until(lambda: agent.node.counters.stacks_received == 1)
        assert agent.counter_values()["ignored_out_of_range"] == 0  # (nor counted out of range)
        assert agent.node.stack.stamps() == {}
        world.publish(KEYS.sim_links("r1"), _links(1, {"r1": (), "r2": ("r1",)}))
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
        await _until(lambda: agent.node.k == 1)
        world.publish(KEYS.stack("r2"), _stack_from(peer))  # step 1's links: r2 → r1 is cut
        await _until(lambda: agent.node.counters.stacks_received == 2)
        assert agent.counter_values()["ignored_out_of_range"] == 1
        assert agent.node.stack.stamps() == {"r1": 1}
        world.publish(KEYS.sim_links("r1"), _links(2, {"r1": ("r2",)}))
        world.publish(KEYS.sim_links("r1"), b"\xff")  # counted, never fatal
        await asyncio.sleep(0.05)
        world.publish(KEYS.stack("r2"), _stack_from(peer))
        await _until(lambda: agent.node.counters.stacks_received == 3)
        assert agent.node.stack.stamps() == {"r1": 1, "r2": 1}
        assert agent.counter_values()["ignored_out_of_range"] == 1
        assert agent.counter_values()["links_invalid"] == 1
        assert not task.done()


async def _listening_r1(
    frames: dict[str, list[SensorFrame]],
) -> tuple[MemoryTransport, dict[str, RobotNode], Agent]:
    """A bare transport to publish as the world, r2 and r3 after their step 1, and a simulated
    real time r1 that subscribes to the peers in range only, on one bus."""
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    peers = _nodes()
    for r in ("r2", "r3"):
        peers[r].on_frame(frames[r][0])
    return world, peers, _agent("r1", bus, "realtime", simulation=True, listen_in_range=True)


@pytest.mark.asyncio
async def test_simulated_agent_subscribes_to_the_stacks_of_whom_the_simulator_says_only(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """With ``listen_in_range``, a simulated real time agent subscribes to ``stack/<peer>`` of
    the robots in range at the coming step only (nobody before the first links): a stack of a
    robot out of range is never even delivered to it. (The core's own filter, for a stack still
    in flight when the range changed, is tested in test_core.)"""
    world, peers, agent = await _listening_r1(frames)
    async with _running(agent) as (task,):
        await _until(lambda: agent.counter_values()["listen_changes"] == 1)
        assert agent.stack_subscriptions.exprs == set()  # no links yet: nobody is heard
        world.publish(KEYS.stack("r2"), _stack_from(peers["r2"]))
        world.publish(KEYS.sim_links("r1"), _links(1, {"r1": (), "r2": ("r1",)}))
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
        await _until(lambda: agent.node.k == 1)
        world.publish(KEYS.stack("r2"), _stack_from(peers["r2"]))  # step 1: r2 → r1 is cut
        world.publish(KEYS.sim_links("r1"), _links(2, {"r1": ("r2",)}))
        world.publish(KEYS.sim_links("r1"), b"\xff")  # counted, never fatal
        await _until(lambda: agent.stack_subscriptions.exprs == {KEYS.stack("r2")})
        assert agent.node.counters.stacks_received == 0
        world.publish(KEYS.stack("r3"), _stack_from(peers["r3"]))  # out of range: not sent
        world.publish(KEYS.stack("r2"), _stack_from(peers["r2"]))
        await _until(lambda: agent.node.counters.stacks_received == 1)
        await asyncio.sleep(0.05)
        assert agent.node.stack.stamps() == {"r1": 1, "r2": 1}
        c = agent.counter_values()
        assert (c["stacks_received"], c["ignored_out_of_range"], c["links_invalid"]) == (1, 0, 1)
        assert c["listen_changes"] == 2
        # Links of a later step already here: their robots are subscribed to as well (the agent
        # will need them), and stay unread until their step comes.
        world.publish(KEYS.sim_links("r1"), _links(3, {"r1": ("r3",)}))
        await _until(
            lambda: agent.stack_subscriptions.exprs == {KEYS.stack(r) for r in ("r2", "r3")}
        )
        world.publish(KEYS.stack("r3"), _stack_from(peers["r3"]))
        await _until(lambda: agent.counter_values()["ignored_out_of_range"] == 1)
        assert agent.node.stack.stamps() == {"r1": 1, "r2": 1}
        assert not task.done()


@pytest.mark.asyncio
async def test_links_sent_a_step_ahead_subscribe_but_are_not_obeyed(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """The simulator sends each step's links a step ahead on ``sim/listen``, with the frames of
    the step before: the agent subscribes to the robots it will hear then (so that the
    subscription is declared before their stacks come), but reads a stack only under the links
    of ``sim/links`` due at its coming step — after step 1, those of step 1 until step 2's come;
    links ahead beyond the agent's window are ignored, and bad ones counted."""
    world, peers, agent = await _listening_r1(frames)
    agent.core.node.roster = frozenset(ROBOTS)  # x9, not in it, is never subscribed to
    async with _running(agent) as (task,):
        await _until(lambda: agent.counter_values()["listen_changes"] == 1)
        world.publish(KEYS.sim_links("r1"), _links(1, {"r1": ("r2",)}))
        world.publish(KEYS.sim_listen("r1"), _links(2, {"r1": ("r2", "r3", "x9")}))
        world.publish(KEYS.sim_listen("r1"), _links(10_000, {"r1": ("r4",)}))  # beyond the window
        world.publish(KEYS.sim_listen("r1"), b"\xff")
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
        await _until(lambda: agent.node.k == 1)
        want = {KEYS.stack(r) for r in ("r2", "r3")}
        await _until(lambda: agent.stack_subscriptions.exprs == want)
        # r3 is subscribed to but not heard before step 2's links come: its stack is not read.
        world.publish(KEYS.stack("r3"), _stack_from(peers["r3"]))
        world.publish(KEYS.stack("r2"), _stack_from(peers["r2"]))
        await _until(lambda: agent.node.counters.stacks_received == 2)
        await _until(lambda: agent.counter_values()["ignored_out_of_range"] == 1)
        assert set(agent.node.stack.stamps()) == {"r1", "r2"}
        assert agent.counter_values()["links_invalid"] == 1
        world.publish(KEYS.sim_links("r1"), _links(2, {"r1": ("r2", "r3")}))
        await asyncio.sleep(0.05)
        world.publish(KEYS.stack("r3"), _stack_from(peers["r3"]))
        await _until(lambda: "r3" in agent.node.stack.stamps())
        assert agent.stack_subscriptions.exprs == want
        assert not task.done()


@pytest.mark.asyncio
async def test_a_real_robots_agent_ignores_simulated_links(
    frames: dict[str, list[SensorFrame]],
) -> None:
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    peer = _nodes()["r2"]
    peer.on_frame(frames["r2"][0])
    agent = _agent("r1", bus, "realtime", simulation=False)
    async with _running(agent):
        world.publish(KEYS.sim_links("r1"), _links(1, {"r1": ()}))
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
        await _until(lambda: agent.node.k == 1)
        world.publish(KEYS.stack("r2"), _stack_from(peer))
        await _until(lambda: agent.node.counters.stacks_received == 1)
        assert agent.node.stack.stamps() == {"r1": 1, "r2": 1}
        assert agent.counter_values()["ignored_out_of_range"] == 0


@pytest.mark.asyncio
async def test_agent_counts_invalid_stacks_frames_and_control_and_keeps_running(
    frames: dict[str, list[SensorFrame]], caplog: pytest.LogCaptureFixture
) -> None:
    bus = MemoryBus()
    world = MemoryTransport(bus)
    estimates = Inbox(64)
    world.subscribe(KEYS.estimate("r1"), estimates)
    await world.open()
    agent = _agent("r1", bus, "realtime", clock=lambda: 100.0)
    garbage = [b"", b"\xc1", b"\x81\xa1v\x02", bytes(range(200)), b"\x93\x01\x02"] * 10
    caplog.set_level(logging.WARNING, logger="agents.core")
    async with _running(agent) as (task,):
        for data in garbage:
            world.publish(KEYS.stack("r2"), data)
        # A well-formed stack of r3 on r2's key: another kind of error from the same source,
        # which must get a line of its own (issue 43, finding 8: the rate limit per source hid
        # one kind behind another, and the log told another story than the counters).
        world.publish(KEYS.stack("r2"), encode(StackMessage("r3", None, Stack(()), 1)))
        world.publish(KEYS.stack("chaos"), b"\x00\x01")
        world.publish(KEYS.frames("r1"), b"not a frame")
        world.publish(KEYS.frames("r1"), encode_frame(frames["r2"][0]))  # another robot's frame
        # r1's frame with point detections (bearing, range), where its model has pose objects
        first = frames["r1"][0]
        points = tuple(Detection(d.object_id, d.z_geo[:2], d.z_sem) for d in first.detections)
        point_frame = SensorFrame("r1", 1, first.odometry, points, first.true_pose)
        assert points
        world.publish(KEYS.frames("r1"), encode_frame(point_frame))
        world.publish(KEYS.ctl("step"), b"\xff\xff")
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
        await _until(lambda: agent.node.k == 1 and len(estimates) > 0)
        counters = agent.counter_values()
        assert counters["stacks_invalid"] == len(garbage) + 2
        assert counters["stacks_misaddressed"] == 1
        assert counters["frames_invalid"] == 3
        assert counters["control_invalid"] == 1
        assert counters["frames_processed"] == 1
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][1]))
        await _until(lambda: agent.node.k == 2)  # still stepping
        assert not task.done()
    # One line per source and kind of error while the (frozen) clock stays within the log
    # period, naming the counter that counted it.
    lines = [r.getMessage().split(": ")[1] for r in caplog.records if "invalid" in r.message]
    assert len(lines) == len(set(lines))
    assert {line.split(" (")[0] for line in lines} == {
        f"invalid input from {s}" for s in ("chaos", "ctl", "frames", "r2")
    }
    assert any(line.endswith(", counted in control_invalid)") for line in lines)
    assert any(line.endswith(", counted in frames_invalid)") for line in lines)
    stack_lines = [line for line in lines if line.startswith("invalid input from r2")]
    assert sorted(stack_lines) == [
        "invalid input from r2 (MalformedMessage, counted in stacks_invalid)",
        "invalid input from r2 (SenderMismatch, counted in stacks_invalid and stacks_misaddressed)",
    ]


@pytest.mark.asyncio
async def test_agent_answers_a_status_request_with_its_counters(
    frames: dict[str, list[SensorFrame]],
) -> None:
    bus = MemoryBus()
    world = MemoryTransport(bus)
    estimates = Inbox(64)
    world.subscribe(KEYS.estimate("r1"), estimates)
    await world.open()
    agent = _agent("r1", bus, "realtime")
    async with _running(agent):
        world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
        await _until(lambda: agent.node.k == 1 and len(estimates) == 1)
        world.publish(KEYS.stack("r2"), b"junk")
        await _until(lambda: agent.node.counters.invalid == 1)
        world.publish(KEYS.ctl("status"), encode_control(Status()))
        await _until(lambda: len(estimates) == 2)
        first, answer = (decode_estimate(m.payload) for m in estimates.drain())
    assert first.counters["stacks_invalid"] == 0
    assert answer.k == 1 and answer.counters["stacks_invalid"] == 1
    assert answer.counters["status_requests"] == 1


# --------------------------------------------------------------------------- journal


@pytest.mark.parametrize("robot", ROBOTS)
def test_agent_journal_replay_rebuilds_the_identical_belief(
    lockstep_run: LockstepRun, robot: str
) -> None:
    journal, records = Journal.open(
        lockstep_run.journals / f"{robot}.log", {"robot": robot, "seed": SEED}
    )
    with journal:
        agent = _agent(robot, MemoryBus(), "lockstep", journal=journal)
        agent.replay(records)
    kinds = [r.kind for r in records]
    assert agent.counter_values()["replayed_frames"] == kinds.count("frame") == STEPS
    assert agent.counter_values()["replayed_stacks"] == kinds.count("stack") > 0
    assert agent.node.k == STEPS
    assert agent.node.current_stack().stamps() == lockstep_run.stamps[robot]
    final = lockstep_run.estimates[(robot, STEPS)].beliefs
    assert_same_snapshot(agent.node.distributed.snapshot(robot), final["distributed"], "D")
    assert_same_snapshot(agent.node.local.snapshot(robot), final["local"], "L")


@pytest.mark.asyncio
async def test_a_realtime_agents_journal_holds_its_stacks_and_replays_to_the_identical_belief(
    frames: dict[str, list[SensorFrame]], tmp_path: Path
) -> None:
    """Realtime: stacks merged between steps are journaled with the next step's commit, so a
    replay merges them at the same point and rebuilds exactly the belief."""
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    peers = _nodes()
    journal, records = Journal.open(tmp_path / "r2.log", {"robot": "r2", "seed": SEED})
    agent = _agent("r2", bus, "realtime", journal=journal)
    async with _running(agent):
        for k in range(1, STEPS + 1):
            for r in ("r1", "r3"):
                peers[r].on_frame(frames[r][k - 1])
                world.publish(KEYS.stack(r), peers[r].encoded_stack())
            await _until(lambda k=k: agent.node.counters.stacks_received == 2 * k)  # type: ignore[misc]
            world.publish(KEYS.frames("r2"), encode_frame(frames["r2"][k - 1]))
            await _until(lambda k=k: agent.node.k == k)  # type: ignore[misc]
        merged = agent.node.counters.stacks_merged
        live = agent.node
    assert merged > 0
    journal, records = Journal.open(tmp_path / "r2.log", {"robot": "r2", "seed": SEED})
    with journal:
        kinds = [r.kind for r in records]
        assert kinds.count("frame") == STEPS and kinds.count("stack") == merged
        again = _agent("r2", MemoryBus(), "realtime", journal=journal)
        again.replay(records)
    assert again.node.current_stack().stamps() == live.current_stack().stamps()
    assert_same_snapshot(
        again.node.distributed.snapshot("r2"), live.distributed.snapshot("r2"), "D"
    )
    assert_same_snapshot(again.node.local.snapshot("r2"), live.local.snapshot("r2"), "L")
    assert "r1" in live.distributed.stamps and "r3" in live.distributed.stamps


@pytest.mark.asyncio
async def test_a_lockstep_peer_that_started_late_still_gets_the_round_0_stack(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """r2 announces its round-0 stack before r3 listens; the timer must re-send it, or r3, ordered
    to hear r2 in round 1, waits forever."""
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    early = _agent("r2", bus, "lockstep", gossip_period=0.05)
    async with _running(early):
        await asyncio.sleep(0.1)  # r2's start-up announcement is gone
        late = _agent("r3", bus, "lockstep", gossip_period=0.05)
        async with _running(late):
            world.publish(KEYS.ctl("step"), encode_control(StepOrder(1, {"r3": ("r2",)})))
            world.publish(KEYS.frames("r3"), encode_frame(frames["r3"][0]))
            await _until(lambda: _stepped(late, 1))


# --------------------------------------------------------------------------- conductor rounds


async def _acknowledge(transport: MemoryTransport, robot: str, k: int, after: float) -> None:
    """An agent that answers round ``k`` with an estimate ``after`` seconds from now."""
    await asyncio.sleep(after)
    snap = _nodes()[robot].distributed.snapshot(robot)
    transport.publish(
        KEYS.estimate(robot), encode_estimate(EstimateMessage(robot, k, {"distributed": snap}, {}))
    )


@pytest.mark.asyncio
async def test_conductor_waits_for_a_slow_round_that_progresses_and_names_a_stuck_one(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """The step timeout counts from the last acknowledgement, not from the order: three agents
    answering 0.3 s apart each (0.9 s in all) finish a round whose timeout is 0.5 s; a round
    where one agent never answers fails 0.5 s after the last answer, naming that agent."""
    bus = MemoryBus()
    side = MemoryTransport(bus)
    conductor = Conductor(SCENARIO, frames, ROBOTS, side, KEYS, CHAIN, retry_period=0.05)
    await conductor.open()
    agent = MemoryTransport(bus)
    orders = Inbox(10_000)
    agent.subscribe(KEYS.ctl("step"), orders)
    await agent.open()
    try:
        slow = [_acknowledge(agent, r, 1, 0.3 * (i + 1)) for i, r in enumerate(ROBOTS)]
        await asyncio.gather(conductor.run_lockstep(1, step_timeout=0.5), *slow)
        assert [conductor.acked(r) for r in ROBOTS] == [1, 1, 1]
        # Round 2: r3 never answers.
        stuck = [_acknowledge(agent, r, 2, 0.3 * (i + 1)) for i, r in enumerate(ROBOTS[:2])]
        t0 = asyncio.get_running_loop().time()
        with pytest.raises(ConductorError, match=r"step 2: no estimate from \['r3'\]"):
            await asyncio.gather(conductor.run_lockstep(2, step_timeout=0.5), *stuck)
        waited = asyncio.get_running_loop().time() - t0
        assert waited >= 0.6 + 0.5  # the last answer at 0.6 s, then the timeout
        # Re-sent orders back off (0.05, 0.1, 0.2, then every 0.4 s): not one every 0.05 s.
        decoded = [decode_control(m.payload) for m in orders.drain()]
        round2 = [o for o in decoded if isinstance(o, StepOrder) and o.k == 2]
        assert 3 <= len(round2) - 1 <= 6, len(round2)
    finally:
        await agent.close()
        await side.close()


@contextlib.asynccontextmanager
async def _conductor_and_a_robot(
    frames: dict[str, list[SensorFrame]],
) -> AsyncIterator[tuple[Conductor, MemoryTransport]]:
    """A conductor of the chain and a bare transport on its bus to publish as the robots."""
    bus = MemoryBus()
    side = MemoryTransport(bus)
    conductor = Conductor(SCENARIO, frames, ROBOTS, side, KEYS, CHAIN)
    await conductor.open()
    agent = MemoryTransport(bus)
    await agent.open()
    try:
        yield conductor, agent
    finally:
        await agent.close()
        await side.close()


@pytest.mark.asyncio
async def test_realtime_conductor_sends_each_steps_links_a_step_ahead_too(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """With the frames of step k the conductor publishes each robot's links of step k on
    ``sim/links/<robot>`` and those of step k + 1 on ``sim/listen/<robot>``: the verdict sent
    ahead is the one obeyed when its step comes (links that change from step to step), and
    nothing goes ahead of the last frame."""
    bus = MemoryBus()
    side = MemoryTransport(bus)
    changing = Schedule(((1, 1, "r1", "r2"), (2, 3, "r2", "r3"), (3, STEPS, "r1", "r3")))
    conductor = Conductor(SCENARIO, frames, ROBOTS, side, KEYS, changing)
    await conductor.open()
    watcher = MemoryTransport(bus)
    obeyed, ahead = Inbox(100), Inbox(100)
    watcher.subscribe(KEYS.sim_links("r1"), obeyed)
    watcher.subscribe(KEYS.sim_listen("r1"), ahead)
    await watcher.open()
    try:
        await conductor.run_realtime(STEPS, 0.001, settle=0.0)
        await asyncio.sleep(0.05)
        links = {
            o.k: o.links
            for m in obeyed.drain()
            if isinstance(o := decode_control(m.payload), StepOrder)
        }
        sent = {
            o.k: o.links
            for m in ahead.drain()
            if isinstance(o := decode_control(m.payload), StepOrder)
        }
        assert sorted(links) == list(range(1, STEPS + 1))
        assert sorted(sent) == list(range(2, STEPS + 1))
        assert all(sent[k] == links[k] for k in sent)
        assert links[1]["r1"] == ("r2",) and links[2]["r1"] == () and links[3]["r1"] == ("r3",)
        # Each robot's own row on its own key: not the whole table (N² ids) to every robot.
        assert all(set(v) == {"r1"} for v in (*links.values(), *sent.values()))
    finally:
        await watcher.close()
        await side.close()


@pytest.mark.asyncio
async def test_conductor_scores_a_step_once_however_often_its_estimate_comes(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """Lock-step agents answer every re-sent order with their estimate: the conductor scores
    each (robot, step) once — the first estimate — counts the repeats, and keeps one step time
    each, while the repeats still refresh the counters."""
    async with _conductor_and_a_robot(frames) as (conductor, agent):
        scored: list[tuple[str, str, int]] = []
        record = conductor.scorer.record

        def counting(belief: str, robot: str, k: int, snap: BeliefSnapshot) -> None:
            scored.append((belief, robot, k))
            record(belief, robot, k, snap)

        conductor.scorer.record = counting  # type: ignore[method-assign]
        nodes = _nodes()
        snap = nodes["r1"].distributed.snapshot("r1")
        for i in range(4):
            counters = {"step_us_distributed": 1000 + i, "stacks_received": i}
            message = EstimateMessage("r1", 1, {"distributed": snap}, counters)
            agent.publish(KEYS.estimate("r1"), encode_estimate(message))
        other = EstimateMessage("r2", 1, {"distributed": nodes["r2"].distributed.snapshot("r2")})
        agent.publish(KEYS.estimate("r2"), encode_estimate(other))
        await asyncio.sleep(0.05)
        conductor.pump()
        assert scored == []  # scored after the run, not while the agents need the cores
        conductor.score_pending()
        c = conductor.collected
        assert scored == [("distributed", "r1", 1), ("distributed", "r2", 1)]
        assert c.received == {"r1": 4, "r2": 1} and c.repeated == 3
        assert c.step_ms["distributed"] == [1.0]
        assert c.counters["r1"]["stacks_received"] == 3  # the latest estimate's counters
        assert np.isfinite(c.metrics["distributed"]["robot_error"][0, 0])


@pytest.mark.asyncio
async def test_conductor_reads_an_estimates_head_as_it_comes_and_its_arrays_when_scoring(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """While the agents run, the conductor reads only an estimate's robot, step and counters; an
    estimate whose arrays are broken (a NaN weight) is counted as received then, and as invalid,
    not scored, when it is scored. A broken head is refused at once, and so is an estimate on
    another robot's key."""
    nodes = _nodes()
    good = encode_estimate(
        EstimateMessage("r2", 1, {"distributed": nodes["r2"].distributed.snapshot("r2")})
    )
    doc = msgpack.unpackb(
        encode_estimate(
            EstimateMessage("r1", 1, {"distributed": nodes["r1"].distributed.snapshot("r1")})
        )
    )
    weights = np.frombuffer(doc["beliefs"]["distributed"]["weights"]).copy()
    weights[0] = np.nan
    doc["beliefs"]["distributed"]["weights"] = weights.tobytes()
    broken_arrays = msgpack.packb(doc)
    doc["k"] = -1
    broken_head = msgpack.packb(doc)
    async with _conductor_and_a_robot(frames) as (conductor, agent):
        for robot, data in (("r2", good), ("r1", broken_arrays), ("r1", broken_head)):
            agent.publish(KEYS.estimate(robot), data)
        agent.publish(KEYS.estimate("r3"), good)  # r2's estimate on r3's key
        await asyncio.sleep(0.05)
        conductor.pump()
        c = conductor.collected
        assert (c.received, c.invalid) == ({"r1": 1, "r2": 1}, 2)
        conductor.score_pending()
        assert c.invalid == 3
        errors = c.metrics["distributed"]["robot_error"][:, 0]
        assert np.isfinite(errors).tolist() == [False, True, False]


@pytest.mark.asyncio
async def test_conductor_scores_during_the_run_only_what_exceeds_its_backlog(
    frames: dict[str, list[SensorFrame]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Scoring waits for the end of the run, but never holds more than MAX_UNSCORED_BYTES of
    estimates: beyond, the oldest are scored as they come."""
    nodes = _nodes()
    sizes = [
        len(
            encode_estimate(
                EstimateMessage(r, 1, {"distributed": nodes[r].distributed.snapshot(r)})
            )
        )
        for r in ROBOTS
    ]
    monkeypatch.setattr(conductor_module, "MAX_UNSCORED_BYTES", max(sizes))
    async with _conductor_and_a_robot(frames) as (conductor, agent):
        nodes = _nodes()
        for r in ROBOTS:
            message = EstimateMessage(r, 1, {"distributed": nodes[r].distributed.snapshot(r)})
            agent.publish(KEYS.estimate(r), encode_estimate(message))
        await asyncio.sleep(0.05)
        conductor.pump()
        errors = conductor.collected.metrics["distributed"]["robot_error"][:, 0]
        assert np.isfinite(errors).tolist() == [True, True, False]  # r3 waits
        conductor.score_pending()
        assert np.isfinite(conductor.collected.metrics["distributed"]["robot_error"][:, 0]).all()


@pytest.mark.asyncio
async def test_an_agent_that_subscribes_to_new_peers_gossips_again_once_subscribed() -> None:
    """What a new peer published while the subscription was being declared is lost: 50 ms after
    it subscribed, the agent gossips once more (its gossip period is far longer here), so that
    the peer learns what it lacks without waiting for a tick."""
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    watched = Inbox(64)
    world.subscribe(KEYS.stack("r1"), watched)
    agent = _agent("r1", bus, "realtime", simulation=True, listen_in_range=True)
    async with _running(agent) as (task,):
        await _until(lambda: agent.counter_values()["listen_changes"] == 1)
        await asyncio.sleep(0.2)
        before = len(watched.drain())
        world.publish(KEYS.sim_links("r1"), _links(1, {"r1": ("r2",)}))
        await _until(lambda: agent.stack_subscriptions.exprs == {KEYS.stack("r2")})
        assert not watched.drain()  # nothing at once: the subscription is being declared
        await _until(lambda: len(watched) >= 1)
        world.publish(KEYS.sim_links("r1"), _links(1, {"r1": ("r2",)}))  # the same peers: no echo
        await asyncio.sleep(0.2)
        assert len(watched.drain()) == 1 and before >= 1
        assert not task.done()


@pytest.mark.asyncio
@pytest.mark.parametrize("mode", ["lockstep", "realtime"])
async def test_a_flood_of_requests_never_displaces_a_stop(
    frames: dict[str, list[SensorFrame]], mode: str
) -> None:
    """Issue 43, findings 3 and 6: requests that any member may put (``ctl/need/<robot>``) wait
    in an inbox of their own, and control messages larger than the agent reads are dropped on
    arrival, so neither can push a Stop out of the control inbox before the loop reads it. A
    real time agent, which answers no round request, does not even subscribe to them (issue 47:
    every peer's requests for frames reached every agent)."""
    bus = MemoryBus()
    world = MemoryTransport(bus)
    await world.open()
    agent = _agent("r1", bus, mode)
    async with _running(agent) as (task,):
        if mode == "realtime":
            world.publish(KEYS.frames("r1"), encode_frame(frames["r1"][0]))
            await _until(lambda: agent.node.k == 1)
        else:
            await _until(lambda: agent.transport.is_open)  # type: ignore[attr-defined]
        # All of it is put before the agent's loop runs again: the Stop first, then a flood on
        # 3,000 distinct request keys (an insecure fleet lets anyone put there) and 40 control
        # messages of 1 MiB on the operator's own key.
        world.publish(KEYS.ctl("stop"), encode_control(Stop("the operator's")))
        need = encode_control(NeedFrames("r1", 1))
        for i in range(3000):
            world.publish(KEYS.ctl("need", f"x{i}"), need)
        for _ in range(40):
            world.publish(KEYS.ctl("status"), bytes(1 << 20))
        await asyncio.wait_for(task, 10)
        assert agent.stop_reason == "the operator's"
        if mode == "lockstep":
            assert agent.requests.dropped >= 3000 - agent.requests.capacity
        else:
            assert agent.requests.dropped == len(agent.requests) == 0
        assert agent.control.dropped == 40  # the 1 MiB messages, on arrival
