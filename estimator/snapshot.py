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

    ``class_probs`` (n, M): the class marginals of a belief with per-object class beliefs
    (``BeliefConfig.classes = "per_object"``), which has one hypothesis (H = 1, its ``classes``
    the most probable class of every object); None for a realisation table, whose marginals are
    summed from ``weights`` and ``classes``. Read them with :meth:`marginals`.
    """

    object_ids: tuple[int, ...]
    weights: Array
    classes: IntArray
    robot_pose: Array
    robot_cov: Array
    object_pose: Array
    object_cov: Array
    class_probs: Array | None = None

    def marginals(self, num_classes: int) -> Array:
        """P(c_j = i) (n, M) of the known objects."""
        if self.class_probs is not None:
            return self.class_probs
        out = np.zeros((self.classes.shape[1], num_classes))
        for i in range(num_classes):  # as estimator.pruning.class_marginals, to the bit
            out[:, i] = self.weights @ (self.classes == i)
        return out
