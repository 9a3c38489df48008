"""The plot of a classifier fit: per class and score component, the samples against ψ, the fitted
mean h_c(ψ) with its ±2σ band from Σ_c(ψ), and optionally the model that generated the samples.
Import it only where the plot is drawn: matplotlib takes a second to import."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes

from deploy.study.classifier_samples import ScoreSamples
from estimator.models import ClassifierModel

_GRID = np.linspace(-math.pi, math.pi, 361)
MAX_PANELS = 6  # classes (rows) and components (columns) drawn at most


def plot_component(
    ax: Axes,
    samples: ScoreSamples,
    model: ClassifierModel,
    c: int,
    i: int,
    truth: ClassifierModel | None = None,
) -> None:
    """Score component ``i`` of class ``c``: samples, fitted mean ± 2σ, the true mean dashed."""
    psi, z = samples.of_class(c)
    deg = np.degrees(_GRID)
    mean = model.mean(c, _GRID)[:, i]
    std = np.sqrt(model.cov(c, _GRID)[:, i, i])
    ax.scatter(np.degrees(psi), z[:, i], s=4, color="0.55", alpha=0.6, label="samples")
    ax.fill_between(deg, mean - 2 * std, mean + 2 * std, color="C0", alpha=0.2, label="±2σ")
    ax.plot(deg, mean, color="C0", label="fitted h")
    if truth is not None:
        ax.plot(deg, truth.mean(c, _GRID)[:, i], "--", color="C3", label="true h")
    ax.set_xlim(-180, 180)
    ax.set_xticks(range(-180, 181, 90))
    ax.set_title(f"class {c + 1}, score z{i + 1}", fontsize=9)
    ax.grid(alpha=0.3)


def save_fit_plot(
    out: Path,
    samples: ScoreSamples,
    model: ClassifierModel,
    truth: ClassifierModel | None = None,
) -> Path:
    """One panel per class (rows) and score component (columns) into the PNG ``out``, the first
    :data:`MAX_PANELS` of each."""
    m, dim = min(model.num_classes, MAX_PANELS), min(model.dim, MAX_PANELS)
    fig, axes = plt.subplots(m, dim, figsize=(3.2 * dim, 2.4 * m), squeeze=False, sharex=True)
    for c in range(m):
        for i in range(dim):
            plot_component(axes[c][i], samples, model, c, i, truth)
    for ax in axes[-1]:
        ax.set_xlabel("viewpoint ψ [deg]")
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
