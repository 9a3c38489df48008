"""What a robot's sensors deliver at one step: the estimators' input."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# The one definition of what a robot id and a step may be, for every layer (wire, files, keys).
ROBOT_ID = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
ROBOT_ID_RULE = "1–32 of A–Z a–z 0–9 _ -"  # (they become Zenoh key segments)
MAX_STEP = 9_999_999  # a belief packs the step into 7 decimal digits of a pose key


@dataclass(frozen=True, slots=True, eq=False)
class Detection:
    """One object seen at step k (data association given).

    ``z_geo`` (3,): the object's pose in the robot's body frame, ``x_k⁻¹ ∘ o_j`` plus noise.
    ``z_sem`` (M,): the classifier's score vector.
    """

    object_id: int
    z_geo: Array
    z_sem: Array


@dataclass(frozen=True, slots=True, eq=False)
class SensorFrame:
    """Robot ``robot``'s data at step ``k`` ≥ 1.

    ``odometry`` (3,): measured ``x_{k−1}⁻¹ ∘ x_k``. ``detections``: objects seen from ``x_k``.
    ``true_pose`` (3,): ground truth ``x_k``, for metrics and link models only — never for
    estimation.
    """

    robot: str
    k: int
    odometry: Array
    detections: tuple[Detection, ...]
    true_pose: Array
