"""Sensor simulation with common random numbers.

Every noise draw is a pure function of (seed, stream, robot, step, object): each (robot, step,
object) triple owns its own ``numpy`` generator seeded from a ``SeedSequence`` of those numbers. A
frame is therefore identical whatever order frames are generated in, and every method of a Monte
Carlo run sees the very same measurements.
"""

from __future__ import annotations

import zlib
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from estimator.models import ClassifierModel, Detection, SensorFrame, se2, viewpoint
from estimator.models.objects import object_kind
from sim.recording import Recording
from sim.scenario import Scenario
from sim.world import World

Array = NDArray[np.float64]

# Stream tags keep the odometry, geometric and semantic draws of one (robot, step) independent.
_ODOMETRY, _GEOMETRIC, _SEMANTIC = 1, 2, 3
_MAX_SEED = 2**63 - 1


def robot_key(robot_id: str) -> int:
    """A stable integer for a robot id, so adding robots never changes another robot's noise."""
    return zlib.crc32(robot_id.encode("utf-8"))


def standard_normals(seed: int, stream: int, robot: str, k: int, obj: int, size: int) -> Array:
    """``size`` standard normal draws owned by (seed, stream, robot, step k, object id)."""
    seq = np.random.SeedSequence([seed, stream, robot_key(robot), k, obj])
    return np.random.default_rng(seq).standard_normal(size)


def check_seed(seed: int) -> int:
    """Seeds are integers in [0, 2⁶³): reject anything else with a clear error."""
    if (
        isinstance(seed, bool)
        or not isinstance(seed, int | np.integer)
        or not 0 <= seed <= _MAX_SEED
    ):
        raise ValueError(f"seed must be an integer in [0, 2**63), got {seed!r}")
    return int(seed)


class Simulator:
    """Produces every robot's :class:`SensorFrame` for steps k = 1..steps of one seeded run."""

    def __init__(
        self, scenario: Scenario, seed: int, classifier: ClassifierModel | None = None
    ) -> None:
        # The world of this run: its own classes when the scenario draws them per run.
        self.seed = check_seed(seed)
        self.scenario = scenario = scenario.for_run(self.seed)
        self.world = World(scenario)
        self.classifier = classifier if classifier is not None else scenario.classifier.build()
        self.kind = object_kind(scenario.sensor.objects)

    @cached_property
    def _object_index(self) -> dict[int, int]:
        return {oid: j for j, oid in enumerate(self.scenario.object_ids)}

    def frame(self, robot: str, k: int) -> SensorFrame:
        """The frame of ``robot`` at step ``k`` (1 ≤ k ≤ steps)."""
        if not 1 <= k <= self.scenario.steps:
            raise ValueError(f"step {k} out of range 1..{self.scenario.steps}")
        traj = self.world.trajectories[robot]
        x_prev, x_k = traj[k - 1], traj[k]
        rec = self.world.recording
        if rec is not None:
            return self._recorded(rec, robot, k, x_k)
        odo_noise = standard_normals(self.seed, _ODOMETRY, robot, k, 0, 3)
        odometry = self.scenario.odometry_noise.corrupt(se2.between(x_prev, x_k), odo_noise)
        detections = tuple(
            self._detect(robot, k, x_k, oid) for oid in self.world.visible_objects(robot, k)
        )
        return SensorFrame(robot, k, odometry, detections, x_k.copy())

    def _recorded(self, rec: Recording, robot: str, k: int, x_k: Array) -> SensorFrame:
        """A recorded run's frame (``sim.recording``): its odometry and detections as the robot
        measured them; only the class scores are drawn, seeded as a simulated frame's, from the
        classifier model at the true viewpoint."""
        i = rec.robots.index(robot)
        ids, zs = rec.detections(i, k)
        detections = tuple(
            Detection(int(oid), z.copy(), self._scores(robot, k, x_k, int(oid)))
            for oid, z in zip(ids.tolist(), zs, strict=True)
        )
        return SensorFrame(robot, k, rec.odometry[i, k - 1].copy(), detections, x_k.copy())

    def _scores(self, robot: str, k: int, x_k: Array, oid: int) -> Array:
        j = self._object_index[oid]
        obj = self.kind.from_pose(self.world.object_poses[j])
        c = self.scenario.objects[j].class_index
        psi = viewpoint(x_k, self.kind.as_pose(obj))
        sem_noise = standard_normals(self.seed, _SEMANTIC, robot, k, oid, self.classifier.dim)
        chol = np.linalg.cholesky(self.classifier.cov(c, psi))
        return np.asarray(self.classifier.mean(c, psi) + chol @ sem_noise)

    def _detect(self, robot: str, k: int, x_k: Array, oid: int) -> Detection:
        j = self._object_index[oid]
        # a point object is its position; the classifier sees it at heading 0 (world frame)
        obj = self.kind.from_pose(self.world.object_poses[j])
        geo_noise = standard_normals(self.seed, _GEOMETRIC, robot, k, oid, self.kind.dim)
        z_geo = self.scenario.geometric_noise.corrupt(self.kind.measure(x_k, obj), geo_noise)
        return Detection(oid, z_geo, self._scores(robot, k, x_k, oid))

    def frames(self, robot: str) -> list[SensorFrame]:
        """All frames of one robot, k = 1..steps."""
        return [self.frame(robot, k) for k in range(1, self.scenario.steps + 1)]

    def all_frames(self) -> dict[str, list[SensorFrame]]:
        """Robot id → its frames, k = 1..steps."""
        return {rid: self.frames(rid) for rid in self.scenario.robot_ids}
