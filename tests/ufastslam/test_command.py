"""`semfleet ufastslam` and its study (deploy.study.ufastslam): the table, results.json /
results.npz, plots and user errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.cli.main import main
from deploy.study.ufastslam import (
    METHODS,
    SeedRun,
    filter_config,
    relation_is_true,
    run_all,
    run_filter,
    run_seed,
    ufastslam_archive,
)
from estimator.ufastslam import AcceptedRelation
from sim.ufastslam import UWorld, parse_world, simulate
from tests.tolerance import assert_close

SEMFLEET = Path(sys.executable).with_name("semfleet")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SCHEMA_METHODS = {"odometry", "ufastslam", "semantic_ufastslam"}
SCHEMA_METRICS = {"pose_rmse", "landmark_rmse", "final_error", "step_ms"}

# A short corridor: 8 m north past wall landmarks sharing x, a turn, 3 m east.
WORLD = """\
format = 1
kind = "ufastslam"
name = "corridor"
dt = 0.5
landmarks = [
  [1, -1.5, 2.0], [2, -1.5, 4.0], [3, -1.5, 6.0], [4, -1.5, 8.0], [5, -1.5, 10.0],
  [6, 1.5, 3.0], [7, 1.5, 5.0], [8, 1.5, 7.0], [9, 1.5, 9.0], [10, 3.0, 10.5], [11, 5.0, 10.5],
]

[path]
start = [0.0, 0.0, 1.5707963267948966]
speed = 0.4
turn_rate_deg = 30.0
legs = [{ forward = 8.0 }, { turn_deg = -90.0 }, { forward = 3.0 }]

[odometry]
speed_std = 0.02
yaw_rate_std_deg = 0.5
scale_error = 0.03
yaw_rate_bias_deg = 0.3

[sensor]
half_angle_deg = 35.0
range = 6.0
range_std = 0.15
bearing_std_deg = 2.0

[filter]
speed_std = 0.04
yaw_rate_std_deg = 1.5

[[groups]]
kind = "x"
name = "west"
members = [1, 2, 3, 4, 5]

[[groups]]
kind = "x"
name = "east"
members = [6, 7, 8, 9]

[[groups]]
kind = "y"
name = "north"
members = [10, 11]
"""


def semfleet(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SEMFLEET), *args],
        capture_output=True,
        text=True,
        timeout=300,  # a guard against hangs, not a speed check
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )


def read_json(out: Path) -> dict[str, Any]:
    def reject(token: str) -> float:
        raise ValueError(f"non-standard JSON constant {token}")

    doc: dict[str, Any] = json.loads(
        (out / "results.json").read_text(encoding="utf-8"), parse_constant=reject
    )
    return doc


def read_npz(out: Path) -> dict[str, np.ndarray]:
    with np.load(out / "results.npz") as npz:
        return {k: npz[k] for k in npz.files}


@pytest.fixture(scope="module")
def world_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("world") / "corridor.toml"
    path.write_text(WORLD, encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def two_runs(
    world_file: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[subprocess.CompletedProcess[str], Path]:
    """Seeds 3 and 4 in two spawned processes, as a real process."""
    out = tmp_path_factory.mktemp("uf") / "out"
    args = ("--particles", "12", "--runs", "2", "--jobs", "2", "--seed", "3")
    r = semfleet("ufastslam", "--scenario", str(world_file), *args, "--out", str(out))
    assert r.returncode == 0, (r.stdout, r.stderr)
    return r, out


def test_command_prints_the_table(two_runs: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    out = two_runs[0].stdout
    for text in (
        "corridor: 2 runs, 12 particles, mean over runs (metres)",
        "dead reckoning",
        "UFastSLAM",
        "Semantic UFastSLAM",
        "(threshold)",
        "(oracle)",
        "pose",
        "landmark",
        "final",
        "RMSE",
        "error",
        "relations",
        "true / false",
        "ms per",
        "has a lower pose RMSE than UFastSLAM on",
        "pose NEES (3 dof",
    ):
        assert text in out, text
    # Progress on a pipe, as each run ends (it printed nothing for 17 s of 20 runs), before the
    # table.
    lines = out.splitlines()
    said = [i for i, line in enumerate(lines) if line.startswith("runs: ")]
    assert [lines[i].split(",")[0] for i in said] == ["runs: 1 of 2 done", "runs: 2 of 2 done"]
    assert said[-1] < next(i for i, line in enumerate(lines) if "dead reckoning" in line)


def test_results_json_schema(two_runs: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    doc = read_json(two_runs[1])
    assert doc["format"] == 2 and doc["study"] == "ufastslam"
    assert doc["scenario"] == "corridor"
    assert doc["runs"] == 2 and doc["seeds"] == [3, 4]
    assert (doc["steps"], doc["particles"]) == (parse_world(WORLD).steps, 12)
    assert set(doc["methods"]) == SCHEMA_METHODS
    for entry in doc["methods"].values():
        assert set(entry) >= SCHEMA_METRICS
        assert all(isinstance(entry[m], float) and entry[m] >= 0 for m in SCHEMA_METRICS)
    semantic = doc["methods"]["semantic_ufastslam"]
    assert semantic["relations"] == "oracle"  # the default source
    assert semantic["relations_false"] == 0.0 and semantic["relations_true"] > 0
    assert set(doc["table"]) == set(METHODS)
    # the filters' pose NEES is reported (RBPF SLAM is overconfident: it is rarely near 3)
    assert "pose_nees" not in doc["methods"]["odometry"]
    for method in ("ufastslam", "semantic_threshold", "semantic_oracle"):
        assert doc["table"][method]["pose_nees"] > 0
        assert 0 <= doc["table"][method]["nees_over_bound"] <= 1


def test_results_npz_holds_the_per_run_values(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    doc, arrays = read_json(two_runs[1]), read_npz(two_runs[1])
    steps = parse_world(WORLD).steps
    np.testing.assert_array_equal(arrays["seeds"], [3, 4])
    assert arrays["truth"].shape == (steps + 1, 3)
    for method in SCHEMA_METHODS:
        for metric in SCHEMA_METRICS:
            values = arrays[f"{method}/{metric}"]
            assert values.shape == (2,)
            assert_close(values.mean(), doc["methods"][method][metric], rtol=1e-12)
        assert arrays[f"{method}/path"].shape == (2, steps + 1, 3)
        assert (f"{method}/pose_nees" in arrays) == (method != "odometry")
        assert (f"{method}/nees_over_bound" in arrays) == (method != "odometry")
        assert arrays[f"{method}/position_error"].shape == (2, steps + 1)
    np.testing.assert_array_equal(
        arrays["semantic_ufastslam/pose_rmse"], arrays["semantic_oracle/pose_rmse"]
    )


def test_plots_are_written(two_runs: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    out = two_runs[1]
    for name in ("paths_seed3.png", "position_error.png", "pose_rmse_per_run.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC, name


def test_jobs_do_not_change_results(
    world_file: Path, tmp_path: Path, two_runs: tuple[subprocess.CompletedProcess[str], Path]
) -> None:
    out = tmp_path / "serial"
    args = ("--particles", "12", "--runs", "2", "--jobs", "1", "--seed", "3", "--out", str(out))
    r = semfleet("ufastslam", "--scenario", str(world_file), *args)
    assert r.returncode == 0, r.stderr
    serial, parallel = read_npz(out), read_npz(two_runs[1])
    assert set(serial) == set(parallel)
    for key in serial:
        if not key.endswith("step_ms"):
            np.testing.assert_array_equal(serial[key], parallel[key], err_msg=key)


@pytest.fixture(scope="module")
def corridor_runs() -> list[SeedRun]:
    """Seeds 3 and 4 with 10 particles, in this process."""
    return run_all(parse_world(WORLD), [3, 4], 10, jobs=1)


def test_a_run_depends_on_its_seed_only(corridor_runs: list[SeedRun]) -> None:
    world = parse_world(WORLD)
    both = corridor_runs
    alone = run_seed(world, 4, 10)
    for method in METHODS:
        np.testing.assert_array_equal(both[1].methods[method].path, alone.methods[method].path)
    assert not np.array_equal(both[0].methods["ufastslam"].path, alone.methods["ufastslam"].path)


@pytest.mark.parametrize("relations", ["threshold", "oracle"])
def test_archive_semantic_ufastslam_is_the_chosen_variant(
    corridor_runs: list[SeedRun], relations: str
) -> None:
    world = parse_world(WORLD)
    archive = ufastslam_archive(world, corridor_runs, 10, relations)
    chosen = f"semantic_{relations}"
    doc = archive.document()
    semantic = doc["methods"]["semantic_ufastslam"]
    assert semantic["relations"] == relations
    for key in ("pose_rmse", "relations_true", "pose_nees", "nees_over_bound"):
        values = [getattr(r.methods[chosen], key) for r in corridor_runs]
        assert semantic[key] == doc["table"][chosen][key] == float(np.mean(values)), key
    wins = [r.methods[chosen].pose_rmse < r.methods["ufastslam"].pose_rmse for r in corridor_runs]
    assert doc["semantic_beats_ufastslam"] == sum(wins)
    paths = np.stack([r.methods[chosen].path for r in corridor_runs])
    np.testing.assert_array_equal(archive.arrays["semantic_ufastslam/path"], paths)
    errors = np.linalg.norm(paths[..., :2] - corridor_runs[0].truth[:, :2], axis=-1)
    np.testing.assert_array_equal(archive.arrays["semantic_ufastslam/position_error"], errors)
    assert (doc["study"], doc["seeds"], doc["particles"]) == ("ufastslam", [3, 4], 10)


def test_archive_with_relations_off_counts_no_wins(corridor_runs: list[SeedRun]) -> None:
    doc = ufastslam_archive(parse_world(WORLD), corridor_runs, 10, "off").document()
    plain = doc["methods"]["ufastslam"]
    assert doc["methods"]["semantic_ufastslam"] == {
        **plain,
        "relations_true": 0.0,
        "relations_false": 0.0,
        "relations": "off",
    }
    assert doc["semantic_beats_ufastslam"] == 0


def test_relations_off_is_plain_ufastslam(world_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "off"
    args = ["--particles", "8", "--runs", "1", "--relations", "off", "--out", str(out)]
    assert main(["ufastslam", "--scenario", str(world_file), *args]) == 0
    doc = read_json(out)
    semantic, plain = doc["methods"]["semantic_ufastslam"], doc["methods"]["ufastslam"]
    assert semantic["relations"] == "off"
    for metric in SCHEMA_METRICS:
        assert semantic[metric] == plain[metric]


def test_semantic_with_relations_off_runs_the_same_filter() -> None:
    """The summary's shortcut for --relations off is what running the filter would give."""
    world = parse_world(WORLD)
    run = simulate(world, 5)
    plain = run_seed(world, 5, 8).methods["ufastslam"]
    again = run_filter(world, run, filter_config(world, 8, "off"))
    np.testing.assert_array_equal(plain.path, again.path)


def test_filter_nees_is_the_median_and_the_share_above_the_chi2_bound(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # χ²₃ 99 % is 11.34487: a NEES of 11.34495 is above it (and below the rounded 11.345)
    import deploy.study.ufastslam as study

    world = parse_world(WORLD)
    values = [*[1.0, 11.34495] * (world.steps // 2), 20.0, 30.0][: world.steps]
    stream = iter(values)
    monkeypatch.setattr(study, "world_pose_nees", lambda mean, cov, truth: next(stream))
    result = run_filter(world, simulate(world, 0), filter_config(world, 4, "off"))
    above = sum(v > 11.3449 for v in values)
    assert above == (world.steps + 1) // 2
    assert result.nees_over_bound == above / world.steps
    assert result.pose_nees == float(np.median(values))


def once_relations(world: UWorld) -> int:
    """What ONCE mode must apply with true labels: at a landmark's first sighting, one relation
    per group of it that has a member seen at an earlier step."""
    first: dict[int, int] = {}
    for k in range(1, world.steps + 1):
        for j in world.visible(k)[0]:
            first.setdefault(world.landmark_ids[j], k)
    count = 0
    for lid, k in first.items():
        for g in world.groups:
            if lid in g.members and any(first.get(m, k) < k for m in g.members):
                count += 1
    return count


def test_relations_are_judged_against_the_truth() -> None:
    world = parse_world(WORLD)
    result = run_seed(world, 0, 20)
    oracle = result.methods["semantic_oracle"]
    assert oracle.relations_false == 0
    assert oracle.relations_true == once_relations(world) == 5
    threshold = result.methods["semantic_threshold"]
    assert threshold.relations_true + threshold.relations_false > 0


def test_relation_truth_judge() -> None:
    world = parse_world(WORLD)
    assert relation_is_true(world, AcceptedRelation("x", "x:west", 3, (2,)))
    assert relation_is_true(world, AcceptedRelation("y", "y:north", 11, (10,)))
    assert not relation_is_true(world, AcceptedRelation("x", "x#0", 6, (2,)))  # 3 m apart
    assert not relation_is_true(world, AcceptedRelation("col", "col#1", 10, (2, 7)))
    assert relation_is_true(world, AcceptedRelation("col", "col#2", 4, (2, 3)))


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--scenario", "nonesuch"], "nonesuch: not a file and not a bundled world"),
        (["--scenario", "missing.toml"], "missing.toml: no such world file"),
        (
            ["--scenario", "rectangle", "--particles", "0"],
            "--particles: 0 must be a positive integer",
        ),
        (["--scenario", "rectangle", "--runs", "many"], "--runs: 'many' is not an integer"),
        (["--scenario", "rectangle", "--jobs", "-2"], "--jobs: -2 must be a positive integer"),
        (["--scenario", "rectangle", "--seed", "-1"], "seeds are non-negative integers"),
        (
            ["--scenario", "rectangle", "--relations", "magic"],
            "--relations: invalid choice: 'magic'",
        ),
    ],
)
def test_user_errors_are_one_clear_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], fragment: str
) -> None:
    out = tmp_path / "out"
    try:
        code = main(["ufastslam", "--runs", "1", "--out", str(out), *args])
    except SystemExit as exc:  # argparse's own errors
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    assert err.count("\n") == 1 and "error: " in err, err  # argparse's errors too: one line
    assert fragment in err
    assert not out.exists()


def test_bad_world_field_is_one_line_from_a_real_process(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(WORLD.replace("members = [10, 11]", "members = [10, 12]"), encoding="utf-8")
    r = semfleet("ufastslam", "--scenario", str(bad), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert r.stderr.strip() == f"semfleet: error: {bad}: groups[2].members[1]: unknown landmark 12"
