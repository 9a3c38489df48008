"""The class prior P(C) in the local, distributed and centralized class posteriors, against the
batch Laplace reference (estimator.reference), with non-uniform priors and pruning off.

With a uniform prior every P(C) is a constant that normalisation removes, so a prior dropped in
the branching of L, in log φ or in the join of D would go unseen; here it moves the marginals.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from deploy.base.build import belief_model
from estimator.reference import laplace_class_posterior
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.exact_worlds import (
    PRIORS,
    centralized_belief,
    class_marginals_by_id,
    distributed_belief,
    local_belief,
    local_slot,
    no_pruning,
    prior_world,
)
from tests.tolerance import assert_close

# Objects seen obliquely (ψ far from the best views) over five steps: the class evidence stays
# open, so the posterior keeps a visible share of the prior.
_OBLIQUE = ((3.0, 0.8, -30.0), (3.5, -1.0, 20.0))
# Measured: every marginal within 0.005 of the reference (the estimator's Monte Carlo noise, 500
# samples); dropping the prior of new objects in L moves them by 0.08–0.33 on 6 of 8 cases.
MARGINAL_ATOL = 0.015


def _objects(classes: str, robot_ys: tuple[float, ...]) -> list[tuple[float, float, float, int]]:
    m = len(PRIORS[classes])
    out = []
    for r, y in enumerate(robot_ys):
        for i, (x, dy, yaw_deg) in enumerate(_OBLIQUE):
            out.append((x, y + dy, math.radians(yaw_deg), 1 + (2 * r + i) % m))
    return out


def _reference(s: Scenario, frames: dict) -> dict[int, np.ndarray]:
    robots = s.robot_ids
    ids, post = laplace_class_posterior(
        belief_model(s),
        {r: s.robot(r).start for r in robots},
        [[frames[r][k] for r in robots] for k in range(s.steps)],
        no_pruning(),
    )
    out = {j: np.zeros(s.num_classes) for j in ids}
    for classes, p in post.items():
        for j, c in zip(ids, classes, strict=True):
            out[j][c] += p
    return out


def _assert_marginals(actual: dict[int, np.ndarray], ref: dict[int, np.ndarray], what: str) -> None:
    assert sorted(actual) == sorted(ref), what
    for j in ref:
        assert_close(actual[j], ref[j], rtol=0.0, atol=MARGINAL_ATOL, what=f"{what}, object {j}")


@pytest.mark.parametrize("classes", ["two", "three"])
@pytest.mark.parametrize("seed", range(4))
def test_local_class_posterior_matches_laplace_reference_with_a_non_uniform_prior(
    classes: str, seed: int
) -> None:
    s = prior_world([0.0], _objects(classes, (0.0,)), PRIORS[classes], steps=5, sensing=6.0)
    frames = Simulator(s, seed).all_frames()
    belief = local_belief(s, "r1", seed, frames, no_pruning())
    _assert_marginals(class_marginals_by_id(belief), _reference(s, frames), "local")


@pytest.mark.parametrize("classes", ["two", "three"])
@pytest.mark.parametrize("seed", range(3))
def test_fused_and_centralized_class_posteriors_match_laplace_reference_with_a_non_uniform_prior(
    classes: str, seed: int
) -> None:
    # Two robots 8 m apart, two objects each: r1's D learns r2's objects from r2's slot only, so
    # their P(C) enters D through log φ (divided out) and the join (multiplied back in).
    ys = (0.0, 8.0)
    s = prior_world(ys, _objects(classes, ys), PRIORS[classes], steps=5, sensing=6.0)
    frames = Simulator(s, seed).all_frames()
    config = no_pruning()
    slot = local_slot(s, "r2", seed, frames, config)
    d = distributed_belief(s, "r1", seed, frames, config)
    assert d.integrate([slot]).integrated == ("r2",)
    ref = _reference(s, frames)
    _assert_marginals(class_marginals_by_id(d), ref, "distributed r1")
    central = centralized_belief(s, seed, frames, config)
    _assert_marginals(class_marginals_by_id(central), ref, "centralized")
