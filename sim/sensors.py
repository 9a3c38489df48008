"""Sensor simulation with common random numbers.

Every noise draw is a pure function of (seed, stream, robot, step, object): each (robot, step,
object) triple owns its own ``numpy`` generator seeded from a ``SeedSequence`` of those numbers. A
frame is therefore identical whatever order frames are generated in, and every method of a Monte
Carlo run sees the very same measurements.

A :class:`Detector` makes the frames a real detector would give (data association issue):
without global ids (``ids = "none"``, or a robot-local tracker's ``"local"`` ids), with clutter
(false detections: per frame Poisson with mean ``clutter`` × the true detections, uniform in the
sensor's field, scores of a random class at a random viewpoint or of no class) and misses (each
true detection lost with probability ``miss``, independently), from streams of their own so that
the true detections keep their noise. The default detector (global ids, no clutter, no misses)
draws nothing more: its frames are those of before, to the bit. What each detection truly is (an
object id or :data:`CLUTTER`) is returned beside the frame (:meth:`Simulator.labelled_frame`),
for scoring only: it never enters a frame. ``confirmable`` keeps, of a given-id detector's frames,
only the detections a robot's association could confirm (``sim.confirmable``): the reference
that tells the association's mistakes from what confirmation gives up.

Over 300 lines for a reason: every draw of a frame (noise, misses, clutter, order, ids) is keyed
by the same (seed, stream, robot, step, object) scheme, which one class keeps in one place.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from estimator.models import (
    GLOBAL_IDS,
    LOCAL_IDS,
    NO_ID,
    NO_IDS,
    ClassifierModel,
    Detection,
    SensorFrame,
    check_id_kind,
    se2,
    viewpoint,
)
from estimator.models.objects import object_kind
from sim.confirmable import CLUTTER, ConfirmRule, confirmable
from sim.recording import Recording
from sim.scenario import Scenario
from sim.world import World

Array = NDArray[np.float64]

# Stream tags keep the odometry, geometric and semantic draws of one (robot, step) independent,
# and the detector's misses, clutter, detection order and tracker ids apart from all three.
_ODOMETRY, _GEOMETRIC, _SEMANTIC = 1, 2, 3
_MISS, _CLUTTER, _ORDER, _TRACKER = 4, 5, 6, 7
_MAX_SEED = 2**63 - 1
# Ids of false detections in a frame of global or tracker ids: above every object id a scenario
# uses (below 2³¹) and unique per (step, detection), so that each is an object of its own.
_CLUTTER_ID_BASE = 2**31
_CLUTTER_PER_FRAME = 64  # at most this many false detections in one frame
_TRACKER_PRIME = 4_294_967_291  # the largest prime below 2³²: tracker ids stay on the wire


@dataclass(frozen=True, slots=True)
class Detector:
    """What the simulated detector delivers beyond the true detections' noise: the frames' id
    kind (``estimator.models.ID_KINDS``), clutter (false detections per true detection, the mean
    of a per-frame Poisson count) and ``miss`` (the probability that a true detection is lost).
    ``confirmable``: with global ids, only the detections of objects their robot's association
    would confirm under this rule (``sim.confirmable``); None: all."""

    ids: str = GLOBAL_IDS
    clutter: float = 0.0
    miss: float = 0.0
    confirmable: ConfirmRule | None = None

    def __post_init__(self) -> None:
        check_id_kind(self.ids)
        if self.confirmable is not None and self.ids != GLOBAL_IDS:
            raise ValueError(
                f"confirmable needs global ids, got ids {self.ids!r} (without them the robot's "
                "association confirms objects itself)"
            )
        if not (math.isfinite(self.clutter) and 0.0 <= self.clutter <= 1.0):
            raise ValueError(
                f"clutter must be in [0, 1] false detections per true one, got {self.clutter}"
            )
        if not (math.isfinite(self.miss) and 0.0 <= self.miss < 1.0):
            raise ValueError(f"miss must be a probability in [0, 1), got {self.miss}")

    @property
    def exact(self) -> bool:
        """Whether the frames are the given-id frames of before (nothing more is drawn)."""
        return (
            self.ids == GLOBAL_IDS
            and self.clutter == 0.0
            and self.miss == 0.0
            and self.confirmable is None
        )


def robot_key(robot_id: str) -> int:
    """A stable integer for a robot id, so adding robots never changes another robot's noise."""
    return zlib.crc32(robot_id.encode("utf-8"))


def standard_normals(seed: int, stream: int, robot: str, k: int, obj: int, size: int) -> Array:
    """``size`` standard normal draws owned by (seed, stream, robot, step k, object id)."""
    seq = np.random.SeedSequence([seed, stream, robot_key(robot), k, obj])
    return np.random.default_rng(seq).standard_normal(size)


def _uniform(seed: int, stream: int, robot: str, k: int, obj: int) -> float:
    """One uniform draw in [0, 1) owned by (seed, stream, robot, step k, object id)."""
    seq = np.random.SeedSequence([seed, stream, robot_key(robot), k, obj])
    return float(np.random.default_rng(seq).uniform())


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
        self,
        scenario: Scenario,
        seed: int,
        classifier: ClassifierModel | None = None,
        detector: Detector | None = None,
    ) -> None:
        # The world of this run: its own classes when the scenario draws them per run.
        self.seed = check_seed(seed)
        self.scenario = scenario = scenario.for_run(self.seed)
        self.world = World(scenario)
        self.classifier = classifier if classifier is not None else scenario.classifier.build()
        self.kind = object_kind(scenario.sensor.objects)
        self.detector = detector or Detector()
        self._kept: dict[str, list[tuple[bool, ...]]] = {}  # robot → confirmable detections

    @cached_property
    def _object_index(self) -> dict[int, int]:
        return {oid: j for j, oid in enumerate(self.scenario.object_ids)}

    def frame(self, robot: str, k: int) -> SensorFrame:
        """The frame of ``robot`` at step ``k`` (1 ≤ k ≤ steps)."""
        return self.labelled_frame(robot, k)[0]

    def labelled_frame(self, robot: str, k: int) -> tuple[SensorFrame, tuple[int, ...]]:
        """The frame of ``robot`` at step ``k`` and, in the order of its detections, what each
        truly is: an object id or :data:`CLUTTER` (for scoring an association only)."""
        if not 1 <= k <= self.scenario.steps:
            raise ValueError(f"step {k} out of range 1..{self.scenario.steps}")
        frame, labels = self._delivered(robot, k)
        rule = self.detector.confirmable
        if rule is None:
            return frame, labels
        if robot not in self._kept:
            steps = range(1, self.scenario.steps + 1)
            every = [self._delivered(robot, s)[1] for s in steps]
            seen = [set(self.world.visible_objects(robot, s)) for s in steps]
            self._kept[robot] = confirmable(every, seen, rule)
        keep = self._kept[robot][k - 1]
        kept = [(d, lab) for d, lab, ok in zip(frame.detections, labels, keep, strict=True) if ok]
        detections = tuple(d for d, _ in kept)
        return dataclasses.replace(frame, detections=detections), tuple(lab for _, lab in kept)

    def _delivered(self, robot: str, k: int) -> tuple[SensorFrame, tuple[int, ...]]:
        """The frame of ``robot`` at step ``k`` as the detector delivers it, before
        ``confirmable``; with its labels."""
        traj = self.world.trajectories[robot]
        x_prev, x_k = traj[k - 1], traj[k]
        rec = self.world.recording
        if rec is not None:
            frame = self._recorded(rec, robot, k, x_k)
        else:
            odo_noise = standard_normals(self.seed, _ODOMETRY, robot, k, 0, 3)
            odometry = self.scenario.odometry_noise.corrupt(se2.between(x_prev, x_k), odo_noise)
            detections = tuple(
                self._detect(robot, k, x_k, oid) for oid in self.world.visible_objects(robot, k)
            )
            frame = SensorFrame(robot, k, odometry, detections, x_k.copy())
        labels = tuple(d.object_id for d in frame.detections)
        if self.detector.exact:
            return frame, labels
        return self._detected(frame, labels)

    def _detected(
        self, frame: SensorFrame, labels: tuple[int, ...]
    ) -> tuple[SensorFrame, tuple[int, ...]]:
        """``frame`` as :attr:`detector` delivers it: misses, clutter, a shuffled order (a
        detector's order says nothing about what it saw) and the id kind; with the labels."""
        det, robot, k = self.detector, frame.robot, frame.k
        kept = [
            (d, label)
            for d, label in zip(frame.detections, labels, strict=True)
            if det.miss == 0.0 or _uniform(self.seed, _MISS, robot, k, label) >= det.miss
        ]
        rng = np.random.default_rng(
            np.random.SeedSequence([self.seed, _CLUTTER, robot_key(robot), k])
        )
        count = min(int(rng.poisson(det.clutter * len(kept))) if kept else 0, _CLUTTER_PER_FRAME)
        # unique per robot and step whatever the other robots (rare collisions across robots)
        slot = robot_key(robot) * 1_000_003 + k
        for i in range(count):
            fake = self._clutter(robot, rng)
            clutter_id = _CLUTTER_ID_BASE + (slot * _CLUTTER_PER_FRAME + i) % _CLUTTER_ID_BASE
            kept.append((Detection(clutter_id, fake.z_geo, fake.z_sem), CLUTTER))
        if det.ids != GLOBAL_IDS:
            order = np.random.default_rng(
                np.random.SeedSequence([self.seed, _ORDER, robot_key(robot), k])
            ).permutation(len(kept))
            kept = [kept[i] for i in order]
        detections = tuple(
            Detection(self._id_of(robot, d.object_id), d.z_geo, d.z_sem) for d, _ in kept
        )
        out = SensorFrame(robot, k, frame.odometry, detections, frame.true_pose, det.ids)
        return out, tuple(label for _, label in kept)

    def _id_of(self, robot: str, oid: int) -> int:
        """What the detector calls object (or false detection) ``oid``."""
        if self.detector.ids == NO_IDS:
            return NO_ID
        if self.detector.ids == LOCAL_IDS:
            a, b = self._tracker(robot)
            return (a * oid + b) % _TRACKER_PRIME
        return oid

    def _tracker(self, robot: str) -> tuple[int, int]:
        """A robot-local tracker's numbering, ``id = (a · key + b) mod p``: a bijection of the
        keys (object ids, and clutter's above 2³¹) onto [0, p), its own per robot, under which a
        false detection's id looks like any object's."""
        seq = np.random.SeedSequence([self.seed, _TRACKER, robot_key(robot)])
        a, b = np.random.default_rng(seq).integers(1, _TRACKER_PRIME, size=2).tolist()
        return int(a), int(b)

    def _clutter(self, robot: str, rng: np.random.Generator) -> Detection:
        """A false detection uniform in ``robot``'s sensor field (area-uniform range, uniform
        bearing and heading), with the scores of a random class at a random viewpoint or, half
        the time, of no class: a uniform point of the simplex plus the classifier's noise."""
        sensor = self.scenario.robot(robot).sensor
        r = sensor.range * math.sqrt(rng.uniform())
        bearing = rng.uniform(-sensor.half_angle, sensor.half_angle)
        heading = rng.uniform(-math.pi, math.pi)
        if self.kind.dim == 3:
            z_geo = np.array([r * math.cos(bearing), r * math.sin(bearing), heading])
        else:
            z_geo = np.array([bearing, r])
        psi = rng.uniform(-math.pi, math.pi)
        c = int(rng.integers(self.classifier.num_classes))
        noise = np.linalg.cholesky(self.classifier.cov(c, psi)) @ rng.standard_normal(
            self.classifier.dim
        )
        if rng.uniform() < 0.5:
            mean = self.classifier.mean(c, psi)
        else:
            mean = rng.dirichlet(np.ones(self.classifier.dim))
        return Detection(NO_ID, z_geo, np.asarray(mean + noise))

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

    def labels(self, robot: str) -> list[tuple[int, ...]]:
        """What every detection of ``robot``'s frames k = 1..steps truly is (an object id or
        :data:`CLUTTER`), in the order of the frames' detections: for scoring only."""
        return [self.labelled_frame(robot, k)[1] for k in range(1, self.scenario.steps + 1)]

    def all_frames(self) -> dict[str, list[SensorFrame]]:
        """Robot id → its frames, k = 1..steps."""
        return {rid: self.frames(rid) for rid in self.scenario.robot_ids}
