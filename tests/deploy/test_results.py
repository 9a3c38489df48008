"""Study results: pooled calibration, time tails and fusion counts, on hand-made runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from deploy.results import pooled_calibration, summarise, tail, write_results
from deploy.study import RunResult
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


def test_summarise_pooled_ece_is_not_the_mean_of_robot_eces() -> None:
    doc = summarise("hand", _two_runs(), ["local", "distributed"])
    # pooled: (|2.7 − 1| + |0.3 − 2|) / 6 = 3.4 / 6; the robots' own ECEs are 0.1, 0.9 and 0.9
    for method in ("local", "distributed"):
        assert_close(doc["methods"][method]["class_ece_pooled"], [3.4 / 6] * STEPS, what=method)


def test_summarise_time_tails_and_fusion_counts() -> None:
    doc = summarise("hand", _two_runs(), ["local", "distributed"])
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


def test_summarise_no_object_known_is_null() -> None:
    nothing = np.zeros((ROBOTS, STEPS, 3, ECE_BINS))
    doc = summarise("hand", [_run(0, nothing, [0] * 6, [0] * 6)], ["local"])
    assert doc["methods"]["local"]["class_ece_pooled"] == [None] * STEPS


def test_write_results_carries_bins_and_counts(tmp_path: Path) -> None:
    runs = _two_runs()
    doc = summarise("hand", runs, ["local", "distributed"])
    write_results(tmp_path, doc, runs, ["local", "distributed"])
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
