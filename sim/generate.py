"""Random worlds for scaling tests and benchmarks, and writing scenarios back to TOML."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from estimator.models import GaussianNoise, se2
from estimator.models.noise import PAPER_GEOMETRIC, PAPER_ODOMETRY
from sim.scenario import (
    ClassifierSpec,
    Communication,
    Object,
    Robot,
    RobotModel,
    Scenario,
    Sensor,
)

# A point landmark's detection noise in generated worlds: (σ²_bearing, σ²_range), σ 0.1 rad and
# 0.32 m, the paper's relative-pose position σ as the range's.
POINT_GEOMETRIC = GaussianNoise((0.01, 0.1))

_SPEED = 0.25
_MAX_TURN = 0.15
_STEER_GAIN = 0.5
_MAX_STEER = 0.3


def generate_scenario(
    robots: int,
    objects: int,
    classes: int,
    seed: int,
    steps: int = 60,
    area: float | None = None,
    comm_range: float = 10.0,
    kind: str = "pose",
    twins: float | None = None,
) -> Scenario:
    """A random world: ``objects`` objects with uniform classes in a square of side ``area`` metres
    (default grows with √objects), ``robots`` robots wandering inside it with smooth turns, an
    aliased classifier with random aliases and best views, the paper's noise, range communication.
    ``kind`` "point": the objects are point landmarks measured by bearing and range
    (:data:`POINT_GEOMETRIC`), heading 0 (their viewpoint is read in the world frame); the
    same world otherwise (the same random draws). ``twins`` (metres): every object gets a twin
    that far away in a random direction, its heading within 0.1 rad, of another class (ids
    ``objects`` + 1 on; drawn after everything else, so the rest of the world is the same):
    objects closer than the noise, which only their classes tell apart (issue 45).
    """
    if kind not in ("pose", "point"):
        raise ValueError(f"object kind {kind!r} (known: pose, point)")
    if robots < 1 or objects < 1 or classes < 2 or steps < 1:
        raise ValueError("need robots ≥ 1, objects ≥ 1, classes ≥ 2 and steps ≥ 1")
    if twins is not None and not (math.isfinite(twins) and twins > 0.0):
        raise ValueError(f"twins must be a distance > 0 m, got {twins}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E4F1EE7]))
    side = float(area) if area is not None else max(12.0, 4.0 * math.sqrt(objects))
    half = side / 2.0
    obj_xy = rng.uniform(-half, half, size=(objects, 2))
    obj_yaw = rng.uniform(-np.pi, np.pi, size=objects)
    obj_cls = rng.integers(0, classes, size=objects)
    if kind == "point":
        obj_yaw = np.zeros(objects)
    object_specs = tuple(
        Object(j + 1, (float(x), float(y), float(t)), int(c))
        for j, ((x, y), t, c) in enumerate(zip(obj_xy, obj_yaw, obj_cls, strict=True))
    )
    sensor = Sensor(math.radians(50.0), 5.0, kind)
    robot_specs = tuple(
        _wandering_robot(f"r{i + 1}", rng, half, steps, sensor) for i in range(robots)
    )
    classifier = random_aliased(rng, classes)
    description = f"random world, seed {seed}, {side:.1f} m square"
    if twins is not None:
        object_specs += _twins(rng, object_specs, classes, twins, kind)
        description += f", every object with a twin {twins:g} m away of another class"
    return Scenario(
        name=f"random-r{robots}-o{objects}-c{classes}-s{seed}",
        description=description,
        source="<generated>",
        steps=steps,
        num_classes=classes,
        class_prior=tuple([1.0 / classes] * classes),
        robots=robot_specs,
        objects=object_specs,
        odometry_noise=PAPER_ODOMETRY,
        geometric_noise=PAPER_GEOMETRIC if kind == "pose" else POINT_GEOMETRIC,
        classifier=classifier,
        sensor=sensor,
        communication=Communication("range", comm_range, ()),
    )


def _twins(
    rng: np.random.Generator, objects: tuple[Object, ...], classes: int, dist: float, kind: str
) -> tuple[Object, ...]:
    """A twin of every object ``dist`` metres away, heading within 0.1 rad, another class."""
    top = max(o.id for o in objects)
    out = []
    for n, o in enumerate(objects):
        a = float(rng.uniform(-np.pi, np.pi))
        yaw = 0.0 if kind == "point" else float(se2.wrap_angle(o.pose[2] + rng.uniform(-0.1, 0.1)))
        cls = (o.class_index + 1 + int(rng.integers(0, classes - 1))) % classes
        x, y = o.pose[0] + dist * math.cos(a), o.pose[1] + dist * math.sin(a)
        out.append(Object(top + 1 + n, (float(x), float(y), yaw), cls))
    return tuple(out)


def random_aliased(
    rng: np.random.Generator, classes: int, noise_std: float = 0.35
) -> ClassifierSpec:
    """An aliased classifier of ``classes`` classes, each with a random alias among the others
    and a random best view (degrees), drawn from ``rng`` in that order, class by class."""
    alias, best = [], []
    for c in range(classes):
        others = [a for a in range(classes) if a != c]
        alias.append(int(others[rng.integers(len(others))]))
        best.append(float(rng.uniform(-180.0, 180.0)))
    return ClassifierSpec("aliased", tuple(alias), tuple(best), noise_std)


def _wandering_robot(
    rid: str, rng: np.random.Generator, half: float, steps: int, sensor: Sensor
) -> Robot:
    """A robot that turns at random but steers back towards the centre near the border."""
    start = np.array([*rng.uniform(-0.8 * half, 0.8 * half, 2), rng.uniform(-np.pi, np.pi)])
    pose = start.copy()
    actions = []
    omega = 0.0
    for k in range(steps):
        if k % 5 == 0:
            omega = float(rng.uniform(-_MAX_TURN, _MAX_TURN))
        turn = omega
        if np.max(np.abs(pose[:2])) > 0.8 * half:
            to_centre = math.atan2(-pose[1], -pose[0])
            turn = float(
                np.clip(_STEER_GAIN * se2.wrap_angle(to_centre - pose[2]), -_MAX_STEER, _MAX_STEER)
            )
        action = (_SPEED, 0.0, round(turn, 6))
        actions.append(action)
        pose = se2.compose(pose, np.array(action))
    return Robot(
        rid,
        (float(start[0]), float(start[1]), float(start[2])),
        tuple(actions),
        sensor,
    )


def dump_scenario(s: Scenario) -> str:
    """TOML text (format 1) that :func:`sim.loader.parse_scenario` reads back into ``s``."""
    out = [
        "format = 1",
        f"name = {_q(s.name)}",
        f"description = {_q(s.description)}",
        f"steps = {s.steps}",
        *([] if s.class_seed is None else [f"class_seed = {s.class_seed}"]),
        "",
        *model_tables(dataclasses.replace(s.robot_model(), classifier=s.classifier), s),
        "",
    ]
    comm = s.communication
    out += ["[communication]", f"mode = {_q(comm.mode)}"]
    if comm.range is not None:
        out.append(f"range = {_num(comm.range)}")
    if comm.schedule:
        edges = ", ".join(f"[{e.first}, {e.last}, {_q(e.a)}, {_q(e.b)}]" for e in comm.schedule)
        out.append(f"schedule = [{edges}]")
    if s.recording is not None:
        out += ["", "[recording]", f"file = {_q(s.recording.file)}"]
        out += [f"sha256 = {_q(s.recording.sha256)}"]
    for r in s.robots:
        out += ["", "[[robots]]", f"id = {_q(r.id)}", f"start = {_nums(r.start)}"]
        out += _motion_lines(r)
        if r.sensor != s.sensor:
            out += ["[robots.sensor]", *_sensor_lines(r.sensor)]
    for o in s.objects:
        out += ["", "[[objects]]", f"id = {o.id}", f"pose = {_nums(o.pose)}"]
        if s.class_seed is None:  # else drawn per run
            out.append(f"class = {o.class_index + 1}")
    for v in s.variants:
        settings = ", ".join(f"{_q(key)} = {_value(value)}" for key, value in v.settings)
        out += ["", f"[variants.{_q(v.name)}]", f"description = {_q(v.description)}"]
        out.append(f"set = {{ {settings} }}")
    return "\n".join(out) + "\n"


def model_tables(model: RobotModel, scenario: Scenario | None = None) -> list[str]:
    """The lines of the ``[classes]``, ``[classifier]``, ``[noise]`` and ``[sensor]`` tables,
    written alike in a scenario and a robot model file; a ``scenario``'s
    ``[classifier.estimator]`` too."""
    out = ["[classes]", f"count = {model.num_classes}", f"prior = {_nums(model.class_prior)}"]
    out += ["", "[classifier]", *_classifier_lines(model.classifier)]
    if scenario is not None and scenario.estimator_classifier is not None:
        out += ["", "[classifier.estimator]", *_classifier_lines(scenario.estimator_classifier)]
    out += ["", "[noise]", f"odometry_var = {_noise(model.odometry_noise)}"]
    out += [f"geometric_var = {_noise(model.geometric_noise)}"]
    if model.geometric_noise.kernel != "gaussian":
        out += [f"geometric_kernel = {_q(model.geometric_noise.kernel)}"]
    return [*out, "", "[sensor]", *_sensor_lines(model.sensor, model=True)]


def _classifier_lines(c: ClassifierSpec) -> list[str]:
    out = [f"model = {_q(c.model)}"]
    if c.model == "aliased":
        out += [
            f"alias = [{', '.join(str(a + 1) for a in c.alias)}]",
            f"best_view_deg = {_nums(c.best_view_deg)}",
            f"noise_std = {_num(c.noise_std)}",
        ]
    if c.model in ("paper", "aliased"):
        out.append(f"viewpoint = {_q(c.viewpoint)}")
    if c.model == "learned":
        out.append(f"file = {_q(c.file)}")  # absolute: valid wherever the text is written
    return out


def _value(value: Any) -> str:
    """A TOML literal for the values a variant may set."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return _num(value)
    if isinstance(value, str):
        return _q(value)
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_q(k)} = {_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")


def _motion_lines(r: Robot) -> list[str]:
    speeds = {(a[0], a[1]) for a in r.actions}
    if len(speeds) == 1 and next(iter(speeds))[1] == 0.0:
        runs: list[list[float]] = []
        for a in r.actions:
            if runs and runs[-1][1] == a[2]:
                runs[-1][0] += 1
            else:
                runs.append([1, a[2]])
        turns = ", ".join(f"[{int(n)}, {_num(w)}]" for n, w in runs)
        return [f"speed = {_num(r.actions[0][0])}", f"turns = [{turns}]"]
    return [f"actions = [{', '.join(_nums(a) for a in r.actions)}]"]


def _sensor_lines(sensor: Sensor, model: bool = False) -> list[str]:
    """A ``[sensor]`` table; ``model``: the model's, which says what it measures (a robot's own
    sensor shares it)."""
    kind = [f'objects = "{sensor.objects}"'] if model and sensor.objects != "pose" else []
    return [
        f"half_angle_deg = {_num(_degrees_read_back(sensor.half_angle))}",
        f"range = {_num(sensor.range)}",
        *kind,
    ]


def _degrees_read_back(angle: float) -> float:
    """``angle`` in degrees, chosen among the nearest floats so that the loader's conversion
    back to radians gives ``angle`` itself (math.degrees alone misses it for ~5 % of angles)."""
    first = math.degrees(angle)
    for direction in (math.inf, -math.inf):
        d = first
        for _ in range(4):
            if math.radians(d) == angle:
                return d
            d = math.nextafter(d, direction)
    return first


def _noise(noise: GaussianNoise) -> str:
    return _nums(noise.variances)


def _num(x: float) -> str:
    return repr(float(x))


def _nums(xs: object) -> str:
    return "[" + ", ".join(_num(x) for x in xs) + "]"  # type: ignore[attr-defined]


def _q(text: str) -> str:
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    return f'"{escaped}"'
