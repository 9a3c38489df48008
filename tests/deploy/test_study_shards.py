"""`semfleet study --shard I/N`, `study merge` and `study --cluster` (issue 15, item 5): shards
merged and a study on a Dask cluster give the single local run's results, whatever wall clocks
say; merges of anything but every shard of one study are refused in one line."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.cli.main import main
from deploy.study.shards import Shard
from tests.estimator.scenarios import fleet_text

SEMFLEET = Path(sys.executable).with_name("semfleet")
STEPS = 8
# Three seeds in two shards: shard 0/2 runs seeds 5 and 7, shard 1/2 seed 6.
STUDY = ("--methods", "local,distributed", "--runs", "3", "--seed", "5", "--jobs", "1")
WALL_CLOCK = ("wall_s", "step_ms", "fusion_ms")


def semfleet(*args: str) -> subprocess.CompletedProcess[str]:
    # This process's environment: the numbers are compared with runs made in this process, and
    # OpenBLAS picks its kernels (and their last bits) from variables such as OPENBLAS_CORETYPE.
    env = {**os.environ, "MPLBACKEND": "Agg", "COLUMNS": "200"}
    return subprocess.run(
        [str(SEMFLEET), *args], capture_output=True, text=True, timeout=120, env=env
    )


def read(out: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    doc = json.loads((out / "results.json").read_text(encoding="utf-8"))
    with np.load(out / "results.npz") as npz:
        return doc, {k: npz[k] for k in npz.files}


def without_wall_clock(doc: dict[str, Any]) -> dict[str, Any]:
    doc = json.loads(json.dumps(doc))
    for entry in doc["methods"].values():
        for key in [k for k in entry if k.startswith(WALL_CLOCK)]:
            del entry[key]
    return doc


def assert_same_results(got: Path, want: Path) -> None:
    """Identical results.json but for wall-clock figures, identical arrays but for times."""
    (doc, arrays), (ref, ref_arrays) = read(got), read(want)
    assert without_wall_clock(doc) == without_wall_clock(ref)
    assert set(arrays) == set(ref_arrays)
    timed = [k for k in arrays if k.endswith(tuple(f"/{w}" for w in WALL_CLOCK))]
    assert {k.split("/")[1] for k in timed} == set(WALL_CLOCK)
    for key in set(arrays) - set(timed):
        np.testing.assert_array_equal(arrays[key], ref_arrays[key], err_msg=key)
    for key in timed:
        assert arrays[key].shape == ref_arrays[key].shape, key


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two robots 4 m apart, each with two objects ahead, in range of each other."""
    objects = [(3.0, 0.5, math.pi / 2, 1), (3.5, -0.5, 0.0, 2), (3.0, 4.5, 0.0, 2)]
    path = tmp_path_factory.mktemp("world") / "pair.toml"
    path.write_text(fleet_text("pair", STEPS, [0.0, 4.0], objects), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def runs(world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The study's two shards (``s0``, ``s1``: the local executor, spawned processes), their
    merge (``m``) and the whole study in one run on a Dask cluster in this process (``full``:
    threads, no process to start). The commands run in this process to save the start-up of
    four; `study merge` is run as a real process below."""
    from distributed import LocalCluster

    root = tmp_path_factory.mktemp("shards")
    for i in range(2):
        argv = ["study", "--scenario", str(world), *STUDY, "--shard", f"{i}/2"]
        assert main([*argv, "--out", str(root / f"s{i}")]) == 0
    merge = ["study", "merge", str(root / "s0"), str(root / "s1")]
    assert main([*merge, "--out", str(root / "m")]) == 0
    with LocalCluster(
        n_workers=1, processes=False, threads_per_worker=1, dashboard_address="127.0.0.1:0"
    ) as cluster:
        argv = ["study", "--scenario", str(world), *STUDY, "--out", str(root / "full")]
        assert main([*argv, "--cluster", cluster.scheduler_address]) == 0
    return root


def test_shard_takes_every_nth_seed_index() -> None:
    assert Shard(1, 3).seeds(list(range(10, 20))) == [11, 14, 17]
    assert Shard(0, 1).seeds([4, 5]) == [4, 5]
    assert Shard.parse("2/4") == Shard(2, 4)
    for bad in ("4/4", "-1/2", "1", "a/2", "1/0"):
        with pytest.raises(ValueError):
            Shard.parse(bad)


def test_study_shards_hold_their_seeds_and_say_which_shard_of_which_study(runs: Path) -> None:
    (s0, _), (s1, _) = read(runs / "s0"), read(runs / "s1")
    assert (s0["seeds"], s0["runs"], s1["seeds"], s1["runs"]) == ([5, 7], 2, [6], 1)
    assert s0["shard"]["index"] == 0 and s1["shard"]["index"] == 1
    shared = ("count", "seed", "runs", "snapshot_step", "snapshot_robot", "key")
    assert {k: s0["shard"][k] for k in shared} == {k: s1["shard"][k] for k in shared}
    assert (s0["shard"]["count"], s0["shard"]["seed"], s0["shard"]["runs"]) == (2, 5, 3)
    assert "shard" not in read(runs / "full")[0]


def test_study_merge_of_two_shards_equals_the_single_run(runs: Path) -> None:
    # (the single run is the one on the Dask cluster: that it equals the local executor's, seed
    # by seed, is the test below)
    assert_same_results(runs / "m", runs / "full")
    doc, arrays = read(runs / "m")
    assert "shard" not in doc and arrays["distributed/stacks_delivered"].sum() > 0
    for png in ("msde.png", "reliability.png", f"hypotheses_distributed_r1_k{STEPS}.png"):
        assert (runs / "m" / png).read_bytes()[:4] == b"\x89PNG", png


def _edited(src: Path, dst: Path, edit: Any) -> Path:
    shutil.copytree(src, dst)
    doc = json.loads((dst / "results.json").read_text())
    edit(doc)
    (dst / "results.json").write_text(json.dumps(doc))
    return dst


def _refusal(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("semfleet: error: "), err
    return err.removeprefix("semfleet: error: ").strip()


def test_study_merge_refuses_anything_but_every_shard_of_one_study_once(
    runs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    s0, s1, out = runs / "s0", runs / "s1", tmp_path / "out"
    other = _edited(s1, tmp_path / "paper_mc", lambda d: d.update(weight_estimator="paper_mc"))
    key = _edited(s1, tmp_path / "key", lambda d: d["shard"].update(key="0" * 64))
    count = _edited(s1, tmp_path / "count", lambda d: d["shard"].update(count=3))
    again = tmp_path / "s0-again"
    shutil.copytree(s0, again)
    cases = {
        (s0,): "shard 1/2 missing: no folder given holds seed 6",
        (s0, again, s1): f"{again} and {s0} are both shard 0/2 (seeds 5, 7)",
        (s0, other): (
            f"{other} and {s0} are shards of different studies: "
            "weight_estimator 'paper_mc' vs 'geo_conditioned'"
        ),
        (s0, count): f"{count} and {s0} are shards of different studies: shard count 3 vs 2",
        (s0, runs / "full"): f"{runs / 'full'}: not a shard of a study",
    }
    for folders, message in cases.items():
        got = _refusal(["study", "merge", *map(str, folders), "--out", str(out)], capsys)
        assert got.startswith(message), (got, message)
    got = _refusal(["study", "merge", str(s0), str(key), "--out", str(out)], capsys)
    assert "the scenario, the belief configuration or semfleet's version differ" in got
    got = _refusal(["study", "merge", str(s0), str(s1), "--runs", "4", "--out", str(out)], capsys)
    assert got == "study merge takes DIR... and --out only, not --runs"
    assert _refusal(["study", "merge", str(s0), str(s1), "--out", str(s1)], capsys).startswith(
        f"--out {s1} is one of the shards"
    )
    assert not out.exists()


def test_study_merge_refusal_is_one_line_from_the_command(runs: Path, tmp_path: Path) -> None:
    r = semfleet("study", "merge", str(runs / "s1"), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert r.stderr == "semfleet: error: shard 0/2 missing: no folder given holds seeds 5, 7\n"


def test_study_shard_without_seeds_is_refused_before_any_run(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def no_run(*args: object, **kwargs: object) -> None:
        raise AssertionError("a run started")

    monkeypatch.setattr("deploy.cli.commands.study.run_study", no_run)
    argv = ["study", "--scenario", "lanes:short", "--runs", "2", "--shard", "2/3"]
    assert _refusal([*argv, "--out", str(tmp_path)], capsys) == "--shard 2/3 of 2 runs has no seeds"
    with pytest.raises(SystemExit) as info:
        main(["study", "--scenario", "lanes:short", "--shard", "3/3"])
    assert info.value.code == 2
    assert "need 0 <= I < N" in capsys.readouterr().err


def test_study_on_a_dask_cluster_equals_the_local_executor_seed_by_seed(runs: Path) -> None:
    # Every seed's arrays from the Dask run equal those the local executor's spawned processes
    # gave for that seed in its shard (the seeds' rows: 5, 6, 7 on Dask; 5, 7 and 6 locally).
    (doc, dask), (_, s0), (_, s1) = read(runs / "full"), read(runs / "s0"), read(runs / "s1")
    assert doc["seeds"] == [5, 6, 7] and "--cluster" not in json.dumps(doc)
    local = {5: (s0, 0), 6: (s1, 0), 7: (s0, 1)}
    seeded = [k for k in dask if k != "seeds" and not k.endswith(("/step_ms", "/wall_s"))]
    seeded = [k for k in seeded if not k.endswith(("/fusion_ms", "/stack_bytes"))]
    assert {"distributed/robot_pose", "true_robot_pose", "distributed/calibration"} <= set(seeded)
    for row, seed in enumerate(doc["seeds"]):
        arrays, i = local[seed]
        for key in seeded:
            np.testing.assert_array_equal(dask[key][row], arrays[key][i], err_msg=f"{seed} {key}")


def test_study_cluster_without_dask_names_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed fails
    argv = ["study", "--scenario", "lanes:short", "--runs", "1", "--out", str(tmp_path)]
    got = _refusal([*argv, "--cluster", "tcp://127.0.0.1:8786"], capsys)
    assert got == "--cluster needs Dask's distributed scheduler: pip install 'semfleet[cluster]'"


def test_study_merge_takes_paper_and_checks_the_world_of_the_shards(
    runs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # --paper is presentation, not a setting the shards decided: merge takes it, and refuses it
    # for a world that is not the paper's as `study` does
    argv = ["study", "merge", str(runs / "s0"), str(runs / "s1"), "--out", str(tmp_path / "m")]
    why = _refusal([*argv, "--paper"], capsys)
    assert "'pair'" in why and "--paper" in why


def _npz_edited(src: Path, dst: Path, edit: Any) -> Path:
    shutil.copytree(src, dst)
    with np.load(dst / "results.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    edit(arrays)
    np.savez_compressed(dst / "results.npz", **arrays)
    return dst


def test_study_merge_refuses_a_shard_whose_arrays_are_missing_or_misshapen(
    runs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    s0, s1 = runs / "s0", runs / "s1"
    out = str(tmp_path / "m")

    def crop(arrays: dict[str, np.ndarray]) -> None:
        arrays["distributed/class_log_loss_local_objects"] = arrays[
            "distributed/class_log_loss_local_objects"
        ][:, :, :-1]

    bad_shape = _npz_edited(s1, tmp_path / "shape", crop)
    why = _refusal(["study", "merge", str(s0), str(bad_shape), "--out", out], capsys)
    assert str(bad_shape) in why and "distributed/class_log_loss_local_objects" in why
    assert "shape" in why

    missing = _npz_edited(s1, tmp_path / "missing", lambda a: a.pop("local/msde"))
    why = _refusal(["study", "merge", str(s0), str(missing), "--out", out], capsys)
    assert str(missing) in why and "local/msde" in why
    assert not (tmp_path / "m").exists()


def test_study_merge_keeps_the_association_figures_of_frames_without_ids(
    world: Path, tmp_path: Path
) -> None:
    """Issue 45: with `--ids none` a study's association and fleet association figures are in
    results.json; the merge of its shards makes the very same figures (all but the times per
    frame, which are the runs' own) from the arrays the shards archive."""
    ids = ("--ids", "none", "--clutter", "0.1")
    for i in range(2):
        argv = ["study", "--scenario", str(world), *STUDY, *ids, "--shard", f"{i}/2"]
        assert main([*argv, "--out", str(tmp_path / f"s{i}")]) == 0
    assert (
        main(
            [
                "study",
                "merge",
                str(tmp_path / "s0"),
                str(tmp_path / "s1"),
                "--out",
                str(tmp_path / "m"),
            ]
        )
        == 0
    )
    argv = ["study", "--scenario", str(world), *STUDY, *ids, "--out", str(tmp_path / "full")]
    assert main(argv) == 0
    (doc, arrays), (ref, ref_arrays) = read(tmp_path / "m"), read(tmp_path / "full")
    for key in ("association", "fleet_association"):
        method = "local" if key == "association" else "distributed"
        got, want = doc["methods"][method][key], ref["methods"][method][key]
        timed = {"ms_mean", "ms_p99"}
        assert {k: v for k, v in got.items() if k not in timed} == {
            k: v for k, v in want.items() if k not in timed
        }
        assert want["frames" if key == "association" else "owner_objects"] > 0
    np.testing.assert_array_equal(arrays["local/association"], ref_arrays["local/association"])
    assert arrays["local/association_ms"].shape == ref_arrays["local/association_ms"].shape
    assert arrays["local/association_frames"].tolist() == [2 * STEPS] * 3  # 2 robots a run
