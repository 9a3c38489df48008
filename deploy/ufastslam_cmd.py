"""`semfleet ufastslam`: dead reckoning, UFastSLAM and Semantic UFastSLAM (threshold and oracle
relations) on one world over seeded runs, like the experiments of the Semantic UFastSLAM paper
(schema in docs/ufastslam.md)."""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from deploy.args import MAX_SEED, positive_int, seed
from deploy.errors import UsageError
from deploy.study_cmd import run_seeded
from estimator.ufastslam import (
    AcceptedRelation,
    Observation,
    RelationConfig,
    UFastSLAM,
    UFastSLAMConfig,
)
from estimator.ufastslam.models import inverse_observe, motion, relation_residual
from sim.ufastslam import Run, UWorld, load_world, simulate
from sim.ufastslam.world import GROUP_TOLERANCE

Array = NDArray[np.float64]

RESULTS_FORMAT = 1
RELATION_CHOICES = ("threshold", "oracle", "off")
# Every method of every run, in table order; results.json's semantic_ufastslam is one of them.
METHODS = ("odometry", "ufastslam", "semantic_threshold", "semantic_oracle")
LABELS = {
    "odometry": "dead reckoning",
    "ufastslam": "UFastSLAM",
    "semantic_threshold": "Semantic UFastSLAM (threshold)",
    "semantic_oracle": "Semantic UFastSLAM (oracle)",
}
METRICS = ("pose_rmse", "landmark_rmse", "final_error", "step_ms")
COUNTS = ("relations_true", "relations_false")
_CHI2_3DOF_99 = 11.345
# Variance floor (m², rad²) when the particles' pose covariance is singular.
_NEES_FLOOR = 1e-12
# The filter's random stream of a run; the same for every method, so that relations "off" is
# bit-identical to plain UFastSLAM.
_FILTER_STREAM = 0x5EED


@dataclass(frozen=True, slots=True)
class MethodRun:
    """One method on one run: the metrics (``pose_nees``: the median over steps, and
    ``nees_over_bound``: the share of steps above the χ²₃ 99 % bound, filters only), the
    estimated path (steps + 1, 3), the final map (landmark ids, (L, 2)) and the relation groups it
    used (kind, name, member ids)."""

    pose_rmse: float
    landmark_rmse: float
    final_error: float
    step_ms: float
    relations_true: int
    relations_false: int
    pose_nees: float | None
    nees_over_bound: float | None
    path: Array
    map_ids: tuple[int, ...]
    map_xy: Array
    groups: tuple[tuple[str, str, tuple[int, ...]], ...]


@dataclass(frozen=True, slots=True)
class SeedRun:
    """Every method on the measurements of one seed."""

    seed: int
    truth: Array
    methods: dict[str, MethodRun]


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


def pose_nees(mean: Array, cov: Array, truth: Array) -> float:
    """Normalised estimation error squared of a pose belief N(mean, cov), 3 dof, θ wrapped; a
    singular covariance is floored (a collapsed particle set is reported as overconfident, not
    hidden)."""
    e = truth - mean
    e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    proj = v.T @ e
    return float(np.sum(proj**2 / np.maximum(w, _NEES_FLOOR)))


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
        nees[frame.k - 1] = pose_nees(*slam.pose_moments(), run.truth[frame.k])
        for rel in report.relations:
            if relation_is_true(world, rel):
                true_rel += 1
            else:
                false_rel += 1
    ids, xy = slam.map_estimate()
    pose_rmse, lm_rmse, final = _errors(world, run, path, ids, xy)
    groups = tuple((k, n, tuple(m)) for k, n, m in slam.group_members())
    step_ms = 1e3 * elapsed / world.steps
    median_nees = float(np.median(nees))
    over = float(np.mean(nees > _CHI2_3DOF_99))
    return MethodRun(
        pose_rmse,
        lm_rmse,
        final,
        step_ms,
        true_rel,
        false_rel,
        median_nees,
        over,
        path,
        tuple(ids),
        xy,
        groups,
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


def _stats(runs: list[SeedRun], method: str) -> dict[str, float]:
    out = {m: float(np.mean([getattr(r.methods[method], m) for r in runs])) for m in METRICS}
    if method.startswith("semantic"):
        out.update(
            {c: float(np.mean([getattr(r.methods[method], c) for r in runs])) for c in COUNTS}
        )
    if method != "odometry":
        for key in ("pose_nees", "nees_over_bound"):
            out[key] = float(np.mean([getattr(r.methods[method], key) for r in runs]))
    return out


def summarise(world: UWorld, runs: list[SeedRun], particles: int, relations: str) -> dict[str, Any]:
    """The results.json document: means over runs."""
    table = {m: _stats(runs, m) for m in METHODS}
    if relations == "off":
        # Relations off is plain UFastSLAM, bit for bit (same filter, same random stream).
        semantic = {**table["ufastslam"], "relations_true": 0.0, "relations_false": 0.0}
    else:
        semantic = dict(table[f"semantic_{relations}"])
    wins = sum(
        r.methods[_semantic_method(relations)].pose_rmse < r.methods["ufastslam"].pose_rmse
        for r in runs
    )
    return {
        "format": RESULTS_FORMAT,
        "scenario": world.name,
        "runs": len(runs),
        "seeds": [r.seed for r in runs],
        "methods": {
            "odometry": table["odometry"],
            "ufastslam": table["ufastslam"],
            "semantic_ufastslam": {**semantic, "relations": relations},
        },
        "particles": particles,
        "steps": world.steps,
        "source": world.source,
        "semantic_beats_ufastslam": int(wins) if relations != "off" else 0,
        "table": {m: {"label": LABELS[m], **table[m]} for m in METHODS},
    }


def _semantic_method(relations: str) -> str:
    return "ufastslam" if relations == "off" else f"semantic_{relations}"


def write_results(out: Path, doc: dict[str, Any], runs: list[SeedRun], relations: str) -> None:
    """``out/results.json`` and ``out/results.npz`` (per-run arrays ``METHOD/METRIC``, paths
    ``METHOD/path`` (runs, steps + 1, 3), ``truth`` (steps + 1, 3) and ``seeds``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(
        json.dumps(doc, indent=1, allow_nan=False) + "\n", encoding="utf-8"
    )
    arrays: dict[str, Array] = {"seeds": np.array([r.seed for r in runs], dtype=np.int64)}
    arrays["truth"] = runs[0].truth
    names = {m: m for m in METHODS}
    names["semantic_ufastslam"] = _semantic_method(relations)
    for name, method in names.items():
        for metric in (*METRICS, *COUNTS):
            arrays[f"{name}/{metric}"] = np.array(
                [getattr(r.methods[method], metric) for r in runs]
            )
        if method != "odometry":
            for key in ("pose_nees", "nees_over_bound"):
                arrays[f"{name}/{key}"] = np.array([getattr(r.methods[method], key) for r in runs])
        paths = np.stack([r.methods[method].path for r in runs])
        arrays[f"{name}/path"] = paths
        arrays[f"{name}/position_error"] = np.linalg.norm(
            paths[..., :2] - runs[0].truth[None, :, :2], axis=-1
        )
    np.savez_compressed(out / "results.npz", **arrays)  # type: ignore[arg-type]


def render(doc: dict[str, Any], console: Console) -> None:
    runs = doc["runs"]
    table = Table(
        title=f"{doc['scenario']}: {runs} run{'s' if runs != 1 else ''}, "
        f"{doc['particles']} particles, mean over runs (metres)"
    )
    table.add_column("method")
    for col in ("pose\nRMSE", "landmark\nRMSE", "final\nerror", "relations\ntrue / false"):
        table.add_column(col, justify="right")
    table.add_column("ms per\nstep", justify="right")
    for entry in doc["table"].values():
        rel = (
            f"{entry['relations_true']:.1f} / {entry['relations_false']:.1f}"
            if "relations_true" in entry
            else "—"
        )
        table.add_row(
            entry["label"].replace(" (", "\n("),
            f"{entry['pose_rmse']:.3f}",
            f"{entry['landmark_rmse']:.3f}",
            f"{entry['final_error']:.3f}",
            rel,
            f"{entry['step_ms']:.3f}",
        )
    console.print(table)
    nees = ", ".join(
        f"{e['label']} {e['pose_nees']:.1f} / {100 * e['nees_over_bound']:.0f} %"
        for e in doc["table"].values()
        if "pose_nees" in e
    )
    console.print(
        "pose NEES (3 dof; median over steps, mean over runs; 3 if consistent) / steps above the "
        f"χ² 99 % bound: {nees}"
    )
    relations = doc["methods"]["semantic_ufastslam"]["relations"]
    if relations != "off":
        console.print(
            f"Semantic UFastSLAM ({relations}) has a lower pose RMSE than UFastSLAM on "
            f"{doc['semantic_beats_ufastslam']} of {runs} runs"
        )


def plot_paths(
    ax: Any, world: UWorld, truth: Array, odometry: Array, est: MethodRun, title: str
) -> None:
    """Like the paper's Fig. 4, 7 and 10: true path, odometry, the estimate, true and estimated
    landmarks, and the relation groups the estimate used (dotted, on the estimated map)."""
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.4, label="true path")
    ax.plot(odometry[:, 0], odometry[:, 1], "--", color="0.55", lw=1.0, label="odometry")
    ax.plot(est.path[:, 0], est.path[:, 1], "-", color="tab:red", lw=1.2, label="estimate")
    ax.plot(*world.landmarks.T, "s", ms=5, mfc="none", mec="k", label="true landmarks")
    ax.plot(*est.map_xy.T, "x", color="tab:blue", ms=5, label="estimated landmarks")
    for lid, (x, y) in zip(world.landmark_ids, world.landmarks, strict=True):
        ax.annotate(str(lid), (x, y), textcoords="offset points", xytext=(3, 3), fontsize=6)
    where = {lid: xy for lid, xy in zip(est.map_ids, est.map_xy, strict=True)}
    colours = {"x": "tab:green", "y": "tab:purple", "col": "tab:orange"}
    shown = set()
    for kind, _, members in est.groups:
        pts = np.array([where[m] for m in members if m in where]).reshape(-1, 2)
        if len(pts) < 2:
            continue
        order = np.argsort(pts[:, 1] if kind == "x" else pts[:, 0])
        label = None if kind in shown else f"{kind} relation"
        shown.add(kind)
        ax.plot(*pts[order].T, ":", color=colours[kind], lw=1.0, label=label)
    ax.plot(*truth[0, :2], "ko", ms=6)
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=4)


def plot_error_curves(ax: Any, curves: dict[str, Array], dt: float, title: str) -> None:
    """Mean position error over time per method: ``curves`` label → (steps + 1,)."""
    for label, curve in curves.items():
        ax.plot(np.arange(len(curve)) * dt, curve, label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def plot_per_run(ax: Any, seeds: list[int], plain: Array, semantic: Array, label: str) -> None:
    """Pose RMSE of UFastSLAM and the semantic variant on every run."""
    x = np.arange(len(seeds))
    ax.bar(x - 0.2, plain, 0.4, label="UFastSLAM", color="tab:gray")
    ax.bar(x + 0.2, semantic, 0.4, label=label, color="tab:red")
    ax.set_xticks(x, [str(s) for s in seeds], fontsize=7)
    ax.set_xlabel("seed")
    ax.set_ylabel("pose RMSE [m]")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)


def write_plots(out: Path, world: UWorld, runs: list[SeedRun], relations: str) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = runs[0]
    semantic = _semantic_method(relations)
    sem_label = f"Semantic UFastSLAM ({relations})"
    odometry = first.methods["odometry"].path
    written = []
    extent = np.ptp(np.vstack([world.landmarks, first.truth[:, :2], odometry[:, :2]]), axis=0)
    height = float(np.clip(6.5 * extent[1] / max(extent[0], 1e-9), 3.0, 10.0))
    fig, axes = plt.subplots(1, 2, figsize=(14, height + 1.6), layout="constrained")
    plot_paths(axes[0], world, first.truth, odometry, first.methods["ufastslam"], "(a) UFastSLAM")
    plot_paths(axes[1], world, first.truth, odometry, first.methods[semantic], f"(b) {sem_label}")
    fig.suptitle(f"{world.name}, seed {first.seed} (like the paper's Fig. 4, 7, 10)")
    written.append(_save(fig, out / f"paths_seed{first.seed}.png", plt))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    curves = {}
    for m in METHODS:
        paths = np.stack([r.methods[m].path for r in runs])
        curves[LABELS[m]] = np.linalg.norm(paths[..., :2] - first.truth[None, :, :2], axis=-1).mean(
            0
        )
    plot_error_curves(
        ax, curves, world.dt, f"{world.name}: mean position error over {len(runs)} runs"
    )
    written.append(_save(fig, out / "position_error.png", plt))
    fig, ax = plt.subplots(figsize=(max(6, 0.4 * len(runs) + 2), 4))
    plot_per_run(
        ax,
        [r.seed for r in runs],
        np.array([r.methods["ufastslam"].pose_rmse for r in runs]),
        np.array([r.methods[semantic].pose_rmse for r in runs]),
        sem_label,
    )
    ax.set_title(f"{world.name}: pose RMSE per run", fontsize=10)
    written.append(_save(fig, out / "pose_rmse_per_run.png", plt))
    return written


def _save(fig: Any, path: Path, plt: Any) -> Path:
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def run(args: argparse.Namespace, console: Console) -> int:
    world = load_world(args.scenario)
    if args.seed + args.runs - 1 > MAX_SEED:
        raise UsageError(f"--seed {args.seed} with --runs {args.runs} runs past the largest seed")
    seeds = [args.seed + i for i in range(args.runs)]
    console.print(
        f"ufastslam: {world.name} ({world.steps} steps of {world.dt} s, "
        f"{len(world.landmark_ids)} landmarks, {len(world.groups)} relation groups), "
        f"{args.particles} particles, {args.runs} runs (seeds {seeds[0]}..{seeds[-1]}), "
        f"{args.jobs} jobs, relations {args.relations}"
    )
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=True) as progress:
        task = progress.add_task("runs", total=len(seeds))
        runs = run_all(world, seeds, args.particles, args.jobs, lambda: progress.advance(task))
    doc = summarise(world, runs, args.particles, args.relations)
    out = Path(args.out)
    write_results(out, doc, runs, args.relations)
    render(doc, console)
    plots = write_plots(out, world, runs, args.relations)
    console.print(
        f"wrote {out / 'results.json'}, {out / 'results.npz'} and {len(plots)} plots in {out}"
    )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "ufastslam",
        help="dead reckoning vs UFastSLAM vs Semantic UFastSLAM on a world, over seeded runs",
    )
    p.add_argument(
        "--scenario",
        required=True,
        help="a world file (.toml) or a bundled world: rectangle, office, aisles",
    )
    p.add_argument("--particles", type=positive_int, default=50)
    p.add_argument("--runs", type=positive_int, default=20)
    p.add_argument("--jobs", type=positive_int, default=1, help="parallel processes")
    p.add_argument("--seed", type=seed, default=0, help="runs use seeds S, S+1, …")
    p.add_argument(
        "--relations",
        choices=RELATION_CHOICES,
        default="oracle",
        help="relation source of results.json's semantic_ufastslam (the table shows both)",
    )
    p.add_argument("--out", default="out/ufastslam", help="output folder")
    p.set_defaults(run=run)
