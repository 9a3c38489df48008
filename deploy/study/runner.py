"""Monte Carlo studies: seeded runs of several methods on one scenario, with common random numbers.

Every run is an independent process (``spawn``: GTSAM's iSAM2 cannot be pickled or forked safely)
that simulates the scenario's frames once and feeds the very same frames to every method.
:func:`run_study` returns one :class:`RunResult` per seed; ``deploy.study.archive.study_archive``
turns them into the results archive. :func:`run_seeded` is the process pool of both studies;
``deploy.study.cluster.run_on_cluster`` runs the same calls on a Dask cluster instead.

Over 300 lines for a reason: one run (frames simulated once, every method fed the same frames),
the Recorder that scores it and the pool that runs many seeds all fill one RunResult layout;
split, that layout would be spread over modules that must change together.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.node import LocalTrack, RobotNode
from deploy.base.build import belief_model, belief_rng, link_model_for, make_nodes, sensor_field
from deploy.study.association import COUNTS, AssociationTally, d_truth, fleet_counts
from deploy.study.fleet import FleetStats, StepCallback, run_fleets
from deploy.study.types import ASSOCIATE_ON, TRACKS, RunResult, StudyError
from estimator.association import AssociationConfig, Associator
from estimator.fleet_association import FleetAssociationConfig
from estimator.hybrid import BeliefConfig, BeliefModel, BeliefSnapshot, HybridBelief
from estimator.metrics import (
    CROSS_METRICS,
    ECE_BINS,
    METRICS,
    class_comparison,
    evaluate,
    evaluate_calibration,
    mixture_moments,
    with_truth,
)
from estimator.models import GLOBAL_IDS, SensorFrame
from sim.scenario import Scenario
from sim.sensors import CLUTTER, Detector, Simulator

Array = NDArray[np.float64]

METHODS = ("local", "distributed", "double_count", "centralized", "received")


def without_ids_needs(ids: str) -> str:
    """Why a study of frames without global ids runs no centralized belief."""
    return (
        f"frames with {ids} ids are associated on each robot and across the fleet by each "
        "robot's D, so local, distributed and double_count run on them: a centralized belief "
        "(centralized, received) would need an association of its own across robots"
    )


RECEIVED_NEEDS = (
    "the method received follows the slots the distributed fleet received: add distributed"
)
# What a study runs unless told: ``received`` costs one centralized belief per robot.
DEFAULT_METHODS = ("local", "distributed", "double_count", "centralized")
FLEET_METHODS = {"distributed": "consistent", "double_count": "double_count"}


def run_study(
    scenario: Scenario,
    methods: list[str],
    seeds: list[int],
    config: BeliefConfig,
    jobs: int,
    snapshot_step: int | None,
    advance: Callable[[], None] = lambda: None,
    comm: str | None = None,
    cluster: str | None = None,
    scored: Collection[int] | None = None,
    gossip: str = "delta",
    detector: Detector | None = None,
    class_evidence: bool = True,
    associate_on: str = ASSOCIATE_ON[0],
) -> list[RunResult]:
    """Run every seed in its own spawned process, at most ``jobs`` at once, or as tasks of the
    Dask cluster whose scheduler is at ``cluster``; results in seed order. Only the first seed
    keeps belief snapshots (at ``snapshot_step``). ``scored``, ``gossip``, ``detector``,
    ``class_evidence``, ``associate_on``: see :func:`run_single`."""
    calls = {
        seed: (
            run_single,
            scenario,
            methods,
            seed,
            config,
            snapshot_step if i == 0 else None,
            comm,
            scored,
            gossip,
            detector,
            class_evidence,
            associate_on,
        )
        for i, seed in enumerate(seeds)
    }
    if cluster is not None:
        from deploy.study.cluster import run_on_cluster  # dask is an optional extra

        return run_on_cluster(calls, cluster, advance)
    return run_seeded(calls, jobs, advance)


def run_seeded(
    calls: dict[int, tuple[Any, ...]], jobs: int, advance: Callable[[], None] = lambda: None
) -> list[Any]:
    """``calls[seed] = (function, *args)``, each in a spawned process (at most ``jobs`` at once;
    ``deploy`` pins their BLAS to one thread); results in the order of ``calls``. The first
    failure cancels the rest: a worker that died becomes a :class:`StudyError` naming its seed,
    an exception raised by a run is re-raised as it is (a bug keeps its traceback, the remote one
    included), with a note naming the seed. ``advance()`` after every finished run."""
    done: dict[int, Any] = {}
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=jobs, mp_context=ctx)
    try:
        futures = {pool.submit(*call): seed for seed, call in calls.items()}
        for fut in as_completed(futures):
            seed = futures[fut]
            try:
                done[seed] = fut.result()
            except Exception as exc:
                if isinstance(exc, BrokenProcessPool):
                    raise StudyError(f"run with seed {seed} failed: {exc}") from exc
                exc.add_note(f"in the run with seed {seed}")
                raise
            advance()
    except BaseException:
        # A failed run, Ctrl-C or a stop signal: the other runs are not waited for. Their
        # workers are stopped here, so none outlives the command.
        for process in list(getattr(pool, "_processes", {}).values()):
            process.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return [done[s] for s in calls]


def run_single(
    scenario: Scenario,
    methods: Sequence[str],
    seed: int,
    config: BeliefConfig,
    snapshot_step: int | None = None,
    comm: str | None = None,
    scored: Collection[int] | None = None,
    gossip: str = "delta",
    detector: Detector | None = None,
    class_evidence: bool = True,
    associate_on: str = ASSOCIATE_ON[0],
) -> RunResult:
    """Run every method on one seeded realisation of ``scenario``; ``comm`` overrides the
    scenario's communication mode for the distributed methods, ``gossip`` says what the fleets'
    stacks carry (``deploy.study.fleet``: the agents' delta gossip, or every held slot).
    ``detector``: what the simulated detector delivers (``sim.sensors.Detector``; default the
    given-id frames of before); frames without global ids are associated on each robot and
    across the fleet (``distributed``, ``double_count``; not ``centralized`` or ``received``:
    :func:`without_ids_needs`), and scored against the simulator's truth (``association`` of
    the result); ``class_evidence`` False: the robots' and the fleet's association on geometry
    alone (the baseline of issue 45's twins); ``associate_on``: what the fleets' robots
    associate such frames on (:data:`ASSOCIATE_ON`: each node's D, or its own L).
    ``scored``: the steps at which the beliefs are scored (default every step; the metrics of the
    others stay NaN). Scoring queries every hypothesis' marginal covariances, about a fifth of a
    run's time: a caller that reads only some steps' metrics saves it; the beliefs themselves do
    not change."""
    if associate_on not in ASSOCIATE_ON:
        raise ValueError(f"associate_on must be one of {ASSOCIATE_ON}, got {associate_on!r}")
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown methods {unknown} (known: {', '.join(METHODS)})")
    if "received" in methods and "distributed" not in methods:
        raise ValueError(RECEIVED_NEEDS)
    detector = detector or Detector()
    if detector.ids != GLOBAL_IDS and {"centralized", "received"} & set(methods):
        raise ValueError(without_ids_needs(detector.ids))
    if detector.ids != GLOBAL_IDS and set(methods) - {"local"} and config.classes != "per_object":
        raise ValueError(
            f"frames with {detector.ids} ids: fleet association needs per-object classes "
            "(--hypotheses per_object)"
        )
    sim = Simulator(scenario, seed, detector=detector)
    scenario = sim.scenario  # this run's world: its classes, when they are drawn per run
    labelled = {
        r: [sim.labelled_frame(r, k) for k in range(1, scenario.steps + 1)]
        for r in scenario.robot_ids
    }
    frames = {r: [f for f, _ in fl] for r, fl in labelled.items()}
    labels = {r: [lab for _, lab in fl] for r, fl in labelled.items()}
    truth_objects = true_objects(scenario)
    robots = scenario.robot_ids
    model = belief_model(scenario)
    metrics: dict[str, dict[str, Array]] = {}
    step_ms: dict[str, list[float]] = {}
    wall: dict[str, float] = {}
    snapshots: dict[str, dict[str, BeliefSnapshot]] = {}
    recorders = {
        m: Recorder(scenario, frames, truth_objects, snapshot_step, scored=scored) for m in methods
    }
    fleet_methods = [m for m in methods if m in FLEET_METHODS]
    for rec in recorders.values():  # the beliefs compare_beliefs holds against each other
        rec.keep_classes = len(recorders) > 1 and bool(
            {"local", "centralized", "received"} & set(methods)
        )
    if "local" in methods or fleet_methods:
        _run_shared_local(
            scenario,
            model,
            config,
            seed,
            comm,
            frames,
            recorders,
            fleet_methods,
            gossip,
            labels,
            class_evidence,
            associate_on,
        )
    if "centralized" in methods:
        rec = recorders["centralized"]
        belief = HybridBelief(model, {r: scenario.robot(r).start for r in robots}, config)
        rng = belief_rng(seed, robots)
        for k in range(1, scenario.steps + 1):
            t = time.perf_counter()
            belief.step([frames[r][k - 1] for r in robots], rng)
            ms = 1e3 * (time.perf_counter() - t)
            rec.step_ms.append(ms)
            if not rec.scores(k):
                rec.wall_s += ms / 1e3
                continue
            snaps = belief.snapshots(robots)
            for i, robot in enumerate(robots):
                rec.record(belief, i, robot, k, ms if i == 0 else 0.0, snaps[robot])
    if "received" in methods:
        _run_received(scenario, model, config, seed, frames, recorders)
    compare_beliefs(recorders, {j: c for j, (_, c) in truth_objects.items()})
    for method in methods:
        rec = recorders[method]
        metrics[method] = rec.arrays
        step_ms[method] = rec.step_ms
        wall[method] = rec.wall_s
        if rec.snapshots:
            snapshots[method] = rec.snapshots
    fleet = {m: recorders[m].fleet for m in fleet_methods}
    return RunResult(
        seed,
        metrics,
        step_ms,
        wall,
        snapshots,
        fusion_ms={m: recorders[m].fusion_ms for m in fleet_methods},
        stack_bytes={m: st.delivered_bytes for m, st in fleet.items()},
        calibration={m: recorders[m].calibration for m in methods},
        empty_joins={m: st.empty_joins for m, st in fleet.items()},
        rebuilds={m: st.rebuilds for m, st in fleet.items()},
        refused={m: st.refused for m, st in fleet.items()},
        robots=tuple(robots),
        association={m: recorders[m].association_counts() for m in methods if recorders[m].tallies},
        fleet_association={
            m: recorders[m].fleet_counts for m in methods if recorders[m].fleet_counts
        },
        association_ms={
            m: [x for t in recorders[m].tallies.values() for x in t.ms]
            for m in methods
            if recorders[m].tallies
        },
    )


def _run_shared_local(
    scenario: Scenario,
    model: BeliefModel,
    config: BeliefConfig,
    seed: int,
    comm: str | None,
    frames: dict[str, list[SensorFrame]],
    recorders: dict[str, Recorder],
    fleet_methods: Sequence[str],
    gossip: str = "delta",
    labels: Mapping[str, Sequence[Sequence[int]]] | None = None,
    class_evidence: bool = True,
    associate_on: str = ASSOCIATE_ON[0],
) -> None:
    """``local`` and the fleets (``distributed``, ``double_count``) in one lock-step loop over one
    local belief per robot: L depends on the robot's own data only, so every method sees the very
    same L, stepped once. Metrics of ``local`` come from L, those of the fleets from each D.
    Frames without global ids are associated on each robot (``LocalTrack``), and the decisions
    scored against ``labels`` (per robot and step, the truth of each detection).
    ``associate_on = "fused"`` with such frames: each fleet's nodes associate on their own D
    (``Associator.associate``'s guide), so each fleet has its own L per robot, scored on its
    own, and ``local`` keeps the robot alone (its L associates on itself)."""
    robots = scenario.robot_ids
    index = {r: i for i, r in enumerate(robots)}
    # only frames without global ids are associated: with given ids the fleets share L as before
    guided = associate_on == "fused" and any(
        fl[0].ids != GLOBAL_IDS for fl in frames.values() if fl
    )

    def new_tracks(guide: bool) -> dict[str, LocalTrack]:
        return {
            r: LocalTrack(
                HybridBelief(model, {r: scenario.robot(r).start}, config),
                belief_rng(seed, [r]),
                Associator(
                    model,
                    sensor_field(scenario, r),
                    AssociationConfig(class_evidence=class_evidence),
                ),
                guided=guide,
            )
            for r in robots
        }

    tracks = new_tracks(False)
    fleets = [
        make_nodes(
            scenario,
            model,
            config,
            lambda r: belief_rng(seed, [r]),
            FLEET_METHODS[m],
            tracks=new_tracks(True) if guided else tracks,
        )
        for m in fleet_methods
    ]
    for nodes in fleets:
        for node in nodes.values():
            node.fleet_config = FleetAssociationConfig(class_evidence=class_evidence)
    local = recorders.get("local")
    received_by = recorders["distributed"] if "received" in recorders else None
    # per robot, its association's decisions against the truth (frames without global ids)
    tallies: dict[str, AssociationTally] = local.tallies if local is not None else {}

    def step_locals(k: int) -> None:
        if guided and local is None:
            return  # every fleet's node steps its own L
        for r in robots:
            t = time.perf_counter()
            tracks[r].advance(frames[r][k - 1], time.perf_counter)
            ms = 1e3 * (time.perf_counter() - t)
            association = tracks[r].association
            if association is not None and labels is not None:
                tally = tallies.setdefault(r, AssociationTally())
                tally.add(association, labels[r][k - 1], 1e3 * tracks[r].association_s)
                if local is not None:
                    local.truth_of[r] = tally.truth_of(tracks[r].belief.object_ids)
            if local is not None:
                local.step_ms.append(ms)
                local.record(tracks[r].belief, index[r], r, k, ms)

    def on_step_for(rec: Recorder) -> StepCallback:
        own = rec.tallies if guided else tallies  # a guided fleet's L is its own

        def on_step(robot: str, k: int, node: RobotNode, fused_ms: float, ms: float) -> None:
            rec.step_ms.append(ms)
            rec.fusion_ms.append(fused_ms)
            association = node.track.association
            if guided and labels and association is not None and association.frame.k == k:
                tally = own.setdefault(robot, AssociationTally())
                tally.add(association, labels[robot][k - 1], 1e3 * node.track.association_s)
            if robot in own and rec.scores(k):
                rec.truth_of[robot] = d_truth(node, own)
            rec.record(node.distributed, index[robot], robot, k, ms)
            if rec is received_by:
                versions = {o: node.stack.version_of(o) for o in robots if o != robot}
                rec.received[robot].append({o: v[1] for o, v in versions.items() if v})

        return on_step

    callbacks = [on_step_for(recorders[m]) for m in fleet_methods]
    links = link_model_for(scenario, comm)
    stats = run_fleets(
        fleets, frames, links, scenario.steps, callbacks, before_step=step_locals, gossip=gossip
    )
    for m, st, nodes in zip(fleet_methods, stats, fleets, strict=True):
        recorders[m].fleet = st
        own = recorders[m].tallies if guided else tallies
        if own:
            recorders[m].fleet_counts = fleet_counts(nodes, own)
        if guided:
            recorders[m].confirmed = {r: list(nodes[r].local.object_ids) for r in own}
    if local is not None:
        local.confirmed = {r: list(tracks[r].belief.object_ids) for r in local.tallies}


def _run_received(
    scenario: Scenario,
    model: BeliefModel,
    config: BeliefConfig,
    seed: int,
    frames: dict[str, list[SensorFrame]],
    recorders: dict[str, Recorder],
) -> None:
    """``received``: for every robot r, a centralized belief over exactly what r's distributed
    belief was given: r's own frames up to k, and each other robot's up to the stamp of its slot
    in r's stack after step k (``Recorder.received`` of the distributed fleet). D approximates
    it (Eq. 20, a sparse ξ), so D against it measures the fusion alone, where D against
    ``centralized`` also counts the news that has not reached r yet. A robot behind by several
    steps catches up in several belief steps of its frames alone. It keeps every robot pose (no
    window, ``BeliefConfig.window``): its robots do not step together."""
    robots = scenario.robot_ids
    rec = recorders["received"]
    stamps = recorders["distributed"].received
    # its robots do not step together (one out of range stays behind): a window of poses would
    # marginalise the pose a lagging robot continues from, so this reference keeps every pose
    config = dataclasses.replace(config, window=None)
    for i, robot in enumerate(robots):
        belief = HybridBelief(model, {r: scenario.robot(r).start for r in robots}, config)
        rng = belief_rng(seed, robots)
        for k in range(1, scenario.steps + 1):
            target = {**{r: 0 for r in robots}, **stamps[robot][k - 1], robot: k}
            t = time.perf_counter()
            while behind := [r for r in robots if belief.step_of[r] < target[r]]:
                belief.step([frames[r][belief.step_of[r]] for r in behind], rng)
            ms = 1e3 * (time.perf_counter() - t)
            rec.step_ms.append(ms)
            snap = belief.snapshots([robot])[robot] if rec.scores(k) else None
            rec.record(belief, i, robot, k, ms, snap)


def compare_beliefs(recorders: Mapping[str, Recorder], true_classes: Mapping[int, int]) -> None:
    """Fill each method's :data:`CROSS_METRICS` from the class marginals its recorder kept, at
    every row and step both it and the other belief scored, and drop the marginals:
    ``class_gap_central`` and ``class_log_loss_centralized_here`` against the centralized
    belief on this belief's objects, ``class_gap_received`` against ``received``,
    ``class_log_loss_local_objects`` this belief's log-loss on the objects the robot's local
    belief knows."""
    pairs = (
        ("centralized", ("class_gap_central", None, "class_log_loss_centralized_here")),
        ("received", ("class_gap_received", None, None)),
        ("local", (None, "class_log_loss_local_objects", None)),
    )
    for method, rec in recorders.items():
        for other, names in pairs:
            if other == method or other not in recorders:
                continue
            theirs = recorders[other].classes
            for (i, k), (ids, prob) in rec.classes.items():
                if (i, k) not in theirs:
                    continue
                figures = class_comparison(ids, prob, *theirs[i, k], true_classes)
                for name, value in zip(names, figures, strict=True):
                    if name is not None:
                        rec.arrays[name][i, k - 1] = value
    for rec in recorders.values():
        rec.classes.clear()


def true_objects(scenario: Scenario) -> dict[int, tuple[Array, int]]:
    """Object id → (true pose, true class index): what the metrics score against."""
    return {o.id: (np.array(o.pose), o.class_index) for o in scenario.objects}


class Recorder:
    """Collects one method's metrics (robots, steps) and :data:`TRACKS` (robots, steps, 3) in
    ``arrays``, class-ECE bin statistics (robots, steps, 3, bins), step times, the requested
    snapshots and, for a fleet, its :class:`FleetStats`. A launch scores its agents' published
    snapshots with it too (:meth:`score`), so a launch and a study are measured by the same code.
    ``robots``: the robot of every row (default: the scenario's robots). ``true_robot_pose`` is
    the truth of every step ``frames`` hold, ``robot_pose`` NaN until a step is scored.
    ``scored``: the steps :meth:`record` scores (default every step; ``snapshot_step`` always)."""

    def __init__(
        self,
        scenario: Scenario,
        frames: Mapping[str, Sequence[SensorFrame]],
        truth_objects: dict[int, tuple[Array, int]],
        snapshot_step: int | None = None,
        robots: Sequence[str] | None = None,
        scored: Collection[int] | None = None,
    ) -> None:
        self.scenario, self.frames, self.truth = scenario, frames, truth_objects
        self.snapshot_step = snapshot_step
        self.scored = None if scored is None else frozenset(scored)
        rows = scenario.robot_ids if robots is None else tuple(robots)
        shape = (len(rows), scenario.steps)
        self.arrays: dict[str, Array] = {
            m: np.full(shape, np.nan) for m in (*METRICS, *CROSS_METRICS)
        }
        self.arrays.update((name, np.full((*shape, 3), np.nan)) for name in TRACKS)
        for i, robot in enumerate(rows):
            poses = [f.true_pose for f in frames[robot][: scenario.steps]]
            self.arrays["true_robot_pose"][i, : len(poses)] = np.reshape(poses, (-1, 3))
        self.calibration = np.zeros((*shape, 3, ECE_BINS))
        self.step_ms: list[float] = []
        self.fusion_ms: list[float] = []
        self.fleet = FleetStats()
        self.snapshots: dict[str, BeliefSnapshot] = {}
        self.wall_s = 0.0
        # (row, step) → the scored belief's object ids and class marginals, while a run keeps
        # them for :func:`compare_beliefs` (``keep_classes``)
        self.keep_classes = False
        self.classes: dict[tuple[int, int], tuple[tuple[int, ...], Array]] = {}
        # robot → per step, the stamp of every other robot's slot its stack held after the step
        # (the distributed fleet's, for ``received``)
        self.received: dict[str, list[dict[str, int]]] = {r: [] for r in rows}
        # Frames without global ids (deploy.study.association): per robot, its association's
        # tally, the true object of each of its map objects (what their estimates are scored
        # against) and, after the run, its map objects
        self.tallies: dict[str, AssociationTally] = {}
        self.truth_of: dict[str, dict[int, int]] = {}
        self.confirmed: dict[str, list[int]] = {}
        # a fleet of robot-local ids: its mappings against the truth at the end
        # (``deploy.study.association.fleet_counts``)
        self.fleet_counts: dict[str, int] = {}

    def association_counts(self) -> dict[str, int]:
        """The association figures (``deploy.study.association.COUNTS``) summed over robots."""
        total: dict[str, int] = dict.fromkeys(COUNTS, 0)
        for r, tally in self.tallies.items():
            for name, value in tally.final(self.confirmed.get(r, ())).items():
                total[name] += value
        return total

    def record(
        self,
        belief: HybridBelief,
        i: int,
        robot: str,
        k: int,
        step_ms: float = 0.0,
        snap: BeliefSnapshot | None = None,
    ) -> None:
        """Evaluate ``belief`` (or its ``snap``, when taken already) for ``robot`` at step k;
        ``step_ms`` and the evaluation itself are added to this method's wall time; a step that is
        not :meth:`scores` only adds ``step_ms``."""
        t = time.perf_counter()
        if not self.scores(k):
            self.wall_s += step_ms / 1e3
            return
        if snap is None:
            snap = belief.snapshot(robot)
        if robot in self.truth_of:
            # robot-local ids: each map object is its true object (the one most of its
            # detections are), one made of false detections none (left out)
            truth = self.truth_of[robot]
            ids = tuple(truth.get(j, CLUTTER) for j in snap.object_ids)
            snap = with_truth(dataclasses.replace(snap, object_ids=ids), self.truth)
        self.score(i, robot, k, snap)
        if k == self.snapshot_step:
            self.snapshots[robot] = snap
        self.wall_s += step_ms / 1e3 + time.perf_counter() - t

    def scores(self, k: int) -> bool:
        """Whether :meth:`record` scores step k."""
        return self.scored is None or k in self.scored or k == self.snapshot_step

    def score(self, i: int, robot: str, k: int, snap: BeliefSnapshot) -> None:
        """Row ``i`` (``robot``), step k: ``snap`` against the ground truth, every metric and
        the class-ECE bin statistics, and the estimated robot pose: x, y the hypotheses'
        weighted mean, θ their weighted circular mean (as ``robot_pose`` of estimates.json)."""
        self.arrays["robot_pose"][i, k - 1] = mixture_moments(
            snap.weights, snap.robot_pose, snap.robot_cov
        )[0]
        true_pose = self.frames[robot][k - 1].true_pose
        num_classes = self.scenario.num_classes
        for name, value in evaluate(snap, num_classes, true_pose, self.truth).items():
            self.arrays[name][i, k - 1] = value
        self.calibration[i, k - 1] = evaluate_calibration(snap, num_classes, self.truth)
        if self.keep_classes:
            known = with_truth(snap, self.truth)
            self.classes[i, k] = (tuple(known.object_ids), known.marginals(num_classes))
