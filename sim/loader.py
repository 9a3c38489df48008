"""Load and validate scenario TOML files (format 1, see docs/scenarios.md).

Every problem becomes a :class:`ScenarioError` whose message names the file, the field and the
reason, e.g. ``paper.toml: objects[3].class: 3 is out of range 1..2``.

Over 300 lines for a reason: one reader per table of the scenario format (robots, objects,
classes, classifier, noise, sensor, communication, variants), each naming its fields in its
errors; the format is one document and is validated as one.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import tomllib
from collections.abc import Iterable, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from estimator.models import ROBOT_ID, ROBOT_ID_RULE, GaussianNoise
from estimator.models.classifier import OBJECT_TO_CAMERA, VIEWPOINTS
from estimator.models.noise import KERNELS
from estimator.models.objects import OBJECT_KINDS, object_kind
from sim.learned_file import LearnedFileError, load_learned
from sim.recording import RecordingError, cached_recording, fits
from sim.scenario import (
    FORMAT_VERSION,
    ClassifierSpec,
    Communication,
    Object,
    RecordingRef,
    Robot,
    RobotModel,
    Scenario,
    ScenarioError,
    ScheduleEdge,
    Sensor,
    Variant,
    draw_classes,
)

_ID_PATTERN = ROBOT_ID
COMM_MODES = ("schedule", "range", "both")
_CRAFTED_MODELS = ("paper", "aliased")  # "learned" too: its file comes from `classifier fit`
_PRIOR_TOLERANCE = 1e-6
_MAX_INT = 2**32 - 1  # ids, steps and counts; ids travel as unsigned 32-bit integers on the wire
_MAX_FLOAT_INT = 2**53
MAX_CLASSES = 64  # the wire carries a class as one byte; scores are at most 64 long
_MAX_STEPS = 1_000_000
# The tables of a robot model file, which a scenario file has too.
MODEL_TABLES = ("classes", "classifier", "noise", "sensor")


def bundled_names() -> list[str]:
    """Names of the scenarios shipped in ``sim/scenarios``."""
    folder = resources.files("sim") / "scenarios"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def read_source(source: str | Path) -> tuple[str, str]:
    """(label, text) of a scenario given as a file path or a bundled name."""
    path = Path(source)
    if path.suffix == ".toml" or path.exists():
        return str(path), read_file(path, "scenario file")
    name = str(source)
    if name not in bundled_names():
        known = ", ".join(bundled_names())
        raise ScenarioError(f"{name}: not a file and not a bundled scenario (bundled: {known})")
    text = (resources.files("sim") / "scenarios" / f"{name}.toml").read_text(encoding="utf-8")
    return f"{name}.toml", text


def read_file(path: Path, what: str) -> str:
    """The text of the file ``path``; a :class:`ScenarioError` naming it (and ``what`` it should
    be) when it cannot be read."""
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError(f"{path}: no such {what}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{path}: cannot read: {exc}") from None


def parse_toml(text: str, label: str) -> dict[str, Any]:
    """The TOML ``text`` as a dict; a :class:`ScenarioError` naming ``label`` if it is not TOML."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{label}: not valid TOML: {exc}") from None


def load_scenario(
    source: str | Path,
    variants: Iterable[str] = (),
    overrides: Mapping[str, Any] | None = None,
) -> Scenario:
    """Load a scenario file or bundled scenario by name.

    ``source`` may carry variants after colons (``paper:sense10``). ``variants`` are applied in
    order, then ``overrides`` (dotted field paths such as ``{"sensor.range": 10.0}``).
    """
    text_source = str(source)
    names = list(variants)
    if not Path(text_source).exists() and ":" in text_source:
        text_source, *inline = text_source.split(":")
        names = inline + names
    label, text = read_source(text_source)
    path = Path(label)
    folder = path.parent if path.is_file() else None  # a bundled scenario has no folder
    return parse_scenario(text, label, names, overrides or {}, folder)


def parse_scenario(
    text: str,
    label: str = "<string>",
    variants: Iterable[str] = (),
    overrides: Mapping[str, Any] | None = None,
    folder: Path | None = None,
) -> Scenario:
    """Validate TOML text into a :class:`Scenario`; ``label`` names the file in errors.

    Every variant defined in the file is validated, whether applied or not. Relative file
    paths in it (``classifier.file``) are relative to ``folder``, by default the current one.
    """
    raw = parse_toml(text, label)
    top = FieldReader(label, raw, "")
    check_format(top)
    defined = _variants(top)
    by_name = {v.name: v for v in defined}
    origins: dict[str, str] = {}
    applied = []
    for name in variants:
        if name not in by_name:
            known = ", ".join(sorted(by_name)) or "none"
            raise ScenarioError(f"{label}: variants: no variant {name!r} (defined: {known})")
        for key, value in by_name[name].settings:
            _apply_override(raw, label, key, value, f"variant {name}")
            origins[key] = f"variant {name}"
        applied.append(name)
    for key, value in (overrides or {}).items():
        _apply_override(raw, label, key, value, "override")
        origins[key] = "override"
    scenario = _build_attributed(raw, label, origins, folder)
    for v in defined:
        if v.name in applied:
            continue
        trial = copy.deepcopy(raw)
        for key, value in v.settings:
            _apply_override(trial, label, key, value, f"variant {v.name}")
        blame = {key: f"variant {v.name}" for key, _ in v.settings}
        _build_attributed(trial, label, blame, folder)
    return _replace_variants(scenario, defined, tuple(applied))


def _replace_variants(
    s: Scenario, defined: tuple[Variant, ...], applied: tuple[str, ...]
) -> Scenario:
    return dataclasses.replace(s, variants=defined, applied_variants=applied)


def _build_attributed(
    raw: dict[str, Any], label: str, origins: Mapping[str, str], folder: Path | None
) -> Scenario:
    """Build, and blame a variant or override for an invalid value it set."""
    try:
        return _build(raw, label, folder)
    except ScenarioError as exc:
        field = exc.field or ""
        for key, origin in origins.items():
            if field == key or field.startswith((f"{key}.", f"{key}[")):
                raise ScenarioError(
                    f"{label}: {origin} {field}: {exc.reason}", field, exc.reason
                ) from None
        raise


def check_format(top: FieldReader) -> None:
    """Checked first, so a file of a newer format is reported as such and not as unknown keys."""
    version = top.integer("format")
    if version != FORMAT_VERSION:
        raise top.fail(
            "format", f"unsupported format {version} (this semfleet reads {FORMAT_VERSION})"
        )


def _variants(top: FieldReader) -> tuple[Variant, ...]:
    if not top.has("variants"):
        return ()
    table = top.table("variants")
    out = []
    for name in table.field_names():
        v = table.table(name)
        v.check_keys({"description", "set"})
        description = v.string("description") if v.has("description") else ""
        settings = v.table("set")
        for key in settings.field_names():
            if not key or any(not part for part in key.split(".")):
                raise settings.fail(key, f"{key!r} is not a field path")
        out.append(Variant(name, description, tuple(settings.raw.items())))
    return tuple(out)


def _apply_override(raw: dict[str, Any], label: str, path: str, value: Any, where: str) -> None:
    parts = path.split(".")
    if not path or any(not part for part in parts):
        raise ScenarioError(f"{label}: {where}: {path!r} is not a field path", where)
    if parts[0] in ("variants", "format"):
        raise ScenarioError(f"{label}: {where}: {path!r} cannot be overridden", where)
    node: Any = raw
    for i, part in enumerate(parts[:-1]):
        if not isinstance(node, dict) or part not in node or not isinstance(node[part], dict):
            prefix = ".".join(parts[: i + 1])
            raise ScenarioError(f"{label}: {where}: {path!r}: {prefix!r} is not a table", where)
        node = node[part]
    node[parts[-1]] = copy.deepcopy(value)


class FieldReader:
    """A cursor into the raw TOML data that knows its dotted path, for precise errors."""

    def __init__(self, label: str, raw: Any, path: str) -> None:
        self.label, self.raw, self.path = label, raw, path

    def _name(self, key: str | int) -> str:
        if isinstance(key, int):
            return f"{self.path}[{key}]"
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str | int | None, reason: str) -> ScenarioError:
        where = self.path if key is None else self._name(key)
        return ScenarioError(f"{self.label}: {where or '<top>'}: {reason}", where, reason)

    def field_names(self) -> list[str]:
        return list(self.raw.keys())

    def check_keys(self, allowed: set[str]) -> None:
        for key in self.raw:
            if key not in allowed:
                options = ", ".join(sorted(allowed))
                raise self.fail(key, f"unknown key (allowed here: {options})")

    def has(self, key: str) -> bool:
        return key in self.raw

    def _get(self, key: str | int) -> Any:
        if isinstance(key, int):
            return self.raw[key]
        if key not in self.raw:
            raise self.fail(key, "missing required field")
        return self.raw[key]

    def table(self, key: str) -> FieldReader:
        value = self._get(key)
        if not isinstance(value, dict):
            raise self.fail(key, f"expected a table, got {_type_name(value)}")
        return FieldReader(self.label, value, self._name(key))

    def optional_table(self, key: str) -> dict[str, Any] | None:
        return self.table(key).raw if key in self.raw else None

    def array(self, key: str | int) -> FieldReader:
        value = self._get(key)
        if not isinstance(value, list):
            raise self.fail(key, f"expected an array, got {_type_name(value)}")
        return FieldReader(self.label, value, self._name(key))

    def tables(self, key: str) -> list[FieldReader]:
        arr = self.array(key)
        out = []
        for i, item in enumerate(arr.raw):
            if not isinstance(item, dict):
                raise arr.fail(i, f"expected a table, got {_type_name(item)}")
            out.append(FieldReader(self.label, item, arr._name(i)))
        return out

    def string(self, key: str | int) -> str:
        value = self._get(key)
        if not isinstance(value, str):
            raise self.fail(key, f"expected a string, got {_type_name(value)}")
        return value

    def integer(self, key: str | int, minimum: int | None = None, maximum: int = _MAX_INT) -> int:
        value = self._get(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"expected an integer, got {_type_name(value)}")
        if minimum is not None and value < minimum:
            raise self.fail(key, f"{value} must be ≥ {minimum}")
        if value > maximum:
            raise self.fail(key, f"{value} must be ≤ {maximum}")
        return value

    def boolean(self, key: str | int) -> bool:
        value = self._get(key)
        if not isinstance(value, bool):
            raise self.fail(key, f"expected true or false, got {_type_name(value)}")
        return value

    def number(self, key: str | int, positive: bool = False) -> float:
        value = self._get(key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(key, f"expected a number, got {_type_name(value)}")
        if isinstance(value, int) and abs(value) > _MAX_FLOAT_INT:
            raise self.fail(key, f"an integer of {len(str(abs(value)))} digits is too large")
        if not math.isfinite(value):
            raise self.fail(key, f"{value} is not a finite number")
        if positive and value <= 0:
            raise self.fail(key, f"{value} must be > 0")
        return float(value)

    def vector(self, key: str | int, length: int | None, positive: bool = False) -> list[float]:
        arr = self.array(key)
        if length is not None and len(arr.raw) != length:
            raise self.fail(key, f"expected {length} numbers, got {len(arr.raw)}")
        return [arr.number(i, positive) for i in range(len(arr.raw))]


def _type_name(value: Any) -> str:
    return {
        bool: "a boolean",
        int: "an integer",
        float: "a number",
        str: "a string",
        list: "an array",
        dict: "a table",
    }.get(type(value), type(value).__name__)


def _build(raw: dict[str, Any], label: str, folder: Path | None) -> Scenario:
    top = FieldReader(label, raw, "")
    check_format(top)
    top.check_keys(
        {"format", "name", "description", "steps", *MODEL_TABLES}
        | {"communication", "robots", "objects", "variants", "recording", "class_seed"}
    )
    name = top.string("name")
    description = top.string("description") if top.has("description") else ""
    steps = top.integer("steps", minimum=1, maximum=_MAX_STEPS)
    model = robot_model_tables(top, "scenario", folder)
    estimator = _estimator_classifier(top.table("classifier"), model.num_classes, folder)
    robots = _robots(top, steps, model.sensor)
    class_seed = top.integer("class_seed", minimum=0) if top.has("class_seed") else None
    objects = _objects(top, model.num_classes, model.sensor.objects, class_seed is not None)
    if class_seed is not None:
        drawn = draw_classes(model.class_prior, len(objects), class_seed, 0)
        objects = tuple(
            dataclasses.replace(o, class_index=int(c)) for o, c in zip(objects, drawn, strict=True)
        )
    robot_ids = [r.id for r in robots]
    communication = _communication(top.table("communication"), steps, robot_ids)
    recording = None
    if top.has("recording"):
        recording = _recording(top.table("recording"), folder, robot_ids, steps, objects)
        if model.sensor.objects != "point":
            raise top.fail(
                "recording", 'a recording holds point landmarks: [sensor] objects = "point"'
            )
    return Scenario(
        name=name,
        description=description,
        source=label,
        steps=steps,
        num_classes=model.num_classes,
        class_prior=model.class_prior,
        robots=robots,
        objects=objects,
        odometry_noise=model.odometry_noise,
        geometric_noise=model.geometric_noise,
        classifier=model.classifier,
        sensor=model.sensor,
        communication=communication,
        estimator_classifier=estimator,
        recording=recording,
        class_seed=class_seed,
    )


def _recording(
    f: FieldReader,
    folder: Path | None,
    robots: list[str],
    steps: int,
    objects: tuple[Object, ...],
) -> RecordingRef:
    """``[recording]``: ``file`` (relative to the scenario's folder) and its ``sha256``; the
    file is read now and must fit the scenario's robots, steps and objects."""
    f.check_keys({"file", "sha256"})
    name = f.string("file")
    digest = f.string("sha256")
    if not name:
        raise f.fail("file", "must name a recording file (.npz)")
    if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
        raise f.fail("sha256", "expected 64 lowercase hexadecimal digits")
    path = Path(name).expanduser()
    path = (path if path.is_absolute() else (folder or Path.cwd()) / path).resolve()
    try:
        rec = cached_recording(str(path), digest)
    except RecordingError as exc:
        raise f.fail("file", str(exc)) from None
    problem = fits(rec, robots, steps, [o.id for o in objects])
    if problem is not None:
        raise f.fail("file", f"{path}: {problem}")
    return RecordingRef(name, str(path), digest)


def robot_model_tables(top: FieldReader, owner: str, folder: Path | None = None) -> RobotModel:
    """The tables a scenario and a robot model file share (``MODEL_TABLES``), in this order;
    ``owner`` ("scenario", "model") names the whole file in errors; relative file paths are
    relative to ``folder`` (None: the current folder)."""
    num_classes, prior = _classes(top.table("classes"))
    classifier = _classifier(top.table("classifier"), num_classes, owner, folder)
    sensor = _sensor(top.table("sensor"), kinds=True)
    odometry, geometric = _noise(top.table("noise"), object_kind(sensor.objects).dim)
    return RobotModel(num_classes, prior, classifier, odometry, geometric, sensor)


def _classes(f: FieldReader) -> tuple[int, tuple[float, ...]]:
    f.check_keys({"count", "prior"})
    m = f.integer("count", minimum=2, maximum=MAX_CLASSES)
    if not f.has("prior"):
        return m, tuple([1.0 / m] * m)
    prior = f.vector("prior", m, positive=True)
    if abs(sum(prior) - 1.0) > _PRIOR_TOLERANCE:
        raise f.fail("prior", f"must sum to 1, sums to {sum(prior):.9g}")
    return m, tuple(prior)


def _classifier(
    f: FieldReader, m: int, owner: str, folder: Path | None, nested: bool = False
) -> ClassifierSpec:
    model = f.string("model")
    if model not in (*_CRAFTED_MODELS, "learned"):
        known = ", ".join(_CRAFTED_MODELS)
        raise f.fail(
            "model", f"unknown model {model!r} (known: {known}), or 'learned' with a model file"
        )
    if f.has("estimator"):
        if owner != "scenario" or nested:
            where = "a scenario's [classifier]" if nested else "a scenario"
            raise f.fail("estimator", f"only in {where}: here [classifier] is the robot's model")
        # [classifier.estimator] is read by _estimator_classifier; the keys of the model
        # itself are checked (and listed in errors) exactly as in a robot model file.
        f = FieldReader(f.label, {k: v for k, v in f.raw.items() if k != "estimator"}, f.path)
    if model == "learned":
        f.check_keys({"model", "file"})
        return _learned(f, m, owner, folder)
    if model == "paper":
        f.check_keys({"model", "viewpoint"})
        if m != 2:
            raise f.fail("model", f"the paper model has 2 classes, the {owner} has {m}")
        return ClassifierSpec("paper", viewpoint=_viewpoint(f))
    f.check_keys({"model", "alias", "best_view_deg", "noise_std", "viewpoint"})
    alias_arr = f.array("alias")
    if len(alias_arr.raw) != m:
        raise f.fail("alias", f"expected {m} class numbers, got {len(alias_arr.raw)}")
    alias = []
    for c in range(m):
        a = alias_arr.integer(c)
        if not 1 <= a <= m:
            raise alias_arr.fail(c, f"class {a} is out of range 1..{m}")
        if a == c + 1:
            raise alias_arr.fail(c, f"class {a} cannot be its own alias")
        alias.append(a - 1)
    best = f.vector("best_view_deg", m)
    noise_std = f.number("noise_std", positive=True)
    return ClassifierSpec("aliased", tuple(alias), tuple(best), noise_std, viewpoint=_viewpoint(f))


def _viewpoint(f: FieldReader) -> str:
    """A crafted model's viewpoint convention; a file that omits it means object → camera."""
    if not f.has("viewpoint"):
        return OBJECT_TO_CAMERA
    convention = f.string("viewpoint")
    if convention not in VIEWPOINTS:
        known = ", ".join(VIEWPOINTS)
        raise f.fail("viewpoint", f"unknown convention {convention!r} (known: {known})")
    return convention


def _estimator_classifier(f: FieldReader, m: int, folder: Path | None) -> ClassifierSpec | None:
    if not f.has("estimator"):
        return None
    return _classifier(f.table("estimator"), m, "scenario", folder, nested=True)


def _learned(f: FieldReader, m: int, owner: str, folder: Path | None) -> ClassifierSpec:
    """A learned model file, read and validated now: a path relative to ``folder``, kept
    absolute (a robot model written elsewhere still names the same file)."""
    name = f.string("file")
    if not name:
        raise f.fail("file", "must name a learned model file (.npz)")
    path = Path(name).expanduser()
    path = (path if path.is_absolute() else (folder or Path.cwd()) / path).resolve()
    try:
        learned, digest = load_learned(path)
    except LearnedFileError as exc:
        raise f.fail("file", str(exc)) from None
    if learned.num_classes != m:
        classes = learned.num_classes
        reason = f"{path}: holds a model of {classes} classes, the {owner} has {m}"
        raise f.fail("file", reason)
    return ClassifierSpec("learned", file=str(path), digest=digest)


def _noise(f: FieldReader, detection_dim: int) -> tuple[GaussianNoise, GaussianNoise]:
    """``geometric_var``: (x, y, θ) of a relative pose, or (bearing, range) of a point
    (``[sensor] objects``); ``geometric_kernel``: the loss the estimators put on a detection's
    residual ("gaussian", the default, or "huber": ``estimator.models.noise``)."""
    f.check_keys({"odometry_var", "geometric_var", "geometric_kernel"})
    odometry = GaussianNoise(tuple(f.vector("odometry_var", 3, positive=True)))
    kernel = "gaussian"
    if f.has("geometric_kernel"):
        kernel = f.string("geometric_kernel")
        if kernel not in KERNELS:
            raise f.fail("geometric_kernel", f"{kernel!r}: expected one of {', '.join(KERNELS)}")
    variances = tuple(f.vector("geometric_var", detection_dim, positive=True))
    return odometry, GaussianNoise(variances, kernel)


def _sensor(f: FieldReader, kinds: bool = False) -> Sensor:
    """A ``[sensor]`` table; ``kinds``: it may say what it measures (``objects``, the model's
    sensor; a robot's own ``sensor`` shares the model's)."""
    f.check_keys({"half_angle_deg", "range", "objects"} if kinds else {"half_angle_deg", "range"})
    half = f.number("half_angle_deg", positive=True)
    if half > 180.0:
        raise f.fail("half_angle_deg", f"{half} must be ≤ 180")
    objects = f.string("objects") if f.has("objects") else "pose"
    if objects not in OBJECT_KINDS:
        raise f.fail(
            "objects", f"{objects!r} is not an object kind (known: {', '.join(OBJECT_KINDS)})"
        )
    return Sensor(math.radians(half), f.number("range", positive=True), objects)


def _check_id(f: FieldReader, key: str | int, value: str) -> None:
    if not _ID_PATTERN.match(value):
        raise f.fail(key, f"{value!r} is not a valid robot id ({ROBOT_ID_RULE})")


def _robots(top: FieldReader, steps: int, default_sensor: Sensor) -> tuple[Robot, ...]:
    robots: list[Robot] = []
    seen: set[str] = set()
    entries = top.tables("robots")
    if not entries:
        raise top.fail("robots", "at least one robot is required")
    for f in entries:
        f.check_keys({"id", "start", "actions", "turns", "speed", "sensor"})
        rid = f.string("id")
        _check_id(f, "id", rid)
        if rid in seen:
            raise f.fail("id", f"duplicate robot id {rid!r}")
        seen.add(rid)
        start = tuple(f.vector("start", 3))
        actions = _actions(f, steps)
        sensor = default_sensor
        if f.has("sensor"):
            own = _sensor(f.table("sensor"))
            sensor = dataclasses.replace(own, objects=default_sensor.objects)
        robots.append(Robot(rid, start, actions, sensor))  # type: ignore[arg-type]
    return tuple(robots)


def _actions(f: FieldReader, steps: int) -> tuple[tuple[float, float, float], ...]:
    if f.has("actions") == f.has("turns"):
        raise f.fail(None, "give exactly one of 'actions' or 'turns'")
    if f.has("actions"):
        if f.has("speed"):
            raise f.fail("speed", "only used with 'turns'")
        arr = f.array("actions")
        if len(arr.raw) != steps:
            raise f.fail("actions", f"expected {steps} actions (one per step), got {len(arr.raw)}")
        return tuple(tuple(arr.vector(i, 3)) for i in range(steps))  # type: ignore[misc]
    speed = f.number("speed") if f.has("speed") else 0.25
    runs = f.array("turns")
    parsed: list[tuple[int, float]] = []
    for i in range(len(runs.raw)):
        run = runs.array(i)
        if len(run.raw) != 2:
            raise runs.fail(i, f"expected [count, turn_rad], got {len(run.raw)} values")
        parsed.append((run.integer(0, minimum=1), run.number(1)))
    total = sum(count for count, _ in parsed)
    if total != steps:
        raise f.fail("turns", f"counts add up to {total} steps, the scenario has {steps}")
    return tuple((speed, 0.0, omega) for count, omega in parsed for _ in range(count))


def _objects(
    top: FieldReader, m: int, kind: str = "pose", drawn: bool = False
) -> tuple[Object, ...]:
    """``kind`` "point": a point object has no heading (its viewpoint is read in the world
    frame), so its yaw must be 0 rather than be silently ignored. ``drawn``: the scenario has a
    ``class_seed``, its classes are drawn per run and an object may not state one (its class
    here is a placeholder, replaced by run seed 0's draw)."""
    objects: list[Object] = []
    seen: set[int] = set()
    for f in top.tables("objects"):
        f.check_keys({"id", "pose", "class"})
        oid = f.integer("id", minimum=0)
        if oid in seen:
            raise f.fail("id", f"duplicate object id {oid}")
        seen.add(oid)
        pose = tuple(f.vector("pose", 3))
        if kind == "point" and pose[2] != 0.0:
            raise f.fail("pose", f"a point object has no heading: yaw {pose[2]:g} must be 0")
        if drawn:
            if f.has("class"):
                raise f.fail("class", "the scenario has a class_seed: classes are drawn per run")
            objects.append(Object(oid, pose, 0))  # type: ignore[arg-type]
            continue
        cls = f.integer("class")
        if not 1 <= cls <= m:
            raise f.fail("class", f"{cls} is out of range 1..{m}")
        objects.append(Object(oid, pose, cls - 1))  # type: ignore[arg-type]
    return tuple(objects)


def _communication(f: FieldReader, steps: int, robot_ids: list[str]) -> Communication:
    f.check_keys({"mode", "range", "schedule"})
    comm_range = f.number("range", positive=True) if f.has("range") else None
    schedule: list[ScheduleEdge] = []
    if f.has("schedule"):
        arr = f.array("schedule")
        for i in range(len(arr.raw)):
            e = arr.array(i)
            if len(e.raw) != 4:
                raise arr.fail(i, f"expected [from_step, to_step, robot_a, robot_b], got {e.raw!r}")
            first, last = e.integer(0, minimum=1), e.integer(1, minimum=1)
            if not first <= last <= steps:
                raise arr.fail(i, f"steps must satisfy 1 ≤ {first} ≤ {last} ≤ {steps}")
            a, b = e.string(2), e.string(3)
            for j, rid in ((2, a), (3, b)):
                if rid not in robot_ids:
                    raise e.fail(j, f"unknown robot {rid!r}")
            if a == b:
                raise arr.fail(i, f"an edge needs two different robots, got {a!r} twice")
            schedule.append(ScheduleEdge(first, last, a, b))
    default = "schedule" if f.has("schedule") else "range"
    mode = f.string("mode") if f.has("mode") else default
    if mode not in COMM_MODES:
        raise f.fail("mode", f"unknown mode {mode!r} (known: {', '.join(COMM_MODES)})")
    if mode in ("range", "both") and comm_range is None:
        raise f.fail("range", f"missing required field (mode {mode!r} needs it)")
    if mode in ("schedule", "both") and not f.has("schedule"):
        raise f.fail("schedule", f"missing required field (mode {mode!r} needs it)")
    return Communication(mode, comm_range, tuple(schedule))
