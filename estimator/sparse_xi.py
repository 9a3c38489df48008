"""A conservative sparse ξ: the owner's dense Λ over n objects replaced by a Λ_s ⪯ Λ that lives on
a Bayes net's moral graph (docs/design map-scale-belief.md §3, "Bayes net, closed form").

Why: a dense ξ grows as n² on the wire and becomes one n-object clique at the receiver. Dropping
blocks of Λ is not safe (the receiver would believe more than the owner knows); scaling the block
diagonal down until it fits under Λ keeps almost nothing, because odometry drift correlates the
objects. Instead the objects are decorrelated by a Bayes net x_f | x_{P_f} fitted to Σ = Λ⁻¹
(rows Ḡ), the small residual correlation R = Ḡ Σ Ḡᵀ is bounded by a block diagonal U ⪰ R, and
Λ_s = Ḡᵀ U⁻¹ Ḡ. Then Λ − Λ_s = Ḡᵀ (R⁻¹ − U⁻¹) Ḡ ⪰ 0 whatever the net, so the net only decides how
much is lost, never whether the result is safe; a net that is exact (Σ Markov on it) loses
nothing. Closed form, no solver; values are always recomputed, so reusing an old structure
(:class:`Structure`) costs quality, not safety.

Over 300 lines for a reason: fitting the net, the closed form, the bound and the conservative
float32 rounding are one argument (each step is what makes the next one safe) and share one
block layout; split over modules, the proof that Λ_s ⪯ Λ would be read in pieces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack
from scipy.sparse import bsr_array, coo_array, csr_array
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from estimator.xi import Xi

if TYPE_CHECKING:  # GTSAM is imported where a factor is made: a decoder needs only the arrays
    import gtsam

Array = NDArray[np.float64]
Index = NDArray[np.intp]

# Up to this many objects Ḡ is a dense array: below it scipy.sparse's fixed costs exceed the
# dense products' (measured per sparsify, dense / sparse: 1.5 / 3.0 ms at 12 objects, 3.8 / 4.8 at
# 36, 8.8 / 7.3 at 48, even at 64 and 96).
DENSE_UP_TO = 40
# Parents of an object beyond its tree parent (``sparsify``'s ``extra_parents``,
# ``BeliefConfig.xi_parents``): the default, and the most a slot may use. With p parents an
# object brings at most p(p + 1)/2 moral edges, so the most bounds a slot's edges on the wire
# (protocol.codec.MAX_EDGES_PER_OBJECT). Each one more costs about 45 bytes per object and buys
# back information; measured on the dense world, D's position σ against the dense ξ's: 1.37, 1.27,
# 1.20 at 1, 2, 3 (docs/estimator.md, "Sparse ξ").
XI_PARENTS = 2
MAX_XI_PARENTS = 3
CANDIDATES = 8  # extra parents are sought among this many earlier objects of highest MI
# Λ_s is scaled by 1 − MARGIN (§3 step 5): Λ − Λ_s ⪰ 0 is exact in exact arithmetic, and the
# margin absorbs the float64 rounding of Σ and of the bound (~u·κ(Λ) relative).
MARGIN = 1e-6
_ID_BYTES = 4  # an object id on the wire
_EDGE_INDEX_BYTES = 4  # an edge's two object indices as uint16


@dataclass(frozen=True, slots=True)
class Structure:
    """A Bayes net over n objects: ``order`` a permutation of range(n), ``parents[f]`` the
    objects x_f is conditioned on, all earlier than f in ``order`` (which makes Ḡ block
    triangular in that order, hence invertible). Indexed by object position in the ξ."""

    order: tuple[int, ...]
    parents: tuple[tuple[int, ...], ...]

    def __post_init__(self) -> None:
        n = len(self.parents)
        if sorted(self.order) != list(range(n)):
            raise ValueError(f"structure order: not a permutation of range({n})")
        pos = {f: k for k, f in enumerate(self.order)}
        for f, ps in enumerate(self.parents):
            if len(set(ps)) != len(ps) or any(p not in pos or pos[p] >= pos[f] for p in ps):
                raise ValueError(f"structure parents[{f}]: {ps} are not distinct earlier objects")

    def edges(self) -> Index:
        """(E, 2) object pairs i < j of the moral graph (each object with its parents, and the
        parents of one object with each other), sorted: the off-diagonal blocks of Λ_s."""
        pairs: set[tuple[int, int]] = set()
        for f, ps in enumerate(self.parents):
            family = sorted((f, *ps))
            pairs.update((a, b) for k, a in enumerate(family) for b in family[k + 1 :])
        return np.array(sorted(pairs), dtype=np.intp).reshape(-1, 2)


@dataclass(frozen=True, slots=True, eq=False)
class SparseXi:
    """ξ with Λ on a sparse block pattern: ``lin`` (n, d) linearisation points as in :class:`Xi`
    (d = 3 for Pose2 objects, 2 for Point2); ``diag_info`` (n, d, d) the diagonal blocks of Λ_s;
    ``edges`` (E, 2) object pairs i < j and ``edge_info`` (E, d, d) the blocks Λ_s[i, j]
    (Λ_s[j, i] is the transpose); every other block is zero. ``eta`` (dn,) η_s. ``structure``
    the sender's Bayes net, kept to be reused by its next rebuild (None where unknown, e.g.
    decoded; the receiver never needs it)."""

    lin: Array
    diag_info: Array
    edges: Index
    edge_info: Array
    eta: Array
    structure: Structure | None = None

    @property
    def dim(self) -> int:
        """d, the tangent dimension of one object (3: Pose2; 2: Point2)."""
        return int(np.shape(self.lin)[1])

    def dense(self) -> Xi:
        """The same ξ with a dense (dn, dn) Λ."""
        n, d = len(self.lin), self.dim
        info = np.zeros((n, n, d, d))
        idx = np.arange(n)
        info[idx, idx] = self.diag_info
        i, j = self.edges.T
        info[i, j] = self.edge_info
        info[j, i] = self.edge_info.swapaxes(1, 2)
        return Xi(self.lin, info.transpose(0, 2, 1, 3).reshape(d * n, d * n), self.eta)

    def bytes_per_object(self, float32: bool = True) -> float:
        """Wire bytes per object of what must travel, Λ_s and η as float32 (else float64): per
        object its id, ``lin`` (float64 always: float32 would move a pose in a 10 km world by
        up to 0.5 mm), η and the 6 distinct entries of its symmetric diagonal block; per edge
        its 9 entries and two uint16 object indices."""
        n, d = len(self.lin), self.dim
        width = 4 if float32 else 8
        per_object = _ID_BYTES + d * 8 + (d + d * (d + 1) // 2) * width
        total = n * per_object + len(self.edges) * (d * d * width + _EDGE_INDEX_BYTES)
        return total / n if n else 0.0

    def float32(self) -> SparseXi:
        """The same ξ with Λ_s and η exactly representable in float32 (held as float64), and
        still Λ_s32 ⪯ Λ_s. Rounding every entry to nearest is not safe: with Λ ill-conditioned
        (κ ≈ 10⁵ for a handful of drift-correlated objects) it perturbs the weakest direction
        by ~u·κ relative, far beyond ``MARGIN``. So each off-diagonal entry is rounded to
        nearest and the diagonal lowered by the absolute rounding errors of its row, rounded
        down: Λ_s − Λ_s32 is then diagonally dominant with a non-negative diagonal, hence ⪰ 0
        (Gershgorin), whatever κ. η32 = Λ_s32 μ rounded keeps the mean (up to η's rounding)."""
        if len(self.lin) == 0:  # nothing to round (and no system to solve)
            return self
        diag32, edge32 = _round_under32(self.diag_info, self.edges, self.edge_info)
        rounded = SparseXi(self.lin, diag32, self.edges, edge32, self.eta, self.structure)
        mean = _solve(self.dense().info, self.eta)
        eta32 = _nearest32(rounded.dense().info @ mean)
        return SparseXi(self.lin, diag32, self.edges, edge32, eta32, self.structure)


def sparsify(
    xi: Xi, extra_parents: int = XI_PARENTS, structure: Structure | None = None
) -> SparseXi:
    """The conservative sparse form of ``xi`` (§3): Λ_s ⪯ Λ (Loewner), positive definite, on
    the moral graph of a Bayes net, scaled by 1 − ``MARGIN``; η_s = Λ_s Λ⁻¹ η keeps the mean.
    The net is ``structure`` if given (same n; its values are recomputed), else fitted: the
    Chow–Liu tree of the objects' mutual information, ordered breadth first, each object's
    parents its tree parent and up to ``extra_parents`` earlier objects chosen greedily.
    ValueError if Λ is not positive definite."""
    n, d = len(xi.lin), xi.dim
    if structure is not None and len(structure.parents) != n:
        raise ValueError(f"structure for {len(structure.parents)} objects, ξ has {n}")
    if n == 0:  # an owner that has seen no object yet
        none = np.zeros((0, d, d))
        return SparseXi(xi.lin, none, np.zeros((0, 2), np.intp), none, xi.eta, Structure((), ()))
    sigma, mean = _covariance_and_mean(xi.info, xi.eta)
    s4 = _blocks(sigma, d)
    if structure is None:
        structure = _fit_structure(s4, extra_parents)
    g = _net_rows(s4, structure)
    r = g @ (g @ sigma).T  # Ḡ Σ Ḡᵀ, Σ symmetric
    bound = _block_bound(_blocks(0.5 * (r + r.T), d))
    info = _weighted_gram(g, np.asarray(np.linalg.inv(bound), dtype=np.float64)) * (1.0 - MARGIN)
    info = 0.5 * (info + info.T)
    edges = structure.edges()
    b4 = _blocks(info, d)
    return SparseXi(
        xi.lin,
        b4[np.arange(n), np.arange(n)].copy(),
        edges,
        b4[edges[:, 0], edges[:, 1]].copy(),
        info @ mean,
        structure,
    )


def sparse_xi_factor(
    keys: Sequence[int], sx: SparseXi, sign: float = 1.0
) -> gtsam.LinearContainerFactor:
    """``sx`` as a GTSAM factor on the object ``keys``, equal to ``xi_factor(keys, sx.dense())``
    but summed from one unary piece per object and one pairwise piece per edge only (not n²
    pieces). ``sign = −1`` gives the anti-factor."""
    import gtsam  # here, not at the top: see the import above

    if len(keys) != len(sx.lin):
        raise ValueError(f"{len(keys)} keys for a ξ of {len(sx.lin)} objects")
    pieces = gtsam.GaussianFactorGraph()
    d = sx.dim
    eta = sign * sx.eta.reshape(-1, d)
    for key, block, g in zip(keys, sign * sx.diag_info, eta, strict=True):
        pieces.add(gtsam.HessianFactor(key, block, g, 0.0))
    zero, none = np.zeros((d, d)), np.zeros(d)
    for (i, j), block in zip(sx.edges, sign * sx.edge_info, strict=True):
        pieces.add(gtsam.HessianFactor(keys[i], keys[j], zero, block, none, zero, none, 0.0))
    lin = gtsam.Values()
    for key, pose in zip(keys, sx.lin, strict=True):
        lin.insert(key, gtsam.Pose2(*pose))
    return gtsam.LinearContainerFactor(gtsam.HessianFactor(pieces), lin)


def _round_under32(diag: Array, edges: Index, edge_info: Array) -> tuple[Array, Array]:
    """Blocks as :meth:`SparseXi.float32` rounds them: off-diagonal entries to nearest, each
    diagonal entry lowered by its row's absolute off-diagonal errors and rounded down."""
    diag32, edge32 = _nearest32(diag), _nearest32(edge_info)
    idx = np.arange(diag.shape[-1])
    inner = np.abs(diag - diag32)
    inner[:, idx, idx] = 0.0
    error = inner.sum(axis=2)  # (n, d): row sums, dn-matrix row di + a at [i, a]
    across = np.abs(edge_info - edge32)
    np.add.at(error, edges[:, 0], across.sum(axis=2))
    np.add.at(error, edges[:, 1], across.sum(axis=1))
    # (1 + 1e-9): the float64 sum's own rounding must not eat into the bound
    diag32[:, idx, idx] = _down32(diag[:, idx, idx] - error * (1.0 + 1e-9))
    return diag32, edge32


def _nearest32(a: Array) -> Array:
    return np.asarray(a, dtype=np.float32).astype(float)


def _down32(a: Array) -> Array:
    """``a`` rounded to float32 towards −∞."""
    near = np.asarray(a, dtype=np.float32)
    over = near.astype(float) > a
    near[over] = np.nextafter(near[over], np.float32(-np.inf))
    return near.astype(float)


def _cholesky(info: Array) -> Array:
    """Upper Cholesky factor of Λ (LAPACK potrf)."""
    c, fail = lapack.dpotrf(info, lower=False, clean=True)
    if fail:
        raise ValueError("ξ's Λ is not positive definite")
    return np.asarray(c)


def _solve(info: Array, eta: Array) -> Array:
    return np.asarray(lapack.dpotrs(_cholesky(info), eta, lower=False)[0])


def _covariance_and_mean(info: Array, eta: Array) -> tuple[Array, Array]:
    """Σ = Λ⁻¹ and μ = Λ⁻¹ η from one Cholesky factor (LAPACK potrf, potri, potrs)."""
    c = _cholesky(info)
    mean, _ = lapack.dpotrs(c, eta, lower=False)
    inv, _ = lapack.dpotri(c, lower=False)
    sigma = np.triu(inv) + np.triu(inv, 1).T
    return np.asarray(sigma, dtype=np.float64), np.asarray(mean, dtype=np.float64)


def _blocks(a: Array, d: int) -> Array:
    """(dn, dn) → (n, n, d, d) view of its d × d blocks."""
    n = len(a) // d
    return a.reshape(n, d, n, d).transpose(0, 2, 1, 3)


def _fit_structure(s4: Array, extra_parents: int) -> Structure:
    mi = _mutual_information(s4)
    order, tree_parent = _chow_liu(mi)
    return _choose_parents(s4, mi, order, tree_parent, extra_parents)


def _mutual_information(s4: Array) -> Array:
    """(n, n) MI of every object pair: with the diagonal blocks whitened, R_ij the whitened
    cross-covariance, MI_ij = −½ log det(I − R_ij R_ijᵀ); 0 on the diagonal."""
    n = len(s4)
    idx = np.arange(n)
    w = np.linalg.inv(np.linalg.cholesky(s4[idx, idx]))
    r = np.einsum("iab,ijbc->ijac", w, s4)
    r = np.einsum("ijac,jdc->ijad", r, w)
    det = np.linalg.det(np.eye(s4.shape[-1]) - r @ r.swapaxes(2, 3))
    mi = -0.5 * np.log(np.clip(det, np.finfo(float).tiny, 1.0))
    mi[idx, idx] = 0.0
    return mi


def _chow_liu(mi: Array) -> tuple[Index, Index]:
    """The maximum-MI spanning tree, ordered breadth first from its highest-degree object:
    (order (n,), tree parent (n,), −1 at the root). Kruskal depends only on the order of the
    weights, so they are MI ranks: positive (scipy reads a zero as no edge) and distinct, so the
    tree spans even where MI is zero or lost to rounding."""
    n = len(mi)
    iu, ju = np.triu_indices(n, 1)
    rank = np.empty(len(iu))
    rank[np.argsort(-mi[iu, ju], kind="stable")] = np.arange(1, len(iu) + 1)
    tree = minimum_spanning_tree(csr_array((rank, (iu, ju)), shape=(n, n)))
    degree = np.bincount(np.concatenate(tree.nonzero()), minlength=n)
    order, pred = breadth_first_order(tree, int(np.argmax(degree)), directed=False)
    return order.astype(np.intp), np.where(pred < 0, -1, pred).astype(np.intp)


def _choose_parents(
    s4: Array, mi: Array, order: Index, tree_parent: Index, extra: int
) -> Structure:
    """Each object's tree parent, then ``extra`` times the earlier object (among its
    ``CANDIDATES`` of highest MI) that most lowers log det Cov(x_f | parents): all objects at
    once per round (an object's choice depends on its own parents only)."""
    n = len(order)
    pos = np.empty(n, dtype=np.intp)
    pos[order] = np.arange(n)
    par = np.full((n, 1 + extra), -1, dtype=np.intp)
    par[:, 0] = tree_parent
    has = np.flatnonzero(tree_parent >= 0)
    score = np.where(pos[None, :] < pos[:, None], mi, -np.inf)
    score[has, tree_parent[has]] = -np.inf
    width = min(CANDIDATES, n)
    cand = np.argpartition(-score, width - 1, axis=1)[:, :width]
    free = np.isfinite(np.take_along_axis(score, cand, axis=1))
    active = has
    for k in range(1, 1 + extra):
        active = active[free[active].any(axis=1)]
        if not len(active):
            break
        rows, cols = np.nonzero(free[active])
        f = active[rows]
        _, cov = _conditionals(s4, f, np.column_stack([par[f, :k], cand[f, cols]]))
        cost = np.full((len(active), width), np.inf)
        cost[rows, cols] = np.linalg.slogdet(cov)[1]
        best = np.argmin(cost, axis=1)
        par[active, k] = cand[active, best]
        free[active, best] = False
    parents = tuple(tuple(int(p) for p in row if p >= 0) for row in par)
    return Structure(tuple(int(f) for f in order), parents)


def _conditionals(s4: Array, f: Index, parents: Index) -> tuple[Array, Array]:
    """For m objects ``f`` (m,) with k parents each (m, k): K = Σ_fP Σ_PP⁻¹ (m, d, dk) and
    Cov(x_f | x_P) = Σ_ff − K Σ_Pf (m, d, d)."""
    m, k = parents.shape
    d = s4.shape[-1]
    cov = s4[f, f]
    if k == 0:
        return np.zeros((m, d, 0)), cov
    spp = s4[parents[:, :, None], parents[:, None, :]].transpose(0, 1, 3, 2, 4)
    sfp = s4[f[:, None], parents].transpose(0, 2, 1, 3).reshape(m, d, d * k)
    gain = np.linalg.solve(spp.reshape(m, d * k, d * k), sfp.swapaxes(1, 2)).swapaxes(1, 2)
    return np.asarray(gain, dtype=np.float64), cov - gain @ sfp.swapaxes(1, 2)


def _net_rows(s4: Array, structure: Structure) -> csr_array | Array:
    """Ḡ (dn, dn): rows G_f = W_f [I, −K_f] on (f, P_f) with W_fᵀ W_f = Ω_f =
    Cov(x_f | x_P)⁻¹, so that Ḡ Σ Ḡᵀ has identity diagonal blocks. W_f = chol(Cov)⁻¹ rather than
    chol(Ω_f)ᵀ: they differ by a rotation per row block, which Λ_s does not see (U_f turns
    with it), and no Ω_f need be formed. Sparse (CSR) above ``DENSE_UP_TO`` objects, a dense
    array up to it (where scipy.sparse's fixed costs exceed the dense products')."""
    n, d = len(s4), s4.shape[-1]
    dense = n <= DENSE_UP_TO
    g4 = np.zeros((n, n, d, d)) if dense else None
    rows, cols, vals = [], [], []
    sizes = np.array([len(ps) for ps in structure.parents])
    for k in np.unique(sizes):
        f = np.flatnonzero(sizes == k)
        parents = np.array([structure.parents[i] for i in f], dtype=np.intp).reshape(len(f), k)
        gain, cov = _conditionals(s4, f, parents)
        w = np.linalg.inv(np.linalg.cholesky(cov))
        block = np.concatenate([w, -w @ gain], axis=2).reshape(len(f), d, k + 1, d)
        family = np.column_stack([f, parents])
        if g4 is not None:
            g4[f[:, None], family] = block.transpose(0, 2, 1, 3)
            continue
        a = np.arange(d)
        rows.append(np.broadcast_to((d * f)[:, None, None, None] + a[:, None, None], block.shape))
        cols.append(np.broadcast_to(d * family[:, None, :, None] + a, block.shape))
        vals.append(block)
    if g4 is not None:
        return g4.transpose(0, 2, 1, 3).reshape(d * n, d * n)
    flat = [np.concatenate([x.ravel() for x in xs]) for xs in (vals, rows, cols)]
    return csr_array(coo_array((flat[0], (flat[1], flat[2])), shape=(d * n, d * n)))


def _weighted_gram(g: csr_array | Array, weights: Array) -> Array:
    """Ḡᵀ blockdiag(``weights``) Ḡ as a dense (dn, dn) array; ``weights`` (n, d, d)."""
    n, d = len(weights), weights.shape[-1]
    if isinstance(g, np.ndarray):
        return np.asarray(g.T @ (weights @ g.reshape(n, d, d * n)).reshape(d * n, d * n))
    w = bsr_array((weights, np.arange(n), np.arange(n + 1)), shape=(d * n,) * 2)
    return np.asarray((g.T @ (w @ g)).toarray())


def _block_bound(r4: Array) -> Array:
    """(n, d, d) U with blockdiag(U) ⪰ R: U_f = R_ff + Σ_{g≠f} (R_fg R_fgᵀ)^½. Per pair, with
    R_fg = A S Bᵀ (SVD), [[A S Aᵀ, −R_fg], [−R_fgᵀ, B S Bᵀ]] = [A; −B] S [A; −B]ᵀ ⪰ 0, so the
    sum over pairs of these is U − R ⪰ 0; one SVD gives both roots as an exact pair."""
    n = len(r4)
    iu, ju = np.triu_indices(n, 1)
    a, s, bt = np.linalg.svd(r4[iu, ju])
    roots = np.zeros(r4.shape)
    roots[iu, ju] = (a * s[:, None, :]) @ a.swapaxes(1, 2)
    roots[ju, iu] = (bt.swapaxes(1, 2) * s[:, None, :]) @ bt
    idx = np.arange(n)
    return np.asarray(r4[idx, idx] + roots.sum(axis=1))
