"""Plots draw what they are given."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from deploy.plots import plot_reliability
from estimator.metrics import ECE_BINS, calibration_stats
from tests.tolerance import assert_close


def test_plot_reliability_points_diagonal_and_counts() -> None:
    # local: 0.9 twice (one hit) and 0.1 twice (one hit); distributed: certain and right
    local = calibration_stats(np.array([[0.9, 0.1], [0.9, 0.1]]), np.array([0, 1]))
    dist = calibration_stats(np.array([[1.0, 0.0]]), np.array([0]))
    fig, (ax, ax_counts) = plt.subplots(2, 1)
    try:
        plot_reliability(ax, ax_counts, {"local": local, "distributed": dist}, "t")
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert set(lines) == {"calibrated", "local (ECE 0.4)", "distributed (ECE 0)"}
        assert_close(lines["calibrated"].get_xydata(), [[0, 0], [1, 1]])
        assert_close(lines["local (ECE 0.4)"].get_xydata(), [[0.1, 0.5], [0.9, 0.5]])
        assert_close(lines["distributed (ECE 0)"].get_xydata(), [[0.0, 0.0], [1.0, 1.0]])
        heights = [bar.get_height() for bar in ax_counts.patches]
        assert len(heights) == 2 * ECE_BINS
        assert_close(heights[:ECE_BINS], local[0])
        assert_close(heights[ECE_BINS:], dist[0])
        assert ax.get_title() == "t"
    finally:
        plt.close(fig)
