"""The worlds of the Semantic UFastSLAM experiments: a unicycle robot driving a path of legs
through point landmarks, with ground-truth relation groups (docs/ufastslam.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from estimator.models.se2 import transform_to, wrap_angle

Array = NDArray[np.float64]

GROUP_KINDS = ("x", "y", "col")
# Ground-truth groups must hold to this many metres.
GROUP_TOLERANCE = 1e-3
_STRAIGHT = 1e-9


@dataclass(frozen=True, slots=True)
class Leg:
    """Drive ``forward`` metres while turning ``turn`` radians, both spread evenly over the leg
    (forward = 0: turn on the spot; turn = 0: straight)."""

    forward: float
    turn: float


@dataclass(frozen=True, slots=True)
class Odometry:
    """The odometry's errors: measured v = (1 + scale_error)·v + σ_v·ε, measured
    ω = ω + yaw_rate_bias + σ_ω·ε (SI units: m/s, rad/s)."""

    speed_std: float
    yaw_rate_std: float
    scale_error: float
    yaw_rate_bias: float


@dataclass(frozen=True, slots=True)
class Camera:
    """A range-bearing sensor: sees a landmark within ``range`` m and ``half_angle`` rad of the
    heading (both inclusive); noise σ_r = ``range_std`` m, σ_b = ``bearing_std`` rad."""

    half_angle: float
    range: float
    range_std: float
    bearing_std: float


@dataclass(frozen=True, slots=True)
class FilterNoise:
    """What the estimator assumes: control noise (m/s, rad/s) and the relation tolerance σ_s (m)."""

    speed_std: float
    yaw_rate_std: float
    relation_std: float


@dataclass(frozen=True, slots=True)
class RelationGroup:
    """A ground-truth relation: ``members`` (landmark ids) share x, share y, or are collinear."""

    kind: str
    name: str
    members: tuple[int, ...]

    @property
    def label(self) -> str:
        return f"{self.kind}:{self.name}"


@dataclass(frozen=True)
class UWorld:
    """A validated world. Steps are k = 1..steps; the controls of step k move x_{k−1} to x_k."""

    name: str
    description: str
    source: str
    dt: float
    start: tuple[float, float, float]
    speed: float
    turn_rate: float
    legs: tuple[Leg, ...]
    landmark_ids: tuple[int, ...]
    landmark_xy: tuple[tuple[float, float], ...]
    groups: tuple[RelationGroup, ...]
    odometry: Odometry
    camera: Camera
    filter_noise: FilterNoise

    @cached_property
    def landmarks(self) -> Array:
        """(L, 2) true landmark positions, in ``landmark_ids`` order."""
        return np.asarray(self.landmark_xy, dtype=float).reshape(-1, 2)

    @cached_property
    def controls(self) -> Array:
        """(steps, 2) true (v, ω) of every step: each leg lasts the whole number of steps that
        keeps |v| ≤ speed and |ω| ≤ turn_rate, at constant v and ω."""
        out = []
        for leg in self.legs:
            duration = max(abs(leg.forward) / self.speed, abs(leg.turn) / self.turn_rate)
            n = max(1, math.ceil(duration / self.dt - 1e-9))
            out += [(leg.forward / (n * self.dt), leg.turn / (n * self.dt))] * n
        return np.asarray(out, dtype=float)

    @property
    def steps(self) -> int:
        return len(self.controls)

    @cached_property
    def trajectory(self) -> Array:
        """(steps + 1, 3) true poses, row k = x_k, integrated exactly along constant-(v, ω) arcs."""
        poses = np.empty((self.steps + 1, 3))
        poses[0] = self.start
        for k, (v, w) in enumerate(self.controls):
            poses[k + 1] = arc(poses[k], v, w, self.dt)
        return poses

    @cached_property
    def labels(self) -> dict[int, tuple[str, ...]]:
        """Landmark id → the labels ``KIND:NAME`` of the ground-truth groups it belongs to."""
        out: dict[int, list[str]] = {i: [] for i in self.landmark_ids}
        for g in self.groups:
            for m in g.members:
                out[m].append(g.label)
        return {i: tuple(v) for i, v in out.items()}

    def visible(self, k: int) -> tuple[NDArray[np.intp], Array]:
        """Landmarks seen from x_k: indices (n,) into ``landmark_ids`` and true (r, b) (n, 2)."""
        pose = self.trajectory[k]
        rel = transform_to(pose, self.landmarks)
        r = np.hypot(rel[:, 0], rel[:, 1])
        b = np.arctan2(rel[:, 1], rel[:, 0])
        seen = np.flatnonzero((r <= self.camera.range) & (np.abs(b) <= self.camera.half_angle))
        return seen, np.column_stack([r[seen], b[seen]])


def arc(pose: Array, v: float, w: float, dt: float) -> Array:
    """The exact unicycle motion over dt at constant (v, ω), from pose (3,)."""
    x, y, t = pose
    if abs(w) < _STRAIGHT:
        return np.array([x + v * dt * math.cos(t), y + v * dt * math.sin(t), t])
    t1 = t + w * dt
    rho = v / w
    return np.array(
        [
            x + rho * (math.sin(t1) - math.sin(t)),
            y + rho * (math.cos(t) - math.cos(t1)),
            float(wrap_angle(t1)),
        ]
    )


def group_residuals(kind: str, points: Array) -> Array:
    """How far each member (n, 2) is from the group's fact: x or y offset from the first member;
    for col, the distance from the line through the two most separated members."""
    if kind == "x":
        return np.asarray(points[:, 0] - points[0, 0])
    if kind == "y":
        return np.asarray(points[:, 1] - points[0, 1])
    dist = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    a, b = points[i], points[j]
    base = b - a
    rel = points - a
    return np.asarray((base[0] * rel[:, 1] - base[1] * rel[:, 0]) / np.hypot(*base))
