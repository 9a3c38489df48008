"""`semfleet demo`: the README's first command.

Launches the paper's 3-robot fleet as three agent processes talking over Zenoh on loopback, in
lock-step with a conductor that simulates the world, shows a live table while they run, then the
comparison of every robot's local and distributed belief and the paper's plots.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from deploy.cli.args import seed
from deploy.cli.commands import ros2_options
from deploy.cli.commands.launch import SECURE_HELP, check_outputs
from deploy.cli.outputs import add_force
from deploy.launch import LaunchPlan
from deploy.launch.report import aoi_entry, counters_table, security_line, write_outputs
from deploy.launch.rerun_view import add_options as add_view_options
from deploy.launch.rerun_view import launch_recorded
from deploy.study.scenario_show import render_show, save_ground_truth_plot
from sim.loader import load_scenario

STUDY_HINT = (
    "semfleet study --scenario paper --methods local,distributed,double_count,centralized "
    "--runs 100"
)


def final_table(doc: dict[str, Any], steps: int) -> Table:
    """Local vs distributed at the final step, mean over robots."""
    t = Table(title=f"paper scenario, final step k = {steps}: mean over robots")
    t.add_column("metric")
    t.add_column("local", justify="right")
    t.add_column("distributed", justify="right")
    for metric in ("msde", "robot_error", "object_error", "robot_sqrt_det", "hypotheses"):
        cells = []
        for method in ("local", "distributed"):
            value = doc["methods"][method]["mean"][metric][steps - 1]
            cells.append("—" if value is None else f"{value:.4f}")
        t.add_row(metric, *cells)
    return t


def run(args: argparse.Namespace, console: Console) -> int:
    start = time.perf_counter()
    scenario = load_scenario("paper")
    ros2 = ros2_options.ros2_table(args, scenario, list(scenario.robot_ids))
    check_outputs(args)
    bag = ros2_options.bag_settings(args, scenario, list(scenario.robot_ids), ros2)
    console.rule("semfleet demo")
    render_show(scenario, console)
    out = Path(args.out)
    png = save_ground_truth_plot(scenario, out / "paper-ground-truth.png", [20, 40, 60])
    plan = LaunchPlan(
        scenario,
        args.seed,
        list(scenario.robot_ids),
        out,
        mode="lockstep",
        secure=args.secure,
        keep_estimates=bool(args.view or args.record or args.ros2_bag),
        ros2=ros2,
    )
    console.print(
        f"launching {len(plan.robots)} agent processes (Zenoh on loopback, lock-step, seed "
        f"{plan.seed}); logs in {out / 'logs'}"
    )
    console.print(security_line(plan))
    if ros2 is not None:
        console.print(ros2_options.describe(ros2, plan.robots))
    start_ns = time.time_ns()
    outcome = launch_recorded(plan, console, args, f"demo seed {plan.seed}")
    console.print(counters_table(outcome))
    if bag is not None:
        ros2_options.write_recording(args, bag, plan, outcome, start_ns, console)
    launched = {"mode": plan.mode, "wall_s": outcome.wall_s, **aoi_entry(outcome, console)}
    doc = write_outputs(plan, outcome, console, {"demo": True, "launch": launched})
    console.print(final_table(doc, scenario.steps))
    console.print(
        f"demo took {time.perf_counter() - start:.1f} s (agents ran {outcome.wall_s:.1f} s); "
        f"ground truth in {png}. All four methods over 100 runs: {STUDY_HINT}"
    )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("demo", help="the paper's fleet as 3 agent processes over Zenoh")
    p.add_argument("--seed", type=seed, default=0, help="seed of the simulated run (default 0)")
    p.add_argument("--out", default="out/demo", help="folder for outputs (default out/demo)")
    p.add_argument("--secure", action="store_true", help=SECURE_HELP)
    add_view_options(p)
    ros2_options.add_options(p)
    add_force(p)
    p.set_defaults(run=run)
