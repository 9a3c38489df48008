"""Data association on the robot (estimator.association; design note "data association" §4):
ids stripped on a sparse world give back the truth, true pairs' NIS is χ²_d (gate calibration),
class evidence tells apart two objects at one pose, clutter alone confirms nothing and leaves the
belief as it was, and the result does not depend on the order of a frame's detections."""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict

import numpy as np
import pytest
from scipy.stats import binom, chi2

from deploy.base.build import belief_model, belief_rng
from estimator.association import AssociationConfig, Associator, SensorField
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.models import LOCAL_IDS, NO_ID, NO_IDS, Detection, SensorFrame
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import CLUTTER, Detector, Simulator
from tests.estimator.scenarios import tiny_scenario


def _sparse(kind: str, steps: int) -> Scenario:
    """One robot in a generated world, only objects at least 3 m from every other kept."""
    s = generate_scenario(1, 40, 3, seed=31, steps=steps, area=24.0, kind=kind)
    kept: list = []
    for o in s.objects:
        if all(math.dist(o.pose[:2], p.pose[:2]) >= 3.0 for p in kept):
            kept.append(o)
    return dataclasses.replace(s, objects=tuple(kept))


def _associator(s: Scenario, **changes: object) -> Associator:
    sensor = s.robots[0].sensor
    config = AssociationConfig(**changes)  # type: ignore[arg-type]
    return Associator(belief_model(s), SensorField(sensor.range, sensor.half_angle), config)


def _run(
    s: Scenario, detector: Detector, assoc: Associator, seed: int = 0
) -> tuple[HybridBelief, list[tuple[int, int, float]]]:
    """The robot's belief stepped on associated frames; (track, true label, NIS) per detection."""
    robot = s.robot_ids[0]
    belief = HybridBelief(belief_model(s), {robot: s.robots[0].start})
    rng = belief_rng(seed, [robot])
    sim = Simulator(s, seed, detector=detector)
    out = []
    for k in range(1, s.steps + 1):
        frame, labels = sim.labelled_frame(robot, k)
        a = assoc.associate(belief, frame)
        out += list(zip(a.tracks, labels, a.nis, strict=True))
        belief.step([a.frame], rng, a.replay)
    return belief, out


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_associate_sparse_world_without_ids_equals_the_truth(kind: str) -> None:
    s = _sparse(kind, 120)
    belief, out = _run(s, Detector(NO_IDS), _associator(s))
    labels_of: dict[int, set[int]] = defaultdict(set)
    confirmed_of: dict[int, set[int]] = defaultdict(set)
    for track, label, _ in out:
        labels_of[track].add(label)
        if track in belief.object_ids:
            confirmed_of[label].add(track)
    # every track (a tentative one dropped out of view too) holds one object, every object
    # at most one map object
    assert all(len(v) == 1 for v in labels_of.values()), "a track holds two objects"
    assert all(len(v) == 1 for v in confirmed_of.values()), "an object split over two tracks"
    assert len(belief.object_ids) == len(confirmed_of) >= 8


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_associate_true_pairs_innovations_are_chi2(kind: str) -> None:
    """With the gate opened (α = 1e-12) on a sparse world, every map pairing is a true one: its
    NIS is χ²_d, and the share above χ²_d(0.999) within a binomial interval of 10⁻³ (a
    Jacobian, frame or covariance error moves both)."""
    s = _sparse(kind, 150)
    nis = np.array(
        [
            v
            for seed in range(7)
            for _, _, v in _run(s, Detector(NO_IDS), _associator(s, alpha=1e-12), seed)[1]
            if not math.isnan(v)
        ]
    )
    dim = 3 if kind == "pose" else 2
    assert len(nis) > 500
    outside = int(np.sum(nis > chi2.ppf(0.999, dim)))
    assert outside <= binom.ppf(0.999, len(nis), 1e-3), (outside, len(nis))
    assert abs(nis.mean() - dim) < 4.0 * math.sqrt(2 * dim / len(nis)) + 0.1 * dim, nis.mean()


def _twins() -> Scenario:
    """Objects 1 (class 1) and 2 (class 2) 5 cm apart with one heading, their best view (the
    camera on their +y side, ψ = π/2 in the paper's classifier) towards the robot, which drives
    towards them."""
    return tiny_scenario([(5.5, -1.0, 0.0, 1), (5.55, -1.0, 0.0, 2)], steps=20, sensing=6.0)


def _twin_choices(class_evidence: bool, seeds: range) -> list[bool]:
    """Per seed and step, whether a lone, id-less detection of one twin (alternating) is given to
    the right object of a belief that knows both from given ids."""
    s = dataclasses.replace(_twins(), sensor=dataclasses.replace(_twins().sensor))
    right = []
    for seed in seeds:
        belief = HybridBelief(belief_model(s), {"r1": s.robots[0].start})
        rng = belief_rng(seed, ["r1"])
        assoc = _associator(s, class_evidence=class_evidence)
        sim = Simulator(s, seed)
        for k in range(1, s.steps + 1):
            frame = sim.frame("r1", k)
            if k > 4 and len(frame.detections) == 2:
                twin = frame.detections[k % 2]
                lone = SensorFrame(
                    "r1",
                    k,
                    frame.odometry,
                    (Detection(NO_ID, twin.z_geo, twin.z_sem),),
                    frame.true_pose,
                    NO_IDS,
                )
                right.append(assoc.associate(belief, lone).tracks == (twin.object_id,))
            belief.step([frame], rng)
    return right


def test_associate_class_evidence_tells_twins_apart() -> None:
    with_class = _twin_choices(True, range(6))
    without = _twin_choices(False, range(6))
    # one detection's scores (the paper's classifier, noise σ ≈ 0.7 on a one-hot mean) pick
    # the right twin 8 times in 10; geometry alone flips a coin
    assert len(with_class) >= 60
    assert np.mean(with_class) >= 0.75, np.mean(with_class)
    assert abs(np.mean(without) - 0.5) < 0.15, np.mean(without)


def _clutter_frames(s: Scenario, rng: np.random.Generator) -> list[SensorFrame]:
    """Odometry-only frames of the scenario's robot with 0–3 false detections each, uniform in
    the sensor's field, scores uniform in [0, 1]."""
    frames = []
    sensor = s.robots[0].sensor
    for f in Simulator(s, 0).frames("r1"):
        dets = []
        for _ in range(int(rng.integers(0, 4))):
            r, b = sensor.range * math.sqrt(rng.uniform()), rng.uniform(-1, 1) * sensor.half_angle
            z = np.array([r * math.cos(b), r * math.sin(b), rng.uniform(-math.pi, math.pi)])
            dets.append(Detection(NO_ID, z, rng.uniform(0, 1, 2)))
        frames.append(SensorFrame("r1", f.k, f.odometry, tuple(dets), f.true_pose, NO_IDS))
    return frames


def test_associate_clutter_alone_confirms_nothing_and_leaves_the_belief() -> None:
    s = tiny_scenario([(100.0, 100.0, 0.0, 1)], steps=80)  # an object it never sees
    frames = _clutter_frames(s, np.random.default_rng(5))
    assert sum(len(f.detections) for f in frames) > 80
    assoc = _associator(s)
    belief = HybridBelief(belief_model(s), {"r1": s.robots[0].start})
    blind = HybridBelief(belief_model(s), {"r1": s.robots[0].start})
    rng, rng_blind = belief_rng(0, ["r1"]), belief_rng(0, ["r1"])
    for f in frames:
        a = assoc.associate(belief, f)
        assert a.frame.detections == () and not a.confirmed
        belief.step([a.frame], rng)
        blind.step([dataclasses.replace(f, detections=())], rng_blind)
    assert belief.object_ids == []
    assert all(len(frames) - t.k < assoc.config.forget_after for t in assoc.tentative)
    got, want = belief.snapshot("r1"), blind.snapshot("r1")
    assert got.robot_pose.tobytes() == want.robot_pose.tobytes()
    assert got.robot_cov.tobytes() == want.robot_cov.tobytes()


def test_associate_ignores_the_order_of_a_frames_detections() -> None:
    s = generate_scenario(1, 120, 4, seed=9002, steps=60, area=30.0)
    sim = Simulator(s, 2, detector=Detector(NO_IDS, clutter=0.1, miss=0.1))
    order_rng = np.random.default_rng(11)
    runs = []
    for shuffle in (False, True):
        belief = HybridBelief(belief_model(s), {"r1": s.robots[0].start})
        rng = belief_rng(2, ["r1"])
        assoc = _associator(s)
        tracks = []
        for k in range(1, s.steps + 1):
            frame = sim.frame("r1", k)
            perm = order_rng.permutation(len(frame.detections)) if shuffle else None
            if perm is not None:
                frame = dataclasses.replace(
                    frame, detections=tuple(frame.detections[i] for i in perm)
                )
            a = assoc.associate(belief, frame)
            by_detection = dict(
                zip((d.z_geo.tobytes() for d in frame.detections), a.tracks, strict=True)
            )
            tracks.append(by_detection)
            belief.step([a.frame], rng, a.replay)
        runs.append((tracks, belief.snapshot("r1").object_pose.tobytes()))
    assert sum(len(t) for t in runs[0][0]) > 100
    assert runs[0] == runs[1]


def test_associate_counts_clutter_apart_from_objects() -> None:
    """On the dense world with 5 % clutter, no false detection ends in a confirmed object and
    every confirmed object is a true one."""
    s = generate_scenario(1, 120, 4, seed=9002, steps=80, area=30.0)
    belief, out = _run(s, Detector(NO_IDS, clutter=0.05, miss=0.1), _associator(s))
    assert any(label == CLUTTER for _, label, _ in out)
    confirmed = set(belief.object_ids)
    assert not any(track in confirmed for track, label, _ in out if label == CLUTTER)


def _search_problem(n: int, seed: int):  # type: ignore[no-untyped-def]
    """n detections and n candidates of a point kind, every pairing within the gate: detection d
    is candidate d's, the others lie a little farther (a crowd of split objects)."""
    from estimator.association import _JointSearch

    rng = np.random.default_rng(seed)
    dim = 2
    r = np.eye(dim) * 0.05
    hph = np.zeros((n, dim, n, dim))
    for c in range(n):
        hph[c, :, c, :] = np.eye(dim) * 0.02
    nu = rng.normal(0.0, 0.12, (n, n, dim))
    nu[np.arange(n), np.arange(n)] *= 0.3
    extra = np.full((n, n), 2.0) + rng.normal(0.0, 0.1, (n, n))
    search = _JointSearch(nu, hph, r, extra, 1e-3)
    s = np.linalg.inv(hph[np.arange(n), :, np.arange(n), :] + r)
    d2 = np.einsum("dni,nij,dnj->dn", nu, s, nu)
    gain = -0.5 * d2 + extra
    return search, d2 <= 13.8, gain


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_joint_search_stops_at_its_budget_and_keeps_the_better_of_best_and_greedy(
    seed: int,
) -> None:
    """Many candidates gating every detection (MRCLAM without barcodes: 55,000 joint
    evaluations, 3.7 s, on one frame): the exhaustive search stops after ``budget`` joint
    evaluations and returns a jointly compatible pairing at least as good as the greedy one;
    with room enough it is the exhaustive optimum, not cut."""
    search, gated, gain = _search_problem(7, seed)
    calls = 0
    joint = search.joint

    def counted(pairs):  # type: ignore[no-untyped-def]
        nonlocal calls
        calls += 1
        return joint(pairs)

    search.joint = counted  # type: ignore[method-assign]
    pairs, cut = search.best(gated, gain, exhaustive=8, budget=300)
    assert cut
    assert calls <= 300 + 1 + 7 + 1  # the budget, then the greedy pairing and its score
    score = joint(list(pairs.items()))
    assert score is not None and len(set(pairs.values())) == len(pairs)
    greedy = search._greedy(gated, gain)
    assert score >= joint(list(greedy.items()))  # type: ignore[operator]
    # Small enough to finish: the optimum, the same with any budget above what it needs.
    small, gated4, gain4 = _search_problem(4, seed)
    full, cut_full = small.best(gated4, gain4, exhaustive=8, budget=10**7)
    again, cut_again = small.best(gated4, gain4, exhaustive=8, budget=2000)
    assert not cut_full and not cut_again and full == again
    assert small.best(gated4, gain4, exhaustive=8, budget=5)[1]  # and cut with too little


# -- a confirmed object's earlier detections (replay) --------------------------------------------


def _replayed_and_given(
    seed: int,
) -> tuple[list[tuple[str, int, Detection]], HybridBelief, HybridBelief, HybridBelief]:
    """Two objects seen from step 1, confirmed at their 3rd hit: (the replay, the belief stepped
    with it, the belief stepped without it, the belief given each object's local id from its
    first detection)."""
    s = tiny_scenario([(4.0, 0.5, 30.0, 2), (5.0, -1.0, -60.0, 1)], steps=6)
    model = belief_model(s)
    sim = Simulator(s, seed, detector=Detector(NO_IDS))
    assoc = _associator(s)
    start = {"r1": s.robots[0].start}
    replayed, without, given = (HybridBelief(model, start) for _ in range(3))
    rngs = [belief_rng(seed, ["r1"]) for _ in range(3)]
    track_of: dict[int, int] = {}
    replay: list[tuple[str, int, Detection]] = []
    for k in range(1, s.steps + 1):
        frame, labels = sim.labelled_frame("r1", k)
        a = assoc.associate(replayed, frame)
        track_of.update(zip(labels, a.tracks, strict=True))
        replay += a.replay
        replayed.step([a.frame], rngs[0], a.replay)
        without.step([a.frame], rngs[1])
        known = tuple(
            Detection(track_of[lab], d.z_geo, d.z_sem)
            for d, lab in zip(frame.detections, labels, strict=True)
        )
        given.step([dataclasses.replace(frame, detections=known, ids=LOCAL_IDS)], rngs[2])
    return replay, replayed, without, given


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_confirmed_object_brings_its_earlier_detections_into_the_belief(seed: int) -> None:
    """Confirmed at its 3rd hit, an object's first two detections enter the belief from the
    poses they were made at, with their class evidence: the belief then equals, up to where
    the weak object prior is centred, one that knew the object from its first detection; left
    out, the object is 0.1–0.25 m and several nats of class evidence away from it."""
    replay, replayed, without, given = _replayed_and_given(seed)
    assert sorted((k, d.object_id) for _, k, d in replay) == [(1, 0), (1, 1), (2, 0), (2, 1)]
    order = [given.object_ids.index(j) for j in replayed.object_ids]
    want = given.snapshot("r1")
    want_pose = want.object_pose[0][order]
    want_var = np.diagonal(want.object_cov[0][order], axis1=1, axis2=2)
    want_classes = given.class_log_posterior()[order]
    got = replayed.snapshot("r1")
    np.testing.assert_allclose(got.object_pose[0], want_pose, atol=0.02)
    np.testing.assert_allclose(np.diagonal(got.object_cov[0], axis1=1, axis2=2), want_var, rtol=0.1)
    np.testing.assert_allclose(replayed.class_log_posterior(), want_classes, atol=0.1)
    # the test sees a replay left out: 50-90 % more variance, poses and classes further off
    missed = without.snapshot("r1")
    assert (np.diagonal(missed.object_cov[0], axis1=1, axis2=2) > 1.4 * want_var).all()
    assert np.abs(missed.object_pose[0] - want_pose).max() > 0.1
    assert np.abs(without.class_log_posterior() - want_classes).max() > 1.0


def test_a_replay_is_checked_and_one_on_a_marginalised_pose_is_counted_and_left_out() -> None:
    s = tiny_scenario([(4.0, 0.5, 30.0, 2)], steps=8)
    model = belief_model(s)
    frames = Simulator(s, 0).frames("r1")
    det = frames[0].detections[0]
    for bad, why in (
        (("r2", 1, det), "not an earlier step"),
        (("r1", 3, det), "not an earlier step"),
        (("r1", 0, det), "not an earlier step"),
        (("r1", 1, Detection(99, det.z_geo, det.z_sem)), "no frame of this step"),
        (("r1", 1, Detection(det.object_id, det.z_geo[:2], det.z_sem)), "z_geo has 2 numbers"),
    ):
        belief = HybridBelief(model, {"r1": s.robots[0].start})
        belief.step([frames[0]], belief_rng(0, ["r1"]))
        step_of = dict(belief.step_of)
        with pytest.raises(ValueError, match=why):
            belief.step([frames[1]], belief_rng(0, ["r1"]), [bad])
        assert belief.step_of == step_of  # refused before anything moved
    windowed = HybridBelief(
        model, {"r1": s.robots[0].start}, dataclasses.replace(BeliefConfig(), window=2)
    )
    rng = belief_rng(0, ["r1"])
    for f in frames[:6]:
        windowed.step([f], rng)
    windowed.step([frames[6]], rng, [("r1", 1, det), ("r1", 6, det)])
    assert windowed.replays_dropped == 1


def test_pair_takes_only_the_objects_it_is_given_and_leaves_the_tentatives() -> None:
    """``Associator.pair``: stage 1 against a subset of the belief's objects; the tentative
    objects and the track numbering are not touched."""
    s = _sparse("pose", 80)
    belief, _ = _run(dataclasses.replace(s, steps=79), Detector(NO_IDS), _associator(s))
    assoc = _associator(s)
    frame = Simulator(s, 0, detector=Detector(NO_IDS)).frame("r1", 80)
    assert len(belief.object_ids) >= 4 and frame.detections
    every = assoc.pair(belief, frame, belief.object_ids)
    assert every and all(j in belief.object_ids for j in every.values())
    seen = next(iter(every.values()))
    assert set(assoc.pair(belief, frame, {seen}).values()) == {seen}
    others = [j for j in belief.object_ids if j != seen]
    assert seen not in assoc.pair(belief, frame, others).values()
    assert assoc.pair(belief, frame, ()) == {}
    assert assoc.tentative == [] and assoc.next_track == 0


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_a_guide_that_knows_the_robot_pairs_what_a_drifted_belief_splits(kind: str) -> None:
    """L and a guide step on the same frames, but L takes one step's odometry 1.5 m off (a
    drift burst, no detection in it). Associated on L, the next frame's detections of mapped
    objects fall outside every gate and start new tentative objects (splits); guided by the
    belief that kept the true odometry, every one goes to its own object. What enters L is
    still L's own detection; a guide at another step is refused."""
    s = generate_scenario(1, 40, 3, seed=31, steps=40, area=24.0, kind=kind)
    robot = s.robot_ids[0]
    model = belief_model(s)
    sim = Simulator(s, 0)
    beliefs = [HybridBelief(model, {robot: s.robots[0].start}) for _ in range(2)]
    rngs = [belief_rng(0, [robot]) for _ in range(2)]
    k = next(  # a step that sees at least two objects the robot saw before it
        k
        for k in range(12, s.steps)
        if len(
            {d.object_id for d in sim.frame(robot, k + 1).detections}
            & {d.object_id for j in range(1, k) for d in sim.frame(robot, j).detections}
        )
        >= 2
    )
    for j in range(1, k):
        for b, rng in zip(beliefs, rngs, strict=True):
            b.step([sim.frame(robot, j)], rng)
    true = sim.frame(robot, k)
    off = np.array([1.5, 0.0, 0.0])
    burst = SensorFrame(robot, k, true.odometry + off, (), true.true_pose)
    local, guide = beliefs
    local.step([burst], rngs[0])
    guide.step([dataclasses.replace(true, detections=())], rngs[1])
    frame, labels = Simulator(s, 0, detector=Detector(NO_IDS)).labelled_frame(robot, k + 1)
    mapped = [i for i, lab in enumerate(labels) if lab in local.object_ids]
    assert len(mapped) >= 2
    alone = _associator(s).associate(local, frame)
    guided = _associator(s).associate(local, frame, guide)
    assert all(guided.tracks[i] == labels[i] for i in mapped), (guided.tracks, labels)
    assert sum(alone.tracks[i] == labels[i] for i in mapped) < len(mapped) / 2
    entered = {d.object_id for d in guided.frame.detections}
    assert entered == {labels[i] for i in mapped}
    with pytest.raises(ValueError, match="guide of r1's association is at step"):
        _associator(s).associate(
            local, sim.frame(robot, k + 1), beliefs[0] if False else _ahead(guide, sim, robot, k)
        )


def _ahead(belief: HybridBelief, sim: Simulator, robot: str, k: int) -> HybridBelief:
    """``belief`` one step further (a guide at another step than the belief it guides)."""
    belief.step([sim.frame(robot, k + 1)], belief_rng(1, [robot]))
    return belief
