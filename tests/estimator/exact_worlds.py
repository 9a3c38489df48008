"""Worlds and runners for the tests that check the estimator's maths exactly (issue 10).

Every world here has a non-uniform class prior, so that a missing or doubled P(C) shows in the
weights, and the beliefs run without pruning, so that every realisation can be compared.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from deploy.base.build import belief_model, belief_rng
from estimator.distributed import DistributedBelief
from estimator.hybrid import BeliefConfig, HybridBelief, Hypothesis
from estimator.models import SensorFrame
from estimator.slots import summarise
from estimator.summary import Slot
from sim.loader import parse_scenario
from sim.scenario import Scenario
from tests.estimator.scenarios import fleet_text

TWO_CLASS_PRIOR = (0.8, 0.2)
THREE_CLASS_PRIOR = (0.6, 0.3, 0.1)
# Three classes, each blurred with an alias away from its best view; the score noise is large
# enough that a few sightings leave the class posterior open and the prior visibly in it.
THREE_CLASS_MODEL = (
    'model = "aliased"\nalias = [2, 3, 1]\nbest_view_deg = [90.0, -30.0, 200.0]\nnoise_std = 0.8'
)
PRIORS = {"two": TWO_CLASS_PRIOR, "three": THREE_CLASS_PRIOR}

# The near-linear regime of the exactness tests: odometry and geometric variances × 0.1.
NEAR_LINEAR = 0.1

_ODOMETRY_VAR = (0.003, 0.003, 0.001)
_GEOMETRIC_VAR = (0.1, 0.1, 0.01)
_UNIFORM_PAPER = '[classes]\ncount = 2\nprior = [0.5, 0.5]\n[classifier]\nmodel = "paper"\n'

Frames = Mapping[str, Sequence[SensorFrame]]
Realisations = dict[tuple[int, ...], Hypothesis]


def no_pruning(**overrides: object) -> BeliefConfig:
    """Keep every realisation; check every variable for relinearisation at every update (see
    docs/estimator.md)."""
    fields: dict[str, object] = {
        "prune_ratio": 1e300,
        "max_hypotheses": 100_000,
        "robot_budget": None,
        "relinearize_skip": 1,
        "partial_relinearization": False,
        "classes": "joint",
    }
    fields.update(overrides)
    return BeliefConfig(**fields)  # type: ignore[arg-type]


def prior_world(
    robot_ys: Sequence[float],
    objects: Sequence[tuple[float, float, float, int]],
    prior: Sequence[float],
    *,
    steps: int,
    noise_scale: float = 1.0,
    **kw: object,
) -> Scenario:
    """:func:`fleet_text`'s world with the class ``prior`` (two classes: the paper's classifier;
    three: :data:`THREE_CLASS_MODEL`) and odometry and geometric variances × ``noise_scale``."""
    text = fleet_text(
        "exact",
        steps,
        robot_ys,
        objects,
        odometry_var=[v * noise_scale for v in _ODOMETRY_VAR],
        geometric_var=[v * noise_scale for v in _GEOMETRIC_VAR],
        **kw,  # type: ignore[arg-type]
    )
    assert _UNIFORM_PAPER in text, "fleet_text's [classes] table changed"
    model = 'model = "paper"' if len(prior) == 2 else THREE_CLASS_MODEL
    classes = f"[classes]\ncount = {len(prior)}\nprior = {list(prior)}\n[classifier]\n{model}\n"
    return parse_scenario(text.replace(_UNIFORM_PAPER, classes), "exact.toml")


def local_belief(
    s: Scenario, robot: str, seed: int, frames: Frames, config: BeliefConfig, steps: int = -1
) -> HybridBelief:
    """L of ``robot`` after its first ``steps`` frames (all by default)."""
    belief = HybridBelief(belief_model(s), {robot: s.robot(robot).start}, config)
    rng = belief_rng(seed, [robot])
    for f in frames[robot][: steps if steps >= 0 else None]:
        belief.step([f], rng)
    return belief


def local_slot(
    s: Scenario, robot: str, seed: int, frames: Frames, config: BeliefConfig, steps: int = -1
) -> Slot:
    """``robot``'s slot after its first ``steps`` frames (all by default), stamped with the step."""
    summary = summarise(local_belief(s, robot, seed, frames, config, steps))
    assert summary is not None, f"{robot} has seen no object"
    return Slot(robot, steps if steps >= 0 else s.steps, summary)


def distributed_belief(
    s: Scenario,
    robot: str,
    seed: int,
    frames: Frames,
    config: BeliefConfig,
    steps: int = -1,
    **kw: str,
) -> DistributedBelief:
    """D of ``robot`` after its first ``steps`` frames (all by default), nothing integrated."""
    d = DistributedBelief(belief_model(s), robot, s.robot(robot).start, config, **kw)
    rng = belief_rng(seed, [robot])
    for f in frames[robot][: steps if steps >= 0 else None]:
        d.step([f], rng)
    return d


def centralized_belief(
    s: Scenario, seed: int, frames: Frames, config: BeliefConfig
) -> HybridBelief:
    """One belief over every robot, fed every frame."""
    robots = s.robot_ids
    belief = HybridBelief(belief_model(s), {r: s.robot(r).start for r in robots}, config)
    rng = belief_rng(seed, robots)
    for k in range(s.steps):
        belief.step([frames[r][k] for r in robots], rng)
    return belief


def by_realisation(belief: HybridBelief) -> Realisations:
    """Every hypothesis keyed by its classes in increasing object id order."""
    order = sorted(belief.object_ids)
    index = [belief.object_ids.index(j) for j in order]
    out = {tuple(h.classes[i] for i in index): h for h in belief.hypotheses}
    assert len(out) == len(belief.hypotheses), "two hypotheses with one realisation"
    return out


def weights_by_realisation(belief: HybridBelief) -> dict[tuple[int, ...], float]:
    """Normalised weights keyed like :func:`by_realisation`."""
    w = dict(zip((id(h) for h in belief.hypotheses), belief.weights(), strict=True))
    return {c: float(w[id(h)]) for c, h in by_realisation(belief).items()}


def class_marginals_by_id(belief: HybridBelief) -> dict[int, np.ndarray]:
    """P(c_j = i) per object id."""
    p = belief.class_marginals()
    return {j: p[i] for i, j in enumerate(belief.object_ids)}
