"""Run every benchmark and print one plain table: ``python -m bench``.

``python -m bench agents study`` (or ``SEMFLEET_BENCH=agents,study``) runs only those modules
(``bench_<name>``), e.g. to re-measure one issue's figures on a quiet machine."""

from __future__ import annotations

import os
import sys
import time

from bench import (
    bench_agents,
    bench_aoi,
    bench_belief,
    bench_capacity,
    bench_crowd,
    bench_draws,
    bench_fleetscale,
    bench_gossip,
    bench_mapscale,
    bench_models,
    bench_relinearization,
    bench_secure,
    bench_study,
    bench_ufastslam,
    format_table,
)

# The study last: it takes the longest and wants a machine the other benchmarks left alone.
MODULES = (
    bench_models,
    bench_belief,
    bench_draws,
    bench_relinearization,
    bench_crowd,
    bench_ufastslam,
    bench_agents,
    bench_aoi,
    bench_gossip,
    bench_capacity,
    bench_secure,
    bench_mapscale,
    bench_fleetscale,
    bench_study,
)


def selected(names: list[str]) -> tuple[object, ...]:
    """The modules named (``agents`` or ``bench_agents``), all if none; unknown names fail."""
    if not names:
        return MODULES
    by_name = {m.__name__.rsplit(".", 1)[-1].removeprefix("bench_"): m for m in MODULES}
    unknown = [n for n in names if n.removeprefix("bench_") not in by_name]
    if unknown:
        raise SystemExit(f"unknown benchmarks {unknown} (known: {', '.join(by_name)})")
    return tuple(by_name[n.removeprefix("bench_")] for n in names)


def main() -> int:
    start = time.perf_counter()
    names = sys.argv[1:] or [n for n in os.environ.get("SEMFLEET_BENCH", "").split(",") if n]
    modules = selected(names)
    results = [r for module in modules for r in module.run()]  # type: ignore[attr-defined]
    print(format_table(results))
    for module in modules:
        for line in getattr(module, "notes", list)():
            print(f"- {line}")
    print(f"\n{len(results)} benchmarks in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
