"""The default hypothesis management against the exact reference on small worlds (issue 10).

``BeliefConfig.exact()`` enumerates every class realisation (M^n ≤ 4096); the default
``BeliefConfig()`` prunes by marginal contribution. On worlds of 2–3 robots and 5–6 objects, some
seen only from viewpoints where their classes look alike (so that realisations multiply), the
local, centralized and distributed beliefs of both configurations see the same frames, and every
object's class marginal must agree at every step. The two configurations draw different numbers
of Monte Carlo samples (one set per parent), so part of the difference is sampling noise; the
largest measured is 0.020 (world "three", seed 1, centralized, k = 8), the paper's ratio rule
reaches 0.13 (world "three", seed 0, r2's local belief, k = 14).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import pytest

from deploy.study.fleet import link_model_for
from estimator.hybrid import BeliefConfig
from sim.loader import parse_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.scenarios import fleet_text
from tests.estimator.stepwise import (
    Array,
    centralized_steps,
    fleet_steps,
    marginals_by_id,
)

# Largest allowed |P_default(c_j = i) − P_exact(c_j = i)|, any object, class, belief and step.
MARGINAL_ERROR = 0.05

CONFIGS = {
    "exact": BeliefConfig.exact(),
    # The exact reference's slots carry class evidence read at L's estimate (joint tables):
    # the default's pruning is compared on the same evidence. Where the default reads it (the
    # fused estimate) is tested against the exact centralized belief below.
    "default": BeliefConfig(slot_evidence="local"),
    "fused_evidence": BeliefConfig(),
    "paper": BeliefConfig.paper(),
}
SEEDS = (0, 1, 2)
STEPS = 14

_UNIFORM_PAPER = '[classes]\ncount = 2\nprior = [0.5, 0.5]\n[classifier]\nmodel = "paper"\n'
# Three classes with a non-uniform prior; classes 1 and 2 look alike from ψ = −90° (as in the
# paper's model), class 3 blurs towards class 1 (the classifier of the bundled world lanes).
_THREE_CLASSES = """\
[classes]
count = 3
prior = [0.5, 0.3, 0.2]
[classifier]
model = "aliased"
alias = [2, 1, 1]
best_view_deg = [90.0, 90.0, 0.0]
noise_std = 0.35
"""

# Yaw −π/2: the robots, driving along +x, see the object from ψ ≈ −90°, where classes 1 and 2
# look alike; yaw π/2: from ψ ≈ +90°, where they are best told apart.
_ALIKE, _APART = -math.pi / 2, math.pi / 2

Marginals = dict[int, Array]


def _schedule(steps: int, pairs: list[tuple[str, str]]) -> str:
    edges = ", ".join(f'[1, {steps}, "{a}", "{b}"]' for a, b in pairs)
    return f'mode = "schedule"\nschedule = [{edges}]'


def _world(name: str) -> Scenario:
    """``two``: 3 robots (chain r1–r2–r3), 6 objects, the paper's 2 classes; ``three``: 2 robots,
    5 objects, 3 aliased classes with prior (0.5, 0.3, 0.2)."""
    if name == "two":
        objects = [
            (2.0, 1.5, _ALIKE, 1),
            (2.5, -1.0, _APART, 2),
            (3.0, 4.0, _ALIKE, 2),
            (3.5, 1.0, _APART, 1),
            (4.0, 5.0, _ALIKE, 1),
            (4.5, 7.5, _ALIKE, 2),
        ]
        comm = _schedule(STEPS, [("r1", "r2"), ("r2", "r3")])
        return parse_scenario(
            fleet_text("two", STEPS, (0.0, 3.0, 6.0), objects, communication=comm), "two.toml"
        )
    objects = [
        (2.0, 1.0, _ALIKE, 1),
        (2.5, -1.0, _APART, 2),
        (3.5, 1.5, _ALIKE, 2),
        (4.0, 4.5, 0.0, 3),
        (4.5, 2.0, _ALIKE, 3),
    ]
    text = fleet_text(
        "three", STEPS, (0.0, 3.0), objects, communication=_schedule(STEPS, [("r1", "r2")])
    )
    assert _UNIFORM_PAPER in text, "fleet_text's [classes] table changed"
    return parse_scenario(text.replace(_UNIFORM_PAPER, _THREE_CLASSES), "three.toml")


@dataclass(frozen=True, slots=True)
class _Run:
    """Class marginals after every step (index k − 1) of every belief of one configuration, and
    the largest number of hypotheses each kind of belief held."""

    local: dict[str, list[Marginals]]
    distributed: dict[str, list[Marginals]]
    centralized: list[Marginals]
    most: dict[str, int]


@functools.cache
def _run(world: str, seed: int, config: str) -> _Run:
    s = _world(world)
    frames = Simulator(s, seed).all_frames()
    cfg = CONFIGS[config]
    fleet = fleet_steps(s, seed, frames, cfg, link_model_for(s), marginals_by_id)
    central, most = centralized_steps(s, seed, frames, cfg, marginals_by_id)
    counts = {
        "local": fleet.max_local_hypotheses,
        "distributed": fleet.max_distributed_hypotheses,
        "centralized": most,
    }
    return _Run(fleet.local, fleet.distributed, central, counts)


def _series(run: _Run, belief: str) -> dict[str, list[Marginals]]:
    """The marginals of every belief of one kind, by owner (``"C"`` for the centralized)."""
    if belief == "centralized":
        return {"C": run.centralized}
    return run.local if belief == "local" else run.distributed


def _worst(actual: list[Marginals], reference: list[Marginals]) -> tuple[float, int, int]:
    """The largest |ΔP(c_j = i)| over steps, objects and classes, with its step k and object j.
    Both beliefs must know the same objects at every step."""
    worst = (0.0, 0, -1)
    for k, (a, ref) in enumerate(zip(actual, reference, strict=True), start=1):
        assert sorted(a) == sorted(ref), f"step {k}: objects {sorted(a)} ≠ {sorted(ref)}"
        for j, p in a.items():
            err = float(np.max(np.abs(p - ref[j])))
            if err > worst[0]:
                worst = (err, k, j)
    return worst


def _worst_of(world: str, seed: int, config: str, belief: str) -> tuple[float, int, int, str]:
    """:func:`_worst` of ``config`` against the exact reference over every belief of a kind."""
    actual = _series(_run(world, seed, config), belief)
    reference = _series(_run(world, seed, "exact"), belief)
    return max((*_worst(actual[owner], reference[owner]), owner) for owner in sorted(reference))


@pytest.mark.parametrize("world", ["two", "three"])
def test_reference_worlds_enumerate_every_realisation_and_make_the_default_prune(
    world: str,
) -> None:
    s = _world(world)
    exact, default = _run(world, 0, "exact"), _run(world, 0, "default")
    objects = len(exact.centralized[-1])
    assert objects == len(s.objects)
    # the reference is an enumeration: nothing pruned, far from the cap of 4096
    assert exact.most["centralized"] == s.num_classes**objects
    assert exact.most["distributed"] == s.num_classes**objects
    assert s.num_classes**objects <= 4096
    # and the default does prune on these worlds: the comparison is not one of equals
    assert default.most["centralized"] < exact.most["centralized"], default.most
    assert default.most["distributed"] < exact.most["distributed"], default.most


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("world", ["two", "three"])
@pytest.mark.parametrize("belief", ["local", "centralized", "distributed"])
def test_default_pruning_keeps_every_class_marginal_of_the_exact_reference(
    belief: str, world: str, seed: int
) -> None:
    err, k, j, owner = _worst_of(world, seed, "default", belief)
    assert err <= MARGINAL_ERROR, f"{belief} belief of {owner}, step {k}, object {j}: {err:.4f}"


def test_default_pruning_keeps_the_marginal_where_the_paper_rule_strays() -> None:
    # On world "three", seed 0, the paper's joint-ratio rule moves r2's local class marginal of
    # object 1 by 0.13 at k = 14 (measured); the default stays within 0.01 of the reference.
    err_paper, k, j, owner = _worst_of("three", 0, "paper", "local")
    assert err_paper > MARGINAL_ERROR, (err_paper, k, j, owner)
    reference = _run("three", 0, "exact").local[owner][k - 1][j]
    default = _run("three", 0, "default").local[owner][k - 1][j]
    err_default = float(np.max(np.abs(default - reference)))
    assert err_default <= MARGINAL_ERROR, (err_default, k, j, owner)
    assert err_default < err_paper / 5


def _last_gap_to_centralized(run: _Run, reference: _Run, last: int = 3) -> float:
    """The largest |ΔP(c_j = i)| between every distributed belief of ``run`` and the exact
    centralized belief of ``reference`` over the last ``last`` steps (when the news has spread)."""
    gap = 0.0
    for series in run.distributed.values():
        for k in range(len(series) - last, len(series)):
            central = reference.centralized[k]
            for j, p in series[k].items():
                if j in central:
                    gap = max(gap, float(np.max(np.abs(p - central[j]))))
    return gap


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("world", ["two", "three"])
def test_slot_evidence_read_at_the_fused_estimate_is_no_farther_from_the_exact_centralized(
    world: str, seed: int
) -> None:
    """``slot_evidence = "fused"`` (the default) against ``"local"``, both against the exact
    centralized belief at the last steps. Measured: world "three" 0.0068 / 0.0060 / 0.0069
    against 0.0113 / 0.0178 / 0.0294 (the fused viewpoints move D towards C); world "two" (a
    chain, where D lags C by what has not reached it) 0.160 / 0.221 / 0.358 against 0.167 /
    0.220 / 0.356."""
    exact = _run(world, seed, "exact")
    fused = _last_gap_to_centralized(_run(world, seed, "fused_evidence"), exact)
    local = _last_gap_to_centralized(_run(world, seed, "default"), exact)
    assert fused <= local + 0.005, (fused, local)
    if world == "three":
        assert fused < 0.8 * local, (fused, local)
