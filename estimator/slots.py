"""What a robot shares: its local belief summarised per class realisation (Eq. 18, design doc §4).

For every hypothesis of the LOCAL belief: ξ, the joint Gaussian over all the owner's object poses
with the object priors divided out exactly (information form Λ, η about the linearisation poses
``lin``), and log φ = log w − Σ_j log P(c_j). The joint marginal comes from the iSAM2 Bayes tree of
the hypothesis' continuous belief; its mean is iSAM2's current Δ at the linearisation point.
Hypotheses that share a continuous belief share one ξ (computed once). A per-object belief with
``BeliefConfig.xi = "sparse"`` sends the conservative sparse form of its ξ instead
(``estimator.sparse_xi``), rounded to float32 as it travels; ``"auto"`` (the default) does so
for a slot of more than ``SPARSE_XI_ABOVE`` objects.

A per-object belief may be summarised at other poses than its own (``at``: the owner's fused
estimate, ``BeliefConfig.slot_linearisation``): its factors are linearised there and every
other variable eliminated, so that ξ is the same information about the objects, taken where
the receivers' estimates are. Its own estimate must not be implausible under its own data:
if the fused estimate costs L's factors more than ``FIT_SIGMAS`` standard deviations of a χ²
over L's dimensions above L's own optimum, ξ is taken at L's point and the refusal counted
(``HybridBelief.slot_fit_refused``): a poisoned D never bends what the owner shares. Where ξ
is taken at the fused estimate, so is the class evidence (``BeliefConfig.slot_evidence``): the
ledger's detections' viewpoints read there (``SemanticLedger.moved_to``).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np
from numpy.typing import NDArray

from estimator.factors import is_object_key, object_array, object_key, object_prior
from estimator.hybrid import (
    SPARSE_XI_ABOVE,
    BeliefConfig,
    Continuous,
    HybridBelief,
    distinct_continuous,
)
from estimator.sparse_xi import SparseXi, sparsify
from estimator.summary import LocalSummary, ObjectClasses, Realisation, Xi

Array = NDArray[np.float64]

# Eigenvalues of Λ below this fraction of the largest are raised to it: ξ must stay a proper
# Gaussian after the prior division even when an object is barely constrained.
EIGEN_FLOOR = 1e-9

# A class ruled out by more than this many nats against an object's most probable class is held
# here in a slot (P ≤ e^-1000: no difference to any probability, and the wire's bound on log φ
# holds however long the mission).
PHI_FLOOR = -1000.0

# How far above L's own optimum the fused estimate may put L's factors' χ² before a slot is taken
# at L's point instead: this many standard deviations of a χ² with L's dimensions (plus a floor
# of ``FIT_FLOOR`` for the smallest maps). An honest fused estimate moves L by what L cannot
# see (its drift), which its factors hardly pay for; a poisoned one pays orders of magnitude.
FIT_SIGMAS = 10.0
FIT_FLOOR = 100.0


def summarise(belief: HybridBelief, at: gtsam.Values | None = None) -> LocalSummary | None:
    """ξ and log φ for every hypothesis of ``belief`` (per-object classes: the one ξ and every
    object's class log φ); None while it knows no object. ``at`` (per-object classes; ignored
    for joint ones): the poses at which ξ is linearised (keys it lacks are taken at the belief's
    estimate); None: at the belief's own linearisation point."""
    if not belief.object_ids:
        return None
    ids = tuple(belief.object_ids)
    dim = belief.model.objects.dim
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(
        np.array(belief.config.object_prior_sigmas[:dim])
    )
    if belief.per_object:
        cont = belief.hypotheses[0].continuous
        taken = None if at is None else _marginal_at(belief, cont, ids, prior_noise, at)
        evidence = belief.log_evidence
        if taken is None:
            xi = _prior_divided_marginal(cont, ids, prior_noise)
        else:
            xi, values = taken
            if cont.ledger is not None and belief.config.slot_evidence == "fused":
                index = {j: i for i, j in enumerate(ids)}
                evidence = evidence + cont.ledger.moved_to(values, belief.model.classifier, index)
        shared: Xi | SparseXi = (
            _sparse(belief, ids, xi) if sends_sparse(belief.config, len(ids)) else xi
        )
        return LocalSummary(ids, (), ObjectClasses(object_log_phi(evidence), shared))
    log_prior = np.log(np.asarray(belief.model.class_prior, dtype=float))
    conts, which = distinct_continuous(belief.hypotheses)
    xis = [_prior_divided_marginal(c, ids, prior_noise) for c in conts]
    # Σ_j log P(c_j) of every hypothesis, summed left to right as Python's sum over its classes
    # would (a cumulative sum is sequential): log φ to the bit.
    prior_sum = np.cumsum(log_prior[belief.class_matrix()], axis=1)[:, -1].tolist()
    out = []
    for h, g, p in zip(belief.hypotheses, which, prior_sum, strict=True):
        out.append(Realisation(h.classes, h.log_weight - p, xis[g]))
    return LocalSummary(ids, tuple(out))


def sends_sparse(config: BeliefConfig, n: int) -> bool:
    """Whether a per-object slot of ``n`` objects carries the sparse ξ (``BeliefConfig.xi``)."""
    return config.xi == "sparse" or (config.xi == "auto" and n > SPARSE_XI_ABOVE)


def linearisation_point(fused: HybridBelief) -> gtsam.Values | None:
    """Where its owner's slot is linearised (``BeliefConfig.slot_linearisation``): the fused
    belief's estimate for a per-object belief set to ``"fused"``, else None (L's own point)."""
    if not fused.per_object or fused.config.slot_linearisation != "fused":
        return None
    return fused.hypotheses[0].continuous.isam.calculateEstimate()


def object_log_phi(log_evidence: Array) -> Array:
    """A slot's per-object class log φ from a belief's class log-evidence L (n, M): each row
    moved so that its largest entry is 0 (the posterior is unchanged: L is defined up to a
    constant per object), and a class ruled out beyond ``PHI_FLOOR`` nats held there, so that
    the numbers stay bounded over any mission. Read-only."""
    phi = log_evidence - log_evidence.max(axis=1, keepdims=True)
    phi = np.maximum(phi, PHI_FLOOR)
    phi.flags.writeable = False
    return phi


def _sparse(belief: HybridBelief, ids: tuple[int, ...], xi: Xi) -> SparseXi:
    """The conservative sparse form of ``xi`` in float32 (``SparseXi.float32``: the values that
    travel, still ⪯ Λ). The Bayes net of the previous one is reused while the belief's objects
    are the same, in the same order (only the values are recomputed: safe whatever the net;
    fitting it is about a third of the cost); a new object fits a new one, with
    ``BeliefConfig.xi_parents`` parents beyond each object's tree parent."""
    held = belief.xi_structure
    structure = held[1] if held is not None and held[0] == ids else None
    sx = sparsify(xi, belief.config.xi_parents, structure)
    assert sx.structure is not None  # sparsify always says which net it used
    belief.xi_structure = (ids, sx.structure)
    return sx.float32()


def _prior_divided_marginal(
    h: Continuous, ids: Sequence[int], prior_noise: gtsam.noiseModel.Base
) -> Xi:
    keys = [object_key(j) for j in ids]
    joint = h.isam.jointMarginalInformation(gtsam.KeyVector(keys))
    info = np.asarray(joint.fullMatrix())  # blocks in the order of ``keys``
    delta = h.isam.getDelta()
    mean = np.concatenate([delta.at(k) for k in keys])
    eta = info @ mean
    return _without_priors(h, ids, prior_noise, h.isam.getLinearizationPoint(), info, eta)


def _marginal_at(
    belief: HybridBelief,
    h: Continuous,
    ids: Sequence[int],
    prior_noise: gtsam.noiseModel.Base,
    at: gtsam.Values,
) -> tuple[Xi, gtsam.Values] | None:
    """The prior-divided marginal on the objects ``ids`` of ``h``'s factors linearised at
    ``at`` (the belief's estimate where ``at`` lacks a key): every other variable eliminated
    from the linearised graph, what is left read as [Λ η]. None (and the refusal counted) when
    ``at`` does not fit the belief's own data (``FIT_SIGMAS``)."""
    graph = h.isam.getFactorsUnsafe()
    estimate = h.isam.calculateEstimate()
    values = gtsam.Values()
    point = h.object_dim == 2
    for key in estimate.keys():  # noqa: SIM118 - gtsam.Values is not iterable
        source = at if at.exists(key) else estimate
        values.insert(
            key, source.atPoint2(key) if point and is_object_key(key) else source.atPose2(key)
        )
    excess = 2.0 * (graph.error(values) - graph.error(estimate))
    dims = values.dim()
    belief.slot_fit = excess / dims
    if not excess <= dims + max(FIT_SIGMAS * np.sqrt(2.0 * dims), FIT_FLOOR):
        belief.slot_fit_refused += 1
        return None
    keys = [object_key(j) for j in ids]
    objects = set(keys)
    others = gtsam.Ordering()
    for key in sorted(k for k in values.keys() if k not in objects):  # noqa: SIM118
        others.push_back(key)  # the robot poses, in step order: a chain
    linear = graph.linearize(values)
    if others.size():
        linear = linear.eliminatePartialMultifrontal(others)[1]
    order = gtsam.Ordering()
    for key in keys:
        order.push_back(key)
    augmented = np.asarray(linear.augmentedHessian(order))
    n = h.object_dim * len(keys)
    info, eta = augmented[:n, :n].copy(), augmented[:n, n].copy()
    return _without_priors(h, ids, prior_noise, values, info, eta), values


def _without_priors(
    h: Continuous,
    ids: Sequence[int],
    prior_noise: gtsam.noiseModel.Base,
    values: gtsam.Values,
    info: Array,
    eta: Array,
) -> Xi:
    """ξ at ``values`` from the marginal [Λ η] on the objects ``ids`` (in place): each object's
    weak prior, linearised there, divided out, tiny eigenvalues floored."""
    d = h.object_dim
    lin = np.empty((len(ids), d))
    for i, j in enumerate(ids):
        key = object_key(j)
        lin[i] = object_array(values, key, d)
        prior = object_prior(key, h.object_priors[j], prior_noise)
        a, b = prior.linearize(values).jacobian()
        block = slice(d * i, d * i + d)
        info[block, block] -= a.T @ a
        eta[block] -= a.T @ b
    return Xi(lin, _floor_eigenvalues(info), eta)


def _floor_eigenvalues(info: Array) -> Array:
    sym = 0.5 * (info + info.T)
    vals, vecs = np.linalg.eigh(sym)
    floor = EIGEN_FLOOR * max(float(vals[-1]), 1e-300)
    if vals[0] >= floor:
        return sym
    return np.asarray((vecs * np.maximum(vals, floor)) @ vecs.T)
