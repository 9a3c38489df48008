"""The UFastSLAM study: dead reckoning, UFastSLAM and Semantic UFastSLAM (threshold and oracle
relations) on one world over seeded runs, like the experiments of the Semantic UFastSLAM paper.

:func:`run_all` returns one :class:`SeedRun` per seed; :func:`ufastslam_archive` turns them into
the results archive (``deploy.study.archive``, schema in docs/results.md and docs/ufastslam.md).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from deploy.study.archive import ResultsArchive
from deploy.study.runner import run_seeded
from deploy.study.types import UFASTSLAM_LABELS as LABELS
from deploy.study.types import UFASTSLAM_METHODS as METHODS
from deploy.study.types import MethodRun, SeedRun, semantic_method
from estimator.metrics import chi2_bound, world_pose_nees
from estimator.ufastslam import (
    AcceptedRelation,
    Observation,
    RelationConfig,
    UFastSLAM,
    UFastSLAMConfig,
)
from estimator.ufastslam.models import inverse_observe, motion, relation_residual
from sim.ufastslam import Run, UWorld, simulate
from sim.ufastslam.world import GROUP_TOLERANCE

Array = NDArray[np.float64]

RELATION_CHOICES = ("threshold", "oracle", "off")
METRICS = ("pose_rmse", "landmark_rmse", "final_error", "step_ms")
COUNTS = ("relations_true", "relations_false")
CONSISTENCY = ("pose_nees", "nees_over_bound")
# A pose NEES above the χ²₃ bound of this probability counts as a step "over the bound".
NEES_PROBABILITY = 0.99
# The filter's random stream of a run; the same for every method, so that relations "off" is
# bit-identical to plain UFastSLAM.
_FILTER_STREAM = 0x5EED


def filter_config(world: UWorld, particles: int, relations: str) -> UFastSLAMConfig:
    """The filter for a world: its assumed noise, and relations ``off``, ``labels`` or
    ``threshold``."""
    fn = world.filter_noise
    return UFastSLAMConfig(
        particles=particles,
        dt=world.dt,
        control_std=(fn.speed_std, fn.yaw_rate_std),
        measurement_std=(world.camera.range_std, world.camera.bearing_std),
        relations=RelationConfig(source=relations, std=fn.relation_std),
    )


def _errors(world: UWorld, run: Run, path: Array, ids: list[int], xy: Array) -> tuple[float, ...]:
    err = np.linalg.norm(path[1:, :2] - run.truth[1:, :2], axis=1)
    index = {lid: j for j, lid in enumerate(world.landmark_ids)}
    truth = world.landmarks[[index[i] for i in ids]]
    lm = math.sqrt(float(np.mean(np.sum((xy - truth) ** 2, axis=1)))) if ids else math.nan
    return math.sqrt(float(np.mean(err**2))), lm, float(err[-1])


def dead_reckoning(world: UWorld, run: Run) -> MethodRun:
    """Odometry integrated with the filter's motion model; each landmark placed at the mean of its
    inverse observations from the dead-reckoned poses."""
    start = time.perf_counter()
    path = np.empty((world.steps + 1, 3))
    path[0] = world.start
    for k, u in enumerate(run.odometry):
        path[k + 1] = motion(path[k], u, world.dt)
    elapsed = time.perf_counter() - start
    sums: dict[int, list[Array]] = {}
    for frame in run.frames:
        for lid, xy in zip(frame.ids, inverse_observe(path[frame.k], frame.z), strict=True):
            sums.setdefault(int(lid), []).append(xy)
    ids = sorted(sums)
    xy = np.array([np.mean(sums[i], axis=0) for i in ids]).reshape(-1, 2)
    pose_rmse, lm_rmse, final = _errors(world, run, path, ids, xy)
    step_ms = 1e3 * elapsed / world.steps
    return MethodRun(pose_rmse, lm_rmse, final, step_ms, 0, 0, None, None, path, tuple(ids), xy, ())


def relation_is_true(world: UWorld, relation: AcceptedRelation) -> bool:
    """Whether an applied relation holds on the true landmarks (to the worlds' tolerance)."""
    index = {lid: j for j, lid in enumerate(world.landmark_ids)}
    m = world.landmarks[index[relation.landmark]]
    refs = world.landmarks[[index[r] for r in relation.refs]]
    return abs(float(relation_residual(relation.kind, m, refs))) <= GROUP_TOLERANCE


def run_filter(world: UWorld, run: Run, config: UFastSLAMConfig) -> MethodRun:
    """One filter over one run; ``labels`` relations receive the world's ground-truth groups."""
    slam = UFastSLAM(config, world.start)
    rng = np.random.default_rng(np.random.SeedSequence([run.seed, _FILTER_STREAM]))
    oracle = config.relations.source == "labels"
    path = np.empty((world.steps + 1, 3))
    path[0] = world.start
    true_rel = false_rel = 0
    elapsed = 0.0
    nees = np.empty(world.steps)
    for frame in run.frames:
        obs = [
            Observation(int(i), (float(z[0]), float(z[1])), world.labels[int(i)] if oracle else ())
            for i, z in zip(frame.ids, frame.z, strict=True)
        ]
        start = time.perf_counter()
        report = slam.step(run.odometry[frame.k - 1], obs, rng)
        path[frame.k] = slam.pose_estimate()
        elapsed += time.perf_counter() - start
        nees[frame.k - 1] = world_pose_nees(*slam.pose_moments(), run.truth[frame.k])
        for rel in report.relations:
            if relation_is_true(world, rel):
                true_rel += 1
            else:
                false_rel += 1
    ids, xy = slam.map_estimate()
    pose_rmse, lm_rmse, final = _errors(world, run, path, ids, xy)
    groups = tuple((k, n, tuple(m)) for k, n, m in slam.group_members())
    step_ms = 1e3 * elapsed / world.steps
    return MethodRun(
        pose_rmse,
        lm_rmse,
        final,
        step_ms,
        true_rel,
        false_rel,
        pose_nees=float(np.median(nees)),
        nees_over_bound=float(np.mean(nees > chi2_bound(3, NEES_PROBABILITY))),
        path=path,
        map_ids=tuple(ids),
        map_xy=xy,
        groups=groups,
    )


def run_seed(world: UWorld, seed_value: int, particles: int) -> SeedRun:
    """Every method on the measurements of one seed (the unit of work of a process)."""
    run = simulate(world, seed_value)
    sources = {"ufastslam": "off", "semantic_threshold": "threshold", "semantic_oracle": "labels"}
    methods = {"odometry": dead_reckoning(world, run)}
    for method, source in sources.items():
        methods[method] = run_filter(world, run, filter_config(world, particles, source))
    return SeedRun(seed_value, run.truth, methods)


def run_all(
    world: UWorld,
    seeds: list[int],
    particles: int,
    jobs: int,
    advance: Callable[[], None] = lambda: None,
) -> list[SeedRun]:
    """Every seed, in seed order: in this process for one job, else in spawned processes."""
    if jobs == 1:
        out = []
        for s in seeds:
            out.append(run_seed(world, s, particles))
            advance()
        return out
    return run_seeded({s: (run_seed, world, s, particles) for s in seeds}, jobs, advance)


def _means(runs: list[SeedRun], method: str) -> dict[str, float]:
    keys = list(METRICS)
    if method.startswith("semantic"):
        keys += COUNTS
    if method != "odometry":
        keys += CONSISTENCY
    return {k: float(np.mean([getattr(r.methods[method], k) for r in runs])) for k in keys}


def ufastslam_archive(
    world: UWorld, runs: list[SeedRun], particles: int, relations: str
) -> ResultsArchive:
    """The archive of a UFastSLAM study: means over runs of ``odometry``, ``ufastslam`` and the
    ``relations`` variant as ``semantic_ufastslam``, the four methods as printed (``table``), and
    the per-run values, paths and position errors behind them."""
    table = {m: _means(runs, m) for m in METHODS}
    if relations == "off":
        # Relations off is plain UFastSLAM, bit for bit (same filter, same random stream).
        semantic: dict[str, Any] = {
            **table["ufastslam"],
            "relations_true": 0.0,
            "relations_false": 0.0,
        }
    else:
        semantic = dict(table[f"semantic_{relations}"])
    chosen = semantic_method(relations)
    wins = sum(r.methods[chosen].pose_rmse < r.methods["ufastslam"].pose_rmse for r in runs)
    methods: dict[str, dict[str, Any]] = {
        "odometry": table["odometry"],
        "ufastslam": table["ufastslam"],
        "semantic_ufastslam": {**semantic, "relations": relations},
    }
    settings = {
        "particles": particles,
        "source": world.source,
        "semantic_beats_ufastslam": int(wins) if relations != "off" else 0,
        "table": {m: {"label": LABELS[m], **table[m]} for m in METHODS},
    }
    seeds = tuple(r.seed for r in runs)
    return ResultsArchive(
        "ufastslam", world.name, seeds, world.steps, methods, settings, _arrays(runs, relations)
    )


def _arrays(runs: list[SeedRun], relations: str) -> dict[str, NDArray[Any]]:
    """``truth`` (steps + 1, 3) and, for every method and ``semantic_ufastslam``, the per-run
    metrics (runs,), paths (runs, steps + 1, 3) and position errors (runs, steps + 1)."""
    truth = runs[0].truth
    arrays: dict[str, NDArray[Any]] = {"truth": truth}
    names = {m: m for m in METHODS}
    names["semantic_ufastslam"] = semantic_method(relations)
    for name, method in names.items():
        keys = [*METRICS, *COUNTS, *(CONSISTENCY if method != "odometry" else ())]
        for key in keys:
            arrays[f"{name}/{key}"] = np.array([getattr(r.methods[method], key) for r in runs])
        paths = np.stack([r.methods[method].path for r in runs])
        arrays[f"{name}/path"] = paths
        arrays[f"{name}/position_error"] = np.linalg.norm(
            paths[..., :2] - truth[None, :, :2], axis=-1
        )
    return arrays
