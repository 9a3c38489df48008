"""Vectorised SE(2) on numpy arrays of shape (..., 3) holding (x, y, θ).

The conventions are GTSAM's ``Pose2``: ``compose(a, b) = a ∘ b``, ``between(a, b) = a⁻¹ ∘ b``,
``retract(p, v) = p ∘ Expmap(v)`` and ``local(p, q) = Logmap(p⁻¹ ∘ q)``; tangent vectors are
(v_x, v_y, ω) in the body frame. Every function broadcasts over the leading axes, so a single call
handles thousands of samples or particles.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

# Below this |θ| the closed forms of Expmap/Logmap lose precision; their Taylor series are used.
SMALL_ANGLE = 1e-6


def wrap_angle(theta: ArrayLike) -> Array:
    """Wrap angles to [-π, π). Shape preserved; angles already in range are returned unchanged."""
    t = np.asarray(theta, dtype=float)
    inside = (t >= -np.pi) & (t < np.pi)
    wrapped = np.where(inside, t, (t + np.pi) % (2.0 * np.pi) - np.pi)
    # (t + π) mod 2π can round up to 2π, which would give +π.
    return np.asarray(np.where(wrapped >= np.pi, wrapped - 2.0 * np.pi, wrapped))


def _split(p: ArrayLike) -> tuple[Array, Array, Array]:
    a = np.asarray(p, dtype=float)
    if a.shape[-1:] != (3,):
        raise ValueError(f"expected poses of shape (..., 3), got {a.shape}")
    return a[..., 0], a[..., 1], a[..., 2]


def _stack(x: Array, y: Array, t: Array) -> Array:
    return np.stack(np.broadcast_arrays(x, y, t), axis=-1)


def compose(a: ArrayLike, b: ArrayLike) -> Array:
    """a ∘ b for poses (..., 3) → (..., 3)."""
    ax, ay, at = _split(a)
    bx, by, bt = _split(b)
    c, s = np.cos(at), np.sin(at)
    return _stack(ax + c * bx - s * by, ay + s * bx + c * by, wrap_angle(at + bt))


def inverse(a: ArrayLike) -> Array:
    """a⁻¹ for poses (..., 3) → (..., 3)."""
    ax, ay, at = _split(a)
    c, s = np.cos(at), np.sin(at)
    return _stack(-c * ax - s * ay, s * ax - c * ay, wrap_angle(-at))


def between(a: ArrayLike, b: ArrayLike) -> Array:
    """a⁻¹ ∘ b for poses (..., 3) → (..., 3)."""
    ax, ay, at = _split(a)
    bx, by, bt = _split(b)
    c, s = np.cos(at), np.sin(at)
    dx, dy = bx - ax, by - ay
    return _stack(c * dx + s * dy, -s * dx + c * dy, wrap_angle(bt - at))


def transform_to(a: ArrayLike, points: ArrayLike) -> Array:
    """Coordinates of world points (..., 2) in the frame of pose a (..., 3) → (..., 2)."""
    ax, ay, at = _split(a)
    pts = np.asarray(points, dtype=float)
    c, s = np.cos(at), np.sin(at)
    dx, dy = pts[..., 0] - ax, pts[..., 1] - ay
    return np.stack(np.broadcast_arrays(c * dx + s * dy, -s * dx + c * dy), axis=-1)


def transform_from(a: ArrayLike, points: ArrayLike) -> Array:
    """World coordinates of points (..., 2) given in the frame of pose a (..., 3) → (..., 2)."""
    ax, ay, at = _split(a)
    pts = np.asarray(points, dtype=float)
    c, s = np.cos(at), np.sin(at)
    px, py = pts[..., 0], pts[..., 1]
    return np.stack(np.broadcast_arrays(ax + c * px - s * py, ay + s * px + c * py), axis=-1)


def expmap(v: ArrayLike) -> Array:
    """Exponential map of tangent vectors (..., 3) → poses (..., 3)."""
    vx, vy, w = _split(v)
    small = np.abs(w) < SMALL_ANGLE
    w_safe = np.where(small, 1.0, w)
    sin_w = np.where(small, 1.0 - w * w / 6.0, np.sin(w_safe) / w_safe)
    # (1 − cos ω)/ω written as 2 sin²(ω/2)/ω, which does not cancel for small ω.
    cos_w = np.where(small, w / 2.0 - w**3 / 24.0, 2.0 * np.sin(w_safe / 2.0) ** 2 / w_safe)
    return _stack(sin_w * vx - cos_w * vy, cos_w * vx + sin_w * vy, wrap_angle(w))


def logmap(p: ArrayLike) -> Array:
    """Logarithm map of poses (..., 3) → tangent vectors (..., 3), θ in [-π, π)."""
    x, y, t = _split(p)
    t = wrap_angle(t)
    half = t / 2.0
    small = np.abs(t) < SMALL_ANGLE
    half_safe = np.where(small, 1.0, half)
    # (θ/2)·cot(θ/2), with its series 1 − θ²/12 near zero.
    a = np.where(small, 1.0 - t * t / 12.0, half_safe / np.tan(half_safe))
    return _stack(a * x + half * y, -half * x + a * y, t)


def retract(p: ArrayLike, v: ArrayLike) -> Array:
    """p ∘ Expmap(v): poses (..., 3), tangent vectors (..., 3) → poses (..., 3)."""
    return compose(p, expmap(v))


def local(p: ArrayLike, q: ArrayLike) -> Array:
    """Logmap(p⁻¹ ∘ q): the tangent vector at p that reaches q, (..., 3)."""
    return logmap(between(p, q))
