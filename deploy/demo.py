"""`semfleet demo`: the most complete thing semfleet can show so far.

Until the Zenoh agents exist (issue 5) the demo runs the paper's scenario once, in one process:
every method of the study (local, distributed, double counting, centralized) on the same seeded
sensor data, then prints the comparison and writes the plots.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.args import seed
from deploy.results import summarise, write_results
from deploy.scenario_cmd import render_show, save_ground_truth_plot
from deploy.study import METHODS, run_single
from deploy.study_cmd import render_summary, write_plots
from estimator.hybrid import BeliefConfig
from sim.loader import load_scenario


def run(args: argparse.Namespace, console: Console) -> int:
    console.rule("semfleet demo")
    console.print(
        "The Zenoh agents are not built yet: this demo runs the paper's 3-robot fleet in one "
        "process (in-memory transport, the paper's communication schedule), every method on the "
        f"same sensor data of seed {args.seed}."
    )
    scenario = load_scenario("paper")
    render_show(scenario, console)
    out = Path(args.out)
    png = save_ground_truth_plot(scenario, out / "paper-ground-truth.png", [20, 40, 60])
    start = time.perf_counter()
    with console.status("running local, distributed, double_count and centralized …"):
        result = run_single(scenario, list(METHODS), args.seed, BeliefConfig(), scenario.steps)
    doc = summarise(scenario.name, [result], list(METHODS), {"demo": True})
    write_results(out, doc, [result], list(METHODS))
    render_summary(doc, console, [15, 30, 45, scenario.steps])
    plots = write_plots(out, doc, scenario, [result], scenario.steps, scenario.robot_ids[0])
    console.print(
        f"ran in {time.perf_counter() - start:.1f} s; wrote {png}, {out / 'results.json'} and "
        f"{len(plots)} plots in {out}"
    )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("demo", help="show what semfleet can do (the README's first command)")
    p.add_argument("--seed", type=seed, default=0, help="seed of the simulated run (default 0)")
    p.add_argument("--out", default="out/demo", help="folder for outputs (default out/demo)")
    p.set_defaults(run=run)
