"""What a launch reports: its results (the one archive writer, as `semfleet study`), the summary
table, the plots and the agents' counters."""

from __future__ import annotations

import dataclasses
from typing import Any

from rich.console import Console

from deploy.base.output import FiguresTable, figures_table, size
from deploy.launch.run import LAUNCH_METHODS, LaunchOutcome, LaunchPlan
from deploy.study.archive import study_archive, write_archive
from deploy.study.report import render_summary, write_plots


def write_outputs(
    plan: LaunchPlan, outcome: LaunchOutcome, console: Console, extra: dict[str, Any]
) -> dict[str, Any]:
    """results.json/npz and plots like `semfleet study`, and the summary table."""
    s = plan.scenario
    methods = list(LAUNCH_METHODS)
    settings = {"communication": plan.comm or s.communication.mode, **extra}
    archive = study_archive(s.name, [outcome.result], methods, settings)
    if outcome.aoi is not None:
        arrays = {**archive.arrays, **outcome.aoi.arrays(plan.robots)}
        archive = dataclasses.replace(archive, arrays=arrays)
    write_archive(plan.out, archive)
    doc = archive.document()
    steps = plan.run_steps
    render_summary(doc, console)
    plots = write_plots(plan.out, doc, s, [outcome.result], steps, plan.robots[0])
    console.print(f"wrote {plan.out / 'results.json'} and {len(plots)} plots in {plan.out}")
    return doc


def aoi_entry(outcome: LaunchOutcome, console: Console | None = None) -> dict[str, Any]:
    """``{"aoi": …}``, the run's age of information (docs/results.md), or nothing; its summary
    line printed on ``console``, if given."""
    if outcome.aoi is None:
        return {}
    if console is not None:
        console.print(outcome.aoi.line())
    return {"aoi": outcome.aoi.document()}


def security_line(plan: LaunchPlan) -> str:
    """How the launch's agents are linked, said before they start (docs/deploy.md, "Secure
    simulations")."""
    if plan.secure:
        return (
            "secure fleet: mutual TLS, access control and owner-signed slots (a throwaway CA, "
            f"certificates and keys in {plan.out / 'fleet'})"
        )
    return "insecure fleet: plain Zenoh, no TLS or access control (--secure for mutual TLS)"


def agents(n: int) -> str:
    return f"{n} agent" if n == 1 else f"{n} agents"


COUNTERS = (
    ("step", "step"),
    ("stacks sent", "stacks_sent"),
    ("stacks in", "stacks_received"),
    ("merged", "stacks_merged"),
    ("invalid", "stacks_invalid"),
    ("out of range", "ignored_out_of_range"),
    ("frames", "frames_processed"),
    ("replayed", "replayed_frames"),
    ("bytes sent", "bytes_sent"),
)


def counters_table(outcome: LaunchOutcome) -> FiguresTable:
    """Each agent's counters in its last estimate; fits 80 columns (bytes sent in kB/MB)."""
    rows = [
        [r, *(size(c.get(k, 0)) if k == "bytes_sent" else str(c.get(k, 0)) for _, k in COUNTERS)]
        for r, c in sorted(outcome.collected.counters.items())
    ]
    return figures_table(
        "agent counters (last estimate)", ["robot", *(h for h, _ in COUNTERS)], rows
    )
