"""The conservative sparse ξ (estimator.sparse_xi): Λ_s ⪯ Λ on real GTSAM marginals and random
SPD matrices (also after the float32 rounding), the mean kept, nothing lost where the exact
structure is a tree, far less lost than the block-diagonal bound, Λ_s only on the moral graph
(against a plain dense re-derivation of the closed form), and the receiver's factor equal to
the dense one's."""

from __future__ import annotations

from functools import cache

import gtsam
import numpy as np
import pytest

from estimator import sparse_xi
from estimator.distributed import xi_factor
from estimator.factors import object_key, pose_key
from estimator.sparse_xi import MARGIN, SparseXi, Structure, sparse_xi_factor, sparsify
from estimator.summary import Xi
from tests.tolerance import assert_close

ODOMETRY = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.02]))
MEASUREMENT = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.1, 0.1, 0.05]))
ANCHOR = gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
SENSOR_RANGE = 6.0  # m
AREA = 30.0  # m


def _tour(obj: np.ndarray) -> np.ndarray:
    """(K, 3) robot poses: from the origin to each object in turn, nearest first, in steps of
    at most 1 m."""
    here, poses, left = np.zeros(2), [np.zeros(3)], set(range(len(obj)))
    while left:
        j = min(left, key=lambda i: float(np.hypot(*(obj[i, :2] - here))))
        left.remove(j)
        d = obj[j, :2] - here
        steps = max(1, int(np.ceil(np.hypot(*d))))
        heading = float(np.arctan2(d[1], d[0]))
        poses += [np.array([*(here + d * s / steps), heading]) for s in range(1, steps + 1)]
        here = obj[j, :2]
    return np.array(poses)


@cache
def _tour_xi(n: int, seed: int) -> Xi:
    """ξ of n objects as a robot sees them: it drives to every object (:func:`_tour`) and
    measures each object within range at every pose, so odometry drift correlates the objects.
    Λ = GTSAM's joint marginal information of the objects; η = Λ δ, δ random."""
    rng = np.random.default_rng(seed)
    obj = np.column_stack([rng.uniform(0, AREA, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    poses = [gtsam.Pose2(*p) for p in _tour(obj).tolist()]
    objects = [gtsam.Pose2(*o) for o in obj.tolist()]
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(pose_key(0, 0), poses[0], ANCHOR))
    for k, pose in enumerate(poses):
        values.insert(pose_key(0, k), pose)
        if k:
            odometry = poses[k - 1].between(pose)
            graph.add(
                gtsam.BetweenFactorPose2(pose_key(0, k - 1), pose_key(0, k), odometry, ODOMETRY)
            )
        for j in np.flatnonzero(
            np.hypot(*(obj[:, :2] - np.array([pose.x(), pose.y()])).T) < SENSOR_RANGE
        ).tolist():
            seen = pose.between(objects[j])
            graph.add(gtsam.BetweenFactorPose2(pose_key(0, k), object_key(j), seen, MEASUREMENT))
    keys = [object_key(j) for j in range(n)]
    for key, o in zip(keys, objects, strict=True):
        values.insert(key, o)
    marginals = gtsam.Marginals(graph, values)
    info = marginals.jointMarginalInformation(gtsam.KeyVector(keys)).fullMatrix()
    info = 0.5 * (info + info.T)
    return Xi(obj, info, info @ rng.normal(0.0, 0.1, 3 * n))


def _random_xi(n: int, seed: int) -> Xi:
    """ξ with a random SPD Λ (Wishart, a few degrees of freedom over the dimension)."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((3 * n, 3 * n + 4))
    info = a @ a.T / (3 * n + 4) + 1e-2 * np.eye(3 * n)
    lin = np.column_stack([rng.uniform(0, AREA, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    return Xi(lin, info, rng.standard_normal(3 * n))


def _tree_xi(parent: list[int], seed: int) -> Xi:
    """ξ of a Gauss–Markov tree: x_f = A_f x_parent + noise, so Λ is zero off the tree's
    blocks (a chain when ``parent[f] = f − 1``), objects numbered in a random order."""
    n = len(parent)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    g = np.eye(3 * n)
    weights = np.zeros((3 * n, 3 * n))
    for f in range(n):
        rows = slice(3 * perm[f], 3 * perm[f] + 3)
        if parent[f] >= 0:
            p = perm[parent[f]]
            g[rows, 3 * p : 3 * p + 3] = -rng.normal(0.0, 0.6, (3, 3))
        c = rng.normal(0.0, 0.3, (3, 3)) + np.eye(3)
        weights[rows, rows] = c @ c.T
    info = g.T @ weights @ g
    return Xi(np.zeros((n, 3)), 0.5 * (info + info.T), rng.standard_normal(3 * n))


def _kl(info: np.ndarray, approx: np.ndarray) -> float:
    """KL(N(μ, Λ⁻¹) ‖ N(μ, Λ_s⁻¹)): what believing Λ_s instead of Λ loses."""
    c = np.linalg.cholesky(info)
    m = np.linalg.solve(c, np.linalg.solve(c, approx).T)  # c⁻¹ Λ_s c⁻ᵀ
    return 0.5 * float(np.trace(m) - len(info) - np.linalg.slogdet(m)[1])


def _eigmin(a: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(a)[0])


def _check_conservative(xi: Xi, sx: SparseXi) -> None:
    for what, s in (("float64", sx), ("float32", sx.float32())):
        dense = s.dense()
        assert _eigmin(xi.info - dense.info) >= 0.0, f"Λ − Λ_s not PSD ({what})"
        assert _eigmin(dense.info) > 0.0, f"Λ_s not positive definite ({what})"
    rounded = sx.float32()
    for a in (rounded.diag_info, rounded.edge_info, rounded.eta):
        assert np.array_equal(a.astype(np.float32).astype(float), a)
    mean = np.linalg.solve(xi.info, xi.eta)
    dense = sx.dense()
    assert_close(np.linalg.solve(dense.info, dense.eta), mean, what="mean kept")


@pytest.mark.parametrize("n", [10, 30, 80])
@pytest.mark.parametrize("seed", range(3))
def test_sparsify_stays_under_gtsam_marginals(n: int, seed: int) -> None:
    xi = _tour_xi(n, seed)
    _check_conservative(xi, sparsify(xi))


@pytest.mark.parametrize("seed", range(8))
def test_sparsify_stays_under_random_spd_matrices(seed: int) -> None:
    n = int(np.random.default_rng(100 + seed).integers(2, 40))
    xi = _random_xi(n, seed)
    for extra in (0, 2, 3):
        _check_conservative(xi, sparsify(xi, extra_parents=extra))


@pytest.mark.parametrize("seed", range(3))
def test_sparsify_loses_nothing_when_the_truth_is_a_chain(seed: int) -> None:
    n = 25
    xi = _tree_xi([f - 1 for f in range(n)], seed)
    sx = sparsify(xi)
    _check_conservative(xi, sx)
    assert _kl(xi.info, sx.dense().info) < 1e-6
    assert_close(sx.dense().info, (1.0 - MARGIN) * xi.info, rtol=1e-6, atol=1e-9)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)  # as _tree_xi numbered them
    chain = {tuple(sorted((int(perm[f - 1]), int(perm[f])))) for f in range(1, n)}
    assert chain <= {tuple(e) for e in sx.edges.tolist()}, "the Chow–Liu tree is the chain"


@pytest.mark.parametrize("seed", range(3))
def test_sparsify_loses_nothing_when_the_truth_is_a_tree(seed: int) -> None:
    rng = np.random.default_rng(50 + seed)
    parent = [-1] + [int(rng.integers(0, f)) for f in range(1, 30)]
    xi = _tree_xi(parent, seed)
    sx = sparsify(xi, extra_parents=0)
    _check_conservative(xi, sx)
    assert _kl(xi.info, sx.dense().info) < 1e-6


@pytest.mark.parametrize("n", [30, 80])
def test_sparsify_loses_far_less_than_the_block_diagonal_bound(n: int) -> None:
    xi = _tour_xi(n, 0)
    no_parents = Structure(tuple(range(n)), ((),) * n)
    block_diagonal = sparsify(xi, structure=no_parents)
    assert len(block_diagonal.edges) == 0
    kl_sparse = _kl(xi.info, sparsify(xi).dense().info)
    assert kl_sparse < 0.2 * _kl(xi.info, block_diagonal.dense().info)


def _reference_info(xi: Xi, structure: Structure) -> np.ndarray:
    """Λ_s re-derived densely, as design §3 writes it: G_f = chol(Ω_f)ᵀ [I, −K_f],
    R = Ḡ Σ Ḡᵀ, U_f = R_ff + Σ_{g≠f} (R_fg R_fgᵀ)^½ by eigh, Λ_s = Ḡᵀ U⁻¹ Ḡ (1 − margin)."""
    n = len(xi.lin)
    sigma = np.linalg.inv(xi.info)
    g = np.zeros((3 * n, 3 * n))

    def rows(objects: tuple[int, ...]) -> np.ndarray:
        return np.array([3 * o + a for o in objects for a in range(3)], dtype=int)

    for f, ps in enumerate(structure.parents):
        ff, pp = rows((f,)), rows(ps)
        gain = sigma[np.ix_(ff, pp)] @ np.linalg.inv(sigma[np.ix_(pp, pp)])
        omega = np.linalg.inv(sigma[np.ix_(ff, ff)] - gain @ sigma[np.ix_(pp, ff)])
        top = np.linalg.cholesky(omega).T
        g[np.ix_(ff, ff)] = top
        g[np.ix_(ff, pp)] = -top @ gain
    r = g @ sigma @ g.T
    u_inv = np.zeros_like(r)
    for f in range(n):
        ff = rows((f,))
        u = r[np.ix_(ff, ff)].copy()
        for h in range(n):
            if h != f:
                b = r[np.ix_(ff, rows((h,)))]
                w, v = np.linalg.eigh(b @ b.T)
                u += (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T
        u_inv[np.ix_(ff, ff)] = np.linalg.inv(u)
    return (1.0 - MARGIN) * g.T @ u_inv @ g


@pytest.mark.parametrize(("n", "seed"), [(12, 0), (20, 1), (30, 2), (50, 3)])
@pytest.mark.parametrize("dense_up_to", [0, 10**6], ids=["sparse-net", "dense-net"])
def test_sparsify_fills_only_the_moral_graph(
    n: int, seed: int, dense_up_to: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Against the plain dense re-derivation, with Ḡ held as scipy.sparse and as a dense array
    (``DENSE_UP_TO`` picks one by size: both must give the same Λ_s)."""
    monkeypatch.setattr(sparse_xi, "DENSE_UP_TO", dense_up_to)
    xi = _tour_xi(n, seed)
    sx = sparsify(xi)
    assert sx.structure is not None
    reference = _reference_info(xi, sx.structure)
    pattern = np.eye(n, dtype=bool)
    pattern[sx.edges[:, 0], sx.edges[:, 1]] = pattern[sx.edges[:, 1], sx.edges[:, 0]] = True
    blocks = np.abs(reference).reshape(n, 3, n, 3).max(axis=(1, 3))
    assert np.all(blocks[~pattern] == 0.0), "Ḡᵀ U⁻¹ Ḡ is non-zero off the moral graph"
    scale = float(np.abs(reference).max())
    assert_close(sx.dense().info, reference, rtol=1e-7, atol=1e-9 * scale)


def test_sparsify_reuses_a_structure_and_stays_conservative() -> None:
    old, new = _tour_xi(30, 0), _tour_xi(30, 1)  # another world: the worst stale structure
    before = sparsify(old)
    assert before.structure is not None
    after = sparsify(new, structure=before.structure)
    assert after.structure is before.structure
    np.testing.assert_array_equal(after.edges, before.edges)
    _check_conservative(new, after)


def test_structure_refuses_what_is_not_a_bayes_net() -> None:
    with pytest.raises(ValueError, match="permutation"):
        Structure((0, 0, 1), ((), (0,), (0,)))
    with pytest.raises(ValueError, match=r"parents\[0\]"):
        Structure((0, 1), ((1,), ()))  # parent after its child
    with pytest.raises(ValueError, match=r"parents\[1\]"):
        Structure((0, 1, 2), ((), (0, 0), (0,)))
    with pytest.raises(ValueError, match="structure for 2 objects"):
        sparsify(_random_xi(3, 0), structure=Structure((0, 1), ((), (0,))))


def test_structure_edges_are_the_moral_graph() -> None:
    s = Structure((2, 0, 1, 3), ((2,), (0, 2), (), (1, 0)))
    assert s.edges().tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3]]


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_sparsify_handles_a_few_objects(n: int) -> None:
    xi = _random_xi(n, 7)
    sx = sparsify(xi)
    assert sx.diag_info.shape == (n, 3, 3)
    assert len(sx.edges) == n * (n - 1) // 2  # so few objects: every pair is in the net
    if n:
        _check_conservative(xi, sx)


def test_bytes_per_object_counts_what_travels() -> None:
    sx = sparsify(_random_xi(4, 3), structure=Structure((0, 1, 2, 3), ((), (0,), (1,), (2,))))
    assert len(sx.edges) == 3
    # per object: id 4, lin 3 × 8, η 3 and 6 of Λ's diagonal block; per edge 9 + two uint16
    assert sx.bytes_per_object() == (4 * (4 + 24 + 9 * 4) + 3 * (9 * 4 + 4)) / 4
    assert sx.bytes_per_object(float32=False) == (4 * (4 + 24 + 9 * 8) + 3 * (9 * 8 + 4)) / 4


def _hessian(factor: gtsam.LinearContainerFactor, keys: list[int], values: gtsam.Values) -> tuple:
    graph = gtsam.GaussianFactorGraph()
    graph.push_back(factor.linearize(values))
    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    return graph.hessian(ordering)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_sparse_xi_factor_equals_the_dense_factor(sign: float) -> None:
    xi = _tour_xi(12, 4)
    sx = sparsify(xi)
    keys = [object_key(j) for j in range(12)]
    sparse, dense = sparse_xi_factor(keys, sx, sign), xi_factor(keys, sx.dense(), sign)
    rng = np.random.default_rng(0)
    for offset in (0.0, 0.05):
        values = gtsam.Values()
        for key, pose in zip(keys, sx.lin, strict=True):
            values.insert(key, gtsam.Pose2(*(pose + offset * rng.standard_normal(3))))
        (h_s, e_s), (h_d, e_d) = _hessian(sparse, keys, values), _hessian(dense, keys, values)
        scale = float(np.abs(h_d).max())
        assert_close(h_s, h_d, atol=1e-12 * scale, what="information")
        assert_close(e_s, e_d, atol=1e-12 * scale, what="information vector")
        assert_close(sparse.error(values), dense.error(values), what="error")


def test_an_owner_with_no_object_has_an_empty_sparse_xi_in_float32_too() -> None:
    empty = sparsify(Xi(np.zeros((0, 3)), np.zeros((0, 0)), np.zeros(0))).float32()
    assert empty.lin.shape == (0, 3) and empty.eta.shape == (0,) and len(empty.edges) == 0
    assert empty.dense().info.shape == (0, 0)


def test_the_sparse_xi_module_loads_no_gtsam_until_a_factor_is_made() -> None:
    """A peer that only decodes slots (protocol.codec imports this module) needs no GTSAM."""
    import subprocess
    import sys

    code = "import sys, estimator.sparse_xi, protocol.codec; print('gtsam' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
