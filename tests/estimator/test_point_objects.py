"""Point objects (``estimator.models.objects``; issue 44 item 1): landmarks measured by bearing and
range, a Point2 per object, ξ over 2 dimensions per object, through the same belief, slots, wire
and fusion as the paper's pose objects.

Each test would fail on the bug it names: the order of (bearing, range), a heading read from a
point, a pose-sized block somewhere in ξ, the weight integral's pinned heading, a conservative
sparse ξ that is not.
"""

from __future__ import annotations

import functools
import math

import gtsam
import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng
from deploy.study.runner import run_single
from estimator.distributed import sparse_xi_factors, xi_factor
from estimator.factors import (
    detection_factor,
    object_key,
    object_prior,
    pose_key,
    semantic_factor,
)
from estimator.hybrid import BeliefConfig, BeliefModel, HybridBelief, as_pose_covariances
from estimator.models import AliasedClassifier, Detection, GaussianNoise, SensorFrame, viewpoint
from estimator.models.classifier import all_log_likelihoods
from estimator.models.objects import POINT, POSE, kind_of_dim, object_kind
from estimator.slots import summarise
from estimator.sparse_xi import SparseXi, sparsify
from estimator.summary import LocalSummary, ObjectClasses, Xi
from protocol.codec import Limits, StackMessage, decode, encode
from protocol.errors import LocalProtocolError
from protocol.stack import Slot, Stack
from sim.generate import dump_scenario, generate_scenario
from sim.loader import ScenarioError, parse_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.tolerance import assert_close

SEEDS = range(3)
METRICS = ("robot_error", "object_error", "class_log_loss")


def _robots(rng: np.random.Generator, k: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-5, 5, (k, 2)), rng.uniform(-np.pi, np.pi, k)])


# --------------------------------------------------------------------------- the kinds


@pytest.mark.parametrize("kind", [POSE, POINT], ids=["pose", "point"])
def test_place_inverts_measure(kind: object) -> None:
    rng = np.random.default_rng(4)
    x = _robots(rng, 50)
    obj = kind.from_pose(_robots(rng, 50))  # type: ignore[attr-defined]
    z = kind.measure(x, obj)  # type: ignore[attr-defined]
    assert z.shape == (50, kind.dim)  # type: ignore[attr-defined]
    placed = kind.place(x, z)  # type: ignore[attr-defined]
    assert_close(placed[:, :2], obj[:, :2], atol=1e-12, what="position")


def test_a_point_is_measured_by_bearing_then_range() -> None:
    """(bearing in the robot's body frame, range): a point 2 m to the robot's left."""
    z = POINT.measure(np.array([1.0, 1.0, math.pi / 2]), np.array([-1.0, 1.0]))
    assert_close(z, [math.pi / 2, 2.0], atol=1e-12)
    assert_close(POINT.as_pose(np.array([3.0, 4.0])), [3.0, 4.0, 0.0], atol=0)
    assert object_kind("point") is POINT and kind_of_dim(2) is POINT and kind_of_dim(3) is POSE
    with pytest.raises(ValueError, match="known: pose, point"):
        object_kind("plane")


def test_point_detection_noise_is_additive_with_the_bearing_wrapped() -> None:
    noise = GaussianNoise((0.04, 0.25))
    got = noise.corrupt(np.array([3.1, 2.0]), np.array([1.0, -1.0]))
    assert_close(got, [3.1 + 0.2 - 2 * math.pi, 2.0 - 0.5], atol=1e-12)
    assert noise.cov.shape == (2, 2)


def test_the_detection_factor_reads_bearing_then_range_with_their_own_variances() -> None:
    """½(δb²/σ²_b + δr²/σ²_r) for a detection off by (δb, δr): the noise of (range, bearing)
    swapped, or a relative-pose factor, gives another error."""
    x, p = np.array([0.5, -1.0, 0.3]), np.array([2.0, 1.5])
    values = gtsam.Values()
    values.insert(pose_key(0, 1), gtsam.Pose2(*x))
    values.insert(object_key(3), p)
    noise = gtsam.noiseModel.Diagonal.Variances(np.array([0.01, 0.09]))
    z = POINT.measure(x, p)
    exact = detection_factor(pose_key(0, 1), object_key(3), z, noise)
    assert exact.error(values) == pytest.approx(0.0, abs=1e-20)
    off = detection_factor(pose_key(0, 1), object_key(3), z + np.array([0.02, 0.3]), noise)
    assert off.error(values) == pytest.approx(0.5 * (0.02**2 / 0.01 + 0.3**2 / 0.09), rel=1e-9)


def test_the_semantic_factor_of_a_point_has_the_numerical_jacobians() -> None:
    """The viewpoint of a point is read at heading 0; its Jacobian in the point is the pose's
    first two columns there (a Point2's tangent is the world translation)."""
    model = AliasedClassifier.random(3, np.random.default_rng(5), noise_std=0.4)
    xk, oj = pose_key(0, 2), object_key(9)
    rng = np.random.default_rng(6)
    for _ in range(5):
        x, p = _robots(rng, 1)[0], rng.uniform(-4, 4, 2)
        z = rng.uniform(0, 1, model.dim)
        values = gtsam.Values()
        values.insert(xk, gtsam.Pose2(*x))
        values.insert(oj, p)
        psi = float(viewpoint(x, POINT.as_pose(p)))
        for c in range(model.num_classes):
            factor = semantic_factor(model, c, z, xk, oj, psi, point=True)
            a, _ = factor.linearize(values).jacobian()
            r = gtsam.noiseModel.Gaussian.Covariance(model.cov(c, psi)).R()
            assert_close(factor.unwhitenedError(values), model.mean(c, psi) - z, atol=1e-12)
            numeric = np.zeros((model.dim, 5))
            for i in range(5):
                for sign in (1.0, -1.0):
                    v = gtsam.Values()
                    step = np.zeros(5)
                    step[i] = sign * 1e-6
                    v.insert(xk, gtsam.Pose2(*x).retract(step[:3]))
                    v.insert(oj, p + step[3:])
                    numeric[:, i] += sign * factor.unwhitenedError(v) / 2e-6
            assert_close(a, r @ numeric, atol=1e-6, what=f"class {c}")


# --------------------------------------------------------------------------- ξ over points


def _point_xi(n: int, seed: int) -> Xi:
    """ξ over n points with a random SPD Λ (Wishart) and a mean near ``lin``."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((2 * n, 2 * n + 4))
    info = a @ a.T / (2 * n + 4) + 1e-2 * np.eye(2 * n)
    lin = rng.uniform(-10, 10, (n, 2))
    return Xi(lin, info, info @ rng.normal(0, 0.1, 2 * n))


@pytest.mark.parametrize("n", [1, 12, 60])  # 60: past DENSE_UP_TO, the sparse Ḡ
@pytest.mark.parametrize("seed", SEEDS)
def test_the_sparse_xi_of_points_is_conservative_and_keeps_the_mean(n: int, seed: int) -> None:
    xi = _point_xi(n, seed)
    sx = sparsify(xi)
    assert sx.dim == 2 and sx.diag_info.shape == (n, 2, 2) and sx.edge_info.shape[1:] == (2, 2)
    for form in (sx, sx.float32()):
        gap = xi.info - form.dense().info
        assert np.linalg.eigvalsh(gap)[0] >= -1e-12 * np.linalg.eigvalsh(xi.info)[-1]
        mean = np.linalg.solve(form.dense().info, form.eta)
        assert_close(mean, np.linalg.solve(xi.info, xi.eta), atol=1e-4, what="mean")
    # per object its id, lin (2 f64), η (2 f32), 3 upper entries (f32); per edge 4 f32, 2 uint16
    assert sx.bytes_per_object() == pytest.approx((n * 40 + len(sx.edges) * 20) / n)


def test_the_factors_of_a_point_xi_are_the_dense_one() -> None:
    xi = _point_xi(7, 1)
    sx = sparsify(xi).float32()
    keys = [object_key(j) for j in range(7)]
    values = gtsam.Values()
    for k, p in zip(keys, sx.lin, strict=True):
        values.insert(k, p + 0.01)
    dense = xi_factor(keys, sx.dense())
    parts = sparse_xi_factors(keys, sx)
    assert sum(f.error(values) for f in parts) == pytest.approx(dense.error(values), rel=1e-9)


def _point_stack(xi: Xi | SparseXi, m: int = 3) -> StackMessage:
    n = len(xi.lin)
    phi = np.linspace(-2.0, 0.0, n * m).reshape(n, m)
    summary = LocalSummary(tuple(range(10, 10 + n)), (), ObjectClasses(phi, xi))
    return StackMessage("r1", (0.0, 0.0), Stack((Slot("r1", 4, summary),)), 4)


@pytest.mark.parametrize("sparse", [False, True], ids=["dense", "sparse"])
def test_point_slots_travel_with_dimension_2_and_come_back_to_the_bit(sparse: bool) -> None:
    xi = _point_xi(6, 2)
    sent: Xi | SparseXi = sparsify(xi).float32() if sparse else xi
    got = decode(encode(_point_stack(sent))).stack.slots[0].summary.per_object
    assert got is not None
    x = got.xi
    assert isinstance(x, SparseXi) == sparse
    assert np.shape(x.lin) == (6, 2)
    assert_close(x.lin, sent.lin, atol=0)
    assert_close(x.eta, sent.eta, atol=0)
    if isinstance(x, SparseXi):
        assert isinstance(sent, SparseXi)
        assert_close(x.diag_info, sent.diag_info, atol=0)
        assert_close(x.edge_info, sent.edge_info, atol=0)
    else:
        assert isinstance(sent, Xi)
        assert_close(x.info, sent.info, atol=0)


def test_a_point_slot_whose_mean_lies_outside_the_world_is_refused_naming_eta() -> None:
    """δmax of points (2√2·W per object), not of poses of 2n/3 objects (0 for one point)."""
    lim = Limits(world_extent=100.0)
    one = Xi(np.zeros((1, 2)), np.eye(2), np.array([250.0, 0.0]))  # δ 250 m < 2√2·100
    decode(encode(_point_stack(one), lim), lim)
    far = Xi(np.zeros((1, 2)), np.eye(2), np.array([290.0, 0.0]))  # beyond 2√2·100 = 283 m
    with pytest.raises(LocalProtocolError) as caught:
        encode(_point_stack(far), lim)
    assert caught.value.field == "slots[0].real.eta"


def test_a_slot_of_objects_of_another_dimension_is_refused_by_name() -> None:
    odd = Xi(np.zeros((2, 4)), np.eye(8), np.zeros(8))
    with pytest.raises(LocalProtocolError) as caught:
        encode(_point_stack(odd))
    assert caught.value.field == "slots[0].real.dim"


# --------------------------------------------------------------------------- worlds of points


@functools.cache
def _world(seed: int, robots: int = 3, objects: int = 20) -> Scenario:
    world = generate_scenario(robots, objects, 3, seed, steps=60, area=12.0, kind="point")
    return parse_scenario(dump_scenario(world), "points.toml")


def test_a_generated_point_world_round_trips_through_its_file() -> None:
    s = _world(7)
    assert s.sensor.objects == "point" and s.geometric_noise.variances == (0.01, 0.1)
    assert all(o.pose[2] == 0.0 for o in s.objects)
    assert belief_model(s).objects is POINT


def test_a_point_object_with_a_heading_is_refused_naming_it() -> None:
    text = dump_scenario(generate_scenario(1, 2, 3, 1, steps=5, kind="point"))
    at = text.index("pose = [", text.index("[[objects]]"))
    end = text.index("]", at)
    bad = text[:at] + "pose = [1.0, 2.0, 0.5" + text[end:]
    with pytest.raises(ScenarioError, match="no heading"):
        parse_scenario(bad, "bad.toml")


def test_point_detections_are_the_kind_s_measurement_with_noise_and_scores_at_heading_0() -> None:
    s = _world(3)
    sim = Simulator(s, 11)
    model = s.classifier.build()
    truth = {o.id: np.array(o.pose[:2]) for o in s.objects}
    seen = 0
    for k in range(1, 20):
        f = sim.frame("r1", k)
        for d in f.detections:
            seen += 1
            z = POINT.measure(f.true_pose, truth[d.object_id])
            err = d.z_geo - z
            err[0] = (err[0] + math.pi) % (2 * math.pi) - math.pi
            assert np.all(np.abs(err) < 6 * np.sqrt(s.geometric_noise.variances))
            psi = viewpoint(f.true_pose, POINT.as_pose(truth[d.object_id]))
            c = s.objects[[o.id for o in s.objects].index(d.object_id)].class_index
            whitened = np.linalg.solve(
                np.linalg.cholesky(model.cov(c, psi)), d.z_sem - model.mean(c, psi)
            )
            assert np.all(np.abs(whitened) < 6)
    assert seen > 10


def test_the_weight_integral_reads_a_point_at_heading_0() -> None:
    """With nearly noiseless geometry, a point's class evidence from one detection is
    log P(z | c, ψ) at the true viewpoint: a heading sampled or read from anywhere else (the
    pinned heading of the involved Gaussian undone) moves ψ and with it the evidence."""
    s = _world(5, robots=1)
    tiny = GaussianNoise((1e-10, 1e-10, 1e-10))
    s = Scenario(
        **{
            **{f: getattr(s, f) for f in Scenario.__dataclass_fields__},
            "odometry_noise": tiny,
            "geometric_noise": GaussianNoise((1e-10, 1e-10)),
        }
    )
    sim = Simulator(s, 2)
    model = belief_model(s)
    belief = HybridBelief(model, {"r1": s.robot("r1").start}, BeliefConfig(num_samples=64))
    rng = belief_rng(2, ["r1"])
    truth = {o.id: np.array(o.pose[:2]) for o in s.objects}
    for k in range(1, 40):
        f = sim.frame("r1", k)
        before = dict(zip(belief.object_ids, belief.log_evidence.copy(), strict=True))
        belief.step([f], rng)
        if len(f.detections) != 1 or f.detections[0].object_id in before:
            continue
        d = f.detections[0]
        psi = viewpoint(f.true_pose, POINT.as_pose(truth[d.object_id]))
        expected = all_log_likelihoods(model.classifier, d.z_sem[None], np.array([[psi]]))[0, 0]
        got = belief.log_evidence[belief.object_ids.index(d.object_id)]
        assert_close(got - got.max(), expected - expected.max(), atol=1e-3, what="evidence")
        return
    pytest.fail("no step with a single new detection")


@pytest.mark.parametrize("seed", SEEDS)
def test_on_a_point_world_the_fleet_matches_the_centralized_belief(seed: int) -> None:
    """L, D, C and ``received`` over 60 steps: D's errors within 5 % of C's and below L's; its
    class log-loss within 0.02 of what it received at every step (measured at most 0.0114,
    0.0027, 0.0070 on these seeds: a point's viewpoint is read in the world frame, so an
    owner's heading drift moves the ψ its class evidence was taken at, where a pose object's
    turns with the robot; pose worlds stay within 0.0022); no refusal, empty join or rebuild."""
    s = _world(7 + seed)
    methods = ("local", "distributed", "centralized", "received")
    r = run_single(s, list(methods), seed, BeliefConfig())
    last = {m: {k: float(np.nanmean(r.metrics[m][k][:, -1])) for k in METRICS} for m in methods}
    for what in ("robot_error", "object_error"):
        assert last["distributed"][what] <= 1.05 * last["centralized"][what], what
        assert last["distributed"][what] < last["local"][what], what
    loss = {m: np.nanmean(r.metrics[m]["class_log_loss"], axis=0) for m in methods}
    assert np.max(loss["distributed"] - loss["received"]) <= 0.02
    assert r.refused.get("distributed", 0) == 0
    assert int(np.sum(r.empty_joins.get("distributed", [0]))) == 0
    assert int(np.sum(r.rebuilds.get("distributed", [0]))) == 0
    assert len(r.stack_bytes.get("distributed", [])) > 0


def test_a_point_snapshot_shows_the_position_and_an_unknown_heading() -> None:
    s = _world(7)
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, BeliefConfig())
    sim, rng = Simulator(s, 1), belief_rng(1, ["r1"])
    for k in range(1, 15):
        belief.step([sim.frame("r1", k)], rng)
    snap = belief.snapshot("r1")
    n = len(belief.object_ids)
    assert snap.object_pose.shape[-2:] == (n, 3) and np.all(snap.object_pose[..., 2] == 0.0)
    assert np.all(snap.object_cov[..., 2, 2] == as_pose_covariances(np.eye(2)[None])[0, 2, 2])
    cont = belief.hypotheses[0].continuous
    key = object_key(belief.object_ids[0])
    assert_close(snap.object_cov[0, 0, :2, :2], cont.isam.marginalCovariance(key), atol=1e-12)
    summary = summarise(belief)
    assert summary is not None and summary.per_object is not None
    assert np.shape(summary.per_object.xi.lin) == (n, 2)
    assert object_prior(key, np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, 1.0)).dim() == 2


def test_the_ledger_reads_each_point_where_the_estimate_holds_it_at_heading_0() -> None:
    s = _world(7)
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, BeliefConfig())
    sim, rng = Simulator(s, 1), belief_rng(1, ["r1"])
    for k in range(1, 25):
        belief.step([sim.frame("r1", k)], rng)
    cont = belief.hypotheses[0].continuous
    ledger = cont.ledger
    assert ledger is not None and len(ledger.robot_keys) > 10
    ledger = ledger.copy()
    index = {j: i for i, j in enumerate(belief.object_ids)}
    ledger.refresh(cont.estimate, belief.model.classifier, index)
    est = cont.estimate
    robots = np.array(
        [[*(lambda p: (p.x(), p.y(), p.theta()))(est.atPose2(k))] for k in ledger.robot_keys]
    )
    points = np.array([est.atPoint2(object_key(j)) for j in ledger.object_ids])
    assert_close(ledger.psi, viewpoint(robots, POINT.as_pose(points)), atol=1e-12, what="ψ")


def _turned(values: gtsam.Values, about: np.ndarray, angle: float, dim: int) -> gtsam.Values:
    """``values`` with every pose and object turned by ``angle`` about the point ``about``."""
    c, s = math.cos(angle), math.sin(angle)
    out = gtsam.Values()
    for key in values.keys():  # noqa: SIM118 - gtsam.Values is not iterable
        if dim == 2 and int(key) >> 56 == ord("o"):
            p = values.atPoint2(key) - about
            out.insert(key, about + np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]]))
            continue
        q = values.atPose2(key)
        x, y = q.x() - about[0], q.y() - about[1]
        out.insert(
            key, gtsam.Pose2(about[0] + c * x - s * y, about[1] + s * x + c * y, q.theta() + angle)
        )
    return out


@pytest.mark.parametrize("kind", ["point", "pose"])
def test_a_slot_reads_its_class_evidence_where_its_xi_is_taken(kind: str) -> None:
    """``slot_evidence = "fused"``: log φ moves every detection's log P(z | c, ψ̂) from L's ψ̂ to
    the one at ``at``. Turning the map by 1 mrad about the start (within L's fit) moves a
    point's world-frame ψ by as much, computed here from the ledger's detections; a pose
    object's ψ turns with the robot, so its log φ stays. ``"local"`` keeps L's log φ."""
    world = generate_scenario(1, 20, 3, 4, steps=30, area=12.0, kind=kind)
    s = parse_scenario(dump_scenario(world), "w.toml")
    model = belief_model(s)
    beliefs = {}
    for ev in ("fused", "local"):
        b = HybridBelief(model, {"r1": s.robot("r1").start}, BeliefConfig(slot_evidence=ev))
        sim, rng = Simulator(s, 3), belief_rng(3, ["r1"])
        for k in range(1, 31):
            b.step([sim.frame("r1", k)], rng)
        beliefs[ev] = b
    b = beliefs["fused"]
    cont = b.hypotheses[0].continuous
    at = _turned(cont.estimate, np.array(s.robot("r1").start[:2]), 1e-3, model.objects.dim)
    own = summarise(b)
    moved = summarise(b, at)
    local = summarise(beliefs["local"], at)
    assert own is not None and moved is not None and local is not None
    assert b.slot_fit_refused == 0
    assert_close(local.per_object.log_phi, own.per_object.log_phi, atol=0)  # type: ignore[union-attr]
    ledger = cont.ledger
    assert ledger is not None
    known = len(ledger.psi)
    expected = b.log_evidence.copy()
    for i in range(known):
        x = at.atPose2(ledger.robot_keys[i])
        key = object_key(ledger.object_ids[i])
        o = (
            POINT.as_pose(at.atPoint2(key))
            if kind == "point"
            else np.array([at.atPose2(key).x(), at.atPose2(key).y(), at.atPose2(key).theta()])
        )
        psi = viewpoint(np.array([x.x(), x.y(), x.theta()]), o)
        now = all_log_likelihoods(b.model.classifier, ledger.scores[i][None], np.array([[psi]]))
        expected[b.object_ids.index(ledger.object_ids[i])] += now[0, 0] - ledger.applied[i]
    expected -= expected.max(axis=1, keepdims=True)
    got = moved.per_object.log_phi  # type: ignore[union-attr]
    assert_close(got, np.maximum(expected, -1000.0), atol=1e-9, what="log φ at the turned map")
    change = np.abs(got - own.per_object.log_phi).max()  # type: ignore[union-attr]
    if kind == "point":
        assert change > 1e-4  # a world-frame viewpoint turns with the map
    else:
        assert change < 1e-8  # a pose object's does not


def test_a_huber_kernel_bounds_what_one_gross_misread_moves_a_point() -> None:
    """``geometric_kernel = "huber"`` (real sightings have gross misreads): one detection whose
    range is 2 m off pulls the object by its whole weight under least squares, and by Huber's
    bounded influence with the kernel — several times less — while on clean detections the two
    estimates agree to a small share of σ."""
    s = _world(4, robots=1)
    frames = Simulator(s, 5).frames("r1")
    hit = next(
        (i, d.object_id)
        for i, f in enumerate(frames[5:], 5)
        for d in f.detections
        if d.z_geo[1] > 3
    )
    k, target = hit
    bad = []
    for i, f in enumerate(frames):
        dets = f.detections
        if i == k:
            dets = tuple(
                Detection(d.object_id, d.z_geo + np.array([0.0, 2.0]), d.z_sem)
                if d.object_id == target
                else d
                for d in dets
            )
        bad.append(SensorFrame(f.robot, f.k, f.odometry, dets, f.true_pose))

    def estimate(kernel: str, run: list[SensorFrame]) -> np.ndarray:
        noise = GaussianNoise(s.geometric_noise.variances, kernel)
        model = belief_model(s)
        model = BeliefModel(
            model.num_classes,
            model.class_prior,
            model.classifier,
            model.odometry_noise,
            noise,
            model.objects,
        )
        belief = HybridBelief(model, {"r1": s.robot("r1").start}, BeliefConfig())
        rng = belief_rng(5, ["r1"])
        for f in run[: k + 1]:
            belief.step([f], rng)
        snap = belief.snapshot("r1")
        return np.array(snap.object_pose[0, snap.object_ids.index(target), :2])

    clean = {kern: estimate(kern, frames) for kern in ("gaussian", "huber")}
    moved = {kern: np.linalg.norm(estimate(kern, bad) - clean[kern]) for kern in clean}
    assert np.linalg.norm(clean["huber"] - clean["gaussian"]) < 0.3 * math.sqrt(0.1)
    assert moved["huber"] < moved["gaussian"] / 2, moved
    assert moved["gaussian"] > 0.1, moved  # the misread does pull a least-squares estimate
