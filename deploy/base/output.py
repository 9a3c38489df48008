"""What the commands print with: the console (plain text when piped) and the runs' progress bar."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator, Sequence
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


PIPE_LINE_S = 5.0  # on a pipe, at most one progress line this often (first and last aside)


@contextlib.contextmanager
def runs_done(
    console: Console, total: int, transient: bool = False
) -> Iterator[Callable[[], None]]:
    """``advance()``, to call as each of ``total`` runs completes. On a terminal it moves the
    :func:`runs_progress` bar; on a pipe, where a bar shows only once it is done, it prints
    ``runs: 3 of 20 done, 12.4 s`` for the first run, the last, and at most once every
    :data:`PIPE_LINE_S` seconds between, so that a log shows the command is working."""
    if console.is_terminal:
        with runs_progress(console, transient) as progress:
            task = progress.add_task("runs", total=total)
            yield lambda: progress.advance(task)
        return
    start = time.monotonic()
    done, said = 0, -math.inf

    def advance() -> None:
        nonlocal done, said
        done += 1
        now = time.monotonic()
        if done in (1, total) or now - said >= PIPE_LINE_S:
            console.print(f"runs: {done} of {total} done, {now - start:.1f} s")
            said = now

    yield advance


@dataclass(frozen=True)
class FiguresTable:
    """Per-row figures that fit the console's width (80 columns when piped): no vertical rules,
    headings whole when everything fits and else wrapped at their spaces, and a figure is never
    wrapped or cut. The columns in ``text`` hold words rather than figures: left-justified, they
    wrap at their spaces to fit (never inside a word). Columns that still do not fit go to a
    further table below, the first column, each row's key, repeated."""

    title: str
    headings: Sequence[str]
    rows: Sequence[Sequence[str]]
    text: frozenset[int] = frozenset()
    caption: str = ""  # under the last table

    def widths(self, width: int) -> list[int]:
        """Each column's width: its widest cell, and its whole heading, when every column fits
        ``width`` that way; else its heading's longest word (the heading then wraps), and a text
        column between its longest word and its widest cell, sharing the width left over."""
        cells = [[Text.from_markup(row[i]).plain for row in self.rows] for i in range(len(self))]
        widest = [max((len(c) for c in column), default=1) for column in cells]
        whole = [max(f, len(h)) for f, h in zip(widest, self.headings, strict=True)]
        if _spread(whole) <= width:
            return whole
        least = [
            max(
                max((_longest_word(c) for c in cells[i]), default=1) if i in self.text else f,
                _longest_word(h),
            )
            for i, (f, h) in enumerate(zip(widest, self.headings, strict=True))
        ]
        wants = {i: whole[i] - least[i] for i in self.text if whole[i] > least[i]}
        spare = width - _spread(least)
        if spare <= 0 or not wants:
            return least
        share = min(1.0, spare / sum(wants.values()))
        return [w + int(wants.get(i, 0) * share) for i, w in enumerate(least)]

    def __len__(self) -> int:
        return len(self.headings)

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
        blocks = self.blocks(options.max_width)
        for n, block in enumerate(blocks):
            t = Table(
                title=self.title if n == 0 else None,
                caption=self.caption or None if n == len(blocks) - 1 else None,
                box=box.SIMPLE_HEAD,
                show_edge=False,
                pad_edge=False,
                collapse_padding=True,
            )
            for i in block:
                justify: JustifyMethod = "left" if i == 0 or i in self.text else "right"
                t.add_column(self.headings[i], justify=justify, width=widths[i])
            for row in self.rows:
                t.add_row(*(row[i] for i in block))
            yield t


def _spread(widths: Sequence[int]) -> int:
    """The width of columns side by side."""
    return sum(widths) + GAP * (len(widths) - 1)


def _longest_word(text: str) -> int:
    return max((len(word) for word in text.split()), default=0)


GAP = 2  # the spaces between two columns


def figures_table(
    title: str,
    headings: Sequence[str],
    rows: Sequence[Sequence[str]],
    text: Sequence[int] = (),
    caption: str = "",
) -> FiguresTable:
    """See :class:`FiguresTable`; cells may carry Rich markup (e.g. ``[green]yes[/]``);
    ``text``: the indices of the columns of words, which wrap; ``caption``: a line under it."""
    return FiguresTable(title, list(headings), [list(r) for r in rows], frozenset(text), caption)


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
