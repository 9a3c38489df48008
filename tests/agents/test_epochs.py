"""Versions and epochs (docs/wire.md): a robot that lost its journal starts its stamps again under
a higher epoch and is taken again by every peer; one whose clock went back moves above its
earlier life as soon as a peer shows it that life's slot; and a version ahead of what its owner
can have made by now is refused, counted and never relayed. Real agent cores, real codec, real
estimator; the journals are the shell's in-memory logs."""

from __future__ import annotations

import pytest

from agents.core import AgentCore, CoreSettings, Publish
from agents.node import CLOCK_SKEW_S, MAX_STEP_RATE, STAMP_SLACK
from agents.runtime import MemoryLog, execute_journal_actions
from agents.transport.base import Keys
from deploy.base.build import belief_model, make_node
from estimator.hybrid import BeliefConfig
from estimator.models import SensorFrame
from protocol.codec import StackMessage, decode, encode
from protocol.frames import encode_frame
from protocol.stack import Slot, Stack
from sim.loader import load_scenario
from sim.sensors import Simulator

SCENARIO = load_scenario("paper")
KEYS = Keys("t")
SEED = 5
NOW = 1_764_000_000.0  # the receivers' wall clock (s since the Unix epoch)
EPOCH = 1_763_999_000_000  # r1's first life began 1000 s before NOW (ms)


@pytest.fixture(scope="module")
def frames() -> dict[str, list[SensorFrame]]:
    return Simulator(SCENARIO, SEED).all_frames()


class Agent:
    """A core with its in-memory journal; keeps what it published on its stack key."""

    def __init__(self, robot: str, epoch: int, clock: float | None = NOW) -> None:
        model = belief_model(SCENARIO)
        start = SCENARIO.robot(robot).start

        def make():  # type: ignore[no-untyped-def]
            return make_node(robot, start, model, SEED, BeliefConfig(), epoch=epoch)

        self.log = MemoryLog()
        wall = None if clock is None else (lambda: clock)
        settings = CoreSettings(stack_gossip="full")  # every publication a whole stack
        self.core = AgentCore(make, KEYS, settings, self.log.records, wall_clock=wall)
        self.stacks: list[bytes] = []

    def _run(self, actions):  # type: ignore[no-untyped-def]
        for a in execute_journal_actions(self.log, actions):
            if isinstance(a, Publish) and a.key == KEYS.stack(self.core.robot):
                self.stacks.append(a.payload)

    def step(self, frame: SensorFrame) -> None:
        self._run(self.core.on_message(KEYS.frames(frame.robot), encode_frame(frame), 0.0))

    def hear(self, sender: str, payload: bytes) -> None:
        self._run(self.core.on_message(KEYS.stack(sender), payload, 0.0))

    def versions(self) -> dict[str, tuple[int, int]]:
        return self.core.node.current_stack().versions()


def _steps(agent: Agent, frames: dict[str, list[SensorFrame]], first: int, last: int) -> None:
    for k in range(first, last):
        agent.step(frames[agent.core.robot][k])


def test_a_robot_that_lost_its_journal_is_taken_again_under_its_new_epoch(frames) -> None:  # type: ignore[no-untyped-def]
    r2 = Agent("r2", EPOCH + 7)
    first_life = Agent("r1", EPOCH)
    _steps(first_life, frames, 0, 8)
    r2.hear("r1", first_life.stacks[-1])
    _steps(r2, frames, 0, 1)
    assert r2.versions()["r1"] == (EPOCH, 8)
    assert r2.core.node.distributed.versions["r1"] == (EPOCH, 8)
    # r1 lost its journal: a new life at step 0, under the epoch of its new start.
    second_life = Agent("r1", EPOCH + 60_000)
    _steps(second_life, frames, 0, 3)
    r2.hear("r1", second_life.stacks[-1])
    assert r2.versions()["r1"] == (EPOCH + 60_000, 3)
    _steps(r2, frames, 1, 2)
    assert r2.core.node.distributed.versions["r1"] == (EPOCH + 60_000, 3)
    # The first life's slot, relayed late by someone else, never comes back.
    r2.hear("r3", _relay("r3", first_life.stacks[-1]))
    assert r2.versions()["r1"] == (EPOCH + 60_000, 3)
    relayed = decode(r2.core.node.encoded_stack()).stack.versions()
    assert relayed["r1"] == (EPOCH + 60_000, 3)


def test_a_robot_whose_clock_went_back_moves_above_its_earlier_life(frames) -> None:  # type: ignore[no-untyped-def]
    r2 = Agent("r2", EPOCH + 7)
    first_life = Agent("r1", EPOCH)
    _steps(first_life, frames, 0, 8)
    r2.hear("r1", first_life.stacks[-1])
    # A robot without a real-time clock: its new life's epoch is *before* the first one's.
    second_life = Agent("r1", EPOCH - 3_600_000)
    _steps(second_life, frames, 0, 3)
    r2.hear("r1", second_life.stacks[-1])
    assert r2.versions()["r1"] == (EPOCH, 8)  # not newer: refused by the merge
    _steps(r2, frames, 0, 1)
    second_life.hear("r2", r2.stacks[-1])  # r2's stack holds the first life's slot of r1
    assert second_life.core.node.epoch == EPOCH + 1
    assert second_life.core.counter_values()["own_superseded"] == 1
    _steps(second_life, frames, 3, 4)
    r2.hear("r1", second_life.stacks[-1])
    assert r2.versions()["r1"] == (EPOCH + 1, 4)
    # The move is journaled with the stack that caused it: a restart from the journal keeps it.
    again = Agent("r1", EPOCH - 3_600_000)
    again.core.replay(second_life.log.records())
    assert again.core.node.epoch == EPOCH + 1 and again.versions()["r1"] == (EPOCH + 1, 4)


def _relay(sender: str, payload: bytes) -> bytes:
    """``payload``'s slots in a stack sent by ``sender``."""
    return encode(StackMessage(sender, None, decode(payload).stack, 1))


def _stack_with(slot: Slot) -> bytes:
    return encode(StackMessage("r3", None, Stack((slot,)), 1))


def test_a_version_ahead_of_its_owners_clock_is_refused_counted_and_never_relayed(frames) -> None:  # type: ignore[no-untyped-def]
    source = Agent("r1", EPOCH)
    _steps(source, frames, 0, 2)
    summary = decode(source.stacks[-1]).stack.by_owner()["r1"].summary
    now_ms = 1000 * (NOW + CLOCK_SKEW_S)
    reachable = int(MAX_STEP_RATE * (now_ms - EPOCH) / 1000 + STAMP_SLACK)
    r2 = Agent("r2", EPOCH)
    for slot in (
        Slot("r1", reachable + 1, summary, EPOCH),  # more steps than r1 can have taken
        Slot("r1", 1, summary, int(now_ms) + 1),  # an epoch after the receiver's clock
        Slot("r1", 9_999_999, summary, 0),  # the largest stamp: epoch 0 began in 1970, fine
    ):
        r2.hear("r3", _stack_with(slot))
    counters = r2.core.counter_values()
    assert counters["slots_implausible"] == 2
    assert r2.versions() == {"r1": (0, 9_999_999)}
    r2.hear("r3", _stack_with(Slot("r1", reachable, summary, EPOCH)))  # the bound itself
    assert r2.versions() == {"r1": (EPOCH, reachable)}
    assert decode(r2.core.node.encoded_stack()).stack.versions() == {"r1": (EPOCH, reachable)}
    # Without a clock (the in-process runner, replays in tests) there is no bound.
    unbounded = Agent("r2", EPOCH, clock=None)
    unbounded.hear("r3", _stack_with(Slot("r1", 1, summary, int(now_ms) + 1)))
    assert unbounded.core.counter_values()["slots_implausible"] == 0


def test_a_message_with_an_implausible_slot_still_tells_what_its_sender_holds(frames) -> None:  # type: ignore[no-untyped-def]
    """Delta gossip: the slot ahead of its owner's clock is refused, the sender's digest is
    still taken (otherwise one bad relayed slot would hide what a peer lacks for good)."""
    source = Agent("r1", EPOCH)
    _steps(source, frames, 0, 2)
    summary = decode(source.stacks[-1]).stack.by_owner()["r1"].summary
    now_ms = 1000 * (NOW + CLOCK_SKEW_S)
    bad = Slot("r1", 1, summary, int(now_ms) + 1)
    have = {"r1": (bad.epoch, 1), "r3": (EPOCH, 4)}
    r2 = Agent("r2", EPOCH)
    r2.hear("r3", encode(StackMessage("r3", None, Stack((bad,)), 1, have=have)))
    assert r2.core.counter_values()["slots_implausible"] == 1
    assert r2.versions() == {}
    assert r2.core.gossip.digests["r3"].have == have
