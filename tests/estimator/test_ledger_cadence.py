"""The per-object step reads only the keys it needs; the ledger re-reads every detection's poses
every ``ledger_every`` steps and loses nothing by it (issue 40, item 4).

Between refreshes a new detection takes its reference at the estimate its step left
(``SemanticLedger.settle``); a refresh moves every detection by the change since its reference.
The changes telescope, so at every refresh the class evidence equals that of a belief that
refreshed at every step: a settle that took the wrong reference (the propagated estimate, or
none) would show here."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest

from deploy.base.build import belief_model, belief_rng
from estimator.hybrid import BeliefConfig, HybridBelief
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.stepwise import class_log_posteriors


def _world(seed: int) -> Scenario:
    s = generate_scenario(2, 10, 3, 40 + seed, steps=40, area=10.0)
    prior = np.array([0.5, 0.3, 0.2])  # non-uniform, so that the prior cannot cancel
    return dataclasses.replace(s, class_prior=tuple(prior))


def _evidence(s: Scenario, seed: int, every: int) -> list[np.ndarray]:
    return class_log_posteriors(s, seed, BeliefConfig(ledger_every=every))[1]


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("every", [4, 10])
def test_a_refresh_every_few_steps_equals_a_refresh_at_every_step(seed: int, every: int) -> None:
    s = _world(seed)
    each = _evidence(s, seed, 1)
    sparse = _evidence(s, seed, every)
    moved = 0.0
    for k in range(every - 1, s.steps, every):  # the steps whose refresh ran
        np.testing.assert_allclose(sparse[k], each[k], rtol=0, atol=1e-9)
    for k in range(s.steps):
        moved = max(moved, float(np.max(np.abs(sparse[k] - each[k]))))
    # In between, the old detections' evidence waits for the refresh: the two differ (or this
    # test would not see a refresh that never ran).
    assert moved > 1e-6


def test_a_step_between_refreshes_computes_no_full_estimate(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    s = _world(0)
    calls = 0
    full = gtsam.ISAM2.calculateEstimate

    def counted(self: gtsam.ISAM2, *args: object) -> object:
        nonlocal calls
        if not args:
            calls += 1
        return full(self, *args)

    monkeypatch.setattr(gtsam.ISAM2, "calculateEstimate", counted)
    robots = s.robot_ids
    belief = HybridBelief(
        belief_model(s), {r: s.robot(r).start for r in robots}, BeliefConfig(ledger_every=10)
    )
    rng = belief_rng(0, robots)
    frames = Simulator(s, 0).all_frames()
    for k in range(30):
        belief.step([frames[r][k] for r in robots], rng)
    assert calls == 3  # one per refresh, at steps 10, 20 and 30


def test_ledger_every_must_be_positive() -> None:
    with pytest.raises(ValueError, match="ledger_every"):
        BeliefConfig(ledger_every=0)


def test_the_relinearisation_threshold_follows_the_motion_model_unless_set() -> None:
    s = _world(0)
    model = belief_model(s)
    start = {"r1": s.robot("r1").start}
    smallest = float(np.min(model.odometry_noise.sigmas))
    assert HybridBelief(model, start).relinearize_threshold == pytest.approx(smallest / 3)
    fixed = HybridBelief(model, start, BeliefConfig(relinearize_threshold=0.05))
    assert fixed.relinearize_threshold == 0.05
    with pytest.raises(ValueError, match="relinearize_threshold"):
        BeliefConfig(relinearize_threshold=0.0)
