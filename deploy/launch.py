"""`semfleet launch`: one conductor and one agent process per robot, on loopback Zenoh.

The launcher allocates loopback ports, writes one agent config per robot, starts every agent with
``subprocess`` (never a fork of a process with an open Zenoh session), opens the conductor's own
Zenoh session, drives the run in ``lockstep`` or ``realtime`` mode while it shows a live table, and
collects the agents' estimates into the results.json/npz schema of ``semfleet study`` (methods
``local`` and ``distributed``). Whatever happens, every agent is stopped before it returns:
``ctl/stop``, then SIGTERM, then SIGKILL after 2 s. An agent that dies unplanned ends the run with
a clear error.
"""

from __future__ import annotations

import asyncio
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from rich.console import Console
from rich.live import Live
from rich.table import Table

from agents.links import LinkModel, Partition
from agents.transport.base import Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport, loopback_endpoint
from deploy.conductor import Collected, Conductor, ConductorError
from deploy.fleet import link_model_for
from deploy.study import RunResult
from sim.robot_model import dump_robot_model
from sim.scenario import Scenario
from sim.sensors import Simulator

LAUNCH_METHODS = ("local", "distributed")
SHUTDOWN_GRACE_S = 2.0
GARBAGE_BURST = 200


class LaunchError(RuntimeError):
    """The launch failed: an agent died, did not start, or the run stalled."""


def free_ports(n: int) -> list[int]:
    """``n`` distinct free TCP ports on 127.0.0.1 (held open together while choosing)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


@dataclass(frozen=True, slots=True)
class Faults:
    """Chaos: seeded loss, partitions, kills and restarts (robot, step), garbage per second."""

    drop: float = 0.0
    partitions: tuple[Partition, ...] = ()
    kills: tuple[tuple[str, int], ...] = ()
    restarts: tuple[tuple[str, int], ...] = ()
    garbage_rate: float = 0.0


@dataclass(slots=True)
class LaunchPlan:
    scenario: Scenario
    seed: int
    robots: list[str]
    out: Path
    mode: str = "lockstep"
    period: float = 0.5
    gossip_period: float = 0.5
    comm: str | None = None
    faults: Faults = field(default_factory=Faults)
    fleet: str = "launch"
    steps: int | None = None
    zenoh_neighbours: Mapping[str, Sequence[str]] | None = None  # None: full mesh via gossip
    publish_local: bool = True
    keep_estimates: bool = False  # every estimate in LaunchOutcome.collected.estimates
    observe_stacks: bool = False  # log every robot's stack stamps (collected.stack_log)


@dataclass(slots=True)
class AgentProcess:
    robot: str
    config: Path
    log: Path
    port: int
    proc: subprocess.Popen[bytes] | None = None
    expected_exit: bool = False
    starts: int = 0


@dataclass(slots=True)
class LaunchOutcome:
    result: RunResult
    collected: Collected
    wall_s: float
    agents: dict[str, AgentProcess]
    events: list[str]
    garbage_sent: int


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def write_agent_config(path: Path, agent: Mapping[str, Any], zenoh: Mapping[str, Any]) -> None:
    lines = ["[agent]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in agent.items() if v is not None]
    lines += ["", "[zenoh]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in zenoh.items() if v is not None]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


class Launcher:
    """Owns the agent processes and the conductor of one launch."""

    def __init__(self, plan: LaunchPlan, scenario_source: str) -> None:
        self.plan = plan
        self.scenario_source = scenario_source
        self.events: list[str] = []
        self.agents: dict[str, AgentProcess] = {}
        self.garbage_sent = 0
        s = plan.scenario
        unknown = [r for r in plan.robots if r not in s.robot_ids]
        if unknown:
            raise LaunchError(f"robots {unknown} are not in scenario {s.name}")
        if plan.steps is not None and not 1 <= plan.steps <= s.steps:
            raise LaunchError(f"steps: {plan.steps} outside 1..{s.steps} (scenario {s.name})")
        self.steps = plan.steps or s.steps
        self.links: LinkModel = link_model_for(
            s, plan.comm, plan.faults.drop, plan.seed, plan.faults.partitions
        )

    # -- processes ---------------------------------------------------------------------------

    def _prepare(self) -> int:
        plan = self.plan
        ports = free_ports(len(plan.robots) + 1)
        conductor_port, agent_ports = ports[0], dict(zip(plan.robots, ports[1:], strict=True))
        model = plan.out / "agents" / "model.toml"
        model.parent.mkdir(parents=True, exist_ok=True)
        model.write_text(dump_robot_model(plan.scenario.robot_model()), encoding="utf-8")
        journal_dir = plan.out / "journal"
        journal_dir.mkdir(parents=True, exist_ok=True)
        for r in plan.robots:
            (journal_dir / f"{r}.log").unlink(missing_ok=True)
        for r in plan.robots:
            if plan.zenoh_neighbours is None:
                connect = [loopback_endpoint(conductor_port)]
                gossip = True
            else:
                # Zenoh links only where the robots may talk; the conductor dials every agent.
                connect = [
                    loopback_endpoint(agent_ports[p])
                    for p in plan.zenoh_neighbours.get(r, ())
                    if p < r
                ]
                gossip = False
            cfg = plan.out / "agents" / f"{r}.toml"
            write_agent_config(
                cfg,
                {
                    "fleet": plan.fleet,
                    "model": "model.toml",
                    "start": [float(v) for v in plan.scenario.robot(r).start],
                    "roster": list(plan.robots),
                    "seed": plan.seed,
                    "mode": plan.mode,
                    "gossip_period": plan.gossip_period,
                    "journal": f"../journal/{r}.log",
                    "publish_local": plan.publish_local,
                    # Loss, partitions and range are the simulator's: it publishes who hears
                    # whom (sim/links), which only a simulated agent obeys.
                    "simulation": True,
                },
                {
                    "listen": [loopback_endpoint(agent_ports[r])],
                    "connect": connect,
                    "gossip": gossip,
                },
            )
            self.agents[r] = AgentProcess(r, cfg, plan.out / "logs" / f"{r}.log", agent_ports[r])
        return conductor_port

    def start_agent(self, robot: str) -> None:
        a = self.agents[robot]
        a.log.parent.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env.setdefault(var, "1")
        cmd = [
            sys.executable,
            "-m",
            "deploy.cli",
            "agent",
            "--robot",
            robot,
            "--config",
            str(a.config),
        ]
        with open(a.log, "ab") as log:
            a.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        a.expected_exit = False
        a.starts += 1

    def kill_agent(self, robot: str) -> None:
        a = self.agents[robot]
        if a.proc is not None and a.proc.poll() is None:
            a.expected_exit = True
            a.proc.send_signal(signal.SIGKILL)
            a.proc.wait()

    def check(self) -> None:
        """Raise if an agent died without being told to."""
        for a in self.agents.values():
            if a.proc is not None and not a.expected_exit and a.proc.poll() is not None:
                tail = _tail(a.log)
                raise LaunchError(
                    f"agent {a.robot} exited unexpectedly with code {a.proc.returncode} "
                    f"(log {a.log}): {tail}"
                )

    def stop_all(self) -> None:
        procs = [a for a in self.agents.values() if a.proc is not None and a.proc.poll() is None]
        for a in procs:
            a.expected_exit = True
            a.proc.send_signal(signal.SIGTERM)  # type: ignore[union-attr]
        deadline = time.monotonic() + SHUTDOWN_GRACE_S
        for a in procs:
            assert a.proc is not None
            try:
                a.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.events.append(f"{a.robot} ignored SIGTERM for {SHUTDOWN_GRACE_S} s: killed")
                a.proc.kill()
                a.proc.wait()

    # -- the run -----------------------------------------------------------------------------

    async def run(self, on_step: Callable[[Conductor, int], None] | None = None) -> LaunchOutcome:
        plan = self.plan
        conductor_port = self._prepare()
        frames = Simulator(plan.scenario, plan.seed).all_frames()
        keys = Keys(plan.fleet)
        connect = (
            ()
            if plan.zenoh_neighbours is None
            else tuple(loopback_endpoint(self.agents[r].port) for r in plan.robots)
        )
        transport = ZenohTransport(
            ZenohSettings(
                listen=(loopback_endpoint(conductor_port),),
                connect=connect,
                gossip=plan.zenoh_neighbours is None,
            )
        )
        conductor = Conductor(
            plan.scenario,
            frames,
            plan.robots,
            transport,
            keys,
            self.links,
            keep_estimates=plan.keep_estimates,
            observe_stacks=plan.observe_stacks,
        )
        kills = {k: r for r, k in plan.faults.kills}
        restarts = {k: r for r, k in plan.faults.restarts}
        garbage: asyncio.Task[None] | None = None
        start = time.perf_counter()
        try:
            for r in plan.robots:
                self.start_agent(r)
            await conductor.open()
            await conductor.wait_alive(90.0, self.check)
            if plan.faults.garbage_rate > 0:
                garbage = asyncio.create_task(self._garbage(transport, keys))

            def step_done(k: int) -> None:
                if k in kills:
                    self.kill_agent(kills[k])
                    self.events.append(f"step {k}: SIGKILL {kills[k]}")
                if k in restarts:
                    self.start_agent(restarts[k])
                    self.events.append(f"step {k}: restarted {restarts[k]} from its journal")
                if on_step is not None:
                    on_step(conductor, k)

            if plan.mode == "lockstep":
                await conductor.run_lockstep(self.steps, step_done, self.check)
            else:
                await conductor.run_realtime(self.steps, plan.period, step_done, self.check)
            conductor.stop_agents()
        except ConductorError as exc:
            raise LaunchError(str(exc)) from None
        finally:
            if garbage is not None:
                garbage.cancel()
            await asyncio.sleep(0.2)
            self.stop_all()
            await transport.close()
        wall = time.perf_counter() - start
        c = conductor.collected
        metrics = {
            m: {name: v[:, : self.steps] for name, v in c.metrics[m].items()}
            for m in LAUNCH_METHODS
        }
        result = RunResult(
            plan.seed,
            metrics,
            {m: c.step_ms.get(m, []) for m in LAUNCH_METHODS},
            {m: wall for m in LAUNCH_METHODS},
            calibration={m: c.calibration[m][:, : self.steps] for m in LAUNCH_METHODS},
        )
        return LaunchOutcome(result, c, wall, self.agents, self.events, self.garbage_sent)

    async def _garbage(self, transport: ZenohTransport, keys: Keys) -> None:
        """Malformed, truncated, NaN-laden and oversized stacks on the stack keys, at
        ``faults.garbage_rate`` per second. asyncio wakes a sleeper about once a millisecond at
        best, and later on a busy loop: every wake-up publishes what is due by then (at most
        ``GARBAGE_BURST``), or high rates would never be reached."""
        rng = random.Random(self.plan.seed ^ 0x6A5BA6E)
        rate = self.plan.faults.garbage_rate
        robots = self.plan.robots
        start, sent = time.monotonic(), 0
        while True:
            due = int((time.monotonic() - start) * rate) + 1
            for _ in range(min(due - sent, GARBAGE_BURST)):
                data = garbage_stack(rng)
                key = keys.stack("chaos") if rng.random() < 0.5 else keys.stack(rng.choice(robots))
                transport.publish(key, data)
                self.garbage_sent += 1
            sent = due
            await asyncio.sleep(1.0 / rate)


def garbage_stack(rng: random.Random) -> bytes:
    """One invalid stack message: random bytes, wrong types, NaNs, too many slots or an unknown
    version."""
    kind = rng.randrange(5)
    if kind == 0:
        data = rng.randbytes(rng.randrange(0, 512))
    elif kind == 1:
        data = msgpack.packb(
            {"v": 1, "type": "stack", "sender": "chaos", "k": 1, "pos": None, "slots": "x"}
        )
    elif kind == 2:
        nan = np.full(3, np.nan).astype("<f8").tobytes()
        data = msgpack.packb(
            {
                "v": 1,
                "type": "stack",
                "sender": "chaos",
                "k": 1,
                "pos": [float("nan"), 0.0],
                "slots": [
                    {
                        "owner": "chaos",
                        "stamp": 1,
                        "objects": [1],
                        "real": [
                            {
                                "c": b"\x00",
                                "phi": 0.0,
                                "lin": nan,
                                "info": nan * 2,
                                "eta": nan,
                            }
                        ],
                    }
                ],
            }
        )
    elif kind == 3:
        data = msgpack.packb(
            {
                "v": 1,
                "type": "stack",
                "sender": "chaos",
                "k": 1,
                "pos": None,
                "slots": [
                    {"owner": f"o{i}", "stamp": 1, "objects": [], "real": []} for i in range(100)
                ],
            }
        )
    else:
        data = msgpack.packb({"v": 99, "type": "stack"})
    return bytes(data)


def _tail(path: Path, lines: int = 3) -> str:
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    except OSError:
        return "(no log)"
    return " | ".join(text[-lines:]) or "(empty log)"


def progress_table(conductor: Conductor, robots: Sequence[str], steps: int) -> Table:
    t = Table(title=f"step {conductor.k}/{steps}")
    for col in (
        "robot",
        "alive",
        "step",
        "hyp L",
        "hyp D",
        "stacks in",
        "merged",
        "invalid",
        "out of range",
    ):
        t.add_column(col, justify="right")
    for r in robots:
        c = conductor.collected.counters.get(r, {})
        t.add_row(
            r,
            "yes" if r in conductor.alive else "no",
            str(conductor.acked(r)),
            str(c.get("hypotheses_local", "")),
            str(c.get("hypotheses_distributed", "")),
            str(c.get("stacks_received", "")),
            str(c.get("stacks_merged", "")),
            str(c.get("stacks_invalid", "")),
            str(c.get("ignored_out_of_range", "")),
        )
    return t


def launch(plan: LaunchPlan, scenario_source: str, console: Console | None = None) -> LaunchOutcome:
    """Run ``plan`` with a live table on ``console`` (if given)."""
    launcher = Launcher(plan, scenario_source)
    if console is None:
        return asyncio.run(launcher.run())
    with Live(console=console, refresh_per_second=4, transient=False) as live:

        def show(conductor: Conductor, k: int) -> None:
            live.update(progress_table(conductor, plan.robots, launcher.steps))

        return asyncio.run(launcher.run(show))
