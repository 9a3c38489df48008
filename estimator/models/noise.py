"""Gaussian noise on SE(2) tangent spaces: motion (odometry) and geometric (relative pose)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator.models import se2

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class GaussianNoise:
    """Zero-mean Gaussian with diagonal covariance in the body-frame tangent space of Pose2.

    ``variances`` is (3,) = (σ²_x, σ²_y, σ²_θ). A measurement of the true relative pose ``t`` is
    ``retract(t, n)`` with ``n ~ N(0, diag(variances))``, matching ``BetweenFactorPose2``'s error
    ``Logmap(t⁻¹ z)``.
    """

    variances: tuple[float, float, float]

    def __post_init__(self) -> None:
        v = np.asarray(self.variances, dtype=float)
        if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(
                f"variances must be three finite positive numbers, got {self.variances}"
            )

    @property
    def sigmas(self) -> Array:
        """Standard deviations (3,)."""
        return np.sqrt(np.asarray(self.variances, dtype=float))

    @property
    def cov(self) -> Array:
        """Covariance (3, 3)."""
        return np.diag(np.asarray(self.variances, dtype=float))

    def corrupt(self, truth: Array, standard_normal: Array) -> Array:
        """Noisy measurement of poses ``truth`` (..., 3) from standard normal draws (..., 3)."""
        return se2.retract(truth, np.asarray(standard_normal) * self.sigmas)

    def sample(self, truth: Array, rng: np.random.Generator) -> Array:
        """Noisy measurement of poses ``truth`` (..., 3) with fresh draws from ``rng``."""
        t = np.asarray(truth, dtype=float)
        return self.corrupt(t, rng.standard_normal(t.shape))


# The paper's simulation (design doc §1, variances): odometry and object relative-pose noise.
PAPER_ODOMETRY = GaussianNoise((0.003, 0.003, 0.001))
PAPER_GEOMETRIC = GaussianNoise((0.1, 0.1, 0.01))
