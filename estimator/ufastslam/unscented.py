"""Scaled unscented transform with angle-aware statistics (design doc §4), batched over any leading
axes (particles, observations).

Every function takes means ``(..., n)`` and covariances ``(..., n, n)``; ``angular`` lists the
components that are angles, whose means are taken relative to the central sigma point and whose
deviations are wrapped to [-π, π).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.models.se2 import wrap_angle

Array = NDArray[np.float64]
SigmaMap = Callable[[Array], Array]

# Relative jitter on the diagonal before a Cholesky: a just-sampled pose has P = 0 exactly.
_JITTER = 1e-12
_LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True, slots=True)
class UTParams:
    """Scaling of the sigma points: λ = α²(n + κ) − n.

    α = 1, β = 2, κ = 0 (the default) keeps every weight non-negative, so every covariance the
    transform returns is PSD; a tiny α makes W_m0 ≈ −10⁵ and cancels catastrophically.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"alpha must be finite and > 0, got {self.alpha}")
        if not (np.isfinite(self.beta) and np.isfinite(self.kappa)):
            raise ValueError("beta and kappa must be finite")


@dataclass(frozen=True, slots=True)
class SigmaWeights:
    """Weights of the 2n + 1 sigma points: ``mean`` and ``cov`` (2n + 1,), ``scale`` = n + λ."""

    mean: Array
    cov: Array
    scale: float


@lru_cache(maxsize=64)
def _weights(n: int, alpha: float, beta: float, kappa: float) -> SigmaWeights:
    lam = alpha**2 * (n + kappa) - n
    scale = n + lam
    if scale <= 0:
        raise ValueError(f"n + λ = {scale} must be > 0 (n = {n}, α = {alpha}, κ = {kappa})")
    wm = np.full(2 * n + 1, 1.0 / (2.0 * scale))
    wc = wm.copy()
    wm[0] = lam / scale
    wc[0] = lam / scale + 1.0 - alpha**2 + beta
    wm.setflags(write=False)
    wc.setflags(write=False)
    return SigmaWeights(wm, wc, scale)


def sigma_weights(n: int, params: UTParams = UTParams()) -> SigmaWeights:
    """Mean and covariance weights of an n-dimensional scaled unscented transform."""
    return _weights(n, params.alpha, params.beta, params.kappa)


def psd_sqrt(cov: ArrayLike) -> Array:
    """A square root S with S Sᵀ = cov for covariances (..., n, n).

    Cholesky of the symmetrised matrix with a tiny relative jitter; if any matrix of the batch is
    still not positive definite, the whole batch falls back to eigenvalues clipped at zero.
    """
    c = np.asarray(cov, dtype=float)
    c = 0.5 * (c + np.swapaxes(c, -1, -2))
    n = c.shape[-1]
    diag = np.einsum("...ii->...i", c)
    jitter = _JITTER * (1.0 + np.abs(diag).mean(axis=-1))
    try:
        return np.linalg.cholesky(c + jitter[..., None, None] * np.eye(n))
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(c)
        return np.asarray(v * np.sqrt(np.clip(w, 0.0, None))[..., None, :])


def sigma_points(mean: ArrayLike, cov: ArrayLike, params: UTParams = UTParams()) -> Array:
    """The 2n + 1 points μ, μ ± columns of √((n + λ)P): (..., n), (..., n, n) → (..., 2n + 1, n)."""
    mu = np.asarray(mean, dtype=float)
    n = mu.shape[-1]
    root = psd_sqrt(cov) * np.sqrt(sigma_weights(n, params).scale)
    offsets = np.swapaxes(root, -1, -2)  # row i = column i of the root
    zero = np.zeros((*offsets.shape[:-2], 1, n))
    return mu[..., None, :] + np.concatenate([zero, offsets, -offsets], axis=-2)


def weighted_mean(points: Array, weights: Array, angular: Sequence[int] = ()) -> Array:
    """Σ W_i y_i over axis −2 of (..., s, m), angles as y_0 + Σ W_i wrap(y_i − y_0) (design §4)."""
    mean = np.einsum("s,...sm->...m", weights, points)
    for a in angular:
        ref = points[..., 0, a]
        rel = wrap_angle(points[..., a] - ref[..., None])
        mean[..., a] = wrap_angle(ref + np.einsum("s,...s->...", weights, rel))
    return np.asarray(mean)


def deviations(points: Array, mean: Array, angular: Sequence[int] = ()) -> Array:
    """y_i − ȳ for (..., s, m) points and an (..., m) mean, angles wrapped."""
    dev = points - mean[..., None, :]
    for a in angular:
        dev[..., a] = wrap_angle(dev[..., a])
    return dev


def weighted_cov(dx: Array, dy: Array, weights: Array) -> Array:
    """Σ W_i dx_i dy_iᵀ for deviations (..., s, p) and (..., s, q) → (..., p, q)."""
    return np.asarray(np.swapaxes(dx * weights[:, None], -1, -2) @ dy)


def transform(
    mean: ArrayLike,
    cov: ArrayLike,
    f: SigmaMap,
    params: UTParams = UTParams(),
    angular: Sequence[int] = (),
) -> tuple[Array, Array]:
    """Mean (..., m) and covariance (..., m, m) of f(x), x ~ N(mean, cov).

    ``f`` maps sigma points (..., 2n + 1, n) to (..., 2n + 1, m); ``angular`` indexes f's output.
    """
    chi = sigma_points(mean, cov, params)
    w = sigma_weights(chi.shape[-1], params)
    y = f(chi)
    y_mean = weighted_mean(y, w.mean, angular)
    dy = deviations(y, y_mean, angular)
    return y_mean, weighted_cov(dy, dy, w.cov)


@dataclass(frozen=True, slots=True)
class UTUpdate:
    """Result of :func:`update`: the updated leading ``n_upd`` components — ``mean`` (..., n_upd),
    ``cov`` (..., n_upd, n_upd) — and the innovation's Gaussian log-likelihood (...)."""

    mean: Array
    cov: Array
    log_likelihood: Array


def update(
    mean: ArrayLike,
    cov: ArrayLike,
    g: SigmaMap,
    y: ArrayLike,
    r_add: ArrayLike,
    n_upd: int,
    params: UTParams = UTParams(),
    angular: Sequence[int] = (),
) -> UTUpdate:
    """Kalman update of an augmented Gaussian by the measurement y = g(a) + v, v ~ N(0, r_add).

    ``mean`` (..., n) and ``cov`` (..., n, n) describe the augmented state a; only its first
    ``n_upd`` components are updated, the rest (noise, "consider" landmarks) only widen S.
    ``y`` (..., m) and ``r_add`` (..., m, m) broadcast against the batch; ``angular`` indexes y.
    S = Σ W_c ΔY ΔYᵀ + R, C = Σ W_c Δχ ΔYᵀ, K = C S⁻¹, μ += Kν, P −= K S Kᵀ,
    ll = −½ νᵀ S⁻¹ ν − ½ log det 2πS  (design doc §5).
    """
    mu = np.asarray(mean, dtype=float)
    chi = sigma_points(mu, cov, params)
    w = sigma_weights(mu.shape[-1], params)
    ys = g(chi)
    y_hat = weighted_mean(ys, w.mean, angular)
    dy = deviations(ys, y_hat, angular)
    dx = chi[..., :n_upd] - mu[..., None, :n_upd]
    s = weighted_cov(dy, dy, w.cov) + np.asarray(r_add, dtype=float)
    c = weighted_cov(dx, dy, w.cov)
    nu = np.asarray(y, dtype=float) - y_hat
    for a in angular:
        nu[..., a] = wrap_angle(nu[..., a])
    m = s.shape[-1]
    rhs = np.concatenate([np.swapaxes(c, -1, -2), nu[..., :, None]], axis=-1)
    sol = np.linalg.solve(s, rhs)  # [S⁻¹Cᵀ | S⁻¹ν]
    gain_t, s_inv_nu = sol[..., :n_upd], sol[..., n_upd]
    new_mean = mu[..., :n_upd] + np.einsum("...mi,...m->...i", gain_t, nu)
    p = np.asarray(cov, dtype=float)[..., :n_upd, :n_upd] - c @ gain_t
    p = 0.5 * (p + np.swapaxes(p, -1, -2))
    _, logdet = np.linalg.slogdet(s)
    ll = -0.5 * np.einsum("...m,...m->...", nu, s_inv_nu) - 0.5 * (logdet + m * _LOG_2PI)
    return UTUpdate(new_mean, p, ll)
