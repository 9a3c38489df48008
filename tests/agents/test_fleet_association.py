"""Nodes of robot-local ids fuse each other's slots (``estimator.fleet_association`` inside
``RobotNode``): the world has r1 and r3 side by side seeing the same four objects and r2 far off,
hearing both; r1 and r3 never hear each other, so what r1 knows of r3 came relayed by r2."""

from __future__ import annotations

import numpy as np

from agents.links import Schedule
from agents.node import RobotNode
from deploy.base.build import belief_model, make_node, sensor_field
from deploy.study.fleet import run_fleet
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig
from protocol.codec import StackMessage, decode, encode
from protocol.stack import Stack
from sim.loader import parse_scenario
from sim.sensors import Detector, Simulator
from tests.estimator.scenarios import fleet_text

STEPS = 16
SEED = 6
_OBJECTS = [(3.0, 0.5, 0.5, 1), (4.0, -0.4, -1.0, 2), (5.0, 1.2, 2.0, 2), (6.0, 0.3, 1.0, 1)]
CHAIN = Schedule(((1, STEPS, "r1", "r2"), (1, STEPS, "r2", "r3")))
SCENARIO = parse_scenario(
    fleet_text(
        "relay",
        STEPS,
        [0.0, 20.0, 1.0],
        _OBJECTS,
        description="r1 and r3 see the same objects; r2, far off, relays between them",
        communication=(
            f'mode = "schedule"\nschedule = [[1, {STEPS}, "r1", "r2"], [1, {STEPS}, "r2", "r3"]]'
        ),
    ),
    "relay.toml",
)


def _nodes() -> dict[str, RobotNode]:
    model = belief_model(SCENARIO)
    return {
        r: make_node(
            r,
            SCENARIO.robot(r).start,
            model,
            SEED,
            BeliefConfig(),
            sensor=sensor_field(SCENARIO, r),
        )
        for r in SCENARIO.robot_ids
    }


def _frames() -> dict[str, list]:  # type: ignore[type-arg]
    return Simulator(SCENARIO, SEED, detector=Detector("none")).all_frames()


def _truth_of_own(node: RobotNode, frames, robot: str) -> dict[int, int]:  # type: ignore[no-untyped-def]
    """A robot's local id → the true object nearest its estimate (the objects are ≥ 1 m apart)."""
    cont = node.local.map_hypothesis().continuous
    truth = np.array([o.pose[:2] for o in SCENARIO.objects])
    out = {}
    for j in node.local.object_ids:
        xy = cont.pose(object_key(j))[:2]
        out[j] = int(np.argmin(np.linalg.norm(truth - xy, axis=1)))
    return out


def test_id_less_nodes_send_and_fuse_and_a_relayed_slot_maps_by_its_owner_ids() -> None:
    nodes = _nodes()
    frames = _frames()
    run_fleet(nodes, frames, CHAIN, STEPS)
    r1, r3 = nodes["r1"], nodes["r3"]
    fleet = r1.distributed.association
    assert fleet is not None and set(fleet.maps) == {"r3"}  # through r2, which sees nothing
    assert r1.stack.version_of("r3") is not None and not r1.counters.unassociated_slots
    mine, theirs = _truth_of_own(r1, frames, "r1"), _truth_of_own(r3, frames, "r3")
    mapping = fleet.mapping("r3")
    assert len(mapping) == len(theirs) == 4
    assert all(mine[j] == theirs[i] for i, j in mapping.items())  # onto r1's own objects
    assert sorted(r1.distributed.object_ids) == sorted(r1.local.object_ids)  # no duplicate


def test_a_relayed_slot_fuses_as_the_same_slot_from_its_owner() -> None:
    """Twin r1 nodes at one step: one hears r3's slot relayed in r2's stack, the other from
    r3 itself; both map it by r3's ids and end with the same D, bit for bit."""
    frames = _frames()
    k = 10
    twins = [_nodes()["r1"], _nodes()["r1"]]
    r3 = _nodes()["r3"]
    for f in frames["r3"][:k]:
        r3.on_frame(f)
    for node in twins:
        for f in frames["r1"][:k]:
            node.on_frame(f)
    data = r3.outgoing()
    assert data is not None
    slot = decode(data).stack.by_owner()["r3"]
    relayed = encode(StackMessage("r2", None, Stack((slot,)), k))
    direct = encode(StackMessage("r3", None, Stack((slot,)), k))
    for node, payload, sender in ((twins[0], relayed, "r2"), (twins[1], direct, "r3")):
        assert node.receive(payload, sender).taken
        node.on_frame(frames["r1"][k])
    a, b = (t.distributed for t in twins)
    assert a.association is not None and b.association is not None
    assert set(a.association.maps) == {"r3"} and a.association.mapping("r3")
    assert a.association.mapping("r3") == b.association.mapping("r3")
    assert a.object_ids == b.object_ids
    for j in a.object_ids:
        pa = a.map_hypothesis().continuous.pose(object_key(j))
        pb = b.map_hypothesis().continuous.pose(object_key(j))
        assert np.array_equal(pa, pb)
    assert np.array_equal(a.class_log_posterior(), b.class_log_posterior())
