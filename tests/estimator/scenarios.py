"""Tiny hand-made scenarios for tests, built through the real scenario loader."""

from __future__ import annotations

import math
from collections.abc import Sequence

from sim.loader import parse_scenario
from sim.scenario import Scenario

RANGE_10_M = 'mode = "range"\nrange = 10.0'


def fleet_text(
    name: str,
    steps: int,
    robot_ys: Sequence[float],
    objects: Sequence[tuple[float, float, float, int]],
    *,
    description: str = "",
    speed: float = 0.25,
    half_angle_deg: float = 60.0,
    sensing: float = 4.0,
    communication: str = RANGE_10_M,
    odometry_var: Sequence[float] = (0.003, 0.003, 0.001),
    geometric_var: Sequence[float] = (0.1, 0.1, 0.01),
) -> str:
    """Scenario TOML: two classes (uniform prior, the paper's classifier), robots r1, r2, …
    starting at (0, y, 0) for each y of ``robot_ys`` and driving straight along +x at ``speed``
    m per step, objects 1, 2, … at ``objects`` (x, y, yaw in radians, class 1..2), and the
    ``communication`` table's body."""
    text = f"""\
format = 1
name = "{name}"
description = "{description}"
steps = {steps}
[classes]
count = 2
prior = [0.5, 0.5]
[classifier]
model = "paper"
[noise]
odometry_var = {list(odometry_var)}
geometric_var = {list(geometric_var)}
[sensor]
half_angle_deg = {half_angle_deg}
range = {sensing}
[communication]
{communication}
"""
    for i, y in enumerate(robot_ys, start=1):
        text += f'\n[[robots]]\nid = "r{i}"\nstart = [0.0, {y}, 0.0]\n'
        text += f"speed = {speed}\nturns = [[{steps}, 0.0]]\n"
    for i, (x, y, yaw, c) in enumerate(objects, start=1):
        text += f"\n[[objects]]\nid = {i}\npose = [{x}, {y}, {yaw}]\nclass = {c}\n"
    return text


def tiny_scenario(
    objects: list[tuple[float, float, float, int]],
    steps: int = 5,
    speed: float = 0.25,
    sensing: float = 6.0,
    noise_scale: float = 1.0,
) -> Scenario:
    """One robot driving along +x from the origin; ``objects`` are (x, y, yaw_deg, class 1..2)."""
    text = fleet_text(
        "tiny",
        steps,
        [0.0],
        [(x, y, math.radians(yaw_deg), c) for x, y, yaw_deg, c in objects],
        speed=speed,
        sensing=sensing,
        odometry_var=[v * noise_scale for v in (0.003, 0.003, 0.001)],
        geometric_var=[v * noise_scale for v in (0.1, 0.1, 0.01)],
    )
    return parse_scenario(text, "tiny.toml")


def objects_ahead(robot_ys: Sequence[float]) -> list[tuple[float, float, float, int]]:
    """Two objects just ahead of each robot starting at (0, y) (seen from k = 1 with a 3.5 m,
    50° sensor), classes alternating: object ids 2i + 1, 2i + 2 belong to robot i."""
    return [
        (x, y + dy, 0.4, 1 + (i + j) % 2)
        for i, y in enumerate(robot_ys)
        for j, (x, dy) in enumerate(((2.0, 0.3), (2.8, -0.6)))
    ]
