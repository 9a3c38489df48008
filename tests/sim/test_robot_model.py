"""Robot model files: a scenario's model written and read back exactly, the scenario format's
validation of [classes], [classifier], [noise] and [sensor] with the model file named, and the
scenario's default sensor."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from sim.generate import dump_scenario, generate_scenario
from sim.loader import bundled_names, load_scenario, parse_scenario
from sim.robot_model import RobotModel, dump_robot_model, load_robot_model, parse_robot_model
from sim.scenario import ScenarioError, Sensor

LABEL = "model.toml"

TABLES = """\
[classes]
count = 2
prior = [0.5, 0.5]

[classifier]
model = "paper"

[noise]
odometry_var = [0.003, 0.003, 0.001]
geometric_var = [0.1, 0.1, 0.01]

[sensor]
half_angle_deg = 50.0
range = 3.5
"""
MODEL = "format = 1\n\n" + TABLES
# The same tables inside a scenario: every edit below must fail there with the same field.
SCENARIO = f"""\
format = 1
name = "one"
steps = 2

{TABLES}
[communication]
mode = "range"
range = 10.0

[[robots]]
id = "a"
start = [0.0, 0.0, 0.0]
turns = [[2, 0.0]]

[[objects]]
id = 1
pose = [1.0, 0.0, 0.0]
class = 1
"""
ALIASED = 'model = "aliased"\nalias = [2, 1]\nbest_view_deg = [90.0, -90.0]\nnoise_std = 0.3'


def _variant_sources() -> list[str]:
    """Every bundled scenario, alone and with each of its variants."""
    out = []
    for name in bundled_names():
        out.append(name)
        out += [f"{name}:{v.name}" for v in load_scenario(name).variants]
    return out


@pytest.mark.parametrize("source", _variant_sources())
def test_robot_model_of_bundled_scenario_round_trips(source: str) -> None:
    s = load_scenario(source)
    for robot in (None, *s.robot_ids):
        model = s.robot_model(robot)
        assert parse_robot_model(dump_robot_model(model), LABEL) == model, robot


@pytest.mark.parametrize("source", _variant_sources())
def test_robot_model_carries_the_scenario_tables(source: str) -> None:
    s = load_scenario(source)
    model = s.robot_model()
    assert model.num_classes == s.num_classes
    assert model.class_prior == s.class_prior
    assert model.classifier == s.classifier
    assert model.odometry_noise == s.odometry_noise
    assert model.geometric_noise == s.geometric_noise
    assert model.sensor == s.sensor


@pytest.mark.parametrize(("seed", "classes"), [(0, 2), (1, 3), (2, 5), (3, 8)])
def test_robot_model_of_generated_aliased_world_round_trips(seed: int, classes: int) -> None:
    model = generate_scenario(robots=2, objects=5, classes=classes, seed=seed).robot_model()
    assert model.classifier.model == "aliased"
    assert parse_robot_model(dump_robot_model(model), LABEL) == model


def test_dump_robot_model_round_trips_any_half_angle_read_from_a_file() -> None:
    # math.degrees then math.radians misses ~5 % of angles by one ulp; the writer picks the
    # degree value that reads back to the very same radians.
    rng = np.random.default_rng(11)
    base = parse_robot_model(MODEL, LABEL)
    for half_deg in map(float, rng.uniform(0.01, 180.0, size=400)):
        model = parse_robot_model(
            MODEL.replace("half_angle_deg = 50.0", f"half_angle_deg = {half_deg!r}"), LABEL
        )
        assert model.sensor.half_angle == math.radians(half_deg)
        assert parse_robot_model(dump_robot_model(model), LABEL) == model, half_deg
    assert base.sensor == Sensor(math.radians(50.0), 3.5)


def test_load_robot_model_reads_a_written_file(tmp_path: Path) -> None:
    model = load_scenario("lanes").robot_model()
    path = tmp_path / "lanes-model.toml"
    path.write_text(dump_robot_model(model), encoding="utf-8")
    assert load_robot_model(path) == model
    assert load_robot_model(str(path)) == model


def test_load_robot_model_missing_file_names_it(tmp_path: Path) -> None:
    path = tmp_path / "absent.toml"
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(path))}: no such robot model file$"):
        load_robot_model(path)


def test_load_robot_model_error_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(MODEL.replace("range = 3.5", "range = -1.0"), encoding="utf-8")
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(path))}: sensor\.range: "):
        load_robot_model(path)


def _edit(text: str, edits: list[tuple[str, str]]) -> str:
    for old, new in edits:
        assert text.count(old) == 1, f"edit target {old!r} is not unique"
        text = text.replace(old, new)
    return text


# (id, edits to the shared tables, field, reason)
SHARED_CASES = [
    ("count-string", [("count = 2", 'count = "2"')], "classes.count", "expected an integer"),
    ("count-bool", [("count = 2", "count = true")], "classes.count", "got a boolean"),
    ("count-one", [("count = 2\nprior = [0.5, 0.5]", "count = 1")], "classes.count", "must be ≥ 2"),
    (
        "prior-sum",
        [("prior = [0.5, 0.5]", "prior = [0.5, 0.6]")],
        "classes.prior",
        "must sum to 1, sums to 1.1",
    ),
    (
        "prior-length",
        [("prior = [0.5, 0.5]", "prior = [1.0]")],
        "classes.prior",
        "expected 2 numbers, got 1",
    ),
    (
        "prior-zero",
        [("prior = [0.5, 0.5]", "prior = [1.0, 0.0]")],
        "classes.prior[1]",
        "must be > 0",
    ),
    (
        "classes-unknown-key",
        [("count = 2", "count = 2\nnames = 3")],
        "classes.names",
        "unknown key",
    ),
    ("model-unknown", [('model = "paper"', 'model = "gp"')], "classifier.model", "unknown model"),
    (
        "paper-with-extra-key",
        [('model = "paper"', 'model = "paper"\nnoise_std = 0.3')],
        "classifier.noise_std",
        "unknown key",
    ),
    (
        "noise-std-negative",
        [('model = "paper"', ALIASED.replace("0.3", "-0.3"))],
        "classifier.noise_std",
        "-0.3 must be > 0",
    ),
    (
        "noise-std-string",
        [('model = "paper"', ALIASED.replace("0.3", '"high"'))],
        "classifier.noise_std",
        "expected a number, got a string",
    ),
    (
        "self-alias",
        [('model = "paper"', ALIASED.replace("[2, 1]", "[1, 1]"))],
        "classifier.alias[0]",
        "class 1 cannot be its own alias",
    ),
    (
        "best-view-nan",
        [('model = "paper"', ALIASED.replace("-90.0", "nan"))],
        "classifier.best_view_deg[1]",
        "not a finite number",
    ),
    (
        "odometry-negative",
        [("odometry_var = [0.003,", "odometry_var = [-0.003,")],
        "noise.odometry_var[0]",
        "must be > 0",
    ),
    (
        "geometric-length",
        [("geometric_var = [0.1, 0.1, 0.01]", "geometric_var = [0.1, 0.1]")],
        "noise.geometric_var",
        "expected 3 numbers, got 2",
    ),
    (
        "noise-missing",
        [("geometric_var = [0.1, 0.1, 0.01]\n", "")],
        "noise.geometric_var",
        "missing",
    ),
    ("noise-unknown-key", [("[noise]", "[noise]\nsigma = 1.0")], "noise.sigma", "unknown key"),
    ("sensor-unknown-key", [("range = 3.5", "rnage = 3.5")], "sensor.rnage", "unknown key"),
    ("sensor-range-zero", [("range = 3.5", "range = 0")], "sensor.range", "0 must be > 0"),
    (
        "sensor-half-angle-wide",
        [("half_angle_deg = 50.0", "half_angle_deg = 200.0")],
        "sensor.half_angle_deg",
        "200.0 must be ≤ 180",
    ),
]


@pytest.mark.parametrize(
    ("edits", "field", "reason"),
    [pytest.param(e, f, r, id=i) for i, e, f, r in SHARED_CASES],
)
def test_parse_robot_model_error_names_file_and_field(
    edits: list[tuple[str, str]], field: str, reason: str
) -> None:
    with pytest.raises(ScenarioError) as info:
        parse_robot_model(_edit(MODEL, edits), LABEL)
    assert str(info.value).startswith(f"{LABEL}: {field}: "), str(info.value)
    assert reason in info.value.reason
    assert info.value.field == field


@pytest.mark.parametrize("edits", [pytest.param(e, id=i) for i, e, _, _ in SHARED_CASES])
def test_scenario_loader_reports_the_model_errors_identically(
    edits: list[tuple[str, str]],
) -> None:
    with pytest.raises(ScenarioError) as model_error:
        parse_robot_model(_edit(MODEL, edits), LABEL)
    with pytest.raises(ScenarioError) as scenario_error:
        parse_scenario(_edit(SCENARIO, edits), LABEL)
    assert scenario_error.value.field == model_error.value.field
    assert str(scenario_error.value) == str(model_error.value)


def test_parse_robot_model_paper_classifier_names_the_model() -> None:
    edits = [("count = 2\nprior = [0.5, 0.5]", "count = 3")]
    with pytest.raises(ScenarioError) as info:
        parse_robot_model(_edit(MODEL, edits), LABEL)
    assert (
        str(info.value)
        == f"{LABEL}: classifier.model: the paper model has 2 classes, the model has 3"
    )


@pytest.mark.parametrize(
    ("text", "field", "reason"),
    [
        pytest.param(MODEL + '\n[communication]\nmode = "range"\n', "communication", "unknown key",
                     id="scenario-table"),
        pytest.param(MODEL.replace("format = 1", 'format = 1\nname = "x"'), "name", "unknown key",
                     id="top-level-key"),
        pytest.param(MODEL.replace("format = 1\n", ""), "format", "missing required field",
                     id="format-missing"),
        pytest.param(MODEL.replace("format = 1", "format = 2"), "format", "unsupported format 2",
                     id="format-2"),
        pytest.param(MODEL.replace("[sensor]\nhalf_angle_deg = 50.0\nrange = 3.5\n", ""), "sensor",
                     "missing required field", id="sensor-missing"),
        pytest.param(MODEL.replace("[classes]\n", ""), "count", "unknown key",
                     id="classes-header-missing"),
        pytest.param(MODEL.replace("format = 1", "format = 1\nsensor = 3").replace(
                     "[sensor]\nhalf_angle_deg = 50.0\nrange = 3.5\n", ""), "sensor",
                     "expected a table, got an integer", id="sensor-not-a-table"),
    ],
)  # fmt: skip
def test_parse_robot_model_rejects_what_is_not_a_model(text: str, field: str, reason: str) -> None:
    with pytest.raises(ScenarioError) as info:
        parse_robot_model(text, LABEL)
    assert str(info.value).startswith(f"{LABEL}: {field}: "), str(info.value)
    assert reason in str(info.value)


def test_parse_robot_model_invalid_toml_names_the_file() -> None:
    with pytest.raises(ScenarioError, match=r"^model\.toml: not valid TOML: "):
        parse_robot_model(MODEL.replace("count = 2", "count = = 2"), LABEL)


def test_robot_model_of_a_robot_has_its_own_sensor() -> None:
    s = load_scenario("paper")
    own = Sensor(math.radians(30.0), 2.0)
    robots = (s.robots[0], dataclasses.replace(s.robots[1], sensor=own), *s.robots[2:])
    s = dataclasses.replace(s, robots=robots)
    assert s.robot_model("r2").sensor == own
    assert s.robot_model("r1").sensor == s.sensor
    assert s.robot_model().sensor == Sensor(math.radians(50.0), 3.5)
    assert isinstance(s.robot_model(), RobotModel)


def test_scenario_default_sensor_is_the_sensor_table_not_the_first_robot() -> None:
    text = SCENARIO.replace(
        "turns = [[2, 0.0]]",
        "turns = [[2, 0.0]]\n[robots.sensor]\nhalf_angle_deg = 20.0\nrange = 9.0",
    )
    s = parse_scenario(text, LABEL)
    assert s.robots[0].sensor == Sensor(math.radians(20.0), 9.0)
    assert s.sensor == Sensor(math.radians(50.0), 3.5)
    assert s.robot_model().sensor == s.sensor
    back = parse_scenario(dump_scenario(s), LABEL)
    assert back == s
