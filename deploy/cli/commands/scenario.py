"""`semfleet scenario show | plot | generate | model` (`frames`: commands/scenario_frames.py)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.base.errors import UsageError
from deploy.base.files import write_atomically, write_text_atomically
from deploy.cli.args import class_count, positive_int, seed
from deploy.cli.commands import scenario_frames
from deploy.cli.outputs import add_force, figure_file, new_file
from deploy.cli.scenario_args import add_scenario_arguments, scenario_from_args
from deploy.study.scenario_show import default_cone_steps, render_show, save_ground_truth_plot
from sim.generate import dump_scenario, generate_scenario
from sim.loader import parse_scenario
from sim.robot_model import dump_robot_model
from sim.scenario import Scenario, ScenarioError


def run_show(args: argparse.Namespace, console: Console) -> int:
    render_show(scenario_from_args(args), console, args.overrides)
    return 0


def run_plot(args: argparse.Namespace, console: Console) -> int:
    scenario = scenario_from_args(args)
    cones = default_cone_steps(scenario.steps) if args.cones is None else args.cones
    bad = [k for k in cones if not 0 <= k <= scenario.steps]
    if bad:
        raise ScenarioError(f"--cones: steps {bad} are outside 0..{scenario.steps}")
    path, note = figure_file(args.output, "--output", args.force, scenario.name)
    write_atomically(path, lambda tmp: save_ground_truth_plot(scenario, tmp, cones))
    console.print(f"wrote {path}" + (f" ({note})" if note else ""), markup=False, highlight=False)
    return 0


def run_generate(args: argparse.Namespace, console: Console) -> int:
    for option, value in (
        ("--area", args.area),
        ("--comm-range", args.comm_range),
        ("--twins", args.twins),
    ):
        if value is not None and not 0 < value < math.inf:
            raise UsageError(f"{option} {value}: must be a positive number of metres")
    out = new_file(Path(args.output), "--output", args.force)
    scenario = generate_scenario(
        robots=args.robots,
        objects=args.objects,
        classes=args.classes,
        seed=args.seed,
        steps=args.steps,
        area=args.area,
        comm_range=args.comm_range,
        kind=args.kind,
        twins=args.twins,
    )
    text = dump_scenario(scenario)
    try:  # never write a file that cannot be read back
        parse_scenario(text, args.output)
    except ScenarioError as exc:
        raise UsageError(f"the generated world would not load: {exc}") from None
    write_text_atomically(out, text)
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


def run_model(args: argparse.Namespace, console: Console) -> int:
    out = new_file(Path(args.output), "--output", args.force)
    text = model_text(scenario_from_args(args), args.robot)
    write_text_atomically(out, text)
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
    plot.add_argument(
        "-o",
        "--output",
        required=True,
        help="the figure to write: .png, .pdf or .svg (no suffix: .png is added; a folder: "
        "FOLDER/<scenario>.png)",
    )
    add_force(plot)
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
    gen.add_argument(
        "--kind",
        choices=("pose", "point"),
        default="pose",
        help="objects with a pose, detected by relative pose (default), or point landmarks "
        "detected by bearing and range",
    )
    gen.add_argument(
        "--twins",
        type=float,
        default=None,
        metavar="METRES",
        help="give every object a twin this far away, of another class (objects closer than "
        "the noise, which only classes tell apart)",
    )
    gen.add_argument("-o", "--output", required=True, help="TOML file to write")
    add_force(gen)
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
    add_force(model)
    model.set_defaults(run=run_model)

    scenario_frames.add_parser(ssub)
