"""`semfleet dataset mrclam DIR -o OUT` as a user runs it (issue 44, item 2): on a synthetic
five-robot dataset (tests/sim/test_mrclam.py), its folder and its .tar.xz archive; the scenario it
writes goes through `scenario show`, `study` and `scenario frames` as it is; a folder that is not
a dataset gets one line naming the file; OUT is not written over without --force."""

from __future__ import annotations

import json
import tarfile
from pathlib import Path

import numpy as np

from deploy.launch.run import LaunchPlan
from sim.loader import load_scenario
from tests.deploy.test_cli import semfleet
from tests.sim.test_mrclam import _rows, _write_noisy

ARGS = ("--rate", "4", "--calibrate", "2")


def _dataset(tmp_path: Path) -> Path:
    rows = {name: [list(r) for r in table] for name, table in _rows().items()}
    return _write_noisy(tmp_path / "MRCLAM_Dataset0", rows, np.random.default_rng(3), 0.05, 0.02)


def test_a_dataset_becomes_a_scenario_that_study_runs_as_it_is(tmp_path: Path) -> None:
    folder = _dataset(tmp_path)
    r = semfleet("dataset", "mrclam", str(folder), "-o", "out", *ARGS, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "wrote out/scenario.toml and out/recording.npz" in r.stdout
    assert "set aside" in r.stdout and "robot sightings" in r.stdout
    scenario = load_scenario(tmp_path / "out" / "scenario.toml")
    assert scenario.recording is not None and len(scenario.robots) == 5
    shown = semfleet("scenario", "show", "out/scenario.toml", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    study = semfleet(
        "study",
        "--scenario",
        "out/scenario.toml",
        "--runs",
        "2",
        "--methods",
        "local,distributed,centralized",
        "--out",
        "study",
        cwd=tmp_path,
    )
    assert study.returncode == 0, study.stderr
    results = json.loads((tmp_path / "study" / "results.json").read_text())
    assert results["steps"] == scenario.steps
    # Each run draws the classes (class_seed): runs 0 and 1 differ, and each is scored against
    # its own (against run 0's, run 1's class log-loss would end near the log-loss of a swap).
    assert scenario.for_run(0).object_classes().tolist() != (
        scenario.for_run(1).object_classes().tolist()
    )
    loss = np.load(tmp_path / "study" / "results.npz")["centralized/class_log_loss"]
    assert np.all(loss[:, :, -1] < 0.3), loss[:, :, -1]
    # the five estimated trajectories against Vicon, one panel per method
    assert (tmp_path / "study" / "trajectories.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    tum = semfleet("export", "tum", "study", "-o", "tum", cwd=tmp_path)
    assert tum.returncode == 0, tum.stderr
    assert (tmp_path / "tum" / "seed-0" / "r5_distributed.tum").exists()
    frames = tmp_path / "r2.jsonl"
    f = semfleet(
        "scenario",
        "frames",
        "out/scenario.toml",
        "--robot",
        "r2",
        "--seed",
        "1",
        "-o",
        str(frames),
        cwd=tmp_path,
    )
    assert f.returncode == 0, f.stderr
    assert frames.read_text().count("\n") == 1 + scenario.steps  # the header, then the frames


def test_the_archive_as_shipped_gives_the_same_scenario(tmp_path: Path) -> None:
    folder = _dataset(tmp_path)
    archive = tmp_path / "MRCLAM_Dataset0.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(folder, arcname=folder.name)
    a = semfleet("dataset", "mrclam", str(folder), "-o", "a", *ARGS, cwd=tmp_path)
    b = semfleet("dataset", "mrclam", str(archive), "-o", "b", *ARGS, cwd=tmp_path)
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    assert (tmp_path / "a" / "recording.npz").read_bytes() == (
        tmp_path / "b" / "recording.npz"
    ).read_bytes()
    body = [(tmp_path / d / "scenario.toml").read_text().split("\nformat = 1\n")[1] for d in "ab"]
    assert body[0] == body[1]


def test_what_is_not_a_dataset_gets_one_line_and_out_is_not_written_over(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    r = semfleet("dataset", "mrclam", str(empty), "-o", "out", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "Barcodes.dat" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()
    folder = _dataset(tmp_path)
    assert (
        semfleet("dataset", "mrclam", str(folder), "-o", "out", *ARGS, cwd=tmp_path).returncode == 0
    )
    again = semfleet("dataset", "mrclam", str(folder), "-o", "out", *ARGS, cwd=tmp_path)
    assert again.returncode == 2 and "--force" in again.stderr
    forced = semfleet("dataset", "mrclam", str(folder), "-o", "out", *ARGS, "--force", cwd=tmp_path)
    assert forced.returncode == 0, forced.stderr
    bad = semfleet("dataset", "mrclam", str(folder), "-o", "x", "--rate", "0", cwd=tmp_path)
    assert bad.returncode == 2 and "--rate 0.0" in bad.stderr


def test_launch_runs_five_agent_processes_on_the_recorded_run(tmp_path: Path) -> None:
    """Real OS processes over Zenoh on loopback, each agent fed the recorded frames."""
    folder = _dataset(tmp_path)
    assert (
        semfleet("dataset", "mrclam", str(folder), "-o", "out", *ARGS, cwd=tmp_path).returncode == 0
    )
    r = semfleet(
        "launch", "--scenario", "out/scenario.toml", "--steps", "6", "--out", "run", cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    assert "launch" in results and set(results["robots"]) == {"r1", "r2", "r3", "r4", "r5"}


def test_a_launch_simulates_and_scores_the_world_of_its_seed(tmp_path: Path) -> None:
    """With a class_seed, the conductor's world (frames and scoring) holds the classes of the
    launch's --seed, as a study's run of that seed does."""
    folder = _dataset(tmp_path)
    assert (
        semfleet("dataset", "mrclam", str(folder), "-o", "out", *ARGS, cwd=tmp_path).returncode == 0
    )
    scenario = load_scenario(tmp_path / "out" / "scenario.toml")
    plan = LaunchPlan(scenario, 3, list(scenario.robot_ids), tmp_path / "run")
    assert plan.scenario.object_classes().tolist() == (
        scenario.for_run(3).object_classes().tolist()
    )
    assert plan.scenario.object_classes().tolist() != scenario.object_classes().tolist()
