"""Association across the fleet (``estimator.fleet_association``): the matching on synthetic maps
(gate, class evidence, PCM), the mappings' life (hysteresis, one-to-one, fresh ids), and the
undo of a wrong mapping inside a distributed belief (design note "data association", §4)."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng, sensor_field
from estimator.association import Associator
from estimator.distributed import DistributedBelief
from estimator.factors import object_key
from estimator.fleet_association import (
    FRESH_TOP,
    FleetAssociation,
    FleetAssociationConfig,
    Objects,
    OwnerMap,
    match,
    same_object_log_ratio,
)
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.slots import summarise
from estimator.summary import LocalSummary, ObjectClasses
from estimator.xi import Xi
from protocol.stack import Slot
from sim.loader import parse_scenario
from sim.sensors import Detector, Simulator
from tests.estimator.scenarios import fleet_text

LOG_PRIOR = np.log([0.5, 0.5])
SURE = {0: np.log([0.99, 0.01]), 1: np.log([0.01, 0.99])}
UNSURE = np.log([0.5, 0.5])


def _objects(ids, xy, cov, classes=None) -> Objects:  # type: ignore[no-untyped-def]
    """Point objects (d = 2) at ``xy`` with joint covariance ``cov`` (2n, 2n)."""
    xy = np.asarray(xy, dtype=float)
    log_p = np.array([SURE[c] if classes else UNSURE for c in (classes or [0] * len(xy))])
    return Objects(tuple(ids), xy, np.asarray(cov, dtype=float), log_p)


def _iid(n: int, var: float) -> np.ndarray:
    return var * np.eye(2 * n)


def test_match_finds_the_same_objects_and_leaves_the_rest_new() -> None:
    """Two noisy copies of a sparse map (objects ≥ 3 m apart) match one to one; an owner object
    that D does not hold, and one outside the gate, match nothing."""
    rng = np.random.default_rng(5)
    truth = rng.uniform(0, 20, size=(8, 2))
    truth = truth[np.argsort(truth[:, 0])]
    keep = [0]
    for i in range(1, len(truth)):
        if min(np.linalg.norm(truth[i] - truth[j]) for j in keep) >= 3.0:
            keep.append(i)
    truth = truth[keep]
    n = len(truth)
    owner = _objects(range(n), truth + rng.normal(0, 0.1, truth.shape), _iid(n, 0.01))
    d_xy = np.vstack([truth[1:] + rng.normal(0, 0.1, (n - 1, 2)), [[50.0, 50.0]]])
    d = _objects(range(100, 100 + n), d_xy, _iid(n, 0.01))
    got = match(owner, d, np.ones(n, bool), LOG_PRIOR, FleetAssociationConfig())
    assert got == {i: 100 + i - 1 for i in range(1, n)}


def _swap_site() -> tuple[Objects, Objects]:
    """Two objects of different classes 0.25 m apart (σ 0.22 m per map), where the owner's
    estimates lie so that geometry alone prefers them swapped; three far objects around."""
    site_o = [[0.0, 0.0], [0.25, 0.0]]
    site_d = [[0.22, 0.0], [0.0, 0.02]]  # D's estimate of the owner's object 0, then of 1
    far = [[6.0, 0.0], [0.0, 7.0], [-5.0, -4.0]]
    owner = _objects(range(5), site_o + far, _iid(5, 0.025), [0, 1, 0, 1, 0])
    d = _objects(range(10, 15), site_d + far, _iid(5, 0.025), [0, 1, 0, 1, 0])
    return owner, d


def test_class_evidence_catches_a_swap_within_a_site_that_pcm_cannot() -> None:
    owner, d = _swap_site()
    mask = np.ones(5, bool)
    right = {0: 10, 1: 11, 2: 12, 3: 13, 4: 14}
    swapped = {**right, 0: 11, 1: 10}
    assert match(owner, d, mask, LOG_PRIOR, FleetAssociationConfig()) == right
    geometry = FleetAssociationConfig(class_evidence=False)
    assert match(owner, d, mask, LOG_PRIOR, geometry) == swapped  # PCM keeps the swap


def test_pcm_drops_a_match_whose_relative_geometry_disagrees() -> None:
    """The owner's map is shifted 1 m (a common drift: its joint covariance has a 1 m² common
    mode, 0.05 m relative); D holds its objects 0–3 where they are and, 1 m off, an object
    that the owner's object 4 lands on individually but not relative to the others."""
    truth = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0], [4.0, 4.0], [8.0, 2.0]])
    shift = np.array([1.0, 0.0])
    common = np.kron(np.ones((5, 5)), np.eye(2))
    owner = _objects(range(5), truth + shift, common + _iid(5, 0.0025))
    d_xy = np.vstack([truth[:4], truth[4] + shift])
    d = _objects(range(10, 15), d_xy, _iid(5, 0.0025))
    mask = np.ones(5, bool)
    assert match(owner, d, mask, LOG_PRIOR, FleetAssociationConfig()) == {
        i: 10 + i for i in range(4)
    }
    without = FleetAssociationConfig(pcm=False)
    assert match(owner, d, mask, LOG_PRIOR, without) == {i: 10 + i for i in range(5)}


def _slot(owner: str, stamp: int, ids: tuple[int, ...]) -> Slot:
    n = len(ids)
    xi = Xi(np.zeros((n, 2)), np.eye(2 * n), np.zeros(2 * n))
    return Slot(owner, stamp, LocalSummary(ids, (), ObjectClasses(np.zeros((n, 2)), xi, True)))


def test_mapping_hysteresis_fresh_ids_and_one_to_one() -> None:
    fa = FleetAssociation(LOG_PRIOR, FleetAssociationConfig(hold=2))
    fa._update(_slot("r2", 1, (0, 1)), {0: 7})
    assert fa.mapping("r2") == {0: 7, 1: FRESH_TOP} and fa.origin(FRESH_TOP) == ("r2", 1)
    fa._update(_slot("r2", 2, (0, 1)), {0: 8, 1: 7})  # both proposed once: not yet
    assert fa.mapping("r2") == {0: 7, 1: FRESH_TOP}
    fa._update(_slot("r2", 3, (0, 1)), {0: 8})  # 0's second proposal of 8; 1's of 7 broke off
    assert fa.mapping("r2") == {0: 8, 1: FRESH_TOP} and fa.changes == 1
    fa._update(_slot("r2", 4, (0, 1, 2)), {2: 8})  # a new object takes 8 at once? 0 holds it
    m = fa.mapping("r2")
    assert m[0] == 8 and m[2] not in (8, m[1]) and fa.origin(m[2]) == ("r2", 2)
    assert fa.orphans([7, 8, FRESH_TOP, m[2]]) == []
    fa._update(_slot("r2", 5, (0, 1)), {0: 8, 1: 9})
    fa._update(_slot("r2", 6, (0, 1)), {0: 8, 1: 9})
    assert fa.mapping("r2") == {0: 8, 1: 9} and fa.orphans([8, 9, FRESH_TOP]) == [FRESH_TOP]


def test_the_younger_of_two_fresh_objects_moves_to_the_older() -> None:
    """r2's and r3's objects of one true object, fresh in D in one batch, would each move to
    the other's fresh object and swap for ever: only the younger moves."""
    fa = FleetAssociation(LOG_PRIOR, FleetAssociationConfig(hold=1))
    fa._update(_slot("r2", 1, (0,)), {})
    fa._update(_slot("r3", 1, (5,)), {})
    old, young = fa.mapping("r2")[0], fa.mapping("r3")[5]
    assert young < old
    fa._update(_slot("r2", 2, (0,)), {0: young})
    fa._update(_slot("r3", 2, (5,)), {5: old})
    assert fa.mapping("r2") == {0: old} and fa.mapping("r3") == {5: old}
    assert fa.orphans([old, young]) == [young]


def test_a_clash_never_maps_two_objects_onto_one_fresh_object() -> None:
    """Found on MRCLAM Dataset 7 with its barcodes hidden (`study --ids none`, D crashed with a
    key inserted twice): r2's object 21 had moved to one of the receiver's objects, and its old
    fresh object had been taken by r2's object 10. When 21 then clashed with another of r2's
    objects, it was sent back to that fresh object, which 10 held: two objects of one slot on
    one D id. It now gets a new fresh object."""
    fa = FleetAssociation(LOG_PRIOR, FleetAssociationConfig(hold=1))
    fa._update(_slot("r2", 1, (21,)), {})
    assert fa.mapping("r2") == {21: FRESH_TOP}
    fa._update(_slot("r2", 2, (5, 10, 21)), {5: 40, 21: 15})
    assert fa.mapping("r2") == {5: 40, 10: FRESH_TOP - 1, 21: 15}
    fa._update(_slot("r2", 3, (5, 10, 21)), {5: 40, 10: FRESH_TOP, 21: 15})  # to the older one
    assert fa.mapping("r2") == {5: 40, 10: FRESH_TOP, 21: 15}
    fa._update(_slot("r2", 4, (5, 10, 21)), {5: 40, 10: FRESH_TOP, 21: 40})  # 5 holds 40
    m = fa.mapping("r2")
    assert len(set(m.values())) == 3, m
    assert (m[5], m[10]) == (40, FRESH_TOP)
    assert m[21] not in (40, FRESH_TOP, FRESH_TOP - 1) and fa.origin(m[21]) == ("r2", 21)


# -- inside a distributed belief ------------------------------------------------------------------

STEPS = 14
SCENARIO = parse_scenario(
    fleet_text(
        "pair",
        STEPS,
        [0.0, 1.0],
        [(3.0, 0.5, 0.5, 1), (4.0, -0.4, -1.0, 2), (5.0, 1.2, 2.0, 2), (6.0, 0.3, 1.0, 1)],
        description="two robots 1 m apart seeing the same four objects",
    ),
    "pair.toml",
)
SEED = 4


def _beliefs() -> tuple[HybridBelief, DistributedBelief, DistributedBelief]:
    """r2's L and two identical D of r1 after STEPS id-less steps."""
    model = belief_model(SCENARIO)
    sim = Simulator(SCENARIO, SEED, detector=Detector("none"))
    out = []
    for robot in ("r2", "r1", "r1"):
        start = SCENARIO.robot(robot).start
        if robot == "r2":
            belief: HybridBelief = HybridBelief(model, {robot: start}, BeliefConfig())
        else:
            belief = DistributedBelief(model, robot, start, BeliefConfig())
        assoc = Associator(model, sensor_field(SCENARIO, robot))
        rng = belief_rng(SEED, [robot])
        for k in range(1, STEPS + 1):
            a = assoc.associate(belief, sim.frame(robot, k))
            belief.step([a.frame], rng, a.replay)
        out.append(belief)
    return out[0], out[1], out[2]  # type: ignore[return-value]


def _state(d: DistributedBelief) -> tuple[np.ndarray, np.ndarray, list[int]]:
    cont = d.map_hypothesis().continuous
    poses = np.array([cont.pose(object_key(j)) for j in d.object_ids])
    return poses, d.class_log_posterior(), list(d.object_ids)


@pytest.mark.parametrize("downdate", ["remove", "anti"])
def test_a_wrong_mapping_corrected_equals_the_right_one_from_scratch(downdate: str) -> None:
    """Fuse r2's slot under a wrong mapping (its objects rotated onto r1's), correct it: the
    down-date of the wrong version and the re-fusion give the D that fused the right mapping
    from the start (to 1e-9)."""
    local2, wrong, right = _beliefs()
    for d in (wrong, right):
        d.downdate = downdate
    slot = Slot("r2", STEPS, summarise(local2).robot_local())
    ids2 = slot.summary.object_ids
    own = sorted(wrong.object_ids)
    assert len(ids2) == len(own) == 4
    fa_right = FleetAssociation(LOG_PRIOR)
    right.association = fa_right
    right.integrate([slot])
    truth = fa_right.mapping("r2")
    assert sorted(truth.values()) == own  # the four objects found: the matching's own test
    rotated = {i: truth[ids2[(a + 1) % 4]] for a, i in enumerate(ids2)}
    fa = FleetAssociation(LOG_PRIOR)
    fa.maps["r2"] = OwnerMap(slot.version, rotated)
    wrong.association = fa
    wrong.integrate([slot])
    assert not np.allclose(_state(wrong)[0], _state(right)[0], atol=1e-3)
    fa.maps["r2"] = OwnerMap(slot.version, truth)
    del wrong.versions["r2"]  # the same version again, under the corrected mapping
    wrong.integrate([slot])
    for a, b in zip(_state(wrong), _state(right), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9, rtol=0)


def test_same_object_ratio_is_neutral_on_the_prior_and_rewards_a_shared_rare_class() -> None:
    prior = np.log([0.9, 0.1])
    sure_rare = np.log([1e-12, 1.0 - 1e-12])
    sure_common = np.log([1.0 - 1e-12, 1e-12])
    assert abs(same_object_log_ratio(prior, sure_rare, prior)) < 1e-12
    assert same_object_log_ratio(sure_rare, sure_rare, prior) == pytest.approx(np.log(10.0))
    assert same_object_log_ratio(sure_common, sure_common, prior) == pytest.approx(np.log(1 / 0.9))
    assert same_object_log_ratio(sure_rare, sure_common, prior) < -20.0


def test_a_held_slot_is_matched_again_onto_objects_confirmed_after_it() -> None:
    """r2's slot reaches r1 before r1 has confirmed any object: all four enter D as fresh
    objects. Once r1 confirms its own, matching the held version again proposes r2's objects
    onto them, and the second proposal moves them (``hold`` = 2, as for a new version), leaving
    the fresh ones orphaned for a rebuild; matching again without news changes nothing."""
    local2 = _beliefs()[0]
    slot = Slot("r2", STEPS, summarise(local2).robot_local())
    model = belief_model(SCENARIO)
    sim = Simulator(SCENARIO, SEED, detector=Detector("none"))
    start = SCENARIO.robot("r1").start
    local = HybridBelief(model, {"r1": start}, BeliefConfig())
    d = DistributedBelief(model, "r1", start, BeliefConfig())
    fa = FleetAssociation(LOG_PRIOR)
    d.association = fa
    assoc = Associator(model, sensor_field(SCENARIO, "r1"))
    rng, rng_d = belief_rng(SEED, ["r1"]), belief_rng(SEED, ["r1"])
    for k in range(1, STEPS + 1):
        if k == 2:
            assert not d.object_ids
            d.integrate([slot])
            assert all(fa.is_fresh(j) for j in fa.mapping("r2").values())
        a = assoc.associate(local, sim.frame("r1", k))  # on L, as a node does
        local.step([a.frame], rng, a.replay)
        d.step([a.frame], rng_d, a.replay)
    own = sorted(j for j in d.object_ids if not fa.is_fresh(j))
    assert len(own) == 4 and not fa.rematch(d, []) and fa.orphans(d.object_ids) == []
    assert not fa.rematch(d, [slot]) and len(fa.maps["r2"].pending) == 4  # proposed once
    assert fa.rematch(d, [slot])
    assert sorted(fa.mapping("r2").values()) == own
    assert len(fa.orphans(d.object_ids)) == 4 and fa.changes == 4
    assert not fa.rematch(d, [slot]) and fa.changes == 4
