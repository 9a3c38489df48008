"""The scoring of a launch: the agents' estimates against ground truth, into the metrics of
``semfleet study`` (``estimator.metrics``), so that a launch and a study are read the same way.

The study records beliefs it steps itself (``deploy.study``); a launch only has the snapshots its
agents published, so it scores those here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from estimator.hybrid import BeliefSnapshot
from estimator.metrics import ECE_BINS, METRICS, evaluate, evaluate_calibration
from estimator.models import SensorFrame
from sim.scenario import Scenario

BELIEFS = ("local", "distributed")


class Scorer:
    """Scores beliefs against ground truth: ``metrics[belief][metric]`` (robots, steps) and the
    class-ECE bin statistics ``calibration[belief]`` (robots, steps, 3, ECE_BINS), for the beliefs
    of :data:`BELIEFS`; a step never recorded stays NaN (metrics) or zero (bins)."""

    def __init__(
        self,
        scenario: Scenario,
        frames: Mapping[str, Sequence[SensorFrame]],
        robots: Sequence[str],
    ) -> None:
        self.num_classes = scenario.num_classes
        self.frames = frames
        self.truth = {o.id: (np.array(o.pose), o.class_index) for o in scenario.objects}
        self.index = {r: i for i, r in enumerate(robots)}
        shape = (len(robots), scenario.steps)
        self.metrics = {b: {m: np.full(shape, np.nan) for m in METRICS} for b in BELIEFS}
        self.calibration = {b: np.zeros((*shape, 3, ECE_BINS)) for b in BELIEFS}

    def record(self, belief: str, robot: str, k: int, snap: BeliefSnapshot) -> None:
        """Score ``robot``'s ``belief`` after step k (a belief not scored here is ignored)."""
        if belief not in self.metrics:
            return
        i = self.index[robot]
        true_pose = self.frames[robot][k - 1].true_pose
        for name, value in evaluate(snap, self.num_classes, true_pose, self.truth).items():
            self.metrics[belief][name][i, k - 1] = value
        stats = evaluate_calibration(snap, self.num_classes, self.truth)
        self.calibration[belief][i, k - 1] = stats
