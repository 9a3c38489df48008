"""Gaussian noise of motion (odometry, on SE(2)'s tangent space) and of detections (a relative
pose on SE(2)'s tangent space, or a point's bearing and range: ``estimator.models.objects``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator.models import se2

Array = NDArray[np.float64]

KERNELS = ("gaussian", "huber")
# Huber's constant: 95 % of least squares' efficiency on Gaussian data (Huber 1964; Zhang,
# "Parameter estimation techniques", 1997), the usual choice and not fitted to any data here.
HUBER_K = 1.345


@dataclass(frozen=True, slots=True)
class GaussianNoise:
    """Zero-mean Gaussian with diagonal covariance.

    ``variances`` (3,) = (σ²_x, σ²_y, σ²_θ) in the body-frame tangent space of Pose2: a
    measurement of the true relative pose ``t`` is ``retract(t, n)`` with
    ``n ~ N(0, diag(variances))``, matching ``BetweenFactorPose2``'s error ``Logmap(t⁻¹ z)``.
    ``variances`` (2,) = (σ²_bearing, σ²_range) of a point's detection: ``t + n``, the bearing
    wrapped to [−π, π), matching ``BearingRangeFactor2D``'s error.
    """

    variances: tuple[float, ...]
    # The loss the estimators put on a residual of this noise (``KERNELS``): "gaussian", least
    # squares; "huber", Huber's M-estimator at HUBER_K standard deviations — quadratic within,
    # linear beyond — for real sensors whose errors have heavier tails than a Gaussian (gross
    # misreads). It changes what the estimators assume, never what a simulator draws.
    kernel: str = "gaussian"

    def __post_init__(self) -> None:
        v = np.asarray(self.variances, dtype=float)
        if v.shape not in ((3,), (2,)) or not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(
                "variances must be three (x, y, θ) or two (bearing, range) finite positive"
                f" numbers, got {self.variances}"
            )
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel {self.kernel!r}: expected one of {', '.join(KERNELS)}")

    @property
    def sigmas(self) -> Array:
        """Standard deviations (3,) or (2,)."""
        return np.sqrt(np.asarray(self.variances, dtype=float))

    @property
    def cov(self) -> Array:
        """Covariance (3, 3) or (2, 2)."""
        return np.diag(np.asarray(self.variances, dtype=float))

    def corrupt(self, truth: Array, standard_normal: Array) -> Array:
        """Noisy measurement of ``truth`` (..., d) from standard normal draws (..., d), d the
        number of variances."""
        n = np.asarray(standard_normal) * self.sigmas
        if len(self.variances) == 3:
            return se2.retract(truth, n)
        z = np.asarray(truth, dtype=float) + n
        return np.stack([se2.wrap_angle(z[..., 0]), z[..., 1]], -1)

    def sample(self, truth: Array, rng: np.random.Generator) -> Array:
        """Noisy measurement of ``truth`` (..., d) with fresh draws from ``rng``."""
        t = np.asarray(truth, dtype=float)
        return self.corrupt(t, rng.standard_normal(t.shape))


# The paper's simulation (design doc §1, variances): odometry and object relative-pose noise.
PAPER_ODOMETRY = GaussianNoise((0.003, 0.003, 0.001))
PAPER_GEOMETRIC = GaussianNoise((0.1, 0.1, 0.01))
