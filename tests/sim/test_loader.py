"""The scenario loader: the bundled paper scenario, variants and overrides, every malformed input
turned into one precise ScenarioError, and the dump/parse round trip."""

from __future__ import annotations

import math
import random
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import sim
from estimator.models import paper_classifier
from sim.generate import dump_scenario, generate_scenario
from sim.loader import load_scenario, parse_scenario
from sim.scenario import Scenario, ScenarioError, ScheduleEdge
from tests.tolerance import assert_close

PAPER_PATH = Path(sim.__file__).parent / "scenarios" / "paper.toml"
LABEL = "base.toml"

# A small valid scenario: 2 robots (one by turns, one by actions), 3 objects, 4 steps. Every
# malformed case below is this text with one edit.
HEADER = """\
format = 1
name = "base"
description = "two robots, three objects"
steps = 4

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

[communication]
mode = "schedule"
range = 10.0
schedule = [[1, 4, "a", "b"]]
"""
ROBOTS = """
[[robots]]
id = "a"
start = [0.0, 0.0, 0.0]
speed = 0.25
turns = [[2, 0.1], [2, -0.1]]

[[robots]]
id = "b"
start = [1.0, 2.0, 0.5]
actions = [[0.25, 0.0, 0.0], [0.25, 0.0, 0.1], [0.25, 0.0, 0.1], [0.25, 0.0, 0.0]]
"""
OBJECTS = """
[[objects]]
id = 1
pose = [1.0, 0.0, 0.0]
class = 1

[[objects]]
id = 2
pose = [2.0, 1.0, 1.5]
class = 2

[[objects]]
id = 3
pose = [0.0, 3.0, -1.5]
class = 1
"""
BASE = HEADER + ROBOTS + OBJECTS
SENSOR = "[sensor]\nhalf_angle_deg = 50.0\nrange = 3.5\n"
ALIASED = 'model = "aliased"\nalias = [2, 1]\nbest_view_deg = [90.0, -90.0]\nnoise_std = 0.3'


def _edit(*edits: tuple[str, str]) -> str:
    """BASE with each (old, new) applied; ``old`` must occur exactly once."""
    text = BASE
    for old, new in edits:
        assert text.count(old) == 1, f"edit target {old!r} is not unique"
        text = text.replace(old, new)
    return text


def _top(line: str) -> tuple[str, str]:
    """An edit that adds a top-level key (it must precede the first table header)."""
    return ("format = 1\n", f"format = 1\n{line}\n")


def _case(
    case_id: str, edits: list[tuple[str, str]], path: str, reason: str, xfail: str = ""
) -> object:
    marks = [pytest.mark.xfail(strict=True, reason=xfail)] if xfail else []
    return pytest.param(edits, path, reason, id=case_id, marks=marks)


MALFORMED = [
    _case("toml-syntax", [("steps = 4", "steps = = 4")], "", "not valid TOML"),
    _case("toml-duplicate-table", [("[sensor]", "[sensor]\n[sensor]")], "", "not valid TOML"),
    _case("format-missing", [("format = 1\n", "")], "format", "missing required field"),
    _case("format-version-2", [("format = 1", "format = 2")], "format", "unsupported format 2"),
    _case("format-string", [("format = 1", 'format = "1"')], "format", "expected an integer"),
    _case(
        "format-2-checked-before-keys",
        [("format = 1", "format = 2\nlayers = 3")],
        "format",
        "unsupported format 2",
    ),
    _case("top-unknown-key", [_top('colour = "red"')], "colour", "unknown key"),
    _case("sensor-unknown-key", [("range = 3.5", "rnage = 3.5")], "sensor.rnage", "unknown key"),
    _case("robot-unknown-key", [("speed = 0.25", "sped = 0.25")], "robots[0].sped", "unknown key"),
    _case("name-missing", [('name = "base"\n', "")], "name", "missing required field"),
    _case("name-integer", [('name = "base"', "name = 7")], "name", "expected a string"),
    _case("steps-missing", [("steps = 4\n", "")], "steps", "missing required field"),
    _case(
        "steps-string", [("steps = 4", 'steps = "4"')], "steps", "expected an integer, got a string"
    ),
    _case("steps-bool", [("steps = 4", "steps = true")], "steps", "got a boolean"),
    _case(
        "steps-float", [("steps = 4", "steps = 4.0")], "steps", "expected an integer, got a number"
    ),
    _case("steps-zero", [("steps = 4", "steps = 0")], "steps", "0 must be ≥ 1"),
    _case(
        "classes-count-missing", [("count = 2\n", "")], "classes.count", "missing required field"
    ),
    _case("classes-count-one", [("count = 2", "count = 1")], "classes.count", "1 must be ≥ 2"),
    _case(
        "classes-count-huge",
        [("count = 2\nprior = [0.5, 0.5]", "count = 100000000000000000000")],
        "classes.count",
        "must be ≤",
    ),
    _case(
        "prior-sum", [("[0.5, 0.5]", "[0.5, 0.6]")], "classes.prior", "must sum to 1, sums to 1.1"
    ),
    _case(
        "prior-length",
        [("[0.5, 0.5]", "[0.3, 0.3, 0.4]")],
        "classes.prior",
        "expected 2 numbers, got 3",
    ),
    _case("prior-zero", [("[0.5, 0.5]", "[1.0, 0.0]")], "classes.prior[1]", "must be > 0"),
    _case("sensor-not-table", [(SENSOR, ""), _top("sensor = 3.5")], "sensor", "expected a table"),
    _case(
        "sensor-range-string", [("range = 3.5", 'range = "3.5"')], "sensor.range", "got a string"
    ),
    _case("sensor-range-bool", [("range = 3.5", "range = true")], "sensor.range", "got a boolean"),
    _case("sensor-range-zero", [("range = 3.5", "range = 0.0")], "sensor.range", "must be > 0"),
    _case(
        "half-angle-over-180",
        [("half_angle_deg = 50.0", "half_angle_deg = 181.0")],
        "sensor.half_angle_deg",
        "181.0 must be ≤ 180",
    ),
    _case(
        "robot-sensor-incomplete",
        [("0.0, 0.0]]\n", "0.0, 0.0]]\n[robots.sensor]\nhalf_angle_deg = 30.0\n")],
        "robots[1].sensor.range",
        "missing required field",
    ),
    _case(
        "odometry-var-nan",
        [("[0.003, 0.003, 0.001]", "[0.003, nan, 0.001]")],
        "noise.odometry_var[1]",
        "nan is not a finite number",
    ),
    _case(
        "geometric-var-inf",
        [("[0.1, 0.1, 0.01]", "[0.1, 0.1, inf]")],
        "noise.geometric_var[2]",
        "inf is not a finite number",
    ),
    _case(
        "geometric-var-negative",
        [("[0.1, 0.1, 0.01]", "[-0.1, 0.1, 0.01]")],
        "noise.geometric_var[0]",
        "-0.1 must be > 0",
    ),
    _case(
        "odometry-var-zero",
        [("[0.003, 0.003, 0.001]", "[0.003, 0.003, 0.0]")],
        "noise.odometry_var[2]",
        "must be > 0",
    ),
    _case(
        "odometry-var-length",
        [("[0.003, 0.003, 0.001]", "[0.003, 0.003]")],
        "noise.odometry_var",
        "expected 3 numbers, got 2",
    ),
    _case(
        "start-nan",
        [("[1.0, 2.0, 0.5]", "[1.0, nan, 0.5]")],
        "robots[1].start[1]",
        "nan is not a finite number",
    ),
    _case(
        "start-inf",
        [("start = [0.0, 0.0, 0.0]", "start = [-inf, 0.0, 0.0]")],
        "robots[0].start[0]",
        "-inf is not a finite number",
    ),
    _case(
        "start-overflow-1e999",
        [("start = [0.0, 0.0, 0.0]", "start = [1e999, 0.0, 0.0]")],
        "robots[0].start[0]",
        "inf is not a finite number",
    ),
    _case(
        "start-huge-integer",
        [("start = [0.0, 0.0, 0.0]", f"start = [1{'0' * 400}, 0.0, 0.0]")],
        "robots[0].start[0]",
        "too large",
    ),
    _case("robots-empty", [(ROBOTS, ""), _top("robots = []")], "robots", "at least one robot"),
    _case("robots-not-array", [(ROBOTS, ""), _top("robots = 3")], "robots", "expected an array"),
    _case("robots-missing", [(ROBOTS, "")], "robots", "missing required field"),
    _case(
        "robot-duplicate-id",
        [('id = "b"', 'id = "a"')],
        "robots[1].id",
        "duplicate robot id 'a'",
    ),
    _case(
        "robot-id-characters",
        [('id = "a"', 'id = "robot one"')],
        "robots[0].id",
        "'robot one' is not a valid robot id",
    ),
    _case("robot-id-integer", [('id = "a"', "id = 1")], "robots[0].id", "expected a string"),
    _case(
        "turns-sum",
        [("[[2, 0.1], [2, -0.1]]", "[[2, 0.1], [1, -0.1]]")],
        "robots[0].turns",
        "counts add up to 3 steps, the scenario has 4",
    ),
    _case(
        "turns-zero-count",
        [("[[2, 0.1], [2, -0.1]]", "[[4, 0.1], [0, -0.1]]")],
        "robots[0].turns[1][0]",
        "0 must be ≥ 1",
    ),
    _case(
        "turns-count-bool",
        [("[[2, 0.1], [2, -0.1]]", "[[true, 0.1], [3, -0.1]]")],
        "robots[0].turns[0][0]",
        "got a boolean",
    ),
    _case(
        "turns-run-shape",
        [("[[2, 0.1], [2, -0.1]]", "[[2, 0.1, 3], [2, -0.1]]")],
        "robots[0].turns[0]",
        "expected [count, turn_rad], got 3 values",
    ),
    _case(
        "turns-count-huge",
        [("[[2, 0.1], [2, -0.1]]", "[[100000000000000000000, 0.1], [2, -0.1]]")],
        "robots[0].turns[0][0]",
        "must be ≤ 4294967295",
    ),
    _case(
        "turns-count-large",
        [("[[2, 0.1], [2, -0.1]]", "[[4294967295, 0.1], [2, -0.1]]")],
        "robots[0].turns",
        "counts add up to 4294967297 steps, the scenario has 4",
    ),
    _case(
        "actions-length",
        [(", [0.25, 0.0, 0.0]]", "]")],
        "robots[1].actions",
        "expected 4 actions (one per step), got 3",
    ),
    _case(
        "action-arity",
        [("actions = [[0.25, 0.0, 0.0]", "actions = [[0.25, 0.0]")],
        "robots[1].actions[0]",
        "expected 3 numbers, got 2",
    ),
    _case(
        "actions-and-turns",
        [("actions = [", "turns = [[4, 0.0]]\nactions = [")],
        "robots[1]",
        "give exactly one of 'actions' or 'turns'",
    ),
    _case(
        "neither-actions-nor-turns",
        [("turns = [[2, 0.1], [2, -0.1]]\n", "")],
        "robots[0]",
        "give exactly one of 'actions' or 'turns'",
    ),
    _case(
        "speed-with-actions",
        [("actions = [", "speed = 0.3\nactions = [")],
        "robots[1].speed",
        "only used with 'turns'",
    ),
    _case("objects-missing", [(OBJECTS, "")], "objects", "missing required field"),
    _case(
        "object-not-table",
        [(OBJECTS, ""), _top("objects = [{ id = 1, pose = [0.0, 0.0, 0.0], class = 1 }, 7]")],
        "objects[1]",
        "expected a table, got an integer",
    ),
    _case("object-duplicate-id", [("id = 3", "id = 2")], "objects[2].id", "duplicate object id 2"),
    _case("object-negative-id", [("id = 3", "id = -3")], "objects[2].id", "-3 must be ≥ 0"),
    _case(
        "object-pose-missing",
        [("pose = [0.0, 3.0, -1.5]\n", "")],
        "objects[2].pose",
        "missing required field",
    ),
    _case(
        "object-class-zero",
        [("0.0, 0.0]\nclass = 1", "0.0, 0.0]\nclass = 0")],
        "objects[0].class",
        "0 is out of range 1..2",
    ),
    _case(
        "object-class-m-plus-1",
        [("class = 2", "class = 3")],
        "objects[1].class",
        "3 is out of range 1..2",
    ),
    _case(
        "object-class-bool", [("class = 2", "class = true")], "objects[1].class", "got a boolean"
    ),
    _case(
        "schedule-unknown-robot",
        [('[[1, 4, "a", "b"]]', '[[1, 4, "a", "c"]]')],
        "communication.schedule[0][3]",
        "unknown robot 'c'",
    ),
    _case(
        "schedule-from-after-to",
        [('[[1, 4, "a", "b"]]', '[[3, 2, "a", "b"]]')],
        "communication.schedule[0]",
        "1 ≤ 3 ≤ 2 ≤ 4",
    ),
    _case(
        "schedule-beyond-steps",
        [('[[1, 4, "a", "b"]]', '[[1, 5, "a", "b"]]')],
        "communication.schedule[0]",
        "1 ≤ 1 ≤ 5 ≤ 4",
    ),
    _case(
        "schedule-step-zero",
        [('[[1, 4, "a", "b"]]', '[[0, 4, "a", "b"]]')],
        "communication.schedule[0][0]",
        "0 must be ≥ 1",
    ),
    _case(
        "schedule-same-robot",
        [('[[1, 4, "a", "b"]]', '[[1, 4, "a", "a"]]')],
        "communication.schedule[0]",
        "two different robots, got 'a' twice",
    ),
    _case(
        "schedule-edge-arity",
        [('[[1, 4, "a", "b"]]', '[[1, 4, "a"]]')],
        "communication.schedule[0]",
        "expected [from_step, to_step, robot_a, robot_b]",
    ),
    _case(
        "comm-range-mode-without-range",
        [('mode = "schedule"\nrange = 10.0', 'mode = "range"')],
        "communication.range",
        "missing required field (mode 'range' needs it)",
    ),
    _case(
        "comm-both-without-schedule",
        [('mode = "schedule"', 'mode = "both"'), ('schedule = [[1, 4, "a", "b"]]\n', "")],
        "communication.schedule",
        "missing required field (mode 'both' needs it)",
    ),
    _case(
        "comm-unknown-mode",
        [('mode = "schedule"', 'mode = "radio"')],
        "communication.mode",
        "unknown mode 'radio'",
    ),
    _case(
        "comm-range-nan", [("range = 10.0", "range = nan")], "communication.range", "not a finite"
    ),
    _case(
        "classifier-unknown-model",
        [('model = "paper"', 'model = "gp"')],
        "classifier.model",
        "unknown model 'gp' (known: paper, aliased)",
    ),
    _case(
        "classifier-paper-with-3-classes",
        [("count = 2\nprior = [0.5, 0.5]", "count = 3")],
        "classifier.model",
        "the paper model has 2 classes, the scenario has 3",
    ),
    _case(
        "classifier-paper-extra-key",
        [('model = "paper"', 'model = "paper"\nnoise_std = 0.3')],
        "classifier.noise_std",
        "unknown key",
    ),
    _case(
        "classifier-self-alias",
        [('model = "paper"', ALIASED.replace("[2, 1]", "[1, 1]"))],
        "classifier.alias[0]",
        "class 1 cannot be its own alias",
    ),
    _case(
        "classifier-alias-out-of-range",
        [('model = "paper"', ALIASED.replace("[2, 1]", "[2, 3]"))],
        "classifier.alias[1]",
        "class 3 is out of range 1..2",
    ),
    _case(
        "classifier-alias-length",
        [('model = "paper"', ALIASED.replace("[2, 1]", "[2]"))],
        "classifier.alias",
        "expected 2 class numbers, got 1",
    ),
    _case(
        "classifier-noise-std-missing",
        [('model = "paper"', ALIASED.replace("\nnoise_std = 0.3", ""))],
        "classifier.noise_std",
        "missing required field",
    ),
    _case(
        "classifier-best-view-inf",
        [('model = "paper"', ALIASED.replace("[90.0, -90.0]", "[90.0, -inf]"))],
        "classifier.best_view_deg[1]",
        "-inf is not a finite number",
    ),
    _case(
        "classifier-viewpoint-unknown",
        [('model = "paper"', 'model = "paper"\nviewpoint = "camera"')],
        "classifier.viewpoint",
        "unknown convention 'camera' (known: object_to_camera, camera_to_object)",
    ),
    _case(
        "classifier-viewpoint-not-string",
        [('model = "paper"', ALIASED + "\nviewpoint = 180")],
        "classifier.viewpoint",
        "expected a string",
    ),
    _case(
        "variants-not-table", [_top("variants = 3")], "variants", "expected a table, got an integer"
    ),
    _case(
        "variant-unknown-key-unapplied",
        [(OBJECTS, OBJECTS + '\n[variants.fast]\nsett = { "sensor.range" = 5.0 }\n')],
        "variants.fast.sett",
        "unknown key",
    ),
]


def test_base_scenario_is_valid() -> None:
    s = parse_scenario(BASE, LABEL)
    assert (s.robot_ids, s.object_ids, s.steps, s.num_classes) == (("a", "b"), (1, 2, 3), 4, 2)
    assert s.robot("a").actions == ((0.25, 0.0, 0.1),) * 2 + ((0.25, 0.0, -0.1),) * 2


def test_base_scenario_with_aliased_classifier_is_valid() -> None:
    s = parse_scenario(_edit(('model = "paper"', ALIASED)), LABEL)
    assert s.classifier.alias == (1, 0)
    assert s.classifier.best_view_deg == (90.0, -90.0)
    assert_close(s.classifier.build().cov(0, 0.0), [[0.09, 0.0], [0.0, 0.09]])


@pytest.mark.parametrize("model", ["paper", "aliased"])
@pytest.mark.parametrize("convention", [None, "object_to_camera", "camera_to_object"])
def test_a_crafted_classifier_states_its_viewpoint_convention(
    model: str, convention: str | None
) -> None:
    """A file that omits ``viewpoint`` keeps object → camera; the model built evaluates a
    camera → object file at ψ + π (its best views turned by π in semfleet's ψ)."""
    table = 'model = "paper"' if model == "paper" else ALIASED
    if convention is not None:
        table += f'\nviewpoint = "{convention}"'
    spec = parse_scenario(_edit(('model = "paper"', table)), LABEL).classifier
    assert spec.viewpoint == (convention or "object_to_camera")
    built = spec.build()
    turn = math.pi if convention == "camera_to_object" else 0.0
    psi = np.linspace(-np.pi, np.pi, 9)
    reference = (
        paper_classifier()
        if model == "paper"
        else parse_scenario(_edit(('model = "paper"', ALIASED)), LABEL).classifier.build()
    )
    for c in range(2):
        assert_close(built.mean(c, psi), reference.mean(c, psi - turn), atol=1e-12)


@pytest.mark.parametrize(("edits", "path", "reason"), MALFORMED)
def test_parse_scenario_rejects_malformed(
    edits: list[tuple[str, str]], path: str, reason: str
) -> None:
    text = _edit(*edits)
    with pytest.raises(ScenarioError) as info:
        parse_scenario(text, LABEL)
    message = str(info.value)
    assert message.startswith(f"{LABEL}: "), message
    if path:
        assert f": {path}: " in message, message
    assert reason in message, message


def test_parse_scenario_malformed_table_is_large_enough() -> None:
    assert len(MALFORMED) >= 25


_FUZZ_TOKENS = ["nan", '"x"', "true", "-1", "[]", "{}", "1e999", "0"]
_LITERAL = re.compile(r'"[^"]*"|-?[0-9][0-9.e+-]*|true|false')


def _mutate(text: str, rng: random.Random) -> str:
    lines = text.splitlines()
    kind = rng.randrange(4)
    if kind == 0:
        del lines[rng.randrange(len(lines))]
    elif kind == 1:
        i = rng.choice([i for i, line in enumerate(lines) if " = " in line])
        key = lines[i].split(" = ", 1)[0]
        lines[i] = f"{key} = {rng.choice(_FUZZ_TOKENS)}"
    elif kind == 2:
        i = rng.choice([i for i, line in enumerate(lines) if _LITERAL.search(line)])
        spans = [m.span() for m in _LITERAL.finditer(lines[i])]
        a, b = rng.choice(spans)
        lines[i] = lines[i][:a] + rng.choice(_FUZZ_TOKENS) + lines[i][b:]
    else:
        starts = [i for i, line in enumerate(lines) if line.startswith("[")]
        j = rng.randrange(len(starts))
        end = starts[j + 1] if j + 1 < len(starts) else len(lines)
        block = lines[starts[j] : end]
        lines[end:end] = block
    return "\n".join(lines) + "\n"


def test_parse_scenario_fuzz_raises_only_scenario_error() -> None:
    rng = random.Random(20240611)
    escaped = []
    outcomes = {"parsed": 0, "rejected": 0}
    for _ in range(300):
        text = BASE
        for _ in range(rng.choice([1, 1, 2])):
            text = _mutate(text, rng)
        try:
            parse_scenario(text, LABEL)
            outcomes["parsed"] += 1
        except ScenarioError as exc:
            assert str(exc).startswith(f"{LABEL}: ")
            outcomes["rejected"] += 1
        except Exception as exc:
            escaped.append(f"{type(exc).__name__}: {exc}\n{text}")
    assert not escaped, escaped[0]
    assert outcomes["rejected"] > 150 and outcomes["parsed"] > 0, outcomes


# The bundled paper scenario


def _check_paper(s: Scenario) -> None:
    assert s.name == "paper"
    assert s.robot_ids == ("r1", "r2", "r3")
    assert s.object_ids == tuple(range(1, 16))
    assert (s.num_classes, s.steps, s.class_prior) == (2, 60, (0.5, 0.5))
    assert all(len(r.actions) == 60 for r in s.robots)
    assert s.objects[1].class_index == 1
    assert s.objects[0].class_index == 0
    assert [o.class_index + 1 for o in s.objects] == [1, 2, 1, 1, 1, 2, 1, 1, 2, 1, 2, 1, 1, 1, 2]
    assert s.object_poses().shape == (15, 3)
    assert_close(s.objects[1].pose, [1.0, 2.0, math.pi / 2])
    r1 = s.robot("r1")
    assert r1.start == (2.0, -8.0, 1.5555)
    assert r1.actions[:4] == ((0.25, 0.0, 0.04),) * 4
    assert r1.actions[-1] == (0.25, 0.0, -0.08)
    for r in s.robots:
        assert_close(r.sensor.half_angle, math.radians(50.0))
        assert r.sensor.range == 3.5
    assert s.odometry_noise.variances == (0.003, 0.003, 0.001)
    assert s.geometric_noise.variances == (0.1, 0.1, 0.01)
    assert s.classifier.model == "paper"
    assert s.communication.mode == "schedule"
    assert s.communication.range == 10.0
    assert s.communication.schedule == (
        ScheduleEdge(6, 60, "r2", "r3"),
        ScheduleEdge(13, 60, "r1", "r2"),
        ScheduleEdge(13, 60, "r1", "r3"),
    )
    assert [v.name for v in s.variants] == ["sense10", "comm10", "experiment", "object_to_camera"]
    assert s.applied_variants == ()


def test_load_scenario_paper_by_name() -> None:
    s = load_scenario("paper")
    _check_paper(s)
    assert s.source == "paper.toml"


@pytest.mark.parametrize("as_path", [True, False], ids=["Path", "str"])
def test_load_scenario_paper_by_path(as_path: bool) -> None:
    s = load_scenario(PAPER_PATH if as_path else str(PAPER_PATH))
    _check_paper(s)
    assert s.source == str(PAPER_PATH)
    assert replace(s, source="paper.toml") == load_scenario("paper")


@pytest.mark.parametrize(
    ("source", "variants"),
    [("paper:sense10", []), ("paper", ["sense10"]), (f"{PAPER_PATH}:sense10", [])],
    ids=["inline", "argument", "path-inline"],
)
def test_load_scenario_sense10_sets_every_robot_range(source: str, variants: list[str]) -> None:
    s = load_scenario(source, variants)
    assert [r.sensor.range for r in s.robots] == [10.0, 10.0, 10.0]
    assert s.applied_variants == ("sense10",)


def test_load_scenario_comm10_switches_to_range_mode() -> None:
    s = load_scenario("paper:comm10")
    assert (s.communication.mode, s.communication.range) == ("range", 10.0)
    assert s.robots == load_scenario("paper").robots


def test_load_scenario_experiment_variant() -> None:
    s = load_scenario("paper", ["experiment"])
    assert s.odometry_noise.variances == (0.0003, 0.0003, 0.0001)
    assert s.geometric_noise.variances == (0.04, 0.04, 0.005)
    assert (s.communication.mode, s.communication.range) == ("range", 3.0)


def test_load_scenario_variants_compose_in_order() -> None:
    s = load_scenario("paper:comm10:sense10", ["experiment"])
    assert s.applied_variants == ("comm10", "sense10", "experiment")
    assert s.communication.range == 3.0
    assert s.robots[0].sensor.range == 10.0


def test_load_scenario_unknown_variant_is_named() -> None:
    with pytest.raises(ScenarioError, match=r"paper\.toml: variants: no variant 'sense20'") as info:
        load_scenario("paper:sense20")
    assert "defined: comm10, experiment, object_to_camera, sense10" in str(info.value)
    with pytest.raises(ScenarioError, match="no variant 'bogus'"):
        load_scenario("paper", ["bogus"])


def test_parse_scenario_variant_without_variants_table() -> None:
    with pytest.raises(ScenarioError, match=r"no variant 'x' \(defined: none\)"):
        parse_scenario(BASE, LABEL, ["x"])


def test_load_scenario_override_sets_field() -> None:
    s = load_scenario("paper", overrides={"sensor.range": 5.0})
    assert [r.sensor.range for r in s.robots] == [5.0, 5.0, 5.0]


def test_load_scenario_override_applies_after_variants() -> None:
    s = load_scenario("paper:sense10", overrides={"sensor.range": 5.0})
    assert s.robots[0].sensor.range == 5.0


def test_load_scenario_override_of_missing_table_path() -> None:
    with pytest.raises(ScenarioError) as info:
        load_scenario("paper", overrides={"sensr.range": 5.0})
    assert str(info.value) == "paper.toml: override: 'sensr.range': 'sensr' is not a table"


def test_load_scenario_override_through_a_value_is_rejected() -> None:
    with pytest.raises(ScenarioError, match=r"'sensor\.range' is not a table"):
        load_scenario("paper", overrides={"sensor.range.max": 5.0})


def test_load_scenario_override_is_validated() -> None:
    with pytest.raises(ScenarioError, match=r"paper\.toml: override sensor\.range: expected a num"):
        load_scenario("paper", overrides={"sensor.range": "far"})
    with pytest.raises(ScenarioError, match=r"override sensor\.rnage: unknown key"):
        load_scenario("paper", overrides={"sensor.rnage": 5.0})


@pytest.mark.parametrize("path", ["format", "variants.sense10.set"])
def test_load_scenario_override_of_protected_field(path: str) -> None:
    with pytest.raises(ScenarioError, match="cannot be overridden"):
        load_scenario("paper", overrides={path: 2})


def test_load_scenario_missing_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ScenarioError) as info:
        load_scenario(missing)
    assert str(info.value) == f"{missing}: no such scenario file"


def test_load_scenario_unknown_bundled_name() -> None:
    with pytest.raises(ScenarioError) as info:
        load_scenario("papper")
    assert str(info.value) == (
        "papper: not a file and not a bundled scenario (bundled: lanes, paper, rendezvous)"
    )


def test_load_scenario_invalid_utf8(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b'format = 1\nname = "\xff\xfe"\n')
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(bad))}: cannot read: .*utf-8"):
        load_scenario(bad)


def test_load_scenario_directory(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(tmp_path))}: cannot read"):
        load_scenario(tmp_path)


def test_load_scenario_file_label_in_errors(tmp_path: Path) -> None:
    path = tmp_path / "mine.toml"
    path.write_text(_edit(("class = 2", "class = 3")), encoding="utf-8")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value) == f"{path}: objects[1].class: 3 is out of range 1..2"


# dump → parse round trip

_ROUND_TRIP = [(0, 3), (2, 2), (2, 5), (3, 3), (4, 4)]


@pytest.mark.parametrize(("seed", "classes"), [*_ROUND_TRIP, (5, 2), (6, 3), (7, 2), (8, 5)])
def test_dump_scenario_round_trips_exactly(seed: int, classes: int) -> None:
    s = generate_scenario(robots=3, objects=8, classes=classes, seed=seed, steps=30)
    back = parse_scenario(dump_scenario(s), "dumped.toml")
    assert back.source == "dumped.toml"
    assert replace(back, source=s.source) == s


def test_dump_scenario_round_trips_paper() -> None:
    s = load_scenario("paper")
    assert replace(parse_scenario(dump_scenario(s), "paper.toml"), source=s.source) == s


def test_dump_scenario_round_trips_paper_without_variants() -> None:
    s = load_scenario("paper")
    back = parse_scenario(dump_scenario(s), "dumped.toml")
    assert replace(back, source=s.source, variants=s.variants) == s


def test_dump_scenario_round_trips_per_robot_sensor_and_variant_result() -> None:
    s = load_scenario("paper:sense10")
    robots = (replace(s.robots[0], sensor=replace(s.robots[0].sensor, range=2.0)), *s.robots[1:])
    s = replace(s, robots=robots)
    back = parse_scenario(dump_scenario(s), "dumped.toml")
    assert back.robots == s.robots
    assert replace(back, source=s.source, variants=s.variants, applied_variants=("sense10",)) == s


def test_load_scenario_override_with_empty_path() -> None:
    with pytest.raises(ScenarioError, match=r"paper\.toml: override: '' is not a field path"):
        load_scenario("paper", overrides={"": 1})


def test_load_scenario_override_error_names_the_override() -> None:
    with pytest.raises(ScenarioError, match=r"override.*sensor\.range: expected a number"):
        load_scenario("paper", overrides={"sensor.range": "far"})


@pytest.mark.parametrize("convention", ["object_to_camera", "camera_to_object"])
@pytest.mark.parametrize("source", ["generated", "paper"])
def test_dump_scenario_writes_the_viewpoint_convention(source: str, convention: str) -> None:
    """`scenario generate` (dump_scenario) states the convention, and it reads back."""
    s = (
        generate_scenario(robots=2, objects=4, classes=3, seed=1)
        if source == "generated"
        else load_scenario("paper")
    )
    s = replace(s, classifier=replace(s.classifier, viewpoint=convention))
    text = dump_scenario(s)
    assert f'viewpoint = "{convention}"' in text.split("[classifier]")[1].split("\n\n")[0]
    assert parse_scenario(text, "dumped.toml").classifier.viewpoint == convention
