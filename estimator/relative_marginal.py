"""The window's marginal, root-shifted (``estimator.smoother``): a linear marginal on poses,
re-expressed in its variables' poses relative to one of them, as a nonlinear factor that iSAM2
relinearises with the map. The Pose2 arithmetic is batched over the factor's keys in numpy, in
GTSAM's conventions (``Pose2.AdjointMap``, ``Logmap``, ``LogmapDerivative``; tested against
them)."""

from __future__ import annotations

import gtsam
import numpy as np

_POSE = ord("x")  # the character of estimator.factors.pose_key


def relative_marginal(g: gtsam.GaussianFactor, estimate: gtsam.Values) -> gtsam.CustomFactor | None:
    """A linear marginal ``g`` on poses, re-expressed in its variables' poses relative to one of
    them (the root: its first robot pose, else its first key), as a nonlinear factor.

    With δ each variable's tangent at the linearisation point ``estimate``, ``g`` is
    ½‖A δ − b‖². Let r_k = x_root⁻¹ v_k; its tangent is ρ_k = δ_k − Ad(r̂_k⁻¹) δ_root to first
    order, so δ_k = ρ_k + Ad(r̂_k⁻¹) ρ_root and the same Gaussian reads ½‖A′ ρ − b‖² with
    A′_root = A_root + Σ_k A_k Ad(r̂_k⁻¹) and A′_k = A_k. Evaluated with ρ_root =
    Log(x̂_root⁻¹ x_root) and ρ_k = Log(r̂_k⁻¹ x_root⁻¹ v_k), the factor equals ``g`` to first order
    at the linearisation point, and a rigid motion of all its variables together (a later loop
    closure turning the old map) leaves every ρ_k unchanged: only the information ``g`` holds on
    the root's absolute pose (from the robots' start priors) sees it, and that is relinearised on
    the group like a prior. A ``LinearContainerFactor`` takes each variable's local coordinates
    on its own: a pure turn of the whole map stays in its null space, but a turn with a bend
    mixes the two (second-order cross terms of the size of the bend; tested), so after a large
    loop correction it pulls the old map towards where it was. This is the root-shifted form of
    the generic linear constraints of Carlevaris-Bianco, Kaess & Eustice (T-RO 2014).

    None when ``g`` holds no information.
    """
    keys = [int(k) for k in g.keys()]  # noqa: SIM118 - not iterable
    info = g.augmentedInformation()
    n = info.shape[0] - 1
    lam, eta = 0.5 * (info[:n, :n] + info[:n, :n].T), info[:n, n]
    s, u = np.linalg.eigh(lam)
    keep = s > max(float(s.max(initial=0.0)), 1.0) * 1e-12
    if not keep.any():
        return None
    a = np.sqrt(s[keep])[:, None] * u[:, keep].T
    b = (u[:, keep].T @ eta) / np.sqrt(s[keep])
    poses = [k for k in keys if k >> 56 == _POSE]
    root = poses[0] if poses else keys[0]
    others = [k for k in keys if k != root]
    order = [root, *others]  # the factor's keys: the root first
    cols = {k: slice(3 * i, 3 * i + 3) for i, k in enumerate(keys)}
    a = np.concatenate([a[:, cols[k]] for k in order], axis=1).reshape(a.shape[0], len(order), 3)
    lin_root = estimate.atPose2(root)
    rel = np.array([_xyt(lin_root.between(estimate.atPose2(k))) for k in others]).reshape(-1, 3)
    # A′: the root's columns gather each other variable's through Ad(r̂_k⁻¹); kept per key,
    # (K, rows, 3), so that the Jacobians are batched products.
    ap = a.transpose(1, 0, 2).copy()
    ap[0] += (a.transpose(1, 0, 2)[1:] @ _adjoint(_inverse(rel))).sum(axis=0)
    flat = ap.transpose(1, 0, 2).reshape(a.shape[0], -1)
    rows = a.shape[0]
    lin_root_inv = _inverse(_xyt(lin_root)[None])
    rel_inv = _inverse(rel)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jac: list | None) -> np.ndarray:
        x_root = _xyt(values.atPose2(root))[None]
        v = np.array([_xyt(values.atPose2(k)) for k in others]).reshape(-1, 3)
        q = _compose(_inverse(x_root), v)  # x_root⁻¹ v_k
        rho = np.empty((len(order), 3))
        rho[0] = _logmap(_compose(lin_root_inv, x_root))[0]
        rho[1:] = _logmap(_compose(rel_inv, q))
        if jac is not None:
            j = _logmap_derivative(rho)  # d ρ / d e, with d e_root / d x_root = d e_k / d v_k = I
            own = ap @ j
            # d e_k / d x_root = −Ad(q_k⁻¹)
            via = -(j[1:] @ _adjoint(_inverse(q)))
            jac[0] = own[0] + (ap[1:] @ via).sum(axis=0)
            for i in range(1, len(order)):
                jac[i] = own[i]
        return flat @ rho.ravel() - b

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows), order, error)


def _xyt(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _wrap(theta: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(theta), np.cos(theta))


def _inverse(p: np.ndarray) -> np.ndarray:
    """Pose2 inverses of poses (K, 3) as (x, y, θ) rows."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    x, y = p[:, 0], p[:, 1]
    return np.stack([-c * x - s * y, s * x - c * y, -p[:, 2]], axis=1)


def _compose(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """p ∘ q of poses (K, 3) or (1, 3) each, as (x, y, θ) rows."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    return np.stack(
        [
            p[:, 0] + c * q[:, 0] - s * q[:, 1],
            p[:, 1] + s * q[:, 0] + c * q[:, 1],
            _wrap(p[:, 2] + q[:, 2]),
        ],
        axis=1,
    )


def _adjoint(p: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose2.AdjointMap`` of poses (K, 3): (K, 3, 3)."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    out = np.zeros((len(p), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = c, -s, p[:, 1]
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = s, c, -p[:, 0]
    out[:, 2, 2] = 1.0
    return out


def _logmap(p: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose2.Logmap`` of poses (K, 3) with θ in (−π, π]."""
    w = p[:, 2]
    small = np.abs(w) < 1e-10
    c1, s = np.cos(w) - 1.0, np.sin(w)
    det = np.where(small, 1.0, c1 * c1 + s * s)
    # R⁻¹ t − t, turned by π/2
    ux = np.cos(w) * p[:, 0] + s * p[:, 1] - p[:, 0]
    uy = -s * p[:, 0] + np.cos(w) * p[:, 1] - p[:, 1]
    scale = w / det
    out = np.stack([-uy * scale, ux * scale, w], axis=1)
    out[small, :2] = p[small, :2]
    return out


def _logmap_derivative(v: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose2.LogmapDerivative`` of tangent vectors (K, 3): (K, 3, 3)."""
    a, v1, v2 = v[:, 2], v[:, 0], v[:, 1]
    out = np.zeros((len(v), 3, 3))
    big = np.abs(a) > 1e-5
    ab = np.where(big, a, 1.0)
    half_cot = 0.5 * np.sin(ab) / (1.0 - np.cos(ab))
    out[:, 0, 0] = np.where(big, a * half_cot, 1.0)
    out[:, 0, 1] = np.where(big, -0.5 * a, 0.0)
    out[:, 0, 2] = np.where(big, v1 / ab - v1 * half_cot + 0.5 * v2, 0.5 * v2)
    out[:, 1, 0] = np.where(big, 0.5 * a, 0.0)
    out[:, 1, 1] = out[:, 0, 0]
    out[:, 1, 2] = np.where(big, v2 / ab - 0.5 * v1 - v2 * half_cot, -0.5 * v1)
    out[:, 2, 2] = 1.0
    return out
