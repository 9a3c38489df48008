"""`semfleet scenario` helpers and commands, run in this process (no subprocess)."""

from __future__ import annotations

from pathlib import Path

import pytest

from deploy.cli.main import main
from deploy.study.scenario_show import default_cone_steps
from sim.generate import dump_scenario
from sim.loader import load_scenario
from sim.robot_model import load_robot_model


@pytest.mark.parametrize(
    ("steps", "cones"),
    [(60, [20, 40, 60]), (56, [19, 37, 56]), (18, [6, 12, 18]), (2, [1, 2]), (1, [1])],
)
def test_default_cone_steps_evenly_spaced_ending_at_the_last_step(
    steps: int, cones: list[int]
) -> None:
    assert default_cone_steps(steps) == cones


def test_scenario_model_writes_a_file_that_loads_to_the_scenarios_model(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "robot" / "paper-model.toml"
    assert main(["scenario", "model", "paper", "-o", str(out)]) == 0
    assert load_robot_model(out) == load_scenario("paper").robot_model()
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed
    assert "[classifier]" in printed and 'model = "paper"' in printed


def test_scenario_model_applies_variants_and_overrides(tmp_path: Path) -> None:
    out = tmp_path / "model.toml"
    args = ["scenario", "model", "paper", "--variant", "experiment", "--set", "sensor.range=7"]
    assert main([*args, "-o", str(out)]) == 0
    expected = load_scenario("paper", ["experiment"], {"sensor.range": 7}).robot_model()
    assert load_robot_model(out) == expected
    assert expected.odometry_noise.variances == (0.0003, 0.0003, 0.0001)
    assert expected.sensor.range == 7.0


def test_scenario_model_of_one_robot_takes_its_own_sensor(tmp_path: Path) -> None:
    text = dump_scenario(load_scenario("paper")).replace(
        'id = "r2"', 'id = "r2"\nsensor = { half_angle_deg = 30.0, range = 2.0 }'
    )
    world = tmp_path / "world.toml"
    world.write_text(text, encoding="utf-8")
    out = tmp_path / "r2.toml"
    assert main(["scenario", "model", str(world), "--robot", "r2", "-o", str(out)]) == 0
    assert load_robot_model(out).sensor.range == 2.0
    assert load_robot_model(out) == load_scenario(world).robot_model("r2")


def test_scenario_model_refuses_to_overwrite_without_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "model.toml"
    out.write_text("keep me\n", encoding="utf-8")
    assert main(["scenario", "model", "paper", "-o", str(out)]) == 2
    assert out.read_text(encoding="utf-8") == "keep me\n"
    assert f"{out}: already exists (--force overwrites it)" in capsys.readouterr().err
    assert main(["scenario", "model", "lanes", "-o", str(out), "--force"]) == 0
    assert load_robot_model(out) == load_scenario("lanes").robot_model()


def test_scenario_model_unknown_robot_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "model.toml"
    assert main(["scenario", "model", "paper", "--robot", "r9", "-o", str(out)]) == 2
    assert "--robot: 'r9' is not a robot of paper (r1, r2, r3)" in capsys.readouterr().err
    assert not out.exists()
