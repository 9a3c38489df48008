"""A scenario shown to its user: as tables (`scenario show`, `demo`) and as a ground-truth
plot (`scenario plot`, `demo`)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from sim.scenario import ClassifierSpec, Scenario
from sim.world import World


def link_intervals(world: World) -> list[tuple[str, str, list[tuple[int, int]]]]:
    """For every robot pair that ever links: the maximal runs of steps [first, last] it may talk."""
    ids = world.scenario.robot_ids
    steps = world.scenario.steps
    per_step = [world.links(k) for k in range(1, steps + 1)]
    out = []
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            runs: list[tuple[int, int]] = []
            for k, links in enumerate(per_step, start=1):
                if (a, b) not in links:
                    continue
                if runs and runs[-1][1] == k - 1:
                    runs[-1] = (runs[-1][0], k)
                else:
                    runs.append((k, k))
            if runs:
                out.append((a, b, runs))
    return out


def render_show(scenario: Scenario, console: Console, overrides: Sequence[str] = ()) -> None:
    """Print the scenario as tables: overview, robots, objects, communication. ``overrides``:
    the ``--set FIELD=VALUE`` texts it was loaded with, named in the header."""
    world = World(scenario)
    s = scenario
    variants = ", ".join(s.applied_variants) or "none"
    changed = "".join(f"; --set {o}" for o in overrides)
    console.print(
        f"[bold]{escape(s.name)}[/bold] ({escape(s.source)}, variants applied: "
        f"{escape(variants + changed)})"
    )
    if s.description:
        # The file's own words, which no variant or override rewrites: the lines below and the
        # tables are the world as loaded.
        before = "the file's description, before variants and --set: "
        console.print((before if s.applied_variants or overrides else "") + s.description)
    prior = ", ".join(f"{p:.3g}" for p in s.class_prior)
    console.print(
        f"steps 1..{s.steps} · {len(s.robots)} robots · {len(s.objects)} objects · "
        f"M = {s.num_classes} classes, prior [{prior}] · classifier {s.classifier.model}"
        + _convention(s.classifier)
    )
    console.print(
        f"noise variances: odometry {list(s.odometry_noise.variances)}, "
        f"geometric {list(s.geometric_noise.variances)}"
        + ("" if s.geometric_noise.kernel == "gaussian" else f" ({s.geometric_noise.kernel})")
    )
    console.print(_sensing(s))
    comm = s.communication
    rng = f", range {comm.range:g} m" if comm.range is not None else ""
    console.print(f"communication: mode {comm.mode}{rng}")
    if s.variants:
        console.print("variants: " + "; ".join(f"{v.name} — {v.description}" for v in s.variants))

    robots = Table(title="robots")
    for col in ("id", "start (x, y, θ)", "sensor", "path [m]", "first sighting", "objects seen"):
        robots.add_column(col)
    for r in s.robots:
        traj = world.trajectories[r.id]
        length = float(sum(math.hypot(*(b[:2] - a[:2])) for a, b in itertools.pairwise(traj)))
        first = world.first_sighting(r.id)
        seen = world.known_objects(r.id, s.steps)
        robots.add_row(
            r.id,
            f"({r.start[0]:.2f}, {r.start[1]:.2f}, {r.start[2]:.3f})",
            f"{math.degrees(r.sensor.half_angle):g}°, {r.sensor.range:g} m",
            f"{length:.1f}",
            "never" if first is None else f"k = {first}",
            f"{len(seen)}: {', '.join(map(str, seen))}",
        )
    console.print(robots)

    objects = Table(title="objects")
    for col in ("id", "x", "y", "yaw [°]", "class", "first seen by"):
        objects.add_column(col)
    for j, o in enumerate(s.objects):
        firsts = []
        for r in s.robots:
            ks = world.visibility[r.id][:, j].nonzero()[0]
            if len(ks):
                firsts.append(f"{r.id}@{int(ks[0])}")
        objects.add_row(
            str(o.id),
            f"{o.pose[0]:g}",
            f"{o.pose[1]:g}",
            f"{math.degrees(o.pose[2]):.1f}",
            str(o.class_index + 1),
            ", ".join(firsts) or "nobody",
        )
    console.print(objects)

    edges = Table(title=f"communication edges over time ({comm.mode})")
    edges.add_column("pair")
    edges.add_column("steps")
    for a, b, runs in link_intervals(world):
        edges.add_row(f"{a}–{b}", ", ".join(f"{f}–{t}" if f != t else str(f) for f, t in runs))
    console.print(edges)


def save_ground_truth_plot(scenario: Scenario, out: Path, cone_steps: list[int]) -> Path:
    """Draw the ground truth of ``scenario`` into the PNG ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from deploy.study.plots import plot_ground_truth

    fig, ax = plt.subplots(figsize=(8, 8))
    plot_ground_truth(ax, World(scenario), cone_steps)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out


def _sensing(s: Scenario) -> str:
    """The robots' sensors as loaded: one for all, or each robot's."""
    sensors = {
        r.id: f"{math.degrees(r.sensor.half_angle):g}°, {r.sensor.range:g} m" for r in s.robots
    }
    if len(set(sensors.values())) == 1:
        return f"sensing: {next(iter(sensors.values()))} (half angle, range; every robot)"
    return "sensing (half angle, range): " + "; ".join(f"{r} {t}" for r, t in sensors.items())


def default_cone_steps(steps: int, count: int = 3) -> list[int]:
    """``count`` evenly spaced steps ending at the last one (20 40 60 for 60 steps, as in the
    paper's Fig. 2a), without repeats when the world has fewer steps than that."""
    return sorted({max(1, round(steps * i / count)) for i in range(1, count + 1)})


def _convention(c: ClassifierSpec) -> str:
    """The viewpoint convention of a crafted model (a learned model's file states its own)."""
    return "" if c.model == "learned" else f", viewpoint {c.viewpoint.replace('_', ' ')}"
