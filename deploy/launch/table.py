"""The live table of a launch: every robot's progress while the run goes on."""

from __future__ import annotations

from collections.abc import Sequence

from deploy.base.output import FiguresTable, figures_table
from deploy.launch.conductor import Conductor

PROGRESS = (
    ("hyp L", "hypotheses_local"),
    ("hyp D", "hypotheses_distributed"),
    ("stacks in", "stacks_received"),
    ("merged", "stacks_merged"),
    ("invalid", "stacks_invalid"),
    ("out of range", "ignored_out_of_range"),
)


def progress_table(conductor: Conductor, robots: Sequence[str], steps: int) -> FiguresTable:
    """Every robot's last estimated step and counters. The title counts the steps every robot
    has estimated — what the rows show — not the frames sent ahead of them."""
    done = min((conductor.acked(r) for r in robots), default=0)
    rows = []
    for r in robots:
        c = conductor.collected.counters.get(r, {})
        alive = "yes" if r in conductor.alive else "no"
        rows.append(
            [r, alive, str(conductor.acked(r)), *(str(c.get(key, "")) for _, key in PROGRESS)]
        )
    headings = ["robot", "alive", "step", *(name for name, _ in PROGRESS)]
    return figures_table(f"step {done}/{steps}", headings, rows)
