"""`semfleet export tum`: a results folder's trajectories (truth, L, D, …) as TUM files for evo
and other trajectory tools. Parses, calls :func:`deploy.study.tum.export_tum`, prints a table."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.base.output import figures_table
from deploy.cli.outputs import add_force, new_folder
from deploy.study.tum import TRUTH, export_tum


def _period(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text}: a step period is a positive number of seconds")
    return value


def run_tum(args: argparse.Namespace, console: Console) -> int:
    out = new_folder(Path(args.out), "--out", args.force)
    written = export_tum(Path(args.results), out, args.period)
    rows = [
        [
            str(f.seed),
            f.robot,
            f.source,
            str(f.poses),
            "—" if f.source == TRUTH or math.isnan(f.rmse_m) else f"{f.rmse_m:.4f}",
        ]
        for f in written
    ]
    headings = ["seed", "robot", "trajectory", "poses", "position RMSE (m)"]
    console.print(figures_table("TUM trajectories", headings, rows))
    estimates = [f for f in written if f.source != TRUTH]
    estimate = next((f for f in estimates if f.source == "distributed"), estimates[0])
    truth = estimate.path.with_name(f"{estimate.robot}_{TRUTH}.tum")
    console.print(f"wrote {len(written)} TUM files in {out}; compare with evo, e.g.")
    console.print(f"  evo_ape tum {truth} {estimate.path}", soft_wrap=True)  # to copy whole
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("export", help="write results in other tools' formats (TUM trajectories)")
    formats = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    tum = formats.add_parser(
        "tum", help="per run and robot: the true, L and D trajectories as TUM files (for evo)"
    )
    tum.add_argument("results", metavar="RESULTS_DIR", help="a folder of results.json/npz")
    tum.add_argument("-o", "--out", required=True, help="output folder (new or empty)")
    add_force(tum)
    tum.add_argument(
        "--period",
        type=_period,
        default=1.0,
        help="seconds per step: the timestamp of step k is k × period (default 1)",
    )
    tum.set_defaults(run=run_tum)
