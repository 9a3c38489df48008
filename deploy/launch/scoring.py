"""The scoring of a launch: the agents' estimates against ground truth, by the study's own
:class:`deploy.study.runner.Recorder`, so that a launch and a study are measured by the same code.

The study records beliefs it steps itself; a launch only has the snapshots its agents published,
so it hands those to a recorder per belief.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from deploy.study.runner import Recorder, true_objects
from estimator.hybrid import BeliefSnapshot
from estimator.models import SensorFrame
from sim.scenario import Scenario

BELIEFS = ("local", "distributed")


class Scorer:
    """Scores beliefs against ground truth: ``metrics[belief][metric]`` (robots, steps), with the
    recorder's tracks (``deploy.study.runner.TRACKS``, (robots, steps, 3): the estimated and the
    true robot pose), and the class-ECE bin statistics ``calibration[belief]`` (robots, steps, 3,
    ECE_BINS), for the beliefs of :data:`BELIEFS`; a step never recorded stays NaN (metrics,
    estimated pose) or zero (bins)."""

    def __init__(
        self,
        scenario: Scenario,
        frames: Mapping[str, Sequence[SensorFrame]],
        robots: Sequence[str],
    ) -> None:
        truth = true_objects(scenario)
        self.index = {r: i for i, r in enumerate(robots)}
        self.recorders = {b: Recorder(scenario, frames, truth, robots=robots) for b in BELIEFS}
        self.metrics = {b: rec.arrays for b, rec in self.recorders.items()}
        self.calibration = {b: rec.calibration for b, rec in self.recorders.items()}

    def record(self, belief: str, robot: str, k: int, snap: BeliefSnapshot) -> None:
        """Score ``robot``'s ``belief`` after step k (a belief not scored here is ignored)."""
        if belief in self.recorders:
            self.recorders[belief].score(self.index[robot], robot, k, snap)
