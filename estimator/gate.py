"""The belief gate: whether a received slot is plausible against what the receiver already
believes (docs/distributed.md, "The belief gate"; issue 43, finding 2).

The wire limits bound a slot's numbers absolutely (``protocol.codec.Limits``). A member with a
valid signing key can still send a slot within them that wrecks every receiver: Λ = 10⁹·I on
objects 9 km from where they are. Two tests refuse such a slot; both follow from the sensor
model, and neither needs anything the receiver does not already hold.

1. **Information bound.** A slot's ξ over objects is the owner's measurement information, its
   weak object prior divided out. Each detection factor (``BetweenFactorPose2`` robot → object,
   geometric noise R) gives the object's own block at most R⁻¹ (its Jacobian in the object is the
   identity), a frame detects an object at most once, and marginalising the robot poses only
   lowers the object blocks (a Schur complement). So at the owner's step ``stamp`` every diagonal
   block obeys λmax(Λ_jj) ≤ stamp · λmax(R⁻¹); ``information_margin`` (2) allows for the Logmap
   Jacobian away from a zero residual and for float32 rounding. Honest slots reach at most 0.89 of
   the bound without the margin (a 120-object, 400-step world; 0.44 on the paper's world). Not
   applied when the semantic factors enter the Gaussians (``semantic_poses``): they add
   information of their own.
2. **Mahalanobis gate.** For every object both hold, the slot's estimate m_s = lin ⊕ Λ⁻¹η and the
   receiver's estimate m_D differ by Δ (at the slot's linearisation point). Under the model Δ has
   covariance at most Σ_s + Σ_D (the two share information, which only shrinks it), so
   d² = Δᵀ(Σ_s + Σ_D)⁻¹Δ is at most χ²₃ and the slot is refused when d² exceeds χ²₃'s quantile at
   ``false_alarm`` per object (10⁻⁹: 44.84). The test runs in three stages, each an upper bound
   on the next, so only an object one cannot pass pays for the next: ΔᵀΛ_jjΔ with the slot's
   conditional block (Λ_jj ⪰ Σ_s⁻¹, no solve), d²_s = Δᵀ Σ_s⁻¹ Δ with the slot's marginal
   (three solves of the factored Λ per object), then d² with the receiver's marginal Σ_D. Honest
   slots gave d²_s ≤ 6.9 (5,852 + 393 object checks on the dense and paper worlds); the first
   stage passes 91 % of the dense world's objects.

3. **Class-evidence bound.** A slot's log φ is its owner's class evidence, the prior divided
   out: a sum over the owner's detections of each object, at most one a frame, of log P(z | c, ψ)
   (the ledger's form: the likelihood integrated over ψ when first weighed, moved by its change
   at the current estimate, so three terms each between two classes at one viewpoint or a
   mixture of them). For any scores z the classifier model calls plausible (within χ²_dim's
   quantile at ``false_alarm`` of some class at some viewpoint) one such term separates two
   classes by at most B (:func:`evidence_per_detection`, from the model's means and covariances
   on a grid of viewpoints). So at the owner's step ``stamp`` an object's log φ spans at most
   3 · stamp · B between its classes (a realisation table's log φ, over n objects, n times
   that), and ``information_margin`` again allows for the grid. Not applied with
   ``semantic_poses`` either: realisation weights then carry geometric evidence too.

Objects the receiver does not hold yet pass on the two bounds alone: the receiver has no belief
to test them against, and an owner's slot carries no trajectory to bound where its objects may
lie.

Over 300 lines for a reason: the three tests share the slot's summary and its factored Λ, and
each is a derivation from the sensor or classifier model whose bound and whose check belong
side by side.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from numpy.typing import NDArray

from estimator.chi2 import chi2_isf
from estimator.factors import object_key
from estimator.models import ClassifierModel, se2
from estimator.smoother import marginal_covariances
from estimator.sparse_xi import SparseXi
from estimator.summary import LocalSummary
from estimator.xi import Xi

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class GateSettings:
    """``false_alarm``: the Mahalanobis gate's false-alarm rate per object under the model (0:
    no Mahalanobis gate); ``information_margin``: the factor over the information bound (0: no
    bound)."""

    false_alarm: float = 1e-9
    information_margin: float = 2.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.false_alarm < 1.0:
            raise ValueError(f"false_alarm {self.false_alarm} must be in [0, 1)")
        if not (self.information_margin == 0.0 or self.information_margin >= 1.0):
            raise ValueError(f"information_margin {self.information_margin}: 0 (off) or ≥ 1")


@lru_cache(maxsize=8)
def gate_threshold(false_alarm: float, dim: int = 3) -> float:
    """χ²'s quantile at 1 − ``false_alarm`` with an object's ``dim`` degrees of freedom (3 for
    a pose, 2 for a point)."""
    return chi2_isf(false_alarm, dim)


class Implausible(ValueError):
    """A slot that contradicts the receiver's belief or the sensor model; the message says which
    object and by how much."""


@dataclass(frozen=True, slots=True)
class Held:
    """What the gate reads of the receiver's belief: object id → index into ``pose`` (n, d),
    the receiver's object estimates, and a function that gives the marginal covariances (K, d, d)
    of the objects of given ids (called only for an object the first stage cannot pass)."""

    index: dict[int, int]
    pose: Array
    covariances: Callable[[Sequence[int]], Array]


def held_objects(belief: object) -> Held:
    """:class:`Held` of a belief's most probable hypothesis (a ``HybridBelief``)."""
    cont = belief.map_hypothesis().continuous  # type: ignore[attr-defined]
    ids = list(belief.object_ids)  # type: ignore[attr-defined]
    pose = np.array([cont.pose(object_key(j)) for j in ids]).reshape(len(ids), cont.object_dim)

    def covariances(which: Sequence[int]) -> Array:
        return marginal_covariances(cont.isam, [object_key(j) for j in which])

    return Held({j: i for i, j in enumerate(ids)}, pose, covariances)


VIEWPOINTS = 360  # the grid over ψ ∈ [0, 2π) on which B is read off the classifier model
EVIDENCE_TERMS = 3  # terms of one detection in a slot's log φ (the module docstring, item 3)


_PER_DETECTION: dict[tuple[int, float], tuple[ClassifierModel, float]] = {}


def evidence_per_detection(classifier: ClassifierModel, false_alarm: float) -> float:
    """:func:`per_detection_bound`, kept for the last few models (every node of a fleet shares
    one model object, and a 64-class model takes about a second)."""
    key = (id(classifier), false_alarm)
    held = _PER_DETECTION.get(key)
    if held is not None and held[0] is classifier:
        return held[1]
    bound = per_detection_bound(classifier, false_alarm)
    if len(_PER_DETECTION) >= 8:
        _PER_DETECTION.clear()
    _PER_DETECTION[key] = (classifier, bound)
    return bound


def per_detection_bound(classifier: ClassifierModel, false_alarm: float) -> float:
    """B: how far one detection's log P(z | c, ψ) can separate two classes a, b at one viewpoint
    ψ, for scores z the model calls plausible: z within χ²_dim's quantile g at ``false_alarm``
    of some class c at some viewpoint ψ₀ (the classifier's Gaussian, Σ_c(ψ₀)).

    log P(z|a,ψ) − log P(z|b,ψ) = ½q_b − ½q_a + ½ log(|Σ_b|/|Σ_a|) with q ≥ 0, and
    q_b ≤ ‖z − μ_b(ψ)‖² / λmin(Σ_b(ψ)), ‖z − μ_b(ψ)‖ ≤ ‖μ_c(ψ₀) − μ_b(ψ)‖ + √(g λmax(Σ_c(ψ₀))).
    Every mean lies within r of their centroid, so ‖μ_c(ψ₀) − μ_b(ψ)‖ ≤ 2r. Maxima over the
    classes and :data:`VIEWPOINTS` viewpoints; 0 for a model without classes to tell apart."""
    m, dim = classifier.num_classes, classifier.dim
    if m < 2:
        return 0.0
    psi = np.linspace(0.0, 2.0 * np.pi, VIEWPOINTS, endpoint=False)
    means = np.stack([np.asarray(classifier.mean(c, psi), float) for c in range(m)])
    eig = np.stack([_cov_eigenvalues(np.asarray(classifier.cov(c, psi), float)) for c in range(m)])
    if not np.isfinite(means).all() or not (eig[..., 0] > 0).all():
        raise ValueError("classifier model: means not finite or a covariance not positive")
    points = means.reshape(-1, dim)
    radius = float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())
    reach = 2.0 * radius + math.sqrt(chi2_isf(false_alarm, dim) * float(eig[..., -1].max()))
    logdet = np.log(eig).sum(axis=-1)
    return 0.5 * reach**2 / float(eig[..., 0].min()) + 0.5 * float(logdet.max() - logdet.min())


def _cov_eigenvalues(covs: Array) -> Array:
    """Eigenvalues (K, dim) of one class's covariances (K, dim, dim) over the viewpoints,
    decomposed once when the model holds them constant over ψ (the aliased model: one Σ)."""
    sym = 0.5 * (covs + covs.swapaxes(-1, -2))
    if (sym == sym[:1]).all():
        return np.broadcast_to(np.linalg.eigvalsh(sym[0]), sym.shape[:2])
    return np.asarray(np.linalg.eigvalsh(sym))


def check_classes(
    owner: str, summary: LocalSummary, stamp: int, per_detection: float, margin: float
) -> None:
    """Raise :class:`Implausible` if a slot's class evidence spans more than ``margin`` ×
    :data:`EVIDENCE_TERMS` × ``stamp`` × ``per_detection`` (B) between two classes of an object
    (a realisation table: between two realisations, n times that). ``per_detection`` or
    ``margin`` 0: not applied."""
    if not per_detection or not margin:
        return
    bound = margin * EVIDENCE_TERMS * max(stamp, 1) * per_detection
    what = "its classes"
    if summary.per_object is not None:
        log_phi = np.asarray(summary.per_object.log_phi, dtype=float)
        spans = log_phi.max(axis=1) - log_phi.min(axis=1) if log_phi.size else log_phi[:, 0]
    else:
        rows = summary.realisations
        log_phi = np.asarray([r.log_phi for r in rows] if isinstance(rows, tuple) else rows.log_phi)
        spans = np.array([np.ptp(log_phi)]) if len(log_phi) else np.zeros(0)
        bound *= max(len(summary.object_ids), 1)
        what = "its realisations"
    bad = np.flatnonzero(~(spans <= bound))
    if len(bad):
        b = int(bad[np.argmax(np.nan_to_num(spans[bad], nan=np.inf))])
        which = f"object {summary.object_ids[b]}" if summary.per_object is not None else "table"
        raise Implausible(
            f"slot of {owner}: {which} has class evidence spanning {spans[b]:.3g} nats between "
            f"{what}, above what {stamp} steps of detections can give ({bound:.3g})"
        )


def _block_lmax(blocks: Array) -> Array:
    """λmax of each symmetric d × d block (n, d, d) → (n,)."""
    return np.asarray(np.linalg.eigvalsh(0.5 * (blocks + blocks.swapaxes(1, 2)))[:, -1], float)


def _diag_blocks(x: Xi | SparseXi) -> Array:
    if isinstance(x, SparseXi):
        return np.asarray(x.diag_info, dtype=float)
    n, d = len(x.lin), x.dim
    info = x.info.reshape(n, d, n, d)
    idx = np.arange(n)
    return info[idx, :, idx, :]


class _Solver:
    """Λ of a ξ factored once: its mean offset δ = Λ⁻¹η and, for chosen objects only, the
    diagonal blocks of Λ⁻¹ (each from d solves, never the whole inverse)."""

    def __init__(self, x: Xi | SparseXi) -> None:
        n, d = len(x.lin), x.dim
        self.n, self.d = n, d
        if isinstance(x, SparseXi):
            base = d * np.arange(n)
            r3, c3 = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
            edges = np.asarray(x.edges, dtype=np.intp).reshape(-1, 2)
            diag = np.asarray(x.diag_info, dtype=float).reshape(n, d, d)
            off = np.asarray(x.edge_info, dtype=float).reshape(len(edges), d, d)
            i, j = edges[:, 0], edges[:, 1]
            rows = np.concatenate(
                [
                    (base[:, None, None] + r3).ravel(),
                    (base[i][:, None, None] + r3).ravel(),
                    (base[j][:, None, None] + r3).ravel(),
                ]
            )
            cols = np.concatenate(
                [
                    (base[:, None, None] + c3).ravel(),
                    (base[j][:, None, None] + c3).ravel(),
                    (base[i][:, None, None] + c3).ravel(),
                ]
            )
            vals = np.concatenate([diag.ravel(), off.ravel(), off.swapaxes(1, 2).ravel()])
            lam = scipy.sparse.csc_matrix((vals, (rows, cols)), (d * n, d * n))
            self._solve = scipy.sparse.linalg.splu(lam).solve
        else:
            factor = scipy.linalg.lu_factor(np.asarray(x.info, dtype=float), check_finite=True)
            self._solve = lambda rhs: scipy.linalg.lu_solve(factor, rhs)
        self.delta = np.asarray(self._solve(np.asarray(x.eta, dtype=float))).reshape(n, d)

    def marginals(self, which: NDArray[np.intp]) -> Array:
        """The diagonal blocks (K, d, d) of Λ⁻¹ for the objects ``which``."""
        d = self.d
        rhs = np.zeros((d * self.n, d * len(which)))
        cols = np.arange(d * len(which))
        rhs[(d * np.repeat(which, d) + np.tile(np.arange(d), len(which))), cols] = 1.0
        sol = np.asarray(self._solve(rhs)).reshape(self.n, d, len(which), d)
        return sol[which, :, np.arange(len(which)), :]


def _mean_and_marginals(x: Xi | SparseXi) -> tuple[Array, Array]:
    """δ = Λ⁻¹η (n, d) and the diagonal blocks of Λ⁻¹ (n, d, d)."""
    solver = _Solver(x)
    return solver.delta, solver.marginals(np.arange(solver.n))


def check_xi(
    owner: str,
    object_ids: Sequence[int],
    x: Xi | SparseXi,
    stamp: int,
    held: Held | None,
    geometric_info: float,
    settings: GateSettings,
) -> None:
    """Raise :class:`Implausible` if ξ breaks the information bound (``geometric_info`` =
    λmax(R⁻¹); 0: not applied) or the Mahalanobis gate against ``held`` (None: not applied)."""
    if settings.information_margin and geometric_info > 0:
        bound = settings.information_margin * max(stamp, 1) * geometric_info
        blocks = _diag_blocks(x)
        # λmax ≤ trace for a positive semi-definite block (the codec refuses a Λ that is not:
        # κ(Λ) ≤ max_condition), so most slots pass on the trace alone.
        trace = np.trace(blocks, axis1=1, axis2=2)
        lmax = _block_lmax(blocks) if not (trace <= bound).all() else trace
        worst = int(np.argmax(lmax)) if len(lmax) else -1
        if worst >= 0 and not lmax[worst] <= bound:
            raise Implausible(
                f"slot of {owner}: object {object_ids[worst]} has information λmax "
                f"{lmax[worst]:.3g}, above what {stamp} steps of detections can give "
                f"({bound:.3g} = {settings.information_margin:g} × {max(stamp, 1)} × "
                f"{geometric_info:.3g})"
            )
    if held is None or not settings.false_alarm:
        return
    shared = [(i, held.index[j]) for i, j in enumerate(object_ids) if j in held.index]
    if not shared:
        return
    mine, theirs = (np.array(v, dtype=np.intp) for v in zip(*shared, strict=True))
    try:
        solver = _Solver(x)
    except (np.linalg.LinAlgError, RuntimeError, ValueError) as exc:
        raise Implausible(f"slot of {owner}: its ξ cannot be solved ({exc})") from exc
    lin = np.asarray(x.lin, dtype=float)[mine]
    if x.dim == 3:
        diff = _local(lin, held.pose[theirs]) - solver.delta[mine]
        diff[:, 2] = se2.wrap_angle(diff[:, 2])
    else:  # a point's tangent is its world translation
        diff = held.pose[theirs] - lin - solver.delta[mine]
    threshold = gate_threshold(settings.false_alarm, x.dim)
    # Three stages, each an upper bound on the last, so that only the objects a stage cannot
    # pass pay for the next: the slot's conditional information Λ_jj ⪰ Σ_s⁻¹ (no solve), the
    # slot's marginal Σ_s (three solves per object), then Σ_s + Σ_D (the receiver's marginal).
    conditional = np.einsum("ki,kij,kj->k", diff, _diag_blocks(x)[mine], diff)
    left = np.flatnonzero(~(conditional <= threshold))
    if not len(left):
        return
    sigma_s = solver.marginals(mine[left])
    second = _quadratic(sigma_s, diff[left])
    keep = np.flatnonzero(~(second <= threshold))
    if not len(keep):
        return
    left, sigma_s = left[keep], sigma_s[keep]
    ids = [int(object_ids[mine[s]]) for s in left]
    cov_d = np.asarray(held.covariances(ids))
    third = _quadratic(sigma_s + cov_d, diff[left])
    bad = np.flatnonzero(~(third <= threshold))
    if len(bad):
        b = int(bad[np.argmax(np.nan_to_num(third[bad], nan=np.inf))])
        raise Implausible(
            f"slot of {owner}: object {ids[b]} lies at Mahalanobis d² {third[b]:.3g} from this "
            f"robot's belief (gate {threshold:.3g}, false alarm {settings.false_alarm:g} per "
            f"object); {len(bad)} of {len(shared)} shared objects fail"
        )


def _local(p: Array, q: Array) -> Array:
    """``se2.local(p, q)`` (Logmap(p⁻¹ ∘ q)) for (K, 3) arrays in a few whole-array operations:
    the gate calls it once per slot version, mostly on a handful of objects, where the general
    routine's per-call overhead dominated (0.3 ms of its 0.8 ms per check, lanes world)."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    dx, dy = q[:, 0] - p[:, 0], q[:, 1] - p[:, 1]
    x, y = c * dx + s * dy, c * dy - s * dx
    t = se2.wrap_angle(q[:, 2] - p[:, 2])
    half = t / 2.0
    small = np.abs(t) < se2.SMALL_ANGLE
    half_safe = np.where(small, 1.0, half)
    a = np.where(small, 1.0 - t * t / 12.0, half_safe / np.tan(half_safe))
    return np.stack([a * x + half * y, -half * x + a * y, t], axis=1)


def _quadratic(cov: Array, diff: Array) -> Array:
    """diffᵀ cov⁻¹ diff per row, (K, d, d) and (K, d) → (K,); infinite where cov is singular."""
    try:
        return np.einsum("ki,ki->k", diff, np.linalg.solve(cov, diff[..., None])[..., 0])
    except np.linalg.LinAlgError:
        pass
    out = np.full(len(diff), np.inf)
    for i, (c, d) in enumerate(zip(cov, diff, strict=True)):
        with contextlib.suppress(np.linalg.LinAlgError):
            out[i] = float(d @ np.linalg.solve(c, d))
    return out


def check_summary(
    owner: str,
    summary: LocalSummary,
    stamp: int,
    held: Held | None,
    geometric_info: float,
    settings: GateSettings,
    per_detection: float = 0.0,
) -> None:
    """:func:`check_classes` (``per_detection``: B of :func:`evidence_per_detection`; 0: not
    applied) and :func:`check_xi` on every distinct ξ of a slot's summary."""
    check_classes(owner, summary, stamp, per_detection, settings.information_margin)
    if summary.per_object is not None:
        xis: list[Xi | SparseXi] = [summary.per_object.xi]
    else:
        xis = list(summary.distinct_xi()[0])
    for x in xis:
        check_xi(owner, summary.object_ids, x, stamp, held, geometric_info, settings)
