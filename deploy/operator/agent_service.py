"""One robot's agent process as a library: its node, journal and Zenoh transport built from an
:class:`~deploy.operator.agent_config.AgentConfig` (:func:`build_agent`), served until
SIGINT/SIGTERM or a ``ctl/stop`` (:func:`serve`), logging one JSON object per line
(:class:`JsonLines`). ``semfleet agent`` (deploy/cli/commands/agent.py) parses its options and
calls these.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import signal
import time
import zlib
from collections.abc import Callable
from functools import partial
from typing import Any

from agents.journal import Journal, Record
from agents.node import RobotNode
from agents.ros2.bridge import Ros2Bridge, Ros2Link
from agents.runtime import Agent, new_agent
from agents.transport.base import Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.base.build import belief_model, make_node, sensor_field
from deploy.operator.agent_config import AgentConfig
from estimator.hybrid import BeliefConfig
from sim.robot_model import dump_robot_model

log = logging.getLogger("semfleet.agent")


def node_factory(config: AgentConfig, epoch: int = 0) -> Callable[[], RobotNode]:
    """Builds the agent's node at step 0: L and D seeded exactly like the in-process runner's,
    holding the slots of the roster's robots only, its own slots of ``epoch``."""
    model = belief_model(config.model)

    return partial(
        make_node,
        config.robot,
        config.start,
        model,
        config.seed,
        BeliefConfig(
            classes=config.classes, window=config.pose_window, xi_parents=config.xi_parents
        ),
        roster=config.roster,
        limits=config.limits,
        signing=config.signing,
        epoch=epoch,
        sensor=sensor_field(config.model),
        keep_slots=config.keep_slots,
        guided=config.associate_on == "fused",
    )


def journal_identity(config: AgentConfig) -> dict[str, str | int]:
    """What a journal must have been written by: this robot, fleet, model, start, seed, mode."""
    model = zlib.crc32(dump_robot_model(config.model).encode())
    start = zlib.crc32(repr(config.start).encode())
    identity: dict[str, str | int] = {
        "robot": config.robot,
        "fleet": config.fleet,
        "model": f"{model:08x}",
        "start": f"{start:08x}",
        "seed": config.seed,
        "mode": config.runtime.mode,
    }
    if config.associate_on != "fused":  # replayed frames would be associated otherwise
        identity["associate_on"] = config.associate_on
    return identity


def build_agent(config: AgentConfig, transport: ZenohTransport) -> Agent:
    """The core (its node from the robot model), its journal replayed, the agent.

    The own slots' epoch is the journal's: the time (ms since the Unix epoch) the journal was
    made, or this start's for an agent without one. A robot that lost its journal so starts
    again above every version it made before (docs/wire.md, "Versions and epochs"). A journal
    whose header is damaged is moved aside with the UTC time in its name, and the agent starts
    with an empty one (a new epoch) instead of refusing to start."""
    journal = None
    records: list[Record] = []
    epoch = time.time_ns() // 1_000_000
    if config.journal is not None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        journal, records = Journal.open(
            config.journal, journal_identity(config), epoch, set_aside_bad_header=stamp
        )
        epoch = journal.epoch
    agent = new_agent(
        node_factory(config, epoch),
        Keys(config.fleet),
        transport,
        config.runtime,
        journal,
        wall_clock=time.time,
        ros2=ros2_link(config, transport),
    )
    agent.replay(records)
    return agent


def ros2_link(config: AgentConfig, transport: ZenohTransport) -> Ros2Link | None:
    """The agent's ROS 2 side (docs/ros2.md) if its config has ``[ros2] enable = true``: a Zenoh
    session of its own, a client of the robot's router (``[ros2] connect``), which forwards for
    its clients whatever the fleet session's gossip (a router never forwards between two of its
    peers); with ``connect = []``, the agent's own session. The ROS graph's session id is a
    fresh random one: rmw_zenoh reads it as an opaque id."""
    if config.ros2 is None:
        return None
    bridge = Ros2Bridge(config.ros2, config.robot, config.model.num_classes, secrets.token_hex(16))
    session = transport
    if config.ros2.connect:
        session = ZenohTransport(ZenohSettings(connect=config.ros2.connect, mode="client"))
    return Ros2Link(bridge, session.publish, session, own_session=session is not transport)


class JsonLines(logging.Formatter):
    """One JSON object per line: time, level, logger, message and any ``extra`` fields."""

    _STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {"message"}

    def __init__(self, robot: str) -> None:
        super().__init__()
        self.robot = robot

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "logger": record.name,
            "robot": self.robot,
            "msg": record.getMessage(),
        }
        doc.update({k: v for k, v in vars(record).items() if k not in self._STANDARD})
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


async def _log_counters(agent: Agent, every: float) -> None:
    while True:
        await asyncio.sleep(every)
        log.info("%s: counters", agent.robot, extra={"event": "counters", **agent.counter_values()})


async def serve(config: AgentConfig) -> int:
    transport = ZenohTransport(config.zenoh)
    agent = build_agent(config, transport)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, agent.stop, signal.Signals(sig).name)
    listen = ", ".join(config.zenoh.endpoints()[0]) or "no endpoint"

    def up() -> None:  # only once the session is open: its listen endpoints are bound
        log.info(
            "%s: up at step %d (%s mode), listening on %s",
            config.robot,
            agent.node.k,
            config.runtime.mode,
            listen,
            extra={"event": "start", "step": agent.node.k, "mode": config.runtime.mode},
        )

    counters = asyncio.create_task(_log_counters(agent, 10.0))
    try:
        await agent.run(on_open=up)
    finally:
        counters.cancel()
    log.info(
        "%s: stopped (%s)",
        config.robot,
        agent.stop_reason,
        extra={"event": "stop", "reason": agent.stop_reason, **agent.counter_values()},
    )
    return 0
