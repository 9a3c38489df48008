"""Motion, range-bearing observation and relation residuals of Semantic UFastSLAM (design doc §3).

All functions broadcast over leading axes: poses (..., 3) = (x, y, θ), landmarks (..., 2),
controls (..., 2) = (v, ω), measurements (..., 2) = (range, bearing).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.models.se2 import wrap_angle

Array = NDArray[np.float64]

RELATION_KINDS = ("x", "y", "col")


def motion(pose: ArrayLike, control: ArrayLike, dt: float) -> Array:
    """Unicycle, midpoint discretisation: a = θ + ωΔt/2, x += vΔt cos a, y += vΔt sin a,
    θ += ωΔt. The heading is left unwrapped so sigma-point deviations stay exact; callers wrap."""
    p = np.asarray(pose, dtype=float)
    u = np.asarray(control, dtype=float)
    v, w = u[..., 0], u[..., 1]
    a = p[..., 2] + 0.5 * w * dt
    return np.stack(
        np.broadcast_arrays(
            p[..., 0] + v * dt * np.cos(a), p[..., 1] + v * dt * np.sin(a), p[..., 2] + w * dt
        ),
        axis=-1,
    )


def observe(pose: ArrayLike, landmark: ArrayLike) -> Array:
    """h(x, m) = [‖m − p‖, wrap(atan2(dy, dx) − θ)] → (..., 2)."""
    p = np.asarray(pose, dtype=float)
    m = np.asarray(landmark, dtype=float)
    dx, dy = m[..., 0] - p[..., 0], m[..., 1] - p[..., 1]
    return np.stack(
        np.broadcast_arrays(np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - p[..., 2])), axis=-1
    )


def observe_jacobians(pose: ArrayLike, landmark: ArrayLike) -> tuple[Array, Array]:
    """∂h/∂x (..., 2, 3) and ∂h/∂m (..., 2, 2) of :func:`observe` (for the association gate)."""
    p = np.asarray(pose, dtype=float)
    m = np.asarray(landmark, dtype=float)
    dx, dy = m[..., 0] - p[..., 0], m[..., 1] - p[..., 1]
    q = np.maximum(dx * dx + dy * dy, 1e-12)
    r = np.sqrt(q)
    h_m = np.stack([np.stack([dx / r, dy / r], -1), np.stack([-dy / q, dx / q], -1)], axis=-2)
    h_x = np.concatenate([-h_m, np.zeros((*h_m.shape[:-1], 1))], axis=-1)
    h_x[..., 1, 2] = -1.0
    return h_x, h_m


def inverse_observe(pose: ArrayLike, z: ArrayLike) -> Array:
    """h⁻¹(x, z) = p + r[cos(θ + b), sin(θ + b)] → (..., 2)."""
    p = np.asarray(pose, dtype=float)
    zz = np.asarray(z, dtype=float)
    r, a = zz[..., 0], p[..., 2] + zz[..., 1]
    return np.stack(
        np.broadcast_arrays(p[..., 0] + r * np.cos(a), p[..., 1] + r * np.sin(a)), axis=-1
    )


def relation_residual(kind: str, landmark: Array, refs: Array) -> Array:
    """c(m_j; refs), ideally 0: same-x m_j,x − m_k,x; same-y m_j,y − m_k,y; collinear
    ((m_b − m_a) × (m_j − m_a)) / ‖m_b − m_a‖, a signed distance in metres.

    ``landmark`` (..., 2); ``refs`` (..., 1, 2) for x and y, (..., 2, 2) = (m_a, m_b) for col.
    """
    if kind == "x":
        return np.asarray(landmark[..., 0] - refs[..., 0, 0])
    if kind == "y":
        return np.asarray(landmark[..., 1] - refs[..., 0, 1])
    if kind == "col":
        a, b = refs[..., 0, :], refs[..., 1, :]
        base = b - a
        rel = landmark - a
        cross = base[..., 0] * rel[..., 1] - base[..., 1] * rel[..., 0]
        return np.asarray(cross / np.hypot(base[..., 0], base[..., 1]))
    raise ValueError(f"unknown relation kind {kind!r} (known: {', '.join(RELATION_KINDS)})")
