"""The results archive of every study: one typed value, one writer, one reader (schema in
docs/results.md).

A :class:`ResultsArchive` is what ``results.json`` and ``results.npz`` hold: the same envelope for
the hybrid-belief study (``semfleet study``, ``launch``, ``chaos``, ``demo``) and the UFastSLAM
study (``semfleet ufastslam``), a summary entry per method, the study's own settings and the
arrays behind the summaries. :func:`study_archive` builds the hybrid-belief study's archive from
its runs, and :func:`study_runs` gives those runs back from the archive's files (what
``semfleet study merge`` combines); ``deploy.study.ufastslam.ufastslam_archive`` makes the
UFastSLAM study's archive.

Over 300 lines for a reason: the writer (:func:`study_archive`, :func:`study_arrays`) and the
reader (:func:`study_runs`) of one schema sit together, so that a field added to one is seen
missing from the other (``semfleet study merge`` re-makes the archive from what it reads).
"""

from __future__ import annotations

import json
import math
import warnings
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from deploy.base.errors import UsageError
from deploy.base.files import write_atomically, write_text_atomically
from deploy.study.association import COUNTS as ASSOCIATION_COUNTS
from deploy.study.association import FLEET_COUNTS, fleet_summary
from deploy.study.association import summarise as association_summary
from deploy.study.types import RunResult
from estimator.metrics import CROSS_METRICS, METRICS, ece_from_stats

Array = NDArray[np.float64]

# Format 2 (issue 12): one envelope for both studies, with the ``study`` key telling them apart;
# format 1 were two unrelated schemas.
RESULTS_FORMAT = 2
STUDIES = ("hybrid", "ufastslam")
# The keys every results.json starts with; a study's settings may not reuse them.
ENVELOPE = ("format", "study", "scenario", "runs", "seeds", "steps", "methods")
# The percentiles of step and fusion times reported next to their maximum.
TAIL_PERCENTILES = (50, 95, 99)


@dataclass(frozen=True, slots=True)
class ResultsArchive:
    """One study's results. ``methods``: method → its summary (JSON values, means over runs);
    ``settings``: the study's run-level values (JSON values, written after ``methods``);
    ``arrays``: the values behind the summaries, ``results.npz`` keys → arrays (``seeds`` is
    added by the writer)."""

    study: str
    scenario: str
    seeds: tuple[int, ...]
    steps: int
    methods: Mapping[str, Mapping[str, Any]]
    settings: Mapping[str, Any]
    arrays: Mapping[str, NDArray[Any]]

    def __post_init__(self) -> None:
        if self.study not in STUDIES:
            raise ValueError(f"unknown study {self.study!r} (known: {', '.join(STUDIES)})")
        clash = sorted(set(self.settings) & set(ENVELOPE))
        if clash:
            raise ValueError(f"settings {clash} would overwrite the results.json envelope")
        if "seeds" in self.arrays:
            raise ValueError("arrays: 'seeds' is written from the archive's seeds")

    def document(self) -> dict[str, Any]:
        """The results.json document."""
        return {
            "format": RESULTS_FORMAT,
            "study": self.study,
            "scenario": self.scenario,
            "runs": len(self.seeds),
            "seeds": list(self.seeds),
            "steps": self.steps,
            "methods": {m: dict(entry) for m, entry in self.methods.items()},
            **self.settings,
        }


def write_archive(out: Path, archive: ResultsArchive) -> None:
    """``out/results.json`` (strict JSON: no NaN or Infinity) and ``out/results.npz``."""
    _write(out, archive.document(), archive.arrays, archive.seeds)


def _write(
    out: Path, doc: Mapping[str, Any], arrays: Mapping[str, NDArray[Any]], seeds: Sequence[int]
) -> None:
    text = json.dumps(doc, indent=1, allow_nan=False) + "\n"
    npz = {**arrays, "seeds": np.array(seeds, dtype=np.int64)}

    def savez(tmp: Path) -> None:
        np.savez_compressed(tmp, **npz)  # type: ignore[arg-type]

    # Each file whole: a study stopped while writing leaves no half archive to read back.
    write_atomically(out / "results.npz", savez)
    write_text_atomically(out / "results.json", text)


def read_results(path: Path) -> dict[str, Any]:
    """Read a results.json and check its format."""
    doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    if doc.get("format") != RESULTS_FORMAT:
        raise ValueError(f"{path}: unsupported results format {doc.get('format')!r}")
    return doc


def read_folder(folder: Path) -> tuple[dict[str, Any], dict[str, NDArray[Any]]]:
    """A results folder's results.json (as :func:`read_results`) and results.npz arrays; a file
    that is missing or not a results file is a ``UsageError`` naming it."""
    path = folder / "results.json"
    try:
        doc = read_results(path)
    except ValueError as exc:  # not JSON, or another format
        raise UsageError(str(exc) if str(path) in str(exc) else f"{path}: {exc}") from None
    try:
        with np.load(folder / "results.npz") as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (ValueError, zipfile.BadZipFile) as exc:
        raise UsageError(f"{folder / 'results.npz'}: not a results archive ({exc})") from None
    return doc, arrays


# ---- the hybrid-belief study ---------------------------------------------------------------


def study_archive(
    scenario: str,
    results: Sequence[RunResult],
    methods: Sequence[str],
    settings: Mapping[str, Any] | None = None,
) -> ResultsArchive:
    """The archive of hybrid-belief runs: per method the mean curves and figures of
    :func:`method_summary`, the arrays of :func:`study_arrays`; ``robots`` (the robot axis of
    every array, from the runs) leads the ``settings``."""
    robots = list(results[0].robots)
    axes = next(iter(results[0].metrics[methods[0]].values())).shape  # (robots, steps)
    if robots and len(robots) != axes[0]:
        raise ValueError(f"robots {robots} do not match the runs' {axes[0]} robots")
    cap = _hypothesis_cap(settings or {})
    return ResultsArchive(
        "hybrid",
        scenario,
        tuple(r.seed for r in results),
        axes[1],
        {m: method_summary(results, m, cap) for m in methods},
        {"robots": robots, **(settings or {})},
        study_arrays(results, methods),
    )


def _hypothesis_cap(settings: Mapping[str, Any]) -> int | None:
    """The cap every belief of the study shares (``max_hypotheses``), where no per-robot budget
    makes it differ between beliefs; None otherwise or where the settings do not say."""
    cap = settings.get("max_hypotheses")
    return int(cap) if cap is not None and settings.get("robot_budget") is None else None


def method_summary(
    results: Sequence[RunResult], method: str, cap: int | None = None
) -> dict[str, Any]:
    """One method's results.json entry: mean curves, pooled class ECE, wall time, step-time
    tails and, where every run measured them, the fleets' fusion times, stack sizes, empty joins
    and rebuilds (each on its own: a run may record some and not others). With the beliefs'
    hypothesis ``cap``: ``runs_at_cap``, the runs in which some belief of the method held that
    many hypotheses at some step (it was pruned to the cap: an ``exact`` reference is then not
    exact)."""
    stacked = stack_runs(results, method)
    all_ms = np.concatenate([r.step_ms[method] for r in results])
    entry: dict[str, Any] = {"mean": {m: mean_curve(stacked[m]) for m in stacked}}
    if cap is not None and cap > 1:  # one hypothesis (per-object classes) is no truncation
        held = stacked["hypotheses"].reshape(len(results), -1)
        entry["runs_at_cap"] = int(np.sum(np.nanmax(held, axis=1, initial=0.0) >= cap))
    pooled = pooled_calibration(results, method)
    if pooled is not None:
        entry["class_ece_pooled"] = _nullable(ece_from_stats(pooled))
    entry["wall_s"] = float(sum(r.wall_s[method] for r in results))
    entry.update(tail("step_ms", all_ms))
    if all(method in r.fusion_ms for r in results):
        entry.update(tail("fusion_ms", np.concatenate([r.fusion_ms[method] for r in results])))
    if all(method in r.stack_bytes for r in results):
        sizes = np.concatenate([r.stack_bytes[method] for r in results]).astype(float)
        entry["stack_bytes_mean"] = float(sizes.mean()) if len(sizes) else 0.0
        entry["stack_bytes_max"] = int(sizes.max()) if len(sizes) else 0
        entry["stacks_delivered"] = len(sizes)
    if all(method in r.association for r in results):
        counts = {
            name: sum(r.association[method].get(name, 0) for r in results)
            for name in ASSOCIATION_COUNTS
        }
        ms = [x for r in results for x in r.association_ms.get(method, [])]
        figures = association_summary(counts, ms)
        entry["association"] = {k: None if math.isnan(v) else v for k, v in figures.items()}
    if all(method in r.fleet_association for r in results):
        fleet = {
            name: sum(r.fleet_association[method][name] for r in results) for name in FLEET_COUNTS
        }
        entry["fleet_association"] = {
            k: None if math.isnan(v) else v for k, v in fleet_summary(fleet).items()
        }
    if all(method in r.empty_joins for r in results):
        entry["empty_joins"] = int(sum(sum(r.empty_joins[method]) for r in results))
        entry["rebuilds"] = int(sum(sum(r.rebuilds[method]) for r in results))
    if all(method in r.refused for r in results):
        entry["refused"] = int(sum(r.refused[method] for r in results))
    return entry


def study_arrays(results: Sequence[RunResult], methods: Sequence[str]) -> dict[str, NDArray[Any]]:
    """``METHOD/METRIC`` (runs, robots, steps), the estimated robot poses ``METHOD/robot_pose``
    and the true ones ``true_robot_pose`` (runs, robots, steps, 3) where the runs recorded them,
    step times, wall times per run, class-ECE bin statistics, the fleets' fusion times, empty
    joins and rebuilds and the sizes of their delivered stacks (``METHOD/stack_bytes``, every
    run's in turn, ``METHOD/stacks_delivered`` of them per run); without global ids, each run's
    association counts (``METHOD/association``, runs × ``ASSOCIATION_COUNTS``), its times per
    frame (``METHOD/association_ms``, every run's in turn, ``METHOD/association_frames`` of them
    per run) and the fleet's (``METHOD/fleet_association``, runs × ``FLEET_COUNTS``), so that
    `study merge` makes the same association figures as one study."""
    arrays: dict[str, NDArray[Any]] = {}
    for method in methods:
        for metric, values in stack_runs(results, method).items():
            arrays[f"{method}/{metric}"] = values
        if all("robot_pose" in r.metrics[method] for r in results):
            arrays[f"{method}/robot_pose"] = np.stack(
                [r.metrics[method]["robot_pose"] for r in results]
            )
        arrays[f"{method}/step_ms"] = np.array([r.step_ms[method] for r in results])
        arrays[f"{method}/wall_s"] = np.array([r.wall_s[method] for r in results])
        if all(method in r.stack_bytes for r in results):
            sizes = [r.stack_bytes[method] for r in results]
            arrays[f"{method}/stack_bytes"] = np.array(
                [b for s in sizes for b in s], dtype=np.int64
            )
            arrays[f"{method}/stacks_delivered"] = np.array([len(s) for s in sizes], dtype=np.int64)
        if method in results[0].fusion_ms:
            arrays[f"{method}/fusion_ms"] = np.array([r.fusion_ms[method] for r in results])
        if all(method in r.calibration for r in results):
            arrays[f"{method}/calibration"] = np.stack([r.calibration[method] for r in results])
        if all(method in r.empty_joins for r in results):
            for key in ("empty_joins", "rebuilds"):
                counts = [getattr(r, key)[method] for r in results]
                arrays[f"{method}/{key}"] = np.array(counts, dtype=np.int64)
        if all(method in r.refused for r in results):
            refused = [r.refused[method] for r in results]
            arrays[f"{method}/refused"] = np.array(refused, dtype=np.int64)
        if all(method in r.association for r in results):
            arrays[f"{method}/association"] = np.array(
                [[r.association[method].get(n, 0) for n in ASSOCIATION_COUNTS] for r in results],
                dtype=np.int64,
            )
            ms = [r.association_ms.get(method, []) for r in results]
            arrays[f"{method}/association_ms"] = np.array([x for m in ms for x in m])
            arrays[f"{method}/association_frames"] = np.array([len(m) for m in ms], np.int64)
        if all(method in r.fleet_association for r in results):
            arrays[f"{method}/fleet_association"] = np.array(
                [[r.fleet_association[method][n] for n in FLEET_COUNTS] for r in results],
                dtype=np.int64,
            )
    truth = [m for m in methods if all("true_robot_pose" in r.metrics[m] for r in results)]
    if truth:  # the same for every method: stored once
        arrays["true_robot_pose"] = np.stack(
            [r.metrics[truth[0]]["true_robot_pose"] for r in results]
        )
    return arrays


def study_runs(doc: Mapping[str, Any], arrays: Mapping[str, NDArray[Any]]) -> list[RunResult]:
    """The runs behind a hybrid-belief archive (its results.json ``doc`` and results.npz
    ``arrays``), without their belief snapshots: :func:`study_archive` makes the very same
    archive again from them. A ``KeyError`` names an array the file lacks (written before the
    wall times and stack sizes were archived, issue 15)."""
    methods = list(doc["methods"])
    truth = arrays.get("true_robot_pose")
    offsets = {
        m: np.concatenate([[0], np.cumsum(arrays[f"{m}/stacks_delivered"])])
        for m in methods
        if f"{m}/stack_bytes" in arrays
    }
    per_run = (len(doc["seeds"]), len(doc["robots"]), doc["steps"])
    for m in methods:
        for name in (*METRICS, *CROSS_METRICS):
            got = arrays.get(f"{m}/{name}")
            if got is not None and got.shape != per_run:
                raise ValueError(
                    f"{m}/{name} has shape {got.shape}, not (runs, robots, steps) {per_run}"
                )
    frames = {
        m: np.concatenate([[0], np.cumsum(arrays[f"{m}/association_frames"])])
        for m in methods
        if f"{m}/association_frames" in arrays
    }
    runs = []
    for i, seed in enumerate(doc["seeds"]):
        metrics: dict[str, dict[str, Array]] = {}
        listed: dict[str, dict[str, list[Any]]] = {
            k: {} for k in ("fusion_ms", "stack_bytes", "empty_joins", "rebuilds")
        }
        for m in methods:
            metrics[m] = {name: arrays[f"{m}/{name}"][i] for name in METRICS}
            for name in CROSS_METRICS:  # (absent from archives written before issue 41)
                if f"{m}/{name}" in arrays:
                    metrics[m][name] = arrays[f"{m}/{name}"][i]
            if f"{m}/robot_pose" in arrays:
                metrics[m]["robot_pose"] = arrays[f"{m}/robot_pose"][i]
            if truth is not None:
                metrics[m]["true_robot_pose"] = truth[i]
            for key in ("fusion_ms", "empty_joins", "rebuilds"):
                if f"{m}/{key}" in arrays:
                    listed[key][m] = arrays[f"{m}/{key}"][i].tolist()
            if m in offsets:
                sizes = arrays[f"{m}/stack_bytes"][offsets[m][i] : offsets[m][i + 1]]
                listed["stack_bytes"][m] = sizes.tolist()
        runs.append(
            RunResult(
                int(seed),
                metrics,
                {m: arrays[f"{m}/step_ms"][i].tolist() for m in methods},
                {m: float(arrays[f"{m}/wall_s"][i]) for m in methods},
                calibration={
                    m: arrays[f"{m}/calibration"][i]
                    for m in methods
                    if f"{m}/calibration" in arrays
                },
                fusion_ms=listed["fusion_ms"],
                stack_bytes=listed["stack_bytes"],
                empty_joins=listed["empty_joins"],
                rebuilds=listed["rebuilds"],
                refused={
                    m: int(arrays[f"{m}/refused"][i]) for m in methods if f"{m}/refused" in arrays
                },
                robots=tuple(doc["robots"]),
                association={
                    m: dict(
                        zip(ASSOCIATION_COUNTS, arrays[f"{m}/association"][i].tolist(), strict=True)
                    )
                    for m in methods
                    if f"{m}/association" in arrays
                },
                association_ms={
                    m: arrays[f"{m}/association_ms"][frames[m][i] : frames[m][i + 1]].tolist()
                    for m in frames
                },
                fleet_association={
                    m: dict(
                        zip(FLEET_COUNTS, arrays[f"{m}/fleet_association"][i].tolist(), strict=True)
                    )
                    for m in methods
                    if f"{m}/fleet_association" in arrays
                },
            )
        )
    return runs


def stack_runs(results: Sequence[RunResult], method: str) -> dict[str, Array]:
    """METRIC → (runs, robots, steps) for one method: every metric of :data:`METRICS`, and each of
    :data:`CROSS_METRICS` that every run recorded."""
    names = [
        *METRICS,
        *(m for m in CROSS_METRICS if all(m in r.metrics[method] for r in results)),
    ]
    return {m: np.stack([r.metrics[method][m] for r in results]) for m in names}


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
