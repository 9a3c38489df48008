"""Load and validate UFastSLAM world files (``kind = "ufastslam"``, format 1; docs/ufastslam.md).

The conventions are those of fleet scenarios (``sim.loader``): TOML, unknown keys rejected, angles
in radians except fields ending in ``_deg``, and every problem a :class:`ScenarioError` naming the
file, the field and the reason, e.g. ``rectangle.toml: groups[2].members[1]: unknown landmark 99``.
"""

from __future__ import annotations

import math
import re
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np

from sim.loader import FieldReader
from sim.scenario import FORMAT_VERSION, ScenarioError
from sim.ufastslam.world import (
    GROUP_KINDS,
    GROUP_TOLERANCE,
    Camera,
    FilterNoise,
    Leg,
    Odometry,
    RelationGroup,
    UWorld,
    group_residuals,
)

KIND = "ufastslam"
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_MAX_STEPS = 100_000
_MAX_LANDMARKS = 10_000
_DEFAULTS = {"relation_std": 0.05}


def _folder():  # type: ignore[no-untyped-def]
    return resources.files("sim") / "scenarios" / "ufastslam"


def bundled_worlds() -> list[str]:
    """Names of the worlds shipped in ``sim/scenarios/ufastslam``."""
    return sorted(p.name[:-5] for p in _folder().iterdir() if p.name.endswith(".toml"))


def load_world(source: str | Path) -> UWorld:
    """A world file (a path, or anything ending in .toml) or a bundled world by name."""
    path = Path(source)
    if path.suffix == ".toml" or path.exists():
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ScenarioError(f"{path}: no such world file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ScenarioError(f"{path}: cannot read: {exc}") from None
        return parse_world(text, str(path))
    name = str(source)
    if name not in bundled_worlds():
        known = ", ".join(bundled_worlds())
        raise ScenarioError(f"{name}: not a file and not a bundled world (bundled: {known})")
    return parse_world((_folder() / f"{name}.toml").read_text(encoding="utf-8"), f"{name}.toml")


def parse_world(text: str, label: str = "<string>") -> UWorld:
    """Validate TOML text into a :class:`UWorld`; ``label`` names the file in errors."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{label}: not valid TOML: {exc}") from None
    top = FieldReader(label, raw, "")
    version = top.integer("format")
    if version != FORMAT_VERSION:
        raise top.fail(
            "format", f"unsupported format {version} (this semfleet reads {FORMAT_VERSION})"
        )
    if not top.has("kind"):
        raise top.fail("kind", f'missing required field (a UFastSLAM world has kind = "{KIND}")')
    kind = top.string("kind")
    if kind != KIND:
        raise top.fail("kind", f'{kind!r}: a UFastSLAM world has kind = "{KIND}"')
    top.check_keys(
        {"format", "kind", "name", "description", "dt", "path", "odometry", "sensor", "filter"}
        | {"landmarks", "groups"}
    )
    dt = top.number("dt", positive=True)
    start, speed, turn_rate, legs = _path(top.table("path"))
    ids, xy = _landmarks(top)
    world = UWorld(
        name=top.string("name"),
        description=top.string("description") if top.has("description") else "",
        source=label,
        dt=dt,
        start=start,
        speed=speed,
        turn_rate=turn_rate,
        legs=legs,
        landmark_ids=ids,
        landmark_xy=xy,
        groups=_groups(top, ids, xy),
        odometry=_odometry(top.table("odometry")),
        camera=_camera(top.table("sensor")),
        filter_noise=_filter(top.table("filter")),
    )
    if world.steps > _MAX_STEPS:
        raise top.fail("path", f"the legs take {world.steps} steps, more than {_MAX_STEPS}")
    return world


def _non_negative(f: FieldReader, key: str) -> float:
    value = f.number(key)
    if value < 0:
        raise f.fail(key, f"{value} must be ≥ 0")
    return value


def _path(f: FieldReader) -> tuple[tuple[float, float, float], float, float, tuple[Leg, ...]]:
    f.check_keys({"start", "speed", "turn_rate_deg", "legs"})
    x, y, theta = f.vector("start", 3)
    speed = f.number("speed", positive=True)
    turn_rate = math.radians(f.number("turn_rate_deg", positive=True))
    legs = []
    entries = f.tables("legs")
    if not entries:
        raise f.fail("legs", "at least one leg is required")
    for leg in entries:
        leg.check_keys({"forward", "turn_deg"})
        if not (leg.has("forward") or leg.has("turn_deg")):
            raise leg.fail(None, "give 'forward' (m), 'turn_deg' or both")
        forward = _non_negative(leg, "forward") if leg.has("forward") else 0.0
        turn = math.radians(leg.number("turn_deg")) if leg.has("turn_deg") else 0.0
        if forward == 0.0 and turn == 0.0:
            raise leg.fail(None, "a leg must move or turn")
        legs.append(Leg(forward, turn))
    return (x, y, theta), speed, turn_rate, tuple(legs)


def _landmarks(top: FieldReader) -> tuple[tuple[int, ...], tuple[tuple[float, float], ...]]:
    arr = top.array("landmarks")
    if not arr.raw:
        raise top.fail("landmarks", "at least one landmark is required")
    if len(arr.raw) > _MAX_LANDMARKS:
        raise top.fail("landmarks", f"{len(arr.raw)} landmarks, more than {_MAX_LANDMARKS}")
    ids: list[int] = []
    xy: list[tuple[float, float]] = []
    for i in range(len(arr.raw)):
        entry = arr.array(i)
        if len(entry.raw) != 3:
            raise arr.fail(i, f"expected [id, x, y], got {len(entry.raw)} values")
        lid = entry.integer(0, minimum=0)
        if lid in ids:
            raise entry.fail(0, f"duplicate landmark id {lid}")
        ids.append(lid)
        xy.append((entry.number(1), entry.number(2)))
    return tuple(ids), tuple(xy)


def _groups(
    top: FieldReader, ids: tuple[int, ...], xy: tuple[tuple[float, float], ...]
) -> tuple[RelationGroup, ...]:
    if not top.has("groups"):
        return ()
    position = dict(zip(ids, xy, strict=True))
    out = []
    names: set[tuple[str, str]] = set()
    for f in top.tables("groups"):
        f.check_keys({"kind", "name", "members"})
        kind = f.string("kind")
        if kind not in GROUP_KINDS:
            raise f.fail("kind", f"unknown kind {kind!r} (known: {', '.join(GROUP_KINDS)})")
        name = f.string("name")
        if not _NAME.match(name):
            raise f.fail("name", f"{name!r} must be 1–64 of A–Z a–z 0–9 _ . -")
        if (kind, name) in names:
            raise f.fail("name", f"duplicate group {kind}:{name}")
        names.add((kind, name))
        arr = f.array("members")
        members: list[int] = []
        for i in range(len(arr.raw)):
            m = arr.integer(i, minimum=0)
            if m not in position:
                raise arr.fail(i, f"unknown landmark {m}")
            if m in members:
                raise arr.fail(i, f"landmark {m} listed twice")
            members.append(m)
        need = 3 if kind == "col" else 2
        if len(members) < need:
            raise f.fail("members", f"a {kind} group needs at least {need} landmarks")
        residual = group_residuals(kind, np.array([position[m] for m in members]))
        worst = int(np.argmax(np.abs(residual)))
        if abs(residual[worst]) > GROUP_TOLERANCE:
            raise arr.fail(
                worst,
                f"landmark {members[worst]} is {abs(residual[worst]):.3g} m off the group's "
                f"{'line' if kind == 'col' else kind + ' coordinate'}",
            )
        out.append(RelationGroup(kind, name, tuple(members)))
    return tuple(out)


def _odometry(f: FieldReader) -> Odometry:
    f.check_keys({"speed_std", "yaw_rate_std_deg", "scale_error", "yaw_rate_bias_deg"})
    scale = f.number("scale_error")
    if not -0.5 < scale < 0.5:
        raise f.fail("scale_error", f"{scale} must be within (−0.5, 0.5)")
    return Odometry(
        speed_std=_non_negative(f, "speed_std"),
        yaw_rate_std=math.radians(_non_negative(f, "yaw_rate_std_deg")),
        scale_error=scale,
        yaw_rate_bias=math.radians(f.number("yaw_rate_bias_deg")),
    )


def _camera(f: FieldReader) -> Camera:
    f.check_keys({"half_angle_deg", "range", "range_std", "bearing_std_deg"})
    half = f.number("half_angle_deg", positive=True)
    if half > 180.0:
        raise f.fail("half_angle_deg", f"{half} must be ≤ 180")
    return Camera(
        half_angle=math.radians(half),
        range=f.number("range", positive=True),
        range_std=f.number("range_std", positive=True),
        bearing_std=math.radians(f.number("bearing_std_deg", positive=True)),
    )


def _filter(f: FieldReader) -> FilterNoise:
    f.check_keys({"speed_std", "yaw_rate_std_deg", "relation_std"})
    relation = (
        f.number("relation_std", positive=True)
        if f.has("relation_std")
        else _DEFAULTS["relation_std"]
    )
    return FilterNoise(
        speed_std=f.number("speed_std", positive=True),
        yaw_rate_std=math.radians(f.number("yaw_rate_std_deg", positive=True)),
        relation_std=relation,
    )
