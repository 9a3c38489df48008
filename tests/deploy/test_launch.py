"""Multi-process launches over real Zenoh on loopback (issue 5): one agent process per robot and
the conductor in this process, every port chosen by ``free_ports``.

Lock-step runs are compared with the in-process runner (``make_nodes`` + ``run_fleet``, the same
seeded nodes): they must agree to 1e-9 in every estimate — clean, with a SIGKILLed and restarted
agent, and under thousands of garbage stacks. Realtime runs (loss, partition, relay) are timed by
the machine, so they are judged by tolerances and stack stamps stated with each test. The
conftest checks that no agent process outlives any test.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.links import Partition
from agents.node import RobotNode
from agents.transport import Inbox, Keys
from agents.transport.zenoh_transport import (
    ZenohTransport,
    loopback_endpoint,
    read_json5,
    settings_for,
)
from deploy.base.build import belief_model, belief_rng
from deploy.launch import (
    Faults,
    Launcher,
    LaunchError,
    LaunchOutcome,
    LaunchPlan,
    free_ports,
    launch,
    write_agent_config,
)
from deploy.launch.conductor import without_truth
from deploy.study.fleet import link_model_for, make_nodes, run_fleet
from estimator.hybrid import BeliefConfig, BeliefSnapshot
from estimator.metrics import METRICS, evaluate
from protocol.frames import encode_frame
from sim.loader import load_scenario, parse_scenario
from sim.robot_model import dump_robot_model
from sim.scenario import Scenario
from sim.sensors import Simulator
from tests.estimator.scenarios import fleet_text, objects_ahead
from tests.tolerance import assert_close

SEMFLEET = Path(sys.executable).with_name("semfleet")
PAPER = load_scenario("paper")
ROBOTS = PAPER.robot_ids
SEED = 0
STEPS = 20  # r2–r3 talk from k = 6, r1 joins both at k = 13: every kind of merge happens
BELIEFS = ("local", "distributed")

StackLog = list[tuple[float, str, dict[str, int]]]


# --------------------------------------------------------------------------- reference


class Reference:
    """The in-process run of the paper scenario, seed ``SEED``, for ``STEPS`` steps: every
    robot's snapshots of L and D after every step, and the metrics computed from them."""

    def __init__(self) -> None:
        frames = Simulator(PAPER, SEED).all_frames()
        model = belief_model(PAPER)
        nodes = make_nodes(PAPER, model, BeliefConfig(), lambda r: belief_rng(SEED, [r]))
        truth = {o.id: (np.array(o.pose), o.class_index) for o in PAPER.objects}
        index = {r: i for i, r in enumerate(ROBOTS)}
        self.snapshots: dict[tuple[str, str, int], BeliefSnapshot] = {}
        self.metrics = {
            b: {m: np.full((len(ROBOTS), STEPS), np.nan) for m in METRICS} for b in BELIEFS
        }

        def record(robot: str, k: int, node: RobotNode, _fused: float, _ms: float) -> None:
            for belief, hybrid in (("local", node.local), ("distributed", node.distributed)):
                snap = hybrid.snapshot(robot)
                self.snapshots[(belief, robot, k)] = snap
                true_pose = frames[robot][k - 1].true_pose
                for name, value in evaluate(snap, PAPER.num_classes, true_pose, truth).items():
                    self.metrics[belief][name][index[robot], k - 1] = value

        run_fleet(nodes, frames, link_model_for(PAPER), STEPS, record)

    def final_mean(self, belief: str, metric: str) -> float:
        return float(np.mean(self.metrics[belief][metric][:, STEPS - 1]))


@pytest.fixture(scope="module")
def reference() -> Reference:
    return Reference()


def assert_same_snapshot(a: BeliefSnapshot, b: BeliefSnapshot, what: str) -> None:
    assert a.object_ids == b.object_ids, what
    np.testing.assert_array_equal(a.classes, b.classes, err_msg=what)
    for name in ("weights", "robot_pose", "robot_cov", "object_pose", "object_cov"):
        assert_close(getattr(a, name), getattr(b, name), what=f"{what}: {name}")
    assert (a.class_probs is None) == (b.class_probs is None), f"{what}: class_probs"
    if a.class_probs is not None and b.class_probs is not None:
        assert_close(a.class_probs, b.class_probs, what=f"{what}: class_probs")


def assert_estimates_match(
    outcome: LaunchOutcome, reference: Reference, steps: int, robots: Sequence[str] = ROBOTS
) -> None:
    """Every kept estimate of ``robots`` at steps 1..``steps`` equals the reference (1e-9)."""
    for r in robots:
        for k in range(1, steps + 1):
            est = outcome.collected.estimates[(r, k)]
            assert (est.robot, est.k) == (r, k)
            for b in BELIEFS:
                ref = reference.snapshots[(b, r, k)]
                assert_same_snapshot(est.beliefs[b], ref, f"{r} step {k} {b}")


def assert_all_agents_finished(outcome: LaunchOutcome, steps: int) -> None:
    c = outcome.collected
    for r, agent in outcome.agents.items():
        assert c.last_step.get(r) == steps, (r, c.last_step)
        assert agent.proc is not None and agent.proc.returncode == 0, (r, agent.log)


def _plan(out: Path, **kwargs: Any) -> LaunchPlan:
    return LaunchPlan(PAPER, SEED, list(ROBOTS), out, **kwargs)


# --------------------------------------------------------------------------- lock-step


@pytest.mark.lockstep
@pytest.mark.slow
@pytest.mark.parametrize(
    ("secure", "gossip", "topology"),
    [(False, "delta", "mesh"), (True, "delta", "mesh"), (False, "full", "mesh"),
     (False, "delta", "router")],
    ids=["plain", "secure", "full-stacks", "router"],
)  # fmt: skip
def test_launch_lockstep_paper_equals_the_in_process_runner(
    tmp_path: Path, reference: Reference, secure: bool, gossip: str, topology: str
) -> None:
    # secure: mutual TLS, access control and owner-signed slots (issue 13) change nothing of
    # the beliefs; every slot that was fused was verified (an unsigned one would be refused).
    # Delta gossip (the default) and full stacks: the same beliefs, round by round. Through a
    # router (the conductor's session; every agent its client): the same (issue 47).
    plan = _plan(
        tmp_path, steps=STEPS, keep_estimates=True, secure=secure, stack_gossip=gossip,
        topology=topology,
    )  # fmt: skip
    outcome = launch(plan)
    assert_estimates_match(outcome, reference, STEPS)
    for b in BELIEFS:
        for name in METRICS:
            assert_close(
                outcome.result.metrics[b][name], reference.metrics[b][name], what=f"{b} {name}"
            )
    assert_all_agents_finished(outcome, STEPS)
    for r, c in outcome.collected.counters.items():
        assert c["frames_processed"] == STEPS and c["stacks_invalid"] == 0, (r, c)
        assert c["empty_joins"] == c["rebuilds"] == 0, (r, c)
    config = (tmp_path / "agents" / "r1.toml").read_text()
    if secure:
        assert "[security]" in config and "zenoh.json5" in config
    assert ('mode = "client"' in config) == (topology == "router")
    # The run exercised fusion: by the end D holds more objects than L for every robot.
    for r in ROBOTS:
        final = outcome.collected.estimates[(r, STEPS)].beliefs
        assert len(final["distributed"].object_ids) > len(final["local"].object_ids), r


KILL_STEP = 8  # r2 merged r3's stacks in rounds 6–8: its journal holds frames and stacks


@pytest.mark.lockstep
@pytest.mark.slow
def test_launch_agent_killed_and_restarted_from_its_journal_continues_exactly(
    tmp_path: Path, reference: Reference
) -> None:
    steps = KILL_STEP + 4
    faults = Faults(kills=(("r2", KILL_STEP),), restarts=(("r2", KILL_STEP),))
    outcome = launch(_plan(tmp_path, steps=steps, keep_estimates=True, faults=faults))
    assert outcome.events == [
        f"step {KILL_STEP}: SIGKILL r2",
        f"step {KILL_STEP}: restarted r2 from its journal",
    ]
    assert outcome.agents["r2"].starts == 2
    # Every step of every robot, r2's after the restart (and its re-announced step 8) included,
    # is the belief the clean in-process run had: same hypotheses, weights and poses.
    assert_estimates_match(outcome, reference, steps)
    r2 = outcome.collected.counters["r2"]
    assert r2["replayed_frames"] == KILL_STEP
    assert r2["replayed_stacks"] == 3  # r3's stacks of rounds 5, 6 and 7, merged at 6, 7, 8
    assert r2["frames_processed"] == steps - KILL_STEP
    assert_all_agents_finished(outcome, steps)


@pytest.mark.slow
def test_launch_garbage_stacks_are_counted_and_change_nothing(
    tmp_path: Path, reference: Reference
) -> None:
    faults = Faults(garbage_rate=2000.0)
    outcome = launch(_plan(tmp_path, steps=STEPS, keep_estimates=True, faults=faults))
    invalid = sum(c["stacks_invalid"] for c in outcome.collected.counters.values())
    print(f"garbage: {outcome.garbage_sent} published, {invalid} counted invalid by the agents")
    assert outcome.garbage_sent >= 500, outcome.garbage_sent
    assert invalid >= 1000, (invalid, outcome.garbage_sent)
    assert_estimates_match(outcome, reference, STEPS)
    assert_all_agents_finished(outcome, STEPS)


# --------------------------------------------------------------------------- realtime

# Realtime steps every 0.3 s, gossip every 0.3 s: short runs, and a resync bound of 0.6 s.
PERIOD = 0.3
GOSSIP = 0.3
# Loss: final robot and object errors of D (mean over robots) within 0.1 m of the lossless run.
# Slots are cumulative summaries and the newest wins, so a lost stack only delays its owner's
# information to the next delivery (at p = 0.3 per link and step, 3 losses in a row: 2.7 %); at
# step 20 D holds nearly the lossless information. Measured: |Δ| ≤ 0.01 m in 3 runs (realtime
# timing moves merges by a step either way). 0.1 m stays well below the gap between D and L at
# step 20 (0.23 m robot, 0.27 m object error), so a D that stopped fusing fails the test.
LOSS_TOL_M = 0.1


@pytest.mark.slow
@pytest.mark.parametrize("gossip", ["delta", "ask"])
def test_launch_realtime_with_30_percent_loss_completes_close_to_lossless(
    tmp_path: Path, reference: Reference, gossip: str
) -> None:
    plan = _plan(
        tmp_path,
        steps=STEPS,
        mode="realtime",
        period=PERIOD,
        gossip_period=GOSSIP,
        faults=Faults(drop=0.3),
        stack_gossip=gossip,
    )
    outcome = launch(plan)
    assert_all_agents_finished(outcome, STEPS)
    for r in ROBOTS:
        # Loss is the simulator's (sim/links): the agents only know they run in a simulation.
        config = (tmp_path / "agents" / f"{r}.toml").read_text()
        assert "simulation = true" in config and "drop" not in config
        assert outcome.collected.counters[r]["frames_processed"] == STEPS
    assert sum(outcome.collected.counters[r]["ignored_out_of_range"] for r in ROBOTS) > 0
    metrics = outcome.result.metrics
    # L never depends on communication: identical to the lossless run.
    for name in METRICS:
        assert_close(metrics["local"][name], reference.metrics["local"][name], what=name)
    for name in ("robot_error", "object_error"):
        got = float(np.mean(metrics["distributed"][name][:, STEPS - 1]))
        want = reference.final_mean("distributed", name)
        print(f"{name} of D at step {STEPS}: {got:.4f} with 30 % loss, {want:.4f} lossless")
        assert abs(got - want) <= LOSS_TOL_M, (name, got, want)
    assert (
        reference.final_mean("local", "robot_error")
        - reference.final_mean("distributed", "robot_error")
        > 2 * LOSS_TOL_M
    )  # the tolerance can tell D from L


def world_text(name: str, n: int, spacing: float, steps: int, speed: float) -> str:
    """``n`` robots ``spacing`` m apart along y, driving along +x at ``speed`` m per step, each
    with two objects just ahead (seen from k = 1, so each has a slot at once); range comms 10 m."""
    ys = [spacing * i for i in range(n)]
    return fleet_text(
        name,
        steps,
        ys,
        objects_ahead(ys),
        description=f"{n} robots {spacing} m apart",
        speed=speed,
        half_angle_deg=50.0,
        sensing=3.5,
    )


def _world(tmp_path: Path, text: str) -> Scenario:
    path = tmp_path / "world.toml"
    path.write_text(text, encoding="utf-8")
    return parse_scenario(text, str(path))


def own_stamps(log: StackLog) -> dict[str, list[tuple[float, int]]]:
    """Robot → (time, its own slot's stamp) of every stack it published."""
    out: dict[str, list[tuple[float, int]]] = {}
    for t, r, stamps in log:
        out.setdefault(r, []).append((t, stamps.get(r, 0)))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("gossip", ["delta", "ask"])
def test_launch_relay_over_zenoh_links_between_neighbours_only(tmp_path: Path, gossip: str) -> None:
    """Six robots 8 m apart on a line, range 10 m: only neighbours are in range, and Zenoh links
    only neighbours (gossip scouting off). r1's final slot reaches r6 through four relays (and
    every robot's reaches every other), and no agent ever received a stack from a non-neighbour:
    it would have been refused by the proximity filter and counted in ``ignored_out_of_range``.
    Realtime, because only there the agent filters by range itself (in lock-step the conductor's
    orders decide). A relay hop waits for the receiver's current step, so on a loaded machine the
    run can end before the last slots arrived: the launch lingers until they have. With
    ``stack_gossip = "ask"`` every robot asks a neighbour for the slots of the robots it does
    not hear, and the neighbours push them."""
    ids = [f"r{i}" for i in range(1, 7)]
    scenario = _world(tmp_path, world_text("line6", 6, 8.0, 12, 0.05))
    neighbours = {
        r: [ids[j] for j in (i - 1, i + 1) if 0 <= j < len(ids)] for i, r in enumerate(ids)
    }
    plan = LaunchPlan(
        scenario,
        SEED,
        ids,
        tmp_path / "run",
        mode="realtime",
        period=PERIOD,
        gossip_period=GOSSIP,
        zenoh_neighbours=neighbours,
        observe_stacks=True,
        linger=60.0,  # a guard against a hang, not a speed check
        stack_gossip=gossip,
    )
    outcome = launch(plan)
    assert_all_agents_finished(outcome, scenario.steps)
    r3 = (tmp_path / "run" / "agents" / "r3.toml").read_text()
    assert "gossip = false" in r3 and r3.count("tcp/127.0.0.1:") == 2  # listen + dial r2
    last = {r: stamps for _, r, stamps in outcome.collected.stack_log}
    assert last["r6"].get("r1") == scenario.steps and last["r1"].get("r6") == scenario.steps, last
    for r, c in outcome.collected.counters.items():
        assert c["ignored_out_of_range"] == 0, (r, c)
        assert c["stacks_merged"] > 0, (r, c)
        # Every robot out of a robot's range asked for (one relay each, at least), and every
        # relay but the line's ends answered asks.
        unheard = len(ids) - 1 - len(neighbours[r])
        assert (c["relays_asked"] >= unheard) == (gossip == "ask"), (r, c)
        if r not in ("r1", "r6"):
            assert (c["asks_answered"] > 0) == (gossip == "ask"), (r, c)
        # Holding times ride with ask gossip only (docs/wire.md, "Holding times"): there every
        # robot's last estimate gives the age of the peers' versions its fusion used.
        aged = c["peers_aged"]
        assert (aged > 0) == (gossip == "ask"), (r, c)
        assert 0 < c["peer_age_median_ms"] <= c["peer_age_max_ms"] or aged == 0, (r, c)
    # The answer time of every step answered: its estimate came after its frames went out.
    answered = outcome.collected.answered_s
    assert {(r, scenario.steps) for r in ids} <= answered.keys(), sorted(answered)
    assert all(s > 0 for s in answered.values()), answered


PARTITION = (5, 9)  # r3 hears nobody and nobody hears r3 from step 5 to step 9


def heal_time(outcome: LaunchOutcome, robots: Sequence[str], healed_after: int) -> float:
    """When every link was up again: the links of step ``healed_after`` + 1 were published
    (they come with that step's frames), and every robot had finished step ``healed_after``
    (a robot still at an earlier step hears under that step's links, still cut)."""
    own = own_stamps(outcome.collected.stack_log)
    finished = max(next(t for t, s in own[r] if s >= healed_after) for r in robots)
    return max(outcome.collected.links_published[healed_after + 1], finished)


def resync_delays(log: StackLog, robots: Sequence[str], t_heal: float) -> dict[str, float]:
    """For each (holder, owner) pair: seconds from the heal until the holder published a stack
    with the owner's slot at least as new as the owner's own stamp at the heal."""
    own = own_stamps(log)
    at_heal = {r: max(s for t, s in own[r] if t <= t_heal) for r in robots}
    delays = {}
    for holder in robots:
        for owner in robots:
            if owner != holder:
                t = next(
                    t
                    for t, r, stamps in log
                    if r == holder and t >= t_heal and stamps.get(owner, 0) >= at_heal[owner]
                )
                delays[f"{holder} holds {owner}"] = t - t_heal
    return delays


def last_view_before(log: StackLog, holder: str, owner: str, t_end: float) -> int:
    return max((s.get(owner, 0) for t, r, s in log if r == holder and t < t_end), default=0)


@pytest.mark.slow
@pytest.mark.parametrize("gossip", ["delta", "ask"])
def test_launch_partition_heals_within_two_gossip_periods(tmp_path: Path, gossip: str) -> None:
    """Every robot holds every other's slot of the heal within two gossip periods of the heal:
    one for the exchange (a digest that shows what a peer lacks, and the push of it), one for
    the holder to publish a stack, the only way the conductor sees what it holds. The clock
    starts when the links came back up (:func:`heal_time`), and each stack is timed at its
    arrival at the conductor."""
    robots = ["r1", "r2", "r3"]
    scenario = _world(tmp_path, world_text("close3", 3, 3.0, 14, 0.1))
    first, last = PARTITION
    plan = LaunchPlan(
        scenario,
        SEED,
        robots,
        tmp_path / "run",
        mode="realtime",
        period=PERIOD,
        gossip_period=GOSSIP,
        faults=Faults(partitions=(Partition(frozenset({"r3"}), first, last),)),
        observe_stacks=True,
        stack_gossip=gossip,
    )
    outcome = launch(plan)
    assert_all_agents_finished(outcome, scenario.steps)
    log = outcome.collected.stack_log
    t_heal = heal_time(outcome, robots, last)
    # The partition held: nobody's copy of the other side got newer than step first − 1.
    for holder, owner in (("r1", "r3"), ("r2", "r3"), ("r3", "r1"), ("r3", "r2")):
        assert last_view_before(log, holder, owner, t_heal) <= first - 1, (holder, owner)
    delays = resync_delays(log, robots, t_heal)
    print(f"resync after the heal (s): {delays}")
    assert max(delays.values()) <= 2 * GOSSIP, delays


# --------------------------------------------------------------------------- shutdown


async def _sigterm_when_busy(
    procs: Mapping[str, subprocess.Popen[bytes]], port: int, keys: Keys
) -> dict[str, float]:
    """Once every agent is alive and stepping, SIGTERM them all while garbage floods the stack
    keys; seconds from the signal to each exit."""
    watcher = ZenohTransport(settings_for(port, []))
    events, estimates = Inbox(256), Inbox(10_000)
    watcher.watch_alive(keys.alive("*"), events)
    watcher.subscribe(keys.estimate("*"), estimates)
    ended: dict[str, float] = {}
    frames = Simulator(PAPER, SEED).all_frames()

    async def feed() -> None:
        """The robots' perception: a truth-less frame every 0.05 s, so a step is always due."""
        for k in range(1, PAPER.steps + 1):
            for r in procs:
                watcher.publish(keys.frames(r), encode_frame(without_truth(frames[r][k - 1])))
            await asyncio.sleep(0.05)

    pump: asyncio.Task[None] | None = None
    try:
        await watcher.open()
        alive: set[str] = set()
        async with asyncio.timeout(60):
            while not set(procs) <= alive:
                await events.wait(0.2)
                alive |= {keys.robot_of(m.key) or "" for m in events.drain() if m.kind == "alive"}
            pump = asyncio.create_task(feed())
            while len({keys.robot_of(m.key) for m in estimates.drain()}) < len(procs):
                await asyncio.sleep(0.3)  # until every agent has published an estimate
        sent = time.monotonic()
        for p in procs.values():
            p.send_signal(signal.SIGTERM)
        while len(ended) < len(procs) and time.monotonic() - sent < 10:
            watcher.publish(keys.stack("chaos"), os.urandom(64))
            await asyncio.sleep(0.002)
            for r, p in procs.items():
                if r not in ended and p.poll() is not None:
                    ended[r] = time.monotonic() - sent
    finally:
        if pump is not None:
            pump.cancel()
        await watcher.close()
    return ended


@pytest.mark.slow
def test_agents_end_within_2_s_of_sigterm(tmp_path: Path) -> None:
    """Three agents stepping the paper scenario (a frame every 0.05 s from the watcher's session,
    so a belief step is running when the signal lands) with a live peer session."""
    keys = Keys("shutdown")
    watcher_port, *ports = free_ports(len(ROBOTS) + 1)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        (tmp_path / "model.toml").write_text(dump_robot_model(PAPER.robot_model()), "utf-8")
        for r, port in zip(ROBOTS, ports, strict=True):
            cfg = tmp_path / f"{r}.toml"
            agent: dict[str, Any] = {"fleet": keys.fleet, "model": "model.toml", "mode": "realtime"}
            agent |= {"start": [float(v) for v in PAPER.robot(r).start], "roster": list(ROBOTS)}
            agent |= {"journal": f"{r}.log"}
            zenoh = {"listen": [loopback_endpoint(port)]}
            zenoh |= {"connect": [loopback_endpoint(watcher_port)]}
            write_agent_config(cfg, agent, zenoh)
            cmd = [sys.executable, "-m", "deploy.cli", "agent", "--robot", r, "--config", str(cfg)]
            with open(tmp_path / f"{r}.out", "wb") as out:
                procs[r] = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        ended = asyncio.run(_sigterm_when_busy(procs, watcher_port, keys))
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    print(f"exit after SIGTERM (s): {ended}")
    for r, p in procs.items():
        log = (tmp_path / f"{r}.out").read_text(errors="replace")
        assert p.returncode == 0, (r, log)
        assert '"reason": "SIGTERM"' in log and "Traceback" not in log, log
    assert set(ended) == set(ROBOTS)
    assert max(ended.values()) <= 2.0, ended


# --------------------------------------------------------------------------- the commands


def semfleet(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"}
    return subprocess.run(
        [str(SEMFLEET), *args], capture_output=True, text=True, timeout=600, cwd=cwd, env=env
    )


@pytest.mark.slow
def test_chaos_command_runs_every_fault_and_prints_the_comparison(tmp_path: Path) -> None:
    r = semfleet(
        "chaos", "--scenario", "paper", "--steps", "12", "--drop", "0.2", "--kill", "r2@5",
        "--restart", "r2@7", "--garbage", "50", "--seed", "1", "--period", "0.3",
        "--out", "chaos",
        cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    out = r.stdout
    for text in (
        "chaos on paper, seed 1: drop 0.2, kill r2@5, restart r2@7, garbage 50 stacks/s "
        "(realtime, period 0.3 s)",
        "- step 5: SIGKILL r2",
        "- step 7: restarted r2 from its journal",
        "agent counters (last estimate)",
        "final step 12: chaos run vs the lossless in-process run of seed 1",
    ):
        assert text in out, text
    garbage = int(out.split("garbage stacks published: ")[1].split()[0])
    assert garbage > 0
    table = out[out.index("final step 12: chaos run") :]
    for metric in ("msde", "robot_error", "object_error", "hypotheses"):
        assert metric in table, metric
    assert (tmp_path / "chaos" / "results.json").exists()
    assert (tmp_path / "chaos" / "journal" / "r2.log").exists()


@pytest.mark.lockstep
@pytest.mark.slow
def test_launch_stops_with_a_clear_error_when_an_agent_dies_unplanned(tmp_path: Path) -> None:
    launcher = Launcher(_plan(tmp_path / "die", steps=8))

    def murder(_conductor: object, k: int) -> None:
        if k == 3:  # not through the chaos schedule: nobody expects this exit
            proc = launcher.agents["r2"].proc
            assert proc is not None
            os.kill(proc.pid, signal.SIGKILL)

    start = time.monotonic()
    with pytest.raises(LaunchError, match=r"agent r2 exited unexpectedly with code -9 \(log "):
        asyncio.run(launcher.run(murder))
    assert time.monotonic() - start < 60  # no waiting for the step timeout (120 s)
    for r, agent in launcher.agents.items():  # every other agent was stopped on the way out
        assert agent.proc is not None and agent.proc.poll() is not None, r


@pytest.mark.lockstep
@pytest.mark.slow
@pytest.mark.parametrize("secure", [False, True], ids=["plain", "secure"])
def test_launch_conductor_only_drives_agents_started_elsewhere(
    tmp_path: Path, reference: Reference, secure: bool
) -> None:
    # `semfleet launch --conductor-only`: no agent is started by the launch; the agents are
    # started from the configs it writes (here on this machine, as another machine would), and
    # the lock-step run is still the in-process runner's. Secure: each robot's folder of the
    # throwaway fleet is copied elsewhere and its agent started there (mutual TLS, access
    # control, owner-signed slots; the agents find each other by gossip through the conductor).
    endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_ports(1)[0]}"
    only = {"conductor_listen": endpoint, "conductor_advertise": endpoint, "wait_agents": 60.0}
    plan = _plan(
        tmp_path / "run", steps=STEPS, keep_estimates=True, conductor_only=True, secure=secure,
        **only,
    )  # fmt: skip
    done: dict[str, Any] = {}

    def conduct() -> None:
        try:
            done["outcome"] = launch(plan)
        except BaseException as exc:  # re-raised in the test's thread
            done["error"] = exc

    thread = threading.Thread(target=conduct)
    thread.start()
    if secure:
        configs = [tmp_path / "run" / "fleet" / "robots" / r / "agent.toml" for r in ROBOTS]
    else:
        configs = [tmp_path / "run" / "agents" / f"{r}.toml" for r in ROBOTS]
    deadline = time.monotonic() + 60
    # The launch's own config (it replaces fleet init's, which has no `simulation`), written whole.
    while time.monotonic() < deadline and not all(
        c.exists() and "simulation" in c.read_text() for c in configs
    ):
        time.sleep(0.1)
    # What docs/deploy.md says to copy onto each robot's machine, alone in a folder there.
    if secure:  # the robot's folder
        for r, c in zip(ROBOTS, list(configs), strict=True):
            shutil.copytree(c.parent, tmp_path / "elsewhere" / r)
        configs = [tmp_path / "elsewhere" / r / "agent.toml" for r in ROBOTS]
        shutil.rmtree(tmp_path / "run" / "fleet" / "robots")
    else:  # the robot's config and the model
        for r, c in zip(ROBOTS, list(configs), strict=True):
            (tmp_path / "elsewhere" / r).mkdir(parents=True)
            for name in (c.name, "model.toml"):
                shutil.copy(c.parent / name, tmp_path / "elsewhere" / r / name)
        configs = [tmp_path / "elsewhere" / r / f"{r}.toml" for r in ROBOTS]
        shutil.rmtree(tmp_path / "run" / "agents")
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "deploy.cli", "agent", "--robot", r, "--config", c.name],
            cwd=c.parent,
            stdout=(tmp_path / f"elsewhere-{r}.log").open("wb"),
            stderr=subprocess.STDOUT,
        )
        for r, c in zip(ROBOTS, configs, strict=True)
    ]
    try:
        thread.join(600)
        if "error" in done:
            raise done["error"]
        outcome = done["outcome"]
        assert not outcome.agents or all(a.proc is None for a in outcome.agents.values())
        assert_estimates_match(outcome, reference, STEPS)
        for r, c in outcome.collected.counters.items():
            assert c["stacks_invalid"] == 0 and c["empty_joins"] == 0, (r, c)
        for r in ROBOTS:  # the agents reached each other: D holds more objects than L
            final = outcome.collected.estimates[(r, STEPS)].beliefs
            assert len(final["distributed"].object_ids) > len(final["local"].object_ids), r
        for p in procs:
            assert p.wait(20) == 0
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    # Everything an agent wrote stays in the folder it was started in (its journal too).
    assert sorted(p.name for p in (tmp_path / "elsewhere").iterdir()) == list(ROBOTS)
    for r in ROBOTS:
        assert (tmp_path / "elsewhere" / r / f"{r}.journal").stat().st_size > 0, r
    if secure:
        config = configs[0].read_text()
        assert "[security]" in config and "/" not in config.split("[security]")[1]  # relative
        zenoh = read_json5(configs[0].parent / "zenoh.json5")
        assert zenoh["transport"]["link"]["tls"]["enable_mtls"] is True
        assert zenoh["listen"]["endpoints"][0].startswith("tls/")
