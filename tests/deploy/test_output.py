"""Tables at 80 columns: every heading word and every figure whole, nothing past the edge."""

from __future__ import annotations

import contextlib
import io
from types import SimpleNamespace
from typing import Any

import pytest
from rich.console import Console

from agents.transport.base import Keys, Message
from deploy.base.output import FiguresTable, figures_table, live_display, size
from deploy.cli.commands.fleet import COUNTER_COLUMNS, fleet_table
from deploy.launch.report import COUNTERS, counters_table
from deploy.launch.table import PROGRESS, progress_table
from deploy.operator.fleet_view import FleetView
from protocol.estimate import EstimateMessage, encode_estimate
from tests.deploy.tables import table_cells
from tests.deploy.test_fleet_cmd import HYP

ROBOTS = [f"robot-{i}" for i in range(1, 11)]  # ids longer than the usual r1
BIG = 987_654  # a long run's stack count


def render(table: FiguresTable, width: int = 80) -> list[str]:
    console = Console(width=width, file=io.StringIO(), force_terminal=False)
    console.print(table)
    assert isinstance(console.file, io.StringIO)
    return console.file.getvalue().splitlines()


def assert_fits(lines: list[str], rows: list[list[str]], width: int = 80) -> None:
    text = "\n".join(lines)
    assert "…" not in text, text
    assert max(len(line) for line in lines) <= width, text
    for row in rows:  # its cells whole and in order, across the blocks its columns went to
        line = " ".join(line for line in lines if line.startswith(row[0] + " "))
        rest = line
        for cell in row:
            assert cell in rest, (cell, line)
            rest = rest[rest.index(cell) + len(cell) :]


def test_counters_table_fits_80_columns_with_large_counters() -> None:
    counters = {r: {key: BIG for _, key in COUNTERS} | {"bytes_sent": 123_456_789} for r in ROBOTS}
    outcome: Any = SimpleNamespace(collected=SimpleNamespace(counters=counters))
    lines = render(counters_table(outcome))
    assert_fits(lines, [[r, *[str(BIG)] * (len(COUNTERS) - 1), "123.5 MB"] for r in ROBOTS])
    assert "stacks" in "\n".join(lines) and "range" in "\n".join(lines)  # headings kept, wrapped


def test_launch_progress_table_fits_80_columns() -> None:
    counters = {r: {key: BIG for _, key in PROGRESS} for r in ROBOTS}
    conductor: Any = SimpleNamespace(
        collected=SimpleNamespace(counters=counters),
        alive=set(ROBOTS[:-1]),
        acked=lambda r: 60,
    )
    lines = render(progress_table(conductor, ROBOTS, 60))
    rows = [
        [r, "yes" if r != ROBOTS[-1] else "no", "60", *[str(BIG)] * len(PROGRESS)] for r in ROBOTS
    ]
    assert_fits(lines, rows)


def test_fleet_status_table_fits_80_columns_with_every_counter_column() -> None:
    keys = Keys("f")
    view = FleetView(keys)
    counters = {key: BIG for key, _ in COUNTER_COLUMNS} | {"step": 60}
    for r in ROBOTS:
        view.on_message(Message(keys.alive(r), b"", "alive"), 0.0)
        est = EstimateMessage(r, 60, {"distributed": HYP, "local": HYP}, counters)
        view.on_message(Message(keys.estimate(r), encode_estimate(est)), 1.0)
    lines = render(fleet_table(view, "fleet f", now=12.5))
    row = ["yes", "60", "3/3", "2/2", *[str(BIG)] * len(COUNTER_COLUMNS), "11.5"]
    assert_fits(lines, [[r, *row] for r in ROBOTS])
    assert sum(line.startswith("robot-1 ") for line in lines) == 2  # split in two blocks


def test_figures_table_keeps_figures_whole_and_wraps_headings_at_spaces() -> None:
    rows = [["r1", "1234567", "12"]]
    lines = render(figures_table("t", ["robot", "a very long heading", "b"], rows), width=40)
    assert_fits(lines, rows, width=40)
    assert sum(line.startswith("r1 ") for line in lines) == 1  # it fits: one block
    assert all(word in "\n".join(lines) for word in ("very", "long", "heading"))


def test_size_is_short_and_exact_to_a_tenth() -> None:
    assert [size(n) for n in (0, 999, 1000, 21_549, 3_400_000, 1.2e9)] == [
        "0 B", "999 B", "1.0 kB", "21.5 kB", "3.4 MB", "1.2 GB",
    ]  # fmt: skip


@pytest.mark.parametrize("ending", ["normal", "interrupted"])
def test_live_display_on_a_pipe_ends_its_last_frame_with_a_newline(ending: str) -> None:
    """Piped, Rich printed the last frame without a newline: the next line was glued to the
    table's border (``└──┘semfleet: error: interrupted``)."""
    out = io.StringIO()
    console = Console(file=out, width=80, force_terminal=False)
    with contextlib.suppress(KeyboardInterrupt), live_display(console) as live:
        live.update(figures_table("t", ["robot", "step"], [["r1", "3"]]))
        if ending == "interrupted":
            raise KeyboardInterrupt
    console.print("next")
    lines = out.getvalue().splitlines()
    assert lines[-1] == "next" and lines[-2].startswith("r1 "), out.getvalue()


def test_a_healthy_fleet_is_one_table_at_80_columns_its_zero_troubles_in_the_caption() -> None:
    """Invalid stacks, rejected slots and quarantined frames take a column only when some robot
    has one: a healthy fleet's table is whole at 80 columns (it was split in two)."""
    keys = Keys("f")
    view = FleetView(keys)
    counters = {key: BIG for key, _ in COUNTER_COLUMNS} | {"step": 60}
    counters |= {"stacks_invalid": 0, "slots_rejected": 0, "frames_quarantined": 0}
    for r in ("r1", "r2", "r3"):
        view.on_message(Message(keys.alive(r), b"", "alive"), 0.0)
        est = EstimateMessage(r, 60, {"distributed": HYP, "local": HYP}, counters)
        view.on_message(Message(keys.estimate(r), encode_estimate(est)), 1.0)
    lines = render(fleet_table(view, "fleet f", now=12.5))
    rule = [i for i, line in enumerate(lines) if set(line.strip()) == {"─"}]
    assert len(rule) == 1, "\n".join(lines)
    rows = table_cells(lines[rule[0] + 1 : rule[0] + 4])
    assert rows == [
        [r, "yes", "60", "3/3", "2/2", *[str(BIG)] * 3, "11.5"] for r in ("r1", "r2", "r3")
    ]
    assert lines[-1].strip() == "0 on every robot: invalid, slots rej., quarantined"
    view.on_message(  # one robot with an invalid stack: the column is back
        Message(keys.estimate("r2"), encode_estimate(
            EstimateMessage("r2", 60, {"distributed": HYP}, counters | {"stacks_invalid": 2})
        )), 2.0,
    )  # fmt: skip
    lines = render(fleet_table(view, "fleet f", now=12.5))
    assert "invalid" in lines[1] + lines[2] and "invalid" not in lines[-1], "\n".join(lines)


def test_text_columns_wrap_at_their_spaces_and_the_table_stays_whole() -> None:
    rows = [
        ["stop", "stopped r1, r2, r3 before step 4", "—", "7/7 (ended at 3)"],
        ["flood", "nothing", "status_requests 2700, inbox_dropped 79", "12/12"],
    ]
    headings = ["attack", "achieved", "agents counted", "same as clean"]
    lines = render(figures_table("t", headings, rows, text=(1, 2)))
    assert max(len(line) for line in lines) <= 80 and "…" not in "\n".join(lines)
    rule = [i for i, line in enumerate(lines) if set(line.strip()) == {"─"}]
    assert len(rule) == 1 and len(lines) > rule[0] + 1 + len(rows), "\n".join(lines)  # wrapped
    assert table_cells(lines[rule[0] + 1 :]) == rows
