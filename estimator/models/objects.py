"""What an object is to the estimators: a pose (the paper's objects) or a point (range–bearing
landmarks, as in the UTIAS MRCLAM dataset), and how a detection measures it.

One interface for both, so that the belief, its slots, the wire and the agents do not fork:

- ``"pose"``: the object's state is a Pose2 (x, y, θ), tangent dimension 3; a detection's
  ``z_geo`` is the object's pose in the robot's body frame, ``x_k⁻¹ ∘ o_j`` (3,);
  ``BetweenFactorPose2``.
- ``"point"``: the object's state is a Point2 (x, y), tangent dimension 2; a detection's
  ``z_geo`` is (bearing, range) of the point from the robot, the bearing in the robot's body
  frame in (−π, π] — GTSAM's ``BearingRangeFactor2D`` order, so that its noise (σ²_bearing,
  σ²_range) is read in the same order everywhere.

The class model needs the viewpoint ψ at which the object is seen. A pose object has a heading;
a point has none, so its viewpoint is read in the world frame: a point is the pose (x, y, 0) to
the classifier model (ψ = the azimuth of the robot seen from the point, measured from the world's
x axis). A scenario of point objects states this convention (``viewpoint_frame = "world"``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.models import se2

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ObjectKind:
    """``name`` "pose" or "point"; ``dim`` the tangent dimension of one object (3 or 2), which is
    also the length of its state and of a detection's ``z_geo``."""

    name: str
    dim: int

    def place(self, robot: ArrayLike, z_geo: ArrayLike) -> Array:
        """The object that a detection ``z_geo`` (..., dim) from ``robot`` (..., 3) measures
        without noise: the inverse of :meth:`measure`. (..., dim)."""
        x, z = np.asarray(robot, dtype=float), np.asarray(z_geo, dtype=float)
        if self.name == "pose":
            return se2.compose(x, z)
        angle = x[..., 2] + z[..., 0]
        return np.stack(
            [x[..., 0] + z[..., 1] * np.cos(angle), x[..., 1] + z[..., 1] * np.sin(angle)], -1
        )

    def measure(self, robot: ArrayLike, obj: ArrayLike) -> Array:
        """The noise-free detection of ``obj`` (..., dim) from ``robot`` (..., 3): (..., dim)."""
        x, o = np.asarray(robot, dtype=float), np.asarray(obj, dtype=float)
        if self.name == "pose":
            return se2.between(x, o)
        dx, dy = o[..., 0] - x[..., 0], o[..., 1] - x[..., 1]
        bearing = se2.wrap_angle(np.arctan2(dy, dx) - x[..., 2])
        return np.stack([bearing, np.hypot(dx, dy)], -1)

    def as_pose(self, obj: ArrayLike) -> Array:
        """The pose the classifier model sees (..., 3): a pose object itself, a point with
        heading 0 (its viewpoint is read in the world frame)."""
        o = np.asarray(obj, dtype=float)
        if self.name == "pose":
            return o
        return np.concatenate([o[..., :2], np.zeros((*o.shape[:-1], 1))], axis=-1)

    def from_pose(self, pose: ArrayLike) -> Array:
        """An object of this kind at ``pose`` (..., 3): the pose, or its position."""
        p = np.asarray(pose, dtype=float)
        return p if self.name == "pose" else p[..., :2]


POSE = ObjectKind("pose", 3)
POINT = ObjectKind("point", 2)
OBJECT_KINDS = {k.name: k for k in (POSE, POINT)}


def object_kind(name: str) -> ObjectKind:
    """The kind called ``name``, else ValueError naming the known ones."""
    if name not in OBJECT_KINDS:
        raise ValueError(f"object kind {name!r} (known: {', '.join(OBJECT_KINDS)})")
    return OBJECT_KINDS[name]


def kind_of_dim(dim: int) -> ObjectKind:
    """The kind whose objects have tangent dimension ``dim`` (3 or 2), else ValueError."""
    for kind in (POSE, POINT):
        if kind.dim == dim:
            return kind
    raise ValueError(f"objects of dimension {dim} (known: 3, Pose2; 2, Point2)")
