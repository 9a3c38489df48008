"""Two sites joined only through `semfleet router`s (issue 13, item 4): real processes, mutual TLS
and access control from `fleet init --router`, gossip scouting off. Site A is robot r1 and router
hub-a, site B robot r2 and router hub-b; each robot dials its site's router and nothing else, hub-b
dials hub-a. Each robot's perception (a RobotLink with the robot's own identity) feeds its agent;
each D ends up holding the other robot's objects, from slots that crossed both routers
owner-signed, and the operator (a client of hub-a) controls both robots through them.

(A Zenoh router forwards between routers and for its clients, not between two of its own peers:
measured, two peers dialling one router with gossip off never hear each other.)"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import pytest

from agents.control import Stop, encode_control
from agents.perception import RobotLink
from agents.transport.base import Inbox, Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.cli.commands.scenario import model_text
from deploy.launch import free_ports
from deploy.operator.fleet_init import FleetSpec, init_fleet
from protocol.estimate import EstimateMessage
from sim.loader import load_scenario
from sim.sensors import Simulator
from tests.deploy.secure_helpers import ask_status, identity_settings

pytestmark = pytest.mark.slow

FLEET = "sites"
KEYS = Keys(FLEET)
ROBOTS = ("r1", "r2")
STEPS = 14
SEED = 2


def _spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", *args],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )


def test_two_agents_linked_only_through_a_router_fuse_each_others_slots(tmp_path: Path) -> None:
    s = load_scenario("paper")
    ports = free_ports(4)
    listen = {r: f"tls/127.0.0.1:{p}" for r, p in zip(ROBOTS, ports, strict=False)}
    hubs = {"hub-a": f"tls/127.0.0.1:{ports[2]}", "hub-b": f"tls/127.0.0.1:{ports[3]}"}
    site = {"r1": hubs["hub-a"], "r2": hubs["hub-b"]}
    starts = {r: (float(x), float(y), float(t)) for r in ROBOTS for x, y, t in [s.robot(r).start]}
    spec = FleetSpec(
        FLEET, ROBOTS, "op", listen, {r: (site[r],) for r in ROBOTS}, starts, model_text(s),
        routers=hubs,
    )  # fmt: skip
    folders = init_fleet(spec, tmp_path / "fleet")
    for r in ROBOTS:  # each robot dials its site's router and nothing else
        doc = ZenohSettings(config_file=folders[r] / "zenoh.json5").document()
        assert doc["connect"]["endpoints"] == [site[r]]
        assert doc["scouting"]["gossip"]["enabled"] is False
    doc = ZenohSettings(config_file=folders["hub-b"] / "zenoh.json5", mode="router").document()
    assert doc["connect"]["endpoints"] == [hubs["hub-a"]]
    procs = []
    for hub in hubs:
        router = ["router", "--config", str(folders[hub] / "zenoh.json5")]
        procs.append(_spawn(router, tmp_path / f"{hub}.log"))
    for r in ROBOTS:
        agent = ["agent", "--robot", r, "--config", str(folders[r] / "agent.toml")]
        procs.append(_spawn(agent, tmp_path / f"{r}.log"))
    frames = Simulator(s, SEED).all_frames()

    async def feed(robot: str) -> None:
        async with RobotLink(
            robot, FLEET, identity_settings(folders[robot], listen[robot])
        ) as link:
            await link.wait_for_agent()
            for f in frames[robot][:STEPS]:
                link.publish_frame(f)
                await asyncio.sleep(0.4)
            await asyncio.sleep(2.0)  # the last slots cross the router

    async def scenario() -> dict[str, EstimateMessage]:
        await asyncio.gather(*(feed(r) for r in ROBOTS))
        operator = ZenohTransport(
            ZenohSettings(
                connect=(hubs["hub-a"],), config_file=folders["op"] / "zenoh.json5", mode="client"
            )
        )
        estimates = Inbox(64)
        operator.subscribe(KEYS.estimate("*"), estimates)
        await operator.open()
        try:
            return {
                r: await ask_status(
                    operator, estimates, KEYS, lambda e, r=r: e.robot == r and e.k == STEPS
                )
                for r in ROBOTS
            }
        finally:
            operator.publish(KEYS.ctl("stop"), encode_control(Stop("test")))
            await asyncio.sleep(0.5)
            await operator.close()

    try:
        final = asyncio.run(scenario())
        for p in procs[2:]:
            p.wait(20)
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
            p.wait(10)
    for r, other in (("r1", "r2"), ("r2", "r1")):
        c = final[r].counters
        assert c["frames_processed"] == STEPS, (r, c)
        assert c["stacks_merged"] >= 1 and c["stacks_invalid"] == 0, (r, c)
        held = set(final[r].beliefs["distributed"].object_ids)
        assert set(final[other].beliefs["local"].object_ids) <= held, r
        assert len(held) > len(final[r].beliefs["local"].object_ids), r
    assert procs[2].returncode == procs[3].returncode == 0
    for hub, proc in zip(hubs, procs[:2], strict=True):  # SIGTERM is a router's normal stop
        said = (tmp_path / f"{hub}.log").read_text(errors="replace")
        assert proc.returncode == 0 and "error" not in said, said
        assert said.endswith("router stopped (SIGTERM), its session closed\n"), said
