"""A fixed world for the agents' and latency benchmarks: robots on a line, each with its own
objects (``line_world``)."""

from __future__ import annotations

import math


def line_world(n: int, steps: int, spacing: float = 8.0) -> str:
    """Scenario TOML: ``n`` robots ``spacing`` m apart on the x axis, driving slowly along +y, each
    with two objects just ahead of it, facing it (the paper classifier's informative viewpoint,
    ψ ≈ +90°, so classes converge); range communication at 10 m, so with the default spacing
    only neighbours hear each other."""
    lines = [
        "format = 1",
        f'name = "line{n}"',
        f"steps = {steps}",
        "[classes]\ncount = 2\nprior = [0.5, 0.5]",
        '[classifier]\nmodel = "paper"',
        "[noise]\nodometry_var = [0.003, 0.003, 0.001]\ngeometric_var = [0.1, 0.1, 0.01]",
        "[sensor]\nhalf_angle_deg = 50.0\nrange = 5.0",
        '[communication]\nmode = "range"\nrange = 10.0',
    ]
    for i in range(n):
        x = spacing * i
        lines.append(
            f'[[robots]]\nid = "r{i + 1}"\nstart = [{x}, 0.0, 1.5707963267948966]\n'
            f"speed = 0.1\nturns = [[{steps}, 0.0]]"
        )
    for i in range(n):
        x = spacing * i
        for j, (dx, dy) in enumerate(((-0.8, 2.5), (0.9, 3.5))):
            lines.append(
                f"[[objects]]\nid = {2 * i + j + 1}\npose = [{x + dx}, {dy}, {math.pi}]\n"
                f"class = {1 + (i + j) % 2}"
            )
    return "\n\n".join(lines) + "\n"
