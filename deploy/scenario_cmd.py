"""`semfleet scenario show | plot | generate | model`."""

from __future__ import annotations

import argparse
import itertools
import math
import tomllib
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from deploy.args import class_count, positive_int, seed
from deploy.errors import UsageError
from sim.generate import dump_scenario, generate_scenario
from sim.loader import load_scenario, parse_scenario
from sim.robot_model import dump_robot_model
from sim.scenario import Scenario, ScenarioError
from sim.world import World


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments every command that reads a scenario shares."""
    p.add_argument("scenario", help="a scenario file (.toml) or a bundled name such as 'paper'")
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME",
        help="apply a variant defined in the file (repeatable), e.g. sense10, comm10",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        dest="overrides",
        help="override a field, e.g. --set sensor.range=10 (repeatable; TOML values)",
    )


def parse_override(text: str) -> tuple[str, Any]:
    """``FIELD=VALUE`` → (field, value); VALUE is read as a TOML value, else kept as a string."""
    field, sep, value = text.partition("=")
    if not sep or not field.strip():
        raise ScenarioError(f"--set {text!r}: expected FIELD=VALUE, e.g. sensor.range=10")
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    return field.strip(), parsed


def scenario_from_args(args: argparse.Namespace) -> Scenario:
    overrides = dict(parse_override(t) for t in args.overrides)
    return load_scenario(args.scenario, args.variant, overrides)


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


def render_show(scenario: Scenario, console: Console) -> None:
    """Print the scenario as tables: overview, robots, objects, communication."""
    world = World(scenario)
    s = scenario
    variants = ", ".join(s.applied_variants) or "none"
    console.print(f"[bold]{s.name}[/bold] ({s.source}, variants applied: {variants})")
    if s.description:
        console.print(s.description)
    prior = ", ".join(f"{p:.3g}" for p in s.class_prior)
    console.print(
        f"steps 1..{s.steps} · {len(s.robots)} robots · {len(s.objects)} objects · "
        f"M = {s.num_classes} classes, prior [{prior}] · classifier {s.classifier.model}"
    )
    console.print(
        f"noise variances: odometry {list(s.odometry_noise.variances)}, "
        f"geometric {list(s.geometric_noise.variances)}"
    )
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


def run_show(args: argparse.Namespace, console: Console) -> int:
    render_show(scenario_from_args(args), console)
    return 0


def save_ground_truth_plot(scenario: Scenario, out: Path, cone_steps: list[int]) -> Path:
    """Draw the ground truth of ``scenario`` into the PNG ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from deploy.plots import plot_ground_truth

    fig, ax = plt.subplots(figsize=(8, 8))
    plot_ground_truth(ax, World(scenario), cone_steps)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out


def default_cone_steps(steps: int, count: int = 3) -> list[int]:
    """``count`` evenly spaced steps ending at the last one (20 40 60 for 60 steps, as in the
    paper's Fig. 2a), without repeats when the world has fewer steps than that."""
    return sorted({max(1, round(steps * i / count)) for i in range(1, count + 1)})


def run_plot(args: argparse.Namespace, console: Console) -> int:
    scenario = scenario_from_args(args)
    cones = default_cone_steps(scenario.steps) if args.cones is None else args.cones
    bad = [k for k in cones if not 0 <= k <= scenario.steps]
    if bad:
        raise ScenarioError(f"--cones: steps {bad} are outside 0..{scenario.steps}")
    path = save_ground_truth_plot(scenario, Path(args.output), cones)
    console.print(f"wrote {path}")
    return 0


def run_generate(args: argparse.Namespace, console: Console) -> int:
    for option, value in (("--area", args.area), ("--comm-range", args.comm_range)):
        if value is not None and not 0 < value < math.inf:
            raise UsageError(f"{option} {value}: must be a positive number of metres")
    scenario = generate_scenario(
        robots=args.robots,
        objects=args.objects,
        classes=args.classes,
        seed=args.seed,
        steps=args.steps,
        area=args.area,
        comm_range=args.comm_range,
    )
    text = dump_scenario(scenario)
    try:  # never write a file that cannot be read back
        parse_scenario(text, args.output)
    except ScenarioError as exc:
        raise UsageError(f"the generated world would not load: {exc}") from None
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    console.print(f"wrote {out} ({scenario.name})")
    return 0


def model_text(scenario: Scenario, robot: str | None = None) -> str:
    """The robot model file of ``scenario`` (with ``robot``'s own sensor if given), headed by a
    comment that says where it comes from."""
    if robot is not None and robot not in scenario.robot_ids:
        known = ", ".join(scenario.robot_ids)
        raise ScenarioError(f"--robot: {robot!r} is not a robot of {scenario.name} ({known})")
    variants = ", ".join(scenario.applied_variants) or "none"
    sensor = "the default [sensor]" if robot is None else f"robot {robot}'s own"
    origin = f"robot model of scenario {scenario.name} ({scenario.source}, variants: {variants})"
    # A name or path with a line break must not end the comment early.
    header = f"# {' '.join(origin.split())}\n# sensor: {sensor}\n"
    return header + dump_robot_model(scenario.robot_model(robot))


def write_new_file(out: Path, text: str, force: bool) -> None:
    """Write ``text`` to ``out``; an existing file is an error unless ``force``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with out.open("w" if force else "x", encoding="utf-8") as f:
            f.write(text)
    except FileExistsError:
        raise FileExistsError(f"{out}: already exists (--force overwrites it)") from None


def run_model(args: argparse.Namespace, console: Console) -> int:
    text = model_text(scenario_from_args(args), args.robot)
    out = Path(args.output)
    write_new_file(out, text, args.force)
    console.print(f"wrote {out}:", markup=False, highlight=False, soft_wrap=True)
    console.print(text, markup=False, highlight=False, soft_wrap=True, end="")
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("scenario", help="inspect, plot and generate scenario files")
    ssub = p.add_subparsers(
        dest="scenario_command", required=True, metavar="show|plot|generate|model"
    )
    show = ssub.add_parser("show", help="tables: robots, objects, first sightings, comm edges")
    add_scenario_arguments(show)
    show.set_defaults(run=run_show)
    plot = ssub.add_parser("plot", help="the ground truth as a PNG (like the paper's Fig. 2a)")
    add_scenario_arguments(plot)
    plot.add_argument("-o", "--output", required=True, help="PNG file to write")
    plot.add_argument(
        "--cones",
        type=int,
        nargs="*",
        default=None,
        metavar="K",
        help="steps at which to draw the sensing cones (default: 3 evenly spaced steps ending at "
        "the last one, 20 40 60 for 60 steps)",
    )
    plot.set_defaults(run=run_plot)
    gen = ssub.add_parser("generate", help="write a random world as a scenario file")
    gen.add_argument("--robots", type=positive_int, required=True)
    gen.add_argument("--objects", type=positive_int, required=True)
    gen.add_argument("--classes", type=class_count, required=True)
    gen.add_argument("--seed", type=seed, required=True)
    gen.add_argument("--steps", type=positive_int, default=60)
    gen.add_argument("--area", type=float, default=None, help="side of the square world [m]")
    gen.add_argument("--comm-range", type=float, default=10.0, help="communication range [m]")
    gen.add_argument("-o", "--output", required=True, help="TOML file to write")
    gen.set_defaults(run=run_generate)
    model = ssub.add_parser("model", help="write a scenario's robot model (for semfleet agent)")
    add_scenario_arguments(model)
    model.add_argument(
        "--robot",
        default=None,
        metavar="ID",
        help="take this robot's own sensor (default: [sensor])",
    )
    model.add_argument("-o", "--output", required=True, help="TOML file to write")
    model.add_argument("--force", action="store_true", help="overwrite an existing file")
    model.set_defaults(run=run_model)
    from deploy import framelog_cmd  # here: it imports this module

    framelog_cmd.add_parser(ssub)
