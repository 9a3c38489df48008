"""The study's value types, at the bottom of ``deploy.study``: what a run returns
(:class:`RunResult`; of the UFastSLAM study, :class:`SeedRun` of :class:`MethodRun`) and how a
run fails (:class:`StudyError`). The runner fills them; the
archive, report, plots, shards and cluster read them, and import no runner for it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from deploy.base.errors import RunFailure
from estimator.hybrid import BeliefSnapshot

# What a fleet's robots associate frames without global ids on (the first is the default): each
# node's D (``Associator``'s guide), or their own L (the robot alone, as ``local`` always does).
ASSOCIATE_ON = ("fused", "local")

Array = NDArray[np.float64]

# What a run records per robot and step next to the metrics, (robots, steps, 3) each: the
# belief's estimate of the robot's pose (the hypotheses' weighted mean) and the true pose.
TRACKS = ("robot_pose", "true_robot_pose")


@dataclass(frozen=True, slots=True)
class RunResult:
    """One seeded run: ``metrics[method][metric]`` (robots, steps) arrays, the wall time of every
    belief step in ms per method, and optional belief snapshots ``snapshots[method][robot]``.
    ``metrics[method]`` also holds the :data:`TRACKS` a :class:`Recorder` keeps, (robots, steps,
    3) x, y, θ, where the run recorded them (a run built by hand may not).

    ``calibration[method]`` (robots, steps, 3, ECE_BINS) holds the class-ECE bin statistics
    (``estimator.metrics.calibration_stats``); the fleets' ``fusion_ms``, ``empty_joins`` and
    ``rebuilds`` have one entry per robot step, in the order of ``step_ms``; ``stack_bytes`` the
    size of every delivered stack. ``robots`` names the robot axis of every array, in order
    (empty: not recorded). ``association[method]``: for frames without global ids, the
    association's figures against the truth (``deploy.study.association.COUNTS``, summed over
    robots) and ``association_ms[method]`` its time per frame; ``fleet_association[method]``
    a fleet's mappings of peers' objects against the truth
    (``deploy.study.association.FLEET_COUNTS``)."""

    seed: int
    metrics: dict[str, dict[str, Array]]
    step_ms: dict[str, list[float]]
    wall_s: dict[str, float]
    snapshots: dict[str, dict[str, BeliefSnapshot]] = field(default_factory=dict)
    fusion_ms: dict[str, list[float]] = field(default_factory=dict)
    stack_bytes: dict[str, list[int]] = field(default_factory=dict)
    calibration: dict[str, Array] = field(default_factory=dict)
    empty_joins: dict[str, list[int]] = field(default_factory=dict)
    rebuilds: dict[str, list[int]] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    robots: tuple[str, ...] = ()
    association: dict[str, dict[str, int]] = field(default_factory=dict)
    association_ms: dict[str, list[float]] = field(default_factory=dict)
    fleet_association: dict[str, dict[str, int]] = field(default_factory=dict)


class StudyError(RunFailure):
    """A worker process of a run died (killed, out of memory); the message names the seed."""


# -- the UFastSLAM study (deploy.study.ufastslam) --------------------------------------------

# Every method of every run, in table order; results.json's semantic_ufastslam is one of them.
UFASTSLAM_METHODS = ("odometry", "ufastslam", "semantic_threshold", "semantic_oracle")
UFASTSLAM_LABELS = {
    "odometry": "dead reckoning",
    "ufastslam": "UFastSLAM",
    "semantic_threshold": "Semantic UFastSLAM (threshold)",
    "semantic_oracle": "Semantic UFastSLAM (oracle)",
}


@dataclass(frozen=True, slots=True)
class MethodRun:
    """One method on one run: the metrics (``pose_nees``: the median over steps, and
    ``nees_over_bound``: the share of steps above the χ²₃ bound of :data:`NEES_PROBABILITY`,
    filters only), the estimated path (steps + 1, 3), the final map (landmark ids, (L, 2)) and the
    relation groups it used (kind, name, member ids)."""

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
    """Every method of :data:`UFASTSLAM_METHODS` on the measurements of one seed; ``truth``
    (steps + 1, 3)."""

    seed: int
    truth: Array
    methods: dict[str, MethodRun]


def semantic_method(relations: str) -> str:
    """The method of :data:`UFASTSLAM_METHODS` that results.json calls ``semantic_ufastslam``."""
    return "ufastslam" if relations == "off" else f"semantic_{relations}"
