"""Fusion against the centralized belief, hypothesis by hypothesis (Eq. 12, 17, 19, 20; design
doc §6), and the replacement of a slot version (÷ ξ_{k−1}, − log φ_{k−1}).

Every hypothesis is matched by its class realisation and compared on its weight, its poses and
its full 3 × 3 covariances, with non-uniform class priors, no pruning, several seeds, and in the
near-linear regime (noise × 0.1) where the ξ factors' first-order error is small. Tolerances are
measured maxima with a margin; each constant says what was measured.

A strong object prior (σ = 0.5) exposes where D and the centralized belief differ by
construction: D centres the prior of an object it first learns from a slot on the slot's
linearisation point, the centralized belief (and the slot's owner) on the first measurement
composed with the predicted pose. The gap is quantified below, and the agreement that carrying the
owner's prior centre in the slot would give is written down as xfail.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import gtsam
import numpy as np
import pytest

from agents.links import Schedule
from agents.node import RobotNode
from deploy.base.build import belief_model, belief_rng
from deploy.study.fleet import make_nodes, run_fleet
from estimator.distributed import DistributedBelief
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.exact_worlds import (
    NEAR_LINEAR,
    PRIORS,
    TWO_CLASS_PRIOR,
    by_realisation,
    centralized_belief,
    distributed_belief,
    local_slot,
    no_pruning,
    prior_world,
    weights_by_realisation,
)
from tests.estimator.scenarios import objects_ahead
from tests.tolerance import assert_angles_close, assert_close

WEAK = 100.0
STRONG = 0.5


@dataclass(frozen=True)
class Tolerance:
    """How closely D must equal the centralized belief: normalised weights (absolute), poses (m
    and rad; inf: not compared), covariances (absolute, as a fraction of the largest entry of the
    centralized one)."""

    weight: float
    pose: float
    cov: float


# Objects seen by one robot each: the fusion is exact up to iSAM2's iterate. Measured over 2 priors
# × 3 seeds × 4 robots: poses ≤ 1.0e-7 m, covariances ≤ 1.2e-7; weights ≤ 0.0034, the Monte Carlo
# noise of the weight integral (D and the centralized belief draw different samples).
EXACT = Tolerance(weight=0.015, pose=1e-5, cov=1e-6)
# Objects shared by neighbours: ξ is first order about its owner's linearisation point. Measured
# over 3 seeds × 4 robots: poses ≤ 1.4e-3 m, covariances ≤ 3.9e-3, weights ≤ 6.5e-5.
SHARED = Tolerance(weight=0.015, pose=3e-3, cov=1e-2)
# The strong prior's covariances and weights: measured ≤ 1.2e-5 and ≤ 0.0017. (Dividing the prior
# out of ξ or not moves these covariances by ~1 %.)
STRONG_COV = Tolerance(weight=0.015, pose=math.inf, cov=1e-4)

RING = (("r1", "r2"), ("r2", "r3"), ("r3", "r4"), ("r4", "r1"))
DISJOINT_YS = (0.0, 8.0, 16.0, 24.0)
SHARED_YS = (0.0, 1.5, 3.0, 4.5)
# Between neighbouring lanes 1.5 m apart: every object is seen by two to four robots.
SHARED_OBJECTS = [
    (2.0, 0.75, 0.4, 1),
    (2.0, 2.25, 1.0, 2),
    (2.0, 3.75, -0.4, 1),
    (2.0, -0.6, 0.2, 2),
]


def _config(sigma: float, semantic_poses: bool = False) -> BeliefConfig:
    sigmas = (sigma, sigma, min(sigma, math.pi))
    return no_pruning(object_prior_sigmas=sigmas, semantic_poses=semantic_poses)


def _ring_world(layout: str, classes: str) -> Scenario:
    """Four robots on parallel lanes driving 0.5 m per step; objects seen in steps 1–3 only, so
    that after 7 steps every D holds every robot's final information (relay takes two hops)."""
    prior = PRIORS[classes]
    if layout == "disjoint":
        ys, objects = DISJOINT_YS, _disjoint_objects(len(prior))
    else:
        ys, objects = SHARED_YS, SHARED_OBJECTS
    return prior_world(ys, objects, prior, steps=7, noise_scale=NEAR_LINEAR, speed=0.5)


def _disjoint_objects(m: int) -> list[tuple[float, float, float, int]]:
    """One object ahead of each robot, seen by it alone, from a different side each."""
    yaws = (0.4, -1.2, 2.0, -2.6)
    lanes = enumerate(zip(DISJOINT_YS, yaws, strict=True))
    return [(2.0, y + 0.3, yaw, 1 + i % m) for i, (y, yaw) in lanes]


@functools.cache
def _centralized(
    layout: str, classes: str, seed: int, sigma: float, semantic_poses: bool = False
) -> HybridBelief:
    s = _ring_world(layout, classes)
    config = _config(sigma, semantic_poses)
    return centralized_belief(s, seed, Simulator(s, seed).all_frames(), config)


@functools.cache
def _ring_fleet(
    layout: str,
    classes: str,
    seed: int,
    sigma: float,
    fusion: str = "consistent",
    semantic_poses: bool = False,
) -> dict[str, RobotNode]:
    """The in-process fleet on the ring r1–r2–r3–r4–r1: r3's slot reaches r1 via r2 and via r4."""
    s = _ring_world(layout, classes)
    frames = Simulator(s, seed).all_frames()
    config = _config(sigma, semantic_poses)
    nodes = make_nodes(s, belief_model(s), config, lambda r: belief_rng(seed, [r]), fusion)
    run_fleet(nodes, frames, Schedule(tuple((1, s.steps, a, b) for a, b in RING)), s.steps)
    last_seen = {r: max(f.k for f in fs if f.detections) for r, fs in frames.items()}
    for r, node in nodes.items():
        # The comparison is meaningful only if D holds every robot's final slot content.
        assert all(node.distributed.stamps[o] >= last_seen[o] for o in nodes if o != r), r
    return nodes


def _assert_equals_centralized(
    d: HybridBelief, central: HybridBelief, robot: str, tol: Tolerance
) -> None:
    assert sorted(d.object_ids) == sorted(central.object_ids), robot
    hd, hc = by_realisation(d), by_realisation(central)
    assert set(hd) == set(hc), f"{robot}: realisations differ"
    wd, wc = weights_by_realisation(d), weights_by_realisation(central)
    keys: list[tuple[str, int | None]] = [
        (f"object {j}", object_key(j)) for j in central.object_ids
    ]
    keys.append((f"pose of {robot}", None))
    for c in hc:
        assert_close(wd[c], wc[c], rtol=0.0, atol=tol.weight, what=f"{robot}: weight of {c}")
        for name, key in keys:
            kd = d.pose_key(robot) if key is None else key
            kc = central.pose_key(robot) if key is None else key
            what = f"{robot}: {name} under {c}"
            pd, pc = hd[c].pose(kd), hc[c].pose(kc)
            if math.isfinite(tol.pose):
                assert_close(pd[:2], pc[:2], rtol=0.0, atol=tol.pose, what=what)
                assert_angles_close(pd[2], pc[2], atol=tol.pose, what=what)
            cd, cc = hd[c].isam.marginalCovariance(kd), hc[c].isam.marginalCovariance(kc)
            scale = float(np.abs(cc).max())
            assert_close(cd, cc, rtol=0.0, atol=tol.cov * scale, what=f"covariance: {what}")


SEMANTIC_POSES = pytest.mark.parametrize(
    "semantic_poses", [False, True], ids=["shared", "per-realisation"]
)


@SEMANTIC_POSES
@pytest.mark.parametrize("classes", ["two", "three"])
@pytest.mark.parametrize("seed", range(3))
def test_fusion_on_a_relaying_ring_equals_centralized_for_every_hypothesis(
    classes: str, seed: int, semantic_poses: bool
) -> None:
    central = _centralized("disjoint", classes, seed, WEAK, semantic_poses)
    fleet = _ring_fleet("disjoint", classes, seed, WEAK, semantic_poses=semantic_poses)
    for r, node in fleet.items():
        _assert_equals_centralized(node.distributed, central, r, EXACT)


@SEMANTIC_POSES
@pytest.mark.parametrize("seed", range(3))
def test_fusion_of_shared_objects_on_a_relaying_ring_equals_centralized_to_first_order(
    seed: int, semantic_poses: bool
) -> None:
    central = _centralized("shared", "two", seed, WEAK, semantic_poses)
    fleet = _ring_fleet("shared", "two", seed, WEAK, semantic_poses=semantic_poses)
    for r, node in fleet.items():
        _assert_equals_centralized(node.distributed, central, r, SHARED)


def test_double_counting_on_the_ring_is_seen_by_the_same_comparison() -> None:
    central = _centralized("disjoint", "two", 0, WEAK)
    for r, node in _ring_fleet("disjoint", "two", 0, WEAK, "double_count").items():
        with pytest.raises(AssertionError):
            _assert_equals_centralized(node.distributed, central, r, EXACT)


@pytest.mark.parametrize("seed", range(3))
def test_fusion_with_a_strong_object_prior_equals_centralized_in_weights_and_covariances(
    seed: int,
) -> None:
    central = _centralized("disjoint", "two", seed, STRONG)
    for r, node in _ring_fleet("disjoint", "two", seed, STRONG).items():
        _assert_equals_centralized(node.distributed, central, r, STRONG_COV)


@pytest.mark.xfail(
    strict=True,
    reason="D centres a slot object's prior on the slot's linearisation point, not on the "
    "owner's prior centre (slots do not carry it); measured gap 0.14–0.20 mm here",
)
@pytest.mark.parametrize("seed", range(3))
def test_fusion_with_a_strong_object_prior_equals_centralized_in_means(seed: int) -> None:
    # With a continuous belief per realisation, whose semantic factors relinearise the objects
    # away from their first estimate. (In the shared belief of this near-linear ring iSAM2 never
    # relinearises, so the slot's linearisation point is the prior centre and the gap does not
    # show; test_strong_prior_gap_is_the_shift_of_the_prior_centres measures it elsewhere.)
    central = _centralized("disjoint", "two", seed, STRONG, True)
    fleet = _ring_fleet("disjoint", "two", seed, STRONG, semantic_poses=True)
    for r, node in fleet.items():
        _assert_equals_centralized(node.distributed, central, r, EXACT)


def _prior_gap(seed: int, sigma: float) -> tuple[float, float]:
    """(gap, unexplained): the largest tangent-space difference between D (r1 with r2's final slot)
    and the centralized belief over every realisation and object, and what is left of it after
    subtracting the shift that moving the object priors' centres from the centralized belief's to
    D's predicts, δ = Σ_C Λ₀ (μ_D ⊖ μ_C) (exact for a linear model)."""
    ys = (0.0, 8.0)
    s = prior_world(ys, objects_ahead(ys), TWO_CLASS_PRIOR, steps=8, noise_scale=NEAR_LINEAR)
    frames = Simulator(s, seed).all_frames()
    config = _config(sigma)
    central = centralized_belief(s, seed, frames, config)
    d = distributed_belief(s, "r1", seed, frames, config)
    d.integrate([local_slot(s, "r2", seed, frames, config)])
    ids = sorted(central.object_ids)
    keys = [object_key(j) for j in ids]
    lam0 = np.kron(np.eye(len(ids)), np.diag(1.0 / np.array(config.object_prior_sigmas) ** 2))
    hd, hc = by_realisation(d), by_realisation(central)
    gap = unexplained = 0.0
    for c, h in hc.items():
        cov = h.isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        centres = np.concatenate(
            [
                gtsam.Pose2(*h.object_priors[j]).localCoordinates(
                    gtsam.Pose2(*hd[c].object_priors[j])
                )
                for j in ids
            ]
        )
        actual = np.concatenate(
            [h.estimate.atPose2(k).localCoordinates(hd[c].estimate.atPose2(k)) for k in keys]
        )
        gap = max(gap, float(np.abs(actual).max()))
        unexplained = max(unexplained, float(np.abs(actual - cov @ lam0 @ centres).max()))
    return gap, unexplained


@pytest.mark.parametrize("seed", range(3))
def test_strong_prior_gap_is_the_shift_of_the_prior_centres(seed: int) -> None:
    # Measured at σ = 0.5, 2 and the default (100 m, π): gaps 1.9 mm, 0.12 mm, 2.1e-6 (∝ 1/σ²,
    # the prior's weight in the posterior), of which all but 1.3 % is the predicted shift. The
    # default prior's gap is why the exact tests pass at EXACT.pose.
    gaps = {sigma: _prior_gap(seed, sigma) for sigma in (STRONG, 2.0, WEAK)}
    for sigma, (gap, unexplained) in gaps.items():
        assert unexplained <= 0.05 * gap + 1e-7, (sigma, gap, unexplained)
    assert gaps[2.0][0] <= gaps[STRONG][0] / 8 + 1e-7, gaps
    assert gaps[WEAK][0] <= EXACT.pose / 2, gaps


# r2 drives next to r1 and meets objects 1–2 at step 1, 3–4 at step 3. r1's D has stepped once
# (objects 1, 2) when it integrates r2's slot of step v1 and then of step 8, or only of step 8.
VERSION_OBJECTS = [
    (2.0, 0.75, 0.4, 1),
    (3.5, 2.2, 1.0, 2),
    (4.5, -0.5, -0.4, 3),
    (5.0, 1.2, 2.0, 2),
]
VERSION_CASES = {"v1_brings_objects": 3, "v2_brings_objects": 2}
# Weights are bookkeeping: measured ≤ 2.2e-16. Poses and covariances are iSAM2 iterates reached
# along two paths: measured ≤ 1.0e-5 m and ≤ 3.5e-5 of the largest covariance entry (the strong
# prior's path dependence, xfail below, is 1.2–5.5 mm).
VERSION_WEIGHT_ATOL = 1e-12
VERSION_POSE_ATOL = 1e-4
VERSION_COV = 5e-4


def _versions(
    seed: int, v1_step: int, sigma: float, downdate: str, fusion: str = "consistent"
) -> tuple[DistributedBelief, DistributedBelief]:
    """(D after r2's slots v1 then v2, D after v2 only)."""
    s = prior_world(
        (0.0, 1.5),
        VERSION_OBJECTS,
        PRIORS["three"],
        steps=8,
        noise_scale=NEAR_LINEAR,
        speed=0.5,
    )
    frames = Simulator(s, seed).all_frames()
    config = _config(sigma)
    v1 = local_slot(s, "r2", seed, frames, config, v1_step)
    v2 = local_slot(s, "r2", seed, frames, config)
    both = distributed_belief(s, "r1", seed, frames, config, 1, fusion=fusion, downdate=downdate)
    assert both.integrate([v1]).integrated == ("r2",)
    assert both.integrate([v2]).integrated == ("r2",)
    latest = distributed_belief(s, "r1", seed, frames, config, 1, fusion=fusion, downdate=downdate)
    assert latest.integrate([v2]).integrated == ("r2",)
    return both, latest


def _assert_same_belief(a: DistributedBelief, b: DistributedBelief) -> None:
    assert a.stamps == b.stamps
    assert sorted(a.object_ids) == sorted(b.object_ids)
    ha, hb = by_realisation(a), by_realisation(b)
    assert set(ha) == set(hb)
    wa, wb = weights_by_realisation(a), weights_by_realisation(b)
    keys = [object_key(j) for j in sorted(a.object_ids)] + [a.pose_key("r1")]
    for c in hb:
        what = f"realisation {c}"
        assert_close(wa[c], wb[c], rtol=0.0, atol=VERSION_WEIGHT_ATOL, what=f"weight of {what}")
        pa = np.array([ha[c].pose(k) for k in keys])
        pb = np.array([hb[c].pose(k) for k in keys])
        assert_close(pa[:, :2], pb[:, :2], rtol=0.0, atol=VERSION_POSE_ATOL, what=what)
        assert_angles_close(pa[:, 2], pb[:, 2], atol=VERSION_POSE_ATOL, what=what)
        ca = ha[c].isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        cb = hb[c].isam.jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        scale = float(np.abs(cb).max())
        assert_close(ca, cb, rtol=0.0, atol=VERSION_COV * scale, what=f"covariance of {what}")


@pytest.mark.parametrize("downdate", ["remove", "anti"])
@pytest.mark.parametrize("case", list(VERSION_CASES))
@pytest.mark.parametrize("seed", range(3))
def test_integrating_v1_then_v2_equals_integrating_only_v2(
    seed: int, case: str, downdate: str
) -> None:
    _assert_same_belief(*_versions(seed, VERSION_CASES[case], WEAK, downdate))


def test_double_counting_v1_is_seen_by_the_version_comparison() -> None:
    both, latest = _versions(0, VERSION_CASES["v2_brings_objects"], WEAK, "remove", "double_count")
    with pytest.raises(AssertionError):
        _assert_same_belief(both, latest)


@pytest.mark.xfail(
    strict=True,
    reason="an object new to D takes its prior centre from the version that brought it (v1's "
    "linearisation point); measured gap 1.2–5.5 mm here",
)
@pytest.mark.parametrize("seed", range(3))
def test_version_replacement_with_a_strong_object_prior_is_path_independent(seed: int) -> None:
    _assert_same_belief(*_versions(seed, VERSION_CASES["v1_brings_objects"], STRONG, "remove"))
