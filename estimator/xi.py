"""ξ, the continuous part of a slot (Eq. 18), in its dense form: its own module so that the dense
form (here), its sparse form (``estimator.sparse_xi``) and the slot that holds either
(``estimator.summary``) import one way."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True, eq=False)
class Xi:
    """ξ of Eq. 18: a prior-divided joint Gaussian over the owner's n objects in information form.

    ``lin`` (n, d) linearisation points (d = 3 for Pose2 objects, x, y, θ; d = 2 for Point2
    objects, x, y); ``info`` (dn, dn) Λ, symmetric positive definite; ``eta`` (dn,) η, so that
    ξ ∝ exp(−½ δᵀΛδ + ηᵀδ) over tangent perturbations δ at ``lin``. Several realisations of one
    slot may share one ξ (the same object): every realisation of a belief whose hypotheses share
    one continuous belief does (docs/estimator.md).
    """

    lin: Array
    info: Array
    eta: Array

    @property
    def dim(self) -> int:
        """d, the tangent dimension of one object: 3 for Pose2 objects, 2 for Point2."""
        return int(np.shape(self.lin)[1])
