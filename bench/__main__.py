"""Run every benchmark and print one plain table: ``python -m bench``."""

from __future__ import annotations

import sys
import time

from bench import Result, bench_belief, bench_models, bench_study, bench_ufastslam

MODULES = (bench_models, bench_belief, bench_ufastslam, bench_study)

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


def main() -> int:
    start = time.perf_counter()
    results = [r for module in MODULES for r in module.run()]
    print(format_table(results))
    for module in MODULES:
        for line in getattr(module, "notes", list)():
            print(f"- {line}")
    print(f"\n{len(results)} benchmarks in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
