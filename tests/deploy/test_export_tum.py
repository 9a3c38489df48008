"""`semfleet export tum` (issue 15, item 3): the truth and every method's estimate of every
robot's pose, per run, as TUM files; runs and launches record those poses."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from deploy.cli.main import main
from deploy.launch.scoring import Scorer
from deploy.study.archive import study_archive, write_archive
from deploy.study.runner import run_single
from deploy.study.tum import tum_lines
from deploy.study.types import RunResult
from estimator.hybrid import BeliefConfig
from sim.loader import parse_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.scenarios import fleet_text
from tests.tolerance import assert_close

SEMFLEET = Path(sys.executable).with_name("semfleet")
STEPS = 8
SEED = 3
METHODS = ["local", "distributed"]


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    objects = [(3.0, 0.5, math.pi / 2, 1), (3.5, -0.5, 0.0, 2), (3.0, 4.5, 0.0, 2)]
    return parse_scenario(fleet_text("pair", STEPS, [0.0, 4.0], objects), "pair.toml")


@pytest.fixture(scope="module")
def run(scenario: Scenario) -> RunResult:
    """One run, with the belief snapshots of its last step."""
    return run_single(scenario, METHODS, SEED, BeliefConfig(), snapshot_step=STEPS)


@pytest.fixture(scope="module")
def results(run: RunResult, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("results")
    write_archive(out, study_archive("pair", [run], METHODS, {"communication": "range"}))
    return out


def weighted_mean_pose(run: RunResult, method: str, robot: str) -> np.ndarray:
    snap = run.snapshots[method][robot]
    w, poses = snap.weights, snap.robot_pose
    theta = math.atan2(float(w @ np.sin(poses[:, 2])), float(w @ np.cos(poses[:, 2])))
    return np.array([w @ poses[:, 0], w @ poses[:, 1], theta])


def test_runs_record_the_weighted_mean_pose_and_the_truth(
    run: RunResult, scenario: Scenario
) -> None:
    frames = Simulator(scenario, SEED).all_frames()
    for method in METHODS:
        poses, truth = run.metrics[method]["robot_pose"], run.metrics[method]["true_robot_pose"]
        assert poses.shape == truth.shape == (2, STEPS, 3) and np.all(np.isfinite(poses))
        for i, robot in enumerate(scenario.robot_ids):
            want = [f.true_pose for f in frames[robot]]
            np.testing.assert_array_equal(truth[i], want, err_msg=robot)
            assert_close(poses[i, -1], weighted_mean_pose(run, method, robot), what=robot)
    # D has fused r2's data by the end: its estimate differs from L's.
    assert not np.array_equal(
        run.metrics["local"]["robot_pose"], run.metrics["distributed"]["robot_pose"]
    )


def test_launch_scoring_records_poses_per_robot_row(run: RunResult, scenario: Scenario) -> None:
    # A launch scores what its agents publish, in its own robot order: r2's snapshot goes to
    # row 0, the truth of every step is there before any estimate, a missing step stays NaN.
    frames = Simulator(scenario, SEED).all_frames()
    scorer = Scorer(scenario, frames, ["r2", "r1"])
    scorer.record("distributed", "r2", STEPS, run.snapshots["distributed"]["r2"])
    track = scorer.metrics["distributed"]
    assert_close(track["robot_pose"][0, -1], run.metrics["distributed"]["robot_pose"][1, -1])
    assert np.all(np.isnan(track["robot_pose"][0, :-1])) and np.all(
        np.isnan(track["robot_pose"][1])
    )
    np.testing.assert_array_equal(track["true_robot_pose"][0], [f.true_pose for f in frames["r2"]])
    np.testing.assert_array_equal(track["true_robot_pose"][1], [f.true_pose for f in frames["r1"]])


def test_tum_lines_are_yaw_quaternions_at_step_times_without_missing_steps() -> None:
    poses = np.array([[1.0, 2.0, math.pi / 2], [np.nan] * 3, [0.5, -1.0, -math.pi]])
    lines = [[float(v) for v in line.split()] for line in tum_lines(poses, 0.25)]
    assert len(lines) == 2
    assert_close(lines[0], [0.25, 1, 2, 0, 0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    assert_close(lines[1], [0.75, 0.5, -1, 0, 0, 0, -1, 0], atol=1e-15)


def test_export_tum_writes_truth_l_and_d_of_every_robot(
    results: Path, run: RunResult, tmp_path: Path
) -> None:
    env = {**os.environ, "COLUMNS": "120"}
    out = tmp_path / "tum"
    r = subprocess.run(
        [str(SEMFLEET), "export", "tum", str(results), "-o", str(out), "--period", "0.5"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert r.returncode == 0, (r.stdout, r.stderr)
    folder = out / f"seed-{SEED}"
    names = {f"{robot}_{s}.tum" for robot in ("r1", "r2") for s in ("truth", *METHODS)}
    assert {p.name for p in folder.iterdir()} == names
    assert f"evo_ape tum {folder / 'r1_truth.tum'} {folder / 'r1_distributed.tum'}" in r.stdout
    table = [line.split() for line in r.stdout.splitlines()]
    for i, robot in enumerate(("r1", "r2")):
        truth = np.loadtxt(folder / f"{robot}_truth.tum")
        for source in ("truth", *METHODS):
            rows = np.loadtxt(folder / f"{robot}_{source}.tum")
            key = "true_robot_pose" if source == "truth" else "robot_pose"
            poses = run.metrics[METHODS[0] if source == "truth" else source][key][i]
            assert rows.shape == (STEPS, 8), source
            assert_close(rows[:, 0], 0.5 * np.arange(1, STEPS + 1), what="timestamps")
            np.testing.assert_array_equal(rows[:, 1:3], poses[:, :2], err_msg=source)
            assert np.all(rows[:, 3:6] == 0), source
            assert_close(np.arctan2(rows[:, 6], rows[:, 7]) * 2, poses[:, 2], what=source)
            if source != "truth":
                rmse = math.sqrt(np.mean(np.sum((rows[:, 1:3] - truth[:, 1:3]) ** 2, axis=1)))
                assert [str(SEED), robot, source, str(STEPS), f"{rmse:.4f}"] in table, rmse


def test_export_tum_refuses_results_without_trajectories(
    results: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old = tmp_path / "old"
    old.mkdir()
    (old / "results.json").write_bytes((results / "results.json").read_bytes())
    with np.load(results / "results.npz") as npz:
        kept = {k: npz[k] for k in npz.files if not k.endswith("robot_pose")}
    np.savez(old / "results.npz", **kept)
    assert main(["export", "tum", str(old), "-o", str(tmp_path / "tum")]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"semfleet: error: {old}/results.npz holds no trajectories: it was written before runs "
        "recorded them (issue 15); run the study or launch again\n"
    )
    assert main(["export", "tum", str(tmp_path / "none"), "-o", str(tmp_path / "tum")]) == 2
    assert "results.json: No such file or directory" in capsys.readouterr().err


def test_export_tum_refuses_a_folder_that_is_not_empty_unless_force(
    results: Path, tmp_path: Path
) -> None:
    out = tmp_path / "tum"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")

    def export(*extra: str) -> subprocess.CompletedProcess[str]:
        argv = [str(SEMFLEET), "export", "tum", str(results), "-o", str(out), *extra]
        return subprocess.run(argv, capture_output=True, text=True, timeout=120)

    r = export()
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stderr == (
        f"semfleet: error: --out {out}: exists and is not empty (--force writes over the outputs "
        "in it)\n"
    )
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    r = export("--force")
    assert r.returncode == 0, r.stderr
    assert (out / "notes.txt").read_text() == "mine\n"  # other files stay
    assert (out / f"seed-{SEED}" / "r1_truth.tum").is_file()
