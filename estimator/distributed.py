"""The distributed belief D (Eq. 12, 17, 19, 20; design doc §6).

D is a hybrid belief over its owner's trajectory and every object it knows of, from its own data
or from other robots' slots. Integrating a newer version of robot i's slot multiplies in its ξ and
φ and divides out the version used before: the old ξ factor leaves iSAM2 (``downdate="remove"``) or
is cancelled by its negation (``"anti"``, DDF-SAM 2.0), and its log φ is subtracted. With
``fusion="double_count"`` neither happens: the paper's double-counting baseline.

Over 300 lines for a reason: the join, the ξ factors, the version replacement (both downdate
modes), the rebuild and their bookkeeping act on the same hypotheses and must stay consistent with
each other (docs/distributed.md); the slot summary itself is :mod:`estimator.slots`.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.factors import object_key, object_prior, object_value
from estimator.fleet_association import FleetAssociation
from estimator.hybrid import (
    BeliefConfig,
    BeliefModel,
    Continuous,
    HybridBelief,
    Hypothesis,
    UsedXi,
    distinct_continuous,
)
from estimator.sparse_xi import SparseXi
from estimator.summary import Realisations, Slot, Xi

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

log = logging.getLogger(__name__)

FUSIONS = ("consistent", "double_count")
DOWNDATES = ("remove", "anti")

# Between two slots of one batch the join keeps at most this many times max_hypotheses candidates;
# ratio pruning and the cap proper apply once, after the whole batch.
_JOIN_GUARD = 20
_FITS_CELLS = 4_000_000  # booleans compared at once when matching hypotheses with realisations


class SlotError(ValueError):
    """A slot cannot be integrated: it contradicts this belief (wrong class count, bad shapes)."""


@dataclass(frozen=True, slots=True)
class FusionStats:
    """What one integration did: slots integrated, slots skipped (empty join), hypotheses.

    ``empty_joins`` counts slots whose join with D's hypotheses was empty and ``rebuilds`` the
    times D was rebuilt from its local data and every held slot because of one; ``completed``
    the hypotheses of D that no realisation of a slot matched and that were joined with their
    nearest realisations instead (:func:`_nearest`)."""

    integrated: tuple[str, ...]
    skipped: tuple[str, ...]
    candidates: int
    kept: int
    empty_joins: int = 0
    rebuilds: int = 0
    completed: int = 0


@dataclass(frozen=True, slots=True)
class _Join:
    """Candidate children of a fusion: parent index (J,), classes of D's objects followed by the
    objects new to D (J, n'), log-weights (J,), the ids of the objects new to D in column order,
    and how each row came to be (``steps``), from which :meth:`picks_and_phis` gives the
    realisation picked from every slot of the batch (J, B; −1 for none) and the log φ each child
    takes from every slot (J, B: the picked realisation's, or its completion's,
    :func:`_nearest`). Those two are made once, for the rows that survive: copied at every slot
    and every pruning of a join of up to ``max_join`` rows, they cost more than the join.

    A step is (rows, b, cols, phi): row i of the join after it is row ``rows[i]`` of the join
    before it, and took realisation ``cols[i]`` of slot ``b`` with log φ ``phi[i]`` (b = −1: a
    pruning, rows only)."""

    parent: IntArray
    classes: IntArray
    log_weight: Array
    order: list[int]
    width: int  # B, the slots of the batch
    steps: tuple[tuple[IntArray, int, IntArray | None, Array | None], ...] = ()

    def keep(self, kept: IntArray, log_weight: Array | None = None) -> _Join:
        return _Join(
            self.parent[kept],
            self.classes[kept],
            self.log_weight[kept] if log_weight is None else log_weight,
            self.order,
            self.width,
            (*self.steps, (kept, -1, None, None)),
        )

    def picks_and_phis(self) -> tuple[IntArray, Array]:
        """The realisation picked from every slot (J, B; −1 for none) and each child's log φ of
        every slot (J, B; NaN for none), followed back through the steps."""
        picks = np.full((len(self.parent), self.width), -1, dtype=np.int64)
        phis = np.full((len(self.parent), self.width), np.nan)
        at = np.arange(len(self.parent))
        for rows, b, cols, phi in reversed(self.steps):
            if cols is not None and phi is not None:
                picks[:, b] = cols[at]
                phis[:, b] = phi[at]
            at = rows[at]
        return picks, phis


def _fits(parent: IntArray, real: IntArray) -> tuple[IntArray, IntArray]:
    """(row, realisation) pairs whose classes agree on every shared column: ``parent`` (J, s)
    against ``real`` (R, s), rows ascending and each row's realisations ascending (the order of
    ``np.nonzero`` on the (J, R) table of matches, which :func:`_fits_by_table` builds).

    Each row's classes of the shared objects are one key (their digits in base M), so the
    matches are found by sorting the R keys and looking up the J: O((J + R) log R + matches)
    instead of J·R·s comparisons (a join of 6,000 rows with 100 realisations on 7 objects)."""
    j, r, width = parent.shape[0], real.shape[0], parent.shape[1]
    if j == 0 or r == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if width == 0:  # nothing shared: every pair
        return np.repeat(np.arange(j), r), np.tile(np.arange(r), j)
    low = min(int(parent.min()), int(real.min()))
    base = max(int(parent.max()), int(real.max())) + 1
    if low < 0 or width * math.log2(base) >= 62:
        return _fits_by_table(parent, real)
    digits = base ** np.arange(width, dtype=np.int64)
    keys = real.astype(np.int64) @ digits
    order = np.argsort(keys, kind="stable")  # equal keys keep their realisations ascending
    ranked = keys[order]
    wanted = parent.astype(np.int64) @ digits
    first = np.searchsorted(ranked, wanted, side="left")
    counts = np.searchsorted(ranked, wanted, side="right") - first
    rows = np.repeat(np.arange(j), counts)
    starts = np.repeat(first - (np.cumsum(counts) - counts), counts)
    return rows, order[starts + np.arange(len(rows))]


def _fits_by_table(parent: IntArray, real: IntArray) -> tuple[IntArray, IntArray]:
    """:func:`_fits` by comparing every row with every realisation, in chunks of rows so that no
    temporary exceeds _FITS_CELLS (for classes whose keys would not fit 62 bits)."""
    j, r = parent.shape[0], real.shape[0]
    step = max(1, _FITS_CELLS // max(1, r * max(1, parent.shape[1])))
    rows, cols = [], []
    for first in range(0, j, step):
        block = np.all(parent[first : first + step, None, :] == real[None, :, :], axis=2)
        b_rows, b_cols = np.nonzero(block)
        rows.append(b_rows + first)
        cols.append(b_cols)
    if not rows:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(rows), np.concatenate(cols)


def _nearest(
    parent: IntArray, real: IntArray, fresh: IntArray, log_phi: Array, unmatched: IntArray
) -> tuple[IntArray, IntArray, Array]:
    """Completion of a truncated slot for the rows of D that no realisation matches.

    A slot carries the heaviest class realisations of its owner, and D the heaviest of its own
    product: two truncated supports can miss each other on the shared objects although each
    holds every class that matters (a row of D whose combination of the shared objects the
    owner's newest version no longer carries would be dropped, and with it, possibly, the last
    carrier of a class). Such a row is joined with its nearest realisations instead — those that
    differ from it on the fewest shared objects — and log φ moved, for every object where they
    differ, by the slot's own evidence for the row's class against the realisation's:
    log Σ_{r: c_j = a} φ_r − log Σ_{r: c_j = b} φ_r, exact when the owner's class posterior
    factorises over those objects (with one continuous belief, the objects' classes couple only
    through the Monte Carlo draws a step's objects share). A class that no realisation carries
    has no evidence (−inf): a row needing it is not completed, so a slot that rules a class out
    still does. Nearest realisations that give a row the same classes of the objects new to it
    (``fresh`` (R, f)) estimate one child's log φ: it is their mean, and the heaviest of them
    stands for the child (its ξ). ``parent`` (J, s) and ``real`` (R, s) are the classes of the
    shared objects. Returns (row, realisation) pairs, one per child, and each child's log φ.
    """
    empty = np.zeros(0, dtype=np.int64)
    if len(unmatched) == 0 or parent.shape[1] == 0 or len(real) == 0:
        return empty, empty, np.zeros(0)
    m = int(max(parent.max(), real.max())) + 1
    evidence = np.full((real.shape[1], m), -np.inf)  # (s, M): log Σ φ over carriers of each class
    for k in range(real.shape[1]):
        for c in np.unique(real[:, k]):
            evidence[k, c] = np.logaddexp.reduce(log_phi[real[:, k] == c])
    cols = np.arange(real.shape[1])
    theirs = evidence[cols[None, :], real]  # (R, s)
    step = max(1, _FITS_CELLS // max(1, len(real) * parent.shape[1]))
    rows_out, cols_out, estimates = [], [], []
    for first in range(0, len(unmatched), step):
        rows = unmatched[first : first + step]
        ours = evidence[cols[None, :], parent[rows]]  # (U, s)
        differ = parent[rows][:, None, :] != real[None, :, :]  # (U, R, s)
        change = np.where(differ, ours[:, None, :] - theirs[None, :, :], 0.0).sum(axis=2)
        usable = np.isfinite(change)
        distance = np.where(usable, differ.sum(axis=2), parent.shape[1] + 1)
        nearest = (distance == distance.min(axis=1, keepdims=True)) & usable
        u, r = np.nonzero(nearest)
        rows_out.append(rows[u])
        cols_out.append(r)
        estimates.append(log_phi[r] + change[u, r])
    row, col, estimate = (np.concatenate(x) for x in (rows_out, cols_out, estimates))
    if len(row) == 0:
        return empty, empty, np.zeros(0)
    child_key = np.concatenate([row[:, None], fresh[col]], axis=1)
    _, child = np.unique(child_key, axis=0, return_inverse=True)
    child = child.reshape(-1)
    mean = np.bincount(child, estimate) / np.bincount(child)
    # The heaviest realisation of each child: sort by (child, −log φ), take the first of each.
    order = np.lexsort((-log_phi[col], child))
    first_of = order[np.r_[True, child[order][1:] != child[order][:-1]]]
    return row[first_of], col[first_of], mean[child[first_of]]


def xi_factor(keys: Sequence[int], r: Xi, sign: float = 1.0) -> gtsam.LinearContainerFactor:
    """ξ as a GTSAM factor on the object ``keys``: an n-key HessianFactor (summed
    from unary and pairwise pieces; Python constructors stop at three keys) wrapped in a
    LinearContainerFactor at ``r.lin``. ``sign = −1`` gives the anti-factor."""
    n, d = len(keys), r.dim
    info, eta = sign * r.info, sign * r.eta
    pieces = gtsam.GaussianFactorGraph()
    zero = np.zeros((d, d))
    for i in range(n):
        bi = slice(d * i, d * i + d)
        pieces.add(gtsam.HessianFactor(keys[i], info[bi, bi], eta[bi], 0.0))
        for j in range(i + 1, n):
            bj = slice(d * j, d * j + d)
            pieces.add(
                gtsam.HessianFactor(
                    keys[i], keys[j], zero, info[bi, bj], np.zeros(d), zero, np.zeros(d), 0.0
                )
            )
    lin = gtsam.Values()
    for key, pose in zip(keys, r.lin, strict=True):
        lin.insert(key, object_value(pose))
    return gtsam.LinearContainerFactor(gtsam.HessianFactor(pieces), lin)


def sparse_xi_factors(
    keys: Sequence[int], sx: SparseXi, sign: float = 1.0
) -> list[gtsam.LinearContainerFactor]:
    """A sparse ξ as GTSAM factors on the object ``keys`` whose sum is
    ``xi_factor(keys, sx.dense(), sign)``: one factor per group of :func:`clique_groups`, each
    a HessianFactor over a few objects that the pattern of Λ_s already links pairwise, in a
    LinearContainerFactor at ``sx.lin``. Eliminated, they fill in nothing the pattern does not
    hold, where one n-key factor is one clique of all n objects. ``sign = −1``: the
    anti-factors."""
    n = len(keys)
    if len(sx.lin) != n:
        raise ValueError(f"{n} keys for a ξ of {len(sx.lin)} objects")
    d = sx.dim
    diag, edge_info, eta = sign * sx.diag_info, sign * sx.edge_info, sign * sx.eta.reshape(n, d)
    edges = np.asarray(sx.edges).tolist()
    # One linearisation point for every group: a LinearContainerFactor keeps only its own
    # keys' values (copied in C++, not inserted one by one from Python).
    lin = gtsam.Values()
    for key, pose in zip(keys, np.asarray(sx.lin, dtype=float), strict=True):
        lin.insert(key, object_value(pose))
    out = []
    for members, edge_ids, objs in _groups(n, np.asarray(sx.edges, dtype=np.intp)):
        at = {v: a for a, v in enumerate(objs)}
        k = len(objs)
        blocks = np.zeros((k, k, d, d))
        g = np.zeros((k, d))
        for v in members:
            blocks[at[v], at[v]] = diag[v]
            g[at[v]] = eta[v]
        for e in edge_ids:
            i, j = edges[e]
            blocks[at[i], at[j]] = edge_info[e]
        factor = _hessian([keys[v] for v in objs], blocks, g)
        out.append(gtsam.LinearContainerFactor(factor, lin))
    return out


# A sender keeps its Bayes net, hence its slots' edges, while its objects stay the same, and a
# receiver builds the factors of every version it takes: the grouping of the last patterns is
# kept rather than recomputed (about a third of the factors' cost at 70–80 objects). Bounded.
_GROUPS_KEPT = 64


_Group = tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]


def _groups(n: int, edges: IntArray) -> tuple[_Group, ...]:
    """:func:`clique_groups` of (n, ``edges``), each group with its sorted objects (members,
    edges, objects), from a bounded cache keyed by the pattern's bytes (read-only tuples)."""
    return _groups_cached(n, np.ascontiguousarray(edges, dtype=np.int64).tobytes())


@functools.lru_cache(maxsize=_GROUPS_KEPT)
def _groups_cached(n: int, edges: bytes) -> tuple[_Group, ...]:
    pairs = np.frombuffer(edges, dtype=np.int64).reshape(-1, 2)
    listed = pairs.tolist()
    return tuple(
        (
            tuple(members),
            tuple(edge_ids),
            tuple(sorted({*members, *(v for e in edge_ids for v in listed[e])})),
        )
        for members, edge_ids in clique_groups(n, pairs)
    )


def _hessian(keys: Sequence[int], blocks: Array, g: Array) -> gtsam.HessianFactor:
    """The HessianFactor ½ δᵀGδ − gᵀδ on up to four ``keys`` from its upper blocks (k, k, d, d)
    (``blocks[a, b]`` for a ≤ b; the lower ones are their transposes) and g (k, d). GTSAM's
    Python constructors stop at three keys: a fourth is added as two more factors."""
    k, d = len(keys), blocks.shape[-1]
    b, z, none = blocks, np.zeros((d, d)), np.zeros(d)
    if k == 1:
        return gtsam.HessianFactor(keys[0], b[0, 0], g[0], 0.0)
    if k == 2:
        return gtsam.HessianFactor(keys[0], keys[1], b[0, 0], b[0, 1], g[0], b[1, 1], g[1], 0.0)
    k0, k1, k2 = keys[:3]
    head = gtsam.HessianFactor(
        k0, k1, k2, b[0, 0], b[0, 1], b[0, 2], g[0], b[1, 1], b[1, 2], g[1], b[2, 2], g[2], 0.0
    )
    if k == 3:
        return head
    if k != 4:
        raise ValueError(f"a factor of {k} keys (at most 4)")
    pieces = gtsam.GaussianFactorGraph()
    pieces.add(head)
    # the fourth key's blocks: with the first two keys, then with the third
    pieces.add(
        gtsam.HessianFactor(
            keys[3], keys[0], keys[1], b[3, 3], b[0, 3].T, b[1, 3].T, g[3], z, z, none, z, none, 0.0
        )
    )
    pieces.add(gtsam.HessianFactor(keys[2], keys[3], z, b[2, 3], none, z, none, 0.0))
    return gtsam.HessianFactor(pieces)


def clique_groups(n: int, edges: IntArray, size: int = 4) -> list[tuple[list[int], list[int]]]:
    """The blocks of a sparse ξ over n objects grouped into factors: (objects whose diagonal
    block it takes, edges (rows of ``edges``) it takes). Every group's objects are pairwise
    linked by ``edges`` (a clique of the pattern, at most ``size`` objects), so a group's factor
    adds no link the pattern lacks; each diagonal block and edge is in exactly one group.
    Greedy, edges in their order: an edge joins the first group holding one of its objects
    that stays a clique with the other, else starts a group; an object's diagonal block goes
    with its first group (its own if it has no edge). Deterministic: sender and receiver, or
    two fusions, group one pattern alike."""
    linked = {(int(i), int(j)) for i, j in edges.tolist()}
    groups: list[tuple[list[int], list[int]]] = []
    member_sets: list[set[int]] = []
    of: list[list[int]] = [[] for _ in range(n)]  # object → its groups
    for e, (i, j) in enumerate(edges.tolist()):
        home = -1
        for g in of[i] + of[j]:
            objs = member_sets[g]
            other = j if i in objs else i
            if other in objs:
                home = g
                break
            if len(objs) < size and all((min(other, o), max(other, o)) in linked for o in objs):
                home = g
                break
        if home < 0:
            home = len(groups)
            groups.append(([], []))
            member_sets.append(set())
        groups[home][1].append(e)
        for v in (i, j):
            if v not in member_sets[home]:
                member_sets[home].add(v)
                of[v].append(home)
    for v in range(n):
        if not of[v]:
            of[v].append(len(groups))
            groups.append(([], []))
            member_sets.append({v})
        groups[of[v][0]][0].append(v)
    return groups


class _XiFactors:
    """The ξ factors of one fusion, built once per (ξ, sign) however many continuous beliefs
    take that ξ: a factor is never changed once built, and iSAM2 only holds a pointer to it (it
    relinearises into new factors), so continuous beliefs can share it. A dense ξ is one factor,
    a sparse one a few per object (:func:`sparse_xi_factors`)."""

    def __init__(self) -> None:
        self._built: dict[
            tuple[int, float], tuple[Xi | SparseXi, list[gtsam.LinearContainerFactor]]
        ] = {}

    def get(
        self, object_ids: Sequence[int], r: Xi | SparseXi, sign: float = 1.0
    ) -> list[gtsam.LinearContainerFactor]:
        key = (id(r), sign)
        if key not in self._built:  # the ξ is kept too, so its id is never reused
            keys = [object_key(j) for j in object_ids]
            if isinstance(r, SparseXi):
                factors = sparse_xi_factors(keys, r, sign)
            else:
                factors = [xi_factor(keys, r, sign)]
            self._built[key] = (r, factors)
        return self._built[key][1]


class DistributedBelief(HybridBelief):
    """D of robot ``owner``: its own data, plus every other robot's latest slot (never its own)."""

    def __init__(
        self,
        model: BeliefModel,
        owner: str,
        start: ArrayLike,
        config: BeliefConfig | None = None,
        fusion: str = "consistent",
        downdate: str = "remove",
    ) -> None:
        if fusion not in FUSIONS:
            raise ValueError(f"fusion {fusion!r} (known: {', '.join(FUSIONS)})")
        if downdate not in DOWNDATES:
            raise ValueError(f"downdate {downdate!r} (known: {', '.join(DOWNDATES)})")
        super().__init__(model, {owner: start}, config)
        self.owner = owner
        self.fusion = fusion
        self.downdate = downdate
        # Owner → (epoch, stamp) of the slot version D used (Slot.version).
        self.versions: dict[str, tuple[int, int]] = {}
        self._incoming: set[str] = set()  # owners of the batch being integrated
        # Per-object classes: owner → (rows in ``object_ids``, log φ (n_i, M)) of the class
        # evidence D holds of that robot — its newest version's (consistent fusion: replacing
        # it divides out the version used before, Eq. 20 per object), or the sum of every
        # version's (double counting).
        self.object_phi: dict[str, tuple[IntArray, Array]] = {}
        self._completed = 0  # rows of the join being built that were completed (_nearest)
        # Slots of robot-local ids (frames without global ids): every batch is matched onto
        # D's objects and integrated under D's ids (estimator.fleet_association).
        self.association: FleetAssociation | None = None

    @property
    def stamps(self) -> dict[str, int]:
        """Owner → stamp of the slot version D used (for people; compare ``versions``)."""
        return {o: v[1] for o, v in self.versions.items()}

    def information_sources(self) -> int:
        """The owner and every robot whose slot D holds or is integrating."""
        return 1 + len(set(self.versions) | self._incoming)

    def class_log_posterior(self) -> Array:
        """Per-object classes: the prior, D's own evidence and every held robot's log φ."""
        out = np.array(super().class_log_posterior())
        for rows, phi in self.object_phi.values():
            out[rows] += phi
        return out

    def orphans(self) -> list[int]:
        """Objects that entered from a slot under a fresh id and that no slot maps to any more
        (a changed mapping, ``estimator.fleet_association``): D holds only their weak prior, and
        a rebuild leaves them out. None under double counting, which keeps old ξ factors."""
        if self.association is None or self.fusion != "consistent":
            return []
        return self.association.orphans(self.object_ids)

    def wants(self, owner: str, version: tuple[int, int]) -> bool:
        """Whether a slot version (epoch, stamp) is new to this belief (never its own slot)."""
        return owner != self.owner and version > self.versions.get(owner, (-1, -1))

    def integrate(self, slots: Sequence[Slot], settle: bool = True) -> FusionStats:
        """Integrate every slot that is newer than the version used before (Eq. 12, 17).

        ``settle`` runs the configured extra iSAM2 updates after the fusion; a caller that steps
        D right away (the RobotNode) passes False, since that step updates iSAM2 again. A slot
        whose join with D's hypotheses is empty is left out and counted in ``empty_joins``: the
        caller decides whether to :meth:`rebuild` (the RobotNode does).
        """
        batch = [s for s in slots if self.wants(s.owner, s.version)]
        owners = [s.owner for s in batch]
        if len(set(owners)) != len(owners):
            raise SlotError(f"two versions of one robot's slot in one batch: {owners}")
        for s in batch:
            self.check(s)
        if not batch:
            return FusionStats((), (), 0, len(self.hypotheses))
        if self.association is not None:
            batch = self.association.associate(self, batch)
        self._incoming = set(owners)
        try:
            if self.per_object:
                return self._integrate_per_object(batch, settle)
            return self._integrate(batch, settle)
        finally:
            self._incoming = set()

    def _integrate_per_object(self, batch: list[Slot], settle: bool) -> FusionStats:
        """Per-object classes: every slot's ξ into the one continuous belief (its version used
        before divided out, as for a realisation), every slot's class log φ replacing the one
        D held of its owner (added to it under double counting). No join: nothing to leave out.
        """
        new: list[int] = []
        for s in batch:
            for j in s.summary.object_ids:
                if j not in self._object_index and j not in new:
                    new.append(j)
        for j in new:
            self._object_index[j] = len(self.object_ids)
            self.object_ids.append(j)
        grown = np.zeros((len(self.object_ids), self.model.num_classes))
        grown[: len(self.log_evidence)] = self.log_evidence
        self.log_evidence = grown
        cont = self.hypotheses[0].continuous
        picks = [(b, 0) for b in range(len(batch))]
        self._fuse(cont, picks, batch, new, settle, _XiFactors())
        n, m = len(self.object_ids), self.model.num_classes
        for s in batch:
            per_object = s.summary.per_object
            assert per_object is not None  # check() refused any other slot
            rows = np.array([self._object_index[j] for j in s.summary.object_ids], dtype=np.int64)
            phi = np.asarray(per_object.log_phi, dtype=float)
            held = self.object_phi.get(s.owner)
            if self.fusion == "double_count" and held is not None:
                total = np.zeros((n, m))
                known = np.zeros(n, dtype=bool)
                for r, p in (held, (rows, phi)):
                    total[r] += p
                    known[r] = True
                rows = np.flatnonzero(known)
                phi = total[rows]
            self.object_phi[s.owner] = (rows, phi)
            self.versions[s.owner] = s.version
        self._set_map_classes()
        owners = tuple(s.owner for s in batch)
        return FusionStats(owners, (), 1, 1)

    def _integrate(self, batch: list[Slot], settle: bool) -> FusionStats:
        join, skipped = self._join(batch)
        used = tuple(s.owner for s in batch if s.owner not in skipped)
        self._incoming = set(used)  # the budget counts the robots D will hold
        if not used:
            return FusionStats(
                (),
                tuple(sorted(skipped)),
                0,
                len(self.hypotheses),
                len(skipped),
                0,
                self._completed,
            )
        candidates = len(join.parent)
        join = join.keep(*self._prune(join.log_weight, join.classes))
        parents = self.hypotheses
        for j in join.order:
            self._object_index[j] = len(self.object_ids)
            self.object_ids.append(j)
        # Children that continue one continuous belief with the same ξ of every slot share
        # one continuous belief: fused once, copied only where the ξ differ. A group is keyed by
        # the parent's continuous belief and the ξ picked from every slot (by their indices
        # among the distinct ones: the same ξ object, the same index), in order of first child.
        conts, cont_of = distinct_continuous(parents)
        key = np.empty((len(join.parent), 1 + len(batch)), dtype=np.int64)
        key[:, 0] = np.asarray(cont_of, dtype=np.int64)[join.parent]
        picked, phis = join.picks_and_phis()
        for b, sl in enumerate(batch):
            which = np.asarray(sl.summary.distinct_xi()[1], dtype=np.int64)
            r = picked[:, b]
            key[:, 1 + b] = np.where(r >= 0, which[np.maximum(r, 0)], -1)
        _, first, group_of = np.unique(key, axis=0, return_index=True, return_inverse=True)
        group_of = group_of.reshape(-1)
        order = np.argsort(first, kind="stable")  # groups in order of their first child
        last_of_cont = {int(key[first[g], 0]): g for g in order}  # the last group of a belief
        classes_of = join.classes.tolist()
        log_weight_of = join.log_weight.tolist()
        picks_of = picked.tolist()
        parent_of = join.parent.tolist()
        # Every row of the join picked a realisation of every slot that joined (a row that
        # matched none was dropped) and none of a skipped one: log φ per row of the used slots.
        used_cols = [b for b, sl in enumerate(batch) if sl.owner not in skipped]
        used_owners = [batch[b].owner for b in used_cols]
        if not (picked[:, used_cols] >= 0).all():
            raise AssertionError("a row of the join lacks a pick of a slot that joined")
        phis_of = phis[:, used_cols].tolist()
        children: dict[int, Hypothesis] = {}
        xi = _XiFactors()
        for g in order:
            members = np.flatnonzero(group_of == g).tolist()
            c = int(key[first[g], 0])
            base = conts[c]
            cont = base if last_of_cont[c] == g else base.copy()
            picks = [(b, r) for b, r in enumerate(picks_of[members[0]]) if r >= 0]
            self._fuse(cont, picks, batch, join.order, settle, xi)
            for n in members:
                used_phi = dict(parents[parent_of[n]].used_phi)
                used_phi.update(zip(used_owners, phis_of[n], strict=True))
                children[n] = Hypothesis(tuple(classes_of[n]), cont, log_weight_of[n], used_phi)
        children_list = [children[n] for n in range(len(join.parent))]
        self.hypotheses = children_list
        self._remember_classes(join.classes)
        self._normalise()
        for s in batch:
            if s.owner not in skipped:
                self.versions[s.owner] = s.version
        return FusionStats(
            used,
            tuple(sorted(skipped)),
            candidates,
            len(children_list),
            len(skipped),
            0,
            self._completed,
        )

    def rebuild(
        self, local: HybridBelief, held: Sequence[Slot], settle: bool = True
    ) -> FusionStats:
        """Make D anew from the owner's local belief ``local`` and every ``held`` slot (the newest
        version of every other robot's slot).

        D is a derived belief: its hypotheses pruned a class combination that a newer slot needs
        (an empty join) can only come back from the undivided pieces, L and the slots. The
        integration that follows is the one of a D that received all held slots at once.
        """
        if local.robots != [self.owner] or local.step_of != self.step_of:
            raise ValueError(
                f"D of {self.owner} at {self.step_of} cannot be rebuilt from a belief of "
                f"{local.robots} at {local.step_of}"
            )
        self.object_ids = list(local.object_ids)
        self._object_index = {j: i for i, j in enumerate(self.object_ids)}
        self.log_evidence = np.array(local.log_evidence)
        self.object_phi = {}
        conts, which = distinct_continuous(local.hypotheses)
        copies = [c.copy() for c in conts]  # with L's semantic ledger; L holds no slot
        self.hypotheses = [
            Hypothesis(h.classes, copies[g], h.log_weight)
            for h, g in zip(local.hypotheses, which, strict=True)
        ]
        self.versions = {}
        self._class_rows = None
        stats = self.integrate([s for s in held if s.owner != self.owner], settle)
        return FusionStats(
            stats.integrated,
            stats.skipped,
            stats.candidates,
            stats.kept,
            stats.empty_joins,
            stats.rebuilds + 1,
            stats.completed,
        )

    def check(self, s: Slot) -> None:
        """Raise :class:`SlotError` if a slot contradicts this belief's model."""
        m = self.model.num_classes
        n = len(s.summary.object_ids)
        # As if every hypothesis held its own ξ: it bounds the slot's objects (223 with the
        # defaults), and with them the work of building and eliminating its dense ξ factor.
        d = self._kind.dim
        fusion_bytes = (1 if self.per_object else self.cap) * (d * n) ** 2 * 8
        if fusion_bytes > self.config.max_fusion_bytes:
            cap = self.config.max_fusion_bytes / 2**20
            raise SlotError(
                f"slot of {s.owner}: {n} objects would take {fusion_bytes / 2**20:.0f} MiB of "
                f"information matrices (max_fusion_bytes {cap:.0f} MiB)"
            )
        if len(set(s.summary.object_ids)) != n:
            raise SlotError(f"slot of {s.owner}: duplicate object ids")
        ours = "per_object" if self.per_object else "table"
        if s.summary.kind != ours:
            raise SlotError(
                f"slot of {s.owner}: classes {s.summary.kind!r}, this belief's are {ours!r} "
                "(every robot of a fleet must run the same BeliefConfig.classes)"
            )
        if s.summary.per_object is not None:
            phi = np.asarray(s.summary.per_object.log_phi)
            if phi.shape != (n, m) or not np.isfinite(phi).all():
                raise SlotError(f"slot of {s.owner}: class log φ is not finite ({n}, {m})")
            mapped = self.association is not None
            if s.summary.per_object.local_ids != mapped:
                raise SlotError(
                    f"slot of {s.owner}: object ids "
                    f"{'robot-local' if s.summary.per_object.local_ids else 'global'}, this "
                    f"belief's {'are matched from robot-local ids' if mapped else 'are global'} "
                    "(every robot of a fleet must have frames of one id kind)"
                )
            x = s.summary.per_object.xi
            _check_dim(s.owner, x, d)
            if isinstance(x, SparseXi):
                _check_sparse(s.owner, x, n)
            elif x.lin.shape != (n, d) or x.info.shape != (d * n, d * n) or x.eta.shape != (d * n,):
                raise SlotError(f"slot of {s.owner}: ξ shapes do not fit {n} objects")
            return
        rs = s.summary.realisations
        fits = isinstance(rs, Realisations) or all(len(r.classes) == n for r in rs)
        cls = s.summary.class_matrix() if fits else None
        if (
            cls is None
            or cls.shape != (len(rs), n)
            or (cls.size and not 0 <= cls.min() <= cls.max() < m)
        ):
            raise SlotError(
                f"slot of {s.owner}: realisation classes do not fit {n} objects, {m} classes"
            )
        for x in s.summary.distinct_xi()[0]:
            _check_dim(s.owner, x, d)
            if x.lin.shape != (n, d) or x.info.shape != (d * n, d * n) or x.eta.shape != (d * n,):
                raise SlotError(f"slot of {s.owner}: ξ shapes do not fit {n} objects")

    def _join(self, batch: Sequence[Slot]) -> tuple[_Join, set[str]]:
        """Join D's hypotheses with every slot's realisations on shared objects (bookkeeping only:
        no iSAM2 is touched). Returns the joins and the owners whose slot joined with nothing."""
        known = dict(self._object_index)
        # The join's classes in the smallest integer type that holds them: its matrices are copied
        # and compared at every slot, and grow to max_join rows (classes are checked < M).
        small = np.min_scalar_type(-max(1, self.model.num_classes))
        join = _Join(
            np.arange(len(self.hypotheses)),
            self.class_matrix().astype(small),
            np.array([h.log_weight for h in self.hypotheses]),
            [],
            len(batch),
        )
        skipped: set[str] = set()
        self._completed = 0
        # log φ of the version of each slot's owner every hypothesis used before (0 if none)
        owners, zeros = [s.owner for s in batch], [0.0] * len(batch)
        old_log_phi = np.array(
            [list(map(h.used_phi.get, owners, zeros)) for h in self.hypotheses], dtype=float
        ).reshape(len(self.hypotheses), len(batch))
        for b, s in enumerate(batch):
            ids = s.summary.object_ids
            shared = [(known[j], i) for i, j in enumerate(ids) if j in known]
            fresh = [i for i, j in enumerate(ids) if j not in known]
            real_cls = s.summary.class_matrix()
            d_cols = np.array([a for a, _ in shared], dtype=np.int64)
            s_cols = np.array([i for _, i in shared], dtype=np.int64)
            # Bounded before anything is built: at most max_join (row, realisation) pairs (the
            # heaviest rows of the join so far), compared in chunks of at most _FITS_CELLS cells.
            width = max(1, len(real_cls))
            if len(join.parent) * width > self.config.max_join:
                heaviest = np.argsort(-join.log_weight, kind="stable")
                join = join.keep(np.sort(heaviest[: max(1, self.config.max_join // width)]))
            log_phi = s.summary.log_phis()
            rows, cols = _fits(join.classes[:, d_cols], real_cls[:, s_cols])
            matched = np.zeros(len(join.parent), dtype=bool)
            matched[rows] = True
            unmatched = np.flatnonzero(~matched)
            near_rows, near_cols, near_phi = _nearest(
                join.classes[:, d_cols], real_cls[:, s_cols], real_cls[:, fresh], log_phi, unmatched
            )
            self._completed += len(np.unique(near_rows))
            phi = np.concatenate([log_phi[cols], near_phi])
            rows = np.concatenate([rows, near_rows])
            cols = np.concatenate([cols, near_cols])
            if len(rows) == 0:
                # Expected under double counting (D becomes overconfident and prunes what the
                # owner keeps); under consistent fusion the RobotNode rebuilds D.
                level = logging.INFO if self.fusion == "consistent" else logging.DEBUG
                log.log(level, "slot of %s (stamp %d) joins with no hypothesis", s.owner, s.stamp)
                skipped.add(s.owner)
                continue
            new_cls = real_cls[:, fresh]
            lw = join.log_weight[rows] + phi + self._log_prior[new_cls[cols]].sum(axis=1)
            if self.fusion == "consistent":
                lw -= old_log_phi[:, b][join.parent[rows]]
            join = _Join(
                join.parent[rows],
                np.concatenate([join.classes[rows], new_cls[cols].astype(small)], axis=1),
                lw,
                join.order + [ids[i] for i in fresh],
                join.width,
                (*join.steps, (rows, b, cols, phi)),
            )
            if len(rows) > _JOIN_GUARD * self.cap:
                join = join.keep(self._select(join.log_weight, join.classes))
            for i in fresh:
                known[ids[i]] = len(known)
        return join, skipped

    def _fuse(
        self,
        h: Continuous,
        picks: Sequence[tuple[int, int]],
        batch: Sequence[Slot],
        order: Sequence[int],
        settle: bool,
        xi: _XiFactors,
    ) -> None:
        """Add the picked realisations' ξ factors and the priors of objects new to D, and divide
        out the versions used before (Eq. 12)."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        remove: list[int] = []
        new_objects = set(order)
        # (slot, ξ, carried factor indices, graph positions of its anti-factors and ξ factors)
        positions = []
        for b, r in picks:
            s = batch[b]
            per_object = s.summary.per_object
            real = s.summary.realisations[r].xi if per_object is None else per_object.xi
            ids = s.summary.object_ids
            for i, j in enumerate(ids):
                if j in new_objects and j not in h.object_priors:
                    obj = np.asarray(real.lin[i], dtype=float)
                    graph.add(object_prior(object_key(j), obj, self._object_prior))
                    values.insert(object_key(j), object_value(obj))
                    h.object_priors[j] = obj.copy()
            old = h.used.get(s.owner)
            carried: tuple[int, ...] = ()
            anti = range(0)
            if old is not None:
                if self.fusion == "double_count":
                    carried = old.factor_indices
                elif self.downdate == "remove":
                    remove.extend(old.factor_indices)
                else:
                    carried = old.factor_indices
                    start = graph.size()
                    for f in xi.get(old.object_ids, old.xi, -1.0):
                        graph.add(f)
                    anti = range(start, graph.size())
            start = graph.size()
            for f in xi.get(ids, real):
                graph.add(f)
            positions.append((s, real, carried, anti, range(start, graph.size())))
        result = h.isam.update(graph, values, remove)
        new_indices = list(result.getNewFactorsIndices())
        for s, real, carried, anti, own in positions:
            indices = (*carried, *(new_indices[i] for i in (*anti, *own)))
            h.used[s.owner] = UsedXi(s.stamp, s.summary.object_ids, real, indices)
        for _ in range(self.config.extra_updates if settle else 0):
            h.isam.update()
        h.updated()


def _check_dim(owner: str, x: Xi | SparseXi, d: int) -> None:
    """A slot's objects are of this belief's kind (``estimator.models.objects``)."""
    if np.ndim(x.lin) != 2 or np.shape(x.lin)[1] != d:
        got = np.shape(x.lin)[1] if np.ndim(x.lin) == 2 else "?"
        raise SlotError(f"slot of {owner}: objects of dimension {got}, this belief's are {d}")


def _check_sparse(owner: str, x: SparseXi, n: int) -> None:
    """A sparse ξ's shapes and pattern fit n objects of dimension d: ``lin`` (n, d),
    ``diag_info`` (n, d, d), ``edges`` (E, 2) integer pairs i < j < n, each once, ``edge_info``
    (E, d, d), ``eta`` (dn,) (its factors index objects by ``edges``: a pair out of range or
    twice would put the information on the wrong objects or count it twice)."""
    edges = np.asarray(x.edges)
    e = len(edges) if edges.ndim == 2 else -1
    d = x.dim
    if (
        np.shape(x.lin) != (n, d)
        or np.shape(x.diag_info) != (n, d, d)
        or edges.shape != (e, 2)
        or np.shape(x.edge_info) != (e, d, d)
        or np.shape(x.eta) != (d * n,)
    ):
        raise SlotError(f"slot of {owner}: sparse ξ shapes do not fit {n} objects")
    if e == 0:
        return
    if edges.dtype.kind not in "iu" or not (
        (edges[:, 0] >= 0).all() and (edges[:, 0] < edges[:, 1]).all() and (edges[:, 1] < n).all()
    ):
        raise SlotError(f"slot of {owner}: sparse ξ edges must be object pairs i < j < {n}")
    pairs = edges.astype(np.int64)  # one integer per pair i < j < n (uint16 would wrap)
    if len(np.unique(pairs[:, 0] * n + pairs[:, 1])) != e:
        raise SlotError(f"slot of {owner}: a sparse ξ edge is listed twice")
