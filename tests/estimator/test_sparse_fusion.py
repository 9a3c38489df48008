"""A sparse ξ end to end (``BeliefConfig.xi = "sparse"``, docs/estimator.md "Sparse ξ"): the slot
that ``summarise`` makes (conservative against the dense ξ of the same belief, float32, its
Bayes net reused while the objects stay), its factors in D (the dense factor's sum, small
groups, removal and anti-factors of every piece), version replacement, and a fusion on
generated worlds against the same fusion with the dense ξ.

The dense ξ is the reference throughout: the same local beliefs (the ξ option does not change
how a belief steps) summarised both ways.
"""

from __future__ import annotations

import dataclasses
import functools

import gtsam
import numpy as np
import pytest

import estimator.distributed
import estimator.slots
from deploy.base.build import belief_model, belief_rng
from estimator.distributed import (
    DistributedBelief,
    SlotError,
    clique_groups,
    sparse_xi_factors,
    xi_factor,
)
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.metrics import world_position_cov
from estimator.models import GaussianNoise
from estimator.slots import summarise
from estimator.sparse_xi import MAX_XI_PARENTS, SparseXi, sparsify
from estimator.summary import LocalSummary, ObjectClasses, Slot, Xi
from protocol.codec import MAX_EDGES_PER_OBJECT, StackMessage, decode, encode
from protocol.stack import Stack
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.exact_worlds import distributed_belief, local_slot, no_pruning
from tests.estimator.test_sparse_xi import _random_xi, _tour_xi
from tests.tolerance import assert_close

DENSE = BeliefConfig(classes="per_object", xi="dense")
AUTO = BeliefConfig(classes="per_object")
SPARSE = BeliefConfig(classes="per_object", xi="sparse")
SEEDS = range(3)


@functools.cache
def _world(seed: int, noise: float = 1.0) -> Scenario:
    """3 robots, 20 objects of 3 classes in a 12 m square, 60 steps; the odometry and geometric
    variances × ``noise``."""
    s = generate_scenario(3, 20, 3, seed, steps=60, area=12.0)
    if noise == 1.0:
        return s
    scaled = [
        GaussianNoise(tuple(v * noise for v in n.variances))  # type: ignore[arg-type]
        for n in (s.odometry_noise, s.geometric_noise)
    ]
    return dataclasses.replace(s, odometry_noise=scaled[0], geometric_noise=scaled[1])


def _eigmin(a: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(a)[0])


# -- the option ---------------------------------------------------------------------------------


def test_a_sparse_xi_needs_per_object_classes() -> None:
    assert SPARSE.xi == "sparse" and BeliefConfig().xi == "auto" and DENSE.xi == "dense"
    assert BeliefConfig.paper().xi == "auto"  # a joint table's slots stay dense
    for joint in (BeliefConfig.paper, BeliefConfig.exact):
        with pytest.raises(ValueError, match="per_object"):
            joint(xi="sparse")
    with pytest.raises(ValueError, match="per_object"):
        BeliefConfig(classes="joint", xi="sparse")
    with pytest.raises(ValueError, match="xi 'banded'"):
        BeliefConfig(classes="per_object", xi="banded")


def test_auto_sends_the_sparse_xi_above_its_size(monkeypatch: pytest.MonkeyPatch) -> None:
    """``xi = "auto"``: r1's slot is dense up to ``SPARSE_XI_ABOVE`` objects and sparse above
    (the bound lowered to 5 so that one small world crosses it), equal to the ξ the fixed
    choices send; "dense" and "sparse" ignore the bound."""
    monkeypatch.setattr(estimator.slots, "SPARSE_XI_ABOVE", 5)
    s = _world(0)
    beliefs = [
        HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, c) for c in (AUTO, DENSE, SPARSE)
    ]
    rngs = [belief_rng(0, ["r1"]) for _ in beliefs]
    seen = set()
    for f in Simulator(s, 0).all_frames()["r1"]:
        for b, rng in zip(beliefs, rngs, strict=True):
            b.step([f], rng)
        if not beliefs[0].object_ids:
            continue
        auto, dense, sparse = (summarise(b) for b in beliefs)
        assert auto is not None and dense is not None and sparse is not None
        assert isinstance(dense.per_object.xi, Xi)  # type: ignore[union-attr]
        assert isinstance(sparse.per_object.xi, SparseXi)  # type: ignore[union-attr]
        n = len(auto.object_ids)
        same = sparse if n > 5 else dense
        got, want = auto.per_object.xi, same.per_object.xi  # type: ignore[union-attr]
        assert type(got) is type(want), f"k = {f.k}, {n} objects: {type(got).__name__}"
        assert_close(
            got.dense().info if isinstance(got, SparseXi) else got.info,
            want.dense().info if isinstance(want, SparseXi) else want.info,
            rtol=1e-12,
            atol=0.0,
            what=f"k = {f.k}: Λ",
        )
        seen.add(n > 5)
    assert seen == {False, True}


# -- the slot -----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_the_slot_is_a_conservative_float32_sparse_form_of_the_dense_xi(seed: int) -> None:
    """Every 10 steps, r1's sparse slot against the dense slot of the same belief: Λ_s ⪯ Λ
    (eigmin(Λ − Λ_s) ≥ −1e-9·λmax; measured ≥ +6.7e-9·λmax), Λ_s positive definite, float32
    values, the same linearisation poses and the mean kept (to η's float32 rounding)."""
    s = _world(seed)
    frames = Simulator(s, seed).all_frames()["r1"]
    beliefs = [
        HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, c) for c in (DENSE, SPARSE)
    ]
    rngs = [belief_rng(seed, ["r1"]) for _ in beliefs]
    checked = 0
    for f in frames:
        for b, rng in zip(beliefs, rngs, strict=True):
            b.step([f], rng)
        if f.k % 10 or not beliefs[0].object_ids:
            continue
        dense, sparse = (summarise(b) for b in beliefs)
        assert dense is not None and sparse is not None
        assert sparse.object_ids == dense.object_ids
        d, sp = dense.per_object, sparse.per_object
        assert d is not None and sp is not None
        assert isinstance(d.xi, Xi) and isinstance(sp.xi, SparseXi)
        assert_close(sp.log_phi, d.log_phi, atol=0.0, what="class log φ")
        np.testing.assert_array_equal(sp.xi.lin, d.xi.lin)
        info = sp.xi.dense().info
        top = float(np.linalg.eigvalsh(d.xi.info)[-1])
        assert _eigmin(d.xi.info - info) >= -1e-9 * top, f"k = {f.k}: Λ_s ⋠ Λ"
        assert _eigmin(info) > 0.0, f"k = {f.k}: Λ_s not positive definite"
        for a in (sp.xi.diag_info, sp.xi.edge_info, sp.xi.eta):
            np.testing.assert_array_equal(a.astype(np.float32).astype(float), a)
        mean, mean_s = np.linalg.solve(d.xi.info, d.xi.eta), np.linalg.solve(info, sp.xi.eta)
        # η_s rounded to float32: the mean moves by ≤ ‖Λ_s⁻¹‖·‖Δη‖ (measured ≤ 5.6e-8 m)
        assert_close(mean_s, mean, atol=1e-5, what=f"k = {f.k}: the mean")
        checked += 1
    assert checked >= 4


def test_the_bayes_net_is_reused_while_the_objects_stay_the_same() -> None:
    """A summary whose objects are those of the previous one reuses its net (the very
    Structure) with values recomputed; a new object fits a new net."""
    s = _world(0)
    frames = Simulator(s, 0).all_frames()["r1"]
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, SPARSE)
    rng = belief_rng(0, ["r1"])
    assert belief.xi_structure is None
    reused = refitted = 0
    held = None
    for f in frames:
        belief.step([f], rng)
        summary = summarise(belief)
        if summary is None:
            continue
        po = summary.per_object
        assert po is not None and isinstance(po.xi, SparseXi) and po.xi.structure is not None
        assert belief.xi_structure == (summary.object_ids, po.xi.structure)
        if held is not None and held[0] == summary.object_ids:
            assert po.xi.structure is held[1]
            reused += 1
        else:
            assert held is None or po.xi.structure is not held[1]
            refitted += 1
        held = belief.xi_structure
        # the values are those of the net on this step's dense ξ
        dense = dataclasses.replace(belief.config, xi="dense")
        exact = summarise(_with_config(belief, dense))
        assert exact is not None and exact.per_object is not None
        assert isinstance(exact.per_object.xi, Xi)
        again = sparsify(exact.per_object.xi, structure=po.xi.structure).float32()
        for name in ("diag_info", "edges", "edge_info", "eta"):
            np.testing.assert_array_equal(getattr(again, name), getattr(po.xi, name))
    assert reused >= 10 and refitted >= 3, (reused, refitted)


def _with_config(belief: HybridBelief, config: BeliefConfig) -> HybridBelief:
    """The same belief object seen with another configuration (summarise reads it only)."""
    other = object.__new__(HybridBelief)
    other.__dict__.update(belief.__dict__)
    other.config = config
    other.xi_structure = None
    return other


# -- factors ------------------------------------------------------------------------------------


def _hessian(
    factors: list[gtsam.LinearContainerFactor], keys: list[int], values: gtsam.Values
) -> tuple:
    graph = gtsam.GaussianFactorGraph()
    for f in factors:
        graph.push_back(f.linearize(values))
    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    return graph.hessian(ordering)


def test_the_kept_groupings_are_bounded_and_build_the_same_factors() -> None:
    """A receiver keeps the grouping of the last patterns it built factors for (a sender's
    slots repeat theirs): a pattern seen again builds factors equal, byte for byte, to its
    first ones, and however many patterns arrive (here 70 nets, each different) the receiver
    keeps at most ``_GROUPS_KEPT``."""
    estimator.distributed._groups_cached.cache_clear()
    xi = _tour_xi(30, 7)
    keys = [object_key(j) for j in range(30)]
    first = [f.serialize() for f in sparse_xi_factors(keys, sparsify(xi).float32())]
    for seed in range(70):
        sparse_xi_factors(keys, sparsify(_tour_xi(30, 100 + seed)).float32())
    info = estimator.distributed._groups_cached.cache_info()
    assert info.currsize <= estimator.distributed._GROUPS_KEPT < 70
    again = [f.serialize() for f in sparse_xi_factors(keys, sparsify(xi).float32())]
    assert again == first


@pytest.mark.parametrize(("n", "seed"), [(1, 0), (2, 1), (3, 2), (4, 3), (12, 4), (30, 5)])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_sparse_factors_sum_to_the_dense_factor(n: int, seed: int, sign: float) -> None:
    xi = _tour_xi(n, seed) if n >= 10 else _random_xi(n, seed)
    sx = sparsify(xi).float32()
    keys = [object_key(j) for j in range(n)]
    sparse, dense = sparse_xi_factors(keys, sx, sign), [xi_factor(keys, sx.dense(), sign)]
    assert all(len(f.keys()) <= 4 for f in sparse)
    rng = np.random.default_rng(seed)
    for offset in (0.0, 0.05):  # at the linearisation point and away from it
        values = gtsam.Values()
        for key, pose in zip(keys, sx.lin, strict=True):
            values.insert(key, gtsam.Pose2(*(pose + offset * rng.standard_normal(3))))
        (h_s, e_s), (h_d, e_d) = _hessian(sparse, keys, values), _hessian(dense, keys, values)
        scale = float(np.abs(h_d).max())
        assert_close(h_s, h_d, atol=1e-12 * scale, what="information")
        assert_close(e_s, e_d, atol=1e-12 * scale, what="information vector")
        total = sum(f.error(values) for f in sparse)
        assert_close(total, dense[0].error(values), rtol=1e-9, atol=1e-9, what="error")


@pytest.mark.parametrize(("n", "seed"), [(5, 0), (30, 1), (80, 2)])
def test_clique_groups_take_every_block_once_in_cliques_of_the_pattern(n: int, seed: int) -> None:
    sx = sparsify(_tour_xi(n, seed))
    linked = {tuple(e) for e in sx.edges.tolist()}
    groups = clique_groups(n, sx.edges)
    diag = [v for members, _ in groups for v in members]
    edges = [e for _, ids in groups for e in ids]
    assert sorted(diag) == list(range(n)) and sorted(edges) == list(range(len(sx.edges)))
    for members, ids in groups:
        objects = sorted({*members, *(int(v) for e in ids for v in sx.edges[e])})
        assert 1 <= len(objects) <= 4
        pairs = {(a, b) for i, a in enumerate(objects) for b in objects[i + 1 :]}
        assert pairs <= linked, "a group links objects the pattern does not"
    assert len(groups) < n + len(sx.edges)  # grouped: fewer factors than pieces
    assert clique_groups(n, sx.edges) == groups  # deterministic


# -- fusion: version replacement -----------------------------------------------------------------

# Version replacement is exact algebra at a common linearisation point; iSAM2's relinearisation
# threshold leaves iterates up to ~1e-4 m from it along different paths (dense ξ alike), so this
# checks at noise × 0.1 with a threshold of 1e-6. Measured over seeds 0–2, both downdates:
# ≤ 2.3e-6 m and ≤ 1.2e-7 of the largest covariance entry (dense: 2.2e-6 m, 1.2e-7).
VERSION_CONFIG = no_pruning(
    classes="per_object", xi="sparse", relinearize_threshold=1e-6, extra_updates=2
)
VERSION_POSE_ATOL = 2e-5
VERSION_COV_RTOL = 2e-6
VERSION_STEPS = (20, 40, 60)


def _version_slots(seed: int) -> list[Slot]:
    s = _world(seed, 0.1)
    frames = Simulator(s, seed).all_frames()
    return [local_slot(s, "r2", seed, frames, VERSION_CONFIG, k) for k in VERSION_STEPS]


def _d_after(seed: int, slots: list[Slot], **kw: str) -> DistributedBelief:
    """D of r1 after 30 steps, the ``slots`` integrated one after another."""
    s = _world(seed, 0.1)
    frames = Simulator(s, seed).all_frames()
    d = distributed_belief(s, "r1", seed, frames, VERSION_CONFIG, 30, **kw)
    for v in slots:
        assert d.integrate([v]).integrated == ("r2",)
    return d


def _poses_and_cov(d: HybridBelief) -> tuple[np.ndarray, np.ndarray]:
    keys = [object_key(j) for j in sorted(d.object_ids)] + [d.pose_key("r1")]
    h = d.hypotheses[0]
    poses = np.array([h.pose(k) for k in keys])
    return poses, h.isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()


@pytest.mark.parametrize("downdate", ["remove", "anti"])
@pytest.mark.parametrize("seed", SEEDS)
def test_sparse_versions_replace_each_other(seed: int, downdate: str) -> None:
    """v1, v2, v3 of r2's sparse slot integrated in turn: D equals D with v3 alone; double
    counting (nothing divided out) does not (measured: covariances 23–28 % of the largest entry
    apart, poses 2–3 cm)."""
    versions = _version_slots(seed)
    assert all(isinstance(v.summary.per_object.xi, SparseXi) for v in versions)  # type: ignore[union-attr]
    path = _d_after(seed, versions, downdate=downdate)
    latest = _d_after(seed, versions[-1:], downdate=downdate)
    assert sorted(path.object_ids) == sorted(latest.object_ids)
    (pa, ca), (pb, cb) = _poses_and_cov(path), _poses_and_cov(latest)
    assert_close(pa, pb, atol=VERSION_POSE_ATOL, what="poses")
    scale = float(np.abs(cb).max())
    assert_close(ca, cb, atol=VERSION_COV_RTOL * scale, what="covariance")
    used = path.hypotheses[0].continuous.used["r2"]
    factors = path.hypotheses[0].isam.getFactorsUnsafe()
    assert all(factors.exists(i) for i in used.factor_indices)
    if downdate == "remove":  # exactly the newest version's factors are left
        assert len(used.factor_indices) == len(
            latest.hypotheses[0].continuous.used["r2"].factor_indices
        )
    doubled = _d_after(seed, versions, fusion="double_count")
    _, cd = _poses_and_cov(doubled)
    assert float(np.abs(cd - cb).max()) > 1e3 * VERSION_COV_RTOL * scale


def test_removal_takes_out_every_factor_of_the_old_version() -> None:
    versions = _version_slots(0)
    d = _d_after(0, versions[:1])
    old = d.hypotheses[0].continuous.used["r2"].factor_indices
    assert len(old) > 3  # a sparse ξ is several factors
    d.integrate([versions[1]])
    factors = d.hypotheses[0].isam.getFactorsUnsafe()
    assert not any(factors.exists(i) for i in old)
    new = d.hypotheses[0].continuous.used["r2"].factor_indices
    assert set(new).isdisjoint(old) and all(len(factors.at(i).keys()) <= 4 for i in new)


# -- fusion: against the dense ξ -----------------------------------------------------------------

# D of r1 with r2's and r3's final slots, sparse against dense, on generated worlds. Measured
# over seeds 0–3: mean object error ratio 0.96–1.04; eigmin(Σ_sparse − Σ_dense) of every
# object's world-frame position covariance ≥ +1.3e-4 m² (never overconfident).
ERROR_RATIO = 1.3
COV_TOL = 1e-6


def _fused(seed: int, config: BeliefConfig) -> tuple[list[int], np.ndarray, np.ndarray]:
    """Object ids, position errors (n,) and world-frame position covariances (n, 2, 2) of D."""
    s = _world(seed)
    frames = Simulator(s, seed).all_frames()
    slots = [local_slot(s, r, seed, frames, config) for r in ("r2", "r3")]
    d = distributed_belief(s, "r1", seed, frames, config)
    assert d.integrate(slots).integrated == ("r2", "r3")
    snap = d.snapshot("r1")
    truth = {o.id: o.pose for o in s.objects}
    ids = list(snap.object_ids)
    pose = snap.object_pose[0]
    err = np.hypot(*(pose[:, :2] - np.array([truth[j][:2] for j in ids])).T)
    return ids, err, world_position_cov(snap.object_pose, snap.object_cov)[0]


@pytest.mark.parametrize("seed", range(4))
def test_sparse_fusion_is_as_accurate_as_dense_and_never_more_confident(seed: int) -> None:
    ids_d, err_d, cov_d = _fused(seed, DENSE)
    ids_s, err_s, cov_s = _fused(seed, SPARSE)
    assert ids_s == ids_d and len(ids_d) >= 10
    assert err_s.mean() <= ERROR_RATIO * err_d.mean(), (err_s.mean(), err_d.mean())
    gap = np.linalg.eigvalsh(cov_s - cov_d)[:, 0]
    assert gap.min() >= -COV_TOL, f"object {ids_d[int(np.argmin(gap))]}: {gap.min():.3g} m²"


def test_a_dense_fleet_member_takes_a_sparse_slot_and_the_other_way_round() -> None:
    """The ξ form is the sender's choice: D reads either whatever its own config says."""
    s = _world(1)
    frames = Simulator(s, 1).all_frames()
    for own, sent in ((DENSE, SPARSE), (SPARSE, DENSE)):
        d = distributed_belief(s, "r1", 1, frames, own)
        slot = local_slot(s, "r2", 1, frames, sent)
        assert d.integrate([slot]).integrated == ("r2",)
        assert set(slot.summary.object_ids) <= set(d.object_ids)


# -- check --------------------------------------------------------------------------------------


def _slot(**changes: object) -> Slot:
    sx = sparsify(_random_xi(5, 2)).float32()
    po = ObjectClasses(np.zeros((5, 3)), dataclasses.replace(sx, **changes))  # type: ignore[arg-type]
    return Slot("r2", 3, LocalSummary(tuple(range(5)), (), po))


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"lin": np.zeros((4, 3))}, "shapes"),
        ({"diag_info": np.zeros((5, 3))}, "shapes"),
        ({"edges": np.zeros((3, 3), dtype=int)}, "shapes"),
        ({"edge_info": np.zeros((1, 3, 3))}, "shapes"),
        ({"eta": np.zeros(14)}, "shapes"),
        ({"edges": np.array([[0, 5]]), "edge_info": np.zeros((1, 3, 3))}, "pairs"),
        ({"edges": np.array([[2, 1]]), "edge_info": np.zeros((1, 3, 3))}, "pairs"),
        ({"edges": np.array([[0.0, 1.0]]), "edge_info": np.zeros((1, 3, 3))}, "pairs"),
        ({"edges": np.array([[0, 1], [0, 1]]), "edge_info": np.zeros((2, 3, 3))}, "twice"),
    ],
)
def test_a_sparse_slot_that_does_not_fit_is_refused(
    changes: dict[str, object], message: str
) -> None:
    s = _world(0)
    frames = Simulator(s, 0).all_frames()
    d = distributed_belief(s, "r1", 0, frames, DENSE, 5)
    d.check(_slot())  # the unchanged slot fits
    with pytest.raises(SlotError, match=message):
        d.check(_slot(**changes))


@pytest.mark.parametrize(
    ("pairs", "refused"),
    [([[0, 83], [218, 219]], False), ([[0, 83], [0, 83]], True)],
    ids=["distinct", "twice"],
)
def test_uint16_edges_of_300_objects_are_told_apart(pairs: list[list[int]], refused: bool) -> None:
    """Edges arrive as uint16 (docs/wire.md). (0, 83) and (218, 219) of 300 objects are distinct
    pairs whose keys i·n + j would be equal if computed in uint16 (83, and 65 619 ≡ 83)."""
    n = 300
    sx = SparseXi(
        np.zeros((n, 3)),
        np.broadcast_to(np.eye(3), (n, 3, 3)).copy(),
        np.array(pairs, dtype=np.uint16),
        np.zeros((2, 3, 3)),
        np.zeros(3 * n),
    )
    slot = Slot("r2", 3, LocalSummary(tuple(range(n)), (), ObjectClasses(np.zeros((n, 3)), sx)))
    s = _world(0)
    d = distributed_belief(s, "r1", 0, Simulator(s, 0).all_frames(), DENSE, 5)
    if refused:
        with pytest.raises(SlotError, match="twice"):
            d.check(slot)
    else:
        d.check(slot)


# -- parents beyond the tree parent (BeliefConfig.xi_parents) -----------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_more_parents_keep_more_information_and_the_slot_still_fits_the_wire(seed: int) -> None:
    """r1's final slot with 0..MAX_XI_PARENTS parents beyond the tree parent: each is Λ_s ⪯ Λ,
    some object has exactly that many more parents (the option reaches the net), log det Λ_s
    grows strictly with every parent (measured on these 20-object worlds: by 0.6–19 nats
    each), and even the most parents give a slot the codec sends and reads back bit for bit
    (its edges within MAX_EDGES_PER_OBJECT per object)."""
    s = _world(seed)
    frames = Simulator(s, seed).all_frames()
    dense = local_slot(s, "r1", seed, frames, DENSE).summary.per_object
    assert dense is not None and isinstance(dense.xi, Xi)
    top = float(np.linalg.eigvalsh(dense.xi.info)[-1])
    logdets = []
    for parents in range(MAX_XI_PARENTS + 1):
        config = dataclasses.replace(SPARSE, xi_parents=parents)
        slot = local_slot(s, "r1", seed, frames, config)
        po = slot.summary.per_object
        assert po is not None and isinstance(po.xi, SparseXi) and po.xi.structure is not None
        assert max(len(p) for p in po.xi.structure.parents) == 1 + parents
        info = po.xi.dense().info
        assert _eigmin(dense.xi.info - info) >= -1e-9 * top, f"{parents} parents: Λ_s ⋠ Λ"
        logdets.append(float(np.linalg.slogdet(info)[1]))
        n = len(po.xi.lin)
        assert len(po.xi.edges) <= MAX_EDGES_PER_OBJECT * n
        got = decode(encode(StackMessage("r1", None, Stack((slot,))))).stack.slots[0]
        back = got.summary.per_object
        assert back is not None and isinstance(back.xi, SparseXi)
        for name in ("diag_info", "edges", "edge_info", "eta"):
            np.testing.assert_array_equal(getattr(back.xi, name), getattr(po.xi, name))
    gains = np.diff(logdets)
    assert (gains > 0.1).all(), f"log det Λ_s by parents: {logdets}"


def test_xi_parents_is_bounded_by_what_the_wire_takes() -> None:
    assert BeliefConfig().xi_parents == 2
    for bad in (-1, MAX_XI_PARENTS + 1):
        with pytest.raises(ValueError, match=r"xi_parents must be 0\.\.3"):
            BeliefConfig(xi_parents=bad)
    # the most parents' moral edges: each object with its 1 + MAX parents, pairwise
    assert MAX_EDGES_PER_OBJECT == (1 + MAX_XI_PARENTS) * (2 + MAX_XI_PARENTS) // 2 == 10
