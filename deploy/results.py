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
from estimator.metrics import METRICS

Array = NDArray[np.float64]

RESULTS_FORMAT = 1


def stack_runs(results: Sequence[RunResult], method: str) -> dict[str, Array]:
    """METRIC → (runs, robots, steps) for one method."""
    return {m: np.stack([r.metrics[method][m] for r in results]) for m in METRICS}


def mean_curve(values: Array) -> list[float | None]:
    """Mean over runs and robots per step (runs, robots, steps) → steps; None where all NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=RuntimeWarning)
        curve = np.nanmean(values.reshape(-1, values.shape[-1]), axis=0)
    return [None if math.isnan(v) else float(v) for v in curve]


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
        entry: dict[str, Any] = {
            "mean": {m: mean_curve(stacked[m]) for m in METRICS},
            "wall_s": float(sum(r.wall_s[method] for r in results)),
            "step_ms_median": float(np.median(all_ms)),
        }
        if any(method in r.fusion_ms for r in results):
            fusion = np.concatenate([r.fusion_ms[method] for r in results])
            sizes = np.concatenate([r.stack_bytes[method] for r in results]).astype(float)
            entry["fusion_ms_median"] = float(np.median(fusion))
            entry["stack_bytes_mean"] = float(sizes.mean()) if len(sizes) else 0.0
            entry["stack_bytes_max"] = int(sizes.max()) if len(sizes) else 0
            entry["stacks_delivered"] = len(sizes)
        doc["methods"][method] = entry
    if extra:
        doc.update(extra)
    return doc


def write_results(
    out: Path, doc: dict[str, Any], results: Sequence[RunResult], methods: Sequence[str]
) -> None:
    """Write ``out/results.json`` and ``out/results.npz`` (arrays ``METHOD/METRIC``)."""
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
    arrays["seeds"] = np.array([r.seed for r in results], dtype=np.int64)
    np.savez_compressed(out / "results.npz", **arrays)  # type: ignore[arg-type]


def read_results(path: Path) -> dict[str, Any]:
    """Read a results.json and check its format."""
    doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    if doc.get("format") != RESULTS_FORMAT:
        raise ValueError(f"{path}: unsupported results format {doc.get('format')!r}")
    return doc
