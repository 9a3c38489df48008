"""What a launch reports: its results (the one archive writer, as `semfleet study`), the summary
table, the plots and the agents' counters."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

from deploy.launch.run import LAUNCH_METHODS, LaunchOutcome, LaunchPlan
from deploy.results import study_archive, write_archive
from deploy.study_report import render_summary, write_plots


def write_outputs(
    plan: LaunchPlan, outcome: LaunchOutcome, console: Console, extra: dict[str, Any]
) -> dict[str, Any]:
    """results.json/npz and plots like `semfleet study`, and the summary table."""
    s = plan.scenario
    methods = list(LAUNCH_METHODS)
    settings = {"communication": plan.comm or s.communication.mode, **extra}
    archive = study_archive(s.name, [outcome.result], methods, settings)
    write_archive(plan.out, archive)
    doc = archive.document()
    steps = plan.run_steps
    render_summary(doc, console)
    plots = write_plots(plan.out, doc, s, [outcome.result], steps, plan.robots[0])
    console.print(f"wrote {plan.out / 'results.json'} and {len(plots)} plots in {plan.out}")
    return doc


def agents(n: int) -> str:
    return f"{n} agent" if n == 1 else f"{n} agents"


def counters_table(outcome: LaunchOutcome) -> Table:
    names = (
        "step", "stacks_sent", "stacks_received", "stacks_merged", "stacks_invalid",
        "ignored_out_of_range", "frames_processed", "replayed_frames", "bytes_sent",
    )  # fmt: skip
    t = Table(title="agent counters (last estimate)")
    t.add_column("robot")
    for n in names:
        t.add_column(n.replace("_", " "), justify="right")
    for r, c in sorted(outcome.collected.counters.items()):
        t.add_row(r, *(f"{c.get(n, 0):,}" for n in names))
    return t
