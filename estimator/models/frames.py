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

# What a frame's detection ids are (``SensorFrame.ids``): the fleet's global object ids (data
# association given, the paper's setting and the default), a robot-local tracker's ids (its own
# numbering, never comparable with another robot's or with the map's), or none at all. A frame of
# local or no ids goes through data association (``estimator.association``) before a belief
# steps on it.
GLOBAL_IDS, LOCAL_IDS, NO_IDS = "global", "local", "none"
ID_KINDS = (GLOBAL_IDS, LOCAL_IDS, NO_IDS)
# ``Detection.object_id`` of every detection of a frame without ids (``ids = "none"``): the codecs
# refuse any other, so that no id (a simulator's truth, say) travels in such a frame.
NO_ID = -1


def check_id_kind(ids: object) -> str:
    """``ids`` if it is one of :data:`ID_KINDS`, else ValueError naming them."""
    if not isinstance(ids, str) or ids not in ID_KINDS:
        raise ValueError(f"id kind {ids!r} (known: {', '.join(ID_KINDS)})")
    return ids


@dataclass(frozen=True, slots=True, eq=False)
class Detection:
    """One object seen at step k.

    ``z_geo`` (3,): the object's pose in the robot's body frame, ``x_k⁻¹ ∘ o_j`` plus noise.
    ``z_sem`` (M,): the classifier's score vector. ``object_id``: what the frame's ``ids`` say it
    is (a global object id, a robot-local tracker id, or :data:`NO_ID`).
    """

    object_id: int
    z_geo: Array
    z_sem: Array


@dataclass(frozen=True, slots=True, eq=False)
class SensorFrame:
    """Robot ``robot``'s data at step ``k`` ≥ 1.

    ``odometry`` (3,): measured ``x_{k−1}⁻¹ ∘ x_k``. ``detections``: objects seen from ``x_k``.
    ``true_pose`` (3,): ground truth ``x_k``, for metrics and link models only — never for
    estimation. ``ids``: what the detections' ``object_id`` are (:data:`ID_KINDS`; global object
    ids by default).
    """

    robot: str
    k: int
    odometry: Array
    detections: tuple[Detection, ...]
    true_pose: Array
    ids: str = GLOBAL_IDS
