"""World files: every malformed field is one ScenarioError naming the file and the field."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sim.scenario import ScenarioError
from sim.ufastslam import load_world, parse_world

LABEL = "w.toml"
BASE = """\
format = 1
kind = "ufastslam"
name = "tiny"
dt = 0.5
landmarks = [
  [1, -1.5, 1.0], [2, -1.5, 3.0], [3, 1.5, 2.0], [4, 1.0, 5.0], [5, 2.0, 6.0], [6, 3.0, 7.0],
]

[path]
start = [0.0, 0.0, 1.5707963267948966]
speed = 0.4
turn_rate_deg = 30.0
legs = [{ forward = 4.0 }, { turn_deg = -90.0 }, { forward = 1.0, turn_deg = 10.0 }]

[odometry]
speed_std = 0.02
yaw_rate_std_deg = 0.5
scale_error = 0.03
yaw_rate_bias_deg = 0.15

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
members = [1, 2]

[[groups]]
kind = "col"
name = "diagonal"
members = [4, 5, 6]
"""


def test_base_world_parses() -> None:
    w = parse_world(BASE, LABEL)
    assert w.name == "tiny" and w.source == LABEL and w.description == ""
    assert w.landmark_ids == (1, 2, 3, 4, 5, 6)
    assert w.filter_noise.relation_std == 0.05  # the default σ_s
    assert w.filter_noise.yaw_rate_std == pytest.approx(math.radians(1.5))
    # 4 m at 0.4 m/s, 90° at 30°/s, 1 m while turning 10°: 20 + 6 + 5 steps of 0.5 s
    assert w.steps == 20 + 6 + 5
    assert [g.label for g in w.groups] == ["x:west", "col:diagonal"]


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("format = 1", "format = 2", "w.toml: format: unsupported format 2"),
        (
            'kind = "ufastslam"\n',
            "",
            'w.toml: kind: missing required field (a UFastSLAM world has kind = "ufastslam")',
        ),
        ('kind = "ufastslam"', 'kind = "fleet"', "w.toml: kind: 'fleet': a UFastSLAM world"),
        ("dt = 0.5", "dt = 0", "w.toml: dt: 0 must be > 0"),
        ("dt = 0.5", "dt = true", "w.toml: dt: expected a number, got a boolean"),
        ('name = "tiny"', 'name = "tiny"\ncolour = 1', "w.toml: colour: unknown key"),
        ("speed = 0.4", 'speed = "fast"', "w.toml: path.speed: expected a number, got a string"),
        (
            "start = [0.0, 0.0, 1.5707963267948966]",
            "start = [0.0, 0.0]",
            "w.toml: path.start: expected 3 numbers, got 2",
        ),
        (
            "legs = [{ forward = 4.0 },",
            "legs = [{},",
            "w.toml: path.legs[0]: give 'forward' (m), 'turn_deg' or both",
        ),
        (
            "{ forward = 4.0 }",
            "{ forward = -4.0 }",
            "w.toml: path.legs[0].forward: -4.0 must be ≥ 0",
        ),
        ("{ forward = 4.0 }", "{ backward = 4.0 }", "w.toml: path.legs[0].backward: unknown key"),
        ("{ forward = 4.0 }", "{ forward = 0.0 }", "w.toml: path.legs[0]: a leg must move or turn"),
        (
            "{ turn_deg = -90.0 }",
            "{ turn_deg = nan }",
            "w.toml: path.legs[1].turn_deg: nan is not a finite number",
        ),
        ("[3, 1.5, 2.0]", "[3, 1.5]", "w.toml: landmarks[2]: expected [id, x, y], got 2 values"),
        ("[3, 1.5, 2.0]", "[1, 1.5, 2.0]", "w.toml: landmarks[2][0]: duplicate landmark id 1"),
        ("[3, 1.5, 2.0]", "[-3, 1.5, 2.0]", "w.toml: landmarks[2][0]: -3 must be ≥ 0"),
        (
            "[3, 1.5, 2.0]",
            '[3, "a", 2.0]',
            "w.toml: landmarks[2][1]: expected a number, got a string",
        ),
        ('kind = "x"', 'kind = "z"', "w.toml: groups[0].kind: unknown kind 'z' (known: x, y, col)"),
        ('name = "west"', 'name = "west wall"', "w.toml: groups[0].name: 'west wall' must be 1–64"),
        ('name = "diagonal"', 'name = "west"\nkind = "x"', "w.toml"),
        (
            "members = [1, 2]",
            "members = [1, 99]",
            "w.toml: groups[0].members[1]: unknown landmark 99",
        ),
        (
            "members = [1, 2]",
            "members = [1, 1]",
            "w.toml: groups[0].members[1]: landmark 1 listed twice",
        ),
        (
            "members = [1, 2]",
            "members = [1, 3]",
            "w.toml: groups[0].members[1]: landmark 3 is 3 m off the group's x coordinate",
        ),
        (
            "members = [1, 2]",
            "members = [1]",
            "w.toml: groups[0].members: a x group needs at least 2 landmarks",
        ),
        (
            "members = [4, 5, 6]",
            "members = [4, 5]",
            "w.toml: groups[1].members: a col group needs at least 3 landmarks",
        ),
        (
            "members = [4, 5, 6]",
            "members = [4, 5, 3]",
            "w.toml: groups[1].members[0]: landmark 4 is 0.868 m off the group's line",
        ),
        (
            "half_angle_deg = 35.0",
            "half_angle_deg = 200.0",
            "w.toml: sensor.half_angle_deg: 200.0 must be ≤ 180",
        ),
        ("range_std = 0.15", "range_std = -0.15", "w.toml: sensor.range_std: -0.15 must be > 0"),
        ("bearing_std_deg = 2.0\n", "", "w.toml: sensor.bearing_std_deg: missing required field"),
        (
            "scale_error = 0.03",
            "scale_error = 0.7",
            "w.toml: odometry.scale_error: 0.7 must be within",
        ),
        ("speed_std = 0.02", "speed_std = -1.0", "w.toml: odometry.speed_std: -1.0 must be ≥ 0"),
        (
            "yaw_rate_std_deg = 1.5",
            "yaw_rate_std_deg = 1.5\nrelation_std = 0",
            "w.toml: filter.relation_std: 0 must be > 0",
        ),
        (
            "[filter]",
            "[filters]",
            "w.toml: filters: unknown key (allowed here: description, dt, filter,",
        ),
        (
            "[filter]\nspeed_std = 0.04\nyaw_rate_std_deg = 1.5\n",
            "",
            "w.toml: filter: missing required field",
        ),
        ("dt = 0.5", "dt = [", "w.toml: not valid TOML"),
    ],
)
def test_malformed_world_names_the_field(old: str, new: str, message: str) -> None:
    assert old in BASE, old
    with pytest.raises(ScenarioError) as info:
        parse_world(BASE.replace(old, new, 1), LABEL)
    assert message in str(info.value), str(info.value)


def test_a_world_needs_landmarks() -> None:
    start = BASE.index("landmarks = [")
    end = BASE.index("],\n]\n", start) + 4
    with pytest.raises(
        ScenarioError, match=r"w\.toml: landmarks: at least one landmark is required"
    ):
        parse_world(BASE[:start] + "landmarks = []" + BASE[end:], LABEL)


def test_duplicate_group_names_are_rejected() -> None:
    text = BASE + '\n[[groups]]\nkind = "x"\nname = "west"\nmembers = [1, 2]\n'
    with pytest.raises(ScenarioError, match=r"w.toml: groups\[2\].name: duplicate group x:west"):
        parse_world(text, LABEL)


def test_load_world_by_name_and_file(tmp_path: Path) -> None:
    path = tmp_path / "tiny.toml"
    path.write_text(BASE, encoding="utf-8")
    assert load_world(path).source == str(path)
    assert load_world("rectangle").source == "rectangle.toml"
    with pytest.raises(
        ScenarioError,
        match="nonesuch: not a file and not a bundled world "
        r"\(bundled: aisles, office, rectangle\)",
    ):
        load_world("nonesuch")
    with pytest.raises(ScenarioError, match=r"missing\.toml: no such world file"):
        load_world(tmp_path / "missing.toml")


def test_a_fleet_scenario_is_not_a_world() -> None:
    import sim

    paper = Path(sim.__file__).parent / "scenarios" / "paper.toml"
    with pytest.raises(ScenarioError, match=r"paper\.toml: kind: missing required field"):
        load_world(paper)
