"""The study fleet sends what the lock-step agents send (delta gossip, the default) or every held
slot (full): the same beliefs and metrics bit for bit, and the same deliveries
(deploy/study/fleet.py; docs/architecture.md, "The study's gossip")."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from deploy.study.fleet import run_fleet
from deploy.study.runner import run_single
from estimator.hybrid import BeliefConfig
from sim.loader import load_scenario
from sim.scenario import Scenario

FLEETS = ["distributed", "double_count"]


def _short(name: str, steps: int) -> Scenario:
    s = load_scenario(name)
    robots = tuple(dataclasses.replace(r, actions=r.actions[:steps]) for r in s.robots)
    return dataclasses.replace(s, steps=steps, robots=robots)


# A delta stack is the full one without the slots no peer lacks, plus the digest: a few bytes a
# robot (an id and an (epoch, stamp) pair; epoch 0 in a study). On the paper world (3 robots, a
# schedule that needs relays) some peer lacks every held slot, so delta costs the digest (+1.2 %);
# on the lanes world (5 robots in range) it saves 7 %.
DIGEST_BYTES_PER_ROBOT = 8


@pytest.mark.parametrize(
    ("world", "steps", "seed", "fewer"), [("paper", 24, 4, False), ("lanes", 30, 11, True)]
)
def test_delta_gossip_gives_the_same_beliefs_as_full_stacks(
    world: str, steps: int, seed: int, fewer: bool
) -> None:
    s = _short(world, steps)
    delta = run_single(s, FLEETS, seed, BeliefConfig(), gossip="delta")
    full = run_single(s, FLEETS, seed, BeliefConfig(), gossip="full")
    for method in FLEETS:
        for metric, values in full.metrics[method].items():
            assert np.array_equal(delta.metrics[method][metric], values, equal_nan=True), (
                method,
                metric,
            )
        assert delta.empty_joins[method] == full.empty_joins[method]
        sent, whole = delta.stack_bytes[method], full.stack_bytes[method]
        assert len(sent) == len(whole) > 0, method  # the same deliveries
        digest = DIGEST_BYTES_PER_ROBOT * (len(s.robots) + 1)
        assert all(d <= f + digest for d, f in zip(sent, whole, strict=True)), method
        assert (sum(sent) < sum(whole)) == fewer, (method, sum(sent), sum(whole))
        assert delta.refused[method] == full.refused[method] == 0


def test_an_unknown_gossip_is_refused_before_a_step() -> None:
    s = _short("paper", 2)
    with pytest.raises(ValueError, match="gossip 'some'"):
        run_fleet({}, {}, None, s.steps, gossip="some")  # type: ignore[arg-type]
