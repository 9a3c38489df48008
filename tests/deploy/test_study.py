"""`semfleet study` end to end, as real processes on a tiny world, and `run_single` in-process."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.study import run_single
from estimator.hybrid import BeliefConfig
from estimator.metrics import METRICS
from sim.loader import parse_scenario
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
    return {k: v for k, v in arrays.items() if "/" in k and not k.endswith("/step_ms")}


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
    for text in ("robot_nees", "class_log_loss", "hypotheses", "median ms per belief step"):
        assert text in r.stdout, text
    assert "seeds 5..6" in r.stdout


def test_study_writes_results_and_plots(
    two_runs: tuple[subprocess.CompletedProcess[str], Path],
) -> None:
    _, out = two_runs
    assert (out / "results.json").stat().st_size > 0
    assert (out / "results.npz").read_bytes()[:2] == b"PK"
    pngs = [f"{m}.png" for m in CURVE_PLOTS]
    pngs += [f"hypotheses_{m}_r1_k{STEPS}.png" for m in METHODS]
    for name in pngs:
        assert (out / name).read_bytes()[:8] == PNG_MAGIC, name


def test_study_results_json_schema(two_runs: tuple[subprocess.CompletedProcess[str], Path]) -> None:
    _, out = two_runs
    doc = read_json(out)
    assert doc["format"] == 1
    assert doc["scenario"] == "tiny"
    assert doc["runs"] == 2
    assert doc["seeds"] == [5, 6]
    assert doc["steps"] == STEPS
    assert doc["weight_estimator"] == "geo_conditioned"
    assert set(doc["methods"]) == set(METHODS)
    for method, entry in doc["methods"].items():
        assert set(entry["mean"]) == set(METRICS), method
        for metric, curve in entry["mean"].items():
            assert isinstance(curve, list) and len(curve) == STEPS, (method, metric)
            assert all(v is None or isinstance(v, float) for v in curve), (method, metric)
        for key in ("wall_s", "step_ms_median"):
            assert isinstance(entry[key], float) and entry[key] > 0, (method, key)
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
    expected = {f"{m}/{k}" for m in METHODS for k in (*METRICS, "step_ms")} | {"seeds"}
    assert set(arrays) == expected
    for key, values in metric_arrays(arrays).items():
        assert values.shape == (2, ROBOTS, STEPS), key
        assert values.dtype == np.float64, key
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


def test_study_reruns_are_identical(
    world: Path, tmp_path: Path, two_runs: tuple[subprocess.CompletedProcess[str], Path]
) -> None:
    args = ("--methods", "local,centralized", "--runs", "1", "--jobs", "1", "--seed", "6")
    study(world, tmp_path / "a", *args)
    study(world, tmp_path / "b", *args)
    a, b = metric_arrays(read_npz(tmp_path / "a")), metric_arrays(read_npz(tmp_path / "b"))
    assert set(a) == {f"{m}/{k}" for m in METHODS for k in METRICS}
    both = metric_arrays(read_npz(two_runs[1]))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        # a run depends on its seed only, not on its place in a larger study
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
    assert result.seed == 5
    for metric in METRICS:
        local, central = result.metrics["local"][metric], result.metrics["centralized"][metric]
        assert local.shape == (1, STEPS), metric
        np.testing.assert_array_equal(local, central, err_msg=metric)


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
    ],
)
def test_study_user_errors_are_one_clear_line(
    world: Path, tmp_path: Path, args: list[str], fragment: str
) -> None:
    out = tmp_path / "out"
    r = semfleet("study", "--scenario", str(world), "--runs", "1", "--out", str(out), *args)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr
    # argparse's own errors come after its usage lines; ours are the whole of stderr
    errors = [line for line in r.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1, r.stderr
    assert fragment in errors[0]
    assert errors[0] == r.stderr.splitlines()[-1]
    assert not out.exists()


def test_study_user_error_is_one_line_on_a_narrow_terminal(tmp_path: Path) -> None:
    r = semfleet("study", "--scenario", "nonesuch", "--out", str(tmp_path), columns=None)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0, r.stderr
