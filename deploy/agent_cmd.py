"""`semfleet agent --robot ID --config FILE`: one robot of the fleet as an asyncio process.

The config file (TOML, docs/agents.md) names the fleet, the robot model file (classes, classifier,
noise, sensor: what the robot knows of itself), the start pose, the fleet roster, the seed, the run
mode, the journal and the Zenoh endpoints. No world, no scenario and no ground truth: exactly what
a robot has. The process runs until SIGINT/SIGTERM or a ``ctl/stop`` and then closes its Zenoh
session and journal within 2 s.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import os
import signal
import sys
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from rich.console import Console

from agents.core import GOSSIP_PERIOD_S, WINDOW_STEPS, AgentCore, CoreSettings
from agents.journal import Journal, Record
from agents.node import RobotNode
from agents.runtime import Agent
from agents.transport.base import Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.build import belief_model, make_node
from estimator.hybrid import BeliefConfig
from protocol.codec import Limits
from protocol.validate import valid_id
from sim.loader import FieldReader, parse_toml, read_file
from sim.robot_model import RobotModel, dump_robot_model, load_robot_model
from sim.scenario import ScenarioError

log = logging.getLogger("semfleet.agent")

MODES = ("lockstep", "realtime")


class AgentConfigError(ValueError):
    """A bad agent config: names the file and field."""

    def __init__(self, path: Path, field: str, reason: str) -> None:
        super().__init__(f"{path}: {field}: {reason}")
        self.field = field


@dataclass(frozen=True, slots=True)
class AgentConfig:
    robot: str
    fleet: str
    model_path: Path
    model: RobotModel
    start: tuple[float, float, float]
    roster: frozenset[str]
    seed: int
    runtime: CoreSettings
    journal: Path | None
    zenoh: ZenohSettings
    limits: Limits


_AGENT_KEYS = {
    "fleet", "model", "start", "roster", "seed", "mode", "gossip_period", "journal",
    "publish_local", "simulation", "window", "world_extent",
}  # fmt: skip
_ZENOH_KEYS = {"listen", "connect", "gossip", "shared_memory", "lease_ms", "config_file"}
MAX_EXTENT = 1e7  # metres: a UTM-like frame; beyond, float64 poses lose millimetres


def load_agent_config(path: Path, robot: str) -> AgentConfig:
    """Parse and validate an agent config; relative paths are relative to the file's folder.
    Read with the scenario format's field reader (one validation path for every config file);
    every error is an :class:`AgentConfigError` naming the file and the field."""
    if not valid_id(robot):
        raise AgentConfigError(path, "--robot", f"invalid robot id {robot!r}")
    try:
        return _read_agent_config(path, robot)
    except ScenarioError as exc:
        raise AgentConfigError(path, exc.field or "toml", exc.reason) from None


def _read_agent_config(path: Path, robot: str) -> AgentConfig:
    label = str(path)
    top = FieldReader(label, parse_toml(read_file(path, "agent config"), label), "")
    top.check_keys({"agent", "zenoh"})
    a = top.table("agent") if top.has("agent") else FieldReader(label, {}, "agent")
    z = top.table("zenoh") if top.has("zenoh") else FieldReader(label, {}, "zenoh")
    a.check_keys(_AGENT_KEYS)
    z.check_keys(_ZENOH_KEYS)
    base = path.parent
    model_path = base / a.string("model")
    try:
        model = load_robot_model(model_path)
    except ScenarioError as exc:
        raise a.fail("model", str(exc)) from None
    extent = a.number("world_extent", positive=True) if a.has("world_extent") else None
    if extent is not None and not 1.0 <= extent <= MAX_EXTENT:
        raise a.fail("world_extent", f"must be in 1..{MAX_EXTENT:g} m")
    limits = Limits(num_classes=model.num_classes, world_extent=extent or Limits().world_extent)
    x, y, theta = a.vector("start", 3)
    if max(abs(x), abs(y)) > limits.world_extent or abs(theta) > 2 * math.pi:
        reason = f"|x|, |y| ≤ world_extent {limits.world_extent:g} m and |theta| ≤ 2π"
        raise a.fail("start", reason)
    roster_field = a.array("roster")
    roster = [roster_field.string(i) for i in range(len(roster_field.raw))]
    if not all(valid_id(r) for r in roster) or len(set(roster)) != len(roster):
        raise a.fail("roster", "expected distinct robot ids")
    if robot not in roster:
        raise a.fail("roster", f"does not list this robot ({robot})")
    fleet = a.string("fleet") if a.has("fleet") else "default"
    if not valid_id(fleet):
        raise a.fail("fleet", f"invalid fleet name {fleet!r}")
    mode = a.string("mode") if a.has("mode") else "realtime"
    if mode not in MODES:
        raise a.fail("mode", f"{mode!r} (known: {', '.join(MODES)})")
    period = a.number("gossip_period") if a.has("gossip_period") else GOSSIP_PERIOD_S
    if not 0.01 <= period <= 3600:
        raise a.fail("gossip_period", "must be in 0.01..3600 s")
    runtime = CoreSettings(
        mode=mode,
        gossip_period=period,
        window=a.integer("window", 1, 100_000) if a.has("window") else WINDOW_STEPS,
        publish_local=a.boolean("publish_local") if a.has("publish_local") else True,
        simulation=a.boolean("simulation") if a.has("simulation") else False,
    )
    endpoints = {}
    for name in ("listen", "connect"):
        field = z.array(name) if z.has(name) else FieldReader(label, [], f"zenoh.{name}")
        values = [field.string(i) for i in range(len(field.raw))]
        for e in values:
            if "/" not in e:
                raise z.fail(name, f"bad endpoint {e!r} (e.g. tcp/127.0.0.1:7447)")
        endpoints[name] = tuple(values)
    zenoh_settings = ZenohSettings(
        listen=endpoints["listen"],
        connect=endpoints["connect"],
        gossip=z.boolean("gossip") if z.has("gossip") else True,
        shared_memory=z.boolean("shared_memory") if z.has("shared_memory") else False,
        lease_ms=z.integer("lease_ms", 100, 3_600_000) if z.has("lease_ms") else 3000,
        config_file=base / z.string("config_file") if z.has("config_file") else None,
    )
    return AgentConfig(
        robot=robot,
        fleet=fleet,
        model_path=model_path,
        model=model,
        start=(x, y, theta),
        roster=frozenset(roster),
        seed=a.integer("seed", 0, 2**63 - 1) if a.has("seed") else 0,
        runtime=runtime,
        journal=base / a.string("journal") if a.has("journal") else None,
        zenoh=zenoh_settings,
        limits=limits,
    )


def node_factory(config: AgentConfig) -> Callable[[], RobotNode]:
    """Builds the agent's node at step 0: L and D seeded exactly like the in-process runner's,
    holding the slots of the roster's robots only."""
    model = belief_model(config.model)

    return partial(
        make_node,
        config.robot,
        config.start,
        model,
        config.seed,
        BeliefConfig(),
        roster=config.roster,
        limits=config.limits,
    )


def journal_identity(config: AgentConfig) -> dict[str, str | int]:
    """What a journal must have been written by: this robot, fleet, model, start, seed, mode."""
    model = zlib.crc32(dump_robot_model(config.model).encode())
    start = zlib.crc32(repr(config.start).encode())
    return {
        "robot": config.robot,
        "fleet": config.fleet,
        "model": f"{model:08x}",
        "start": f"{start:08x}",
        "seed": config.seed,
        "mode": config.runtime.mode,
    }


def build_agent(config: AgentConfig, transport: ZenohTransport) -> Agent:
    """The core (its node from the robot model), its journal replayed, the agent."""
    journal = None
    records: list[Record] = []
    if config.journal is not None:
        journal, records = Journal.open(config.journal, journal_identity(config))
    core = AgentCore(node_factory(config), Keys(config.fleet), config.runtime)
    agent = Agent(core, transport, journal)
    agent.replay(records)
    return agent


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
    log.info(
        "%s: up at step %d (%s mode)",
        config.robot,
        agent.node.k,
        config.runtime.mode,
        extra={"event": "start", "step": agent.node.k, "mode": config.runtime.mode},
    )
    counters = asyncio.create_task(_log_counters(agent, 10.0))
    try:
        await agent.run()
    finally:
        counters.cancel()
    log.info(
        "%s: stopped (%s)",
        config.robot,
        agent.stop_reason,
        extra={"event": "stop", "reason": agent.stop_reason, **agent.counter_values()},
    )
    return 0


def run(args: argparse.Namespace, console: Console) -> int:
    config = load_agent_config(Path(args.config), args.robot)
    handler = logging.StreamHandler()
    handler.setFormatter(JsonLines(config.robot))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO if not args.verbose else logging.DEBUG)
    code = asyncio.run(serve(config))
    # The Zenoh session and the journal are closed and flushed by now; tearing down the
    # interpreter (tokio's threads, GTSAM's statics) can take seconds on a loaded machine, which
    # would break the 2 s shutdown promise. Leave at once.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("agent", help="run one robot of the fleet (asyncio, Zenoh)")
    p.add_argument("--robot", required=True, help="the robot id (listed in the roster)")
    p.add_argument("--config", required=True, help="agent config TOML (docs/agents.md)")
    p.set_defaults(run=run)
