"""RobotNode, the sans-I/O core of one robot, and the in-process fleet that drives several.

The world: three robots 10 m apart driving along +x, each seeing only its own objects (r1 sees 1
and 2 from k = 1, r2 sees 3 from k = 7, r3 sees 4 from k = 1), so whatever a robot's D knows of
another robot's objects came over the wire.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gtsam
import msgpack
import numpy as np
import pytest

from agents.links import Schedule
from agents.node import FIT_LOG_STEPS, RobotNode
from deploy.base.build import belief_model, belief_rng, link_model_for, make_node, sensor_field
from deploy.study.fleet import FleetStats, make_nodes, run_fleet
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.models import SensorFrame
from estimator.slots import object_log_phi
from estimator.smoother import pose_step
from estimator.summary import LocalSummary, ObjectClasses
from estimator.xi import Xi
from protocol.codec import Limits, StackMessage, decode, encode
from protocol.stack import Slot, Stack
from sim.loader import load_scenario, parse_scenario
from sim.sensors import Detector, Simulator
from sim.world import World
from tests.estimator.scenarios import fleet_text

STEPS = 12
SEED = 3
_OBJECTS = [(3.0, 0.5, 0.5, 1), (4.0, -0.8, -1.0, 2), (5.5, 10.3, 2.0, 2), (3.0, 20.5, 1.0, 1)]
SCENARIO = parse_scenario(
    fleet_text(
        "chain",
        STEPS,
        [0.0, 10.0, 20.0],
        _OBJECTS,
        description="three robots 10 m apart, each with objects of its own",
        communication=(
            f'mode = "schedule"\nschedule = [[1, {STEPS}, "r1", "r2"], [1, {STEPS}, "r2", "r3"]]'
        ),
    ),
    "chain.toml",
)
WORLD = World(SCENARIO)
R2_FIRST_SIGHTING = 7
# r1–r2 and r2–r3 talk at every step, r1–r3 never: r1's news reaches r3 only through r2.
CHAIN = Schedule(((1, STEPS, "r1", "r2"), (1, STEPS, "r2", "r3")))


@pytest.fixture(scope="module")
def frames() -> dict[str, list[SensorFrame]]:
    return Simulator(SCENARIO, SEED).all_frames()


def _nodes(seed: int = SEED) -> dict[str, RobotNode]:
    return make_nodes(
        SCENARIO, belief_model(SCENARIO), BeliefConfig(), lambda r: belief_rng(seed, [r])
    )


def _node(robot: str) -> RobotNode:
    return _nodes()[robot]


def _advance(node: RobotNode, frames: dict[str, list[SensorFrame]], to_step: int) -> None:
    for f in frames[node.robot][node.k : to_step]:
        node.on_frame(f)


def _poses(belief: HybridBelief, robot: str) -> np.ndarray:
    """(H, 1 + n, 3): every hypothesis' latest pose of ``robot`` and its object poses."""
    keys = [belief.pose_key(robot)] + [object_key(j) for j in belief.object_ids]
    return np.array([[h.pose(key) for key in keys] for h in belief.hypotheses])


def _assert_same_belief(a: HybridBelief, b: HybridBelief, robot: str) -> None:
    """Bit-identical: same objects, hypotheses, classes, log weights and pose estimates."""
    assert a.object_ids == b.object_ids
    assert len(a.hypotheses) == len(b.hypotheses)
    assert [h.classes for h in a.hypotheses] == [h.classes for h in b.hypotheses]
    assert [h.log_weight for h in a.hypotheses] == [h.log_weight for h in b.hypotheses]
    assert np.array_equal(_poses(a, robot), _poses(b, robot))
    map_a, map_b = a.map_hypothesis(), b.map_hypothesis()
    assert map_a.classes == map_b.classes
    assert np.array_equal(map_a.pose(a.pose_key(robot)), map_b.pose(b.pose_key(robot)))


def _own_slot(node: RobotNode) -> Slot:
    return decode(node.outgoing(), node.limits).stack.by_owner()[node.robot]


# -- no communication ----------------------------------------------------------------------------


@pytest.mark.parametrize("robot", ["r1", "r2"])
def test_node_without_communication_keeps_d_equal_to_l(
    robot: str, frames: dict[str, list[SensorFrame]]
) -> None:
    node = _node(robot)
    for f in frames[robot]:
        report = node.on_frame(f)
        assert report.k == f.k and report.fusion.integrated == ()
        _assert_same_belief(node.distributed, node.local, robot)
    assert node.local.object_ids  # the robot saw something: the equality is not vacuous
    assert node.distributed.stamps == {}


def test_node_rejects_a_frame_of_another_robot(frames: dict[str, list[SensorFrame]]) -> None:
    with pytest.raises(ValueError, match="r2"):
        _node("r1").on_frame(frames["r2"][0])


# -- outgoing ------------------------------------------------------------------------------------


def test_a_fused_estimate_that_l_cannot_fit_leaves_the_own_slot_at_ls_point(
    frames: dict[str, list[SensorFrame]], caplog: pytest.LogCaptureFixture
) -> None:
    """A poisoned D (every object pulled 40 m away by a strong prior, as a forged slot would)
    does not bend the own slot: it is taken at L's point and the refusal counted."""
    node = _node("r2")
    _advance(node, frames, STEPS)
    cont = node.distributed.hypotheses[0].continuous
    graph = gtsam.NonlinearFactorGraph()
    strong = gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
    for j in node.distributed.object_ids:
        p = cont.isam.calculateEstimate().atPose2(object_key(j))
        graph.add(gtsam.PriorFactorPose2(object_key(j), gtsam.Pose2(p.x() + 40, p.y(), 0), strong))
    cont.isam.update(graph, gtsam.Values())
    node._own_slot_stale = True
    slot = node.current_stack().by_owner()["r2"]
    assert slot.summary.per_object is not None
    local = node.local.hypotheses[0].continuous.isam.getLinearizationPoint()
    keys = [object_key(j) for j in slot.summary.object_ids]
    at_l = [[local.atPose2(k).x(), local.atPose2(k).y(), local.atPose2(k).theta()] for k in keys]
    np.testing.assert_allclose(slot.summary.per_object.xi.lin, at_l, rtol=0, atol=1e-5)
    assert node.local.slot_fit_refused == 1
    assert "r2: own slot at step 12 taken at L's point" in caplog.text
    # Counted every time, logged at most once per FIT_LOG_STEPS steps.
    caplog.clear()
    node._own_slot_stale = True
    node.current_stack()
    assert node.local.slot_fit_refused == 2 and "L's point" not in caplog.text
    node.k += FIT_LOG_STEPS  # (as if that many steps had gone by)
    node._own_slot_stale = True
    node.current_stack()
    assert node.local.slot_fit_refused == 3 and "3 so far" in caplog.text


@pytest.mark.parametrize("where", ["fused", "local"])
def test_the_own_slot_is_linearised_where_the_config_says(
    where: str, frames: dict[str, list[SensorFrame]]
) -> None:
    """``BeliefConfig.slot_linearisation``: r2's slot ξ is taken at D's estimate of its objects
    (``"fused"``) or at L's own linearisation point (``"local"``)."""
    config = BeliefConfig(slot_linearisation=where)
    nodes = make_nodes(SCENARIO, belief_model(SCENARIO), config, lambda r: belief_rng(SEED, [r]))
    r1, r2 = nodes["r1"], nodes["r2"]
    for k in range(STEPS):
        for n in (r1, r2):
            n.on_frame(frames[n.robot][k])
        for a, b in ((r1, r2), (r2, r1)):
            data = a.outgoing()
            if data is not None:
                b.on_stack(data)
    slot = r2.current_stack().by_owner()["r2"]
    assert slot.summary.per_object is not None
    lin = np.asarray(slot.summary.per_object.xi.lin)
    keys = [object_key(j) for j in slot.summary.object_ids]
    fused = r2.distributed.hypotheses[0].continuous.isam.calculateEstimate()
    local = r2.local.hypotheses[0].continuous.isam.getLinearizationPoint()
    at_d = np.array(
        [[fused.atPose2(k).x(), fused.atPose2(k).y(), fused.atPose2(k).theta()] for k in keys]
    )
    at_l = np.array(
        [[local.atPose2(k).x(), local.atPose2(k).y(), local.atPose2(k).theta()] for k in keys]
    )
    assert np.abs(at_d - at_l).max() > 1e-6  # the two points differ: the test can tell them apart
    np.testing.assert_array_equal(lin, at_d if where == "fused" else at_l)
    assert r2.local.slot_fit_refused == 0


def test_node_outgoing_is_none_until_the_robot_sees_an_object(
    frames: dict[str, list[SensorFrame]],
) -> None:
    node = _node("r2")
    assert node.outgoing() is None
    for f in frames["r2"][: R2_FIRST_SIGHTING - 1]:
        node.on_frame(f)
        assert node.outgoing() is None, f.k
    node.on_frame(frames["r2"][R2_FIRST_SIGHTING - 1])
    data = node.outgoing()
    assert isinstance(data, bytes)
    message = decode(data, node.limits)
    assert message.sender == "r2"
    assert message.position == node.position
    assert [s.owner for s in message.stack] == ["r2"]
    slot = message.stack.by_owner()["r2"]
    assert slot.stamp == R2_FIRST_SIGHTING == node.k
    _is_slot_of_local(slot, node)


def test_node_delta_bytes_are_those_of_the_node_now_even_when_kept(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """``encoded_delta`` keeps the bytes it made while the stack, step and position stay: what it
    returns is always the encoding of the node as it is now (it used to re-encode every time)."""
    r1, r2 = _node("r1"), _node("r2")

    def fresh(node: RobotNode, owners: tuple[str, ...]) -> bytes:
        stack = node.current_stack()
        chosen = Stack(tuple(s for s in stack if s.owner in owners))
        have = stack.versions()
        return encode(StackMessage(node.robot, node.position, chosen, node.k, have=have))

    for k in range(1, R2_FIRST_SIGHTING + 3):
        _advance(r1, frames, k)
        _advance(r2, frames, k)
        for owners in ((), ("r1",), ("r1", "r2"), ()):
            assert r1.encoded_delta(owners) == fresh(r1, owners), (k, owners)
        digest = r1.encoded_delta(())
        assert r1.encoded_delta(()) is digest  # kept, not made again
        before = r1.current_stack()
        data = r2.outgoing()
        if data is not None and r1.on_stack(data):  # a newer slot of r2: a new stack
            assert r1.current_stack() is not before
            assert r1.encoded_delta(()) == fresh(r1, ())
            assert r1.encoded_delta(("r2",)) == fresh(r1, ("r2",))
            assert "r2" in decode(r1.encoded_delta(("r2",)), r1.limits).stack.by_owner()
        else:  # nothing newer: the stack object itself is kept, and so are the bytes
            assert r1.current_stack() is before
            assert r1.encoded_delta(()) is digest
    assert "r2" in r1.current_stack().by_owner()


def test_node_own_slot_is_built_from_local_not_distributed(
    frames: dict[str, list[SensorFrame]],
) -> None:
    peer, node = _node("r1"), _node("r2")
    _advance(peer, frames, 3)
    assert node.on_stack(peer.outgoing())
    _advance(node, frames, R2_FIRST_SIGHTING + 2)
    assert set(node.distributed.object_ids) > set(node.local.object_ids)  # D differs from L
    message = decode(node.outgoing(), node.limits)
    assert sorted(message.stack.stamps()) == ["r1", "r2"]
    slot = message.stack.by_owner()["r2"]
    assert slot.stamp == node.k == R2_FIRST_SIGHTING + 2
    _is_slot_of_local(slot, node)
    assert node.outgoing() is node.outgoing()  # encoded once until something changes


# -- invalid input -------------------------------------------------------------------------------


def _body(doc: dict[str, Any]) -> dict[str, Any]:
    """The first slot's per-object map, or its first realisation (a table slot)."""
    real = doc["slots"][0]["real"]
    return real if isinstance(real, dict) else real[0]


def _mutated(data: bytes, field: str, value: object) -> bytes:
    """``data`` with ``field`` of its first slot's body (:func:`_body`) replaced."""
    doc = msgpack.unpackb(data, raw=False)
    _body(doc)[field] = value
    return bytes(msgpack.packb(doc, use_bin_type=True))


def _with_nan(data: bytes) -> bytes:
    lin = np.frombuffer(_body(msgpack.unpackb(data, raw=False))["lin"], "<f8").copy()
    lin[1] = np.nan
    return _mutated(data, "lin", lin.tobytes())


def _with_unknown_class(data: bytes) -> bytes:
    # A two-class world: a slot of 5 classes (or class index 5) is well-formed but meaningless.
    body = _body(msgpack.unpackb(data, raw=False))
    if "c" in body:
        return _mutated(data, "c", bytes([5]) + body["c"][1:])
    n = len(body["phi"]) // (4 * body["m"])
    doc = msgpack.unpackb(data, raw=False)
    _body(doc)["m"] = 5
    _body(doc)["phi"] = np.zeros(n * 5, "<f4").tobytes()
    return bytes(msgpack.packb(doc, use_bin_type=True))


def _is_slot_of_local(slot: Slot, node: RobotNode) -> None:
    """``slot`` summarises the node's L: its objects, and every object's class log φ (float32
    on the wire) or every realisation."""
    local = node.local
    assert slot.summary.object_ids == tuple(local.object_ids)
    per_object = slot.summary.per_object
    if per_object is None:
        assert [r.classes for r in slot.summary.realisations] == [
            h.classes for h in local.hypotheses
        ]
        return
    expected = object_log_phi(local.log_evidence).astype(np.float32).astype(float)
    assert np.array_equal(per_object.log_phi, expected)


@pytest.mark.parametrize(
    ("corrupt", "error"),
    [
        (lambda data: b"\xc1 this is not msgpack" + data[:7], "MalformedMessage"),
        (lambda data: data[: len(data) // 2], "MalformedMessage"),
        (_with_nan, "InvalidValue"),
        (_with_unknown_class, "InvalidValue"),
    ],
    ids=["garbage", "truncated", "nan", "unknown-class"],
)
def test_node_on_stack_drops_invalid_input_and_keeps_what_it_had(
    corrupt, error: str, frames: dict[str, list[SensorFrame]]
) -> None:
    peer, node = _node("r1"), _node("r2")
    _advance(peer, frames, 3)
    _advance(node, frames, 2)
    data = peer.outgoing()
    assert node.on_stack(data)
    held = node.stack.by_owner()["r1"]
    stamps = node.stack.stamps()
    _advance(peer, frames, 4)  # a newer version: one the node parses (an older one it skips)
    bad = corrupt(peer.outgoing())
    assert bad != data
    assert not node.on_stack(bad)
    c = node.counters
    assert (c.invalid, c.errors_by_type, c.stacks_received, c.stacks_merged) == (
        1,
        {error: 1},
        2,
        1,
    )
    assert c.bytes_received == len(data) + len(bad)
    assert c.slots_skipped == 0
    assert c.last_error
    assert node.stack.stamps() == stamps
    assert node.stack.by_owner()["r1"] is held
    # The node lives on and still fuses what it accepted before the bad message.
    node.on_frame(frames["r2"][2])
    assert node.distributed.stamps == {"r1": 3}


def test_node_parses_each_slot_version_once_and_relays_the_bytes_it_received(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """Decoding only what is new: a version the node holds is skipped unparsed however often it
    comes back, even corrupted (it is never used, so never relayed); the node relays a slot as
    the very bytes its owner sent."""
    peer, node = _node("r1"), _node("r2")
    _advance(peer, frames, 3)
    _advance(node, frames, 2)
    data = peer.outgoing()
    for _ in range(5):
        node.on_stack(data)
    c = node.counters
    assert (c.slots_decoded, c.slots_skipped, c.invalid) == (1, 4, 0)
    assert not node.on_stack(_with_nan(data))  # the held version, corrupted: not even parsed
    assert (c.slots_decoded, c.slots_skipped, c.invalid) == (1, 5, 0)
    owner_bytes = msgpack.unpackb(data, raw=False)["slots"][0]
    relayed = msgpack.unpackb(node.outgoing(), raw=False)
    assert [s for s in relayed["slots"] if s["owner"] == "r1"] == [owner_bytes]
    assert node.stack.by_owner()["r1"].wire.data in data  # the very bytes, spliced in
    assert node.stack.by_owner()["r1"].wire.data in node.outgoing()


def test_node_reuses_a_parsed_version_only_for_the_same_bytes(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """Before a decoded slot is merged (a lock-step round waits), another copy with the same
    bytes is taken from what was parsed; a copy of that version with other bytes — corrupted, or
    forged on a fleet that does not sign — is parsed and judged on its own."""
    peer, node = _node("r1"), _node("r2")
    _advance(peer, frames, 3)
    _advance(node, frames, 2)
    data = peer.outgoing()
    assert data is not None
    first = node.decode_stack(data)
    again = node.decode_stack(data)
    assert first is not None and again is not None
    assert again.reused == ("r1",) and first.reused == ()
    assert again.stack.by_owner()["r1"] is first.stack.by_owner()["r1"]
    c = node.counters
    assert (c.slots_decoded, c.slots_reused, c.invalid) == (1, 1, 0)
    assert node.decode_stack(_with_nan(data)) is None  # same version, other bytes: parsed, refused
    assert (c.slots_decoded, c.slots_reused, c.invalid) == (1, 1, 1)
    assert node.merge(again)
    assert node.decode_stack(data) is not None  # held now: skipped, not reused
    assert (c.slots_decoded, c.slots_reused, c.slots_skipped) == (1, 1, 1)
    # A node whose roster leaves out the owner keeps nothing of its slots for later: every copy
    # is parsed (and refused by the merge), so an outsider cannot crowd out the roster's slots.
    outside = _node("r3")
    outside.roster = frozenset({"r2", "r3"})
    _advance(outside, frames, 2)
    copies = [outside.decode_stack(data) for _ in range(2)]
    assert [m.reused for m in copies if m is not None] == [(), ()]
    assert outside.counters.slots_decoded == 2 and not outside.merge(copies[1])  # type: ignore[arg-type]


def test_node_keeps_parsed_slots_within_a_message_of_bytes(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """What a node keeps parsed for later copies is bounded by one message's bytes, however many
    new versions arrive (the oldest is forgotten first, then parsed again if it comes back)."""
    peer, node = _node("r1"), _node("r2")
    _advance(node, frames, 1)
    sent = []
    for k in range(2, 7):
        _advance(peer, frames, k)
        data = peer.outgoing()
        if data is not None:
            sent.append(data)
    assert len(sent) >= 3
    one = max(len(d) for d in sent)
    node.limits = dataclasses.replace(node.limits, max_message_bytes=2 * one)
    for data in sent:
        assert node.decode_stack(data) is not None
    kept = [s.wire.data for s in node._parsed.values() if s.wire is not None]
    assert 1 <= len(kept) <= 2 and sum(len(b) for b in kept) <= 2 * one
    c = node.counters
    decoded = c.slots_decoded
    assert node.decode_stack(sent[0]) is not None  # forgotten: parsed again
    assert (c.slots_decoded, c.slots_reused) == (decoded + 1, 0)
    assert node.decode_stack(sent[-1]) is not None  # still kept
    assert (c.slots_decoded, c.slots_reused) == (decoded + 1, 1)


def test_node_nan_error_names_the_field(frames: dict[str, list[SensorFrame]]) -> None:
    peer, node = _node("r1"), _node("r2")
    _advance(peer, frames, 2)
    assert not node.on_stack(_with_nan(peer.outgoing()))
    assert "lin" in node.counters.last_error
    assert len(node.stack) == 0


# -- versions ------------------------------------------------------------------------------------


def test_node_on_stack_is_idempotent(frames: dict[str, list[SensorFrame]]) -> None:
    peer, twice, once = _node("r1"), _node("r2"), _node("r2")
    _advance(peer, frames, R2_FIRST_SIGHTING)
    _advance(twice, frames, R2_FIRST_SIGHTING)
    _advance(once, frames, R2_FIRST_SIGHTING)
    data = peer.outgoing()
    assert twice.on_stack(data)
    assert not twice.on_stack(data)
    assert once.on_stack(data)
    c = twice.counters
    assert (c.stacks_received, c.stacks_merged, c.stacks_unchanged, c.invalid) == (2, 1, 1, 0)
    nxt = frames["r2"][R2_FIRST_SIGHTING]
    twice.on_frame(nxt)
    once.on_frame(nxt)
    assert twice.distributed.stamps == once.distributed.stamps == {"r1": R2_FIRST_SIGHTING}
    _assert_same_belief(twice.distributed, once.distributed, "r2")
    assert twice.outgoing() == once.outgoing()


def test_node_never_takes_its_own_slot_from_a_relayed_stack(
    frames: dict[str, list[SensorFrame]],
) -> None:
    node, relay = _node("r1"), _node("r2")
    _advance(node, frames, 3)
    assert relay.on_stack(node.outgoing())  # relay now holds r1's slot at stamp 3
    _advance(node, frames, 6)
    relayed = relay.outgoing()
    assert decode(relayed).stack.stamps() == {"r1": 3}
    decoded, skipped = node.counters.slots_decoded, node.counters.slots_skipped
    assert not node.on_stack(relayed)
    assert node.counters.stacks_unchanged == 1
    # An older version of its own slot is not even parsed.
    assert (node.counters.slots_decoded, node.counters.slots_skipped) == (decoded, skipped + 1)
    own = _own_slot(node)
    assert own.stamp == node.k == 6
    assert own.summary.object_ids == tuple(node.local.object_ids)
    # Its own information did not come back into D either: D still repeats L exactly.
    node.on_frame(frames["r1"][6])
    assert "r1" not in node.distributed.stamps
    _assert_same_belief(node.distributed, node.local, "r1")


def test_node_never_takes_its_own_slot_from_a_peer_and_moves_above_a_newer_version(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """A peer holding a version of r1's slot newer than r1 made (an earlier life of r1 that lost
    its journal, or a forgery on an unsigned fleet): r1 keeps its own slot and moves to the next
    epoch, so that its next versions replace that one everywhere (docs/wire.md)."""
    node = _node("r1")
    _advance(node, frames, 4)
    summary = node.current_stack().by_owner()["r1"].summary
    older = encode(StackMessage("r2", None, Stack((Slot("r1", 3, summary),))))
    assert not node.on_stack(older) and node.epoch == 0  # one it made: nothing to do
    forged = encode(StackMessage("r2", None, Stack((Slot("r1", 100, summary),))))
    assert node.on_stack(forged)  # True: a replay of the journal must see this stack again
    assert node.stack.stamps() == {"r1": 4} and node.counters.own_superseded == 1
    assert node.epoch == 1 and _own_slot(node).version == (1, 4)
    assert not node.on_stack(forged) and node.counters.own_superseded == 1  # once is enough
    node.on_frame(frames["r1"][4])
    assert _own_slot(node).version == (1, 5)
    assert node.distributed.stamps == {}
    relayed = Stack((Slot("r1", 100, summary),)).merge([_own_slot(node)], own="r2")
    assert relayed.versions() == {"r1": (1, 5)}


def _peer_after_6_and_its_stack_after_3(
    frames: dict[str, list[SensorFrame]],
) -> tuple[RobotNode, bytes | None]:
    """r1 after 6 frames, and the stack message it had to send after 3 (an older version)."""
    peer = _node("r1")
    _advance(peer, frames, 3)
    old = peer.outgoing()
    _advance(peer, frames, 6)
    return peer, old


def test_node_ignores_an_older_version_of_a_slot_it_holds(
    frames: dict[str, list[SensorFrame]],
) -> None:
    peer, old = _peer_after_6_and_its_stack_after_3(frames)
    node = _node("r2")
    new = peer.outgoing()
    assert node.on_stack(new)
    node.on_frame(frames["r2"][0])
    assert node.distributed.stamps == {"r1": 6}
    assert not node.on_stack(old)
    assert node.counters.stacks_unchanged == 1
    assert node.stack.stamps() == {"r1": 6}
    node.on_frame(frames["r2"][1])
    assert node.distributed.stamps == {"r1": 6}
    assert {h.continuous.used["r1"].stamp for h in node.distributed.hypotheses} == {6}


def test_node_takes_the_newer_version_after_an_older_one(
    frames: dict[str, list[SensorFrame]],
) -> None:
    peer, old = _peer_after_6_and_its_stack_after_3(frames)
    node = _node("r2")
    assert node.on_stack(old)
    node.on_frame(frames["r2"][0])
    assert node.on_stack(peer.outgoing())
    node.on_frame(frames["r2"][1])
    assert node.distributed.stamps == {"r1": 6}
    assert node.counters.stacks_merged == 2


# -- the in-process fleet ------------------------------------------------------------------------


def _run_chain(
    frames: dict[str, list[SensorFrame]],
) -> tuple[dict[str, RobotNode], FleetStats]:
    nodes = _nodes()
    return nodes, run_fleet(nodes, frames, CHAIN, STEPS)


@pytest.fixture(scope="module")
def chain_run(
    frames: dict[str, list[SensorFrame]],
) -> tuple[dict[str, RobotNode], FleetStats]:
    return _run_chain(frames)


def test_run_fleet_is_deterministic(chain_run, frames: dict[str, list[SensorFrame]]) -> None:
    nodes, stats = chain_run
    again, stats_again = _run_chain(frames)
    for r in SCENARIO.robot_ids:
        _assert_same_belief(again[r].distributed, nodes[r].distributed, r)
        assert again[r].stack.stamps() == nodes[r].stack.stamps()
    assert stats_again.delivered_bytes == stats.delivered_bytes


def test_run_fleet_relays_over_two_hops(chain_run) -> None:
    nodes, _ = chain_run
    only_r1 = set(WORLD.known_objects("r1", STEPS))
    for other in ("r2", "r3"):
        only_r1 -= set(WORLD.known_objects(other, STEPS))
    assert only_r1 == {1, 2}
    r3 = nodes["r3"]
    assert only_r1 <= set(r3.distributed.object_ids)
    assert not only_r1 & set(r3.local.object_ids)
    # One hop per step: r1's end-of-step-10 slot reaches r2 at step 11 and r3 at step 12.
    assert r3.stack.stamps()["r1"] == STEPS - 2
    assert r3.distributed.stamps["r1"] == STEPS - 2
    assert set(nodes["r1"].distributed.object_ids) == {1, 2, 3, 4}


def _expected_deliveries() -> int:
    """Deliveries of the chain run: a sender delivers once it has a non-empty stack, i.e. once it
    has seen an object or received a non-empty stack before the step."""
    has = dict.fromkeys(SCENARIO.robot_ids, False)
    count = 0
    for k in range(1, STEPS + 1):
        pairs = [
            (a, b) for a in has for b in has if a != b and CHAIN.allowed(a, b, k, (0, 0), (0, 0))
        ]
        sending = {a for a, _ in pairs if has[a]}
        count += sum(1 for a, _ in pairs if a in sending)
        for a, b in pairs:
            has[b] = has[b] or a in sending
        for r in has:
            has[r] = has[r] or bool(WORLD.visible_objects(r, k))
    return count


def test_run_fleet_counts_deliveries_consistently_with_nodes(chain_run) -> None:
    nodes, stats = chain_run
    counters = [n.counters for n in nodes.values()]
    assert stats.deliveries == len(stats.delivered_bytes) == _expected_deliveries()
    assert sum(c.stacks_received for c in counters) == stats.deliveries
    assert sum(c.stacks_sent for c in counters) == stats.deliveries
    assert sum(c.bytes_received for c in counters) == sum(stats.delivered_bytes)
    assert sum(c.bytes_sent for c in counters) == sum(stats.delivered_bytes)
    assert all(c.invalid == 0 and c.rejected_slots == 0 for c in counters)
    assert min(stats.delivered_bytes) > 0
    assert stats.refused == 0


def test_run_fleet_counts_the_slots_its_nodes_refuse(frames: dict[str, list[SensorFrame]]) -> None:
    """r2's wire limits hold one object per slot: every stack of a peer's slot of more is
    refused and counted (and so would be an own slot of more); FleetStats.refused sums them."""
    nodes = _nodes()
    nodes["r2"].limits = Limits(num_classes=2, max_objects=1)
    stats = run_fleet(nodes, frames, CHAIN, STEPS)
    c = nodes["r2"].counters
    assert c.invalid > 0 and c.errors_by_type == {"LimitExceeded": c.invalid}
    assert stats.refused == sum(
        n.counters.invalid
        + n.counters.rejected_slots
        + n.counters.foreign_slots
        + n.counters.own_slot_invalid
        for n in nodes.values()
    )
    assert stats.refused >= c.invalid


def test_run_fleet_calls_on_step_for_every_robot_and_step(
    frames: dict[str, list[SensorFrame]],
) -> None:
    calls = []

    def on_step(robot: str, k: int, node: RobotNode, fusion_ms: float, step_ms: float) -> None:
        assert node.robot == robot and node.k == k
        assert 0.0 <= fusion_ms <= step_ms
        calls.append((robot, k))

    run_fleet(_nodes(), frames, Schedule(()), 4, on_step)
    assert calls == [(r, k) for k in range(1, 5) for r in SCENARIO.robot_ids]


def test_a_node_holds_every_realisation_its_belief_may_keep() -> None:
    """The default wire limits of a node admit its own belief's cap (4,096 realisations for the
    exact reference, more than the wire's default 1,024), and given limits that cannot hold it
    are refused at construction, naming the field (issue 41: the exact reference lost its own
    slot once a belief held more than 1,024 realisations)."""
    model = belief_model(SCENARIO)
    start = SCENARIO.robot("r1").start
    rngs = (belief_rng(SEED, ["r1"]), belief_rng(SEED, ["r1"]))
    exact = BeliefConfig.exact()
    node = RobotNode("r1", start, model, *rngs, exact)
    assert node.limits.max_realisations == exact.cap() == 4096
    assert RobotNode("r1", start, model, *rngs).limits.max_realisations == 1024
    with pytest.raises(ValueError, match=r"max_realisations 1024 cannot hold .* \(up to 4096"):
        RobotNode("r1", start, model, *rngs, exact, limits=Limits(num_classes=2))


# -- the belief gate (issue 43, finding 2) --------------------------------------------------------


def _poisoned(node: RobotNode, info: float, shift: float, stamp: int) -> bytes:
    """``node``'s own slot as a compromised member would make it: its real objects moved by
    ``shift`` metres in x, with information ``info``·I and no mean offset, within every wire
    limit."""
    own = next(s for s in node.current_stack() if s.owner == node.robot)
    po = own.summary.per_object
    assert po is not None
    n = len(own.summary.object_ids)
    xi = Xi(po.xi.lin + np.array([shift, 0.0, 0.0]), info * np.eye(3 * n), np.zeros(3 * n))
    summary = LocalSummary(own.summary.object_ids, (), ObjectClasses(po.log_phi, xi))
    slot = Slot(node.robot, stamp, summary, node.epoch)
    return encode(StackMessage(node.robot, node.position, Stack((slot,)), stamp), node.limits)


def test_the_belief_gate_refuses_poisoned_slots_and_not_the_owners_next_one(
    frames: dict[str, list[SensorFrame]],
) -> None:
    nodes, twin = _nodes(), _nodes()
    run_fleet(nodes, frames, CHAIN, 8)
    run_fleet(twin, frames, CHAIN, 8)
    r1, r2 = nodes["r1"], nodes["r2"]
    assert r2.distributed.stamps["r1"] == 7  # r2's D holds r1's objects 1 and 2
    # Finding 2 as found: Λ = 10⁹·I (the wire's cap), 9 km away.
    got = r2.receive(_poisoned(r1, 1e9, 9000.0, 9), "r1")
    assert got.message is None and got.gated == 1 and "information" in str(got.error)
    # Within the information bound (2 × 9 steps × 100), so the Mahalanobis test must catch it.
    got = r2.receive(_poisoned(r1, 500.0, 9000.0, 9), "r1")
    assert got.message is None and got.gated == 1 and "Mahalanobis" in str(got.error)
    assert r2.counters.rejected_slots == 2 and r2.stack.version_of("r1") == (0, 7)
    # Relayed by r3 as part of its stack: only that slot is dropped.
    relayed = decode(_poisoned(r1, 500.0, 9000.0, 9)).stack
    r3_own = [s for s in nodes["r3"].current_stack() if s.owner == "r3"]
    bytes_ = encode(StackMessage("r3", None, Stack((*r3_own, *relayed)), 9), r2.limits)
    got = r2.receive(bytes_, "r3")
    assert got.message is not None and got.gated == 1
    assert [s.owner for s in got.message.stack] == ["r3"]
    r2.counters.rejected_slots = 2
    # r1's genuine next version is taken, and r2 steps exactly as if no poison had come.
    got = r2.receive(r1.outgoing(), "r1")
    assert got.taken and got.gated == 0 and r2.stack.version_of("r1") == (0, 8)
    assert twin["r2"].receive(twin["r1"].outgoing(), "r1").taken
    twin_r3 = [s for s in twin["r3"].current_stack() if s.owner == "r3"]
    assert (
        twin["r2"]
        .receive(encode(StackMessage("r3", None, Stack(tuple(twin_r3)), 9), r2.limits), "r3")
        .taken
    )
    r2.on_frame(frames["r2"][8])
    twin["r2"].on_frame(frames["r2"][8])
    _assert_same_belief(r2.distributed, twin["r2"].distributed, "r2")


def _class_poisoned(node: RobotNode, boost: float, stamp: int) -> bytes:
    """``node``'s own slot with its genuine ξ, and ``boost`` nats on the last class of its first
    object: within the wire's |log φ| ≤ 10⁶, beyond any detections' worth."""
    own = next(s for s in node.current_stack() if s.owner == node.robot)
    po = own.summary.per_object
    assert po is not None
    phi = np.array(po.log_phi, dtype=float)
    phi[0, -1] += boost
    summary = LocalSummary(own.summary.object_ids, (), ObjectClasses(phi, po.xi))
    slot = Slot(node.robot, stamp, summary, node.epoch)
    return encode(StackMessage(node.robot, node.position, Stack((slot,)), stamp), node.limits)


def test_the_belief_gate_refuses_class_evidence_no_detections_can_give(
    frames: dict[str, list[SensorFrame]],
) -> None:
    nodes = _nodes()
    run_fleet(nodes, frames, CHAIN, 8)
    r1, r2 = nodes["r1"], nodes["r2"]
    first = next(s for s in r1.current_stack() if s.owner == "r1").summary.object_ids[0]
    b = r2.gate.per_detection
    assert 10.0 < b < 1e3  # the paper's classifier: tens of nats per detection at most
    got = r2.receive(_class_poisoned(r1, 1e5, 9), "r1")
    assert got.message is None and got.gated == 1
    assert f"object {first} has class evidence" in str(got.error)
    assert r2.counters.rejected_slots == 1 and r2.stack.version_of("r1") == (0, 7)
    # Without the bound the same slot is taken, and r2's D is certain of the forged class.
    r2.gate.per_detection = 0.0
    r2.gate.changed()
    assert r2.receive(_class_poisoned(r1, 1e5, 9), "r1").taken
    r2.on_frame(frames["r2"][8])
    d = r2.distributed
    marginal = d.class_marginals()[list(d.object_ids).index(first)]
    assert marginal[-1] > 1 - 1e-9, marginal


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_belief_gate_refuses_nothing_on_honest_runs(seed: int) -> None:
    paper = load_scenario("paper")
    nodes = make_nodes(paper, belief_model(paper), BeliefConfig(), lambda r: belief_rng(seed, [r]))
    frames = Simulator(paper, seed).all_frames()
    stats = run_fleet(nodes, frames, link_model_for(paper), paper.steps)
    assert stats.deliveries > 50
    assert [n.counters.rejected_slots for n in nodes.values()] == [0, 0, 0]


def test_the_own_slot_goes_out_with_ls_position_when_ds_is_outside_the_limits(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """A robot's own slot is built from L: a D pushed outside the world (finding 2 of issue 43
    before the gate) must not silence it."""
    node = _node("r1")
    _advance(node, frames, 3)
    node.position = (2e4, 0.0)  # D's position, beyond ±world_extent
    message = decode(node.encoded_stack(), node.limits)
    assert [s.owner for s in message.stack] == ["r1"]
    assert message.position == node.local.position("r1")
    assert node.counters.own_slot_invalid == 0
    delta = decode(node.encoded_delta(["r1"]), node.limits)
    assert [s.owner for s in delta.stack] == ["r1"] and delta.position == message.position


def test_a_refused_large_slot_leaves_no_bytes_behind(frames: dict[str, list[SensorFrame]]) -> None:
    """Issue 43, finding 4: slots of tens of MB that are refused (here by the belief gate, and by
    the model fit) must not stay in the receiver's memory: measured with tracemalloc, which
    counts what Python and numpy hold, not what the allocator keeps from the OS."""
    import gc
    import tracemalloc

    nodes = _nodes()
    run_fleet(nodes, frames, CHAIN, 4)
    r1, r2 = nodes["r1"], nodes["r2"]
    n = 512  # the most objects a slot may carry: a dense ξ of 1,536 × 1,536, 9.5 MB on the wire
    ids = tuple(range(1000, 1000 + n))
    xi = Xi(np.zeros((n, 3)), 1e9 * np.eye(3 * n), np.zeros(3 * n))
    phi = np.zeros((n, SCENARIO.num_classes))
    poison = LocalSummary(ids, (), ObjectClasses(phi, xi))
    payloads = [
        encode(StackMessage("r1", None, Stack((Slot("r1", stamp, poison),)), stamp), r2.limits)
        for stamp in (5, 6)
    ]
    assert min(len(p) for p in payloads) > 9_000_000
    del xi, poison
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for payload in payloads:
            got = r2.receive(payload, "r1")
            assert got.message is None and got.gated == 1
        del got
        gc.collect()
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert held < 200_000, held
    assert r2.stack.version_of("r1") == (0, 3) and r1.k == 4


def test_a_node_with_robot_local_ids_and_joint_classes_neither_sends_nor_holds_slots(
    frames,
) -> None:  # type: ignore[no-untyped-def]
    """Frames without global ids under a table of joint classes: the node associates them (L
    and D on the same local ids), but fleet association needs per-object classes, so its slot,
    whose ids no peer shares, stays home, and a peer's slot is counted and not held."""
    model = belief_model(SCENARIO)
    sensor = sensor_field(SCENARIO, "r1")
    joint = BeliefConfig.joint()
    r1 = make_node("r1", SCENARIO.robot("r1").start, model, SEED, joint, sensor=sensor)
    r2 = make_node("r2", SCENARIO.robot("r2").start, model, SEED, joint)
    id_less = Simulator(SCENARIO, SEED, detector=Detector("none")).frames("r1")
    for k in range(1, STEPS + 1):
        r1.on_frame(id_less[k - 1])
        r2.on_frame(frames["r2"][k - 1])
    assert r1.local_ids and r1.local.object_ids and r1.distributed.object_ids == r1.local.object_ids
    assert r1.distributed.association is None and r1.outgoing() is None
    peer = r2.outgoing()
    assert peer is not None
    got = r1.receive(encode(StackMessage("r2", None, decode(peer).stack, STEPS)))
    assert not got.taken and r1.counters.unassociated_slots == 1 and len(r1.stack) == 0


# -- the neighbourhood bound (issue 47) ----------------------------------------------------------


def _single(owner: str, stamp: int, summary: LocalSummary) -> bytes:
    return encode(StackMessage(owner, None, Stack((Slot(owner, stamp, summary),)), stamp))


def test_a_full_stack_takes_a_fresher_slot_for_its_stalest_and_d_follows(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """With room for two peers' slots, a slot of a new owner made later than the stalest held
    one takes its place (counted), one made no later is neither parsed nor held; D keeps the
    evicted owners' last versions until it keeps two (as many as the stack holds peers), and
    then drops them at its next step (a rebuild from L and the held slots)."""
    limits = dataclasses.replace(Limits(num_classes=SCENARIO.num_classes), max_slots=3)
    model = belief_model(SCENARIO)
    nodes = make_nodes(
        SCENARIO, model, BeliefConfig(), lambda r: belief_rng(SEED, [r]), limits=limits
    )
    r1, r3 = nodes["r1"], nodes["r3"]
    _advance(r3, frames, 6)
    _advance(r1, frames, 6)
    summary = _own_slot(r3).summary
    for owner, stamp in (("a", 6), ("b", 7)):
        assert r1.receive(_single(owner, stamp, summary), owner).taken
    _advance(r1, frames, 7)
    assert set(r1.distributed.versions) == {"a", "b"}
    skipped = r1.counters.slots_skipped
    assert not r1.receive(_single("c", 6, summary), "c").taken  # no later than a's
    assert r1.counters.slots_skipped == skipped + 1 and r1.counters.evicted_slots == 0
    assert r1.receive(_single("c", 8, summary), "c").taken
    assert {s.owner for s in r1.current_stack()} == {"r1", "b", "c"}
    assert r1.counters.evicted_slots == 1 and len(r1.stack) <= limits.max_slots
    rebuilds = r1.counters.rebuilds
    _advance(r1, frames, 8)
    assert set(r1.distributed.versions) == {"a", "b", "c"}  # a's last version kept
    assert r1.counters.rebuilds == rebuilds
    assert r1.receive(_single("d", 9, summary), "d").taken  # b evicted: two dropped now
    assert {s.owner for s in r1.current_stack()} == {"r1", "c", "d"}
    _advance(r1, frames, 9)
    assert set(r1.distributed.versions) == {"c", "d"}
    assert r1.counters.rebuilds == rebuilds + 1 and r1.counters.evicted_slots == 2
    assert r1.outgoing() is not None and r1.counters.own_slot_invalid == 0


def test_a_robot_that_keeps_fewer_slots_than_a_stack_holds_takes_stacks_of_any_size(
    frames: dict[str, list[SensorFrame]],
) -> None:
    """``keep_slots`` (``[agent] keep_slots``) bounds what one robot keeps, not what it takes:
    with 3 (two peers) and the wire's 64 slots a stack, a stack of four peers' slots is taken,
    not refused whole — two held, two refused for want of room — and the robot's own stacks
    carry at most three; a fresher slot of a new owner then takes the stalest's place."""
    model = belief_model(SCENARIO)
    r1 = make_node("r1", SCENARIO.robot("r1").start, model, SEED, BeliefConfig(), keep_slots=3)
    r3 = make_nodes(SCENARIO, model, BeliefConfig(), lambda r: belief_rng(SEED, [r]))["r3"]
    assert r1.limits.max_slots == 64 and r1.keep_slots == 3
    _advance(r3, frames, 6)
    _advance(r1, frames, 6)
    summary = _own_slot(r3).summary
    four = Stack(tuple(Slot(o, 6 + i, summary) for i, o in enumerate(("a", "b", "c", "d"))))
    got = r1.receive(encode(StackMessage("a", None, four, 9)), "a")
    assert got.taken and got.error is None
    assert {s.owner for s in r1.current_stack()} == {"r1", "a", "b"}
    assert r1.counters.foreign_slots == 2 and r1.counters.evicted_slots == 0
    assert len(decode(r1.outgoing(), r1.limits).stack) == 3
    assert r1.receive(_single("e", 10, summary), "e").taken  # fresher than a's 6: a goes
    assert {s.owner for s in r1.current_stack()} == {"r1", "b", "e"}
    assert r1.counters.evicted_slots == 1
    for bad in (1, 65):
        with pytest.raises(ValueError, match="keep_slots"):
            make_node("r1", SCENARIO.robot("r1").start, model, SEED, BeliefConfig(), keep_slots=bad)


def test_a_nodes_d_takes_the_earlier_detections_its_l_confirms() -> None:
    """Frames without ids: when L confirms an object, its earlier detections enter L and D
    alike, so a node that has heard no peer has D equal to L (without them in D, D's objects
    would hold fewer detections than L's)."""
    model = belief_model(SCENARIO)
    node = make_node(
        "r1",
        SCENARIO.robot("r1").start,
        model,
        SEED,
        BeliefConfig(),
        sensor=sensor_field(SCENARIO, "r1"),
    )
    replayed = 0
    for frame in Simulator(SCENARIO, SEED, detector=Detector("none")).frames("r1"):
        node.on_frame(frame)
        assert node.track.association is not None
        replayed += len(node.track.association.replay)
    assert replayed >= 2 and node.local.object_ids
    local, dist = node.local.snapshot("r1"), node.distributed.snapshot("r1")
    assert node.distributed.object_ids == node.local.object_ids
    np.testing.assert_allclose(dist.object_pose, local.object_pose, atol=1e-9)
    np.testing.assert_allclose(dist.object_cov, local.object_cov, atol=1e-12)
    np.testing.assert_allclose(
        node.distributed.class_log_posterior(), node.local.class_log_posterior(), atol=1e-9
    )


def _pair_without_ids() -> tuple[RobotNode, RobotNode, Simulator]:
    """Two robots 1 m apart seeing the same four objects, frames without ids: r1's node before
    its first frame, r2's after all of its, and the simulator of r1's frames."""
    pair = parse_scenario(
        fleet_text(
            "pair",
            14,
            [0.0, 1.0],
            [(3.0, 0.5, 0.5, 1), (4.0, -0.4, -1.0, 2), (5.0, 1.2, 2.0, 2), (6.0, 0.3, 1.0, 1)],
        ),
        "pair.toml",
    )
    model = belief_model(pair)
    r1, r2 = (
        make_node(r, pair.robot(r).start, model, 4, BeliefConfig(), sensor=sensor_field(pair, r))
        for r in ("r1", "r2")
    )
    sim = Simulator(pair, 4, detector=Detector("none"))
    for frame in sim.frames("r2"):
        r2.on_frame(frame)
    return r1, r2, sim


def test_a_node_matches_a_held_slot_again_when_its_l_confirms_objects() -> None:
    """Frames without ids: r2's stack reaches r1 before r1 has confirmed any object, and no
    newer one follows. When r1 confirms its own objects, the node matches r2's held slot again
    and rebuilds D: r2's objects land on r1's own, and no fresh duplicate stays (without it,
    D would hold every object twice until r2's next version)."""
    r1, r2, sim = _pair_without_ids()
    for k, frame in enumerate(sim.frames("r1"), start=1):
        if k == 2:
            assert not r1.local.object_ids
            message = r2.outgoing()
            assert message is not None
            assert r1.receive(message).taken
        r1.on_frame(frame)
    fleet = r1.distributed.association
    assert fleet is not None and r1.without_ids.rematches >= 1
    assert len(r1.local.object_ids) == 4
    assert sorted(r1.distributed.object_ids) == sorted(r1.local.object_ids)
    assert all(fleet.sources(j) == {"", "r2"} for j in r1.distributed.object_ids)


def _sightings(belief: HybridBelief) -> int:
    """The detection factors a belief holds (a robot pose and an object)."""
    graph = belief.map_hypothesis().continuous.isam.getFactorsUnsafe()
    n = 0
    for i in range(graph.size()):
        factor = graph.at(i)
        keys = [] if factor is None else list(factor.keys())
        n += len(keys) == 2 and sum(pose_step(k) is not None for k in keys) == 1
    return n


def test_d_takes_a_peers_object_at_its_first_sightings_and_never_counts_one_twice() -> None:
    """r2's stack reaches r1 at step 2, before r1 confirms anything: r1's next unconfirmed
    detections of those objects go to D at once (its L waits for its 3rd hit). At every step
    D holds each of r1's detections once: L's, plus those D took for objects L has not
    confirmed; at the confirmation the replay into D leaves out what D took."""
    r1, r2, sim = _pair_without_ids()
    message = r2.outgoing()
    assert message is not None
    for k, frame in enumerate(sim.frames("r1"), start=1):
        if k == 2:
            assert r1.receive(message).taken
        r1.on_frame(frame)
        unconfirmed = {t for _, t in r1.without_ids.took} - set(r1.local.object_ids)
        pending = sum(t in unconfirmed for _, t in r1.without_ids.took)
        assert _sightings(r1.distributed) == _sightings(r1.local) + pending, k
    assert r1.without_ids.peer_sightings >= 4


def test_a_fleet_of_two_id_kinds_refuses_each_others_slots_and_counts_them() -> None:
    """r2's frames have no ids, so its slot states robot-local ids. r1 with given ids refuses
    it (its D would read r2's track numbers as global ids), counts it, and fuses nothing of
    it; r1 without ids refuses a slot of global ids the same way, and before its own first
    frame it refuses r2's slot too (it does not know yet how its D reads ids): the next
    version, after that frame, is matched and fused."""
    r1, r2, sim = _pair_without_ids()
    message = r2.outgoing()
    assert message is not None
    slot = decode(message, r2.limits).stack.by_owner()["r2"]
    assert slot.summary.per_object is not None and slot.summary.per_object.local_ids
    assert not r1.receive(message).taken and r1.counters.rejected_slots == 1  # no frame yet
    given = Simulator(sim.scenario, 4)
    r1.on_frame(given.frame("r1", 1))
    assert not r1.receive(message).taken and r1.counters.rejected_slots == 2
    assert "object ids robot-local" in r1.counters.last_error
    assert r1.distributed.versions.get("r2") is None
    # the other way round: r2 (without ids) and a slot of global ids
    from_given = r1.outgoing()
    assert from_given is not None
    rejected = r2.counters.rejected_slots
    assert not r2.receive(from_given).taken and r2.counters.rejected_slots == rejected + 1
    assert "object ids global" in r2.counters.last_error
    # an id-less r1 takes r2's slot once its first frame told it its kind
    fresh, _, _ = _pair_without_ids()
    fresh.on_frame(sim.frame("r1", 1))
    assert fresh.receive(message).taken and fresh.counters.rejected_slots == 0
