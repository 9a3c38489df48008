"""The results archive (envelope, writer, reader) and the hybrid-belief study's summaries: pooled
calibration, time tails and fusion counts, on hand-made runs."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.study.archive import (
    RESULTS_FORMAT,
    ResultsArchive,
    pooled_calibration,
    read_results,
    study_archive,
    tail,
    write_archive,
)
from deploy.study.types import RunResult
from estimator.metrics import ECE_BINS, METRICS, calibration_stats
from tests.tolerance import assert_close

ROBOTS, STEPS = 2, 3


def _calibration(prob_by_robot: list[list[list[float]] | None]) -> np.ndarray:
    """(robots, STEPS, 3, bins): robot r's objects, all of true class 0, have the marginals
    ``prob_by_robot[r]`` at every step (None: nothing known)."""
    out = np.zeros((ROBOTS, STEPS, 3, ECE_BINS))
    for r, prob in enumerate(prob_by_robot):
        if prob is not None:
            p = np.array(prob)
            out[r, :] = calibration_stats(p, np.zeros(len(p), dtype=np.int64))
    return out


def _run(seed: int, calibration: np.ndarray, joins: list[int], rebuilds: list[int]) -> RunResult:
    metrics = {
        method: {m: np.full((ROBOTS, STEPS), float(seed)) for m in METRICS}
        for method in ("local", "distributed")
    }
    return RunResult(
        seed,
        metrics,
        {"local": [1.0, 2.0, 3.0], "distributed": [float(seed + 1)] * ROBOTS * STEPS},
        {"local": 1.0, "distributed": 2.0},
        fusion_ms={"distributed": [0.5] * ROBOTS * STEPS},
        stack_bytes={"distributed": [100, 300]},
        calibration={"local": calibration, "distributed": calibration},
        empty_joins={"distributed": joins},
        rebuilds={"distributed": rebuilds},
        robots=("r1", "r2"),
    )


def _two_runs() -> list[RunResult]:
    # run 0: robot 0 says P(class 0) = 0.9 of one object (true class 0), robot 1 knows nothing;
    # run 1: both robots say 0.9 of an object of class 1 (the hit is on the 0.1)
    right = _calibration([[[0.9, 0.1]], None])
    wrong = np.zeros((ROBOTS, STEPS, 3, ECE_BINS))
    for r in range(ROBOTS):
        wrong[r, :] = calibration_stats(np.array([[0.9, 0.1]]), np.array([1]))
    steps = ROBOTS * STEPS
    return [
        _run(0, right, [0, 1, 0, 0, 2, 0], [0, 1, 0, 0, 1, 0]),
        _run(1, wrong, [0] * steps, [0, 0, 0, 0, 0, 1]),
    ]


def test_tail_percentiles_and_max() -> None:
    got = tail("step_ms", list(range(1, 101)))
    assert list(got) == ["step_ms_p50", "step_ms_p95", "step_ms_p99", "step_ms_max"]
    assert_close(list(got.values()), [50.5, 95.05, 99.01, 100.0])


def test_tail_of_nothing_is_null() -> None:
    assert tail("fusion_ms", []) == dict.fromkeys(
        ["fusion_ms_p50", "fusion_ms_p95", "fusion_ms_p99", "fusion_ms_max"]
    )


def test_pooled_calibration_sums_runs_and_robots() -> None:
    runs = _two_runs()
    pooled = pooled_calibration(runs, "local")
    assert pooled is not None and pooled.shape == (STEPS, 3, ECE_BINS)
    # three 0.9s (one hit) and three 0.1s (two hits) at every step
    expected = np.zeros((3, ECE_BINS))
    expected[:, 9] = (3, 2.7, 1)
    expected[:, 1] = (3, 0.3, 2)
    for k in range(STEPS):
        assert_close(pooled[k], expected, what=f"k = {k + 1}")
    assert pooled_calibration(runs, "centralized") is None


def test_study_archive_pooled_ece_is_not_the_mean_of_robot_eces() -> None:
    doc = study_archive("hand", _two_runs(), ["local", "distributed"]).document()
    # pooled: (|2.7 − 1| + |0.3 − 2|) / 6 = 3.4 / 6; the robots' own ECEs are 0.1, 0.9 and 0.9
    for method in ("local", "distributed"):
        assert_close(doc["methods"][method]["class_ece_pooled"], [3.4 / 6] * STEPS, what=method)


def test_study_archive_time_tails_and_fusion_counts() -> None:
    doc = study_archive("hand", _two_runs(), ["local", "distributed"]).document()
    local, dist = doc["methods"]["local"], doc["methods"]["distributed"]
    assert_close(local["step_ms_p50"], 2.0)
    assert local["step_ms_max"] == 3.0
    assert_close(dist["step_ms_p50"], 1.5)
    assert dist["step_ms_max"] == 2.0
    assert dist["fusion_ms_p99"] == 0.5
    assert "fusion_ms_p50" not in local and "step_ms_median" not in local
    assert (dist["empty_joins"], dist["rebuilds"]) == (3, 3)
    assert "empty_joins" not in local and "rebuilds" not in local
    assert isinstance(dist["empty_joins"], int) and isinstance(dist["rebuilds"], int)


def test_study_archive_no_object_known_is_null() -> None:
    nothing = np.zeros((ROBOTS, STEPS, 3, ECE_BINS))
    doc = study_archive("hand", [_run(0, nothing, [0] * 6, [0] * 6)], ["local"]).document()
    assert doc["methods"]["local"]["class_ece_pooled"] == [None] * STEPS


def test_write_archive_carries_bins_and_counts(tmp_path: Path) -> None:
    runs = _two_runs()
    write_archive(tmp_path, study_archive("hand", runs, ["local", "distributed"]))
    json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))
    with np.load(tmp_path / "results.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    for method in ("local", "distributed"):
        calibration = arrays[f"{method}/calibration"]
        assert calibration.shape == (2, ROBOTS, STEPS, 3, ECE_BINS)
        assert_close(calibration[0], runs[0].calibration[method])
    np.testing.assert_array_equal(arrays["distributed/empty_joins"], [[0, 1, 0, 0, 2, 0], [0] * 6])
    np.testing.assert_array_equal(
        arrays["distributed/rebuilds"], [[0, 1, 0, 0, 1, 0], [0] * 5 + [1]]
    )
    assert arrays["distributed/empty_joins"].dtype == np.int64
    assert "local/empty_joins" not in arrays


def _archive(**changes: Any) -> ResultsArchive:
    fields: dict[str, Any] = {
        "study": "ufastslam",
        "scenario": "w",
        "seeds": (4, 5),
        "steps": 3,
        "methods": {"a": {"x": 1.5}},
        "settings": {"particles": 7},
        "arrays": {"a/x": np.array([1.0, 2.0])},
    }
    return ResultsArchive(**(fields | changes))


def test_archive_document_is_the_envelope_then_the_settings() -> None:
    doc = _archive().document()
    assert list(doc) == [
        "format", "study", "scenario", "runs", "seeds", "steps", "methods", "particles",
    ]  # fmt: skip
    assert doc["format"] == RESULTS_FORMAT == 2
    assert (doc["study"], doc["runs"], doc["seeds"]) == ("ufastslam", 2, [4, 5])
    assert doc["methods"] == {"a": {"x": 1.5}}


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"study": "mystery"}, "unknown study 'mystery'"),
        ({"settings": {"runs": 3, "seeds": [], "x": 1}}, "settings ['runs', 'seeds'] would"),
        ({"arrays": {"seeds": np.zeros(2)}}, "'seeds' is written from the archive's seeds"),
    ],
)
def test_archive_refuses_what_the_files_cannot_hold(changes: dict[str, Any], fragment: str) -> None:
    with pytest.raises(ValueError, match=re.escape(fragment)):
        _archive(**changes)


def test_write_archive_reads_back(tmp_path: Path) -> None:
    write_archive(tmp_path, _archive())
    assert read_results(tmp_path / "results.json") == _archive().document()
    with np.load(tmp_path / "results.npz") as npz:
        assert sorted(npz.files) == ["a/x", "seeds"]
        np.testing.assert_array_equal(npz["seeds"], [4, 5])
        assert npz["seeds"].dtype == np.int64


def test_read_results_refuses_another_format(tmp_path: Path) -> None:
    path = tmp_path / "results.json"
    path.write_text(json.dumps({**_archive().document(), "format": 1}), encoding="utf-8")
    with pytest.raises(ValueError, match="unsupported results format 1"):
        read_results(path)


def test_write_archive_refuses_nan(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="Out of range float"):
        write_archive(tmp_path, _archive(methods={"a": {"x": math.nan}}))


def test_study_archive_records_robots_and_settings() -> None:
    runs = _two_runs()
    settings = {"communication": "range", "launch": {"mode": "lockstep"}}
    archive = study_archive("hand", runs, ["local"], settings)
    assert (archive.study, archive.seeds, archive.steps) == ("hybrid", (0, 1), STEPS)
    doc = archive.document()
    assert doc["robots"] == ["r1", "r2"]
    assert doc["communication"] == "range" and doc["launch"] == {"mode": "lockstep"}
    keys = (*METRICS, "step_ms", "wall_s", "calibration")
    assert set(archive.arrays) == {f"local/{k}" for k in keys}


def test_study_archive_refuses_robots_that_are_not_the_robot_axis() -> None:
    runs = [dataclasses.replace(r, robots=("r1", "r2", "r3")) for r in _two_runs()]
    with pytest.raises(ValueError, match=r"robots \['r1', 'r2', 'r3'\] do not match the runs' 2"):
        study_archive("hand", runs, ["local"])


def test_study_archive_takes_fusion_times_and_stack_sizes_each_on_its_own() -> None:
    # what a launcher may record: stack sizes without fusion times, or the reverse
    sizes_only = [dataclasses.replace(r, fusion_ms={}) for r in _two_runs()]
    entry = study_archive("hand", sizes_only, ["distributed"]).methods["distributed"]
    assert (entry["stack_bytes_mean"], entry["stack_bytes_max"], entry["stacks_delivered"]) == (
        200.0,
        300,
        4,
    )
    assert "fusion_ms_p50" not in entry
    times_only = [dataclasses.replace(r, stack_bytes={}) for r in _two_runs()]
    archive = study_archive("hand", times_only, ["distributed"])
    assert archive.methods["distributed"]["fusion_ms_max"] == 0.5
    assert "stack_bytes_mean" not in archive.methods["distributed"]
    assert archive.arrays["distributed/fusion_ms"].shape == (2, ROBOTS * STEPS)


@pytest.mark.parametrize(
    ("settings", "expected"),
    [
        ({"max_hypotheses": 4}, {"local": 1, "distributed": 0}),  # run 1's local held 4
        ({"max_hypotheses": 5}, {"local": 0, "distributed": 0}),
        ({"max_hypotheses": 4, "robot_budget": 2}, None),  # caps differ between beliefs
        ({}, None),
    ],
)
def test_runs_at_the_hypothesis_cap_are_counted(
    settings: dict[str, Any], expected: dict[str, int] | None
) -> None:
    """runs_at_cap: the runs in which some belief held the study's cap of hypotheses (it was
    pruned to it: an exact reference is then not exact); NaN (unscored) steps are no holding."""
    runs = _two_runs()
    held = runs[1].metrics["local"]["hypotheses"]
    held[:] = np.nan
    held[1, 2] = 4.0
    doc = study_archive("w", runs, ["local", "distributed"], settings).document()
    got = {m: doc["methods"][m].get("runs_at_cap") for m in ("local", "distributed")}
    if expected is None:
        assert got == {"local": None, "distributed": None}
    else:
        assert got == expected
