"""The study's value types, at the bottom of ``deploy.study``: what a run returns
(:class:`RunResult`) and how a run fails (:class:`StudyError`). The runner fills them; the
archive, report, plots, shards and cluster read them, and import no runner for it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from deploy.base.errors import RunFailure
from estimator.hybrid import BeliefSnapshot

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
    (empty: not recorded)."""

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


class StudyError(RunFailure):
    """A worker process of a run died (killed, out of memory); the message names the seed."""
