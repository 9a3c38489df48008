"""`semfleet study`: the paper's Monte Carlo comparison, as parallel seeded processes. Parses the
options, runs :func:`deploy.study.run_study`, writes its archive and plots, prints the tables."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from deploy.args import MAX_SEED, plural, positive_int, seed, writable_out
from deploy.errors import UsageError
from deploy.fleet import COMM_MODES
from deploy.results import study_archive, write_archive
from deploy.scenario_cmd import scenario_from_args

# StudyError, run_seeded: imported from here by tests/deploy/test_cli.py before issue 12.
from deploy.study import METHODS, RunResult, run_study
from deploy.study import StudyError as StudyError
from deploy.study import run_seeded as run_seeded
from estimator.hybrid import BeliefConfig
from estimator.metrics import chi2_bounds
from estimator.weights import WEIGHT_ESTIMATORS
from sim.scenario import Scenario

# Rows of the comparison table per method: a curve of the method's results.json entry
# (class_ece_pooled) or of its means.
SUMMARY_METRICS = (
    "msde",
    "class_log_loss",
    "class_ece_pooled",
    "robot_error",
    "object_error",
    "robot_nees",
    "hypotheses",
)


def _methods(text: str) -> list[str]:
    methods = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise argparse.ArgumentTypeError(
            f"unknown method(s) {unknown} (available: {', '.join(METHODS)})"
        )
    return list(dict.fromkeys(methods))


def table_steps(steps: int, count: int = 4) -> list[int]:
    """``count`` evenly spaced steps ending at the last one, k = ⌈i·steps/count⌉: 15, 30, 45, 60
    for the paper's 60 steps, 5, 10, 15, 20 for 20."""
    return sorted({max(1, -(-i * steps // count)) for i in range(1, count + 1)})


def _tail_cell(entry: dict[str, Any], name: str) -> str:
    figures = [entry.get(f"{name}_{q}") for q in ("p50", "p95", "p99", "max")]
    if any(v is None for v in figures):
        return "—"
    return " / ".join(f"{v:.2f}" for v in figures)


def render_summary(
    doc: dict[str, Any], console: Console, at_steps: list[int] | None = None
) -> None:
    """The comparison table at ``at_steps`` (default :func:`table_steps`), the cost table and the
    robot NEES band."""
    steps = doc["steps"]
    at = [k for k in (at_steps or table_steps(steps)) if 1 <= k <= steps] or [steps]
    runs = plural(doc["runs"], "run")
    table = Table(title=f"{doc['scenario']}: {runs}, mean over runs and robots")
    table.add_column("method")
    table.add_column("metric")
    for k in at:
        table.add_column(f"k = {k}", justify="right")
    for method, entry in doc["methods"].items():
        for i, metric in enumerate(SUMMARY_METRICS):
            curve = entry[metric] if metric in entry else entry["mean"].get(metric)
            if curve is None:
                curve = [None] * steps
            cells = ["—" if curve[k - 1] is None else f"{curve[k - 1]:.4g}" for k in at]
            table.add_row(
                method if i == 0 else "", metric, *cells, end_section=i == len(SUMMARY_METRICS) - 1
            )
    console.print(table)
    timing = Table(title="cost (times in ms: p50 / p95 / p99 / max; stack bytes: mean / max)")
    columns = ("method", "wall s (all runs)", "belief step ms", "fusion ms", "stack bytes")
    for col in (*columns, "empty joins", "rebuilds"):
        timing.add_column(col, justify="right")
    for method, entry in doc["methods"].items():
        size = (
            f"{entry['stack_bytes_mean']:,.0f} / {entry['stack_bytes_max']:,}"
            if "stack_bytes_mean" in entry
            else "—"
        )
        timing.add_row(
            method,
            f"{entry['wall_s']:.1f}",
            _tail_cell(entry, "step_ms"),
            _tail_cell(entry, "fusion_ms"),
            size,
            *(f"{entry[key]:,}" if key in entry else "—" for key in ("empty_joins", "rebuilds")),
        )
    console.print(timing)
    lo, hi = chi2_bounds(3, doc["runs"])
    console.print(
        f"robot NEES (3 dof) 95 % band for the mean over {plural(doc['runs'], 'run')}: "
        f"[{lo:.2f}, {hi:.2f}]"
    )


def write_plots(
    out: Path,
    doc: dict[str, Any],
    scenario: Scenario,
    results: list[RunResult],
    step: int,
    robot: str,
) -> list[Path]:
    """:func:`deploy.plots.write_study_plots`, imported when called: matplotlib takes a second to
    import, and every command imports this module (deploy/launch_cmd.py calls it by this name)."""
    from deploy.plots import write_study_plots

    return write_study_plots(out, doc, scenario, results, step, robot)


# Named hypothesis managements (docs/estimator.md): the default, the paper's, none.
HYPOTHESIS_MANAGEMENT: dict[str, Callable[..., BeliefConfig]] = {
    "marginal": BeliefConfig,
    "paper": BeliefConfig.paper,
    "exact": BeliefConfig.exact,
}


def run(args: argparse.Namespace, console: Console) -> int:
    scenario = scenario_from_args(args)
    robot = args.snapshot_robot or scenario.robot_ids[0]
    if robot not in scenario.robot_ids:
        raise UsageError(f"--snapshot-robot: no robot {robot!r} in {scenario.name}")
    step = scenario.steps if args.snapshot_step is None else args.snapshot_step
    if not 1 <= step <= scenario.steps:
        raise UsageError(f"--snapshot-step: {step} is outside 1..{scenario.steps}")
    changes = {"weight_estimator": args.weights, "num_samples": args.samples}
    if args.max_hypotheses is not None:
        changes["max_hypotheses"] = args.max_hypotheses
    config = HYPOTHESIS_MANAGEMENT[args.hypotheses](**changes)
    if args.seed + args.runs - 1 > MAX_SEED:
        raise UsageError(f"--seed {args.seed} with --runs {args.runs} runs past the largest seed")
    seeds = [args.seed + i for i in range(args.runs)]
    comm = args.comm or scenario.communication.mode
    writable_out(Path(args.out))  # before any run, not after all of them
    console.print(
        f"study: {scenario.name}, methods {', '.join(args.methods)}, "
        f"{plural(args.runs, 'run')} (seeds {seeds[0]}..{seeds[-1]}), "
        f"{plural(args.jobs, 'job')}, weights {args.weights}, "
        f"hypotheses {args.hypotheses}, communication {comm}"
    )
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task("runs", total=len(seeds))
        results = run_study(
            scenario,
            args.methods,
            seeds,
            config,
            args.jobs,
            step,
            lambda: progress.advance(task),
            args.comm,
        )
    settings = {
        "weight_estimator": args.weights,
        "hypotheses": args.hypotheses,
        "max_hypotheses": config.max_hypotheses,
        "communication": comm,
    }
    archive = study_archive(scenario.name, results, args.methods, settings)
    out = Path(args.out)
    write_archive(out, archive)
    doc = archive.document()
    render_summary(doc, console)
    plots = write_plots(out, doc, scenario, results, step, robot)
    console.print(
        f"wrote {out / 'results.json'}, {out / 'results.npz'} and {len(plots)} plots in {out}"
    )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("study", help="Monte Carlo comparison of methods over seeded runs")
    p.add_argument("--scenario", required=True, help="scenario file or bundled name (e.g. paper)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", dest="overrides")
    p.add_argument(
        "--methods",
        type=_methods,
        default=list(METHODS),
        help=f"comma-separated, from: {', '.join(METHODS)}",
    )
    p.add_argument("--runs", type=positive_int, default=10)
    p.add_argument("--jobs", type=positive_int, default=2, help="parallel processes")
    p.add_argument("--seed", type=seed, default=0, help="runs use seeds S, S+1, …")
    p.add_argument("--out", default="out/study", help="output folder")
    p.add_argument("--weights", choices=WEIGHT_ESTIMATORS, default="geo_conditioned")
    p.add_argument(
        "--comm",
        choices=COMM_MODES,
        default=None,
        help="communication for distributed methods: the schedule table, the range rule "
        "(scenario's range, 10 m in paper) or both (default: the scenario's mode)",
    )
    p.add_argument("--samples", type=positive_int, default=BeliefConfig().num_samples)
    p.add_argument(
        "--hypotheses",
        choices=tuple(HYPOTHESIS_MANAGEMENT),
        default="marginal",
        help="hypothesis management: marginal (default), paper (joint ratio 1/150, to replicate "
        "the paper) or exact (no pruning, small worlds only)",
    )
    p.add_argument(
        "--max-hypotheses",
        type=positive_int,
        default=None,
        help=f"cap on hypotheses per belief (default {BeliefConfig().max_hypotheses}; "
        f"{BeliefConfig.exact().max_hypotheses} with --hypotheses exact)",
    )
    p.add_argument(
        "--snapshot-step",
        type=int,
        default=None,
        help="step of the hypothesis plot (default: last)",
    )
    p.add_argument(
        "--snapshot-robot", default=None, help="robot of the hypothesis plot (default: first)"
    )
    p.set_defaults(run=run)
