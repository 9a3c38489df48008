"""Every plot of semfleet. Each ``plot_*`` function draws data on an axes it is given; the
``write_*`` functions lay out and save the figures of a study. None reads settings from the
environment. Import it only where a plot is drawn: matplotlib takes a second to import.

Over 300 lines for a reason: the one home of the project's plots (issue 12), with the hybrid-belief
study's, the UFastSLAM study's, the scenario's and the fleet operator's figures side by side.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Wedge

from deploy.study.archive import pooled_calibration
from deploy.study.paper_figures import PaperValue, by_metric
from deploy.study.types import UFASTSLAM_LABELS as LABELS
from deploy.study.types import UFASTSLAM_METHODS as METHODS
from deploy.study.types import MethodRun, RunResult, SeedRun, semantic_method
from estimator.hybrid import BeliefSnapshot
from estimator.metrics import chi2_bounds
from sim.scenario import Scenario
from sim.ufastslam import UWorld
from sim.world import World

DPI = 110

_ROBOT_COLOURS = plt.get_cmap("tab10")
_CLASS_COLOURS = plt.get_cmap("Set1")


def plot_ground_truth(ax: Axes, world: World, cone_steps: Sequence[int] = ()) -> None:
    """Trajectories, objects with orientation and class colour, sensing cones at ``cone_steps``
    (like the paper's Fig. 2a)."""
    s = world.scenario
    for i, r in enumerate(s.robots):
        traj = world.trajectories[r.id]
        colour = _ROBOT_COLOURS(i % 10)
        ax.plot(traj[:, 0], traj[:, 1], "-", color=colour, lw=1.5, label=r.id)
        ax.plot(*traj[0, :2], "o", color=colour, ms=6)
        ax.annotate(
            r.id, tuple(traj[0, :2]), textcoords="offset points", xytext=(4, 4), color=colour
        )
        for k in cone_steps:
            if not 0 <= k <= s.steps:
                continue
            x, y, t = traj[k]
            half = np.degrees(r.sensor.half_angle)
            ax.add_patch(
                Wedge(
                    (x, y),
                    r.sensor.range,
                    np.degrees(t) - half,
                    np.degrees(t) + half,
                    color=colour,
                    alpha=0.12,
                )
            )
            ax.plot(x, y, ">", color=colour, ms=5)
            ax.annotate(
                f"k={k}",
                (x, y),
                textcoords="offset points",
                xytext=(-8, 6),
                color=colour,
                fontsize=7,
            )
    poses = world.object_poses
    classes = s.object_classes()
    arrow = 0.6
    for c in range(s.num_classes):
        sel = classes == c
        if not sel.any():
            continue
        colour = _CLASS_COLOURS(c % 9)
        ax.scatter(
            poses[sel, 0],
            poses[sel, 1],
            s=40,
            color=colour,
            marker="s",
            label=f"class {c + 1}",
            zorder=3,
        )
        ax.quiver(
            poses[sel, 0],
            poses[sel, 1],
            arrow * np.cos(poses[sel, 2]),
            arrow * np.sin(poses[sel, 2]),
            color=colour,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            width=0.004,
            zorder=3,
        )
    for o, (x, y, _) in zip(s.objects, poses, strict=True):
        ax.annotate(str(o.id), (x, y), textcoords="offset points", xytext=(5, -10), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{s.name}: ground truth")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)


_METHOD_STYLE: dict[str, dict[str, Any]] = {
    "local": {"color": "tab:blue", "ls": "-"},
    "distributed": {"color": "tab:green", "ls": "-"},
    "double_count": {"color": "tab:red", "ls": "--"},
    "centralized": {"color": "black", "ls": ":"},
    "received": {"color": "tab:purple", "ls": "-."},
}


def plot_curves(
    ax: Axes,
    curves: dict[str, list[float | None]],
    ylabel: str,
    title: str,
    band: tuple[float, float] | None = None,
) -> None:
    """One line per method against the step k = 1..steps; ``band`` shades a reference interval."""
    for method, curve in curves.items():
        k = np.arange(1, len(curve) + 1)
        y = np.array([np.nan if v is None else v for v in curve], dtype=float)
        ax.plot(k, y, label=method, lw=1.6, **_METHOD_STYLE.get(method, {}))
    if band is not None:
        ax.axhspan(*band, color="grey", alpha=0.15, label="χ² 95 % band")
    ax.set_xlabel("step k")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def plot_paper_values(ax: Axes, values: Sequence[PaperValue]) -> None:
    """The paper's read-off values (deploy.study.paper_figures) as open diamonds at their step, the
    bar spanning the interval read, in the colour of their method's curve."""
    for v in values:
        colour = _METHOD_STYLE.get(v.method, {}).get("color", "grey")
        ax.errorbar(
            [v.step],
            [v.middle],
            yerr=[[v.middle - v.low], [v.high - v.middle]],
            fmt="D",
            color=colour,
            mfc="white",
            ms=6,
            capsize=4,
            zorder=4,
            label=f"paper {v.figure}, {v.method} (read off)",
        )
    if values:
        ax.legend(fontsize=7)


def plot_reliability(ax: Axes, ax_counts: Axes, stats: dict[str, np.ndarray], title: str) -> None:
    """Reliability diagram of the class marginals: per method, the mean predicted probability
    against the observed frequency of the class in every non-empty bin, over the diagonal of
    perfect calibration; ``ax_counts`` shows the marginals per bin (log scale). ``stats`` maps
    method → pooled bin statistics (3, bins) (``estimator.metrics.calibration_stats``)."""
    from estimator.metrics import ECE_BINS, ece_from_stats

    bins = next(iter(stats.values())).shape[-1] if stats else ECE_BINS
    width = 1.0 / bins / max(1, len(stats))
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls="--", label="calibrated")
    for n, (method, st) in enumerate(stats.items()):
        count, sum_p, hits = st
        used = count > 0
        style = _METHOD_STYLE.get(method, {})
        ece = float(ece_from_stats(st))
        ax.plot(
            sum_p[used] / count[used],
            hits[used] / count[used],
            marker="o",
            ms=4,
            lw=1.4,
            label=f"{method} (ECE {ece:.3g})",
            **style,
        )
        left = np.arange(bins) / bins + n * width
        ax_counts.bar(left, count, width=width, align="edge", color=style.get("color"))
    # Most marginals sit at 0 or 1: a margin keeps their points inside the axes.
    ax.set_xlim(-0.02, 1.02)
    ax.set_ylim(-0.02, 1.02)
    ax.set_ylabel("observed frequency of the class")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax_counts.set_yscale("symlog", linthresh=1.0)
    ax_counts.set_xticks(np.arange(bins + 1) / bins)
    ax_counts.set_xlabel("predicted probability P(c_j = i)")
    ax_counts.set_ylabel("marginals per bin")
    ax_counts.grid(True, alpha=0.3)


def covariance_ellipse(
    ax: Axes, mean: np.ndarray, cov: np.ndarray, nsigma: float = 2.0, **kw: object
) -> None:
    """Draw the ``nsigma`` ellipse of a 2×2 covariance at ``mean``."""
    vals, vecs = np.linalg.eigh(cov)
    t = np.linspace(0, 2 * np.pi, 60)
    circle = np.stack([np.cos(t), np.sin(t)])
    pts = mean[:, None] + nsigma * vecs @ (np.sqrt(np.maximum(vals, 0))[:, None] * circle)
    ax.plot(pts[0], pts[1], **kw)  # type: ignore[arg-type]


def plot_hypotheses(
    ax_map: Axes,
    ax_class: Axes,
    snap: BeliefSnapshot,
    world: World,
    robot: str,
    k: int,
    max_hypotheses: int = 5,
) -> None:
    """Fig. 3b/3c: the heaviest hypotheses' robot and object estimates with 2σ ellipses over the
    truth, and P(c = 1) per known object against its true class (objects of false detections,
    which given ids with clutter bring, have no truth to draw)."""
    from estimator.metrics import world_position_cov

    s = world.scenario
    w = snap.weights
    order = np.argsort(-w)[:max_hypotheses]
    traj = world.trajectories[robot]
    ax_map.plot(traj[: k + 1, 0], traj[: k + 1, 1], "k-", lw=1, label=f"{robot} true path")
    truth = {o.id: o for o in s.objects}
    ids = snap.object_ids
    for j in ids:
        if j not in truth:  # a false detection's object (given ids with clutter): no truth
            continue
        tx, ty = truth[j].pose[:2]
        ax_map.plot(tx, ty, "ks", ms=5, mfc="none")
        ax_map.annotate(str(j), (tx, ty), textcoords="offset points", xytext=(4, 4), fontsize=7)
    cmap = plt.get_cmap("viridis")
    # Lightest first, so the heaviest hypothesis is drawn on top.
    for rank, h in reversed(list(enumerate(order))):
        colour = cmap(rank / max(1, len(order) - 1))
        label = f"h{rank + 1}: w = {w[h]:.2f}"
        rp = snap.robot_pose[h]
        ax_map.plot(*rp[:2], "o", color=colour, ms=4, label=label)
        covariance_ellipse(
            ax_map, rp[:2], world_position_cov(rp, snap.robot_cov[h]), color=colour, lw=0.8
        )
        for n in range(len(ids)):
            op = snap.object_pose[h, n]
            oc = world_position_cov(op, snap.object_cov[h, n])
            covariance_ellipse(ax_map, op[:2], oc, color=colour, lw=0.8)
            ax_map.plot(*op[:2], ".", color=colour, ms=4)
    ax_map.set_aspect("equal")
    ax_map.set_xlabel("x [m]")
    ax_map.set_ylabel("y [m]")
    ax_map.set_title(f"{robot} at k = {k}: top {len(order)} of {len(w)} hypotheses (2σ)")
    ax_map.legend(fontsize=7)
    ax_map.grid(True, alpha=0.3)
    prob = snap.marginals(s.num_classes)
    x = np.arange(len(ids))
    true_c1 = np.array([float(truth[j].class_index == 0) if j in truth else math.nan for j in ids])
    ax_class.bar(x, prob[:, 0], color="tab:blue", label="P(c = 1)")
    ax_class.scatter(
        x, true_c1, marker="_", s=300, color="red", linewidths=2, label="truth", zorder=3
    )
    ax_class.set_xticks(x, [str(j) for j in ids])
    ax_class.set_ylim(0, 1.05)
    ax_class.set_xlabel("object id")
    ax_class.set_ylabel("P(c = 1)")
    ax_class.set_title("class 1 probability per object")
    ax_class.legend(fontsize=7)


def save(fig: Figure, path: Path) -> Path:
    """Save ``fig`` as a PNG at ``path`` and close it."""
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


# ---- the hybrid-belief study (docs/results.md, "Plots") ----------------------------------------

# metric, y label, title, the NEES degrees of freedom of its χ² band (None: no band)
STUDY_CURVES = (
    ("msde", "MSDE", "class accuracy (paper Fig. 3a)", None),
    ("robot_error", "robot position error [m]", "robot error (Fig. 2b)", None),
    ("object_error", "object position error [m]", "object error (Fig. 2c)", None),
    ("robot_sqrt_det", "√det Σ_robot [m²]", "robot uncertainty (Fig. 2d)", None),
    ("object_sqrt_det", "√det Σ_objects [m²]", "object uncertainty (Fig. 2e)", None),
    ("robot_nees", "NEES (top hypothesis, 3 dof)", "robot pose NEES", 3),
    ("object_nees", "NEES (top hypothesis, 2 dof)", "object position NEES", 2),
    ("hypotheses", "hypotheses", "hypotheses per belief", None),
)


def write_curves_and_reliability(
    out: Path,
    doc: dict[str, Any],
    results: Sequence[RunResult],
    step: int,
    paper: Sequence[PaperValue] = (),
) -> list[Path]:
    """The curves of ``doc``'s means and the reliability diagram at ``step`` pooled over
    ``results`` into ``out`` (a study's, or a merge of its shards); the paths written. ``paper``:
    read-off values of the paper's figures, drawn on the curves of their metrics."""
    matplotlib.use("Agg")
    written = []
    published = by_metric(paper)
    for metric, ylabel, title, dof in STUDY_CURVES:
        fig, ax = plt.subplots(figsize=(7, 4.5))
        curves = {m: e["mean"][metric] for m, e in doc["methods"].items()}
        band = None if dof is None else chi2_bounds(dof, doc["runs"])
        plot_curves(ax, curves, ylabel, f"{doc['scenario']}: {title}", band)
        plot_paper_values(ax, published.get(metric, []))
        written.append(save(fig, out / f"{metric}.png"))
    pooled = {m: pooled_calibration(results, m) for m in doc["methods"]}
    at_step = {m: p[step - 1] for m, p in pooled.items() if p is not None}
    if at_step:
        fig, (ax, ax_counts) = plt.subplots(
            2, 1, figsize=(6.5, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
        )
        title = f"{doc['scenario']}: class calibration at k = {step}"
        plot_reliability(ax, ax_counts, at_step, title)
        written.append(save(fig, out / "reliability.png"))
    return written


def write_study_plots(
    out: Path,
    doc: dict[str, Any],
    scenario: Scenario,
    results: Sequence[RunResult],
    step: int,
    robot: str,
    paper: Sequence[PaperValue] = (),
) -> list[Path]:
    """The curves of ``doc``'s means (with ``paper``'s read-off values), the reliability
    diagram at ``step`` and the first run's hypothesis snapshots of ``robot`` into ``out``; the
    paths written."""
    written = write_curves_and_reliability(out, doc, results, step, paper)
    trajectories = plot_trajectories(scenario, results[0])
    if trajectories is not None:
        written.append(save(trajectories, out / "trajectories.png"))
    world = World(scenario)
    for method, snaps in results[0].snapshots.items():
        if robot not in snaps:
            continue
        fig, (ax_map, ax_class) = plt.subplots(
            1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.4, 1]}
        )
        plot_hypotheses(ax_map, ax_class, snaps[robot], world, robot, step)
        fig.suptitle(f"{method}, seed {results[0].seed} (paper Fig. 3b/3c)")
        written.append(save(fig, out / f"hypotheses_{method}_{robot}_k{step}.png"))
    return written


def plot_trajectories(scenario: Scenario, run: RunResult) -> Figure | None:
    """Every robot's estimated trajectory (solid) against the true one (dashed, e.g. Vicon for a
    recorded run), one panel per method of ``run`` that recorded trajectories, with the true
    objects; None when no method did."""
    methods = [
        m
        for m, tracks in run.metrics.items()
        if "robot_pose" in tracks and "true_robot_pose" in tracks
    ]
    if not methods:
        return None
    fig, axes = plt.subplots(1, len(methods), figsize=(5.2 * len(methods), 4.6), squeeze=False)
    objects = scenario.object_poses()[:, :2]
    colours = plt.get_cmap("tab10")
    for ax, method in zip(axes[0], methods, strict=True):
        tracks = run.metrics[method]
        for i, robot in enumerate(run.robots or scenario.robot_ids):
            colour = colours(i % 10)
            truth, est = tracks["true_robot_pose"][i], tracks["robot_pose"][i]
            ax.plot(truth[:, 0], truth[:, 1], "--", color=colour, lw=0.8, alpha=0.7)
            ax.plot(est[:, 0], est[:, 1], "-", color=colour, lw=1.1, label=robot)
        ax.plot(*objects.T, "s", ms=4, mfc="none", mec="k", label="objects (true)")
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title(f"{method}: estimate (solid), truth (dashed)", fontsize=10)
    axes[0][0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{scenario.name}, seed {run.seed}: robot trajectories")
    return fig


# ---- the UFastSLAM study (docs/ufastslam.md) ---------------------------------------------------


def plot_paths(
    ax: Axes,
    landmark_ids: Sequence[int],
    landmarks: np.ndarray,
    truth: np.ndarray,
    odometry: np.ndarray,
    est: MethodRun,
    title: str,
) -> None:
    """Like the paper's Fig. 4, 7 and 10: true path (steps + 1, 3), odometry (steps + 1, 3), the
    estimate, true landmarks (L, 2) and estimated ones, and the relation groups the estimate used
    (dotted, on the estimated map)."""
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.4, label="true path")
    ax.plot(odometry[:, 0], odometry[:, 1], "--", color="0.55", lw=1.0, label="odometry")
    ax.plot(est.path[:, 0], est.path[:, 1], "-", color="tab:red", lw=1.2, label="estimate")
    ax.plot(*landmarks.T, "s", ms=5, mfc="none", mec="k", label="true landmarks")
    ax.plot(*est.map_xy.T, "x", color="tab:blue", ms=5, label="estimated landmarks")
    for lid, (x, y) in zip(landmark_ids, landmarks, strict=True):
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


def plot_error_curves(ax: Axes, curves: dict[str, np.ndarray], dt: float, title: str) -> None:
    """Mean position error over time per method: ``curves`` label → (steps + 1,)."""
    for label, curve in curves.items():
        ax.plot(np.arange(len(curve)) * dt, curve, label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def plot_per_run(
    ax: Axes, seeds: Sequence[int], plain: np.ndarray, semantic: np.ndarray, label: str
) -> None:
    """Pose RMSE of UFastSLAM and the semantic variant on every run: plain, semantic (runs,)."""
    x = np.arange(len(seeds))
    ax.bar(x - 0.2, plain, 0.4, label="UFastSLAM", color="tab:gray")
    ax.bar(x + 0.2, semantic, 0.4, label=label, color="tab:red")
    ax.set_xticks(x, [str(s) for s in seeds], fontsize=7)
    ax.set_xlabel("seed")
    ax.set_ylabel("pose RMSE [m]")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)


def write_ufastslam_plots(
    out: Path, world: UWorld, runs: Sequence[SeedRun], relations: str
) -> list[Path]:
    """The first seed's paths, the mean position error over time and the pose RMSE per run of a
    UFastSLAM study into ``out``; the paths written."""
    matplotlib.use("Agg")
    first = runs[0]
    semantic = semantic_method(relations)
    sem_label = f"Semantic UFastSLAM ({relations})"
    odometry = first.methods["odometry"].path
    written = []
    extent = np.ptp(np.vstack([world.landmarks, first.truth[:, :2], odometry[:, :2]]), axis=0)
    height = float(np.clip(6.5 * extent[1] / max(extent[0], 1e-9), 3.0, 10.0))
    fig, axes = plt.subplots(1, 2, figsize=(14, height + 1.6), layout="constrained")
    for ax, method, title in (
        (axes[0], "ufastslam", "(a) UFastSLAM"),
        (axes[1], semantic, f"(b) {sem_label}"),
    ):
        plot_paths(
            ax,
            world.landmark_ids,
            world.landmarks,
            first.truth,
            odometry,
            first.methods[method],
            title,
        )
    fig.suptitle(f"{world.name}, seed {first.seed} (like the paper's Fig. 4, 7, 10)")
    written.append(save(fig, out / f"paths_seed{first.seed}.png"))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    curves = {}
    for m in METHODS:
        paths = np.stack([r.methods[m].path for r in runs])
        error = np.linalg.norm(paths[..., :2] - first.truth[None, :, :2], axis=-1)
        curves[LABELS[m]] = error.mean(0)
    title = f"{world.name}: mean position error over {len(runs)} runs"
    plot_error_curves(ax, curves, world.dt, title)
    written.append(save(fig, out / "position_error.png"))
    fig, ax = plt.subplots(figsize=(max(6, 0.4 * len(runs) + 2), 4))
    plot_per_run(
        ax,
        [r.seed for r in runs],
        np.array([r.methods["ufastslam"].pose_rmse for r in runs]),
        np.array([r.methods[semantic].pose_rmse for r in runs]),
        sem_label,
    )
    ax.set_title(f"{world.name}: pose RMSE per run", fontsize=10)
    written.append(save(fig, out / "pose_rmse_per_run.png"))
    return written


def plot_robot_map(
    ax: Axes, robot: str, doc: Mapping[str, Any], belief: str, colours: Mapping[str, Any]
) -> None:
    """One robot's ``belief`` from an estimates.json document: objects coloured by their most
    probable class with 2σ ellipses, every robot's trail and latest position (its own belief)."""
    entry = doc["robots"][robot]
    b = entry["beliefs"][belief]
    drawn: set[int] = set()
    for obj in b["objects"]:
        c = int(np.argmax(obj["marginals"]))
        colour = _CLASS_COLOURS(c % 9)
        xy = np.array(obj["pose"][:2])
        covariance_ellipse(ax, xy, np.array(obj["cov_xy"]), color=colour, lw=0.8)
        label = f"class {c + 1}" if c not in drawn else None
        drawn.add(c)
        ax.plot(*xy, "s", color=colour, ms=5, label=label)
        ax.annotate(
            str(obj["id"]), tuple(xy), textcoords="offset points", xytext=(4, 4), fontsize=7
        )
    for other, e in doc["robots"].items():
        colour = colours[other]
        trail = np.array(e["trail"], dtype=float).reshape(-1, 3)
        ax.plot(trail[:, 1], trail[:, 2], "-", color=colour, lw=1.5 if other == robot else 0.8)
        own = e["beliefs"][_main_belief(e)]
        x, y, theta = own["robot_pose"]
        if other == robot:
            covariance_ellipse(ax, np.array([x, y]), np.array(own["robot_cov_xy"]), color=colour)
        marker = (3, 0, math.degrees(theta) - 90)  # a triangle pointing along θ
        ax.plot(x, y, marker=marker, color=colour, ms=10 if other == robot else 6, ls="none")
        ax.annotate(other, (x, y), textcoords="offset points", xytext=(6, -10), color=colour)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (fleet frame)")
    ax.set_ylabel("y [m] (fleet frame)")
    ax.set_title(f"{robot} at k = {entry['k']}: {belief}, {b['hypotheses']} hypotheses (2σ)")
    ax.grid(True, alpha=0.3)
    if drawn:
        ax.legend(fontsize=7, loc="best")


def _main_belief(entry: Mapping[str, Any]) -> str:
    beliefs = entry["beliefs"]
    return "distributed" if "distributed" in beliefs else sorted(beliefs)[0]


def write_fleet_map(path: Path, doc: Mapping[str, Any]) -> None:
    """map.png: one panel per robot (its D, or its only belief), on common axes."""
    matplotlib.use("Agg")
    robots = sorted(doc["robots"])
    colours = {r: plt.get_cmap("tab10")(i % 10) for i, r in enumerate(robots)}
    cols = min(3, len(robots))
    rows = math.ceil(len(robots) / cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(6 * cols, 6 * rows), squeeze=False, sharex=True, sharey=True
    )
    for ax, robot in zip(axes.flat, robots, strict=False):
        plot_robot_map(ax, robot, doc, _main_belief(doc["robots"][robot]), colours)
    for ax in list(axes.flat)[len(robots) :]:
        ax.set_visible(False)
    fig.suptitle(f"fleet {doc['fleet']}: estimates after {doc['watched_s']:.0f} s of watch")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
