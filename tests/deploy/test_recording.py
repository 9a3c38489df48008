"""`--record FILE.rrd` and `--view` of `launch`, `chaos` and `demo` (deploy/launch/rerun_view.py):
runs recorded as real processes and read back with Rerun's own reader; no display, no network."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from deploy.base.errors import UsageError
from deploy.cli.main import main
from deploy.launch.rerun_layout import COUNTER_PLOTS, top_down_eye
from deploy.launch.rerun_view import (
    ellipses,
    has_display,
    import_rerun,
    link_strips,
    open_log,
)
from sim.loader import load_scenario
from tests.deploy.test_launch import world_text
from tests.tolerance import assert_close

rerun_chunk = pytest.importorskip("rerun.chunk", reason="the optional extra `view` (rerun-sdk)")

SEMFLEET = Path(sys.executable).with_name("semfleet")
STEPS = 3
# Rerun stores positions as float32: a few metres to within 1e-6 relative.
F32_ATOL = 1e-5
Recording = dict[str, dict[int | None, dict[str, Any]]]
_SKIP = {"log_time", "rerun.controls.RowId"}


def semfleet(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SEMFLEET), *args],
        capture_output=True,
        text=True,
        timeout=600,  # a guard against hangs
        cwd=cwd,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},  # no DISPLAY
    )


def read_recording(path: Path) -> Recording:
    """entity path → step (None: static) → component column → value of the last row."""
    out: Recording = {}
    for chunk in rerun_chunk.RrdReader(path).store().stream():
        entity = str(chunk.entity_path).lstrip("/")
        if entity.startswith("__"):  # the recording's properties
            continue
        batch = chunk.to_record_batch()
        rows = batch.select([c for c in batch.schema.names if c not in _SKIP]).to_pydict()
        steps = rows.pop("step", [None] * chunk.num_rows)
        for i, k in enumerate(steps):
            cells = out.setdefault(entity, {}).setdefault(k, {})
            cells.update({column: values[i] for column, values in rows.items()})
    return out


def _position(rec: Recording, path: str, k: int) -> np.ndarray:
    return np.array(rec[path][k]["Points3D:positions"][0], dtype=float)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    site = tmp_path_factory.mktemp("site")
    (site / "pair.toml").write_text(world_text("pair", 2, 3.0, 4, 0.1), encoding="utf-8")
    return site


def test_launch_record_holds_every_step_as_the_conductor_received_it(site: Path) -> None:
    r = semfleet("launch", "--scenario", "pair.toml", "--steps", str(STEPS), "--out", "run",
                 "--record", "run/pair.rrd", cwd=site)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "recorded the run in run/pair.rrd (open it with: rerun run/pair.rrd)" in r.stdout
    rec = read_recording(site / "run" / "pair.rrd")
    results = np.load(site / "run" / "results.npz")
    steps = set(range(1, STEPS + 1))
    truth_objects = rec["world/truth/objects"][None]
    assert len(truth_objects["Points3D:positions"]) == 4  # two objects ahead of each robot
    for i, robot in enumerate(("r1", "r2")):
        for belief in ("truth", "local", "distributed"):
            path = f"world/robots/{robot}/{belief}"
            for part in ("", "/heading", "/trail"):
                assert set(rec[path + part]) == steps, path + part
        assert set(rec[f"world/robots/{robot}/distributed/cov"]) == steps
        counters = rec[f"robots/{robot}/counters/frames_processed"]
        assert {k: counters[k]["Scalars:scalars"] for k in steps} == {k: [k] for k in steps}
        # Every counter the layout's plots name is one the agents publish (a renamed counter
        # would leave its plot empty).
        for _, names in COUNTER_PLOTS:
            for name in names:
                assert set(rec[f"robots/{robot}/counters/{name}"]) == steps, name
        # D's labels are shown, L's only on hover (they would hide D's).
        for belief, shown in (("distributed", True), ("local", False)):
            for part in ("", "/objects"):
                cells = rec[f"world/robots/{robot}/{belief}{part}"][STEPS]
                assert cells["Points3D:show_labels"] == [shown], (belief, part)
        for k in steps:
            # The D pose is the mixture mean the conductor scored from the estimate it received.
            want = results["distributed/robot_pose"][0, i, k - 1, :2]
            got = _position(rec, f"world/robots/{robot}/distributed", k)
            assert_close(got, [*want, 0.0], atol=F32_ATOL, what=f"{robot} D at step {k}")
            truth = results["true_robot_pose"][0, i, k - 1, :2]
            assert_close(_position(rec, f"world/robots/{robot}/truth", k), [*truth, 0.0],
                         atol=F32_ATOL, what=f"{robot} truth at step {k}")  # fmt: skip
        objects = rec[f"world/robots/{robot}/distributed/objects"][STEPS]
        assert objects["Points3D:labels"] and all(
            " class " in label and label.endswith(")") for label in objects["Points3D:labels"]
        )
        classes = rec[f"robots/{robot}/distributed/classes"][STEPS]
        prob = np.array(classes["Tensor:data"][0]["buffer"], dtype=float)
        assert_close(prob.reshape(len(objects["Points3D:labels"]), -1).sum(axis=1), 1.0)
    # 3 m apart, 10 m range: the two robots hear each other at every step.
    assert {k: rec["world/links"][k]["LineStrips3D:labels"] for k in steps} == {
        k: ["r1↔r2"] for k in steps
    }


def test_chaos_records_its_realtime_run(site: Path) -> None:
    args = ["--steps", "2", "--period", "0.3", "--partition", "r1:1-2", "--out", "chaos"]
    r = semfleet("chaos", "--scenario", "pair.toml", *args, "--record", "chaos.rrd", cwd=site)
    assert r.returncode == 0, r.stderr[-3000:]
    rec = read_recording(site / "chaos.rrd")
    assert set(rec["world/robots/r2/truth"]) == {1, 2}
    # Partitioned: no link at either step, and an empty batch clears the last one shown.
    assert [rec["world/links"][k].get("LineStrips3D:labels") for k in (1, 2)] == [[], []]
    # Realtime estimates are logged at their own step whenever they came in, the last ones after
    # the last step: every estimate the conductor scored, none else.
    results = np.load(site / "chaos" / "results.npz")
    for i, robot in enumerate(("r1", "r2")):
        scored = np.flatnonzero(~np.isnan(results["distributed/robot_pose"][0, i, :, 0])) + 1
        assert len(scored) and set(rec[f"world/robots/{robot}/distributed"]) == set(scored)


@pytest.mark.parametrize(
    "command",
    [["launch", "--scenario", "pair.toml"], ["demo"], ["chaos", "--scenario", "pair.toml"]],
)
def test_view_without_a_display_is_one_line_before_anything_starts(
    site: Path, command: list[str]
) -> None:
    """One line and nothing else: demo printed its 60 lines of scenario before it (issue 46)."""
    r = semfleet(*command, "--out", "view", "--view", cwd=site)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "--view: no display here" in r.stderr, r.stderr
    assert r.stdout == "" and not (site / "view").exists(), r.stdout


def test_view_and_record_together_are_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--view", "--record", "x.rrd"])
    assert exc.value.code == 2 and "not allowed with argument" in capsys.readouterr().err


def test_chaos_attack_refuses_record(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["chaos", "--scenario", "paper", "--attack", "all", "--record", "x.rrd"]) == 2
    assert "--view/--record: not with --attack" in capsys.readouterr().err


def test_record_into_an_unwritable_place_is_a_usage_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("", encoding="utf-8")
    scenario = load_scenario("paper")
    with pytest.raises(UsageError, match=r"--record .*file/x.rrd: cannot write there"):
        open_log(False, tmp_path / "file" / "x.rrd", "t", scenario, scenario.robot_ids)


def test_import_rerun_missing_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(UsageError, match=r"pip install 'semfleet\[view\]'"):
        import_rerun()


@pytest.mark.parametrize(
    ("environ", "platform", "expected"),
    [
        ({}, "linux", False),
        ({"DISPLAY": ""}, "linux", False),
        ({"DISPLAY": ":0"}, "linux", True),
        ({"WAYLAND_DISPLAY": "wayland-0"}, "linux", True),
        ({}, "darwin", True),
    ],
)
def test_has_display(environ: Mapping[str, str], platform: str, expected: bool) -> None:
    assert has_display(environ, platform) is expected


def test_ellipses_reach_nsigma_along_the_principal_axes() -> None:
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 9.0]]])
    rings = ellipses(np.array([[1.0, 2.0], [0.0, 0.0]]), cov, nsigma=2.0)
    assert rings.shape[0] == 2 and rings.shape[2] == 2
    assert_close(rings[:, 0], rings[:, -1])  # closed
    assert_close(np.abs(rings[0] - [1.0, 2.0]).max(axis=0), [4.0, 2.0], atol=1e-2)
    assert_close(np.abs(rings[1]).max(axis=0), [2.0, 6.0], atol=1e-2)


def test_link_strips_label_both_ways_and_one_way() -> None:
    positions = {r: np.array([x, 0.0, 0.0]) for r, x in (("a", 0.0), ("b", 1.0), ("c", 2.0))}
    verdict = {"a": ("b",), "b": ("a", "c"), "c": ()}
    strips, labels = link_strips(verdict, positions)
    assert labels == ["a↔b", "c→b"]
    assert_close(strips[1], [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])


def test_the_fleet_view_looks_down_on_the_middle_of_the_world_from_above_it() -> None:
    rr = import_rerun()
    scenario = load_scenario("paper")
    starts = np.array([r.start[:2] for r in scenario.robots])
    points = np.concatenate([starts, scenario.object_poses()[:, :2]])
    middle = (points.min(axis=0) + points.max(axis=0)) / 2.0
    eye = top_down_eye(rr.blueprint, scenario)
    target = np.array(eye.look_target.as_arrow_array().to_pylist()[0])
    position = np.array(eye.position.as_arrow_array().to_pylist()[0])
    assert_close(target, [*middle, 0.0], atol=1e-9, what="look target")
    extent = float(np.max(points.max(axis=0) - points.min(axis=0)))
    # Looking down (a slight tilt towards +y): everything within ±45° of the view axis.
    assert position[2] >= extent and abs(position[0] - middle[0]) < 1e-9
    assert 0.0 < middle[1] - position[1] < 0.1 * position[2]
