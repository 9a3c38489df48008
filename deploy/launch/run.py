"""One launch: a plan, the launcher that runs it, and :func:`launch` with its live table.

The launcher allocates loopback ports, writes one agent config per robot, starts every agent
(:mod:`deploy.launch.supervisor`), opens the conductor's own Zenoh session, drives the run in
``lockstep`` or ``realtime`` mode (:mod:`deploy.launch.conductor`) with the plan's faults
(:mod:`deploy.launch.chaos`), and returns the agents' scored estimates as a
:class:`deploy.study.runner.RunResult` (methods ``local`` and ``distributed``). Whatever happens —
success, an agent that died unplanned, SIGTERM, SIGHUP, Ctrl-C — every agent is stopped before
:meth:`Launcher.run` returns or raises.

With ``net = "netns"`` every agent runs in its own network namespace on a bridge
(:mod:`deploy.launch.netns`), the agents are not simulated (``simulation = false``: they never
see a link verdict) and the conductor turns each step's verdict into nftables rules on real
packets (:mod:`deploy.launch.packet_faults`); the network is removed in the same ``finally``.

Over 300 lines for a reason: the plan, the files the launcher writes for every agent (plain or as
a throwaway secure fleet) and the run that uses them share the same ports and paths; the agents,
the conductor and the chaos already live in their own modules.
"""

from __future__ import annotations

import asyncio
import dataclasses
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from agents.core import CATCH_UP_STEPS, GOSSIP_PERIOD_S
from agents.links import LinkModel
from agents.transport.base import Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport, loopback_endpoint
from deploy.base.output import live_display
from deploy.launch.aoi import AgeOfInformation, age_of_information, link_hops
from deploy.launch.chaos import KILL, Faults, Garbage
from deploy.launch.conductor import Collected, Conductor, ConductorError, links_at
from deploy.launch.errors import LaunchError, PlanError
from deploy.launch.netns import Network
from deploy.launch.packet_faults import describe_cuts
from deploy.launch.supervisor import (
    AgentProcess,
    SignalStop,
    Supervisor,
    free_ports,
    write_agent_config,
)
from deploy.launch.table import progress_table
from deploy.operator.fleet_init import FleetSpec, endpoint_host, init_fleet
from deploy.study.fleet import link_model_for
from deploy.study.types import RunResult
from sim.robot_model import dump_robot_model
from sim.scenario import Scenario
from sim.sensors import Simulator

LAUNCH_METHODS = ("local", "distributed")
MODES = ("lockstep", "realtime")
NETS = ("loopback", "netns")
TOPOLOGIES = ("mesh", "router")
CONDUCTOR = "conductor"  # the operator identity of a secure launch's conductor
STOP_SETTLE_S = 0.2  # after ctl/stop, before SIGTERM: agents that heard it exit on their own
NETNS_LEASE_MS = 10_000  # Zenoh's own default: a session outlives a cut of up to 10 s

OnStep = Callable[[Conductor, int], None]


@dataclass(slots=True)
class LaunchPlan:
    """What to run. Checked when made (:class:`PlanError`): robots of the scenario, each once;
    ``steps`` within the scenario's; faults within the run (:meth:`Faults.check`)."""

    scenario: Scenario
    seed: int
    robots: list[str]
    out: Path
    mode: str = "lockstep"
    period: float = 0.5
    gossip_period: float = GOSSIP_PERIOD_S
    stack_gossip: str = "ask"  # or "delta", "full" (docs/wire.md, "Delta gossip", "Asks")
    relay: str = "event"  # or "tick": when asked slots go (agents.gossip; docs/wire.md, "Asks")
    keep_slots: int | None = None  # the slots each agent keeps, its own included (None: 64)
    catch_up: int = CATCH_UP_STEPS  # realtime: steps in a row that may defer fusion (agents.core)
    listen_in_range: bool = True  # realtime simulation: subscribe to the peers in range only
    comm: str | None = None
    faults: Faults = field(default_factory=Faults)
    fleet: str = "launch"
    steps: int | None = None
    zenoh_neighbours: Mapping[str, Sequence[str]] | None = None  # None: full mesh via gossip
    publish_local: bool = True
    keep_estimates: bool = False  # every estimate in LaunchOutcome.collected.estimates
    observe_stacks: bool = False  # log every robot's stack stamps (collected.stack_log)
    # With observe_stacks: after the last estimates, keep the fleet gossiping up to this many
    # seconds until every robot's stack holds every robot's final slot (Conductor.linger).
    linger: float = 0.0
    # A throwaway secure fleet (deploy.operator.fleet_init) under out/fleet: mutual TLS on loopback,
    # access control, owner-signed slots; the conductor holds the operator's identity.
    secure: bool = False
    # Drive the world for agents started elsewhere (a lab test of a real network): the conductor
    # listens on ``conductor_listen``, the agent configs written under out/agents dial
    # ``conductor_advertise``; no agent process is started here, and the run waits up to
    # ``wait_agents`` seconds for every agent's token.
    conductor_only: bool = False
    conductor_listen: str | None = None
    conductor_advertise: str | None = None
    wait_agents: float = 90.0
    # A secure conductor-only launch: the names (DNS or IP) of the agents' machines, written into
    # every member's certificate, since an agent dialling another verifies the name it dialled.
    agent_hosts: tuple[str, ...] = ()
    # "loopback": every process on 127.0.0.1, links simulated (sim/links); "netns": one network
    # namespace per agent, loss, partitions and range applied to real packets (root only).
    net: str = "loopback"
    # Every agent config's ``[ros2]`` table (docs/ros2.md), None: ROS 2 off.
    ros2: Mapping[str, Any] | None = None
    # "mesh": every agent a Zenoh peer, linked to the others (gossip scouting); "router": the
    # conductor's session is a Zenoh router and every agent its client (one link each; the
    # router forwards), as Zenoh recommends beyond a few dozen peers (issue 47).
    topology: str = "mesh"

    def __post_init__(self) -> None:
        # The world of the run with this seed (its classes, when they are drawn per run): what
        # the conductor simulates and scores against. The agents see only the robot model.
        self.scenario = s = self.scenario.for_run(self.seed)
        if self.mode not in MODES:
            raise PlanError(f"mode {self.mode!r}: expected one of {', '.join(MODES)}")
        unknown = [r for r in self.robots if r not in s.robot_ids]
        if unknown or not self.robots:
            raise PlanError(f"robots {unknown} are not in scenario {s.name}")
        twice = sorted({r for r in self.robots if self.robots.count(r) > 1})
        if twice:
            raise PlanError(f"robots: {', '.join(twice)} listed more than once")
        if self.linger and not (self.observe_stacks and 0 < self.linger <= 600):
            raise PlanError(f"linger {self.linger}: needs observe_stacks and 0 < linger ≤ 600 s")
        if self.steps is not None and not 1 <= self.steps <= s.steps:
            raise PlanError(f"steps: {self.steps} outside 1..{s.steps} (scenario {s.name})")
        self.faults.check(self.robots, self.run_steps, self.mode == "lockstep")
        if self.agent_hosts and not (self.conductor_only and self.secure):
            raise PlanError("agent hosts: only for a secure conductor-only launch")
        if self.conductor_only:
            if self.zenoh_neighbours is not None:
                raise PlanError("conductor only: not with a Zenoh topology")
            if self.faults.kills or self.faults.restarts:
                raise PlanError("conductor only: the agents run elsewhere, no kills or restarts")
            if not (self.conductor_listen and self.conductor_advertise):
                raise PlanError("conductor only: needs the endpoint to listen on and to advertise")
            for name, e in (
                ("listen", self.conductor_listen),
                ("advertise", self.conductor_advertise),
            ):
                if self.secure and not e.startswith("tls/"):
                    raise PlanError(f"conductor {name} {e}: a secure fleet's endpoints are tls/…")
        if self.topology not in TOPOLOGIES:
            raise PlanError(f"topology {self.topology!r}: expected one of {', '.join(TOPOLOGIES)}")
        if self.topology == "router" and (
            self.secure or self.conductor_only or self.zenoh_neighbours is not None
            or self.net != "loopback" or self.ros2 is not None
        ):  # fmt: skip
            raise PlanError("topology router: a plain loopback launch only (not secure, "
                            "conductor-only, netns, ROS 2 or with a Zenoh topology)")  # fmt: skip
        if not 1.0 <= self.wait_agents <= 86_400:
            raise PlanError(f"wait for agents {self.wait_agents}: must be in 1..86400 s")
        if self.net not in NETS:
            raise PlanError(f"net {self.net!r}: expected one of {', '.join(NETS)}")
        if self.net == "netns":
            # Lock-step orders carry the links themselves; a conductor-only or Zenoh-topology
            # launch has its own idea of who dials whom.
            if self.mode != "realtime":
                raise PlanError("--net netns: realtime runs only (the agents obey real packets)")
            if self.conductor_only or self.zenoh_neighbours is not None:
                raise PlanError("--net netns: not with --conductor-only or a Zenoh topology")
            if self.ros2 is not None:  # each agent's localhost is its own namespace's
                raise PlanError("--net netns: not with ROS 2 (no rmw_zenohd in the namespaces)")

    @property
    def run_steps(self) -> int:
        return self.steps or self.scenario.steps


def _pose(start: Sequence[float]) -> tuple[float, float, float]:
    x, y, theta = (float(v) for v in start)
    return x, y, theta


@dataclass(slots=True)
class LaunchOutcome:
    result: RunResult
    collected: Collected
    wall_s: float
    agents: dict[str, AgentProcess]
    events: list[str]
    garbage_sent: int
    # A netns run: packets each robot's namespace dropped, {robot: {"lost": n, "cut": n}}.
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)
    # How long each robot's steps took to reach the others' fusion (deploy.launch.aoi).
    aoi: AgeOfInformation | None = None


class Launcher:
    """Owns the agent processes and the conductor of one launch. Agents are configured from the
    scenario's robot model, written next to their configs."""

    def __init__(self, plan: LaunchPlan) -> None:
        self.plan = plan
        self.steps = plan.run_steps
        self.supervisor = Supervisor()
        self.agents = self.supervisor.agents
        self.events = self.supervisor.events
        self.garbage = Garbage(plan.robots, plan.faults.garbage_rate, plan.seed)
        self._garbage_task: asyncio.Task[None] | None = None
        self.conductor: Conductor | None = None  # once the run has begun
        self._fleet: dict[str, Path] | None = None  # a secure launch's member folders
        self.network: Network | None = None  # a netns run's, while it exists
        # Per packet in a netns run (nftables), per stack and step in a simulated one.
        drop = 0.0 if plan.net == "netns" else plan.faults.drop
        self.links: LinkModel = link_model_for(
            plan.scenario, plan.comm, drop, plan.seed, plan.faults.partitions
        )
        self.dropped: dict[str, dict[str, int]] = {}  # a netns run's nftables counters

    def _prepare(self) -> int:
        """Ports, the robot model and one config per agent under ``out/agents``; returns the
        conductor's port."""
        plan = self.plan
        conductor_port, *ports = free_ports(len(plan.robots) + 1)
        agent_ports = dict(zip(plan.robots, ports, strict=True))
        model = plan.out / "agents" / "model.toml"
        model.parent.mkdir(parents=True, exist_ok=True)
        model.write_text(dump_robot_model(plan.scenario.robot_model()), encoding="utf-8")
        journal_dir = plan.out / "journal"
        journal_dir.mkdir(parents=True, exist_ok=True)
        for r in plan.robots:
            (journal_dir / f"{r}.log").unlink(missing_ok=True)
        self._fleet = self._secure_fleet(agent_ports, conductor_port) if plan.secure else None
        for r in plan.robots:
            cfg = plan.out / "agents" / f"{r}.toml"
            if self._fleet is None:
                zenoh = self._zenoh_section(r, agent_ports, conductor_port)
                write_agent_config(cfg, self._agent_section(r), zenoh, ros2=plan.ros2)
            elif plan.conductor_only:
                # Everything the robot's machine needs, in its own folder, paths relative to it.
                cfg = self._fleet[r] / "agent.toml"
                agent = self._agent_section(r)
                security = {"signing_key": "signing.key", "roster": "roster.toml"}
                zenoh = {"config_file": "zenoh.json5"}
                write_agent_config(cfg, agent, zenoh, security, plan.ros2)
            else:
                folder = self._fleet[r].resolve()
                security = {"signing_key": str(folder / "signing.key")}
                security["roster"] = str(folder / "roster.toml")
                zenoh = {"config_file": str(folder / "zenoh.json5")}
                write_agent_config(cfg, self._agent_section(r), zenoh, security, plan.ros2)
            log = plan.out / "logs" / f"{r}.log"
            prefix = () if self.network is None else self.network.exec_prefix(r)
            self.supervisor.add(AgentProcess(r, cfg, log, agent_ports[r], prefix=prefix))
        return conductor_port

    def _secure_fleet(self, ports: Mapping[str, int], conductor_port: int) -> dict[str, Path]:
        """The fleet's files under ``out/fleet`` (made anew for every launch): each agent listens
        on its port with TLS and dials the conductor and the robots before it (or, with
        ``zenoh_neighbours``, its neighbours before it; the conductor then dials every agent).
        In a netns run on the bridge's addresses, which the certificates name."""
        plan = self.plan
        robots = plan.robots
        host, conductor_host = {r: "127.0.0.1" for r in robots}, "127.0.0.1"
        if self.network is not None:
            host, conductor_host = self.network.layout.addresses, self.network.layout.host
        conductor = f"tls/{conductor_host}:{conductor_port}"
        names: tuple[str, ...] = ()
        if plan.conductor_only:
            # Agents on machines of their own dial the advertised conductor and find each other
            # through gossip scouting; each listens on every interface of its machine (on
            # loopback only when the conductor is on loopback: then so are they).
            assert plan.conductor_advertise is not None
            conductor = plan.conductor_advertise
            conductor_host = endpoint_host(conductor)
            on_loopback = not ZenohSettings(connect=(conductor,)).off_loopback()
            host = {r: "127.0.0.1" if on_loopback else "0.0.0.0" for r in robots}
            names = plan.agent_hosts
        listen = {r: f"tls/{host[r]}:{ports[r]}" for r in robots}
        hosts = tuple(dict.fromkeys(("localhost", "127.0.0.1", conductor_host, *names)))
        neighbours = plan.zenoh_neighbours
        connect: dict[str, tuple[str, ...]]
        if plan.conductor_only:
            connect = {r: (conductor,) for r in robots}
        elif neighbours is None:
            connect = {
                r: (conductor, *(listen[p] for p in robots[:i])) for i, r in enumerate(robots)
            }
        else:
            connect = {r: tuple(listen[p] for p in neighbours.get(r, ()) if p < r) for r in robots}
        starts = {r: _pose(plan.scenario.robot(r).start) for r in robots}
        model = dump_robot_model(plan.scenario.robot_model())
        spec = FleetSpec(plan.fleet, tuple(robots), CONDUCTOR, listen, connect, starts, model)
        spec = dataclasses.replace(spec, simulator=True, hosts=hosts, gossip=plan.conductor_only)
        shutil.rmtree(plan.out / "fleet", ignore_errors=True)
        return init_fleet(spec, plan.out / "fleet")

    def _agent_section(self, robot: str) -> dict[str, Any]:
        plan = self.plan
        return {
            "fleet": plan.fleet,
            "model": "model.toml",
            "start": [float(v) for v in plan.scenario.robot(robot).start],
            "roster": list(plan.robots),
            "seed": plan.seed,
            "mode": plan.mode,
            "gossip_period": plan.gossip_period,
            "stack_gossip": plan.stack_gossip,
            "relay": plan.relay,
            **({} if plan.keep_slots is None else {"keep_slots": plan.keep_slots}),
            "catch_up": plan.catch_up,
            "listen_in_range": plan.listen_in_range,
            # A conductor-only agent runs on a machine of its own, from a folder with its config
            # in it (docs/deploy.md): its journal goes in that folder too.
            "journal": f"{robot}.journal" if plan.conductor_only else f"../journal/{robot}.log",
            "publish_local": plan.publish_local,
            # Loss, partitions and range are the simulator's: it publishes who hears whom
            # (sim/links), which only a simulated agent obeys; in a netns run they happen to
            # the agents' packets instead.
            "simulation": self.network is None,
        }

    def _zenoh_section(
        self, robot: str, ports: Mapping[str, int], conductor_port: int
    ) -> dict[str, Any]:
        neighbours = self.plan.zenoh_neighbours
        if self.network is not None:
            # Each agent listens on its namespace's address and dials the conductor and the
            # agents before it: the side that dials re-dials after a cut heals. Plain TCP and
            # UDP on a bridge no other host can reach: each agent-to-agent session is two
            # links, TCP for what must arrive, UDP for the best-effort gossip, which a healed
            # cut lets through at once (docs/deploy.md, "Radio links"). The lease outlasts
            # cuts of up to NETNS_LEASE_MS, so the sessions need not be opened again.
            lay = self.network.layout
            mine = f"{lay.address(robot)}:{ports[robot]}"
            listen = [f"tcp/{mine}?rel=1", f"udp/{mine}?rel=0"]
            before = self.plan.robots[: self.plan.robots.index(robot)]
            dial = [f"tcp/{lay.host}:{conductor_port}"]
            for p in before:
                peer = f"{lay.address(p)}:{ports[p]}"
                dial += [f"tcp/{peer}?rel=1", f"udp/{peer}?rel=0"]
            return {
                "listen": listen,
                "connect": dial,
                "gossip": True,
                "insecure": True,
                "lease_ms": NETNS_LEASE_MS,
            }
        if self.plan.conductor_only:
            # An agent on another machine dials the conductor; gossip scouting links it to the
            # other agents the conductor knows of. Off loopback this lab harness runs without TLS.
            advertise = self.plan.conductor_advertise
            exposed = bool(ZenohSettings(connect=(str(advertise),)).off_loopback())
            return {"connect": [advertise], "gossip": True, "insecure": exposed or None}
        if self.plan.topology == "router":
            return {"mode": "client", "connect": [loopback_endpoint(conductor_port)]}
        listen = [loopback_endpoint(ports[robot])]
        if neighbours is None:
            return {
                "listen": listen,
                "connect": [loopback_endpoint(conductor_port)],
                "gossip": True,
            }
        # Zenoh links only where the robots may talk; the conductor dials every agent.
        dial = [loopback_endpoint(ports[p]) for p in neighbours.get(robot, ()) if p < robot]
        return {"listen": listen, "connect": dial, "gossip": False}

    def _conductor(self, conductor_port: int) -> Conductor:
        plan = self.plan
        neighbours = plan.zenoh_neighbours
        dial = (
            ()
            if neighbours is None
            else tuple(loopback_endpoint(self.agents[r].port) for r in plan.robots)
        )
        listen = (loopback_endpoint(conductor_port),)
        if plan.conductor_listen is not None:
            listen = (plan.conductor_listen,)
        if self.network is not None:
            listen = (f"tcp/{self.network.layout.host}:{conductor_port}",)
        mode = "router" if plan.topology == "router" else "peer"
        settings = ZenohSettings(listen=listen, connect=dial, gossip=neighbours is None, mode=mode)
        if self._fleet is not None and plan.conductor_only:
            settings = ZenohSettings(
                listen=listen, config_file=self._fleet[CONDUCTOR] / "zenoh.json5"
            )
        elif self._fleet is not None:
            tls = tuple(e.replace("tcp/", "tls/", 1) for e in (*listen, *dial))
            settings = ZenohSettings(
                listen=tls[:1], connect=tls[1:], config_file=self._fleet[CONDUCTOR] / "zenoh.json5"
            )
        return Conductor(
            plan.scenario,
            Simulator(plan.scenario, plan.seed).all_frames(),
            plan.robots,
            ZenohTransport(settings),
            Keys(plan.fleet),
            self.links,
            keep_estimates=plan.keep_estimates,
            observe_stacks=plan.observe_stacks,
            on_links=None if self.network is None else self._enforce,
        )

    def _enforce(self, k: int, verdict: Mapping[str, tuple[str, ...]]) -> None:
        """A netns run: step k's verdict as nftables rules on the agents' packets."""
        assert self.network is not None
        if self.network.enforce(verdict, self.plan.faults.drop):
            cuts = describe_cuts(verdict, self.plan.robots)
            self.events.append(f"step {k}: nftables rules: cut {cuts}")

    # -- the run -----------------------------------------------------------------------------

    async def run(self, on_step: OnStep | None = None) -> LaunchOutcome:
        """Run the plan; ``on_step(conductor, k)`` after every step.
        Raises :class:`LaunchError` if the run fails, :class:`~deploy.launch.Stopped` (or
        ``KeyboardInterrupt`` for SIGINT) if a signal stopped it — each after every agent was
        stopped."""
        with SignalStop() as signals:
            try:
                if self.plan.net == "netns":  # recorded first, removed in the finally below
                    self.network = Network.create(self.plan.robots)
                conductor = self.conductor = self._conductor(self._prepare())
                start = time.perf_counter()
                await self._drive(conductor, on_step)
            except ConductorError as exc:
                raise LaunchError(str(exc)) from None
            except asyncio.CancelledError:
                if signals.received is None:
                    raise
            finally:
                signals.hold()
                try:
                    if self.conductor is not None:
                        await self._shutdown(self.conductor, signals)
                finally:
                    self._remove_network()
            signals.raise_if_stopped()
        assert self.conductor is not None
        return self._outcome(self.conductor, time.perf_counter() - start)

    async def _drive(self, conductor: Conductor, on_step: OnStep | None) -> None:
        plan = self.plan
        schedule: dict[int, list[tuple[str, str]]] = {}
        for k, kind, robot in plan.faults.schedule():
            schedule.setdefault(k, []).append((kind, robot))
        if not plan.conductor_only:
            for r in plan.robots:
                self.supervisor.start(r)
        await conductor.open()
        await conductor.wait_alive(plan.wait_agents, self.supervisor.check)
        if plan.faults.garbage_rate > 0:
            self._garbage_task = asyncio.create_task(
                self.garbage.run(conductor.transport, conductor.keys)
            )

        def step_done(k: int) -> None:
            for kind, robot in schedule.get(k, ()):
                if kind == KILL:
                    self.supervisor.kill(robot)
                    self.events.append(f"step {k}: SIGKILL {robot}")
                else:
                    self.supervisor.start(robot)
                    self.events.append(f"step {k}: restarted {robot} from its journal")
            if on_step is not None:
                on_step(conductor, k)

        check = self.supervisor.check
        if plan.mode == "lockstep":
            await conductor.run_lockstep(self.steps, step_done, check)
        else:
            await conductor.run_realtime(self.steps, plan.period, step_done, check)
        if plan.linger:
            await conductor.linger(plan.linger, check)
        conductor.stop_agents()

    async def _shutdown(self, conductor: Conductor, signals: SignalStop) -> None:
        if self._garbage_task is not None:
            self._garbage_task.cancel()
        if self.network is not None:  # the run is over: sessions close at once, journals too
            self.network.heal()
        if signals.received is not None:
            conductor.stop_agents(f"launcher stopped by {signals.received.name}")
        await asyncio.sleep(STOP_SETTLE_S)
        self.supervisor.stop_all()
        await conductor.transport.close()

    def _remove_network(self) -> None:
        """After every agent stopped: the nftables counters, then the network itself."""
        network, self.network = self.network, None
        if network is None:
            return
        try:
            self.dropped = network.dropped()
        finally:
            left = network.remove()
        lost = sum(d["lost"] for d in self.dropped.values())
        cut = sum(d["cut"] for d in self.dropped.values())
        self.events.append(f"nftables dropped {lost} packets at random and {cut} on cut links")
        if left:
            raise LaunchError(f"netns run {network.layout.run}: could not remove {', '.join(left)}")

    def _outcome(self, conductor: Conductor, wall: float) -> LaunchOutcome:
        conductor.score_pending()
        c = conductor.collected
        steps = self.steps
        metrics = {m: {n: v[:, :steps] for n, v in c.metrics[m].items()} for m in LAUNCH_METHODS}
        result = RunResult(
            self.plan.seed,
            metrics,
            {m: c.step_ms.get(m, []) for m in LAUNCH_METHODS},
            {m: wall for m in LAUNCH_METHODS},
            calibration={m: c.calibration[m][:, :steps] for m in LAUNCH_METHODS},
            robots=tuple(self.plan.robots),  # the conductor's robot axis
        )
        robots, frames = self.plan.robots, conductor.frames
        hops = link_hops(
            lambda k: links_at(self.links, frames, robots, k), robots, self.plan.zenoh_neighbours
        )
        aoi = age_of_information(robots, c.ended, c.fused_log, hops)
        return LaunchOutcome(
            result, c, wall, self.agents, self.events, self.garbage.sent, self.dropped, aoi
        )


def launch(
    plan: LaunchPlan, console: Console | None = None, on_step: OnStep | None = None
) -> LaunchOutcome:
    """Run ``plan`` with a live table on ``console`` (if given); ``on_step(conductor, k)`` after
    every step (a recording, :mod:`deploy.launch.rerun_view`)."""
    launcher = Launcher(plan)
    if console is None:
        return asyncio.run(launcher.run(on_step))
    with live_display(console) as live:

        def show(conductor: Conductor, k: int = 0) -> None:
            if on_step is not None and k:
                on_step(conductor, k)
            live.update(progress_table(conductor, plan.robots, launcher.steps))

        outcome = asyncio.run(launcher.run(show))
        assert launcher.conductor is not None
        show(launcher.conductor)  # a realtime run's last estimates come in after its last frame
        return outcome
