"""The weight integral of Eq. 6 (locally) and Eq. 14–15 (distributed), design doc §3.

Both estimators see the same linear-Gaussian picture of the propagated belief over the involved
variables ``inv = [X_k …] + [O_j for detected j]``: tangent perturbations δ (n,) at the
linearisation point, δ ~ N(0, Λ⁻¹), and the whitened, linearised geometric factors ``J δ − b``.
Only the semantic term needs samples; it is evaluated jointly for every class assignment of a
parent's children so that one set of samples serves them all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solve_triangular

from estimator.logsumexp import logsumexp
from estimator.models import ClassifierModel, se2, viewpoint
from estimator.models.classifier import all_log_likelihoods

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

WEIGHT_ESTIMATORS = ("geo_conditioned", "paper_mc")


@dataclass(frozen=True, slots=True)
class InvolvedGaussian:
    """The propagated belief over the involved variables and the new geometric factors.

    ``lin`` (v, 3) linearisation poses of the v involved variables (n = 3v); ``info`` (n, n) their
    joint marginal information; ``jac`` (m, n), ``rhs`` (m,) the whitened linearised geometric
    factors; ``geo_log_norm`` the sum of −½ log det(2πΣ_geo) over the m/3 geometric factors.
    """

    lin: Array
    info: Array
    jac: Array
    rhs: Array
    geo_log_norm: float


@dataclass(frozen=True, slots=True)
class SemanticTerms:
    """The semantic measurements of one step: detection d seen by the robot variable
    ``robot_var[d]`` of the object variable ``object_var[d]`` (indices into ``lin``) with scores
    ``z[d]`` (D, dim)."""

    robot_var: IntArray
    object_var: IntArray
    z: Array


def _cholesky_lower(a: Array) -> Array:
    return np.asarray(np.linalg.cholesky(0.5 * (a + a.T)), dtype=float)


def _log_det_chol(chol: Array) -> float:
    return float(2.0 * np.sum(np.log(np.diagonal(chol))))


def _retract_samples(lin: Array, delta: Array) -> Array:
    """Poses (S, v, 3) from tangent samples δ (S, 3v) at ``lin`` (v, 3)."""
    s = delta.shape[0]
    return se2.retract(lin[None, :, :], delta.reshape(s, -1, 3))


def sampled_viewpoints(
    lin: Array, delta: Array, robot_var: IntArray, object_var: IntArray
) -> Array:
    """ψ of every detection at every sample: ``lin`` (..., v, 3), tangent samples ``delta``
    (..., S, v, 3) → (..., S, D). The same maths as ``viewpoint`` of ``se2.retract`` (GTSAM's
    p ∘ Expmap(δ)), fused: only the robots' positions and the objects' poses that ψ reads are
    formed, and no angle is wrapped (ψ reads angles only through cos and sin)."""
    lin = lin[..., None, :, :]
    vx, vy, w = delta[..., 0], delta[..., 1], delta[..., 2]
    small = np.abs(w) < se2.SMALL_ANGLE
    w_safe = np.where(small, 1.0, w)
    half_sin = np.sin(0.5 * w_safe)
    # V(ω)·v with sin ω/ω and (1 − cos ω)/ω = 2 sin²(ω/2)/ω, their series near zero (as expmap).
    a = np.where(small, 1.0 - w * w / 6.0, np.sin(w_safe) / w_safe)
    b = np.where(small, w / 2.0 - w**3 / 24.0, 2.0 * half_sin * half_sin / w_safe)
    tx, ty = a * vx - b * vy, b * vx + a * vy
    theta = lin[..., 2]
    c, s = np.cos(theta), np.sin(theta)
    px = lin[..., 0] + c * tx - s * ty
    py = lin[..., 1] + s * tx + c * ty
    ot = theta[..., object_var] + w[..., object_var]
    co, so = np.cos(ot), np.sin(ot)
    dx = px[..., robot_var] - px[..., object_var]
    dy = py[..., robot_var] - py[..., object_var]
    return np.asarray(np.arctan2(-so * dx + co * dy, co * dx + so * dy))


def semantic_log_likelihoods(model: ClassifierModel, poses: Array, terms: SemanticTerms) -> Array:
    """log P(z_d | poses, c) for every sample, detection and class: poses (S, v, 3) → (S, D, M)."""
    psi = viewpoint(poses[:, terms.robot_var, :], poses[:, terms.object_var, :])  # (S, D)
    return all_log_likelihoods(model, np.asarray(terms.z, dtype=float), psi)


def assignment_log_means(log_lik: Array, assignments: IntArray) -> Array:
    """log (1/S) Σ_s Π_d P(z_d | c = assignments[a, d]) per assignment: (S, D, M), (A, D) → (A,)."""
    s, d_count, _ = log_lik.shape
    if d_count == 0:
        return np.zeros(len(assignments))
    picked = log_lik[:, np.arange(d_count)[None, :], assignments]  # (S, A, D)
    total = picked.sum(axis=2)
    return np.asarray(logsumexp(total, axis=0) - np.log(s))


@dataclass(frozen=True, slots=True)
class SampledEvidence:
    """Δlog w of a parent's children, per Monte Carlo sample and before the class assignment.

    For an assignment c of the detections, Δlog w(c) = log (1/S) Σ_s exp(``base[s]`` +
    Σ_d ``log_lik[s, d, c_d]``): ``base`` (S,) holds the class-independent part (the closed-form
    geometric evidence, or the sampled geometric likelihood of ``paper_mc``), ``log_lik``
    (S, D, M) the semantic log-likelihoods. One set of samples serves every assignment, so sums over
    the classes of some detections are exact marginals of the children's weights.
    """

    base: Array
    log_lik: Array

    def log_means(self, assignments: IntArray) -> Array:
        """Δlog w per assignment: (A, D) class indices → (A,)."""
        d_count = self.log_lik.shape[1]
        if d_count == 0:
            total = np.broadcast_to(self.base[:, None], (len(self.base), len(assignments)))
        else:
            picked = self.log_lik[:, np.arange(d_count)[None, :], assignments]  # (S, A, D)
            total = self.base[:, None] + picked.sum(axis=2)
        return np.asarray(logsumexp(total, axis=0) - np.log(len(self.base)))


def geo_conditioned_samples(
    g: InvolvedGaussian,
    terms: SemanticTerms,
    model: ClassifierModel,
    num_samples: int,
    rng: np.random.Generator,
) -> SampledEvidence:
    """Default estimator: closed-form geometric evidence × Monte Carlo of the semantic term over
    the geometry-conditioned Gaussian (an exact rewrite of the integral)."""
    post_info = g.info + g.jac.T @ g.jac
    chol_post = _cholesky_lower(post_info)
    chol_prior = _cholesky_lower(g.info)
    jtb = g.jac.T @ g.rhs
    mean = solve_triangular(chol_post.T, solve_triangular(chol_post, jtb, lower=True), lower=False)
    # log N(b; 0, S) with S = J Λ⁻¹ Jᵀ + I, by Woodbury and the determinant lemma.
    quad = float(g.rhs @ g.rhs - jtb @ mean)
    log_det_s = _log_det_chol(chol_post) - _log_det_chol(chol_prior)
    log_geo = -0.5 * quad - 0.5 * log_det_s + g.geo_log_norm
    if len(terms.z) == 0:
        return SampledEvidence(np.array([log_geo]), np.zeros((1, 0, model.num_classes)))
    eps = rng.standard_normal((num_samples, len(mean)))
    delta = mean + solve_triangular(chol_post.T, eps.T, lower=False).T
    log_lik = semantic_log_likelihoods(model, _retract_samples(g.lin, delta), terms)
    return SampledEvidence(np.full(num_samples, log_geo), log_lik)


def geo_conditioned_batch(
    gs: Sequence[InvolvedGaussian],
    terms: SemanticTerms,
    model: ClassifierModel,
    eps: Array,
) -> tuple[Array, Array]:
    """:func:`geo_conditioned_samples` for several parents that share the detections ``terms``
    (same involved variables, same order), vectorised over the parents: ``base`` (P, S) and
    ``log_lik`` (P, S, D, M). ``eps`` (S, n): the standard normal draws, the same for every
    parent (common random numbers): what each parent would get from
    :func:`geo_conditioned_samples` with a generator that draws these ``eps``.

    Pruning compares the weights of children of different parents, and parents differ little
    in their Gaussians over the involved variables (docs/estimator.md, "Weights"): with the
    same draws their Monte Carlo errors largely cancel in those comparisons, which independent
    draws per parent would not."""
    info = np.stack([g.info for g in gs])
    jac = np.stack([g.jac for g in gs])
    rhs = np.stack([g.rhs for g in gs])
    post = info + np.swapaxes(jac, 1, 2) @ jac
    chol_post = np.linalg.cholesky(0.5 * (post + np.swapaxes(post, 1, 2)))
    chol_prior = np.linalg.cholesky(0.5 * (info + np.swapaxes(info, 1, 2)))
    jtb = np.einsum("pmn,pm->pn", jac, rhs)
    mean = np.linalg.solve(post, jtb[..., None])[..., 0]
    quad = np.einsum("pm,pm->p", rhs, rhs) - np.einsum("pn,pn->p", jtb, mean)
    diag_post = np.log(np.diagonal(chol_post, axis1=1, axis2=2)).sum(axis=1)
    diag_prior = np.log(np.diagonal(chol_prior, axis1=1, axis2=2)).sum(axis=1)
    log_geo = -0.5 * quad - (diag_post - diag_prior) + np.array([g.geo_log_norm for g in gs])
    m = model.num_classes
    if len(terms.z) == 0:
        return log_geo[:, None], np.zeros((len(gs), 1, 0, m))
    p, n = mean.shape
    num_samples = len(eps)
    if eps.shape != (num_samples, n):
        raise ValueError(f"eps has shape {eps.shape}, the parents need (S, {n})")
    # δ = μ + L⁻ᵀε for the posterior information L Lᵀ; in rows, εᵀ L⁻¹.
    delta = mean[:, None, :] + eps[None, :, :] @ np.linalg.inv(chol_post)
    lin = np.stack([g.lin for g in gs])  # (P, v, 3)
    tangent = delta.reshape(p, num_samples, -1, 3)
    psi = sampled_viewpoints(lin, tangent, terms.robot_var, terms.object_var)
    z = np.asarray(terms.z, dtype=float)
    log_lik = all_log_likelihoods(model, z, psi.reshape(p * num_samples, -1))
    base = np.broadcast_to(log_geo[:, None], (p, num_samples))
    return base, log_lik.reshape(p, num_samples, len(z), m)


def geo_conditioned(
    g: InvolvedGaussian,
    terms: SemanticTerms,
    assignments: IntArray,
    model: ClassifierModel,
    num_samples: int,
    rng: np.random.Generator,
) -> Array:
    """:func:`geo_conditioned_samples` evaluated for every assignment: Δlog w (A,)."""
    return geo_conditioned_samples(g, terms, model, num_samples, rng).log_means(assignments)


def geometric_log_likelihoods(
    poses: Array, robot_var: IntArray, object_var: IntArray, z_geo: Array, cov: Array
) -> Array:
    """Σ_d log N(Logmap(z_d⁻¹ · x⁻¹o); 0, Σ_geo) per sample: poses (S, v, 3) → (S,)."""
    rel = se2.between(poses[:, robot_var, :], poses[:, object_var, :])  # (S, D, 3)
    r = se2.local(z_geo[None, :, :], rel)
    info = np.linalg.inv(cov)
    _, log_det = np.linalg.slogdet(2.0 * np.pi * cov)
    quad = np.einsum("sdi,ij,sdj->sd", r, info, r)
    return np.asarray(np.sum(-0.5 * quad - 0.5 * log_det, axis=1))


def paper_mc_samples(
    g: InvolvedGaussian,
    terms: SemanticTerms,
    geo_terms: tuple[IntArray, IntArray, Array, Array],
    model: ClassifierModel,
    num_samples: int,
    rng: np.random.Generator,
) -> SampledEvidence:
    """The paper's literal estimator: sample the involved variables from the propagated belief and
    average L_geo · L_sem. Unbiased but noisy for newly seen objects."""
    chol = _cholesky_lower(g.info)
    eps = rng.standard_normal((num_samples, g.info.shape[0]))
    delta = solve_triangular(chol.T, eps.T, lower=False).T
    poses = _retract_samples(g.lin, delta)
    robot_var, object_var, z_geo, geo_cov = geo_terms
    log_geo = geometric_log_likelihoods(poses, robot_var, object_var, z_geo, geo_cov)  # (S,)
    if len(terms.z) == 0:
        return SampledEvidence(log_geo, np.zeros((num_samples, 0, model.num_classes)))
    return SampledEvidence(log_geo, semantic_log_likelihoods(model, poses, terms))


def paper_mc(
    g: InvolvedGaussian,
    terms: SemanticTerms,
    geo_terms: tuple[IntArray, IntArray, Array, Array],
    assignments: IntArray,
    model: ClassifierModel,
    num_samples: int,
    rng: np.random.Generator,
) -> Array:
    """:func:`paper_mc_samples` evaluated for every assignment: Δlog w (A,)."""
    samples = paper_mc_samples(g, terms, geo_terms, model, num_samples, rng)
    return samples.log_means(assignments)
