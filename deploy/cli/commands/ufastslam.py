"""`semfleet ufastslam`: parses the options, runs :func:`deploy.study.ufastslam.run_all`, writes
its archive and plots, prints the table (docs/ufastslam.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from deploy.base.errors import UsageError
from deploy.base.output import runs_done
from deploy.cli.args import MAX_SEED, positive_int, seed
from deploy.cli.outputs import add_force, new_folder
from deploy.study.archive import write_archive

# filter_config: imported from here by bench/bench_ufastslam.py before issue 12.
from deploy.study.ufastslam import RELATION_CHOICES, run_all, ufastslam_archive
from sim.ufastslam import load_world


def render(doc: dict[str, Any], console: Console) -> None:
    runs = doc["runs"]
    table = Table(
        title=f"{doc['scenario']}: {runs} run{'s' if runs != 1 else ''}, "
        f"{doc['particles']} particles, mean over runs (metres)"
    )
    table.add_column("method")
    for col in ("pose\nRMSE", "landmark\nRMSE", "final\nerror", "relations\ntrue / false"):
        table.add_column(col, justify="right")
    table.add_column("ms per\nstep", justify="right")
    for entry in doc["table"].values():
        rel = (
            f"{entry['relations_true']:.1f} / {entry['relations_false']:.1f}"
            if "relations_true" in entry
            else "—"
        )
        table.add_row(
            entry["label"].replace(" (", "\n("),
            f"{entry['pose_rmse']:.3f}",
            f"{entry['landmark_rmse']:.3f}",
            f"{entry['final_error']:.3f}",
            rel,
            f"{entry['step_ms']:.3f}",
        )
    console.print(table)
    nees = ", ".join(
        f"{e['label']} {e['pose_nees']:.1f} / {100 * e['nees_over_bound']:.0f} %"
        for e in doc["table"].values()
        if "pose_nees" in e
    )
    console.print(
        "pose NEES (3 dof; median over steps, mean over runs; 3 if consistent) / steps above the "
        f"χ² 99 % bound: {nees}"
    )
    relations = doc["methods"]["semantic_ufastslam"]["relations"]
    if relations != "off":
        console.print(
            f"Semantic UFastSLAM ({relations}) has a lower pose RMSE than UFastSLAM on "
            f"{doc['semantic_beats_ufastslam']} of {runs} runs"
        )


def run(args: argparse.Namespace, console: Console) -> int:
    world = load_world(args.scenario)
    if args.seed + args.runs - 1 > MAX_SEED:
        raise UsageError(f"--seed {args.seed} with --runs {args.runs} runs past the largest seed")
    seeds = [args.seed + i for i in range(args.runs)]
    out = new_folder(Path(args.out), "--out", args.force)  # before the runs, not after them
    console.print(
        f"ufastslam: {world.name} ({world.steps} steps of {world.dt} s, "
        f"{len(world.landmark_ids)} landmarks, {len(world.groups)} relation groups), "
        f"{args.particles} particles, {args.runs} runs (seeds {seeds[0]}..{seeds[-1]}), "
        f"{args.jobs} jobs, relations {args.relations}"
    )
    with runs_done(console, len(seeds), transient=True) as advance:
        runs = run_all(world, seeds, args.particles, args.jobs, advance)
    archive = ufastslam_archive(world, runs, args.particles, args.relations)
    write_archive(out, archive)
    render(archive.document(), console)
    # Imported here: matplotlib takes a second to import, and every command imports this module.
    from deploy.study.plots import write_ufastslam_plots

    plots = write_ufastslam_plots(out, world, runs, args.relations)
    console.print(
        f"wrote {out / 'results.json'}, {out / 'results.npz'} and {len(plots)} plots in {out}"
    )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "ufastslam",
        help="dead reckoning vs UFastSLAM vs Semantic UFastSLAM on a world, over seeded runs",
    )
    p.add_argument(
        "--scenario",
        required=True,
        help="a world file (.toml) or a bundled world: rectangle, office, aisles",
    )
    p.add_argument("--particles", type=positive_int, default=50)
    p.add_argument("--runs", type=positive_int, default=20)
    p.add_argument("--jobs", type=positive_int, default=1, help="parallel processes")
    p.add_argument("--seed", type=seed, default=0, help="runs use seeds S, S+1, …")
    p.add_argument(
        "--relations",
        choices=RELATION_CHOICES,
        default="oracle",
        help="relation source of results.json's semantic_ufastslam (the table shows both)",
    )
    p.add_argument("--out", default="out/ufastslam", help="output folder (new or empty)")
    add_force(p)
    p.set_defaults(run=run)
