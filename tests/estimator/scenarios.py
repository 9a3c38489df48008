"""Tiny hand-made scenarios for estimator tests, built through the real scenario loader."""

from __future__ import annotations

import math

from sim.loader import parse_scenario
from sim.scenario import Scenario

_TEMPLATE = """
format = 1
name = "tiny"
steps = {steps}
[classes]
count = 2
[classifier]
model = "paper"
[noise]
odometry_var = {odometry_var}
geometric_var = {geometric_var}
[sensor]
half_angle_deg = 60.0
range = {sensing}
[communication]
mode = "range"
range = 10.0
[[robots]]
id = "r1"
start = [0.0, 0.0, 0.0]
speed = {speed}
turns = [[{steps}, 0.0]]
"""


def tiny_scenario(
    objects: list[tuple[float, float, float, int]],
    steps: int = 5,
    speed: float = 0.25,
    sensing: float = 6.0,
    noise_scale: float = 1.0,
) -> Scenario:
    """One robot driving along +x from the origin; ``objects`` are (x, y, yaw_deg, class 1..2)."""
    odometry = [v * noise_scale for v in (0.003, 0.003, 0.001)]
    geometric = [v * noise_scale for v in (0.1, 0.1, 0.01)]
    text = _TEMPLATE.format(
        steps=steps, speed=speed, sensing=sensing, odometry_var=odometry, geometric_var=geometric
    )
    for i, (x, y, yaw_deg, c) in enumerate(objects, start=1):
        text += f"[[objects]]\nid = {i}\npose = [{x}, {y}, {math.radians(yaw_deg)}]\nclass = {c}\n"
    return parse_scenario(text, "tiny.toml")
