"""The scenario data model: frozen dataclasses built by :mod:`sim.loader` from TOML files."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimator.models import AliasedClassifier, ClassifierModel, GaussianNoise, paper_classifier
from estimator.models.classifier import OBJECT_TO_CAMERA
from sim.learned_file import LearnedFileError, load_learned

Array = NDArray[np.float64]

FORMAT_VERSION = 1


class ScenarioError(ValueError):
    """A scenario file or override is invalid. The message names the file, the field and why;
    ``field`` (dotted path, or None) and ``reason`` are kept for callers that rephrase it."""

    def __init__(self, message: str, field: str | None = None, reason: str = "") -> None:
        super().__init__(message)
        self.field = field
        self.reason = reason or message


@dataclass(frozen=True, slots=True)
class Variant:
    """A named set of field overrides defined in the file, e.g. ``sense10``."""

    name: str
    description: str
    settings: tuple[tuple[str, Any], ...]


@dataclass(frozen=True, slots=True)
class Sensor:
    """Camera-like sensor: objects within ``range`` metres and ``|bearing| ≤ half_angle`` rad.
    ``objects``: what it measures (``estimator.models.objects``): ``"pose"`` objects by their
    relative pose (the paper's), ``"point"`` landmarks by bearing and range."""

    half_angle: float
    range: float
    objects: str = "pose"


@dataclass(frozen=True, slots=True)
class RecordingRef:
    """A scenario's ``[recording]`` (``sim.recording``): ``file`` as the scenario writes it
    (relative to its folder, or absolute), ``path`` resolved, and the file's ``sha256``."""

    file: str
    path: str
    sha256: str


@dataclass(frozen=True, slots=True)
class Robot:
    """A robot: ``start`` pose (3,) and per-step body-frame actions ``actions`` (steps, 3);
    ``x_k = x_{k−1} ∘ actions[k−1]``."""

    id: str
    start: tuple[float, float, float]
    actions: tuple[tuple[float, float, float], ...]
    sensor: Sensor


@dataclass(frozen=True, slots=True)
class Object:
    """A static object with pose (x, y, yaw) and its true class index 0..M−1."""

    id: int
    pose: tuple[float, float, float]
    class_index: int


@dataclass(frozen=True, slots=True)
class ScheduleEdge:
    """Robots ``a`` and ``b`` may exchange stacks at every step k with ``first ≤ k ≤ last``."""

    first: int
    last: int
    a: str
    b: str


@dataclass(frozen=True, slots=True)
class Communication:
    """Who may talk to whom. ``mode``: ``schedule`` (the table), ``range`` (true positions at step k
    within ``range`` metres) or ``both`` (an edge must satisfy the two)."""

    mode: str
    range: float | None
    schedule: tuple[ScheduleEdge, ...]


@dataclass(frozen=True, slots=True)
class ClassifierSpec:
    """Which classifier model generates (and by default explains) the semantic scores.

    ``model = "learned"``: ``file`` is the model file's absolute path and ``digest`` the SHA-256
    of the bytes the loader validated; :meth:`build` refuses a file replaced since."""

    model: str
    alias: tuple[int, ...] = ()
    best_view_deg: tuple[float, ...] = ()
    noise_std: float = 0.0
    file: str = ""
    digest: str = ""
    viewpoint: str = OBJECT_TO_CAMERA

    def build(self) -> ClassifierModel:
        if self.model == "paper":
            return paper_classifier(self.viewpoint)
        if self.model == "learned":
            try:
                return load_learned(self.file, self.digest)[0]
            except LearnedFileError as exc:
                raise ScenarioError(str(exc), "classifier.file") from None
        m = len(self.alias)
        best = tuple(math.radians(b) for b in self.best_view_deg)
        return AliasedClassifier(self.alias, best, np.eye(m) / self.noise_std, self.viewpoint)


@dataclass(frozen=True, slots=True)
class RobotModel:
    """What a robot knows of itself and of the objects it may meet, without any world: the
    classes and their prior, the classifier model, the odometry and geometric noise and the
    sensor (a scenario's ``[classes]``, ``[classifier]``, ``[noise]`` and ``[sensor]``)."""

    num_classes: int
    class_prior: tuple[float, ...]
    classifier: ClassifierSpec
    odometry_noise: GaussianNoise
    geometric_noise: GaussianNoise
    sensor: Sensor


@dataclass(frozen=True, slots=True)
class Scenario:
    """A validated scenario (see docs/scenarios.md). Steps are k = 1..steps. ``sensor`` is the
    default sensor (``[sensor]``); each robot carries the one it uses."""

    name: str
    description: str
    source: str
    steps: int
    num_classes: int
    class_prior: tuple[float, ...]
    robots: tuple[Robot, ...]
    objects: tuple[Object, ...]
    odometry_noise: GaussianNoise
    geometric_noise: GaussianNoise
    classifier: ClassifierSpec
    sensor: Sensor
    communication: Communication
    variants: tuple[Variant, ...] = ()
    applied_variants: tuple[str, ...] = ()
    # [classifier.estimator]: the robots' model when it is not the one generating the scores.
    estimator_classifier: ClassifierSpec | None = None
    # [recording]: frames recorded by real robots (sim.recording) instead of simulated ones
    recording: RecordingRef | None = None
    # ``class_seed``: the objects' classes are drawn per run (:meth:`for_run`); ``objects``
    # then hold run seed 0's draw. None: the classes are the file's, the same in every run.
    class_seed: int | None = None

    def for_run(self, seed: int) -> Scenario:
        """The world of the run with ``seed``: with a ``class_seed``, every object's class drawn
        from the class prior for this run (:func:`draw_classes`), so that a study's seeds vary
        the class assignment as well as the scores; without one, this scenario itself. The
        world returned holds its classes fixed (a second call changes nothing)."""
        if self.class_seed is None:
            return self
        drawn = draw_classes(self.class_prior, len(self.objects), self.class_seed, seed)
        objects = tuple(
            dataclasses.replace(o, class_index=int(c))
            for o, c in zip(self.objects, drawn, strict=True)
        )
        return dataclasses.replace(self, objects=objects, class_seed=None)

    @property
    def robot_ids(self) -> tuple[str, ...]:
        return tuple(r.id for r in self.robots)

    @property
    def object_ids(self) -> tuple[int, ...]:
        return tuple(o.id for o in self.objects)

    def robot(self, robot_id: str) -> Robot:
        for r in self.robots:
            if r.id == robot_id:
                return r
        raise KeyError(robot_id)

    def robot_model(self, robot_id: str | None = None) -> RobotModel:
        """The robot model of this world's robots: the one of ``robot_id`` (with its own sensor),
        or with the default ``[sensor]`` when None. Its classifier is ``[classifier.estimator]``
        when the scenario has one, else the generating ``[classifier]``."""
        sensor = self.sensor if robot_id is None else self.robot(robot_id).sensor
        return RobotModel(
            self.num_classes,
            self.class_prior,
            self.estimator_classifier or self.classifier,
            self.odometry_noise,
            self.geometric_noise,
            sensor,
        )

    def object_poses(self) -> Array:
        """(n, 3) object poses in file order."""
        return np.array([o.pose for o in self.objects], dtype=float).reshape(-1, 3)

    def object_classes(self) -> NDArray[np.int64]:
        """(n,) true class indices 0..M−1 in file order."""
        return np.array([o.class_index for o in self.objects], dtype=np.int64)


CLASS_STREAM = 0xC1A55  # keeps the class draw apart from every other stream of a run's seed


def draw_classes(
    prior: Sequence[float], n: int, class_seed: int, run_seed: int
) -> NDArray[np.int64]:
    """(n,) class indices 0..M−1 drawn independently from ``prior`` for the run with
    ``run_seed`` of a world with ``class_seed`` (``Scenario.for_run``)."""
    rng = np.random.default_rng(np.random.SeedSequence([class_seed, run_seed, CLASS_STREAM]))
    return rng.choice(len(prior), size=n, p=np.asarray(prior, dtype=float)).astype(np.int64)
