"""AgentCore, the sans-I/O agent, under bad input: every failure is counted and never fatal, a
failed step is never committed (the node is rolled back from the committed records), and every
buffer stays bounded. Real estimator, real codecs; the journal is the in-memory log of the shell
(tests/agents/test_runtime.py and tests/deploy/test_agent_process.py use real files)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import msgpack
import numpy as np
import pytest

import agents.recovery as recovery
from agents.control import (
    NeedFrames,
    NeedRound,
    Status,
    StepOrder,
    Stop,
    decode_control,
    encode_control,
)
from agents.core import (
    Action,
    AgentCore,
    CoreSettings,
    CutJournal,
    Halt,
    Hear,
    Publish,
    Quarantine,
)
from agents.journal import Record
from agents.node import RobotNode
from agents.rounds import GIVE_UP_ASKS
from agents.runtime import MemoryLog, execute_journal_actions
from agents.transport.base import Keys
from deploy.base.build import belief_model, make_node, sensor_field
from estimator.distributed import DistributedBelief
from estimator.hybrid import BeliefConfig
from estimator.models import Detection, SensorFrame
from estimator.summary import LocalSummary, ObjectClasses
from estimator.xi import Xi
from protocol.codec import StackMessage, decode, encode
from protocol.estimate import decode_estimate
from protocol.frames import encode_frame
from protocol.stack import Slot, Stack
from sim.loader import load_scenario
from sim.sensors import Detector, Simulator

SCENARIO = load_scenario("paper")
KEYS = Keys("t")
SEED = 3


@pytest.fixture(scope="module")
def frames() -> dict[str, list[SensorFrame]]:
    return Simulator(SCENARIO, SEED).all_frames()


def _factory(  # type: ignore[no-untyped-def]
    robot: str, roster: Sequence[str] | None = None, config: BeliefConfig | None = None
):
    model = belief_model(SCENARIO)

    def make() -> RobotNode:
        members = None if roster is None else frozenset(roster)
        start = SCENARIO.robot(robot).start
        return make_node(robot, start, model, SEED, config or BeliefConfig(), roster=members)

    return make


class Driver:
    """Feeds a core and carries out its journal actions on an in-memory log, like the shell."""

    def __init__(self, robot: str = "r1", mode: str = "realtime", **settings: object) -> None:
        self.log = MemoryLog()
        roster = settings.pop("roster", None)
        self.config = settings.pop("config", None)
        self.core = AgentCore(
            _factory(robot, roster, self.config),  # type: ignore[arg-type]
            KEYS,
            CoreSettings(mode=mode, **settings),  # type: ignore[arg-type]
            self.log.records,
        )
        self.quarantined: list[Quarantine] = []
        self.published: list[Publish] = []

    def run(self, actions: Sequence[Action]) -> None:
        self.quarantined += [a for a in actions if isinstance(a, Quarantine)]
        rest = execute_journal_actions(self.log, actions)
        self.published += [a for a in rest if isinstance(a, Publish)]

    def send(self, key: str, payload: bytes) -> None:
        self.run(self.core.on_message(key, payload, 0.0))

    def frame(self, frame: SensorFrame) -> None:
        self.send(KEYS.frames(frame.robot), encode_frame(frame))


def _replayed(driver: Driver, robot: str = "r1") -> AgentCore:
    fresh = AgentCore(
        _factory(robot, config=driver.config), KEYS, driver.core.settings, driver.log.records
    )
    assert fresh.replay(driver.log.records()) == []
    return fresh


def _same_belief(a: RobotNode, b: RobotNode) -> None:
    for x, y in ((a.distributed, b.distributed), (a.local, b.local)):
        sx, sy = x.snapshot(a.robot), y.snapshot(b.robot)
        assert sx.object_ids == sy.object_ids
        np.testing.assert_array_equal(sx.classes, sy.classes)
        np.testing.assert_array_equal(sx.weights, sy.weights)
        np.testing.assert_array_equal(sx.object_pose, sy.object_pose)


def _poisoned(frame: SensorFrame) -> SensorFrame:
    """Finite on the wire, but the classifier's likelihood overflows: the step raises."""
    m = SCENARIO.num_classes
    det = Detection(999, np.array([1.0, 0.0, 0.0]), -1e300 * np.ones(m))
    return SensorFrame(
        frame.robot, frame.k, frame.odometry, (*frame.detections, det), frame.true_pose
    )


def test_a_step_that_raises_is_rolled_back_quarantined_and_taken_on_odometry(frames) -> None:  # type: ignore[no-untyped-def]
    d = Driver()
    d.frame(frames["r1"][0])
    bad = _poisoned(frames["r1"][1])
    d.frame(bad)
    c = d.core.counter_values()
    assert (c["steps_failed"], c["frames_quarantined"], c["frames_degraded"]) == (1, 1, 1)
    assert c["restores"] >= 1 and d.core.node.k == 2
    assert [q.kind for q in d.quarantined] == ["frame"]
    assert d.quarantined[0].body == encode_frame(bad)
    assert "FloatingPointError" in d.quarantined[0].reason
    d.frame(frames["r1"][2])  # and it goes on
    assert d.core.node.k == 3
    # The committed records hold the odometry-only step: a replay rebuilds the same belief.
    assert [r.kind for r in d.log.records()] == ["frame"] * 3
    _same_belief(_replayed(d).node, d.core.node)
    # The same failing bytes again (a re-sent frame) are not tried a second time.
    d.frame(bad)
    assert d.core.counter_values()["steps_failed"] == 1


def test_a_step_that_fails_after_window_rebuilds_rolls_back_across_them(frames) -> None:  # type: ignore[no-untyped-def]
    """A window of 4 steps (``BeliefConfig.window``): by step 20 both smoothers have
    marginalised their old poses several times. A failing step is rolled back from the journal,
    whose replay must rebuild at the same steps; the belief then equals a fresh replay's."""
    d = Driver(config=BeliefConfig(window=4))
    for f in frames["r1"][:20]:
        d.frame(f)
    local = d.core.node.local.hypotheses[0].continuous.isam
    rebuilt = local.rebuilds
    assert rebuilt >= 3  # the roll-back below crosses rebuilds
    d.frame(_poisoned(frames["r1"][20]))
    c = d.core.counter_values()
    assert (c["steps_failed"], c["frames_degraded"], d.core.node.k) == (1, 1, 21)
    assert d.core.node.local.slot_fit_refused == 0  # an honest fused estimate fits L's data
    for f in frames["r1"][21:30]:
        d.frame(f)
    node = d.core.node
    assert node.k == 30 and node.local.hypotheses[0].continuous.isam.rebuilds > rebuilt
    _same_belief(_replayed(d).node, node)


def _seen_something(robot: str, frames: dict[str, list[SensorFrame]]) -> RobotNode:
    """A peer stepped until its own slot exists."""
    node = _factory(robot)()
    for f in frames[robot]:
        node.on_frame(f)
        if len(node.current_stack()):
            return node
    raise AssertionError(f"{robot} never sees an object")


def test_a_slot_whose_fusion_raises_is_refused_and_the_step_goes_on(frames, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    peer = _seen_something("r2", frames)
    d = Driver()
    d.frame(frames["r1"][0])
    original = DistributedBelief.integrate

    def integrate(self, slots, settle=True):  # type: ignore[no-untyped-def]
        if any(s.owner == "r2" for s in slots):
            self.hypotheses[0].log_weight = float("nan")  # half-fused, then raise
            raise RuntimeError("Indeterminate linear system (forged slot)")
        return original(self, slots, settle)

    monkeypatch.setattr(DistributedBelief, "integrate", integrate)
    stack = peer.encoded_stack()
    d.send(KEYS.stack("r2"), stack)
    d.frame(frames["r1"][1])
    c = d.core.counter_values()
    assert c["steps_failed"] == 1 and c["frames_quarantined"] == 0 and d.core.node.k == 2
    assert c["slots_refused"] == 1
    assert "r2" not in d.core.node.distributed.stamps
    assert np.isfinite([h.log_weight for h in d.core.node.distributed.hypotheses]).all()
    d.send(KEYS.stack("r2"), stack)  # relayed again: refused before it is merged
    assert d.core.counter_values()["slots_refused"] == 2
    assert d.core.node.stack.stamps() == {"r1": 2}


def test_frames_orders_and_rounds_stay_within_the_window(frames) -> None:  # type: ignore[no-untyped-def]
    d = Driver(mode="lockstep", window=8)
    for k in range(1, 5001):
        d.send(KEYS.ctl("step"), encode_control(StepOrder(k, {"r1": ("r2",)})))
    assert d.core.rounds is not None and len(d.core.rounds.orders) == 8
    assert d.core.counter_values()["orders_ahead"] == 5000 - 8
    far = SensorFrame("r1", 500, frames["r1"][0].odometry, (), frames["r1"][0].true_pose)
    d.frame(far)
    assert d.core.counters.frames_ahead == 1 and not d.core._frames
    peer = _factory("r2")()
    for k in range(1, 40):
        peer.on_frame(frames["r2"][k - 1])
        d.send(KEYS.stack("r2"), peer.encoded_stack())
    assert max(step for _, step in d.core.rounds.held) <= 8
    assert d.core.counter_values()["rounds_dropped"] == 0


def test_control_messages_are_taken_only_on_their_own_key() -> None:
    """A member's certificate lets it put on ctl/need/<its robot> only: a Stop, Status or step
    order there — or another robot's request — is refused and counted, never obeyed (issue 43,
    finding 1: one Stop on ctl/need/r3 halted the whole fleet)."""
    d = Driver(mode="lockstep")
    d.core.start(0.0)
    misplaced = [
        (KEYS.ctl("need", "r3"), Stop("a member's stop")),
        (KEYS.ctl("need", "r3"), Status()),
        (KEYS.ctl("need", "r3"), StepOrder(1, {"r1": ()})),
        (KEYS.ctl("need", "r3"), NeedFrames("r2", 1)),  # r2's request on r3's key
        (KEYS.ctl("status"), Stop("stop on the status key")),
        (KEYS.ctl("step"), Status()),
        (KEYS.ctl("stop"), StepOrder(1, {"r1": ()})),
        (KEYS.ctl("anything"), Stop("an unknown key")),
    ]
    for key, message in misplaced:
        actions = d.core.on_message(key, encode_control(message), 1.0)
        assert not any(isinstance(a, (Halt, Publish)) for a in actions), (key, message)
    assert d.core.counters.invalid_control == len(misplaced) and not d.core.stop_reason
    assert d.core.rounds is not None and not d.core.rounds.orders
    assert d.core.counters.status_requests == 0
    # Each on its own key is obeyed.
    d.send(KEYS.ctl("need", "r3"), encode_control(NeedFrames("r3", 1)))
    d.send(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": ()})))
    assert 1 in d.core.rounds.orders and d.core.counters.invalid_control == len(misplaced)
    assert any(
        isinstance(a, Publish)
        for a in d.core.on_message(KEYS.ctl("status"), encode_control(Status()), 2.0)
    )
    assert any(
        isinstance(a, Halt)
        for a in d.core.on_message(KEYS.ctl("stop"), encode_control(Stop("end")), 3.0)
    )


def test_a_batch_of_status_requests_is_answered_with_one_estimate(frames) -> None:  # type: ignore[no-untyped-def]
    """Issue 43, finding 3: 2,000 status requests a second made every agent publish 2,000
    estimates; now a batch costs one, made after the batch's steps (so it is the newest)."""
    d = Driver()
    status = (KEYS.ctl("status"), encode_control(Status()))
    frame = (KEYS.frames("r1"), encode_frame(frames["r1"][0]))
    actions = d.core.on_messages([status] * 500 + [frame] + [status] * 500, 1.0)
    estimates = [a for a in actions if isinstance(a, Publish) and a.key == KEYS.estimate("r1")]
    assert len(estimates) == 2  # the step's own, and one for every request of the batch
    assert decode_estimate(estimates[-1].payload).k == 1
    assert d.core.counters.status_requests == 1000
    again = d.core.on_messages([status] * 3, 2.0)
    assert sum(isinstance(a, Publish) and a.key == KEYS.estimate("r1") for a in again) == 1


def test_oversized_and_malformed_control_is_counted_unread() -> None:
    d = Driver(max_control_bytes=4096)
    huge = encode_control(
        StepOrder(1, {f"r{i}": tuple(f"s{j}" for j in range(20)) for i in range(100)})
    )
    assert len(huge) > 4096
    d.send(KEYS.ctl("step"), huge)
    d.send(KEYS.ctl("step"), b"\xc1")
    d.send(KEYS.ctl("step"), msgpack.packb({"type": "step", "k": -1, "links": {}}))
    assert d.core.counters.invalid_control == 3
    assert d.core.rounds is None  # real time keeps no orders at all


def test_slots_of_owners_outside_the_roster_are_refused(frames) -> None:  # type: ignore[no-untyped-def]
    d = Driver(roster=("r1", "r2"))
    stranger = _seen_something("r3", frames)
    d.send(KEYS.stack("r3"), stranger.encoded_stack())
    assert d.core.node.counters.foreign_slots == 1
    assert "r3" not in d.core.node.stack.stamps()


def test_replay_quarantines_a_bad_record_and_cuts_the_journal_there(frames) -> None:  # type: ignore[no-untyped-def]
    d = Driver()
    for f in frames["r1"][:3]:
        d.frame(f)
    records = d.log.records()
    broken = [
        records[0],
        Record("stack", b"\x93not a stack"),
        records[1],
        Record("frame", b"\x00"),
        records[2],
    ]
    log = MemoryLog()
    for r in broken:
        log.append(r.kind, r.body)
    log.commit()
    core = AgentCore(_factory("r1"), KEYS, CoreSettings(), log.records)
    actions = core.replay(broken)
    quarantined = [a for a in actions if isinstance(a, Quarantine)]
    assert [(q.kind, q.index) for q in quarantined] == [("stack", 1), ("frame", 3)]
    assert CutJournal(3) in actions
    assert core.node.k == 2 and core.counters.records_quarantined == 2
    _same_belief(core.node, _replayed_prefix(records[:2]))


def _replayed_prefix(records: list[Record]) -> RobotNode:
    core = AgentCore(_factory("r1"), KEYS, CoreSettings())
    core.replay(records)
    return core.node


def test_a_stack_that_would_overflow_the_own_stack_is_refused(frames) -> None:  # type: ignore[no-untyped-def]
    """Held slots stay within what a stack may carry, so the own gossip always encodes."""
    d = Driver()
    node = d.core.node
    limits = node.limits
    peer = _seen_something("r2", frames)
    slot = peer.current_stack().by_owner()["r2"]
    from protocol.stack import Slot, Stack

    forged = Stack(tuple(Slot(f"x{i}", 1, slot.summary) for i in range(limits.max_slots)))
    d.send(KEYS.stack("r2"), encode(StackMessage("r2", None, forged, 1)))
    assert len(node.stack) <= limits.max_slots - 1
    d.frame(frames["r1"][0])
    assert any(p.key == KEYS.stack("r1") for p in d.published)  # own stack still encodes


def test_an_own_slot_outside_the_limits_is_never_sent_and_the_rest_still_is(frames) -> None:  # type: ignore[no-untyped-def]
    from protocol.codec import Limits, decode

    tight = Limits(num_classes=SCENARIO.num_classes, world_extent=5.0)  # r1 is at y ≈ −8 m
    model = belief_model(SCENARIO)
    node = make_node("r1", SCENARIO.robot("r1").start, model, SEED, BeliefConfig(), limits=tight)
    peer = _seen_something("r2", frames)  # its objects lie within 3.7 m of the origin
    assert node.on_stack(encode(StackMessage("r2", None, peer.current_stack(), peer.k), tight))
    for f in frames["r1"]:
        node.on_frame(f)
        if len(node.current_stack()) == 2:
            break
    message = decode(node.encoded_stack(), tight)
    assert message.position is None
    assert [s.owner for s in message.stack] == ["r2"]
    assert node.counters.own_slot_invalid == 1


def test_lockstep_ticks_back_off_while_the_stacks_are_unchanged(frames) -> None:  # type: ignore[no-untyped-def]
    """A round's stacks go out when it ends; the ticks only repair a loss. With nothing new,
    the pair (this round's, the previous round's) is re-sent after 1, 2, 4, 8, 8 ... periods;
    a new round starts over at one period. Real time keeps a tick every period."""
    d = Driver(mode="lockstep")
    d.run(d.core.start(0.0))

    def ticks(count: int) -> list[int]:
        sent = []
        for i in range(1, count + 1):
            stacks = [a for a in d.core.on_timer(float(i)) if a.key == KEYS.stack("r1")]
            if stacks:
                sent.append(i)
        return sent

    assert ticks(40) == [1, 2, 4, 8, 16, 24, 32, 40]
    d.send(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": ()})))
    d.frame(frames["r1"][0])
    assert d.core.node.k == 1  # a new round: its stack and the previous one
    assert ticks(5) == [1, 2, 4]
    r = Driver(mode="realtime")
    r.run(r.core.start(0.0))
    assert all(
        [a for a in r.core.on_timer(float(i)) if a.key == KEYS.stack("r1")] for i in range(1, 12)
    )


def test_lockstep_ticks_keep_backing_off_when_a_round_stack_changes_within_the_round(
    frames,
) -> None:  # type: ignore[no-untyped-def]
    """What a round's stack carries shrinks as peers' digests come (they hold the slots
    already); the ticks of the round keep their back-off instead of starting over at one period
    (with 50 agents, starting over at every change re-sent stacks several times a period)."""
    d = Driver(mode="lockstep", roster=["r1", "r2"])
    d.run(d.core.start(0.0))
    d.send(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": ()})))
    d.frame(frames["r1"][0])
    assert d.core.node.k == 1 and d.core.node.current_stack().stamps() == {"r1": 1}

    def sent(first: int, last: int) -> list[int]:
        return [
            i
            for i in range(first, last + 1)
            if any(a.key == KEYS.stack("r1") for a in d.core.on_timer(float(i)))
        ]

    assert sent(1, 5) == [1, 2, 4]
    before = d.core._out.stack
    have = d.core.node.current_stack().versions()  # r2 holds r1's slot now
    d.send(KEYS.stack("r2"), encode(StackMessage("r2", None, Stack(), 1, have=have)))
    assert d.core._out.stack != before  # the round's stack no longer carries the slot
    assert sent(6, 17) == [8, 16]


def test_a_lockstep_agent_does_not_ask_for_the_frame_it_is_stepping_with(frames) -> None:  # type: ignore[no-untyped-def]
    """The gossip timer runs while a step does: once the frame of the step is here, it stops
    asking the conductor for it (each request made the conductor send the frame again, and each
    copy was answered with an estimate: 400 estimates per agent in a 50-agent launch)."""
    ticks: list[list[Action]] = []
    cores: list[AgentCore] = []
    make = _factory("r1")

    class Watched(RobotNode):
        def on_frame(self, frame: SensorFrame, fuse: bool = True, clock=None):  # type: ignore[no-untyped-def]
            ticks.append(cores[0].on_timer(100.0 + len(ticks)))  # a tick during the step
            return super().on_frame(frame, fuse, clock)

    def make_watched() -> RobotNode:
        node = make()
        node.__class__ = Watched
        return node

    core = AgentCore(make_watched, KEYS, CoreSettings(mode="lockstep"))
    cores.append(core)
    core.start(0.0)
    core.on_message(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": ()})), 1.0)
    assert any(a.key == KEYS.ctl("need", "r1") for a in core.on_timer(2.0))  # it lacks frame 1
    core.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][0]), 3.0)
    assert core.node.k == 1 and len(ticks) == 1
    assert not any(a.key == KEYS.ctl("need", "r1") for a in ticks[0])


def test_a_frame_of_the_current_step_sent_again_is_answered_at_most_once_a_period(frames) -> None:  # type: ignore[no-untyped-def]
    """A frame of the step the agent is at means the conductor lacks its estimate: answered,
    but at most once a gossip period however many copies come."""
    d = Driver(mode="lockstep", gossip_period=0.5)
    d.run(d.core.start(0.0))
    d.send(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": ()})))
    d.frame(frames["r1"][0])
    data = encode_frame(frames["r1"][0])

    def answered(now: float) -> bool:
        actions = d.core.on_message(KEYS.frames("r1"), data, now)
        return any(isinstance(a, Publish) and a.key == KEYS.estimate("r1") for a in actions)

    times = [1.0, 1.1, 1.2, 1.5, 1.7, 2.1, 5.0]
    assert [t for t in times if answered(t)] == [1.0, 1.5, 2.1, 5.0]


def _round_2_waiting_for_r1(frames) -> tuple[Driver, Driver]:  # type: ignore[no-untyped-def]
    """Lock-step r1 and r2 after step 1; r2 has the order and frame of step 2, whose round merges
    r1's round-1 stack, which has not come."""
    roster = ["r1", "r2"]
    a = Driver("r1", mode="lockstep", roster=roster, gossip_period=0.5)
    b = Driver("r2", mode="lockstep", roster=roster, gossip_period=0.5)
    for d in (a, b):
        d.run(d.core.start(0.0))
        d.send(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": (), "r2": ()})))
        d.frame(frames[d.core.robot][0])
        assert d.core.node.k == 1
    b.send(KEYS.ctl("step"), encode_control(StepOrder(2, {"r1": (), "r2": ("r1",)})))
    b.frame(frames["r2"][1])
    assert b.core.node.k == 1
    return a, b


def test_a_lockstep_agent_asks_for_a_round_stack_that_did_not_come_and_gets_it(frames) -> None:  # type: ignore[no-untyped-def]
    """r2's round 2 merges r1's stack of round 1, which was lost: a gossip period after the
    order and frame are there, r2 asks r1 for it (``NeedRound`` on its own ``ctl/need`` key),
    at most once a period; r1 sends it again at once — at most once a period however many ask,
    and never for a request on another robot's key — and r2 steps."""
    a, b = _round_2_waiting_for_r1(frames)  # r1's round-1 stack never came

    def asked(now: float) -> list[Publish]:
        actions = b.core.on_timer(now)
        return [x for x in actions if isinstance(x, Publish) and x.key == KEYS.ctl("need", "r2")]

    assert asked(10.0) == [] and asked(10.3) == []  # missing for less than a period
    (request,) = asked(10.6)
    assert decode_control(request.payload) == NeedRound("r2", 1, ("r1",))
    assert asked(10.8) == [] and len(asked(11.2)) == 1
    # r1 answers on the worker, once a period; a request on r3's key is not r2's
    assert a.core.on_message(KEYS.ctl("need", "r3"), request.payload, 20.0) == []
    (answer,) = a.core.on_message(KEYS.ctl("need", "r2"), request.payload, 20.0)
    assert a.core.on_message(KEYS.ctl("need", "r2"), request.payload, 20.2) == []
    assert answer.key == KEYS.stack("r1") and decode(answer.payload).step == 1
    b.send(answer.key, answer.payload)
    assert b.core.node.k == 2
    assert asked(30.0) == [] and asked(31.0) == []  # nothing missing any more
    counts = a.core.counter_values(), b.core.counter_values()
    assert (counts[0]["rounds_resent"], counts[1]["round_requests"]) == (1, 2)


def _own_slot_forged(node: RobotNode, info: float, step: int) -> bytes:
    """``node``'s own slot with information ``info``·I on its objects: within the wire's caps,
    beyond what ``step`` steps of detections can give (the belief gate's information bound)."""
    own = next(s for s in node.current_stack() if s.owner == node.robot)
    po = own.summary.per_object
    assert po is not None and len(own.summary.object_ids) > 0
    d = po.xi.dim
    n = len(own.summary.object_ids)
    xi = Xi(po.xi.lin, info * np.eye(d * n), np.zeros(d * n))
    summary = LocalSummary(own.summary.object_ids, (), ObjectClasses(po.log_phi, xi))
    slot = Slot(node.robot, own.version[1], summary, node.epoch)
    return encode(StackMessage(node.robot, node.position, Stack((slot,)), step), node.limits)


def test_a_lockstep_round_whose_senders_own_slot_is_gated_completes_without_it(frames) -> None:  # type: ignore[no-untyped-def]
    """r2's round 2 merges r1's round-1 stack, and r2's belief gate refuses r1's own slot in it
    (a drifted peer on real data, or a member that is the attacker). Copies that came before r2
    asked never complete the round — an attacker's forged copy published ahead of the round
    must not beat the honest one, which then wins — but once r1 has been asked and a copy comes
    in answer, the round completes without r1: r2 steps, merges nothing of r1 and counts the
    refusal, as the in-process runner does. (Found on UTIAS Dataset 7: a five-robot lock-step
    launch stalled at step 32 for good.)"""
    a, b = _round_2_waiting_for_r1(frames)
    forged = _own_slot_forged(a.core.node, 1e9, 1)
    for now in (1.0, 1.3, 9.0):
        b.run(b.core.on_message(KEYS.stack("r1"), forged, now))
        assert b.core.node.k == 1  # refused, and not asked for yet

    def asks(now: float) -> list[NeedRound]:
        actions = b.core.on_timer(now)
        return [decode_control(x.payload) for x in actions if x.key == KEYS.ctl("need", "r2")]

    assert asks(9.1) == []  # missing (or not heard) for less than a period
    times = [9.7 + 0.6 * i for i in range(GIVE_UP_ASKS)]
    for now in times[:-1]:
        assert asks(now) == [NeedRound("r2", 1, ("r1",))]
        b.run(b.core.on_message(KEYS.stack("r1"), forged, now + 0.1))
        assert b.core.node.k == 1  # fewer than GIVE_UP_ASKS requests: the honest copy may come
    assert asks(times[-1]) == [NeedRound("r2", 1, ("r1",))]
    b.run(b.core.on_message(KEYS.stack("r1"), forged, times[-1] + 0.1))  # sent again on request
    assert b.core.node.k == 2
    assert b.core.node.stack.version_of("r1") is None
    assert b.core.counter_values()["slots_rejected"] == 1  # counted by the merge that refused it
    # The honest copy wins over the forged ones that came first, however many.
    a, b = _round_2_waiting_for_r1(frames)
    honest = [p.payload for p in a.published if p.key == KEYS.stack("r1")][-1]
    assert decode(honest).step == 1
    for i, info in enumerate((1e9, 1e8, 1e7, 1e6)):  # more distinct forgeries than are kept
        b.run(b.core.on_message(KEYS.stack("r1"), _own_slot_forged(a.core.node, info, 1), i))
    b.run(b.core.on_message(KEYS.stack("r1"), honest, 5.0))
    assert b.core.node.k == 2 and b.core.node.stack.version_of("r1") is not None


def test_lockstep_ticks_of_a_large_fleet_back_off_to_two_periods_per_peer() -> None:
    """In a roster of N robots every agent re-sends to N − 1 peers: the back-off grows to
    2 (N − 1) periods (38 for 20 robots), so each agent receives about one re-sent stack every two
    periods whatever N; a fleet of up to 5 robots keeps the cap of 8."""
    for robots, want in ((20, [1, 2, 4, 8, 16, 32, 64, 102]), (5, [1, 2, 4, 8, 16, 24, 32])):
        roster = ["r1", "r2", "r3"] + [f"x{i}" for i in range(robots - 3)]
        d = Driver(mode="lockstep", roster=roster)
        d.run(d.core.start(0.0))
        sent = [
            i
            for i in range(1, want[-1] + 1)
            if any(a.key == KEYS.stack("r1") for a in d.core.on_timer(float(i)))
        ]
        assert sent == want, robots


def test_a_repeated_order_is_answered_with_the_estimate_at_backed_off_times(frames) -> None:  # type: ignore[no-untyped-def]
    """The conductor re-orders the whole fleet for one late agent; an agent answers a repeated
    order of its round at once, then after 1, 2, 4 ... gossip periods (0.5 s here)."""
    d = Driver(mode="lockstep", gossip_period=0.5)
    d.run(d.core.start(0.0))
    order = encode_control(StepOrder(1, {"r1": ()}))
    d.send(KEYS.ctl("step"), order)
    d.frame(frames["r1"][0])
    assert d.core.node.k == 1

    def answered(now: float) -> bool:
        actions = d.core.on_message(KEYS.ctl("step"), order, now)
        return any(isinstance(a, Publish) and a.key == KEYS.estimate("r1") for a in actions)

    times = [1.0, 1.1, 1.4, 1.5, 2.0, 2.4, 2.5, 3.0, 4.5, 4.6]
    assert [t for t in times if answered(t)] == [1.0, 1.5, 2.5, 4.5]


def test_repeated_orders_of_a_large_fleet_are_answered_at_longer_backed_off_times(frames) -> None:  # type: ignore[no-untyped-def]
    """With N robots the conductor's repeated order is answered by N − 1 other agents too: the
    answers back off to 2 (N − 1) gossip periods (19 s for 20 robots at 0.5 s) instead of 8."""
    for robots, want in (
        (3, [1.0, 1.5, 2.5, 4.5, 8.5, 12.5, 16.5]),
        (20, [1.0, 1.5, 2.5, 4.5, 8.5, 16.5]),
    ):
        roster = ["r1", "r2", "r3"] + [f"x{i}" for i in range(robots - 3)]
        d = Driver(mode="lockstep", gossip_period=0.5, roster=roster)
        d.run(d.core.start(0.0))
        order = encode_control(StepOrder(1, {"r1": ()}))
        d.send(KEYS.ctl("step"), order)
        d.frame(frames["r1"][0])
        assert d.core.node.k == 1
        times = [1.0, 1.5, 2.5, 4.5, 8.5, 12.5, 16.5]
        got = [
            t
            for t in times
            if any(
                isinstance(a, Publish) and a.key == KEYS.estimate("r1")
                for a in d.core.on_message(KEYS.ctl("step"), order, t)
            )
        ]
        assert got == want, robots


def test_an_order_that_names_the_robots_it_waits_for_is_answered_by_those_only(frames) -> None:  # type: ignore[no-untyped-def]
    """A re-sent order naming the robots whose estimate is missing: an agent it names answers at
    once and again at most once a gossip period (no back-off: its answers were lost); one it
    does not name stays silent, however often the order comes."""
    d = Driver(mode="lockstep", gossip_period=0.5)
    d.run(d.core.start(0.0))
    d.send(KEYS.ctl("step"), encode_control(StepOrder(1, {"r1": ()})))
    d.frame(frames["r1"][0])
    assert d.core.node.k == 1

    def answered(order: StepOrder, now: float) -> bool:
        actions = d.core.on_message(KEYS.ctl("step"), encode_control(order), now)
        return any(isinstance(a, Publish) and a.key == KEYS.estimate("r1") for a in actions)

    named = StepOrder(1, {"r1": ()}, waiting=("r2", "r1"))
    times = [1.0, 1.2, 1.5, 1.6, 2.0, 2.1, 2.6, 9.0, 9.1]
    assert [t for t in times if answered(named, t)] == [1.0, 1.5, 2.0, 2.6, 9.0]
    others = StepOrder(1, {"r1": ()}, waiting=("r2",))
    assert not any(answered(others, t) for t in (10.0, 11.0, 20.0, 60.0))
    assert not any(answered(StepOrder(1, {"r1": ()}, waiting=()), t) for t in (61.0, 70.0))


def test_a_lockstep_agent_parses_a_buffered_slot_version_once(frames) -> None:  # type: ignore[no-untyped-def]
    """A stack for a later round waits in the buffer, and its copies keep coming (re-sends,
    relays): the agent parses each slot version once and takes it from what it parsed for every
    later copy with the same bytes; the round then merges what a fresh decode gives."""
    peer = _factory("r2")()
    while not peer.current_stack():
        peer.on_frame(frames["r2"][peer.k])
    data = peer.encoded_stack()  # r2's first slot, after its step K: for r1's round K + 1
    big_k = peer.k
    d = Driver(mode="lockstep")
    d.run(d.core.start(0.0))

    def round_(k: int, links: tuple[str, ...] = ()) -> None:
        d.send(KEYS.ctl("step"), encode_control(StepOrder(k, {"r1": links})))
        d.frame(frames["r1"][k - 1])
        assert d.core.node.k == k

    for k in range(1, big_k):
        round_(k)
    for _ in range(5):
        d.send(KEYS.stack("r2"), data)
    c = d.core.node.counters
    assert (c.slots_decoded, c.slots_reused, c.slots_skipped, c.invalid) == (1, 4, 0, 0)
    round_(big_k)
    d.send(KEYS.stack("r2"), data)  # one more copy while its round is pending
    round_(big_k + 1, ("r2",))
    assert (c.slots_decoded, c.slots_reused) == (1, 5)
    held = d.core.node.stack.by_owner()["r2"]
    fresh = decode(data).stack.by_owner()["r2"]
    assert held.version == fresh.version == (0, big_k)
    assert held.wire is not None and fresh.wire is not None and held.wire.data == fresh.wire.data
    assert d.core.node.distributed.stamps == {"r2": big_k}
    # Held now: a later copy is skipped unparsed, and the parsed slot is let go.
    d.send(KEYS.stack("r2"), data)
    assert (c.slots_decoded, c.slots_reused, c.slots_skipped) == (1, 5, 1)
    assert not d.core.node._parsed


def test_a_simulated_agent_does_not_read_the_stacks_of_robots_out_of_range() -> None:
    """A simulated radio: what a robot out of range sends is counted as received and out of
    range, and never decoded (garbage from it is not even found invalid); what a robot in range
    sends is read and judged."""
    d = Driver(mode="realtime", simulation=True)
    d.run(d.core.start(0.0))
    links = StepOrder(1, {"r1": ("r3",)})
    d.send(KEYS.sim_links("r1"), encode_control(links))
    d.send(KEYS.stack("r2"), b"\xc1 not a stack")
    c = d.core.counter_values()
    assert (c["stacks_received"], c["ignored_out_of_range"], c["stacks_invalid"]) == (1, 1, 0)
    d.send(KEYS.stack("r3"), b"\xc1 not a stack")
    c = d.core.counter_values()
    assert (c["stacks_received"], c["ignored_out_of_range"], c["stacks_invalid"]) == (2, 1, 1)


def test_a_simulated_agent_wakes_only_for_the_stacks_of_robots_it_will_hear() -> None:
    """``Hear``: the keys (stacks, and pushes to this robot) of the robots heard under the links
    due at the coming step and under
    every later links already received (so the shell never keeps back a stack the core would
    read), without the agent's own; again only when that set changes; none in lock-step or off
    a simulation (every stack wakes the agent there)."""

    def hears(d: Driver, k: int, links: dict[str, tuple[str, ...]]) -> list[frozenset[str] | None]:
        order = encode_control(StepOrder(k, links))
        actions = d.core.on_messages([(KEYS.sim_links("r1"), order)], 0.0)
        return [a.keys for a in actions if isinstance(a, Hear)]

    def keys(*robots: str) -> frozenset[str]:  # their stacks, and their pushes to r1
        return frozenset(k for r in robots for k in (KEYS.stack(r), KEYS.stack_to(r, "r1")))

    d = Driver(mode="realtime", simulation=True)
    d.run(d.core.start(0.0))
    assert hears(d, 1, {"r1": ("r1", "r3")}) == [keys("r3")]
    assert hears(d, 1, {"r1": ("r3", "r1")}) == []  # the same robots: nothing to say
    # Links for step 2 already here while step 1 is coming: both steps' robots wake it.
    assert hears(d, 2, {"r1": ("r2",)}) == [keys("r2", "r3")]
    for other in (Driver(mode="lockstep", simulation=True), Driver(mode="realtime")):
        other.run(other.core.start(0.0))
        assert hears(other, 1, {"r1": ("r3",)}) == []


# --------------------------------------------------------------------------- catching up


def _batch(d: Driver, messages: Sequence[tuple[str, bytes]]) -> list[Action]:
    """Messages that arrived together (the shell drains its inboxes into one batch)."""
    actions = d.core.on_messages(messages, 0.0)
    d.run(actions)
    return actions


def _published(actions: Sequence[Action], key: str) -> list[bytes]:
    return [a.payload for a in actions if isinstance(a, Publish) and a.key == key]


def _frames_of(fs: Sequence[SensorFrame]) -> list[tuple[str, bytes]]:
    return [(KEYS.frames(f.robot), encode_frame(f)) for f in fs]


def test_a_realtime_agent_behind_its_frames_defers_the_fusion_to_the_step_that_catches_up(
    frames,  # type: ignore[no-untyped-def]
) -> None:
    """Frames 2, 3 and 4 waiting together with r2's stack: steps 2 and 3 take their frame
    without fusing (journaled ``frame_unfused``, no stack published), step 4 fuses r2's slot.
    The journal holds the stack after the deferred frames, so that a replay rebuilds exactly the
    same belief; and the D of the catching-up agent is the D of an agent that got r2's stack just
    before step 4."""
    peer = _seen_something("r2", frames)
    stack = (KEYS.stack("r2"), peer.encoded_stack())
    d = Driver()
    d.frame(frames["r1"][0])
    actions = _batch(d, [*_frames_of(frames["r1"][1:4]), stack])
    c = d.core.counter_values()
    assert (c["frames_processed"], c["fusions_deferred"], d.core.node.k) == (4, 2, 4)
    assert d.core.node.distributed.stamps == {"r2": peer.k}
    kinds = [r.kind for r in d.log.records()]
    assert kinds == ["frame", "frame_unfused", "frame_unfused", "stack", "frame"]
    published = [a.key for a in actions if isinstance(a, Publish)]
    assert published.count(KEYS.stack("r1")) == 1  # after step 4 only
    # Only the newest step is reported: the estimates of steps 2 and 3 were superseded at once.
    assert published.count(KEYS.estimate("r1")) == 1
    assert c["estimates_skipped"] == 2
    assert decode_estimate(_published(actions, KEYS.estimate("r1"))[-1]).k == 4
    _same_belief(_replayed(d).node, d.core.node)
    # The same D as an agent not behind that received the stack between steps 3 and 4.
    e = Driver()
    for f in frames["r1"][:3]:
        e.frame(f)
    e.send(*stack)
    e.frame(frames["r1"][3])
    assert e.core.counter_values()["fusions_deferred"] == 0
    _same_belief(e.core.node, d.core.node)
    # Without catching up, every step fuses: r2's slot at step 2 already, a different D.
    f = Driver(catch_up=0)
    f.frame(frames["r1"][0])
    f_actions = _batch(f, [*_frames_of(frames["r1"][1:4]), stack])
    assert f.core.counter_values()["fusions_deferred"] == 0
    assert len(_published(f_actions, KEYS.estimate("r1"))) == 3  # and reports every step
    assert [r.kind for r in f.log.records()] == ["frame", "stack", "frame", "frame", "frame"]
    snapshots = [x.core.node.distributed.snapshot("r1") for x in (d, f)]
    m = SCENARIO.num_classes
    assert not np.array_equal(snapshots[0].marginals(m), snapshots[1].marginals(m))


def test_an_estimate_says_which_peer_versions_its_fusion_integrated(frames) -> None:  # type: ignore[no-untyped-def]
    """``fused`` is D's integrated versions at the step reported: none before the peer's stack
    is fused (a stack merged between steps waits for the next step), the peer's stamp after."""
    peer = _seen_something("r2", frames)
    d = Driver()
    d.frame(frames["r1"][0])
    assert decode_estimate(d.published[-1].payload).fused == {}
    d.send(KEYS.stack("r2"), peer.encoded_stack())
    d.frame(frames["r1"][1])
    estimates = [p for p in d.published if p.key == KEYS.estimate("r1")]
    assert decode_estimate(estimates[-1].payload).fused == {"r2": peer.k} != {}


def test_catching_up_defers_at_most_catch_up_steps_in_a_row(frames) -> None:  # type: ignore[no-untyped-def]
    d = Driver(catch_up=2)
    _batch(d, _frames_of(frames["r1"][:7]))
    kinds = [r.kind for r in d.log.records()]
    assert kinds == ["frame_unfused", "frame_unfused", "frame"] * 2 + ["frame"]
    lockstep = Driver(mode="lockstep")
    assert lockstep.core.settings.catch_up > 0  # the setting applies to real time only
    with pytest.raises(ValueError, match="catch_up"):
        CoreSettings(catch_up=-1)


def test_an_agent_that_skipped_estimates_while_catching_up_answers_with_its_current_one(
    frames,
    monkeypatch,  # type: ignore[no-untyped-def]
) -> None:
    """Steps 1–3 arrive together: only step 3 is reported; asked for it again (the conductor
    re-sends the last frame), the agent sends the same bytes, or a fresh one (a status). An agent
    whose step after a skipped report cannot be taken at all (stuck at step 3, whose estimate
    was never published) makes the estimate of step 3 when asked, not step 1's again."""
    d = Driver()
    actions = _batch(d, _frames_of(frames["r1"][:3]))
    sent = _published(actions, KEYS.estimate("r1"))
    assert [decode_estimate(b).k for b in sent] == [3]
    again = d.core.on_messages(_frames_of(frames["r1"][2:3]), 1.0)
    assert _published(again, KEYS.estimate("r1")) == sent
    status = d.core.on_messages([(KEYS.ctl("status"), encode_control(Status()))], 2.0)
    assert [decode_estimate(b).k for b in _published(status, KEYS.estimate("r1"))] == [3]

    original = RobotNode.on_frame

    def fails_at_4(self, frame, fuse=True, clock=None):  # type: ignore[no-untyped-def]
        if frame.k == 4:
            raise FloatingPointError("step 4 cannot be taken")
        return original(self, frame, fuse, clock)

    monkeypatch.setattr(RobotNode, "on_frame", fails_at_4)
    e = Driver()
    e.frame(frames["r1"][0])
    actions = _batch(e, _frames_of(frames["r1"][1:4]))
    assert e.core.node.k == 3 and e.core.counter_values()["steps_stuck"] == 1
    assert _published(actions, KEYS.estimate("r1")) == []  # steps 2 and 3 were superseded
    again = e.core.on_messages(_frames_of(frames["r1"][2:3]), 1.0)  # frame 3 sent again
    assert [decode_estimate(b).k for b in _published(again, KEYS.estimate("r1"))] == [3]
    # Frame 4 sent again, the very bytes that failed: not tried a second time.
    failed = e.core.counter_values()["steps_failed"]
    e.core.on_messages(_frames_of(frames["r1"][3:4]), 3.0)
    assert (e.core.counter_values()["steps_failed"], e.core.node.k) == (failed, 3)


def test_failed_frames_and_refused_slots_are_remembered_within_a_bound(
    frames,
    monkeypatch,  # type: ignore[no-untyped-def]
) -> None:
    """The frames whose bytes failed a step and the slot versions refused are remembered (so
    that they are never tried again) up to MAX_REFUSED each, the oldest forgotten first: a flood
    of distinct failing inputs cannot grow them."""
    monkeypatch.setattr(recovery, "MAX_REFUSED", 3)

    original = RobotNode.on_frame

    def fails(self, frame, fuse=True, clock=None):  # type: ignore[no-untyped-def]
        if frame.k == 2:
            raise FloatingPointError("step 2 cannot be taken")
        return original(self, frame, fuse, clock)

    d = Driver()
    d.frame(frames["r1"][0])
    monkeypatch.setattr(RobotNode, "on_frame", fails)
    second = frames["r1"][1]
    variants = [dataclasses.replace(second, odometry=second.odometry + 1e-3 * i) for i in range(5)]
    for f in variants:
        d.frame(f)
    assert d.core.counter_values()["steps_failed"] == 5 and d.core.node.k == 1
    d.frame(variants[4])  # remembered: not tried again
    assert d.core.counter_values()["steps_failed"] == 5
    d.frame(variants[0])  # forgotten (the oldest of five, three kept): tried again
    assert d.core.counter_values()["steps_failed"] == 6
    d.core.ledger.took([("r2", (1, i)) for i in range(5)], b"stack")
    d.core.ledger.failed(b"frame")
    assert list(d.core.ledger.refused) == [("r2", (1, i)) for i in (2, 3, 4)]


def test_a_fusion_that_fails_after_deferred_steps_refuses_the_slots_merged_before_them(
    frames,
    monkeypatch,  # type: ignore[no-untyped-def]
) -> None:
    """The stacks merged before a deferred step stay suspects until the step that fuses them: if
    that fusion raises, they are refused and the step goes on without them (not quarantined)."""
    peer = _seen_something("r2", frames)
    d = Driver()
    d.frame(frames["r1"][0])
    original = DistributedBelief.integrate

    def integrate(self, slots, settle=True):  # type: ignore[no-untyped-def]
        if any(s.owner == "r2" for s in slots):
            raise RuntimeError("Indeterminate linear system (forged slot)")
        return original(self, slots, settle)

    monkeypatch.setattr(DistributedBelief, "integrate", integrate)
    _batch(d, [(KEYS.stack("r2"), peer.encoded_stack()), *_frames_of(frames["r1"][1:3])])
    c = d.core.counter_values()
    assert (c["fusions_deferred"], c["steps_failed"], c["slots_refused"]) == (1, 1, 1)
    assert (c["frames_quarantined"], d.core.node.k) == (0, 3)
    assert "r2" not in d.core.node.distributed.stamps
    assert [r.kind for r in d.log.records()] == ["frame", "frame_unfused", "frame"]
    _same_belief(_replayed(d).node, d.core.node)


def test_a_step_that_fails_after_another_of_the_same_batch_rolls_back_to_that_one(frames) -> None:  # type: ignore[no-untyped-def]
    """Frames 2 and a failing 3 in one batch: the batch's actions (step 2's commit among them)
    are carried out only after the batch, so the roll-back must start from step 2 committed in
    this batch, not from the journal alone (it went back to step 1, and step 3 could never be
    taken)."""
    d = Driver(catch_up=0)
    d.frame(frames["r1"][0])
    _batch(d, [*_frames_of([frames["r1"][1], _poisoned(frames["r1"][2])])])
    c = d.core.counter_values()
    assert (c["steps_failed"], c["frames_quarantined"], c["frames_degraded"]) == (1, 1, 1)
    assert (c["steps_stuck"], d.core.node.k) == (0, 3)
    assert [r.kind for r in d.log.records()] == ["frame"] * 3
    _same_belief(_replayed(d).node, d.core.node)


def test_an_agent_associates_frames_without_ids_and_replays_them_to_the_same_belief() -> None:
    """Id-less frames (with clutter and misses) are associated on the robot before L and D
    step, and an id-less peer's slots are mapped onto D; the journal's replay associates and
    maps them again to the very same belief; a frame whose id kind is malformed is counted in
    frames_invalid and changes nothing."""
    model = belief_model(SCENARIO)
    sensor = sensor_field(SCENARIO, "r1")

    def make() -> RobotNode:
        return make_node(
            "r1", SCENARIO.robot("r1").start, model, SEED, BeliefConfig(), sensor=sensor
        )

    log = MemoryLog()
    core = AgentCore(make, KEYS, CoreSettings(mode="realtime"), log.records)
    sim = Simulator(SCENARIO, SEED, detector=Detector("none", clutter=0.2, miss=0.1))
    peer = make_node(  # an id-less peer whose stacks reach r1 (fleet association)
        "r2",
        SCENARIO.robot("r2").start,
        model,
        SEED,
        BeliefConfig(),
        sensor=sensor_field(SCENARIO, "r2"),
    )
    for k in range(1, 41):
        execute_journal_actions(
            log, core.on_message(KEYS.frames("r1"), encode_frame(sim.frame("r1", k)), 0.0)
        )
        peer.on_frame(sim.frame("r2", k))
        if k % 5 == 0 and (stack := peer.outgoing()) is not None:
            execute_journal_actions(log, core.on_message(KEYS.stack("r2"), stack, 0.0))
    bad = msgpack.unpackb(encode_frame(sim.frame("r1", 41)), raw=False)
    execute_journal_actions(
        log, core.on_message(KEYS.frames("r1"), msgpack.packb({**bad, "ids": "tracker"}), 0.0)
    )
    counters = core.counter_values()
    assert counters["frames_processed"] == 40 and counters["frames_invalid"] == 1
    node = core.node
    assert node.k == 40 and node.local_ids and len(node.local.object_ids) >= 3
    fleet = node.distributed.association
    assert fleet is not None and fleet.mapping("r2") and not node.counters.unassociated_slots
    assert set(node.distributed.object_ids) == set(node.local.object_ids) | set(
        fleet.mapping("r2").values()
    )
    fresh = AgentCore(make, KEYS, core.settings, log.records)
    assert fresh.replay(log.records()) == []
    _same_belief(fresh.node, node)


def test_the_status_counters_report_the_node_and_relay_counters_they_name() -> None:
    core = AgentCore(_factory("r1"), KEYS, CoreSettings())
    c = core.node.counters
    c.evicted_slots, c.foreign_slots = 3, 5
    core.gossip.pushes, core.gossip.flushes = 2, 7
    values = core.counter_values()
    assert values["slots_evicted"] == 3 and values["slots_foreign"] == 5
    assert values["relay_pushes"] == 9
