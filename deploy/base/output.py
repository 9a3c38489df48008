"""What the commands print with: the console (plain text when piped) and the runs' progress bar."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from rich import box
from rich.console import Console, ConsoleOptions, JustifyMethod, RenderResult
from rich.live import Live
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text


def make_console() -> Console:
    """Colours, live tables and progress bars on a terminal; plain text when the output is piped
    or redirected (no escape codes, 80 columns, live displays print once at their end)."""
    return Console(highlight=False)


@contextlib.contextmanager
def live_display(console: Console) -> Iterator[Live]:
    """A live display (redrawn 4 times a second on a terminal) that leaves the output at the
    start of a line however it ends: on a pipe Rich prints the last frame once, without a final
    newline, and whatever came next (the next table, an error line) was glued to its border."""
    try:
        with Live(console=console, refresh_per_second=4, transient=False) as live:
            yield live
    finally:
        if not console.is_terminal:
            console.line()


def runs_progress(console: Console, transient: bool = False) -> Progress:
    """The bar a study shows while its seeded runs complete (``transient``: erased at the end)."""
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=transient,
    )


@dataclass(frozen=True)
class FiguresTable:
    """Per-robot figures that fit the console's width (80 columns when piped): no vertical
    rules, headings whole when everything fits and else wrapped at their spaces, and a figure is
    never wrapped or cut. Columns that still do not fit go to a further table below, the robot
    column (the first) repeated."""

    title: str
    headings: Sequence[str]
    rows: Sequence[Sequence[str]]

    def widths(self, width: int) -> list[int]:
        """Each column's width: its widest figure, and its whole heading when every column fits
        ``width`` that way, else its heading's longest word (the heading then wraps)."""
        figures = [
            max((len(Text.from_markup(row[i]).plain) for row in self.rows), default=1)
            for i in range(len(self.headings))
        ]
        whole = [max(f, len(h)) for f, h in zip(figures, self.headings, strict=True)]
        if sum(whole) + GAP * (len(whole) - 1) <= width:
            return whole
        return [
            max(f, *(len(word) for word in h.split()))
            for f, h in zip(figures, self.headings, strict=True)
        ]

    def blocks(self, width: int) -> list[list[int]]:
        """The column indices of each table printed, each fitting ``width`` where it can."""
        widths = self.widths(width)
        blocks: list[list[int]] = [[0]]
        used = widths[0]
        for i in range(1, len(widths)):
            if used + GAP + widths[i] > width and len(blocks[-1]) > 1:
                blocks.append([0])
                used = widths[0]
            blocks[-1].append(i)
            used += GAP + widths[i]
        return blocks

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        widths = self.widths(options.max_width)
        for n, block in enumerate(self.blocks(options.max_width)):
            t = Table(
                title=self.title if n == 0 else None,
                box=box.SIMPLE_HEAD,
                show_edge=False,
                pad_edge=False,
                collapse_padding=True,
            )
            for i in block:
                justify: JustifyMethod = "left" if i == 0 else "right"
                t.add_column(self.headings[i], justify=justify, width=widths[i])
            for row in self.rows:
                t.add_row(*(row[i] for i in block))
            yield t


GAP = 2  # the spaces between two columns


def figures_table(
    title: str, headings: Sequence[str], rows: Sequence[Sequence[str]]
) -> FiguresTable:
    """See :class:`FiguresTable`; cells may carry Rich markup (e.g. ``[green]yes[/]``)."""
    return FiguresTable(title, list(headings), [list(r) for r in rows])


def size(n: float) -> str:
    """A byte count in at most 8 characters: ``812 B``, ``21.5 kB``, ``3.4 MB``, ``1.2 GB``."""
    units = ("B", "kB", "MB", "GB", "TB")
    i = 0
    while abs(n) >= 1000 and i < len(units) - 1:
        n /= 1000
        i += 1
    return f"{n:.0f} B" if i == 0 else f"{n:.1f} {units[i]}"


def plural(count: int, noun: str) -> str:
    """``1 run``, ``2 runs``."""
    return f"{count} {noun}{'' if count == 1 else 's'}"
