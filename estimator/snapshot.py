"""A belief as plain arrays (for metrics, plots and the estimate wire codec).

Kept apart from ``estimator.hybrid`` so that what only reads beliefs (``protocol.estimate``)
never imports GTSAM.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class BeliefSnapshot:
    """A belief as plain arrays, for metrics and plots.

    ``object_ids`` (n,); ``weights`` (H,) normalised; ``classes`` (H, n); ``robot_pose`` (H, 3) and
    ``robot_cov`` (H, 3, 3) of the robot's latest pose (body-frame tangent covariance);
    ``object_pose`` (H, n, 3) and ``object_cov`` (H, n, 3, 3).
    """

    object_ids: tuple[int, ...]
    weights: Array
    classes: IntArray
    robot_pose: Array
    robot_cov: Array
    object_pose: Array
    object_cov: Array
