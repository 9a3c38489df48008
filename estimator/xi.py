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

    ``lin`` (n, 3) linearisation poses; ``info`` (3n, 3n) Λ, symmetric positive definite; ``eta``
    (3n,) η, so that ξ ∝ exp(−½ δᵀΛδ + ηᵀδ) over tangent perturbations δ at ``lin``. Several
    realisations of one slot may share one ξ (the same object): every realisation of a belief
    whose hypotheses share one continuous belief does (docs/estimator.md).
    """

    lin: Array
    info: Array
    eta: Array
