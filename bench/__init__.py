"""Benchmarks, run with ``python -m bench`` (``make bench``).

Each benchmark module exposes ``run() -> list[Result]``; ``bench.__main__`` runs them all and prints
one table. Wall-clock numbers belong here only, never in assertions inside tests.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

# Each timed repeat runs the subject often enough to last about this long, so that fast calls are
# not dominated by timer resolution.
_MIN_REPEAT_SECONDS = 0.02


@dataclass(frozen=True, slots=True)
class Result:
    """One row of the table.

    ``ms`` is the median wall time of one call on ``n`` items. ``baseline_ms``, if any, is the
    reference implementation's time for the same ``n`` (possibly scaled from fewer items, as
    ``note`` says). ``per_second`` is a throughput in ``unit`` per second, if one is meaningful.
    """

    name: str
    n: int
    ms: float
    baseline_ms: float | None = None
    per_second: float | None = None
    unit: str = ""
    note: str = ""

    @property
    def speedup(self) -> float | None:
        """How many times faster than the baseline."""
        return None if self.baseline_ms is None else self.baseline_ms / self.ms


def median_seconds(fn: Callable[[], object], repeats: int = 5) -> float:
    """Median wall time of one ``fn()`` call over ``repeats`` timed repeats, after a warm-up."""
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    number = max(1, int(_MIN_REPEAT_SECONDS / max(first, 1e-9)))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - start) / number)
    return statistics.median(times)


_HEADER = ("benchmark", "N", "ms", "baseline ms", "speed-up", "throughput /s", "note")


def _cells(r: Result) -> tuple[str, ...]:
    baseline = "" if r.baseline_ms is None else f"{r.baseline_ms:.3f}"
    speedup = "" if r.speedup is None else f"{r.speedup:.1f}x"
    rate = "" if r.per_second is None else f"{r.per_second:,.0f} {r.unit}"
    return (r.name, str(r.n), f"{r.ms:.3f}", baseline, speedup, rate, r.note)


def format_table(results: list[Result]) -> str:
    """Aligned plain-text table: text columns left-aligned, numbers right-aligned."""
    rows = [_HEADER, *(_cells(r) for r in results)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(_HEADER))]
    left = {0, len(_HEADER) - 1}

    def line(row: tuple[str, ...]) -> str:
        cells = (
            c.ljust(w) if i in left else c.rjust(w)
            for i, (c, w) in enumerate(zip(row, widths, strict=True))
        )
        return "  ".join(cells).rstrip()

    rule = "  ".join("-" * w for w in widths)
    return "\n".join([line(rows[0]), rule, *(line(r) for r in rows[1:])])
