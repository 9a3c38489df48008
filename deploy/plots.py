"""Plots. Each function draws on an axes it is given; none reads settings from the environment."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Wedge

from sim.world import World

_ROBOT_COLOURS = plt.get_cmap("tab10")
_CLASS_COLOURS = plt.get_cmap("Set1")


def plot_ground_truth(ax: Axes, world: World, cone_steps: Sequence[int] = ()) -> None:
    """Trajectories, objects with orientation and class colour, sensing cones at ``cone_steps``
    (like the paper's Fig. 2a)."""
    s = world.scenario
    for i, r in enumerate(s.robots):
        traj = world.trajectories[r.id]
        colour = _ROBOT_COLOURS(i % 10)
        ax.plot(traj[:, 0], traj[:, 1], "-", color=colour, lw=1.5, label=r.id)
        ax.plot(*traj[0, :2], "o", color=colour, ms=6)
        ax.annotate(r.id, traj[0, :2], textcoords="offset points", xytext=(4, 4), color=colour)
        for k in cone_steps:
            if not 0 <= k <= s.steps:
                continue
            x, y, t = traj[k]
            half = np.degrees(r.sensor.half_angle)
            ax.add_patch(
                Wedge(
                    (x, y),
                    r.sensor.range,
                    np.degrees(t) - half,
                    np.degrees(t) + half,
                    color=colour,
                    alpha=0.12,
                )
            )
            ax.plot(x, y, ">", color=colour, ms=5)
            ax.annotate(
                f"k={k}",
                (x, y),
                textcoords="offset points",
                xytext=(-8, 6),
                color=colour,
                fontsize=7,
            )
    poses = world.object_poses
    classes = s.object_classes()
    arrow = 0.6
    for c in range(s.num_classes):
        sel = classes == c
        if not sel.any():
            continue
        colour = _CLASS_COLOURS(c % 9)
        ax.scatter(
            poses[sel, 0],
            poses[sel, 1],
            s=40,
            color=colour,
            marker="s",
            label=f"class {c + 1}",
            zorder=3,
        )
        ax.quiver(
            poses[sel, 0],
            poses[sel, 1],
            arrow * np.cos(poses[sel, 2]),
            arrow * np.sin(poses[sel, 2]),
            color=colour,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            width=0.004,
            zorder=3,
        )
    for o, (x, y, _) in zip(s.objects, poses, strict=True):
        ax.annotate(str(o.id), (x, y), textcoords="offset points", xytext=(5, -10), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{s.name}: ground truth")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
