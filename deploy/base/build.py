"""What every runner builds from a robot model: beliefs, random streams, links and nodes.

The Monte Carlo study, the in-process fleet and the agent process build them here, so a robot
is seeded and configured the same way in each, and lock-step runs can agree bit for bit.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from agents.links import AllOf, LinkModel, Partition, Proximity, RandomDrop, Schedule
from agents.node import LocalTrack, RobotNode, Signing
from estimator.association import SensorField
from estimator.hybrid import BeliefConfig, BeliefModel
from estimator.models.objects import object_kind
from protocol.codec import Limits
from sim.loader import COMM_MODES
from sim.scenario import RobotModel, Scenario

__all__ = [
    "COMM_MODES",
    "HYPOTHESIS_MANAGEMENT",
    "belief_model",
    "belief_rng",
    "link_model_for",
    "make_node",
    "make_nodes",
    "sensor_field",
]

# Named class representations and hypothesis managements (docs/estimator.md): per-object class
# beliefs (the default), the joint realisations with marginal pruning, the paper's, none.
HYPOTHESIS_MANAGEMENT: dict[str, Callable[..., BeliefConfig]] = {
    "per_object": BeliefConfig,
    "marginal": BeliefConfig.joint,
    "paper": BeliefConfig.paper,
    "exact": BeliefConfig.exact,
}


def belief_model(model: RobotModel | Scenario) -> BeliefModel:
    """The estimators' model: a robot model's, or a scenario's robot model's (the generating
    model, as in the paper)."""
    if isinstance(model, Scenario):
        model = model.robot_model()
    return BeliefModel(
        model.num_classes,
        model.class_prior,
        model.classifier.build(),
        model.odometry_noise,
        model.geometric_noise,
        object_kind(model.sensor.objects),
    )


def sensor_field(model: RobotModel | Scenario, robot: str | None = None) -> SensorField:
    """Where a robot's sensor sees (``estimator.association``): a robot model's sensor, or
    ``robot``'s in a scenario (its default sensor without one)."""
    if isinstance(model, Scenario):
        sensor = model.sensor if robot is None else model.robot(robot).sensor
    else:
        sensor = model.sensor
    return SensorField(sensor.range, sensor.half_angle)


def belief_rng(seed: int, robots: Sequence[str]) -> np.random.Generator:
    """The weight estimator's randomness for a belief over ``robots`` in run ``seed``.

    It depends on the robots, not the method: beliefs over the same robots draw the same Monte
    Carlo samples in every method (common random numbers for the estimator too), so a one-robot
    centralized belief is exactly that robot's local belief. Independent of the sensor noise.
    """
    tags = [zlib.crc32(r.encode()) for r in robots]
    return np.random.default_rng(np.random.SeedSequence([seed, 0xBE11EF, *tags]))


def link_model_for(
    scenario: Scenario,
    comm: str | None = None,
    drop: float = 0.0,
    seed: int = 0,
    partitions: Sequence[Partition] = (),
) -> LinkModel:
    """The scenario's communication as a link model; ``comm`` overrides its mode, ``drop`` adds
    seeded random loss, ``partitions`` cut the fleet for a while."""
    c = scenario.communication
    mode = comm or c.mode
    if mode not in COMM_MODES:
        raise ValueError(f"communication mode {mode!r} (known: {', '.join(COMM_MODES)})")
    schedule = Schedule(tuple((e.first, e.last, e.a, e.b) for e in c.schedule))
    proximity = Proximity(c.range if c.range is not None else 10.0)
    model: LinkModel
    if mode == "schedule":
        model = schedule
    elif mode == "range":
        model = proximity
    else:
        model = AllOf((schedule, proximity))
    if drop > 0.0:
        model = AllOf((model, RandomDrop(drop, seed)))
    if partitions:
        model = AllOf((model, *partitions))
    return model


def make_node(
    robot: str,
    start: ArrayLike,
    model: BeliefModel,
    seed: int,
    config: BeliefConfig,
    fusion: str = "consistent",
    downdate: str = "remove",
    roster: frozenset[str] | None = None,
    limits: Limits | None = None,
    signing: Signing | None = None,
    epoch: int = 0,
    sensor: SensorField | None = None,
    keep_slots: int | None = None,
    guided: bool = True,
) -> RobotNode:
    """The node of ``robot`` starting at ``start`` (3,) in run ``seed``, exactly as
    :func:`make_nodes` builds it with ``rng_for = lambda r: belief_rng(seed, [r])``; ``roster``
    limits the slots it holds to those robots' (None: any owner); ``limits`` what it accepts and
    sends (default: the wire defaults with the model's class count); ``epoch`` its own slots'
    epoch (docs/wire.md, "Versions and epochs"); ``sensor``: the robot's sensor field, with
    which it associates frames without global ids (``estimator.association``); ``keep_slots``:
    the slots it keeps, its own included (default: a stack's ``max_slots``); ``guided``: its
    association gates on its D (default) or, False, on its own L."""
    rng_for = lambda r: belief_rng(seed, [r])  # noqa: E731
    node = _node(
        robot,
        start,
        model,
        rng_for,
        config,
        fusion,
        downdate,
        roster=roster,
        limits=limits,
        signing=signing,
        epoch=epoch,
        sensor=sensor,
        keep_slots=keep_slots,
    )
    node.track.guided = guided
    return node


def make_nodes(
    scenario: Scenario,
    model: BeliefModel,
    config: BeliefConfig,
    rng_for: Callable[[str], np.random.Generator],
    fusion: str = "consistent",
    downdate: str = "remove",
    tracks: Mapping[str, LocalTrack] | None = None,
    limits: Limits | None = None,
) -> dict[str, RobotNode]:
    """One node per robot of the scenario; ``rng_for(robot)`` builds a fresh generator, called
    twice per robot so that L and D draw identical streams. ``tracks`` shares local beliefs;
    ``limits``: every node's wire limits (default ``agents.node.node_limits``)."""
    return {
        r.id: _node(
            r.id,
            r.start,
            model,
            rng_for,
            config,
            fusion,
            downdate,
            None if tracks is None else tracks[r.id],
            limits=limits,
        )
        for r in scenario.robots
    }


def _node(
    robot: str,
    start: ArrayLike,
    model: BeliefModel,
    rng_for: Callable[[str], np.random.Generator],
    config: BeliefConfig,
    fusion: str,
    downdate: str,
    local: LocalTrack | None = None,
    roster: frozenset[str] | None = None,
    limits: Limits | None = None,
    signing: Signing | None = None,
    epoch: int = 0,
    sensor: SensorField | None = None,
    keep_slots: int | None = None,
) -> RobotNode:
    return RobotNode(
        robot,
        start,
        model,
        rng_for(robot),
        rng_for(robot),
        config,
        fusion,
        downdate,
        local=local,
        roster=roster,
        limits=limits,
        signing=signing,
        epoch=epoch,
        sensor=sensor,
        keep_slots=keep_slots,
    )
