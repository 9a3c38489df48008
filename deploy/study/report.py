"""What a study prints and draws: the comparison and cost tables of a results document and its
plots (`semfleet study`, `semfleet launch`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from deploy.base.output import figures_table, plural
from deploy.study.paper_figures import Comparison, PaperValue
from deploy.study.types import RunResult
from estimator.metrics import chi2_bounds
from sim.scenario import Scenario

# Rows of the comparison table per method: a curve of the method's results.json entry
# (class_ece_pooled) or of its means.
SUMMARY_METRICS = (
    "msde",
    "class_log_loss",
    "class_ece_pooled",
    "class_gap_central",
    "class_gap_received",
    "robot_error",
    "object_error",
    "robot_nees",
    "hypotheses",
)


def table_steps(steps: int, count: int = 4) -> list[int]:
    """``count`` evenly spaced steps ending at the last one, k = ⌈i·steps/count⌉: 15, 30, 45, 60
    for the paper's 60 steps, 5, 10, 15, 20 for 20."""
    return sorted({max(1, -(-i * steps // count)) for i in range(1, count + 1)})


def _tail_cell(entry: dict[str, Any], name: str) -> str:
    figures = [entry.get(f"{name}_{q}") for q in ("p50", "p95", "p99", "max")]
    if any(v is None for v in figures):
        return "—"
    return " / ".join(f"{v:.2f}" for v in figures)


def render_association(doc: dict[str, Any], console: Console) -> None:
    """Frames without global ids: each method's association against the simulator's truth,
    one line per method."""

    def fig(value: float | None, form: str) -> str:
        return "—" if value is None else form.format(value)

    for method, entry in doc["methods"].items():
        a = entry.get("association")
        if a is None:
            continue
        console.print(
            f"association ({method}, against the simulator's truth): precision "
            f"{fig(a['precision'], '{:.4f}')}, recall {fig(a['recall'], '{:.4f}')}, wrong merges "
            f"{a['wrong_merges']:.0f}, splits {a['splits']:.0f}, map objects "
            f"{a['confirmed']:.0f} ({a['confirmed_clutter']:.0f} of clutter), false detections "
            f"in the belief {a['clutter_entered']:.0f}, {fig(a['ms_mean'], '{:.1f}')} ms per frame "
            f"(p99 {fig(a['ms_p99'], '{:.1f}')}), {a.get('searches_cut', 0):.0f} joint searches "
            "cut at their budget"
        )
    for method, entry in doc["methods"].items():
        f = entry.get("fleet_association")
        if f is None:
            continue
        console.print(
            f"fleet association ({method}, peers' objects in each D, at the end): precision "
            f"{fig(f['precision'], '{:.4f}')}, recall {fig(f['recall'], '{:.4f}')}, wrong "
            f"matches {f['wrong']:.0f} ({fig(f['wrong_per_1000_pairs'], '{:.3f}')} per 1,000 "
            f"pairs), {f['matched']:.0f} matched of {f['owner_objects']:.0f}, mapping changes "
            f"{f['changes']:.0f}"
        )


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

    def curve(entry: dict[str, Any], metric: str) -> list[float | None]:
        values = entry[metric] if metric in entry else entry["mean"].get(metric)
        return [None] * steps if values is None else values

    # a row no method has a figure for (a comparison with a method the study did not run) is left
    # out of every method's rows
    shown = [
        metric
        for metric in SUMMARY_METRICS
        if any(curve(e, metric)[k - 1] is not None for e in doc["methods"].values() for k in at)
    ]
    for method, entry in doc["methods"].items():
        for i, metric in enumerate(shown):
            values = curve(entry, metric)
            cells = ["—" if values[k - 1] is None else f"{values[k - 1]:.4g}" for k in at]
            table.add_row(method if i == 0 else "", metric, *cells, end_section=i == len(shown) - 1)
    console.print(table)
    columns = ("method", "wall s", "belief step ms", "fusion ms", "stack bytes")
    counts = ("empty_joins", "rebuilds", "refused")
    rows = []
    for method, entry in doc["methods"].items():
        size = (
            f"{entry['stack_bytes_mean']:,.0f} / {entry['stack_bytes_max']:,}"
            if "stack_bytes_mean" in entry
            else "—"
        )
        wall = f"{entry['wall_s']:.1f}"
        tails = (_tail_cell(entry, "step_ms"), _tail_cell(entry, "fusion_ms"))
        rows.append(
            [method, wall, *tails, size, *(f"{entry[k]:,}" if k in entry else "—" for k in counts)]
        )
    title = "cost (wall s: all runs; ms: p50 / p95 / p99 / max; stack bytes: mean / max)"
    timing = figures_table(title, [*columns, "empty joins", "rebuilds", "refused"], rows)
    console.print(timing)
    lo, hi = chi2_bounds(3, doc["runs"])
    console.print(
        f"robot NEES (3 dof) 95 % band for the mean over {plural(doc['runs'], 'run')}: "
        f"[{lo:.2f}, {hi:.2f}]"
    )
    for method, entry in doc["methods"].items():
        if entry.get("runs_at_cap"):
            console.print(
                f"{method}: a belief held the cap of {doc['max_hypotheses']:,} hypotheses in "
                f"{entry['runs_at_cap']} of {plural(doc['runs'], 'run')} and was pruned to it "
                "(--hypotheses exact is then not exact)"
            )


def render_paper(rows: list[Comparison], console: Console) -> None:
    """The study's means against the paper's read-off values (`study --paper`)."""
    table_rows = []
    for row in rows:
        v = row.value
        read = f"{v.low:.2g}–{v.high:.2g}"
        ours = "—" if row.ours is None else f"{row.ours:.3g}"
        ratio = "—" if row.ratio is None else f"{row.ratio:.2f}"
        within = {None: "—", True: "yes", False: "no"}[row.holds]
        figure = v.figure.removeprefix("Fig. ")
        table_rows.append([figure, v.metric, v.method, str(v.step), read, ours, ratio, within])
    columns = ("fig.", "metric", "method", "k", "paper", "ours", "ratio", "in")
    title = "the study's means against values read off the paper's figures (docs/paper.md)"
    console.print(figures_table(title, columns, table_rows))


def write_plots(
    out: Path,
    doc: dict[str, Any],
    scenario: Scenario,
    results: list[RunResult],
    step: int,
    robot: str,
    paper: list[PaperValue] | None = None,
) -> list[Path]:
    """:func:`deploy.study.plots.write_study_plots`, imported when called: matplotlib takes a
    second to import, and every command imports this module."""
    from deploy.study.plots import write_study_plots

    return write_study_plots(out, doc, scenario, results, step, robot, paper or ())
