"""A quiet fleet's distributed beliefs equal the centralized belief (issue 10).

No robot sees anything after step ``QUIET_AFTER`` (every later frame keeps its odometry and loses
its detections). Once the fleet has been quiet for as many steps as its communication graph has
hops, every robot's D has integrated every robot's last informative slot, so every D must know
exactly the centralized belief's objects, with the same class marginals (within 0.02) and the same
object means (the hypotheses' weighted mean position, within 1e-3 m). Near-linear regime: odometry
and geometric variances × 0.1, iSAM2 relinearising at every update; default pruning.

Worlds: ``lanes:short`` (5 robots, the chain r1–r2–r3–r4–r5: 4 hops) and a ring of 4 robots
(links r1–r2, r2–r3, r3–r4, r4–r1 only: 2 hops).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np
import pytest

from deploy.study.fleet import link_model_for
from estimator.hybrid import BeliefConfig, HybridBelief
from sim.loader import load_scenario, parse_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.scenarios import fleet_text
from tests.estimator.stepwise import (
    Array,
    centralized_steps,
    fleet_steps,
    marginals_by_id,
    mean_positions_by_id,
    quiet_after,
    scaled_noise,
)

POSITION_ERROR = 1e-3  # m, between D's and the centralized belief's mean object positions
MARGINAL_ERROR = 0.02  # |ΔP(c_j = i)|
NEAR_LINEAR = 0.1
# The default (dense) ξ. With xi = "sparse" the means measured the same to 1 µm: on these worlds
# (≤ 7 objects per slot) its Bayes net holds every object's neighbours.
CONFIG = BeliefConfig(relinearize_skip=1, partial_relinearization=False)
QUIET_AFTER = 12
SEEDS = (0, 1, 2, 3)

RING_STEPS = 16
RING_EDGES = (("r1", "r2"), ("r2", "r3"), ("r3", "r4"), ("r4", "r1"))
HOPS = {"lanes": 4, "ring": 2}

# With every slot linearised at its owner's own point (``slot_linearisation = "local"``, the
# reference) the weighted object means differ by more than 1e-3 m where several robots' slots
# carry one object linearised far apart: ξ is first order about that point (docs/
# distributed.md, "Known approximation"), and the gap scales with the variances. Ring, seed 0:
# object 7 is seen by r2, r3 and r4, whose estimates differ by up to 0.37 m and 0.11 rad; 16.7 mm
# at the nominal noise, 1.74 mm at × 0.1, 0.18 mm at × 0.01. Lanes, seed 3: object 11 is seen by
# r4 and r5 (4 steps each), estimates 0.45 m and 0.09 rad apart; 1.91 mm at × 0.1, 0.20 mm at
# × 0.01 (lanes 0 and ring 2 were 1.03 and 1.27 mm). Linearised at their owners' fused
# estimates (the default) every case is within 0.5 mm (measured 0.09–0.49 mm at × 0.1).
LOCAL = dataclasses.replace(CONFIG, slot_linearisation="local")


def _ring() -> Scenario:
    """4 robots along +x, 3 m apart, 7 objects between and beside them; the schedule links each
    robot to its two ring neighbours at every step (r1 and r4, 9 m apart, are neighbours)."""
    alike, apart = -math.pi / 2, math.pi / 2
    objects = [
        (2.0, 1.5, alike, 1),
        (3.0, -1.0, apart, 2),
        (3.5, 4.5, 0.0, 2),
        (2.5, 7.5, alike, 1),
        (4.0, 10.5, apart, 2),
        (5.0, 1.5, apart, 1),
        (5.5, 6.0, alike, 2),  # seen by r2, r3 and r4
    ]
    edges = ", ".join(f'[1, {RING_STEPS}, "{a}", "{b}"]' for a, b in RING_EDGES)
    comm = f'mode = "schedule"\nschedule = [{edges}]'
    text = fleet_text("ring", RING_STEPS, (0.0, 3.0, 6.0, 9.0), objects, communication=comm)
    return parse_scenario(text, "ring.toml")


def _world(name: str, scale: float) -> Scenario:
    s = load_scenario("lanes:short") if name == "lanes" else _ring()
    return scaled_noise(s, scale)


@dataclass(frozen=True, slots=True)
class _Summary:
    marginals: dict[int, Array]
    means: dict[int, Array]


def _summary(belief: HybridBelief) -> _Summary:
    return _Summary(marginals_by_id(belief), mean_positions_by_id(belief))


@dataclass(frozen=True, slots=True)
class _Quiet:
    """Every robot's D and the centralized belief at the steps k ≥ QUIET_AFTER + hops."""

    distributed: dict[tuple[str, int], _Summary]
    centralized: dict[int, _Summary]


@functools.cache
def _quiet_run(
    world: str, seed: int, scale: float = NEAR_LINEAR, config: BeliefConfig = CONFIG
) -> _Quiet:
    s = _world(world, scale)
    frames = quiet_after(Simulator(s, seed).all_frames(), QUIET_AFTER)
    fleet = fleet_steps(s, seed, frames, config, link_model_for(s), _summary)
    central, _ = centralized_steps(s, seed, frames, CONFIG, _summary)
    steps = range(QUIET_AFTER + HOPS[world], s.steps + 1)
    assert len(steps) >= 2
    return _Quiet(
        {(r, k): fleet.distributed[r][k - 1] for r in s.robot_ids for k in steps},
        {k: central[k - 1] for k in steps},
    )


def _worst(
    world: str, seed: int, field: str, scale: float = NEAR_LINEAR, config: BeliefConfig = CONFIG
) -> tuple[float, str, int, int]:
    """The largest gap between a D and the centralized belief: (gap, robot, k, object)."""
    run = _quiet_run(world, seed, scale, config)
    worst = (0.0, "", 0, -1)
    for (r, k), d in run.distributed.items():
        c = run.centralized[k]
        for j, value in getattr(d, field).items():
            ref = getattr(c, field)[j]
            gap = float(np.hypot(*(value - ref))) if field == "means" else np.abs(value - ref).max()
            worst = max(worst, (float(gap), r, k, j))
    return worst


def _cases() -> list[tuple[str, int]]:
    return [(world, seed) for world in ("lanes", "ring") for seed in SEEDS]


@pytest.mark.parametrize(("world", "seed"), _cases())
def test_quiet_fleet_knows_the_centralized_objects_and_class_marginals(
    world: str, seed: int
) -> None:
    run = _quiet_run(world, seed)
    for (r, k), d in run.distributed.items():
        assert sorted(d.marginals) == sorted(run.centralized[k].marginals), (r, k)
    gap, r, k, j = _worst(world, seed, "marginals")
    assert gap <= MARGINAL_ERROR, f"D of {r}, step {k}, object {j}: {gap:.4f}"


@pytest.mark.parametrize(("world", "seed"), _cases())
def test_quiet_fleet_object_means_equal_the_centralized(world: str, seed: int) -> None:
    gap, r, k, j = _worst(world, seed, "means")
    assert gap <= POSITION_ERROR, f"D of {r}, step {k}, object {j}: {1e3 * gap:.3f} mm"


@pytest.mark.parametrize(("world", "seed"), [("lanes", 3), ("ring", 0)])
def test_quiet_fleet_slots_at_their_owners_points_are_off_by_xis_first_order_error(
    world: str, seed: int
) -> None:
    # The reference (every slot at L's own point): the gap is ξ's first-order error, second
    # order in the noise's standard deviation, so a tenth of the variances gives about a tenth
    # of it. The default above closes it: the slots are linearised where the receivers are.
    gap, *where = _worst(world, seed, "means", config=LOCAL)
    smaller, *_ = _worst(world, seed, "means", NEAR_LINEAR / 10, LOCAL)
    assert gap > POSITION_ERROR, (gap, *where)
    assert smaller < gap / 5, (smaller, gap)
    assert smaller <= POSITION_ERROR / 2, smaller
