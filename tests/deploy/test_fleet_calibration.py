"""Fusion keeps the classes the robots' own evidence leaves open (issue 10).

At every step, for every object whose true class some robot's LOCAL belief still holds with
P ≥ 1e-2, the centralized belief and every robot's DISTRIBUTED belief that knows the object must
hold that class with P ≥ 1e-6: pruning class combinations in the joint (or in D's joins) must not
remove a class that the robots' own evidence leaves open. Ground truth comes from the scenario;
beliefs use the default configuration.

Beyond that floor, an object that only one robot has seen and that nobody has seen for longer
than the information needs to cross the fleet carries the same evidence in every D as in the
centralized belief, so its class marginal must agree with the centralized one.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
import pytest

from deploy.study.fleet import link_model_for
from estimator.hybrid import BeliefConfig
from sim.loader import load_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.stepwise import (
    Array,
    FleetSteps,
    centralized_steps,
    fleet_steps,
    marginals_by_id,
    truncate,
)

KEPT = 1e-2  # a local belief keeps the true class while P(c_j = true) is at least this
LOST = 1e-6  # the fused beliefs must then hold it with at least this
SETTLED_ERROR = 0.05  # |ΔP(c_j = i)| between a D and the centralized belief, settled objects

# The paper's world is cut to 35 steps (all three links are up from k = 13); its whole 60 steps
# run in the slow variant. Seed 5 is where the paper's ratio rule (BeliefConfig.paper()) drops
# object 7's true class to 0 in the centralized belief and every D at k = 31 (measured); seed 3
# where it loses object 12's true class in the centralized belief at k = 50.
PAPER_STEPS = 35
WHOLE_PAPER_SEEDS = (3, 5)
# Seeds of the 100-run study on 12000..12099 where, before the join completed truncated slots
# (estimator.distributed._nearest), the D of r2 and r3 lost a true class at k = 57 that the
# centralized belief and r1's local belief held at 0.015..0.53: r1's newest slot no longer
# carried the combinations of the shared objects D's rows had (even a rebuild lost it).
HELD_OUT_SEEDS = (12003, 12036, 12087)
# (scenario, steps or None for all, seed, first step from which every link is up, hops)
WORLDS = [
    ("lanes:short", None, 0, 1, 4),
    ("lanes:short", None, 1, 1, 4),
    ("paper", PAPER_STEPS, 0, 13, 1),
    ("paper", PAPER_STEPS, 5, 13, 1),
]

Marginals = dict[int, Array]


@dataclass(frozen=True, slots=True)
class _Run:
    """One seeded run: the scenario, the class marginals of every belief after every step (index
    k − 1), and per step the robots that detected each object (``seen[k − 1][j]``)."""

    scenario: Scenario
    fleet: FleetSteps[Marginals]
    centralized: list[Marginals]
    seen: list[dict[int, set[str]]]


def _run(name: str, steps: int | None, seed: int) -> _Run:
    """The run of ``name`` cut to ``steps``; a cut paper world is the first steps of the whole
    one (a run's first k steps do not depend on the steps after them: the frames are drawn step
    by step and every belief steps in order), so the cut and the whole world share one run."""
    if name == "paper" and steps is not None and seed in WHOLE_PAPER_SEEDS:
        return _first_steps(_computed(name, None, seed), steps)
    return _computed(name, steps, seed)


def _first_steps(run: _Run, steps: int) -> _Run:
    fleet = run.fleet
    return _Run(
        truncate(run.scenario, steps),
        dataclasses.replace(
            fleet,
            local={r: v[:steps] for r, v in fleet.local.items()},
            distributed={r: v[:steps] for r, v in fleet.distributed.items()},
        ),
        run.centralized[:steps],
        run.seen[:steps],
    )


@functools.cache
def _computed(name: str, steps: int | None, seed: int) -> _Run:
    s = load_scenario(name)
    s = s if steps is None else truncate(s, steps)
    config = BeliefConfig()
    frames = Simulator(s, seed).all_frames()
    fleet = fleet_steps(s, seed, frames, config, link_model_for(s), marginals_by_id)
    central, _ = centralized_steps(s, seed, frames, config, marginals_by_id)
    seen: list[dict[int, set[str]]] = []
    for k in range(s.steps):
        step: dict[int, set[str]] = {}
        for r in s.robot_ids:
            for d in frames[r][k].detections:
                step.setdefault(d.object_id, set()).add(r)
        seen.append(step)
    return _Run(s, fleet, central, seen)


def _lost_true_classes(run: _Run) -> tuple[list[tuple[object, ...]], int]:
    """Every (belief, step, object, P fused, max P local) where a fused belief lost a true class
    a local belief keeps, and how many (belief, step, object) were checked."""
    s = run.scenario
    truth = {o.id: o.class_index for o in s.objects}
    lost: list[tuple[object, ...]] = []
    checked = 0
    for k in range(1, s.steps + 1):
        for j, c in truth.items():
            local = max(
                (
                    float(run.fleet.local[r][k - 1][j][c])
                    for r in s.robot_ids
                    if j in run.fleet.local[r][k - 1]
                ),
                default=0.0,
            )
            if local < KEPT:
                continue
            fused = {"C": float(run.centralized[k - 1][j][c])}
            for r in s.robot_ids:
                if j in run.fleet.distributed[r][k - 1]:
                    fused[f"D of {r}"] = float(run.fleet.distributed[r][k - 1][j][c])
            checked += len(fused)
            lost.extend((who, k, j, p, local) for who, p in fused.items() if p < LOST)
    return lost, checked


@pytest.mark.parametrize(("name", "steps", "seed", "linked", "hops"), WORLDS)
def test_fused_beliefs_keep_every_true_class_the_local_beliefs_keep(
    name: str, steps: int | None, seed: int, linked: int, hops: int
) -> None:
    run = _run(name, steps, seed)
    lost, checked = _lost_true_classes(run)
    assert checked > 10 * run.scenario.steps, checked  # several objects and beliefs per step
    assert not lost, f"(belief, k, object, P fused, max P local): {lost[:10]}"


@pytest.mark.slow
@pytest.mark.parametrize("seed", WHOLE_PAPER_SEEDS + HELD_OUT_SEEDS)
def test_fused_beliefs_keep_every_true_class_on_the_whole_paper_world(seed: int) -> None:
    # Seed 3 is where the paper's ratio rule loses object 12's true class in the centralized
    # belief at k = 50 (docs/estimator.md, "Known limits"); seed 5 where the default's D of r3
    # held object 7's true class at only 0.0012..0.0026 from k = 36 on (see below; measured
    # before the weights shared their draws across parents).
    run = _run("paper", None, seed)
    lost, checked = _lost_true_classes(run)
    assert checked > 10 * run.scenario.steps, checked
    assert not lost, f"(belief, k, object, P fused, max P local): {lost[:10]}"


def _settled_gaps(run: _Run, linked: int, hops: int) -> list[tuple[float, str, int, int]]:
    """(|ΔP|, robot, k, object) between every D and the centralized belief, for every object
    seen by one robot only and by nobody since step k − hops − 1, at the steps k ≥ linked + hops:
    every D then holds a slot version with all the evidence on it."""
    s = run.scenario
    observers: dict[int, set[str]] = {}
    last: dict[int, int] = {}
    gaps = []
    for k in range(1, s.steps + 1):
        for j, robots in run.seen[k - 1].items():
            observers.setdefault(j, set()).update(robots)
            last[j] = k
        if k < linked + hops:
            continue
        for j, robots in observers.items():
            if len(robots) > 1 or last[j] > k - hops - 1:
                continue
            reference = run.centralized[k - 1][j]
            for r in s.robot_ids:
                d = run.fleet.distributed[r][k - 1].get(j)
                if d is not None:
                    gaps.append((float(np.abs(d - reference).max()), r, k, j))
    return gaps


# The paper world's seeds 3 and 5 are where pruning in D used to correlate an object's class with
# others' (docs/estimator.md, "Hypothesis management"): with the ratios at 150, r3's D pruned 144 →
# 84 hypotheses at k = 27 in seed 5, after which P(c7 true | c9 = 2) was 0.08 against 0.30, and
# r3's own evidence on object 9 dragged object 7 (seen by r1 only, 0.30 in r1's L and in the
# centralized belief) down to 0.007 by k = 35; in seed 3 the D of r1 and r2 held object 12 (seen
# by r3 only) at 0.24 against 0.47 at k = 35. With the default ratios of 1e4 the settled gaps are
# 0.023 and 0.012 (measured); the paper world with seed 3 is checked here only (its run is the
# whole-world one's).
@pytest.mark.parametrize(
    ("name", "steps", "seed", "linked", "hops"), [*WORLDS, ("paper", PAPER_STEPS, 3, 13, 1)]
)
def test_distributed_class_marginals_of_settled_objects_equal_the_centralized(
    name: str, steps: int | None, seed: int, linked: int, hops: int
) -> None:
    gaps = _settled_gaps(_run(name, steps, seed), linked, hops)
    assert len(gaps) > 10, gaps
    gap, r, k, j = max(gaps)
    assert gap <= SETTLED_ERROR, f"D of {r}, step {k}, object {j}: {gap:.4f}"
