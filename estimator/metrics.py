"""Evaluation of an estimate against ground truth (design doc §8), for both estimators: the hybrid
belief's metrics, and the consistency measures every study shares — NEES and its χ² bounds (from
scipy). Pure functions of arrays.

Over 300 lines for a reason: every figure the studies and the launches report is defined here,
side by side (errors, calibration, consistency, the mixture moments the viewers draw), so that
all of them score a belief the same way."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from estimator.hybrid import BeliefSnapshot
from estimator.models import se2

Array = NDArray[np.float64]

# The per-step metrics every study reports (docs/results.md).
METRICS = (
    "msde",
    "robot_error",
    "object_error",
    "robot_sqrt_det",
    "object_sqrt_det",
    "robot_nees",
    "object_nees",
    "robot_nees_mixture",
    "object_nees_mixture",
    "class_log_loss",
    "class_ece",
    "hypotheses",
)

# Per-step metrics that compare one belief with another of the same robot and step, on the
# objects both know (docs/results.md, "Against another belief"): the largest |ΔP| of a class
# marginal against the centralized belief, the centralized belief's class log-loss on this
# belief's objects, the largest |ΔP| against the centralized belief over what this robot received,
# and this belief's class log-loss on the objects the robot's local belief knows.
# A method's own class_log_loss is over its own objects: a belief that knows more objects than
# another is scored on harder ones too, and these say how the two compare on the same ones.
CROSS_METRICS = (
    "class_gap_central",
    "class_log_loss_centralized_here",
    "class_gap_received",
    "class_log_loss_local_objects",
)

# Equal-width bins on [0, 1] of the class expected calibration error.
ECE_BINS = 10

# Variance floor (m², rad²) of :func:`nees` for a covariance that may be singular: a collapsed
# particle set (one particle copied N times, P = 0) is reported as overconfident, not hidden.
NEES_VARIANCE_FLOOR = 1e-12

# A probability below this is clipped before the log-loss, so a pruned true class costs a large
# but finite amount.
_MIN_PROBABILITY = 1e-12


def msde(prob: Array, true_classes: NDArray[np.int64]) -> float:
    """Eq. 24: (1/|O|) Σ_j (1/M) Σ_i (1[c_j = i] − P(c_j = i))²; NaN when no object is known."""
    if len(true_classes) == 0:
        return float("nan")
    m = prob.shape[1]
    onehot = true_classes[:, None] == np.arange(m)[None, :]
    return float(np.mean(np.sum((onehot - prob) ** 2, axis=1) / m))


def class_log_loss(prob: Array, true_classes: NDArray[np.int64]) -> float:
    """Mean −log P(c_j = true class) over known objects; NaN when none is known."""
    if len(true_classes) == 0:
        return float("nan")
    p = prob[np.arange(len(true_classes)), true_classes]
    return float(np.mean(-np.log(np.maximum(p, _MIN_PROBABILITY))))


def class_comparison(
    ids: Sequence[int],
    prob: Array,
    other_ids: Sequence[int],
    other_prob: Array,
    true_classes: Mapping[int, int],
) -> tuple[float, float, float]:
    """One belief's class marginals ``prob`` (n, M) over objects ``ids`` against another's on the
    objects both know: the largest |P − P_other| of any class (NaN when none is shared), and the
    class log-loss of each on those objects (``true_classes``: object id → class index)."""
    where = {j: i for i, j in enumerate(other_ids)}
    shared = [(i, where[j]) for i, j in enumerate(ids) if j in where]
    if not shared:
        return float("nan"), float("nan"), float("nan")
    mine, theirs = (np.array(x, dtype=np.int64) for x in zip(*shared, strict=True))
    truth = np.array([true_classes[ids[i]] for i in mine], dtype=np.int64)
    gap = float(np.max(np.abs(prob[mine] - other_prob[theirs])))
    return gap, class_log_loss(prob[mine], truth), class_log_loss(other_prob[theirs], truth)


def calibration_stats(prob: Array, true_classes: NDArray[np.int64], bins: int = ECE_BINS) -> Array:
    """Per-bin sufficient statistics (3, bins) of every class marginal P(c_j = i), prob (n, M),
    against the true classes (n,): row 0 counts the marginals in the bin, row 1 sums them, row 2
    counts those whose class is the true one. Bin b holds b/bins ≤ p < (b+1)/bins, the last one
    also p = 1. Additive over objects, robots and runs: sum first, then :func:`ece_from_stats`."""
    m = prob.shape[1]
    p = prob.ravel()
    outcome = (true_classes[:, None] == np.arange(m)[None, :]).ravel().astype(float)
    # b/bins is correctly rounded, so p = 0.1 (the same float as 1/10) opens bin 1.
    edges = np.arange(bins + 1) / bins
    b = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, bins - 1)
    return np.stack(
        [
            np.bincount(b, minlength=bins).astype(float),
            np.bincount(b, weights=p, minlength=bins),
            np.bincount(b, weights=outcome, minlength=bins),
        ]
    )


def ece_from_stats(stats: Array) -> Array:
    """ECE = Σ_b (n_b/N) |mean p_b − mean 1[c = i]_b| = Σ_b |Σp_b − Σ1_b| / N from (pooled)
    statistics (..., 3, bins) → (...); NaN where N = 0."""
    n = stats[..., 0, :].sum(axis=-1)
    gap = np.abs(stats[..., 1, :] - stats[..., 2, :]).sum(axis=-1)
    return np.asarray(np.where(n > 0, gap / np.maximum(n, 1.0), np.nan))


def class_ece(prob: Array, true_classes: NDArray[np.int64]) -> float:
    """Expected calibration error of the class marginals prob (n, M) over every object and class
    (:data:`ECE_BINS` bins); NaN when no object is known."""
    return float(ece_from_stats(calibration_stats(prob, true_classes)))


def world_position_cov(pose: Array, cov: Array) -> Array:
    """World-frame 2×2 position covariance R Σ_xy Rᵀ of poses (..., 3) with body-frame tangent
    covariances (..., 3, 3)."""
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    return np.asarray(rot @ cov[..., :2, :2] @ np.swapaxes(rot, -1, -2))


def nees(error: Array, cov: Array, floor: float | None = None) -> Array:
    """Normalised estimation error squared eᵀΣ⁻¹e: error (..., d), cov (..., d, d) → (...).

    With ``floor``, the eigenvalues of the symmetrised Σ are raised to at least ``floor`` before
    inverting, so a singular Σ gives a large NEES instead of an error (see
    :data:`NEES_VARIANCE_FLOOR`)."""
    if floor is None:
        solved = np.linalg.solve(cov, error[..., None])[..., 0]
        return np.asarray(np.einsum("...i,...i->...", error, solved))
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    proj = (np.swapaxes(v, -1, -2) @ error[..., None])[..., 0]
    return np.asarray(np.sum(proj**2 / np.maximum(w, floor), axis=-1))


def pose_nees(estimate: Array, cov: Array, truth: Array) -> Array:
    """NEES of a pose whose covariance lives in the body-frame tangent space (GTSAM's marginals),
    3 dof: e = Logmap(x̂⁻¹ x_gt); estimate (..., 3), cov (..., 3, 3) → (...)."""
    return nees(se2.local(estimate, truth), cov)


def world_pose_nees(mean: Array, cov: Array, truth: Array) -> float:
    """NEES of a pose belief N(mean, cov) in world coordinates (x, y, θ) — a particle filter's
    moments — 3 dof: e = truth − mean with θ wrapped, Σ floored by :data:`NEES_VARIANCE_FLOOR`;
    mean (3,), cov (3, 3), truth (3,)."""
    e = truth - mean
    e[2] = (e[2] + math.pi) % (2 * math.pi) - math.pi
    return float(nees(e, cov, NEES_VARIANCE_FLOOR))


def mixture_position_moments(weights: Array, pose: Array, cov: Array) -> tuple[Array, Array]:
    """Moment match of the hypotheses' world positions: the weighted mean (..., 2) and the
    covariance Σ_h w_h [R Σ^h_xy Rᵀ + (t^h − μ)(t^h − μ)ᵀ] (..., 2, 2), within plus between
    hypotheses; weights (H,), pose (H, ..., 3), cov (H, ..., 3, 3)."""
    w = weights.reshape((-1,) + (1,) * (pose.ndim - 1))
    xy = pose[..., :2]
    mean = np.sum(w * xy, axis=0)
    spread = xy - mean
    within = world_position_cov(pose, cov)
    total = np.sum(w[..., None] * (within + spread[..., :, None] * spread[..., None, :]), axis=0)
    return mean, total


def mixture_moments(weights: Array, poses: Array, covs: Array) -> tuple[Array, Array]:
    """Weighted mean pose (..., 3) and moment-matched world position covariance (..., 2, 2) of
    the hypotheses' Gaussians: weights (H,), poses (H, ..., 3), covs (H, ..., 3, 3).

    x, y and the covariance are :func:`mixture_position_moments`; θ is the
    weighted circular mean.
    """
    w = weights.reshape((-1,) + (1,) * (poses.ndim - 2))
    xy, cov = mixture_position_moments(weights, poses, covs)
    theta = np.arctan2(
        np.sum(w * np.sin(poses[..., 2]), axis=0),
        np.sum(w * np.cos(poses[..., 2]), axis=0),
    )
    return np.concatenate([xy, theta[..., None]], axis=-1), cov


def mixture_position_nees(weights: Array, pose: Array, cov: Array, truth_xy: Array) -> Array:
    """NEES of the world position under the Gaussian-mixture moment match (2 dof).

    weights (H,), pose (H, ..., 3), cov (H, ..., 3, 3), truth_xy (..., 2) → (...).
    """
    mean, total = mixture_position_moments(weights, pose, cov)
    return nees(truth_xy - mean, total)


def with_truth(snap: BeliefSnapshot, true_objects: Mapping[int, object]) -> BeliefSnapshot:
    """``snap`` restricted to the objects that have a ground truth (itself if all of them do),
    its per-object class marginals (``class_probs``) too."""
    keep = [i for i, j in enumerate(snap.object_ids) if j in true_objects]
    if len(keep) == len(snap.object_ids):
        return snap
    return dataclasses.replace(
        snap,
        object_ids=tuple(snap.object_ids[i] for i in keep),
        classes=snap.classes[:, keep],
        class_probs=None if snap.class_probs is None else snap.class_probs[keep],
        object_pose=snap.object_pose[:, keep],
        object_cov=snap.object_cov[:, keep],
    )


def evaluate(
    snap: BeliefSnapshot,
    num_classes: int,
    true_pose: Array,
    true_objects: Mapping[int, tuple[Array, int]],
) -> dict[str, float]:
    """Every metric of :data:`METRICS` for one robot of one belief at one step.

    ``true_pose`` (3,) is the robot's true pose; ``true_objects`` maps object id → (pose (3,),
    class index). Object metrics are NaN while the belief knows no object. Objects the belief
    holds but the world does not (a phantom: a forged slot or frame) have no error to measure and
    are left out of the object metrics (:func:`with_truth`). The class metrics score
    :meth:`BeliefSnapshot.marginals` (a belief's per-object ``class_probs`` when it has them).
    """
    snap = with_truth(snap, true_objects)
    w = snap.weights
    top = int(np.argmax(w))
    out: dict[str, float] = {"hypotheses": float(len(w))}
    robot_xy_err = np.hypot(*(snap.robot_pose[:, :2] - true_pose[:2]).T)
    out["robot_error"] = float(w @ robot_xy_err)
    robot_pos_cov = world_position_cov(snap.robot_pose, snap.robot_cov)
    out["robot_sqrt_det"] = float(w @ np.sqrt(np.linalg.det(robot_pos_cov)))
    out["robot_nees"] = float(pose_nees(snap.robot_pose[top], snap.robot_cov[top], true_pose))
    out["robot_nees_mixture"] = float(
        mixture_position_nees(w, snap.robot_pose, snap.robot_cov, true_pose[:2])
    )
    n = len(snap.object_ids)
    if n == 0:
        for key in ("msde", "class_log_loss", "class_ece", "object_error", "object_sqrt_det"):
            out[key] = float("nan")
        out["object_nees"] = out["object_nees_mixture"] = float("nan")
        return out
    truth = np.array([true_objects[j][0] for j in snap.object_ids])
    true_classes = np.array([true_objects[j][1] for j in snap.object_ids], dtype=np.int64)
    prob = snap.marginals(num_classes)
    out["msde"] = msde(prob, true_classes)
    out["class_log_loss"] = class_log_loss(prob, true_classes)
    out["class_ece"] = class_ece(prob, true_classes)
    err = np.hypot(*(snap.object_pose[..., :2] - truth[None, :, :2]).transpose(2, 0, 1))  # (H, n)
    out["object_error"] = float(np.mean(w @ err))
    obj_pos_cov = world_position_cov(snap.object_pose, snap.object_cov)
    out["object_sqrt_det"] = float(np.mean(w @ np.sqrt(np.linalg.det(obj_pos_cov))))
    top_e = snap.object_pose[top, :, :2] - truth[:, :2]
    top_cov = obj_pos_cov[top]
    out["object_nees"] = float(np.mean(nees(top_e, top_cov)))
    out["object_nees_mixture"] = float(
        np.mean(mixture_position_nees(w, snap.object_pose, snap.object_cov, truth[:, :2]))
    )
    return out


def evaluate_calibration(
    snap: BeliefSnapshot, num_classes: int, true_objects: Mapping[int, tuple[Array, int]]
) -> Array:
    """:func:`calibration_stats` (3, :data:`ECE_BINS`) of one robot's belief at one step, the
    poolable counterpart of ``evaluate(...)["class_ece"]``; zeros while no object is known."""
    snap = with_truth(snap, true_objects)
    true_classes = np.array([true_objects[j][1] for j in snap.object_ids], dtype=np.int64)
    prob = snap.marginals(num_classes)
    return calibration_stats(prob, true_classes)


def chi2_bounds(dof: int, runs: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds of the average NEES over ``runs`` runs of a ``dof``-dimensional error:
    the ANEES of a consistent estimator lies inside with ``probability``."""
    # Imported here: scipy.stats takes 0.3 s to import, and every process that scores a belief
    # imports this module.
    from scipy.stats import chi2

    tail = (1.0 - probability) / 2.0
    return float(chi2.ppf(tail, dof * runs) / runs), float(chi2.ppf(1.0 - tail, dof * runs) / runs)


def chi2_bound(dof: int, probability: float = 0.99) -> float:
    """The upper bound of one NEES of a ``dof``-dimensional error: a consistent estimator's NEES
    stays below it with ``probability`` (χ²₃ 99 %: 11.34)."""
    from scipy.stats import chi2

    return float(chi2.ppf(probability, dof))
