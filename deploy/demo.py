"""`semfleet demo`: the most complete thing semfleet can show so far.

Until the agents exist (issue 5) the demo loads the paper's scenario, prints its summary, simulates
one seeded run of every robot's sensor frames and draws the ground truth.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from deploy.scenario_cmd import render_show, save_ground_truth_plot
from sim.loader import load_scenario
from sim.sensors import Simulator


def run(args: argparse.Namespace, console: Console) -> int:
    console.rule("semfleet demo")
    console.print(
        "The estimators and agents are not built yet; this demo shows the paper's scenario and "
        "one seeded run of simulated sensor data."
    )
    scenario = load_scenario("paper")
    render_show(scenario, console)
    sim = Simulator(scenario, args.seed)
    table = Table(title=f"simulated sensor frames (seed {args.seed})")
    for col in (
        "robot",
        "frames",
        "detections",
        "odometry |Δ| mean [m]",
        "mean score of true class",
    ):
        table.add_column(col)
    for rid, frames in sim.all_frames().items():
        dets = [
            (d, scenario.objects[scenario.object_ids.index(d.object_id)].class_index)
            for f in frames
            for d in f.detections
        ]
        odo = np.mean([np.hypot(*f.odometry[:2]) for f in frames])
        true_score = np.mean([d.z_sem[c] for d, c in dets]) if dets else float("nan")
        table.add_row(rid, str(len(frames)), str(len(dets)), f"{odo:.3f}", f"{true_score:.3f}")
    console.print(table)
    out = Path(args.out)
    png = save_ground_truth_plot(scenario, out / "paper-ground-truth.png", [20, 40, 60])
    console.print(f"wrote {png}")
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("demo", help="show what semfleet can do (the README's first command)")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated run (default 1)")
    p.add_argument("--out", default="out/demo", help="folder for outputs (default out/demo)")
    p.set_defaults(run=run)
