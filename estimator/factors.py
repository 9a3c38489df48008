"""GTSAM factors and keys of the hybrid belief.

Keys: robot poses ``pose_key(slot, k)`` (one slot per robot in a belief, so a centralized belief can
hold several trajectories) and objects ``object_key(j)`` with the global object id j.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from estimator.models import MAX_STEP, AliasedClassifier, ClassifierModel, GaussianNoise
from estimator.models.noise import HUBER_K

Array = NDArray[np.float64]
_OBJECT = ord("o")  # the character of object_key (gtsam.Symbol: it sits in the top 8 bits)


def pose_key(slot: int, k: int) -> int:
    """Key of robot ``slot``'s pose at step ``k`` (0 ≤ k ≤ MAX_STEP)."""
    return int(gtsam.symbol("x", slot * (MAX_STEP + 1) + k))


def object_key(object_id: int) -> int:
    """Key of object ``object_id``'s pose."""
    return int(gtsam.symbol("o", object_id))


def is_object_key(key: int) -> bool:
    """Whether ``key`` is an object's (``object_key``), not a robot pose's."""
    return int(key) >> 56 == _OBJECT


def object_value(obj: Array) -> gtsam.Pose2 | Array:
    """The GTSAM value of an object (``estimator.models.objects``): a Pose2 for (x, y, θ), a
    Point2 (a 2-vector) for (x, y)."""
    o = np.asarray(obj, dtype=float)
    if o.shape == (3,):
        return gtsam.Pose2(*o)
    if o.shape == (2,):
        return o.copy()
    raise ValueError(f"an object is (x, y, θ) or (x, y), got shape {o.shape}")


def object_array(values: gtsam.Values, key: int, dim: int) -> Array:
    """Object ``key`` of ``values`` as an array (dim,): (x, y, θ) or (x, y)."""
    if dim == 3:
        p = values.atPose2(key)
        return np.array([p.x(), p.y(), p.theta()])
    return np.asarray(values.atPoint2(key), dtype=float).copy()


def object_prior(key: int, obj: Array, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    """A prior on object ``key`` at ``obj`` (3,) or (2,), in its own tangent space."""
    value = object_value(obj)
    if isinstance(value, gtsam.Pose2):
        return gtsam.PriorFactorPose2(key, value, noise)
    return gtsam.PriorFactorPoint2(key, value, noise)


def detection_factor(
    x_key: int, o_key: int, z_geo: Array, noise: gtsam.noiseModel.Base
) -> gtsam.NonlinearFactor:
    """The geometric factor of one detection (``estimator.models.objects``): the relative pose
    of a pose object (``BetweenFactorPose2``), or (bearing, range) of a point
    (``BearingRangeFactor2D``)."""
    z = np.asarray(z_geo, dtype=float)
    if z.shape == (3,):
        return gtsam.BetweenFactorPose2(x_key, o_key, gtsam.Pose2(*z), noise)
    if z.shape == (2,):
        return gtsam.BearingRangeFactor2D(x_key, o_key, gtsam.Rot2(float(z[0])), float(z[1]), noise)
    raise ValueError(
        f"a detection's z_geo is 3 (relative pose) or 2 (bearing, range), got {z.shape}"
    )


def diagonal_noise(noise: GaussianNoise) -> gtsam.noiseModel.Base:
    """The GTSAM noise model of a :class:`GaussianNoise`: diagonal, inside Huber's robust
    M-estimator at HUBER_K σ when its kernel says so (iSAM2 then re-weights the factor at every
    re-linearisation, and the marginals it gives hold the weights)."""
    diagonal = gtsam.noiseModel.Diagonal.Variances(np.asarray(noise.variances, dtype=float))
    if noise.kernel == "huber":
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(HUBER_K), diagonal
        )
    return diagonal


def viewpoint_with_jacobians(x: Array, o: Array) -> tuple[float, Array, Array]:
    """ψ of camera pose ``x`` (3,) seen from object pose ``o`` (3,), with dψ/dδx and dψ/dδo (3,)
    for the retractions ``x ∘ Exp(δx)`` and ``o ∘ Exp(δo)``.

    Scalar maths on purpose: this runs inside a GTSAM callback, once per linearisation.
    """
    co, so = math.cos(o[2]), math.sin(o[2])
    dx, dy = x[0] - o[0], x[1] - o[1]
    px, py = co * dx + so * dy, -so * dx + co * dy  # p = R_oᵀ (t_x − t_o)
    r2 = px * px + py * py
    gx, gy = -py / r2, px / r2  # dψ/dp
    d = x[2] - o[2]
    c, s = math.cos(d), math.sin(d)
    # dp/dδx = [R(θx − θo) | 0]; dp/dδo = [−I | (p_y, −p_x)ᵀ]
    dpsi_dx = np.array([gx * c + gy * s, -gx * s + gy * c, 0.0])
    dpsi_do = np.array([-gx, -gy, gx * py - gy * px])
    return math.atan2(py, px), dpsi_dx, dpsi_do


def semantic_error(
    model: ClassifierModel, c: int, z_sem: Array, x: Array, o: Array
) -> tuple[Array, Array, Array]:
    """Unwhitened error ``h_c(ψ) − z_sem`` (dim,) and its Jacobians (dim, 3) w.r.t. x and o."""
    psi, dpsi_dx, dpsi_do = viewpoint_with_jacobians(x, o)
    err = model.mean(c, psi) - z_sem
    dh = model.mean_dpsi(c, psi)[:, None]
    return err, dh * dpsi_dx, dh * dpsi_do


def semantic_factor(
    model: ClassifierModel,
    c: int,
    z_sem: Array,
    x_key: int,
    o_key: int,
    psi0: float,
    point: bool = False,
) -> gtsam.CustomFactor:
    """Eq. 1 as a factor on (X_k, O_j): error ``h_c(ψ) − z_sem`` with Σ_c evaluated at ``psi0``.
    ``point``: O_j is a Point2, whose viewpoint is read in the world frame (heading 0,
    ``estimator.models.objects``).

    For models with constant Σ_c (the paper's and the aliased model) this is exact; a model whose
    Σ_c varies with ψ is linearised at the viewpoint of the first estimate.
    """
    z = np.asarray(z_sem, dtype=float).copy()
    if isinstance(model, AliasedClassifier):
        noise = _aliased_noise(model)
        # h_c(ψ) = blur + s(ψ)·sharp, s = ½(1 + cos(ψ − b)): constants bound once per factor.
        blur, sharp, best = model.components(c)
        blur_minus_z = blur - z

        def residual(psi: float) -> Array:
            return blur_minus_z + (0.5 * (1.0 + math.cos(psi - best))) * sharp

        def slope(psi: float) -> Array:
            return (-0.5 * math.sin(psi - best)) * sharp

    else:
        noise = gtsam.noiseModel.Gaussian.Covariance(model.cov(c, psi0))

        def residual(psi: float) -> Array:
            return np.asarray(model.mean(c, psi) - z)

        def slope(psi: float) -> Array:
            return model.mean_dpsi(c, psi)

    callback = _semantic_callback(x_key, o_key, residual, slope, point)
    return gtsam.CustomFactor(noise, gtsam.KeyVector([x_key, o_key]), callback)


@functools.lru_cache(maxsize=64)
def _aliased_noise(model: AliasedClassifier) -> gtsam.noiseModel.Base:
    """The aliased model's Σ is one matrix for every class and viewpoint: one noise model."""
    return gtsam.noiseModel.Gaussian.SqrtInformation(np.array(model.sqrt_info))


def _semantic_callback(
    x_key: int,
    o_key: int,
    residual: Callable[[float], Array],
    slope: Callable[[float], Array],
    point: bool = False,
) -> Callable[..., Array]:
    """The GTSAM callback of a semantic factor: ``residual(ψ)`` = h_c(ψ) − z and its Jacobians
    ``slope(ψ)`` = dh_c/dψ times dψ/dδx, dψ/dδo. The same maths as viewpoint_with_jacobians, inlined
    on plain floats: this runs inside iSAM2 at every relinearisation and dominates a belief step."""

    def error(
        this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[Array] | None
    ) -> Array:
        x = values.atPose2(x_key)
        if point:
            ox, oy = values.atPoint2(o_key)
            ot = 0.0
        else:
            o = values.atPose2(o_key)
            ox, oy, ot = o.x(), o.y(), o.theta()
        co, so = math.cos(ot), math.sin(ot)
        dx, dy = x.x() - ox, x.y() - oy
        px, py = co * dx + so * dy, -so * dx + co * dy
        psi = math.atan2(py, px)
        if jacobians is not None:
            r2 = px * px + py * py
            gx, gy = -py / r2, px / r2
            d = x.theta() - ot
            cd, sd = math.cos(d), math.sin(d)
            dh = slope(psi)[:, None]
            jacobians[0] = dh * np.array((gx * cd + gy * sd, -gx * sd + gy * cd, 0.0))
            # a point's tangent is the world translation: the pose's first two columns at θ = 0
            jacobians[1] = dh * (
                np.array((-gx, -gy)) if point else np.array((-gx, -gy, gx * py - gy * px))
            )
        return residual(psi)

    return error


def semantic_log_normaliser(model: ClassifierModel, c: int, psi0: float) -> float:
    """−½ log det(2πΣ_c(ψ0)): ``log N(z) = −factor.error − ½ log det(2πΣ)``."""
    cov = model.cov(c, psi0)
    _, logdet = np.linalg.slogdet(2.0 * np.pi * cov)
    return float(-0.5 * logdet)
