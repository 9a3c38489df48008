"""The `semfleet` command, run as a real process: outputs, files written and exit codes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SEMFLEET = Path(sys.executable).with_name("semfleet")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def semfleet(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(SEMFLEET), *args],
        capture_output=True,
        text=True,
        timeout=600,  # a guard against hangs, not a speed check
        cwd=cwd,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )


def test_console_script_installed() -> None:
    assert SEMFLEET.exists(), f"{SEMFLEET} missing: is the package installed (pip install -e .)?"


def test_scenario_show_paper_lists_robots_sightings_and_edges() -> None:
    r = semfleet("scenario", "show", "paper")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for text in ("r1", "r2", "r3", "first sighting", "k = 1", "k = 3", "r2–r3", "6–60", "13–60"):
        assert text in out, text
    # object 7 is only ever seen by r1, first at step 1
    assert "r1@1" in out


def test_scenario_show_applies_variants_and_overrides() -> None:
    r = semfleet("scenario", "show", "paper", "--variant", "comm10", "--set", "sensor.range=10")
    assert r.returncode == 0, r.stderr
    assert "variants applied: comm10" in r.stdout
    assert "50°, 10 m" in r.stdout
    assert "mode range" in r.stdout


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["scenario", "show", "nonexistent.toml"], "nonexistent.toml: no such scenario file"),
        (["scenario", "show", "nonesuch"], "not a file and not a bundled scenario"),
        (["scenario", "show", "paper", "--variant", "nope"], "no variant 'nope'"),
        (["scenario", "show", "paper", "--set", "sensor.range=-1"], "sensor.range: -1 must be > 0"),
        (["scenario", "show", "paper", "--set", "bogus"], "expected FIELD=VALUE"),
        (["scenario", "plot", "paper", "-o", "x.png", "--cones", "99"], "outside 0..60"),
    ],
)
def test_cli_user_errors_are_one_clear_line(tmp_path: Path, args: list[str], fragment: str) -> None:
    r = semfleet(*args, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert fragment in r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0, r.stderr


def test_cli_bad_scenario_file_names_the_field(tmp_path: Path) -> None:
    text = (Path(__file__).parents[2] / "sim" / "scenarios" / "paper.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(
        text.replace(
            "id = 15\npose = [-2.5, 2.0, 0.0]\nclass = 2",
            "id = 15\npose = [-2.5, 2.0, 0.0]\nclass = 3",
        )
    )
    r = semfleet("scenario", "show", str(bad))
    assert r.returncode == 2
    assert f"{bad}: objects[14].class: 3 is out of range 1..2" in r.stderr


def test_scenario_plot_writes_png(tmp_path: Path) -> None:
    out = tmp_path / "sub" / "truth.png"
    r = semfleet("scenario", "plot", "paper", "-o", str(out), "--cones", "1", "30")
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert out.stat().st_size > 20_000


def test_scenario_plot_default_cones_fit_a_world_shorter_than_60_steps(tmp_path: Path) -> None:
    out = tmp_path / "short.png"
    r = semfleet("scenario", "plot", "lanes:short", "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:8] == PNG_MAGIC


def test_scenario_generate_then_show(tmp_path: Path) -> None:
    out = tmp_path / "world.toml"
    r = semfleet(
        "scenario",
        "generate",
        "--robots",
        "4",
        "--objects",
        "25",
        "--classes",
        "3",
        "--seed",
        "5",
        "-o",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    shown = semfleet("scenario", "show", str(out))
    assert shown.returncode == 0, shown.stderr
    assert "random-r4-o25-c3-s5" in shown.stdout
    again = tmp_path / "again.toml"
    semfleet(
        "scenario",
        "generate",
        "--robots",
        "4",
        "--objects",
        "25",
        "--classes",
        "3",
        "--seed",
        "5",
        "-o",
        str(again),
    )
    assert again.read_text() == out.read_text()


def test_scenario_generate_rejects_bad_arguments(tmp_path: Path) -> None:
    r = semfleet(
        "scenario",
        "generate",
        "--robots",
        "0",
        "--objects",
        "5",
        "--classes",
        "2",
        "--seed",
        "1",
        "-o",
        str(tmp_path / "x.toml"),
    )
    assert r.returncode == 2
    assert "must be a positive integer" in r.stderr


def test_demo_launches_three_agents_over_zenoh_and_prints_the_final_table(tmp_path: Path) -> None:
    r = semfleet("demo", "--out", str(tmp_path / "demo"))
    assert r.returncode == 0, r.stderr
    assert "launching 3 agent processes" in r.stdout
    assert "final step k = 60" in r.stdout
    demo = tmp_path / "demo"
    for png in ("paper-ground-truth.png", "msde.png", "robot_error.png"):
        assert (demo / png).read_bytes()[:8] == PNG_MAGIC, png
    doc = json.loads((demo / "results.json").read_text())
    assert set(doc["methods"]) == {"local", "distributed"}
    final = {m: doc["methods"][m]["mean"]["msde"][-1] for m in ("local", "distributed")}
    assert final["distributed"] < final["local"]  # the paper's result, seed 0
    for robot in ("r1", "r2", "r3"):  # every agent really ran as its own process, with a log
        assert "up at step 0" in (demo / "logs" / f"{robot}.log").read_text()
