"""Issue 47, item 4: the in-process fleet (``deploy.study.fleet``, lock-step, delta gossip, relay
one hop per step) of N = 10, 25, 50, 100 robots on generated worlds at one density: 3 objects
per robot, 16 m² per object (``generate_scenario(N, 3N, 3, seed, steps, area=4·√(3N))``, a side
of 22 m at N = 10 and 69 m at N = 100), 10 m radio range, so that a robot has about as many
neighbours at every N (5 to 8 heard a step).

Per N, per robot and step, CPU time (``time.process_time``, over the second half of the
mission): L's step; D's fusion of the slots and D's step (its rebuilds included); gossip —
encoding its stack once and decoding and merging every stack it heard — per stack heard (per
neighbour); the digests of the whole fleet its delta-gossip policy notes (the lock-step agents'
protocol: every robot reads every digest); bytes sent; the age of information: for every pair
(i, j) and every version v of j's slot (made at j's step v), the steps until i's D first fuses a
version ≥ v (p50 / p99 / max, and in seconds at the agents' 0.5 s step), and its median against
the hops between them at step v; L's and D's robot and object error at the last step and the
objects each knows. Then each cost against N (the exponent b of a least-squares fit of
log(ms) = a + b·log N, and the linear fit's ms per robot added) and the target: at N = 100, L
and gossip per neighbour ≤ 1.5× N = 25, in the same run.

And the 64-slot cap's question (docs/distributed.md, "How many robots a D holds"): the largest
N again with every node's ``max_slots`` set (``SEMFLEET_BENCH_FLEETSCALE_BOUNDS``, default
``25,256``: a robot keeps the slots of the max_slots − 1 freshest robots, the nearest by hops;
256 holds every robot, the cap raised), each with the target, so that what a bound saves in CPU
and bytes is read beside what it costs in accuracy.

``SEMFLEET_BENCH_FLEETSCALE_SIZES`` (default ``10,25,50,100``), ``SEMFLEET_BENCH_FLEETSCALE_STEPS``
(default 40), ``SEMFLEET_BENCH_WORLD_SEED`` (the generated world, default 11) and
``SEMFLEET_BENCH_FLEETSCALE_SEED`` (the simulation's noise, default 1) choose what runs. At the
defaults one N = 100 run takes 1.5 to 4 min of one core, the whole module 10 to 15 min.

Over 300 lines for a reason: one fleet run's measures (CPU by phase, versions fused, hops,
accuracy) and the rows, slopes and targets that read them share the ``Point`` layout; split,
the two halves would change together.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.sparse.csgraph import shortest_path

from agents.node import RobotNode, node_limits
from bench import Result, format_table
from bench.bench_agents import PERIOD_S
from deploy.base.build import belief_model, belief_rng, link_model_for, make_nodes
from deploy.study.fleet import FleetStats, linked_pairs, run_fleet
from deploy.study.runner import true_objects
from estimator.hybrid import BeliefConfig
from estimator.metrics import evaluate
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator

SIZES = tuple(
    int(n) for n in os.environ.get("SEMFLEET_BENCH_FLEETSCALE_SIZES", "10,25,50,100").split(",")
)
STEPS = int(os.environ.get("SEMFLEET_BENCH_FLEETSCALE_STEPS", "40"))
WORLD_SEED = int(os.environ.get("SEMFLEET_BENCH_WORLD_SEED", "11"))
SEED = int(os.environ.get("SEMFLEET_BENCH_FLEETSCALE_SEED", "1"))
BOUNDS = tuple(
    int(n) for n in os.environ.get("SEMFLEET_BENCH_FLEETSCALE_BOUNDS", "25,256").split(",") if n
)
OBJECTS_PER_ROBOT = 3
M2_PER_OBJECT = 16.0
CLASSES = 3
TARGET = (25, 100, 1.5)  # (N, N, ratio): at the second N, L and gossip ≤ ratio × the first's

_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


def world(n: int, seed: int = WORLD_SEED, steps: int = STEPS) -> Scenario:
    """The generated world of ``n`` robots at the benchmark's density."""
    objects = OBJECTS_PER_ROBOT * n
    return generate_scenario(
        n, objects, CLASSES, seed, steps=steps, area=math.sqrt(M2_PER_OBJECT * objects)
    )


@dataclass(frozen=True)
class Point:
    """One fleet run: per robot and step (steps, robots) arrays of CPU seconds and counts, D's
    stamp of every robot's slot after each step (steps, robots, robots; −1: none), the hops
    between robots at each step (steps, robots, robots; inf: no path), the stamp of each
    robot's first slot (robots,), and L's and D's figures at the last step."""

    n: int
    side: float
    stats: FleetStats
    sent: NDArray[np.float64]
    fused: NDArray[np.int64]
    hops: NDArray[np.float64]
    first: NDArray[np.int64]
    accuracy: dict[str, float]
    foreign: int
    evicted: int
    wall_s: float


def run_point(s: Scenario, seed: int, max_slots: int | None = None) -> Point:
    """The fleet of ``s`` (noise ``seed``), every node's ``max_slots`` as given (default the
    wire's)."""
    robots = s.robot_ids
    n, steps = len(robots), s.steps
    frames = Simulator(s, seed).all_frames()
    model, config = belief_model(s), BeliefConfig()
    limits = node_limits(model.num_classes, config)
    if max_slots is not None:
        limits = replace(limits, max_slots=max_slots)
    nodes = make_nodes(s, model, config, lambda r: belief_rng(seed, [r]), limits=limits)
    index = {r: i for i, r in enumerate(robots)}
    fused = np.full((steps, n, n), -1, dtype=np.int64)
    sent = np.zeros((steps, n))
    first = np.full(n, steps + 1, dtype=np.int64)

    def on_step(robot: str, k: int, node: RobotNode, fusion_ms: float, step_ms: float) -> None:
        i = index[robot]
        for owner, (_, stamp) in node.distributed.versions.items():
            fused[k - 1, i, index[owner]] = stamp
        sent[k - 1, i] = node.counters.bytes_sent
        if node.local.object_ids and first[i] > steps:
            first[i] = k

    links = link_model_for(s)
    start = time.perf_counter()
    stats = run_fleet(nodes, frames, links, steps, on_step, clock=time.process_time)
    wall = time.perf_counter() - start
    hops = np.stack(
        [_hops(robots, linked_pairs(robots, frames, links, k)) for k in range(1, steps + 1)]
    )
    sent = np.diff(sent, axis=0, prepend=0.0)
    side = math.sqrt(M2_PER_OBJECT * len(s.objects))
    foreign = sum(node.counters.foreign_slots for node in nodes.values())
    evicted = sum(node.counters.evicted_slots for node in nodes.values())
    accuracy = _accuracy(s, nodes, frames)
    return Point(n, side, stats, sent, fused, hops, first, accuracy, foreign, evicted, wall)


def _hops(robots: tuple[str, ...], pairs: list[tuple[str, str]]) -> NDArray[np.float64]:
    """Fewest hops from every robot (row) to every other (column) over ``pairs``."""
    index = {r: i for i, r in enumerate(robots)}
    adjacency = np.zeros((len(robots), len(robots)))
    for a, b in pairs:
        adjacency[index[a], index[b]] = 1.0
    return np.asarray(shortest_path(adjacency, unweighted=True), dtype=float)


def _accuracy(s: Scenario, nodes: dict[str, RobotNode], frames: dict) -> dict[str, float]:
    """Mean over robots at the last step: L's and D's robot and object error and objects known."""
    truth = true_objects(s)
    out: dict[str, list[float]] = {}
    for r, node in nodes.items():
        true_pose = frames[r][-1].true_pose
        for name, belief in (("L", node.local), ("D", node.distributed)):
            snap = belief.snapshot(r)
            figures = evaluate(snap, s.num_classes, true_pose, truth)
            out.setdefault(f"{name} robot", []).append(figures["robot_error"])
            out.setdefault(f"{name} object", []).append(figures["object_error"])
            out.setdefault(f"{name} objects", []).append(float(len(snap.object_ids)))
    return {k: float(np.nanmean(v)) for k, v in out.items()}


def aoi(point: Point) -> tuple[NDArray[np.int64], NDArray[np.float64], int]:
    """Age of information: for every pair (i, j), i ≠ j, and every version v of j's slot (made
    at j's step v, from its first slot on), the steps from v until i's D first fuses a version
    ≥ v, with the hops from j to i at step v; and how many versions no D had fused by the end
    (left out: their age is not known yet)."""
    steps, n = point.fused.shape[0], point.n
    ages, hops, open_ = [], [], 0
    held = np.maximum.accumulate(point.fused, axis=0)
    for j in range(n):
        versions = np.arange(point.first[j], steps + 1)
        if len(versions) == 0:
            continue
        for i in range(n):
            if i == j:
                continue
            at = np.searchsorted(held[:, i, j], versions, side="left")  # first step index ≥ v
            done = at < steps
            open_ += int((~done).sum())
            ages.append(at[done] + 1 - versions[done])
            hops.append(point.hops[versions[done] - 1, j, i])
    if not ages:
        return np.zeros(0, dtype=np.int64), np.zeros(0), open_
    return np.concatenate(ages), np.concatenate(hops), open_


@dataclass(frozen=True)
class Costs:
    """Per robot and step over the second half of the mission: CPU ms of L, of D (fusion and
    D's step) and of the digests; gossip CPU ms per stack heard; stacks heard; kB sent."""

    local: float
    d: float
    gossip: float
    digests: float
    heard: float
    sent_kb: float


def costs(point: Point) -> Costs:
    st, n = point.stats, point.n
    shape = (-1, n)
    half = slice(point.fused.shape[0] // 2, None)

    def ms(values: list[float]) -> NDArray[np.float64]:
        return 1e3 * np.reshape(values, shape)[half]

    heard = np.reshape(st.heard, shape)[half]
    gossip = ms(st.gossip_s).sum() / max(1, heard.sum())
    d = ms(st.fusion_s) + ms(st.distributed_s)
    return Costs(
        float(ms(st.local_s).mean()),
        float(d.mean()),
        float(gossip),
        float(ms(st.digest_s).mean()),
        float(heard.mean()),
        float(point.sent[half].mean() / 1e3),
    )


def _row(name: str, point: Point) -> Result:
    c = costs(point)
    ages, hops, open_ = aoi(point)
    a = point.accuracy
    if len(ages):
        p50, p99, top = np.percentile(ages, [50, 99, 100])
        by_hops = ", ".join(
            f"{h:.0f}: {np.median(ages[hops == h]):.0f}"
            for h in np.unique(hops[np.isfinite(hops)])[:12]
        )
        unlinked = int((~np.isfinite(hops)).sum())
        age = (
            f"AoI p50/p99/max {p50:.0f}/{p99:.0f}/{top:.0f} steps "
            f"({p50 * PERIOD_S:g}/{p99 * PERIOD_S:g}/{top * PERIOD_S:g} s at {PERIOD_S:g} s), "
            f"median by hops at the version's step {{{by_hops}}}, {unlinked} with no path then, "
            f"{open_} of {len(ages) + open_} versions not fused by the end"
        )
    else:
        age = "no version fused"
    note = (
        f"per robot and step, CPU ms: L {c.local:.2f}, D {c.d:.2f}, gossip {c.gossip:.3f} per "
        f"stack heard ({c.heard:.1f} heard), digests {c.digests:.3f}; {c.sent_kb:.1f} kB sent; "
        f"{age}; last step: robot error L/D {a['L robot']:.3f}/{a['D robot']:.3f} m, object error "
        f"L/D {a['L object']:.3f}/{a['D object']:.3f} m, objects known L/D "
        f"{a['L objects']:.1f}/{a['D objects']:.1f} of {OBJECTS_PER_ROBOT * point.n}; "
        f"{point.foreign} slots refused for want of room, {point.evicted} evicted for a fresher "
        f"one, {sum(point.stats.rebuilds)} rebuilds of D; {point.wall_s:.0f} s wall"
    )
    return Result(name, point.n, c.local + c.d + c.gossip * c.heard + c.digests, note=note)


def slope(sizes: list[int], ms: list[float]) -> tuple[float, float]:
    """The exponent b of the least-squares fit log(ms) = a + b·log N, and the linear fit's ms
    per robot added."""
    b = float(np.polyfit(np.log(sizes), np.log(ms), 1)[0])
    per_robot = float(np.polyfit(sizes, ms, 1)[0])
    return b, per_robot


def _scaling_rows(points: dict[int, Point]) -> list[Result]:
    sizes = sorted(points)
    c = {n: costs(points[n]) for n in sizes}
    rows = []
    if len(sizes) >= 2:
        for what, values in (
            ("D (fusion and step)", [c[n].d for n in sizes]),
            ("L", [c[n].local for n in sizes]),
            ("gossip per stack heard", [c[n].gossip for n in sizes]),
            ("digests", [c[n].digests for n in sizes]),
            ("kB sent", [c[n].sent_kb for n in sizes]),
        ):
            b, per_robot = slope(sizes, values)
            rows.append(
                Result(
                    f"fleet scale: {what} per robot and step against N",
                    sizes[-1],
                    values[-1],
                    note=f"∝ N^{b:.2f} (log-log least squares over N = {sizes}), "
                    f"{per_robot:+.4f} per robot added (linear); "
                    + ", ".join(f"N={n}: {v:.3f}" for n, v in zip(sizes, values, strict=True)),
                )
            )
    low, high, _ = TARGET
    if low in points and high in points:
        rows.append(target_row(f"N={high}", points[low], points[high]))
    return rows


def target_row(name: str, low: Point, high: Point) -> Result:
    """The target: ``high``'s L and gossip per neighbour against ``low``'s."""
    a, b, ratio = costs(low), costs(high), TARGET[2]
    local, gossip = b.local / a.local, b.gossip / a.gossip
    met = "met" if max(local, gossip) <= ratio else "NOT met"
    return Result(
        f"fleet scale target: {name} against N={low.n} at equal density",
        high.n,
        b.local + b.gossip,
        note=f"L {local:.2f}×, gossip per neighbour {gossip:.2f}× (target ≤ {ratio:g}×) {met}; "
        f"D {b.d / a.d:.2f}×, digests {b.digests / max(a.digests, 1e-9):.2f}×, kB sent "
        f"{b.sent_kb / a.sent_kb:.2f}×",
    )


def run() -> list[Result]:
    _notes.clear()
    points: dict[int, Point] = {}
    rows = []
    for n in SIZES:
        s = world(n)
        points[n] = run_point(s, SEED)
        name = f"fleet N={n} ({STEPS} steps, {points[n].side:.0f} m, world {WORLD_SEED})"
        rows.append(_row(name, points[n]))
    rows += _scaling_rows(points)
    largest, low = max(SIZES), TARGET[0]
    for bound in BOUNDS:
        point = run_point(world(largest), SEED, bound)
        kept = "every robot held" if bound >= largest else f"the {bound - 1} nearest by hops kept"
        name = f"N={largest}, max_slots {bound}"
        rows.append(_row(f"fleet {name} ({kept})", point))
        if low in points and low < largest:
            rows.append(target_row(name, points[low], point))
    return rows


if __name__ == "__main__":
    print(format_table(run()))
    for line in notes():
        print(f"- {line}")
