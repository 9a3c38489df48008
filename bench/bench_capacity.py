"""Issue 14's capacity figures: N agents (5, 10, 20, 30) of a generated world in realtime mode at
the step period — whether they keep up (each agent's steps behind one period after the last frame,
and its last step 10 s later; when each step's estimate came after its frames: the margin left),
CPU % and peak RSS per agent from /proc — and a lock-step launch of 50 agents that must
complete. Target: 20 agents keep up at a 0.5 s step on 2 cores (≤ 1 step behind at the end:
every agent, one period after the last frame, in every run).
The target size runs on three generated worlds (seeds 11, 12, 13, or from
``SEMFLEET_BENCH_WORLD_SEED``), the other sizes on the first. ``SEMFLEET_BENCH_AGENTS`` (sizes,
"5,10,20,30"), ``SEMFLEET_BENCH_CAPACITY_REPEATS`` (worlds at the target size, 3) and
``SEMFLEET_BENCH_LOCKSTEP_AGENTS`` (50; 0: no lock-step launch) choose what runs.
Issue 47 adds 50 agents in real time (``SEMFLEET_BENCH_SCALE_AGENTS``) on a world seed the rows
above never use (``SEMFLEET_BENCH_SCALE_SEED``, 31), once as a mesh of Zenoh peers and once
through a router (the conductor's session; every agent its client), with the CPU per agent-step.

The agents gossip at the default gossip period (``agents.core.GOSSIP_PERIOD_S``, 0.5 s: what a
launch or an agent config gets unless it says otherwise). At the target size the runs alternate
with a baseline of the same run that never catches up (``catch_up = 0``: every step fuses;
docs/agents.md, "Catching up"), with the fusions deferred and D's errors at the last step of
both, so that what catching up buys and costs is measured on the same machine state; and with a
run that gossips twice as often (``FAST_GOSSIP_S``, bench_agents' 0.25 s), the setting of this
benchmark's earlier figures.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from agents.core import CATCH_UP_STEPS, GOSSIP_PERIOD_S
from bench import Result
from bench.bench_agents import GOSSIP_S, PERIOD_S, _run_launch
from deploy.launch import LaunchPlan
from deploy.launch.conductor import Collected
from sim.generate import dump_scenario, generate_scenario
from sim.loader import parse_scenario
from sim.scenario import Scenario

AGENT_COUNTS = tuple(
    int(n) for n in os.environ.get("SEMFLEET_BENCH_AGENTS", "5,10,20,30").split(",")
)
LOCKSTEP_AGENTS = int(os.environ.get("SEMFLEET_BENCH_LOCKSTEP_AGENTS", "50"))
# Issue 47: fleets beyond 20 in real time, as a mesh of peers and through a router, on a world
# seed none of the rows above uses (``SEMFLEET_BENCH_SCALE_AGENTS``, "50"; empty: none;
# ``SEMFLEET_BENCH_SCALE_SEED``, 31). Target: 50 agents keep up (every agent ≤ 1 step behind).
SCALE_AGENTS = tuple(
    int(n) for n in os.environ.get("SEMFLEET_BENCH_SCALE_AGENTS", "50").split(",") if n
)
SCALE_SEED = int(os.environ.get("SEMFLEET_BENCH_SCALE_SEED", "31"))
SCALE_TARGET = 50
TOPOLOGIES = ("mesh", "router")
Usage = dict[str, dict[str, float]]  # per agent: CPU seconds and times sampled, peak RSS
STEPS = 20


class Run(NamedTuple):
    """One launch: the seed of its world, its wall time (s), what the conductor collected and
    each agent's CPU and memory."""

    seed: int
    wall: float
    collected: Collected
    usage: Usage


def notes() -> list[str]:
    return []


# Runs of each fleet size: the target size is run several times (this machine's speed varies by a
# third between runs of the same launch), each time on another generated world (consecutive seeds
# from the one the other sizes use: a target met on one world may not be on the next), the others
# once.
TARGET_AGENTS = 20
# The first world's seed (SEMFLEET_BENCH_WORLD_SEED, default 11): the target is meant to hold on
# any generated world, so it can be measured on others than the bundled figures' 11, 12 and 13.
WORLD_SEED = int(os.environ.get("SEMFLEET_BENCH_WORLD_SEED", "11"))
REPEATS = {TARGET_AGENTS: int(os.environ.get("SEMFLEET_BENCH_CAPACITY_REPEATS", "3"))}
FAST_GOSSIP_S = GOSSIP_S
# (catch_up, gossip period) of the runs of each size: the target size also runs the baseline that
# never catches up and the faster gossip.
DEFAULT = (CATCH_UP_STEPS, GOSSIP_PERIOD_S)
TARGET_VARIANTS = [DEFAULT, (0, GOSSIP_PERIOD_S), (CATCH_UP_STEPS, FAST_GOSSIP_S)]


def _capacity_rows(tmp: Path) -> list[Result]:
    rows = []
    for n in AGENT_COUNTS:
        variants = TARGET_VARIANTS if n == TARGET_AGENTS else [DEFAULT]
        runs: dict[tuple[int, float], list[Run]] = {v: [] for v in variants}
        for i in range(REPEATS.get(n, 1)):
            s = _world(tmp, n, WORLD_SEED + i)
            for c, gossip in variants:
                name = f"cap{n}-{i}-{c}-{round(1e3 * gossip)}"
                plan = LaunchPlan(
                    s, 0, list(s.robot_ids), tmp / name, mode="realtime", period=PERIOD_S,
                    gossip_period=gossip, fleet=name, publish_local=False, catch_up=c,
                )  # fmt: skip
                start = time.perf_counter()
                try:
                    outcome, usage = _run_launch(plan, sample=True)
                except Exception as exc:  # a capacity probe may fail at high N: the figure
                    note = f"failed: {exc}"
                    rows.append(
                        Result(f"realtime capacity: {n} agents", n, float("nan"), note=note)
                    )
                    continue
                wall = time.perf_counter() - start
                runs[(c, gossip)].append(Run(WORLD_SEED + i, wall, outcome.collected, usage))
        rows += [_capacity_row(n, STEPS, runs[v], *v) for v in variants if runs[v]]
    return rows


def _world(tmp: Path, n: int, seed: int) -> Scenario:
    """The generated world of ``n`` robots and 3n objects of ``seed``, through its file."""
    path = tmp / f"gen{n}-{seed}.toml"
    world = generate_scenario(n, 3 * n, 3, seed=seed, steps=STEPS)
    path.write_text(dump_scenario(world), encoding="utf-8")
    return parse_scenario(path.read_text(encoding="utf-8"), str(path))


def _scale_rows(tmp: Path) -> list[Result]:
    """Realtime launches of ``SCALE_AGENTS`` agents on the world of ``SCALE_SEED``, as a mesh
    and through a router, one after the other (issue 47)."""
    rows = []
    for n in SCALE_AGENTS:
        s = _world(tmp, n, SCALE_SEED)
        for topology in TOPOLOGIES:
            name = f"scale{n}-{topology}"
            plan = LaunchPlan(
                s, 0, list(s.robot_ids), tmp / name, mode="realtime", period=PERIOD_S,
                fleet=name, publish_local=False, topology=topology, wait_agents=600.0,
            )  # fmt: skip
            start = time.perf_counter()
            try:
                outcome, usage = _run_launch(plan, sample=True)
            except Exception as exc:
                note = f"failed: {exc}"
                rows.append(
                    Result(f"realtime capacity: {n} agents, {topology}", n, np.nan, note=note)
                )
                continue
            run = Run(SCALE_SEED, time.perf_counter() - start, outcome.collected, usage)
            rows.append(_capacity_row(n, STEPS, [run], *DEFAULT, topology=topology))
    return rows


def _capacity_row(
    n: int, steps: int, runs: list[Run], catch_up: int, gossip: float, topology: str = ""
) -> Result:
    """Steps behind one period after the last frame (when every robot should have taken it),
    per run (and its world): mean and worst agent; the last step 10 s later; CPU and peak RSS per
    agent; the stacks each agent received and the fusions it deferred; D's errors at the last
    step."""
    behind = [
        [steps - run.collected.on_time.get(r, 0) for r in run.collected.on_time] for run in runs
    ]
    later = [
        np.mean([run.collected.last_step.get(r, 0) for r in run.collected.on_time]) for run in runs
    ]
    samples = [u for run in runs for u in run.usage.values()]
    cpu = [
        100 * (u["cpu"] - u["cpu0"]) / max(u["t"] - u["t0"], 1e-9) for u in samples if "cpu" in u
    ]
    rss = [u["rss"] for u in samples]
    # CPU per step taken while the frames came (sampled at every frame, so from frame 1 to the
    # last; the steps are those acknowledged one period later): what a step costs an agent on a
    # shared machine, less dependent on the scheduling than how far behind the agents end.
    cpu_s = sum(u["cpu"] - u["cpu0"] for u in samples if "cpu" in u)
    taken = sum(max(1, run.collected.on_time.get(r, 0) - 1) for run in runs for r in run.usage)
    cpu_ms_per_step = 1e3 * cpu_s / max(1, taken)
    # How long after its frames each step was answered (its estimate arrived), the last step
    # apart (it decides the target: answered within the period), in ms; the margin the runs had.
    last_ms = [
        1e3 * run.collected.answered_s.get((r, steps), np.nan) for run in runs for r in run.usage
    ]
    every_ms = [1e3 * s for run in runs for s in run.collected.answered_s.values()]
    worst = max(max(b) for b in behind)
    met = "met" if worst <= 1 else "NOT met"
    per_run = "; ".join(
        f"world {run.seed}: mean {np.mean(b):.2f}, worst {max(b)}, "
        f"{100 * np.mean(np.array(b) <= 1):.0f} % ≤ 1, last step answered within "
        f"{_slowest_ms(run, steps):.0f} ms"
        for run, b in zip(runs, behind, strict=True)
    )
    target = (
        f" (target for {n}: every agent ≤ 1 behind) {met}"
        if n in (TARGET_AGENTS, SCALE_TARGET)
        else ""
    )
    counters = [run.collected.counters[r] for run in runs for r in run.collected.counters]
    received = np.mean([x.get("stacks_received", 0) for x in counters])
    deferred = np.mean([x.get("fusions_deferred", 0) for x in counters])
    # Over the robots that reached the last step (none may have, at 30 agents).
    last = {
        name: np.concatenate([run.collected.metrics["distributed"][name][:, -1] for run in runs])
        for name in ("robot_error", "object_error")
    }
    reached = int(np.isfinite(last["robot_error"]).sum())
    errors = (
        ", ".join(
            f"{name} {np.mean(v[np.isfinite(v)]):.3f} m" if reached else f"{name} n/a"
            for name, v in last.items()
        )
        + f" ({reached} of {len(last['robot_error'])} robot runs reached it)"
    )
    label = "" if catch_up == CATCH_UP_STEPS else f", catch_up {catch_up} (baseline)"
    label += f", {topology}" if topology else ""
    return Result(
        f"realtime capacity: {n} agents, period {PERIOD_S:g} s, gossip {gossip:g} s{label}",
        n,
        1e3 * float(np.median([run.wall for run in runs])),
        note=f"steps behind one period after the last frame, {len(runs)} run(s): {per_run}"
        f"{target}; {_answered(last_ms, every_ms)}; mean last step 10 s later "
        f"{', '.join(f'{x:.1f}' for x in later)} of "
        f"{steps}; CPU per agent {np.mean(cpu):.1f} % (max {np.max(cpu):.1f} %), "
        f"{cpu_ms_per_step:.0f} ms per step taken; peak RSS per "
        f"agent {np.mean(rss):.0f} MB (max {np.max(rss):.0f} MB); per agent {received:.0f} stacks "
        f"received, {deferred:.1f} fusions deferred; D at the last step: {errors}",
    )


def _slowest_ms(run: Run, step: int) -> float:
    """The last answer to ``step`` in ``run``: ms after its frames (inf if one never came)."""
    return max(1e3 * run.collected.answered_s.get((r, step), np.inf) for r in run.usage)


def _answered(last_ms: list[float], every_ms: list[float]) -> str:
    """The answer times of the last step and of every step (ms after the step's frames)."""
    answered = np.array(last_ms)[np.isfinite(last_ms)]
    if len(answered) == 0 or not every_ms:
        return "no answer times"
    return (
        f"last step answered {np.median(answered):.0f} ms after its frames (median; max "
        f"{np.max(answered):.0f}, {len(answered)} of {len(last_ms)} agents answered it; period "
        f"{1e3 * PERIOD_S:.0f} ms), every step p95 {np.percentile(every_ms, 95):.0f} ms, max "
        f"{np.max(every_ms):.0f} ms"
    )


def _lockstep_rows(tmp: Path) -> list[Result]:
    """A lock-step launch of LOCKSTEP_AGENTS agents of a generated world that must complete."""
    n = LOCKSTEP_AGENTS
    s = generate_scenario(n, 2 * n, 3, seed=12, steps=5)
    path = tmp / f"lock{n}.toml"
    path.write_text(dump_scenario(s), encoding="utf-8")
    s = parse_scenario(path.read_text(encoding="utf-8"), str(path))
    plan = LaunchPlan(
        s, 0, list(s.robot_ids), tmp / f"lock{n}", mode="lockstep", fleet=f"lock{n}",
        publish_local=False, wait_agents=600.0,
    )  # fmt: skip
    start = time.perf_counter()
    try:
        outcome, usage = _run_launch(plan, sample=True)
    except Exception as exc:
        return [Result(f"lock-step launch of {n} agents", n, float("nan"), note=f"failed: {exc}")]
    wall = time.perf_counter() - start
    done = sum(outcome.collected.last_step.get(r, 0) == s.steps for r in s.robot_ids)
    rss = [u["rss"] for u in usage.values()]
    return [
        Result(
            f"lock-step launch of {n} agents ({s.steps} steps)",
            n,
            1e3 * wall,
            note=f"{done}/{n} agents finished every step; wall time includes starting {n} "
            f"processes; peak RSS per agent {np.mean(rss):.0f} MB (max {np.max(rss):.0f} MB)",
        )
    ]


def run() -> list[Result]:
    with tempfile.TemporaryDirectory() as d:
        rows = _capacity_rows(Path(d)) + _scale_rows(Path(d))
        return rows + (_lockstep_rows(Path(d)) if LOCKSTEP_AGENTS > 0 else [])
