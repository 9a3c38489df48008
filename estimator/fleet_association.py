"""Association across the fleet (design note "data association", §3; issue 45, item 3): which of a
distributed belief's objects each object of a peer's slot is, when the robots' frames carry no
global ids and every slot holds its owner's robot-local ids.

A receiver keeps, per owner, a mapping owner id → the id of one of its D's objects, stamped with
the slot version it was made from (:class:`OwnerMap`). It is keyed by the slot's *owner* and the
owner's ids, whoever relayed the slot, so a relayed copy maps as the owner's own. Every new
version is matched again (the slot rate):

1. **Cost** of owner object i against D object j: ``d²_ij − 2 log Σ_c p_i(c) p_j(c) / P(c)``,
   d² the Mahalanobis distance of their means under Σ_i + Σ_j (world coordinates), the second
   term the likelihood ratio of "one object" against "two objects" on their class beliefs
   (``class_evidence``). D's side is D *without the owner* (:func:`_without_owner`): the
   owner's class log φ taken out of the rows it maps to, and its ξ's marginal divided out of
   those objects' Gaussians, so a match is judged on the others' evidence only (otherwise a
   match, once made, would vouch for itself).
2. **Gate and assignment**: pairs with d² above χ²_d(1 − α) are out; one-to-one by
   ``scipy.optimize.linear_sum_assignment`` with one dummy per owner object at the gate's cost
   (an object that matches nothing cheaper than the gate is new to D).
3. **Pairwise consistency** (PCM, Mangelson et al. 2018): two matches agree when the relative
   geometry of their owner objects and of their D objects differ by less than χ²_d(1 − α) under
   the sum of the owner's joint covariance and D's; the largest set of matches that agree
   pairwise (a maximum clique) is kept, the rest become unmatched.
4. **Hysteresis**: an owner object keeps its target until ``hold`` consecutive matchings
   propose the same other one; objects new to the mapping take theirs at once.

Objects that match nothing enter D under a *fresh* id (counted down from 2³² − 1, never reused,
sticky per owner object): D is the fleet's map, and the objects only peers have seen are half of
what a fused map is for; leaving them out would give up exactly that. The cost is a duplicate
while the receiver's own detections of such an object are not yet matched to the peer's; the next
version's matching merges them (the fresh object is then *orphaned*, and the node rebuilds D
without it).

A mapping change is undone by the ordinary down-date: D integrates the owner's next version under
the new mapping, which removes the old version's ξ factors (on the old ids) and replaces its log φ
rows. ``DistributedBelief.integrate`` (``estimator.distributed``) calls
:meth:`FleetAssociation.associate` on every batch, so the in-process study and the agents share
this code. Pure: no clock, no randomness.

Over 300 lines for a reason: the two sides' Gaussians and class beliefs, the gated assignment, the
consistency check and the mapping's life are one decision per slot version over one set of
candidates; split, each would need the others' layouts.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import gtsam
import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from estimator.chi2 import chi2_ppf
from estimator.factors import object_key
from estimator.hybrid import Hypothesis
from estimator.logsumexp import logsumexp
from estimator.models import se2
from estimator.smoother import WindowedISAM2
from estimator.sparse_xi import SparseXi
from estimator.summary import LocalSummary, Slot

Array = NDArray[np.float64]

FRESH_TOP = 2**32 - 1  # fresh ids count down from here: the wire's largest object id
_BIG = 1e12  # an assignment cost that is never taken (outside the gate)
_PSD = 1e-9  # relative eigenvalue floor of a divided-out Gaussian


class FusedBelief(Protocol):
    """What the matching reads of a distributed belief (``estimator.distributed``, which
    imports this module): its objects, its class posterior and, per owner, the rows and class
    log φ it holds of that owner's slot."""

    object_ids: list[int]
    object_phi: dict[str, tuple[NDArray[np.int64], Array]]

    def map_hypothesis(self) -> Hypothesis: ...

    def class_log_posterior(self) -> Array: ...


@dataclass(frozen=True, slots=True)
class FleetAssociationConfig:
    """``alpha``: the gates' false-rejection rate (the match gate and PCM's); ``class_evidence``:
    whether the class term enters the cost (off: geometry alone, the baseline); ``pcm``: whether
    matches must agree pairwise; ``hold``: consecutive matchings that must propose another
    target before an owner object moves to it; ``max_cover``: the most inconsistent matches
    PCM's exact search drops (beyond, it drops greedily)."""

    alpha: float = 1e-3
    class_evidence: bool = True
    pcm: bool = True
    hold: int = 2
    max_cover: int = 12

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if self.hold < 1 or self.max_cover < 0:
            raise ValueError("hold must be ≥ 1 and max_cover ≥ 0")


@dataclass(frozen=True, slots=True)
class Objects:
    """One side of a matching in world coordinates: ``ids`` (n,), means (n, d) (x, y[, θ]), their
    joint covariance (n·d, n·d) and class log-probabilities (n, M), each row normalised."""

    ids: tuple[int, ...]
    mean: Array
    cov: Array
    log_p: Array

    @property
    def dim(self) -> int:
        return int(self.mean.shape[1])

    def block(self, i: int) -> Array:
        d = self.dim
        return self.cov[d * i : d * i + d, d * i : d * i + d]


@dataclass(slots=True)
class OwnerMap:
    """One owner's mapping: owner id → D id for the objects of its ``version`` (epoch, stamp);
    ``pending``: owner id → (another proposed D id, consecutive matchings that proposed it)."""

    version: tuple[int, int]
    ids: dict[int, int]
    pending: dict[int, tuple[int, int]] = field(default_factory=dict)


# -- the two sides ------------------------------------------------------------------------------


def _to_world(mean: Array, cov: Array) -> Array:
    """A joint covariance (n·d, n·d) in the objects' tangents (Pose2's body frame, a point's
    world translation) at ``mean`` (n, d), in world coordinates (x, y[, θ])."""
    n, d = mean.shape
    if d == 2:
        return cov
    a = np.zeros((n, 3, 3))
    c, s = np.cos(mean[:, 2]), np.sin(mean[:, 2])
    a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1], a[:, 2, 2] = c, -s, s, c, 1.0
    big = scipy.linalg.block_diag(*a)
    return np.asarray(big @ cov @ big.T)


def _normalised(log_p: Array) -> Array:
    return np.asarray(log_p - np.asarray(logsumexp(log_p, axis=1))[:, None])


def slot_objects(summary: LocalSummary, log_prior: Array) -> Objects:
    """The owner side: a per-object slot's means lin ⊕ Λ⁻¹η, joint covariance Λ⁻¹ and class
    beliefs P(c) φ_i(c), normalised."""
    if summary.per_object is None:
        raise ValueError("fleet association needs per-object slots (BeliefConfig.classes)")
    x = summary.per_object.xi
    dense = x.dense() if isinstance(x, SparseXi) else x
    lin = np.asarray(dense.lin, dtype=float)
    n, d = lin.shape
    info = np.asarray(dense.info, dtype=float)
    cov = np.asarray(scipy.linalg.cho_solve(scipy.linalg.cho_factor(info), np.eye(n * d)))
    delta = (cov @ np.asarray(dense.eta, dtype=float)).reshape(n, d)
    mean = se2.retract(lin, delta) if d == 3 else lin + delta
    log_p = _normalised(log_prior[None, :] + np.asarray(summary.per_object.log_phi, dtype=float))
    return Objects(tuple(summary.object_ids), mean, _to_world(mean, cov), log_p)


def belief_objects(belief: FusedBelief) -> Objects:
    """D's side: its most probable hypothesis' object estimates, their joint marginal covariance
    (one query of the smoother) and D's class posterior."""
    cont = belief.map_hypothesis().continuous
    ids = tuple(belief.object_ids)
    d = cont.object_dim
    mean = np.array([cont.pose(object_key(j)) for j in ids], dtype=float).reshape(len(ids), d)
    if ids:
        isam = cont.isam.isam if isinstance(cont.isam, WindowedISAM2) else cont.isam
        keys = gtsam.KeyVector([object_key(j) for j in ids])
        cov = np.asarray(isam.jointMarginalCovariance(keys).fullMatrix())
    else:
        cov = np.zeros((0, 0))
    return Objects(ids, mean, _to_world(mean, cov), _normalised(belief.class_log_posterior()))


def _wrapped(diff: Array) -> Array:
    if diff.shape[-1] == 3:
        diff = diff.copy()
        diff[..., 2] = se2.wrap_angle(diff[..., 2])
    return diff


def _without_owner(
    d: Objects, owner: Objects, mapped: dict[int, int], owner_phi: Array | None
) -> tuple[Objects, NDArray[np.bool_]]:
    """D without what the owner gave it (module docstring, 1): for every D object the owner maps
    to, the owner's class log φ (``owner_phi`` (n_o, M), rows as ``owner.ids``) subtracted and
    its marginal Gaussian divided out of D's (information form, world coordinates). Returns
    that side and which of its objects are left with information of their own (the others held
    the owner's alone)."""
    index = {j: a for a, j in enumerate(d.ids)}
    at = {i: b for b, i in enumerate(owner.ids)}
    mean, cov, log_p = d.mean.copy(), d.cov.copy(), d.log_p.copy()
    usable = np.ones(len(d.ids), dtype=bool)
    dim = d.dim
    for i, j in mapped.items():
        a, b = index.get(j), at.get(i)
        if a is None or b is None:
            continue
        if owner_phi is not None:
            log_p[a] -= owner_phi[b]
        sl = slice(dim * a, dim * a + dim)
        lam_d = np.linalg.inv(d.block(a))
        lam_o = np.linalg.inv(owner.block(b))
        lam = lam_d - lam_o
        w, v = np.linalg.eigh(0.5 * (lam + lam.T))
        if w[0] <= _PSD * w[-1]:
            usable[a] = False  # (nearly) all D knows of it is the owner's
            continue
        c = (v / w) @ v.T
        o_mean = d.mean[a] + _wrapped(owner.mean[b] - d.mean[a])
        mean[a] = c @ (lam_d @ d.mean[a] - lam_o @ o_mean)
        cov[sl, sl] = c
    return Objects(d.ids, mean, cov, _normalised(log_p)), usable


# -- the matching ----------------------------------------------------------------------------


def same_object_log_ratio(log_p: Array, log_q: Array, log_prior: Array) -> Array:
    """log Σ_c p(c) q(c) / P(c) over the last axis (broadcast): the likelihood ratio of two
    class beliefs p, q (normalised logs) being of one object against two independent ones, each
    with prior P. 0 when either belief is the prior; log 1/P(c) when both are sure of c."""
    return np.asarray(logsumexp(log_p + log_q - log_prior, axis=-1))


def match(
    owner: Objects,
    d: Objects,
    candidates: NDArray[np.bool_],
    log_prior: Array,
    config: FleetAssociationConfig,
) -> dict[int, int]:
    """Owner id → D id for the owner objects that match (module docstring, 1–3); ``candidates``
    (m,): the D objects that may be matched."""
    n, dim = len(owner.ids), owner.dim
    cols = np.flatnonzero(candidates)
    if n == 0 or len(cols) == 0:
        return {}
    gate = chi2_ppf(1.0 - config.alpha, dim)
    o_cov = np.array([owner.block(i) for i in range(n)])
    d_cov = np.array([d.block(int(j)) for j in cols])
    diff = _wrapped(owner.mean[:, None, :] - d.mean[cols][None, :, :])  # (n, c, d)
    s = o_cov[:, None] + d_cov[None, :]
    d2 = np.einsum("ncj,ncj->nc", diff, np.linalg.solve(s, diff[..., None])[..., 0])
    cost = np.where(d2 <= gate, d2, _BIG)
    if config.class_evidence:
        same = same_object_log_ratio(owner.log_p[:, None, :], d.log_p[cols][None, :, :], log_prior)
        cost = np.where(d2 <= gate, d2 - 2.0 * same, _BIG)
    dummy = np.full((n, n), _BIG)
    np.fill_diagonal(dummy, gate)
    from scipy.optimize import linear_sum_assignment  # here: scipy.optimize's import is 0.4 s

    rows, picked = linear_sum_assignment(np.concatenate([cost, dummy], axis=1))
    pairs = [(int(r), int(cols[c])) for r, c in zip(rows, picked, strict=True) if c < len(cols)]
    pairs = [(r, c) for r, c in pairs if d2[r, np.searchsorted(cols, c)] <= gate]
    if config.pcm and len(pairs) > 1:
        pairs = [pairs[a] for a in _consistent(owner, d, pairs, config)]
    return {owner.ids[r]: d.ids[c] for r, c in pairs}


def _pair_cov(side: Objects, idx: Sequence[int]) -> Array:
    """(P, P, d, d): the covariance of x_b − x_a for every pair of the objects ``idx``."""
    dim = side.dim
    sel = np.concatenate([np.arange(dim * i, dim * i + dim) for i in idx])
    joint = side.cov[np.ix_(sel, sel)].reshape(len(idx), dim, len(idx), dim).transpose(0, 2, 1, 3)
    diag = joint[np.arange(len(idx)), np.arange(len(idx))]
    return np.asarray(diag[:, None] + diag[None, :] - joint - joint.transpose(1, 0, 3, 2))


def _consistent(
    owner: Objects, d: Objects, pairs: Sequence[tuple[int, int]], config: FleetAssociationConfig
) -> list[int]:
    """PCM: the indices of the largest set of ``pairs`` (owner row, D row) whose relative
    geometry agrees pairwise in both maps (χ²_d(1 − α) under both maps' joint covariances)."""
    mine = [r for r, _ in pairs]
    theirs = [c for _, c in pairs]
    rel_o = owner.mean[mine][None, :, :] - owner.mean[mine][:, None, :]  # (P, P, d): b − a
    rel_d = d.mean[theirs][None, :, :] - d.mean[theirs][:, None, :]
    e = _wrapped(rel_o - rel_d)
    cov = _pair_cov(owner, mine) + _pair_cov(d, theirs)
    p, dim = len(pairs), owner.dim
    cov = cov + np.eye(dim)[None, None] * np.eye(p)[:, :, None, None]  # the diagonal: unused
    d2 = np.einsum("abi,abi->ab", e, np.linalg.solve(cov, e[..., None])[..., 0])
    bad = ~(d2 <= chi2_ppf(1.0 - config.alpha, dim))
    np.fill_diagonal(bad, False)
    drop = _vertex_cover(bad, config.max_cover)
    return [a for a in range(p) if a not in drop]


def _vertex_cover(bad: NDArray[np.bool_], limit: int) -> set[int]:
    """A smallest set of vertices touching every edge of the graph ``bad`` (P, P) (the
    complement of a maximum clique of agreeing matches): exact by iterative deepening up to
    ``limit`` vertices, then greedy by degree. Deterministic (lowest indices first)."""
    edges = [(int(a), int(b)) for a, b in zip(*np.nonzero(np.triu(bad)), strict=True)]

    def search(left: list[tuple[int, int]], k: int) -> set[int] | None:
        if not left:
            return set()
        if k == 0:
            return None
        a, b = left[0]
        for v in (a, b):
            rest = search([(x, y) for x, y in left if v not in (x, y)], k - 1)
            if rest is not None:
                return {v, *rest}
        return None

    for k in range(min(limit, len(edges)) + 1):
        found = search(edges, k)
        if found is not None:
            return found
    cover: set[int] = set()
    left = edges
    while left:
        degree: dict[int, int] = {}
        for a, b in left:
            degree[a] = degree.get(a, 0) + 1
            degree[b] = degree.get(b, 0) + 1
        v = max(sorted(degree), key=degree.__getitem__)
        cover.add(v)
        left = [(a, b) for a, b in left if v not in (a, b)]
    return cover


# -- the mappings --------------------------------------------------------------------------------


class FleetAssociation:
    """A receiver's mappings of every owner's objects onto its D (module docstring)."""

    def __init__(self, log_prior: Array, config: FleetAssociationConfig | None = None) -> None:
        self.config = config or FleetAssociationConfig()
        self.log_prior = np.asarray(log_prior, dtype=float)
        self.maps: dict[str, OwnerMap] = {}
        self._fresh: dict[tuple[str, int], int] = {}  # (owner, owner id) → its fresh id
        self._origin: dict[int, tuple[str, int]] = {}  # fresh id → (owner, owner id)
        self.changes = 0  # owner objects moved to another D object (hysteresis passed)

    def is_fresh(self, j: int) -> bool:
        return j in self._origin

    def origin(self, j: int) -> tuple[str, int] | None:
        """The (owner, owner id) a fresh D id was made for; None for the receiver's own."""
        return self._origin.get(j)

    def sources(self, j: int) -> set[str]:
        """Who informs D object j: the owners that map to it, and "" for the receiver itself."""
        out = {o for o, m in self.maps.items() if j in m.ids.values()}
        if not self.is_fresh(j):
            out.add("")
        return out

    def associate(
        self, belief: FusedBelief, slots: Sequence[Slot], again: bool = False
    ) -> list[Slot]:
        """Match every slot of a batch against ``belief`` as it is before the batch, update the
        owners' mappings and return the slots with D's ids. ``again``: match versions matched
        before too (:meth:`rematch`)."""
        fresh = [s for s in slots if again or not self._mapped(s)]
        d = belief_objects(belief) if fresh else None
        out = []
        for s in slots:
            if d is None or (self._mapped(s) and not again):
                out.append(self.translate(s))  # a version matched before (D rebuilt)
                continue
            held = self.maps.get(s.owner)
            owner = slot_objects(s.summary, self.log_prior)
            mapped = dict(held.ids) if held is not None else {}
            rows, phi = belief.object_phi.get(s.owner, (None, None))
            owner_phi = None
            if rows is not None and phi is not None and held is not None:
                by_row = {int(r): p for r, p in zip(rows, phi, strict=True)}
                index = {j: a for a, j in enumerate(d.ids)}
                owner_phi = np.zeros((len(owner.ids), len(self.log_prior)))
                for b, i in enumerate(owner.ids):
                    a = index.get(mapped.get(i, -1))
                    if a is not None and a in by_row:
                        owner_phi[b] = by_row[a]
            view, usable = _without_owner(d, owner, mapped, owner_phi)
            others = np.array([bool(self.sources(j) - {s.owner}) for j in d.ids], dtype=bool)
            proposal = match(owner, view, usable & others, self.log_prior, self.config)
            self._update(s, proposal)
            out.append(self.translate(s))
        return out

    def rematch(self, belief: FusedBelief, held: Sequence[Slot]) -> bool:
        """Match the ``held`` slots (each owner's newest version, already integrated) again
        against ``belief``, whose own objects have changed since: whether any mapping changed
        (D must then be rebuilt under the new mappings). A rematch is a matching like any
        other: a move waits for ``hold`` consecutive proposals. Without it an object the
        receiver confirms after a peer's version arrived stays a duplicate of that peer's fresh
        object until the peer's next versions, which a robot out of the peer's range never
        gets."""
        before = {o: dict(m.ids) for o, m in self.maps.items()}
        self.associate(belief, [s for s in held if s.owner in self.maps], again=True)
        return any(self.maps[o].ids != ids for o, ids in before.items())

    def _mapped(self, s: Slot) -> bool:
        held = self.maps.get(s.owner)
        return (
            held is not None
            and held.version == s.version
            and all(i in held.ids for i in s.summary.object_ids)
        )

    def _update(self, s: Slot, proposal: dict[int, int]) -> None:
        """The owner's new mapping from a matching's ``proposal`` (hysteresis, one-to-one)."""
        held = self.maps.get(s.owner) or OwnerMap(s.version, {})
        ids: dict[int, int] = {}
        pending: dict[int, tuple[int, int]] = {}
        order = sorted(s.summary.object_ids, key=lambda i: (i not in held.ids, i))
        for i in order:
            want = proposal.get(i)
            if want is None:
                want = self._fresh_id(s.owner, i)
            current = held.ids.get(i)
            if current is not None and self._origin.get(current) == (s.owner, i) and want < current:
                # Two owners' fresh objects of one true object would each move to the other's
                # and swap forever: only the younger one (a lower id) moves, to the older one.
                want = current if self.is_fresh(want) else want
            if current is None or current == want:
                ids[i] = want
                continue
            before = held.pending.get(i)
            count = before[1] + 1 if before is not None and before[0] == want else 1
            if count >= self.config.hold:
                ids[i] = want
            else:
                ids[i] = current
                pending[i] = (want, count)
        taken: set[int] = set()
        for i in order:  # one-to-one: unchanged targets first, a clash makes a fresh object
            if ids[i] in taken:
                # Its fresh object, or a new one when that is taken too: by this very clash,
                # or by an object of this owner matched onto it since another owner maps there.
                ids[i] = self._fresh_id(s.owner, i)
                if ids[i] in taken:
                    ids[i] = self._fresh_id(s.owner, i, renew=True)
            taken.add(ids[i])
        # the moves that stand (one that clashed went back to a fresh object)
        self.changes += sum(held.ids.get(i, j) != j for i, j in ids.items())
        self.maps[s.owner] = OwnerMap(s.version, ids, pending)

    def _fresh_id(self, owner: str, i: int, renew: bool = False) -> int:
        key = (owner, i)
        if key not in self._fresh or renew:
            j = FRESH_TOP - len(self._origin)
            self._fresh[key] = j
            self._origin[j] = key
        return self._fresh[key]

    def translate(self, s: Slot) -> Slot:
        """``s`` with its objects under D's ids (the owner's current mapping; every object of
        the version it was made from)."""
        held = self.maps[s.owner]
        ids = tuple(held.ids[i] for i in s.summary.object_ids)
        summary = LocalSummary(ids, s.summary.realisations, s.summary.per_object)
        return Slot(s.owner, s.stamp, summary, s.epoch)

    def orphans(self, object_ids: Collection[int]) -> list[int]:
        """Fresh objects of D that no owner maps to any more (D holds only their weak prior)."""
        used = {j for m in self.maps.values() for j in m.ids.values()}
        return [j for j in object_ids if self.is_fresh(j) and j not in used]

    def mapping(self, owner: str) -> dict[int, int]:
        """Owner id → D id of ``owner``'s objects (empty when none is held)."""
        held = self.maps.get(owner)
        return dict(held.ids) if held is not None else {}
