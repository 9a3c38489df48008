"""Reading a table as a user reads it: from the lines a command printed."""

from __future__ import annotations


def table_cells(body: list[str]) -> list[list[str]]:
    """The rows of a table as printed, from its lines below the heading's rule: a line that
    starts at the left edge begins a row, an indented one continues it (a wrapped cell). A
    column is a run of positions holding text on some line, columns are apart by at least two
    blank positions, and a cell is its column's text on the row's lines, joined by spaces."""
    width = max(len(line) for line in body)
    padded = [line.ljust(width) for line in body]
    used = [any(line[i] != " " for line in padded) for i in range(width)]
    spans: list[list[int]] = []
    for i, filled in enumerate(used):
        if not filled:
            continue
        if spans and i - spans[-1][1] <= 1:  # one blank: a space inside a cell
            spans[-1][1] = i + 1
        else:
            spans.append([i, i + 1])
    rows: list[list[list[str]]] = []
    for line in padded:
        if not line.startswith(" "):
            rows.append([[] for _ in spans])
        for cell, (a, b) in zip(rows[-1], spans, strict=True):
            if line[a:b].strip():
                cell.append(line[a:b].strip())
    return [[" ".join(parts) for parts in row] for row in rows]
