"""Study results: aggregation over runs and robots, and the results.json / results.npz files
(schema in docs/results.md)."""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from deploy.study import RunResult
from estimator.metrics import METRICS, ece_from_stats

Array = NDArray[np.float64]

RESULTS_FORMAT = 1
# The percentiles of step and fusion times reported next to their maximum.
TAIL_PERCENTILES = (50, 95, 99)


def stack_runs(results: Sequence[RunResult], method: str) -> dict[str, Array]:
    """METRIC → (runs, robots, steps) for one method."""
    return {m: np.stack([r.metrics[method][m] for r in results]) for m in METRICS}


def mean_curve(values: Array) -> list[float | None]:
    """Mean over runs and robots per step (runs, robots, steps) → steps; None where all NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        curve = np.nanmean(values.reshape(-1, values.shape[-1]), axis=0)
    return _nullable(curve)


def _nullable(curve: Array) -> list[float | None]:
    return [None if math.isnan(v) else float(v) for v in curve]


def pooled_calibration(results: Sequence[RunResult], method: str) -> Array | None:
    """Class-ECE bin statistics summed over runs and robots (steps, 3, bins); None when a run
    has none for ``method``."""
    if not all(method in r.calibration for r in results):
        return None
    return np.asarray(sum(r.calibration[method].sum(axis=0) for r in results))


def tail(name: str, values: Sequence[float] | Array) -> dict[str, float | None]:
    """``NAME_p50``, ``NAME_p95``, ``NAME_p99`` (linear interpolation) and ``NAME_max`` of
    ``values``; None when there are none."""
    keys = [f"{name}_p{q}" for q in TAIL_PERCENTILES] + [f"{name}_max"]
    if len(values) == 0:
        return dict.fromkeys(keys)
    figures = [*np.percentile(values, TAIL_PERCENTILES), np.max(values)]
    return {k: float(v) for k, v in zip(keys, figures, strict=True)}


def summarise(
    scenario: str,
    results: Sequence[RunResult],
    methods: Sequence[str],
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The results.json document."""
    steps = next(iter(results[0].metrics[methods[0]].values())).shape[-1]
    doc: dict[str, Any] = {
        "format": RESULTS_FORMAT,
        "scenario": scenario,
        "runs": len(results),
        "seeds": [r.seed for r in results],
        "steps": steps,
        "methods": {},
    }
    for method in methods:
        stacked = stack_runs(results, method)
        all_ms = np.concatenate([r.step_ms[method] for r in results])
        entry: dict[str, Any] = {"mean": {m: mean_curve(stacked[m]) for m in METRICS}}
        pooled = pooled_calibration(results, method)
        if pooled is not None:
            entry["class_ece_pooled"] = _nullable(ece_from_stats(pooled))
        entry["wall_s"] = float(sum(r.wall_s[method] for r in results))
        entry.update(tail("step_ms", all_ms))
        if any(method in r.fusion_ms for r in results):
            fusion = np.concatenate([r.fusion_ms[method] for r in results])
            sizes = np.concatenate([r.stack_bytes[method] for r in results]).astype(float)
            entry.update(tail("fusion_ms", fusion))
            entry["stack_bytes_mean"] = float(sizes.mean()) if len(sizes) else 0.0
            entry["stack_bytes_max"] = int(sizes.max()) if len(sizes) else 0
            entry["stacks_delivered"] = len(sizes)
        if all(method in r.empty_joins for r in results):
            entry["empty_joins"] = int(sum(sum(r.empty_joins[method]) for r in results))
            entry["rebuilds"] = int(sum(sum(r.rebuilds[method]) for r in results))
        doc["methods"][method] = entry
    if extra:
        doc.update(extra)
    return doc


def write_results(
    out: Path, doc: dict[str, Any], results: Sequence[RunResult], methods: Sequence[str]
) -> None:
    """Write ``out/results.json`` and ``out/results.npz`` (arrays ``METHOD/METRIC``, step times,
    class-ECE bin statistics and the fleets' fusion figures)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(
        json.dumps(doc, indent=1, allow_nan=False) + "\n", encoding="utf-8"
    )
    arrays = {}
    for method in methods:
        for metric, values in stack_runs(results, method).items():
            arrays[f"{method}/{metric}"] = values
        arrays[f"{method}/step_ms"] = np.array([r.step_ms[method] for r in results])
        if method in results[0].fusion_ms:
            arrays[f"{method}/fusion_ms"] = np.array([r.fusion_ms[method] for r in results])
        if all(method in r.calibration for r in results):
            arrays[f"{method}/calibration"] = np.stack([r.calibration[method] for r in results])
        if all(method in r.empty_joins for r in results):
            for key in ("empty_joins", "rebuilds"):
                counts = [getattr(r, key)[method] for r in results]
                arrays[f"{method}/{key}"] = np.array(counts, dtype=np.int64)
    arrays["seeds"] = np.array([r.seed for r in results], dtype=np.int64)
    np.savez_compressed(out / "results.npz", **arrays)  # type: ignore[arg-type]


def read_results(path: Path) -> dict[str, Any]:
    """Read a results.json and check its format."""
    doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    if doc.get("format") != RESULTS_FORMAT:
        raise ValueError(f"{path}: unsupported results format {doc.get('format')!r}")
    return doc
