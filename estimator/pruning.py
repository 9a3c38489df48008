"""Which hypotheses a hybrid belief keeps (docs/estimator.md, "Hypothesis management").

A belief's class posterior is a weighted set of joint class realisations. Pruning on the *joint*
weight ratio alone (the paper's rule, ``"ratio"``) is irreversible for the classes it removes: a
class of one object that dips below ``w_max / ratio`` once, because the realisations carrying it
are combined with unlikely classes of *other* objects, is gone for good, however strongly later
evidence favours it. The default ``"marginal"`` rule judges a realisation by what it contributes
to the per-object class marginals P(c_j = i) as well:

- kept if its joint weight is within ``prune_ratio`` of the heaviest (the paper's rule), or
- kept if, for one of its objects j, it carries at least ``1 / marginal_ratio`` of the marginal
  P(c_j = c_hj) of its own class for that object — the realisations that make up a class marginal
  survive even when that class is combined with unlikely classes elsewhere, and
- the heaviest realisation carrying class i of object j is always kept while P(c_j = i) ≥
  ``class_floor`` (support: no class with non-negligible probability loses its last carrier).

The cap ``max_hypotheses`` keeps the support representatives first, then cuts by marginal
contribution (the largest share of one of its class marginals a realisation carries), not by joint
weight. Pure numpy: the caller passes log-weights and the class matrix of the candidates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

PRUNINGS = ("marginal", "ratio")


@dataclass(frozen=True, slots=True)
class PruningRule:
    """The parameters of :func:`select` (copied from ``BeliefConfig``)."""

    strategy: str
    prune_ratio: float
    marginal_ratio: float
    class_floor: float
    max_hypotheses: int


def class_marginals(weights: Array, classes: IntArray, num_classes: int) -> Array:
    """P(c_j = i) (n, M) from normalised weights (K,) and realisations (K, n)."""
    out = np.zeros((classes.shape[1], num_classes))
    for i in range(num_classes):
        out[:, i] = weights @ (classes == i)
    return out


def select(
    log_weights: Array,
    classes: IntArray,
    num_classes: int,
    rule: PruningRule,
    reference: float | None = None,
) -> IntArray:
    """Indices (ascending) of the candidates to keep: log-weights (K,), classes (K, n) → (k,).

    The heaviest candidate always survives; non-finite log-weights never do. ``reference``, if
    given, replaces the heaviest log-weight in the joint ratio rule: partial children (whose
    weights are sums over their completions) are compared with the weight of a full child, so that
    no partial child is dropped whose completions the final rule would keep.
    """
    finite = np.isfinite(log_weights)
    if not finite.any():
        return np.zeros(0, dtype=np.int64)
    lw = np.where(finite, log_weights, -np.inf)
    best = float(lw.max())
    w = np.exp(lw - best)
    w /= w.sum()
    top = best if reference is None else min(best, reference)
    keep = lw >= top - np.log(rule.prune_ratio)
    protected = np.zeros(len(lw), dtype=bool)
    protected[int(np.argmax(lw))] = True
    score = w.copy()
    if rule.strategy == "marginal" and classes.shape[1] > 0:
        marg = class_marginals(w, classes, num_classes)
        own = marg[np.arange(classes.shape[1])[None, :], classes]  # (K, n): P(c_j = c_hj)
        score = w / np.maximum(own.min(axis=1), 1e-300)
        keep |= score >= 1.0 / rule.marginal_ratio
        protected |= _support(w, classes, marg, rule.class_floor)
    keep &= finite
    keep |= protected
    score[int(np.argmax(lw))] = np.inf
    if keep.sum() > rule.max_hypotheses:
        keep = _cap(keep, protected, score, w, rule.max_hypotheses)
    return np.flatnonzero(keep).astype(np.int64)


def _support(w: Array, classes: IntArray, marg: Array, floor: float) -> NDArray[np.bool_]:
    """The heaviest carrier of every (object, class) whose marginal is at least ``floor``."""
    out = np.zeros(len(w), dtype=bool)
    order = np.argsort(-w, kind="stable")
    ranked = classes[order]  # (K, n), heaviest first
    for j in range(classes.shape[1]):
        for i in np.flatnonzero(marg[j] >= floor):
            out[order[int(np.argmax(ranked[:, j] == i))]] = True
    return out


def _cap(
    keep: NDArray[np.bool_],
    protected: NDArray[np.bool_],
    score: Array,
    w: Array,
    cap: int,
) -> NDArray[np.bool_]:
    """At most ``cap`` of ``keep``: protected candidates first (heaviest first), then by score."""
    # lexsort: last key is primary — protected first, then higher score, then heavier.
    candidates = np.flatnonzero(keep)
    order = np.lexsort((-w[candidates], -score[candidates], ~protected[candidates]))
    out = np.zeros_like(keep)
    out[candidates[order[:cap]]] = True
    return out
