"""`semfleet study` end to end, as real processes on a tiny world, and `run_single` in-process."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from agents.node import RobotNode
from deploy.cli.main import main
from deploy.study.archive import study_archive
from deploy.study.report import render_summary, table_steps
from deploy.study.runner import run_single
from deploy.study.types import ASSOCIATE_ON
from estimator.distributed import FusionStats
from estimator.hybrid import POSE_WINDOW, BeliefConfig
from estimator.metrics import CROSS_METRICS, ECE_BINS, METRICS, class_comparison, ece_from_stats
from sim.loader import load_scenario, parse_scenario
from sim.sensors import Detector
from tests.estimator.scenarios import fleet_text
from tests.tolerance import assert_close

SEMFLEET = Path(sys.executable).with_name("semfleet")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
METHODS = ("local", "centralized")
STEPS = 12
ROBOTS = 2
CURVE_PLOTS = ("msde", "robot_error", "object_error", "robot_sqrt_det", "object_sqrt_det")


def scenario_text(robots: int) -> str:
    """Robots drive along +x at 0.25 m per step, 4 m apart; each has two objects of its own ahead
    of it, first in range at k = 3 and k = 5. Steps 1–2 see nothing, so the object metrics of
    those steps are NaN for every robot and run: the JSON must carry them as null."""
    objects = []
    for i in range(robots):
        y = 4.0 * i
        objects += [(4.5, y + 0.5, math.pi / 2, 1 + i), (5.0, y - 0.5, 0.0, 2 - i)]
    ys = [4.0 * i for i in range(robots)]
    return fleet_text("tiny", STEPS, ys, objects, description="a fast world for study tests")


def semfleet(*args: str, columns: int | None = 200) -> subprocess.CompletedProcess[str]:
    env = {"PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"}
    if columns is not None:
        env["COLUMNS"] = str(columns)
    return subprocess.run(
        [str(SEMFLEET), *args], capture_output=True, text=True, timeout=120, env=env
    )


def study(world: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    r = semfleet("study", "--scenario", str(world), "--out", str(out), *extra)
    assert r.returncode == 0, (r.stdout, r.stderr)
    return r


def _reject_constant(token: str) -> float:
    raise ValueError(f"non-standard JSON constant {token}")


def read_json(out: Path) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(
        (out / "results.json").read_text(encoding="utf-8"), parse_constant=_reject_constant
    )
    return doc


def read_npz(out: Path) -> dict[str, np.ndarray]:
    with np.load(out / "results.npz") as npz:
        return {k: npz[k] for k in npz.files}


def metric_arrays(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Every array a run's seed decides: all but the seeds and the wall-clock times."""
    return {
        k: v
        for k, v in arrays.items()
        if k != "seeds" and not k.endswith(("/step_ms", "/wall_s", "/fusion_ms"))
    }


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("world") / "tiny.toml"
    path.write_text(scenario_text(ROBOTS), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def two_runs(
    world: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[subprocess.CompletedProcess[str], Path]:
    """The study every file test reads: both methods, seeds 5 and 6, two processes."""
    out = tmp_path_factory.mktemp("study") / "out"
    r = study(
        world, out, "--methods", "local,centralized", "--runs", "2", "--jobs", "2", "--seed", "5"
    )
    return r, out


def test_study_prints_summary_table(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    r, _ = two_runs
    assert "Traceback" not in r.stderr
    for text in ("tiny: 2 runs", f"k = {STEPS}", *METHODS, "msde", "robot_error", "object_error"):
        assert text in r.stdout, text
    for text in ("robot_nees", "class_log_loss", "class_ece_pooled", "hypotheses"):
        assert text in r.stdout, text
    for text in ("belief step ms", "p50 / p95 / p99 / max", "empty joins", "rebuilds"):
        assert text in r.stdout, text
    # 12 steps: four evenly spaced columns ending at the last step
    assert all(f"k = {k} " in r.stdout for k in (3, 6, 9, 12))
    assert "seeds 5..6" in r.stdout


def test_study_writes_results_and_plots(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    _, out = two_runs
    assert (out / "results.json").stat().st_size > 0
    assert (out / "results.npz").read_bytes()[:2] == b"PK"
    pngs = [f"{m}.png" for m in CURVE_PLOTS] + ["reliability.png"]
    pngs += [f"hypotheses_{m}_r1_k{STEPS}.png" for m in METHODS]
    for name in pngs:
        assert (out / name).read_bytes()[:8] == PNG_MAGIC, name


def test_study_results_json_schema(two_runs: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    _, out = two_runs
    doc = read_json(out)
    assert doc["format"] == 2
    assert doc["study"] == "hybrid"
    assert doc["scenario"] == "tiny"
    assert doc["runs"] == 2
    assert doc["seeds"] == [5, 6]
    assert doc["steps"] == STEPS
    assert doc["robots"] == ["r1", "r2"]
    assert doc["weight_estimator"] == "geo_conditioned"
    assert (doc["hypotheses"], doc["communication"]) == ("per_object", "range")
    assert doc["classes"] == "per_object"
    assert doc["max_hypotheses"] == BeliefConfig().max_hypotheses
    assert doc["robot_budget"] == BeliefConfig().robot_budget
    assert doc["semantic_poses"] is False
    assert doc["xi"] == "auto"
    assert set(doc["methods"]) == set(METHODS)
    for method, entry in doc["methods"].items():
        assert set(entry["mean"]) == {*METRICS, *CROSS_METRICS}, method
        for metric, curve in entry["mean"].items():
            assert isinstance(curve, list) and len(curve) == STEPS, (method, metric)
            assert all(v is None or isinstance(v, float) for v in curve), (method, metric)
        tail = [entry[f"step_ms_{q}"] for q in ("p50", "p95", "p99", "max")]
        for key, value in zip(("wall_s", "step_ms_p50"), (entry["wall_s"], tail[0]), strict=True):
            assert isinstance(value, float) and value > 0, (method, key)
        assert tail == sorted(tail), method
        assert "step_ms_median" not in entry and "fusion_ms_p50" not in entry
        assert "empty_joins" not in entry and "rebuilds" not in entry and "refused" not in entry
        pooled = entry["class_ece_pooled"]
        assert len(pooled) == STEPS and pooled[:2] == [None, None], method
        assert all(isinstance(v, float) and 0.0 <= v <= 1.0 for v in pooled[2:]), method
        # nothing is in range before k = 3: no object is known, so there is no class accuracy
        assert entry["mean"]["msde"][:2] == [None, None]
        assert all(v is not None for v in entry["mean"]["msde"][2:])
        assert all(v is not None for v in entry["mean"]["robot_error"])


def test_study_results_json_is_strict(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    _, out = two_runs
    text = (out / "results.json").read_text(encoding="utf-8")
    for token in ("NaN", "Infinity"):
        assert token not in text
    read_json(out)


def test_study_results_npz_shapes(two_runs: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    _, out = two_runs
    arrays = read_npz(out)
    keys = (*METRICS, *CROSS_METRICS, "robot_pose", "step_ms", "wall_s", "calibration")
    expected = {f"{m}/{k}" for m in METHODS for k in keys} | {"seeds", "true_robot_pose"}
    assert set(arrays) == expected
    for method in METHODS:
        for metric in (*METRICS, *CROSS_METRICS):
            values = arrays[f"{method}/{metric}"]
            assert values.shape == (2, ROBOTS, STEPS), (method, metric)
            assert values.dtype == np.float64, (method, metric)
        calibration = arrays[f"{method}/calibration"]
        assert calibration.shape == (2, ROBOTS, STEPS, 3, ECE_BINS), method
        assert calibration.dtype == np.float64, method
    np.testing.assert_array_equal(arrays["seeds"], [5, 6])
    # local steps every robot's belief separately, centralized steps one belief for all
    assert arrays["local/step_ms"].shape == (2, ROBOTS * STEPS)
    assert arrays["centralized/step_ms"].shape == (2, STEPS)
    for method in METHODS:
        assert np.all(arrays[f"{method}/step_ms"] > 0)


def test_study_json_means_are_npz_means(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    _, out = two_runs
    doc, arrays = read_json(out), read_npz(out)
    for method in METHODS:
        for metric in METRICS:
            values = arrays[f"{method}/{metric}"]
            curve = doc["methods"][method]["mean"][metric]
            known = ~np.all(np.isnan(values), axis=(0, 1))
            assert [v is not None for v in curve] == known.tolist(), (method, metric)
            mean = np.nanmean(values[:, :, known], axis=(0, 1))
            got = [v for v in curve if v is not None]
            assert_close(got, mean, rtol=0.0, atol=1e-12, what=f"{method}/{metric}")


def test_study_pooled_ece_is_the_ece_of_summed_bins(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    _, out = two_runs
    doc, arrays = read_json(out), read_npz(out)
    for method in METHODS:
        calibration = arrays[f"{method}/calibration"]
        # every known object contributes M = 2 marginals per robot, run and step
        counts = calibration[..., 0, :].sum(axis=-1)
        assert np.all(counts % 2 == 0) and np.all(counts[:, :, :2] == 0), method
        # the per-robot class_ece is the ECE of that robot's own bins
        own = ece_from_stats(calibration)
        np.testing.assert_array_equal(
            np.isnan(own), np.isnan(arrays[f"{method}/class_ece"]), err_msg=method
        )
        assert_close(
            own[~np.isnan(own)], arrays[f"{method}/class_ece"][~np.isnan(own)], what=method
        )
        # the pooled curve sums bins over runs and robots before dividing
        pooled = ece_from_stats(calibration.sum(axis=(0, 1)))
        got = doc["methods"][method]["class_ece_pooled"]
        assert [v is None for v in got] == np.isnan(pooled).tolist(), method
        assert_close([v for v in got if v is not None], pooled[2:], what=method)


def test_study_step_time_tails_are_npz_percentiles(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    _, out = two_runs
    doc, arrays = read_json(out), read_npz(out)
    for method in METHODS:
        ms = arrays[f"{method}/step_ms"].ravel()
        entry = doc["methods"][method]
        expected = [*np.percentile(ms, [50, 95, 99]), ms.max()]
        got = [entry[f"step_ms_{q}"] for q in ("p50", "p95", "p99", "max")]
        assert_close(got, expected, what=method)


def test_study_reruns_are_identical(
    world: Path, tmp_path: Path, two_runs: tuple[subprocess.CompletedProcess[str], Path]
) -> None:
    # Seed 6 again, alone and in one process: the very numbers it gave as the second run of the
    # two-process study (a run depends on its seed only, not on its place in a larger study).
    args = ("--methods", "local,centralized", "--runs", "1", "--jobs", "1", "--seed", "6")
    study(world, tmp_path / "a", *args)
    a = metric_arrays(read_npz(tmp_path / "a"))
    keys = (*METRICS, *CROSS_METRICS, "robot_pose", "calibration")
    assert set(a) == {f"{m}/{k}" for m in METHODS for k in keys} | {"true_robot_pose"}
    both = metric_arrays(read_npz(two_runs[1]))
    for key in a:
        np.testing.assert_array_equal(a[key][0], both[key][1], err_msg=key)


def test_study_jobs_do_not_change_metrics(
    world: Path, tmp_path: Path, two_runs: tuple[subprocess.CompletedProcess[str], Path]
) -> None:
    out = tmp_path / "serial"
    extra = ("--snapshot-robot", "r2", "--snapshot-step", "4")
    study(
        world,
        out,
        "--methods",
        "local,centralized",
        "--runs",
        "2",
        "--jobs",
        "1",
        "--seed",
        "5",
        *extra,
    )
    serial, parallel = metric_arrays(read_npz(out)), metric_arrays(read_npz(two_runs[1]))
    assert set(serial) == set(parallel)
    for key in serial:
        np.testing.assert_array_equal(serial[key], parallel[key], err_msg=key)
    for method in METHODS:
        assert (out / f"hypotheses_{method}_r2_k4.png").read_bytes()[:8] == PNG_MAGIC


def test_run_single_one_robot_local_equals_centralized() -> None:
    # With one robot the centralized belief is that robot's local belief: same frames (common
    # random numbers) and the same estimator samples, so every metric must agree exactly.
    scenario = parse_scenario(scenario_text(1), "one.toml")
    result = run_single(scenario, list(METHODS), 5, BeliefConfig())
    assert result.seed == 5 and result.robots == ("r1",)
    for metric in METRICS:
        local, central = result.metrics["local"][metric], result.metrics["centralized"][metric]
        assert local.shape == (1, STEPS), metric
        np.testing.assert_array_equal(local, central, err_msg=metric)


def test_run_single_scores_only_the_steps_asked_for_and_the_same_values_there() -> None:
    # Scoring reads the beliefs and changes none of them: the scored steps hold exactly the
    # values of a run that scores every step, the others NaN (every method, the fleets too).
    scenario = parse_scenario(scenario_text(ROBOTS), "tiny.toml")
    methods = ["local", "distributed", "double_count", "centralized"]
    every = run_single(scenario, methods, 5, BeliefConfig())
    some = run_single(scenario, methods, 5, BeliefConfig(), scored={4, STEPS})
    at = [3, STEPS - 1]  # steps 4 and STEPS, zero-based
    rest = [k for k in range(STEPS) if k not in at]
    for method in methods:
        for metric in METRICS:
            full, part = every.metrics[method][metric], some.metrics[method][metric]
            np.testing.assert_array_equal(part[:, at], full[:, at], err_msg=(method, metric))
            assert np.isnan(part[:, rest]).all(), (method, metric)
            assert not np.isnan(full[:, rest]).all(), (method, metric)
        np.testing.assert_array_equal(
            some.calibration[method][:, at], every.calibration[method][:, at]
        )
        assert not some.calibration[method][:, rest].any(), method


def test_run_single_sums_every_fusion_report_of_the_fleets(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The fleets' empty joins and rebuilds are whatever RobotNode's FusionStats report: here a
    # fake two empty joins and one rebuild per integration, tallied per fusion mode.
    reported = {"consistent": [0, 0], "double_count": [0, 0]}
    integrate = RobotNode.integrate_pending

    def counting(node: RobotNode) -> FusionStats:
        stats = integrate(node)
        reported[node.distributed.fusion][0] += 2
        reported[node.distributed.fusion][1] += 1
        return dataclasses.replace(
            stats, empty_joins=stats.empty_joins + 2, rebuilds=stats.rebuilds + 1
        )

    monkeypatch.setattr(RobotNode, "integrate_pending", counting)
    scenario = parse_scenario(scenario_text(ROBOTS), "tiny.toml")
    methods = ["local", "distributed", "double_count"]
    result = run_single(scenario, methods, 5, BeliefConfig())
    doc = study_archive("tiny", [result, result], methods).document()
    for method, fusion in (("distributed", "consistent"), ("double_count", "double_count")):
        joins, rebuilds = result.empty_joins[method], result.rebuilds[method]
        assert len(joins) == len(rebuilds) == ROBOTS * STEPS == len(result.step_ms[method])
        assert [sum(joins), sum(rebuilds)] == reported[fusion] != [0, 0], method
        entry = doc["methods"][method]
        assert (entry["empty_joins"], entry["rebuilds"]) == (2 * sum(joins), 2 * sum(rebuilds))
        assert result.refused[method] == entry["refused"] == 0, method  # an honest fleet
    assert "local" not in result.empty_joins and "empty_joins" not in doc["methods"]["local"]
    assert "refused" not in doc["methods"]["local"]


def test_table_steps_end_at_the_last_step() -> None:
    assert table_steps(60) == [15, 30, 45, 60]
    assert table_steps(20) == [5, 10, 15, 20]
    assert table_steps(STEPS) == [3, 6, 9, 12]
    assert table_steps(50) == [13, 25, 38, 50]
    assert table_steps(2) == [1, 2]
    assert table_steps(1) == [1]


def _doc(steps: int) -> dict[str, Any]:
    """A results.json document of a ``steps``-step world: local, and a fleet method with every
    figure the cost table shows."""
    curve: list[float | None] = [None] + [0.5] * (steps - 1)
    entry: dict[str, Any] = {
        "mean": {m: curve for m in METRICS},
        "class_ece_pooled": [None] + [0.125] * (steps - 1),
        "wall_s": 1.0,
        **{f"step_ms_{q}": v for q, v in (("p50", 1.0), ("p95", 2.0), ("p99", 3.0), ("max", 4.0))},
    }
    fleet = {
        **entry,
        "mean": {**entry["mean"], "class_gap_central": [0.0625] * steps},
        **{
            f"fusion_ms_{q}": v for q, v in (("p50", 0.1), ("p95", 0.2), ("p99", 0.3), ("max", 0.4))
        },
        "stack_bytes_mean": 10.0,
        "stack_bytes_max": 20,
        "stacks_delivered": 2,
        "empty_joins": 7,
        "rebuilds": 1234,
        "refused": 5,
    }
    return {
        "scenario": "w",
        "runs": 2,
        "steps": steps,
        "methods": {"local": entry, "distributed": fleet},
    }


def test_render_summary_on_a_20_step_world() -> None:
    console = Console(record=True, width=250)
    render_summary(_doc(20), console)
    text = console.export_text()
    assert [f"k = {k}" in text for k in (5, 10, 15, 20)] == [True] * 4
    assert "k = 30" not in text and "k = 60" not in text
    lines = text.splitlines()
    ece_rows = [line for line in lines if "class_ece_pooled" in line]
    assert len(ece_rows) == 2 and all(line.count("0.125") == 4 for line in ece_rows)
    local = next(line for line in lines if "1.00 / 2.00" in line and "local" in line)
    assert "1.00 / 2.00 / 3.00 / 4.00" in local and local.count("—") == 5  # no fleet: 5 cells
    fleet = next(line for line in lines if "1,234" in line)
    assert "0.10 / 0.20 / 0.30 / 0.40" in fleet and "10 / 20" in fleet
    assert fleet.split()[-3:] == ["7", "1,234", "5"]  # empty joins, rebuilds, refused


def test_render_summary_fits_80_columns_without_cutting_a_figure() -> None:
    """The cost table's cells hold four figures each: at 80 columns a column that does not fit
    goes to a second block; nothing is cut (it printed ``distrib…`` in the demo)."""
    console = Console(record=True, width=80)
    render_summary(_doc(20), console)
    text = console.export_text()
    assert "…" not in text and max(len(line) for line in text.splitlines()) <= 80, text
    assert "1.00 / 2.00 / 3.00 / 4.00" in text and "0.10 / 0.20 / 0.30 / 0.40" in text
    assert "distributed" in text and "rebuilds" in text


def test_render_summary_leaves_out_a_comparison_no_method_has() -> None:
    # the fleet has a gap to the centralized belief, local has none (dashes); no method has one
    # to `received`, which the study did not run: no row
    console = Console(record=True, width=250)
    render_summary(_doc(8), console, [4, 8])
    rows = [line for line in console.export_text().splitlines() if "class_gap" in line]
    assert len(rows) == 2 and all("class_gap_central" in r for r in rows), rows
    assert sorted(r.count("0.0625") for r in rows) == [0, 2]
    assert sorted(r.count("—") for r in rows) == [0, 2]


def test_render_summary_without_pooled_ece_shows_dashes() -> None:
    doc = _doc(8)
    del doc["methods"]["local"]["class_ece_pooled"]
    console = Console(record=True, width=250)
    render_summary(doc, console, [4, 8])
    row = next(line for line in console.export_text().splitlines() if "class_ece_pooled" in line)
    assert row.count("—") == 2


def test_run_single_rejects_unknown_method() -> None:
    scenario = parse_scenario(scenario_text(1), "one.toml")
    with pytest.raises(ValueError, match="unknown methods"):
        run_single(scenario, ["local", "bogus"], 5, BeliefConfig())


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--methods", "local,bogus"], "unknown method(s) ['bogus']"),
        (["--runs", "0"], "--runs: 0 must be a positive integer"),
        (["--jobs", "0"], "--jobs: 0 must be a positive integer"),
        (["--seed", "-1"], "seeds are non-negative integers"),
        (["--scenario", "nonesuch"], "nonesuch: not a file and not a bundled scenario"),
        (["--scenario", "missing.toml"], "missing.toml: no such scenario file"),
        (["--snapshot-step", "999"], f"--snapshot-step: 999 is outside 1..{STEPS}"),
        (["--snapshot-step", "-1"], f"--snapshot-step: -1 is outside 1..{STEPS}"),
        (["--snapshot-step", "0"], f"--snapshot-step: 0 is outside 1..{STEPS}"),
        (["--snapshot-robot", "nobody"], "--snapshot-robot: no robot 'nobody' in tiny"),
        *(
            (["--xi", "sparse", "--hypotheses", joint], "--xi sparse needs --hypotheses per_object")
            for joint in ("marginal", "paper", "exact")
        ),
        (["--hypotheses", "per_object", "--xi", "banded"], "invalid choice: 'banded'"),
        (["--xi", "dense", "--xi-parents", "3"], "--xi-parents shapes a sparse ξ: it needs"),
        (["--hypotheses", "marginal", "--xi-parents", "0"], "--xi-parents shapes a sparse ξ"),
        (["--xi-parents", "4"], "invalid choice: 4 (choose from 0, 1, 2, 3)"),
        (["--semantic-poses"], "--semantic-poses needs a continuous belief per class"),
        (["--window", "5", "--hypotheses", "marginal"], "--window 5 needs --hypotheses per_object"),
        (["--window", "0"], "--window must be ≥ 1 step (or all), got 0"),
        (["--window", "x"], "--window 'x': a number of steps ≥ 1, or all"),
        (
            ["--slot-lin", "local", "--hypotheses", "marginal"],
            "--slot-lin local needs --hypotheses per_object",
        ),
        (["--slot-lin", "D"], "invalid choice: 'D'"),
        (["--ids", "none", "--methods", "local,centralized"], "would need an association of its"),
        (
            ["--ids", "none", "--methods", "local,distributed", "--hypotheses", "marginal"],
            "fleet association needs --hypotheses per_object",
        ),
        (["--ids", "tracker"], "invalid choice: 'tracker'"),
        (["--clutter", "2"], "expected a number in [0, 1), got '2'"),
    ],
)
def test_study_user_errors_are_one_clear_line(
    world: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    fragment: str,
) -> None:
    out = tmp_path / "out"
    try:
        code = main(["study", "--scenario", str(world), "--runs", "1", "--out", str(out), *args])
    except SystemExit as exc:  # argparse's own errors
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    # argparse's own errors and ours alike: one line, the whole of stderr
    assert err.count("\n") == 1 and "error: " in err, err
    assert fragment in err
    assert not out.exists()


def test_study_user_error_is_one_line_on_a_narrow_terminal(tmp_path: Path) -> None:
    r = semfleet("study", "--scenario", "nonesuch", "--out", str(tmp_path), columns=None)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0, r.stderr


@pytest.mark.parametrize(
    ("options", "semantic_poses"),
    [
        (("--semantic-poses", "--hypotheses", "marginal"), True),
        (("--hypotheses", "paper"), True),
        ((), False),
    ],
)
def test_study_semantic_poses_reach_the_beliefs_and_the_results(
    world: Path, tmp_path: Path, options: tuple[str, ...], semantic_poses: bool
) -> None:
    out = tmp_path / "out"
    r = study(world, out, "--methods", "local", "--runs", "1", "--jobs", "1", *options)
    assert r.returncode == 0, r.stderr
    assert read_json(out)["semantic_poses"] is semantic_poses


@pytest.mark.parametrize(
    ("options", "settings"),
    [
        ((), {"classes": "per_object", "xi": "auto"}),
        (("--xi", "dense"), {"classes": "per_object", "xi": "dense"}),
        (("--xi", "sparse"), {"classes": "per_object", "xi": "sparse"}),
        # a window of 3 steps of a 12-step study marginalises three times
        (("--window", "3"), {"classes": "per_object", "window": 3}),
        ((), {"classes": "per_object", "slot_linearisation": "fused"}),
        (("--slot-lin", "local"), {"classes": "per_object", "slot_linearisation": "local"}),
    ],
)
def test_study_xi_and_window_reach_the_beliefs_and_the_results(
    world: Path, tmp_path: Path, options: tuple[str, ...], settings: dict[str, object]
) -> None:
    """--xi picks the ξ of a per-object slot, --window the beliefs' window of poses; every
    method fuses and scores with either."""
    out = tmp_path / "out"
    methods = ("local", "distributed", "centralized")
    r = study(world, out, "--methods", ",".join(methods), "--runs", "1", "--jobs", "1", *options)
    assert r.returncode == 0, r.stderr
    doc = read_json(out)
    assert {key: doc[key] for key in settings} == settings
    for method in methods:
        error = doc["methods"][method]["mean"]["object_error"]
        assert all(v is None or np.isfinite(v) for v in error) and error[-1] is not None


def test_study_xi_parents_reach_the_slots_and_the_results(tmp_path: Path) -> None:
    """--xi-parents shapes the fleet's sparse slots: on the paper's world (12 objects, enough
    for parents to choose from) the stacks grow with the parents (more edges); a study on the
    default writes no key."""
    doc = {}
    for parents in ("0", "2", "3"):
        out = tmp_path / parents
        options = ("--xi", "sparse", "--xi-parents", parents, "--runs", "1", "--jobs", "1")
        r = study(Path("paper"), out, "--methods", "distributed", *options)
        assert r.returncode == 0, r.stderr
        doc[parents] = read_json(out)
    assert "xi_parents" not in doc["2"]
    assert doc["0"]["xi_parents"] == 0 and doc["3"]["xi_parents"] == 3
    mean = {p: d["methods"]["distributed"]["stack_bytes_mean"] for p, d in doc.items()}
    assert mean["0"] < mean["2"] < mean["3"], mean


@pytest.mark.parametrize(
    ("options", "window"),
    [((), POSE_WINDOW), (("--window", "all"), None), (("--hypotheses", "marginal"), None)],
)
def test_study_window_is_the_default_and_all_keeps_every_pose(
    world: Path, tmp_path: Path, options: tuple[str, ...], window: int | None
) -> None:
    """Per-object beliefs keep a window of poses by default; --window all and joint class
    tables keep every pose."""
    out = tmp_path / "out"
    r = study(world, out, "--methods", "local", "--runs", "1", "--jobs", "1", *options)
    assert r.returncode == 0, r.stderr
    assert read_json(out)["window"] == window


def test_render_summary_says_which_beliefs_were_pruned_to_the_cap() -> None:
    doc = _doc(20)
    doc["max_hypotheses"] = 4096
    doc["methods"]["distributed"]["runs_at_cap"] = 2
    doc["methods"]["local"]["runs_at_cap"] = 0
    console = Console(record=True, width=250)
    render_summary(doc, console)
    lines = [line for line in console.export_text().splitlines() if "cap of" in line]
    assert lines == [
        "distributed: a belief held the cap of 4,096 hypotheses in 2 of 2 runs and was pruned to "
        "it (--hypotheses exact is then not exact)"
    ]


def test_run_single_compares_each_belief_with_the_centralized_and_local_ones() -> None:
    # The cross metrics are class_comparison of the very snapshots the study scores: at the
    # snapshot step, recomputed from the beliefs' own marginals; NaN where a belief is compared
    # with itself, and absent (NaN) when the study runs no belief to compare with.
    scenario = parse_scenario(scenario_text(ROBOTS), "tiny.toml")
    methods = ["local", "distributed", "centralized"]
    result = run_single(scenario, methods, 5, BeliefConfig(), snapshot_step=STEPS)
    truth = {o.id: o.class_index for o in scenario.objects}
    k = STEPS - 1
    for i, robot in enumerate(scenario.robot_ids):
        snaps = {m: result.snapshots[m][robot] for m in methods}
        marg = {m: (s.object_ids, s.marginals(scenario.num_classes)) for m, s in snaps.items()}
        got = {m: result.metrics[m] for m in methods}
        gap, _, central = class_comparison(*marg["distributed"], *marg["centralized"], truth)
        assert got["distributed"]["class_gap_central"][i, k] == pytest.approx(gap)
        assert got["distributed"]["class_log_loss_centralized_here"][i, k] == pytest.approx(central)
        _, on_local, _ = class_comparison(*marg["distributed"], *marg["local"], truth)
        assert got["distributed"]["class_log_loss_local_objects"][i, k] == pytest.approx(on_local)
        _, c_on_local, _ = class_comparison(*marg["centralized"], *marg["local"], truth)
        assert got["centralized"]["class_log_loss_local_objects"][i, k] == pytest.approx(c_on_local)
        assert np.isnan(got["centralized"]["class_gap_central"][i]).all()
        assert np.isnan(got["local"]["class_log_loss_local_objects"][i]).all()
        # the other robot's objects reach D through its slot: D knows more than L here
        assert len(marg["distributed"][0]) > len(marg["local"][0])
    assert np.isfinite(result.metrics["local"]["class_gap_central"][:, k]).all()
    alone = run_single(scenario, ["distributed"], 5, BeliefConfig())
    for name in CROSS_METRICS:
        assert np.isnan(alone.metrics["distributed"][name]).all(), name


def test_received_is_the_centralized_belief_over_what_each_robot_was_given(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # The robots talk from step 8 only: until then each has received nothing and `received`
    # knows the robot's own objects, as L and D do (not C, which knows both robots'); from step 8
    # on it catches up with the other robot's frames up to the stamp D holds (7 at step 8, several
    # belief steps at once) and knows what D knows. D then differs from it by the fusion alone:
    # far less than from C, which is a step ahead with the other robot's news.
    objects = []
    for i in range(ROBOTS):
        y = 4.0 * i
        objects += [(4.5, y + 0.5, math.pi / 2, 1 + i), (5.0, y - 0.5, 0.0, 2 - i)]
    comm = 'mode = "schedule"\nrange = 10.0\nschedule = [[8, 12, "r1", "r2"]]'
    text = fleet_text("late", STEPS, [0.0, 4.0], objects, communication=comm)
    scenario = parse_scenario(text, "late.toml")
    methods = ["local", "distributed", "centralized", "received"]
    for step in (7, STEPS):
        result = run_single(scenario, methods, 5, BeliefConfig(), snapshot_step=step)
        for robot in scenario.robot_ids:
            known = {m: set(result.snapshots[m][robot].object_ids) for m in methods}
            assert known["received"] == known["distributed"], (step, robot)
            assert known["centralized"] == {1, 2, 3, 4}
            if step == 7:
                assert known["received"] == known["local"] != known["centralized"]
            else:
                assert known["received"] == known["centralized"] != known["local"]
    d = result.metrics["distributed"]
    assert np.nanmax(d["class_gap_received"]) < 0.02
    assert np.nanmax(d["class_gap_central"]) > 0.1
    assert np.isnan(result.metrics["received"]["class_gap_received"]).all()
    assert np.isfinite(result.metrics["received"]["robot_error"]).all()

    with pytest.raises(ValueError, match="add distributed"):
        run_single(scenario, ["local", "received"], 5, BeliefConfig())
    argv = ["study", "--scenario", "paper", "--methods", "local,received", "--runs", "1"]
    with pytest.raises(SystemExit) as refused:  # argparse's own refusal, as one line
        main(argv)
    assert refused.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "add distributed" in err, err


def test_study_without_ids_associates_on_each_robot_and_across_the_fleet() -> None:
    """``--ids none``: each robot's association and each D's mapping of peers' objects scored
    against the truth; the maps scored through each map object's true object, close to the same
    run with given ids; a centralized belief is refused in one line."""
    paper = load_scenario("paper")
    methods = ["local", "distributed"]
    none = run_single(paper, methods, 0, BeliefConfig(), detector=Detector("none"))
    given = run_single(paper, methods, 0, BeliefConfig())
    a = none.association["local"]
    assert a["matched"] > 150 and a["right"] >= 0.98 * a["matched"]
    assert a["right"] >= 0.95 * a["matchable"] and a["confirmed_clutter"] == 0
    assert not given.association and len(none.association_ms["local"]) == 3 * paper.steps
    f = none.fleet_association["distributed"]
    assert f["matched"] >= 30 and f["right"] == f["matched"] and f["right"] >= 0.9 * f["matchable"]
    assert not given.fleet_association
    for method in methods:
        for metric in ("object_error", "robot_error"):
            ours, theirs = (np.nanmean(r.metrics[method][metric][:, -1]) for r in (none, given))
            assert ours < 1.5 * theirs + 0.05, (method, metric, ours, theirs)
    with pytest.raises(ValueError, match="would need an association of its own"):
        run_single(paper, ["local", "centralized"], 0, BeliefConfig(), detector=Detector("local"))
    doc = study_archive("paper", [none], methods).document()
    assert doc["methods"]["local"]["association"]["precision"] >= 0.98
    assert doc["methods"]["distributed"]["fleet_association"]["precision"] == 1.0


def test_study_with_given_ids_and_clutter_writes_its_report(tmp_path: Path) -> None:
    """``--ids global --clutter R``: false detections come with ids of objects no world holds;
    the study scores, archives and plots them (it crashed drawing the hypotheses plot)."""
    out = tmp_path / "out"
    argv = ["study", "--scenario", "paper", "--methods", "local", "--runs", "1", "--out", str(out)]
    assert main([*argv, "--ids", "global", "--clutter", "0.3", "--miss", "0.1"]) == 0
    assert (out / "hypotheses.png").stat().st_size > 0 and (out / "results.npz").exists()
    doc = json.loads((out / "results.json").read_text())
    assert np.isfinite(doc["methods"]["local"]["mean"]["object_error"]).all()


def test_class_evidence_off_is_the_geometry_alone_baseline_on_twins(tmp_path: Path) -> None:
    """Objects with a twin 0.3 m away of another class (``--twins``): the robots' association
    on geometry alone (``--class-evidence off``) merges at least half as many again as with the
    class scores; the setting is in results.json, and refused with given ids."""
    from sim.generate import generate_scenario

    world = generate_scenario(2, 15, 3, seed=5, steps=80, area=14.0, twins=0.3)
    merges = {}
    for on in (True, False):
        r = run_single(
            world, ["local"], 0, BeliefConfig(), detector=Detector("none"), class_evidence=on
        )
        merges[on] = r.association["local"]["wrong_merges"]
    assert merges[False] >= 1.5 * merges[True] > 0, merges
    argv = ["study", "--scenario", "paper", "--methods", "local", "--runs", "1"]
    out = tmp_path / "off"
    assert main([*argv, "--ids", "none", "--class-evidence", "off", "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["association"] == {"class_evidence": False}
    assert main([*argv, "--class-evidence", "off", "--out", str(tmp_path / "global")]) == 2
    assert not (tmp_path / "global").exists()


def test_confirmable_is_a_given_id_reference_and_needs_global_ids(tmp_path: Path) -> None:
    """``--confirmable``: given ids on the detections each robot's association could confirm
    (``sim.confirmable``); the rule is in results.json, and other id kinds are refused."""
    argv = ["study", "--scenario", "paper", "--methods", "local", "--runs", "1"]
    out = tmp_path / "ref"
    assert main([*argv, "--miss", "0.3", "--confirmable", "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["detector"]["confirmable"] == {"confirm": 3, "drop_after": 3, "forget_after": 50}
    assert main([*argv, "--ids", "none", "--confirmable", "--out", str(tmp_path / "no")]) == 2
    assert not (tmp_path / "no").exists()


def test_associate_on_fused_gives_each_fleet_its_own_guided_robots(tmp_path: Path) -> None:
    """Frames without ids: with ``--associate-on fused`` each fleet robot's association gates
    on its node's D, so the fleet's robots are scored on their own (``association`` of
    ``distributed``) beside ``local``'s robots alone; ``local`` is the shared L (only ``local``
    scored). The choice is in results.json when not the default, and refused with given ids."""
    paper = load_scenario("paper")
    detector = Detector("none", clutter=0.05)
    runs = {
        on: run_single(
            paper, ["local", "distributed"], 3, BeliefConfig(), detector=detector, associate_on=on
        )
        for on in ASSOCIATE_ON
    }
    fused, alone = runs["fused"], runs["local"]
    assert set(fused.association) == {"local", "distributed"} and set(alone.association) == {
        "local"
    }
    assert fused.association["local"] == alone.association["local"]  # the robot alone, both ways
    np.testing.assert_array_equal(
        fused.metrics["local"]["robot_error"], alone.metrics["local"]["robot_error"]
    )
    guided = fused.association["distributed"]
    assert guided["right"] >= 0.95 * guided["matched"] > 0 and guided["confirmed"] >= 10
    with pytest.raises(ValueError, match="associate_on must be one of"):
        run_single(paper, ["local"], 0, BeliefConfig(), detector=detector, associate_on="D")
    argv = ["study", "--scenario", "paper", "--methods", "local,distributed", "--runs", "1"]
    other = ASSOCIATE_ON[1]
    out = tmp_path / "other"
    assert main([*argv, "--ids", "none", "--associate-on", other, "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert doc["association"] == {"associate_on": other}
    assert main([*argv, "--associate-on", other, "--out", str(tmp_path / "given")]) == 2


def test_given_ids_share_one_l_per_robot_whatever_associate_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Only frames without global ids are associated: with given ids (clutter included) the
    fleets step the very L ``local`` does, one per robot, not one per fleet (a run of L per
    fleet doubled D's step time with the same results)."""
    import agents.node

    made: list[str] = []
    original = agents.node.LocalTrack.__init__

    def counting(self: agents.node.LocalTrack, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        made.append(self.robot)

    monkeypatch.setattr(agents.node.LocalTrack, "__init__", counting)
    paper = load_scenario("paper")
    methods = ["local", "distributed"]
    run_single(paper, methods, 0, BeliefConfig(), detector=Detector(clutter=0.1))
    assert sorted(made) == sorted(paper.robot_ids)
    made.clear()
    run_single(paper, methods, 0, BeliefConfig(), detector=Detector("none"))
    assert sorted(made) == sorted(paper.robot_ids * 2)  # local's, and the fleet's own
