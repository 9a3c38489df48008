"""Sensor simulation: configured noise statistics and common random numbers."""

from __future__ import annotations

import dataclasses
import random

import numpy as np
import pytest

from estimator.models import NO_ID, SensorFrame, se2, viewpoint
from sim.loader import load_scenario
from sim.scenario import Scenario
from sim.sensors import CLUTTER, Detector, Simulator, check_seed
from tests.tolerance import assert_close

SEEDS = range(40)


@pytest.fixture(scope="module")
def paper() -> Scenario:
    return load_scenario("paper")


@pytest.fixture(scope="module")
def residuals(paper: Scenario) -> dict[str, np.ndarray]:
    """Tangent-space residuals of every odometry and geometric measurement and whitened score
    residuals, over 40 seeded runs of the paper scenario."""
    odo, geo, sem = [], [], []
    poses = {o.id: np.array(o.pose) for o in paper.objects}
    classes = {o.id: o.class_index for o in paper.objects}
    for seed in SEEDS:
        sim = Simulator(paper, seed)
        model = sim.classifier
        for rid in paper.robot_ids:
            traj = sim.world.trajectories[rid]
            for f in sim.frames(rid):
                odo.append(se2.local(se2.between(traj[f.k - 1], traj[f.k]), f.odometry))
                for d in f.detections:
                    truth = se2.between(f.true_pose, poses[d.object_id])
                    geo.append(se2.local(truth, d.z_geo))
                    c = classes[d.object_id]
                    psi = viewpoint(f.true_pose, poses[d.object_id])
                    chol = np.linalg.cholesky(model.cov(c, psi))
                    sem.append(np.linalg.solve(chol, d.z_sem - model.mean(c, psi)))
    return {"odometry": np.array(odo), "geometric": np.array(geo), "semantic": np.array(sem)}


def _assert_covariance(samples: np.ndarray, expected: np.ndarray) -> None:
    """Sample covariance matches ``expected`` within 5 standard errors (whitened check)."""
    n, d = samples.shape
    chol = np.linalg.cholesky(expected)
    white = np.linalg.solve(chol, samples.T).T
    cov = np.cov(white, rowvar=False)
    tol = 5.0 * np.sqrt(2.0 / n)
    assert np.all(np.abs(np.diag(cov) - 1.0) < tol), np.diag(cov)
    off = cov[~np.eye(d, dtype=bool)]
    assert np.all(np.abs(off) < 5.0 / np.sqrt(n)), off
    assert np.all(np.abs(white.mean(axis=0)) < 5.0 / np.sqrt(n)), white.mean(axis=0)


def test_simulator_odometry_noise_has_configured_covariance(paper: Scenario, residuals) -> None:
    samples = residuals["odometry"]
    assert len(samples) == len(SEEDS) * 3 * paper.steps
    _assert_covariance(samples, paper.odometry_noise.cov)


def test_simulator_geometric_noise_has_configured_covariance(paper: Scenario, residuals) -> None:
    assert len(residuals["geometric"]) > 5000
    _assert_covariance(residuals["geometric"], paper.geometric_noise.cov)


def test_simulator_semantic_noise_has_model_covariance(residuals) -> None:
    _assert_covariance(residuals["semantic"], np.eye(2))


def test_covariance_check_rejects_wrong_noise(paper: Scenario, residuals) -> None:
    with pytest.raises(AssertionError):
        _assert_covariance(residuals["odometry"], 1.2 * paper.odometry_noise.cov)


def _frame_arrays(f: SensorFrame) -> list[np.ndarray]:
    out = [f.odometry, f.true_pose]
    for d in f.detections:
        out += [np.array([d.object_id]), d.z_geo, d.z_sem]
    return out


def _assert_identical(a: SensorFrame, b: SensorFrame) -> None:
    assert (a.robot, a.k, len(a.detections)) == (b.robot, b.k, len(b.detections))
    for x, y in zip(_frame_arrays(a), _frame_arrays(b), strict=True):
        assert x.tobytes() == y.tobytes()


def test_simulator_frames_bit_identical_in_any_generation_order(paper: Scenario) -> None:
    forward = Simulator(paper, 123).all_frames()
    keys = [(r, k) for r in paper.robot_ids for k in range(1, paper.steps + 1)]
    random.Random(7).shuffle(keys)
    shuffled_sim = Simulator(paper, 123)
    for rid, k in keys:
        _assert_identical(shuffled_sim.frame(rid, k), forward[rid][k - 1])


def test_simulator_noise_independent_of_other_robots(paper: Scenario) -> None:
    alone = dataclasses.replace(paper, robots=paper.robots[2:])
    for k in (1, 20, 60):
        _assert_identical(Simulator(alone, 5).frame("r3", k), Simulator(paper, 5).frame("r3", k))


def test_simulator_seeds_give_different_noise(paper: Scenario) -> None:
    a, b = Simulator(paper, 1).frame("r1", 10), Simulator(paper, 2).frame("r1", 10)
    assert not np.array_equal(a.odometry, b.odometry)


def test_simulator_detections_match_visibility(paper: Scenario) -> None:
    sim = Simulator(paper, 0)
    for rid in paper.robot_ids:
        for f in sim.frames(rid):
            assert [d.object_id for d in f.detections] == sim.world.visible_objects(rid, f.k)
            assert_close(f.true_pose, sim.world.trajectories[rid][f.k])


def test_simulator_rejects_bad_step_and_seed(paper: Scenario) -> None:
    sim = Simulator(paper, 0)
    with pytest.raises(ValueError, match="step 0"):
        sim.frame("r1", 0)
    with pytest.raises(ValueError, match="step 61"):
        sim.frame("r1", 61)
    for bad in (-1, 2**63, 1.5, True):
        with pytest.raises(ValueError, match="seed"):
            check_seed(bad)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- the detector


def test_detector_default_draws_nothing_more(paper: Scenario) -> None:
    """``--ids global`` without clutter or misses: the frames of before, to the bit."""
    before = Simulator(paper, 8)
    after = Simulator(paper, 8, detector=Detector())
    for rid in paper.robot_ids:
        for k in (1, 30, 60):
            frame, labels = after.labelled_frame(rid, k)
            _assert_identical(frame, before.frame(rid, k))
            assert frame.ids == "global"
            assert labels == tuple(d.object_id for d in frame.detections)


@pytest.mark.parametrize("ids", ["none", "local"])
def test_detector_drops_ids_and_keeps_the_truth_beside_the_frame(paper: Scenario, ids: str) -> None:
    given = Simulator(paper, 4)
    sim = Simulator(paper, 4, detector=Detector(ids, clutter=0.3, miss=0.2))
    trackers: dict[str, dict[int, int]] = {r: {} for r in paper.robot_ids}
    for rid in paper.robot_ids:
        for k in range(1, paper.steps + 1):
            frame, labels = sim.labelled_frame(rid, k)
            truth = {d.object_id: d for d in given.frame(rid, k).detections}
            assert frame.ids == ids and len(labels) == len(frame.detections)
            for d, label in zip(frame.detections, labels, strict=True):
                if ids == "none":
                    assert d.object_id == NO_ID
                elif label != CLUTTER:  # one tracker id per object and robot, not its own
                    assert trackers[rid].setdefault(label, d.object_id) == d.object_id
                    assert d.object_id != label
                if label != CLUTTER:  # a true detection keeps its noise, to the bit
                    assert d.z_geo.tobytes() == truth[label].z_geo.tobytes()
                    assert d.z_sem.tobytes() == truth[label].z_sem.tobytes()
    if ids == "local":
        shared = set(trackers["r1"]) & set(trackers["r2"])
        assert shared and all(trackers["r1"][j] != trackers["r2"][j] for j in shared)


def test_detector_is_seeded_and_order_free(paper: Scenario) -> None:
    detector = Detector("none", clutter=0.5, miss=0.1)
    forward = {r: Simulator(paper, 6, detector=detector).labels(r) for r in paper.robot_ids}
    sim = Simulator(paper, 6, detector=detector)
    for rid, k in [("r3", 40), ("r1", 12), ("r2", 55), ("r1", 11)]:
        frame, labels = sim.labelled_frame(rid, k)
        again, _ = Simulator(paper, 6, detector=detector).labelled_frame(rid, k)
        _assert_identical(frame, again)
        assert labels == forward[rid][k - 1]
    other = Simulator(paper, 7, detector=detector)
    assert any(other.labels(r) != forward[r] for r in paper.robot_ids)


def test_detector_miss_and_clutter_rates_are_as_configured(paper: Scenario) -> None:
    """Misses: a binomial share P; clutter: a Poisson count with mean R × the kept detections."""
    miss, clutter = 0.2, 0.4
    seen = kept = false = 0
    for seed in range(8):
        given = Simulator(paper, seed)
        sim = Simulator(paper, seed, detector=Detector("none", clutter, miss))
        for rid in paper.robot_ids:
            for k in range(1, paper.steps + 1):
                labels = sim.labelled_frame(rid, k)[1]
                seen += len(given.frame(rid, k).detections)
                true = sum(label != CLUTTER for label in labels)
                kept += true
                false += len(labels) - true
    share = 1 - kept / seen
    assert abs(share - miss) < 3.5 * np.sqrt(miss * (1 - miss) / seen), (share, seen)
    assert abs(false - clutter * kept) < 3.5 * np.sqrt(clutter * kept), (false, kept)


def test_detector_clutter_lies_in_the_sensor_field(paper: Scenario) -> None:
    sim = Simulator(paper, 2, detector=Detector("none", clutter=1.0))
    count = 0
    for rid in paper.robot_ids:
        sensor = paper.robot(rid).sensor
        for k in range(1, paper.steps + 1):
            frame, labels = sim.labelled_frame(rid, k)
            for d, label in zip(frame.detections, labels, strict=True):
                if label == CLUTTER:
                    count += 1
                    assert np.hypot(d.z_geo[0], d.z_geo[1]) <= sensor.range
                    assert abs(np.arctan2(d.z_geo[1], d.z_geo[0])) <= sensor.half_angle + 1e-12
    assert count > 50


def test_detector_refuses_bad_settings() -> None:
    with pytest.raises(ValueError, match="id kind 'tracker'"):
        Detector("tracker")
    with pytest.raises(ValueError, match="miss must be"):
        Detector(miss=1.0)
    with pytest.raises(ValueError, match="clutter must be"):
        Detector(clutter=-0.1)
