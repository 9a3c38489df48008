"""Plots draw what they are given."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

from agents.transport.base import Keys, Message
from deploy.operator.fleet_view import FleetView, estimates_doc
from deploy.study.plots import (
    plot_error_curves,
    plot_hypotheses,
    plot_paths,
    plot_per_run,
    plot_reliability,
    plot_robot_map,
)
from deploy.study.ufastslam import MethodRun
from estimator.metrics import ECE_BINS, calibration_stats
from estimator.snapshot import BeliefSnapshot
from protocol.estimate import EstimateMessage, encode_estimate
from sim.loader import load_scenario
from sim.world import World
from tests.deploy.test_fleet_cmd import HYP
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


def _method_run(path: np.ndarray, map_ids: tuple[int, ...], map_xy: np.ndarray) -> MethodRun:
    groups = (("x", "west", (1, 2, 3)), ("x", "east", (4, 5)), ("y", "north", (1, 9)))
    return MethodRun(0.1, 0.2, 0.3, 1.0, 2, 0, 3.0, 0.5, path, map_ids, map_xy, groups)


def test_plot_paths_draws_the_estimate_and_its_mapped_groups() -> None:
    truth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.5, 0.0]])
    odometry = truth + 0.3
    estimate = truth + 0.1
    # landmark 9 is not mapped: group "north" has one mapped member and is not drawn
    map_ids = (1, 2, 3, 4, 5)
    map_xy = np.array([[0.0, 3.0], [0.1, 1.0], [0.0, 2.0], [3.0, 1.0], [3.1, 2.0]])
    landmarks = np.array([[0.0, 3.0], [0.0, 1.0], [0.0, 2.0], [3.0, 1.0], [3.0, 2.0], [5.0, 5.0]])
    fig, ax = plt.subplots()
    try:
        run = _method_run(estimate, map_ids, map_xy)
        plot_paths(ax, (1, 2, 3, 4, 5, 9), landmarks, truth, odometry, run, "t")
        lines = {line.get_label(): line for line in ax.get_lines()}
        assert_close(lines["estimate"].get_xydata(), estimate[:, :2])
        assert_close(lines["odometry"].get_xydata(), odometry[:, :2])
        assert_close(lines["estimated landmarks"].get_xydata(), map_xy)
        dotted = [line for line in ax.get_lines() if line.get_linestyle() == ":"]
        assert len(dotted) == 2  # west and east; north has one mapped member
        # a same-x group is drawn in order of y, labelled once per kind
        assert_close(dotted[0].get_xydata(), [[0.1, 1.0], [0.0, 2.0], [0.0, 3.0]])
        assert dotted[0].get_label() == "x relation"
        assert dotted[1].get_label().startswith("_")  # no second legend entry for "x"
        assert len(ax.texts) == 6 and ax.get_title() == "t"
    finally:
        plt.close(fig)


def test_plot_error_curves_time_axis_and_plot_per_run_bars() -> None:
    fig, (ax, ax_bars) = plt.subplots(1, 2)
    try:
        plot_error_curves(ax, {"a": np.array([0.0, 1.0, 4.0])}, 0.5, "t")
        assert_close(ax.get_lines()[0].get_xydata(), [[0.0, 0.0], [0.5, 1.0], [1.0, 4.0]])
        plot_per_run(ax_bars, [7, 8], np.array([0.4, 0.6]), np.array([0.1, 0.2]), "sem")
        heights = [bar.get_height() for bar in ax_bars.patches]
        assert_close(heights, [0.4, 0.6, 0.1, 0.2])
        assert [t.get_text() for t in ax_bars.get_xticklabels()] == ["7", "8"]
    finally:
        plt.close(fig)


def test_plot_hypotheses_draws_per_object_class_marginals() -> None:
    """A belief with per-object class marginals: the class bars are P(c = 1) from them, not from
    its one hypothesis' classes (here (1, 2), whose bars would be 1 and 0)."""
    world = World(load_scenario("paper"))
    cov = np.diag([0.04, 0.01, 0.001])
    snap = BeliefSnapshot(
        (1, 2),
        np.array([1.0]),
        np.array([[0, 1]], dtype=np.int64),
        np.array([[0.0, 0.0, 0.0]]),
        cov[None],
        np.array([[o.pose for o in world.scenario.objects[:2]]], dtype=float),
        np.tile(cov, (1, 2, 1, 1)),
        class_probs=np.array([[0.3, 0.7], [0.8, 0.2]]),
    )
    fig, (ax_map, ax_class) = plt.subplots(1, 2)
    try:
        plot_hypotheses(ax_map, ax_class, snap, world, "r1", 5)
        heights = [bar.get_height() for bar in ax_class.patches]
        assert_close(heights, [0.3, 0.8])
        assert (ax_map.get_xlabel(), ax_map.get_ylabel()) == ("x [m]", "y [m]")
        assert (ax_class.get_xlabel(), ax_class.get_ylabel()) == ("object id", "P(c = 1)")
    finally:
        plt.close(fig)


def test_fleet_map_panels_say_their_axes_and_units() -> None:
    """`fleet watch`'s map.png: each robot's panel in metres of the fleet's frame."""
    view = FleetView(Keys("f"))
    est = EstimateMessage("r1", 4, {"distributed": HYP}, {"step": 4})
    view.on_message(Message("semfleet/f/estimate/r1", encode_estimate(est)), now=1.0)
    fig, ax = plt.subplots()
    try:
        plot_robot_map(ax, "r1", estimates_doc(view, watched_s=2.0), "distributed", {"r1": "k"})
        assert ax.get_xlabel() == "x [m] (fleet frame)" and ax.get_ylabel() == "y [m] (fleet frame)"
    finally:
        plt.close(fig)


def test_plot_hypotheses_draws_an_object_without_truth() -> None:
    """Given ids with clutter: a false detection's object is in the belief and in no world's
    truth. Its estimate is drawn; no truth marker or class truth is (the study crashed here)."""
    world = World(load_scenario("paper"))
    cov = np.diag([0.04, 0.01, 0.001])
    clutter = 2_731_202_176
    assert clutter not in {o.id for o in world.scenario.objects}
    snap = BeliefSnapshot(
        (1, clutter),
        np.array([1.0]),
        np.array([[0, 1]], dtype=np.int64),
        np.array([[0.0, 0.0, 0.0]]),
        cov[None],
        np.array([[world.scenario.objects[0].pose, (3.0, 4.0, 0.5)]], dtype=float),
        np.tile(cov, (1, 2, 1, 1)),
        class_probs=np.array([[0.3, 0.7], [0.6, 0.4]]),
    )
    fig, (ax_map, ax_class) = plt.subplots(1, 2)
    try:
        plot_hypotheses(ax_map, ax_class, snap, world, "r1", 5)
        assert [t.get_text() for t in ax_map.texts] == ["1"]
        marks = ax_class.collections[0].get_offsets()
        assert np.isfinite(marks[0]).all() and not np.isfinite(marks[1]).all()
        assert_close([bar.get_height() for bar in ax_class.patches], [0.3, 0.6])
    finally:
        plt.close(fig)
