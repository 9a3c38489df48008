"""Plots. Each function draws on an axes it is given; none reads settings from the environment."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Wedge

from sim.world import World

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
        ax.annotate(r.id, traj[0, :2], textcoords="offset points", xytext=(4, 4), color=colour)
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


_METHOD_STYLE = {
    "local": {"color": "tab:blue", "ls": "-"},
    "distributed": {"color": "tab:green", "ls": "-"},
    "double_count": {"color": "tab:red", "ls": "--"},
    "centralized": {"color": "black", "ls": ":"},
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
    snap: object,
    world: World,
    robot: str,
    k: int,
    max_hypotheses: int = 5,
) -> None:
    """Fig. 3b/3c: the heaviest hypotheses' robot and object estimates with 2σ ellipses over the
    truth, and P(c = 1) per known object against its true class."""
    from estimator.metrics import class_marginals, world_position_cov

    s = world.scenario
    w = snap.weights  # type: ignore[attr-defined]
    order = np.argsort(-w)[:max_hypotheses]
    traj = world.trajectories[robot]
    ax_map.plot(traj[: k + 1, 0], traj[: k + 1, 1], "k-", lw=1, label=f"{robot} true path")
    truth = {o.id: o for o in s.objects}
    ids = snap.object_ids  # type: ignore[attr-defined]
    for j in ids:
        ax_map.plot(*truth[j].pose[:2], "ks", ms=5, mfc="none")
        ax_map.annotate(
            str(j), truth[j].pose[:2], textcoords="offset points", xytext=(4, 4), fontsize=7
        )
    cmap = plt.get_cmap("viridis")
    # Lightest first, so the heaviest hypothesis is drawn on top.
    for rank, h in reversed(list(enumerate(order))):
        colour = cmap(rank / max(1, len(order) - 1))
        label = f"h{rank + 1}: w = {w[h]:.2f}"
        rp = snap.robot_pose[h]  # type: ignore[attr-defined]
        ax_map.plot(*rp[:2], "o", color=colour, ms=4, label=label)
        covariance_ellipse(
            ax_map, rp[:2], world_position_cov(rp, snap.robot_cov[h]), color=colour, lw=0.8
        )  # type: ignore[attr-defined]
        for n in range(len(ids)):
            op = snap.object_pose[h, n]  # type: ignore[attr-defined]
            oc = world_position_cov(op, snap.object_cov[h, n])  # type: ignore[attr-defined]
            covariance_ellipse(ax_map, op[:2], oc, color=colour, lw=0.8)
            ax_map.plot(*op[:2], ".", color=colour, ms=4)
    ax_map.set_aspect("equal")
    ax_map.set_title(f"{robot} at k = {k}: top {len(order)} of {len(w)} hypotheses (2σ)")
    ax_map.legend(fontsize=7)
    ax_map.grid(True, alpha=0.3)
    prob = class_marginals(w, snap.classes, s.num_classes)  # type: ignore[attr-defined]
    x = np.arange(len(ids))
    true_c1 = np.array([1.0 if truth[j].class_index == 0 else 0.0 for j in ids])
    ax_class.bar(x, prob[:, 0], color="tab:blue", label="P(c = 1)")
    ax_class.scatter(
        x, true_c1, marker="_", s=300, color="red", linewidths=2, label="truth", zorder=3
    )
    ax_class.set_xticks(x, [str(j) for j in ids])
    ax_class.set_ylim(0, 1.05)
    ax_class.set_xlabel("object")
    ax_class.set_title("class 1 probability per object")
    ax_class.legend(fontsize=7)
