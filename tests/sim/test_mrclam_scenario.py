"""An MRCLAM dataset as a scenario with a recorded run (``sim.mrclam_scenario``,
``sim.recording``; issue 44 item 2), on the synthetic five-robot dataset of test_mrclam: the
recording holds what the robots measured and nothing else enters a frame; the ground truth is
Vicon's at the steps; the scenario file names its recording by digest and reads back."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from deploy.base.build import belief_model
from estimator.models import viewpoint
from estimator.models.objects import POINT
from sim.generate import dump_scenario
from sim.loader import load_scenario, parse_scenario
from sim.mrclam import (
    MrclamDataset,
    landmark_steps,
    odometry_increments,
    read_mrclam,
    sightings,
    step_times,
    truth_at,
)
from sim.mrclam_scenario import mrclam_scenario, with_digest
from sim.recording import Recording, RecordingError, read_recording, recording_bytes, sha256_of
from sim.scenario import ScenarioError
from sim.sensors import Simulator
from tests.sim.test_mrclam import _rows, _write_noisy
from tests.tolerance import assert_close

RATE, CALIBRATE = 4.0, 2.0


@functools.cache
def _data(folder: str) -> MrclamDataset:
    rows = {name: [list(r) for r in table] for name, table in _rows().items()}
    return read_mrclam(_write_noisy(Path(folder), rows, np.random.default_rng(3), 0.05, 0.02))


def _written(tmp_path: Path, **kw: object) -> tuple[Path, MrclamDataset, Recording]:
    data = _data(str(tmp_path / "data"))
    out = tmp_path / "out"
    out.mkdir()
    scenario, rec, _ = mrclam_scenario(data, out / "recording.npz", RATE, CALIBRATE, **kw)  # type: ignore[arg-type]
    (out / "recording.npz").write_bytes(recording_bytes(rec))
    scenario = with_digest(scenario, sha256_of(out / "recording.npz"))
    (out / "scenario.toml").write_text(dump_scenario(scenario))
    return out / "scenario.toml", data, rec


def test_the_recording_is_the_robots_own_measurements_at_the_steps(tmp_path: Path) -> None:
    path, data, rec = _written(tmp_path)
    every = step_times(data, RATE)
    times = every[every >= every[0] + CALIBRATE]
    assert rec.steps == len(times) - 1 > 5
    assert_close(rec.times, times - times[0], atol=1e-9)
    for i, log in enumerate(data.robots):
        assert_close(rec.truth[i], truth_at(log, times), atol=1e-12, what="Vicon at the steps")
        assert_close(rec.odometry[i], odometry_increments(log, times), atol=1e-12)
        rows = landmark_steps(log, sightings(data, log).landmarks, times)
        mine = rec.det_robot == i
        # every kept detection is one of the robot's own sightings at its step, nearest t_k
        for k, j, (b, r) in zip(
            rec.det_step[mine], rec.det_object[mine], rec.det_z[mine], strict=True
        ):
            same = rows[(rows[:, 0] == k) & (rows[:, 1] == j)]
            nearest = same[np.argmin(same[:, 4])]
            assert r == pytest.approx(nearest[2]) and b == pytest.approx(nearest[3])
        assert len(set(zip(rows[:, 0], rows[:, 1], strict=True))) == mine.sum()
    s = load_scenario(path)
    assert s.recording is not None and s.sensor.objects == "point"
    assert [r.id for r in s.robots] == ["r1", "r2", "r3", "r4", "r5"]
    assert_close(
        np.array([o.pose for o in s.objects])[:, :2], [data.landmarks[o.id] for o in s.objects]
    )


def test_frames_carry_the_recording_and_draw_only_the_scores(tmp_path: Path) -> None:
    path, _, rec = _written(tmp_path)
    s = load_scenario(path)
    model = s.classifier.build()
    truth = {o.id: np.array(o.pose[:2]) for o in s.objects}
    one, two = Simulator(s, 1), Simulator(s, 2)
    seen = 0
    for i, robot in enumerate(rec.robots):
        for k in range(1, rec.steps + 1):
            f, g = one.frame(robot, k), two.frame(robot, k)
            assert_close(f.odometry, rec.odometry[i, k - 1], atol=0)
            assert_close(f.true_pose, rec.truth[i, k], atol=0)
            ids, zs = rec.detections(i, k)
            assert [d.object_id for d in f.detections] == ids.tolist()
            for d, e, z in zip(f.detections, g.detections, zs, strict=True):
                seen += 1
                assert_close(d.z_geo, z, atol=0)
                assert not np.allclose(d.z_sem, e.z_sem)  # the scores are the run's, per seed
                world = one.scenario  # this run's classes (drawn per run)
                c = world.objects[[o.id for o in world.objects].index(d.object_id)].class_index
                psi = float(viewpoint(f.true_pose, POINT.as_pose(truth[d.object_id])))
                mean = model.mean(c, psi)
                white = np.linalg.solve(np.linalg.cholesky(model.cov(c, psi)), d.z_sem - mean)
                assert np.all(np.abs(white) < 6)
    assert seen > 20


def test_the_scenario_reads_back_and_a_changed_recording_is_refused_by_name(tmp_path: Path) -> None:
    path, _, _ = _written(tmp_path)
    s = load_scenario(path)
    again = parse_scenario(dump_scenario(s), str(path), folder=path.parent)
    assert again.recording == s.recording
    blob = path.parent / "recording.npz"
    blob.write_bytes(blob.read_bytes()[:-3] + b"abc")
    with pytest.raises(ScenarioError, match=r"recording\.file: .*sha256"):
        parse_scenario(path.read_text(), "changed.toml", folder=path.parent)
    with pytest.raises(RecordingError, match="sha256"):
        read_recording(blob, s.recording.sha256)  # type: ignore[union-attr]
    (path.parent / "recording.npz").unlink()
    with pytest.raises(ScenarioError, match=r"recording\.file: .*cannot read"):
        parse_scenario(path.read_text(), "gone.toml", folder=path.parent)


def test_a_recording_whose_arrays_do_not_fit_is_refused_naming_the_array() -> None:
    r = np.zeros((1, 3, 3))
    good = dict(
        robots=("r1",),
        times=np.arange(3.0),
        truth=r,
        odometry=np.zeros((1, 2, 3)),
        det_robot=np.array([0, 0]),
        det_step=np.array([1, 1]),
        det_object=np.array([7, 7]),
        det_z=np.array([[0.1, 1.0], [0.2, 1.0]]),
    )
    with pytest.raises(RecordingError, match="det_object: object 7 twice at step 1"):
        Recording(**good)  # type: ignore[arg-type]
    with pytest.raises(RecordingError, match="odometry: shape"):
        Recording(**{**good, "odometry": np.zeros((1, 3, 3)), "det_object": np.array([7, 8])})  # type: ignore[arg-type]
    with pytest.raises(RecordingError, match="det_z: a bearing or range"):
        Recording(
            **{**good, "det_object": np.array([7, 8]), "det_z": np.array([[0.1, -1.0], [0.2, 1.0]])}
        )  # type: ignore[arg-type]


def test_a_hostile_recording_file_is_refused_naming_it(tmp_path: Path) -> None:
    """Truncated bytes, a pickled array, NaN odometry, a missing array: each one line naming
    the file (and the array), never a crash or a pickle loaded."""
    _, _, rec = _written(tmp_path)
    good = recording_bytes(rec)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(good[: len(good) // 2])
    with pytest.raises(RecordingError, match=r"bad\.npz: not a recording"):
        read_recording(bad)
    arrays = {a: getattr(rec, a) for a in ("times", "truth", "odometry", "det_robot")}
    arrays |= {"det_step": rec.det_step, "det_object": rec.det_object, "det_z": rec.det_z}
    np.savez(bad, robots=np.array([object()] * len(rec.robots), dtype=object), **arrays)
    with pytest.raises(RecordingError, match=r"bad\.npz"):
        read_recording(bad)
    nan = rec.odometry.copy()
    nan[0, 0, 0] = np.nan
    np.savez(bad, robots=np.array(rec.robots), **{**arrays, "odometry": nan})
    with pytest.raises(RecordingError, match=r"bad\.npz: odometry: non-finite"):
        read_recording(bad)
    np.savez(bad, robots=np.array(rec.robots), **{k: v for k, v in arrays.items() if k != "det_z"})
    with pytest.raises(RecordingError, match="missing arrays det_z"):
        read_recording(bad)


def test_each_run_draws_the_landmarks_classes_from_the_prior(tmp_path: Path) -> None:
    """``class_seed``: run seed s draws every landmark's class (``Scenario.for_run``), so a
    study's seeds vary the assignment as well as the scores; the file lists no class, and the
    scenario as loaded holds run 0's draw. The simulator draws the scores from the run's
    classes, and the study scores against them."""
    path, _, _ = _written(tmp_path, seed=5)
    s = load_scenario(path)
    assert s.class_seed == 5 and "class =" not in path.read_text()
    assert s.for_run(0).object_classes().tolist() == s.object_classes().tolist()
    runs = [s.for_run(seed).object_classes() for seed in range(400)]
    assert len({tuple(c) for c in runs[:20]}) > 15  # assignments differ from run to run
    assert s.for_run(3).for_run(7) == s.for_run(3)  # a run's world keeps its classes
    counts = np.bincount(np.concatenate(runs), minlength=s.num_classes)
    expected = counts.sum() / s.num_classes  # the uniform prior
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < 13.8, counts  # χ²₂ at 0.001
    model = s.classifier.build()
    for seed in (1, 2, 3):
        sim = Simulator(s, seed)
        assert sim.scenario.object_classes().tolist() == runs[seed].tolist()
        truth = {o.id: (np.array(o.pose[:2]), o.class_index) for o in sim.scenario.objects}
        right = wrong = 0.0
        for robot in s.robot_ids:
            for f in sim.frames(robot):
                for d in f.detections:
                    xy, c = truth[d.object_id]
                    psi = float(viewpoint(f.true_pose, POINT.as_pose(xy)))
                    right += model.log_likelihood(d.z_sem, c, psi)
                    wrong += model.log_likelihood(d.z_sem, (c + 1) % s.num_classes, psi)
        assert right > wrong + 50  # the scores come from the run's classes


def test_a_class_seed_and_a_stated_class_are_refused_together(tmp_path: Path) -> None:
    path, _, _ = _written(tmp_path)
    text = path.read_text()
    stated = text.replace("pose = [", "class = 1\npose = [", 1)
    with pytest.raises(ScenarioError, match=r"objects\[0\]\.class: .*class_seed"):
        parse_scenario(stated, "stated.toml", folder=path.parent)
    without = "\n".join(line for line in text.splitlines() if not line.startswith("class_seed"))
    with pytest.raises(ScenarioError, match="class"):
        parse_scenario(without, "without.toml", folder=path.parent)


def test_the_scenario_weighs_sightings_by_huber_and_a_wrong_kernel_is_refused(
    tmp_path: Path,
) -> None:
    path, _, _ = _written(tmp_path)
    s = load_scenario(path)
    assert s.geometric_noise.kernel == "huber"
    assert belief_model(s).geometric_noise.kernel == "huber"  # what the estimators get
    again = parse_scenario(dump_scenario(s), str(path), folder=path.parent)
    assert again.geometric_noise == s.geometric_noise
    text = path.read_text().replace('geometric_kernel = "huber"', 'geometric_kernel = "cauchy"')
    with pytest.raises(ScenarioError, match=r"noise\.geometric_kernel: 'cauchy': expected one of"):
        parse_scenario(text, "bad.toml", folder=path.parent)
