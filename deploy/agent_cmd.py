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
import tomllib
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


def _get(
    table: dict[str, Any], key: str, kind: type | tuple[type, ...], path: Path, where: str
) -> Any:
    value = table[key]
    if isinstance(value, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise AgentConfigError(path, f"{where}.{key}", f"expected {_name(kind)}, got a boolean")
    if not isinstance(value, kind):
        raise AgentConfigError(
            path, f"{where}.{key}", f"expected {_name(kind)}, got {type(value).__name__}"
        )
    return value


def _name(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(k.__name__ for k in kinds)


_AGENT_KEYS = {
    "fleet", "model", "start", "roster", "seed", "mode", "gossip_period", "journal",
    "publish_local", "simulation", "window", "world_extent",
}  # fmt: skip
_ZENOH_KEYS = {"listen", "connect", "gossip", "shared_memory", "lease_ms", "config_file"}
MAX_EXTENT = 1e7  # metres: a UTM-like frame; beyond, float64 poses lose millimetres


def load_agent_config(path: Path, robot: str) -> AgentConfig:
    """Parse and validate an agent config; relative paths are relative to the file's folder."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise AgentConfigError(path, "toml", str(exc)) from None
    if not valid_id(robot):
        raise AgentConfigError(path, "--robot", f"invalid robot id {robot!r}")
    unknown = set(doc) - {"agent", "zenoh"}
    if unknown:
        raise AgentConfigError(path, sorted(unknown)[0], "unknown table (known: agent, zenoh)")
    a = doc.get("agent", {})
    z = doc.get("zenoh", {})
    for table, keys, name in ((a, _AGENT_KEYS, "agent"), (z, _ZENOH_KEYS, "zenoh")):
        if not isinstance(table, dict):
            raise AgentConfigError(path, name, "expected a table")
        extra = set(table) - keys
        if extra:
            raise AgentConfigError(path, f"{name}.{sorted(extra)[0]}", "unknown key")
    for key in ("model", "start", "roster"):
        if key not in a:
            raise AgentConfigError(path, f"agent.{key}", "missing")
    base = path.parent
    model_path = base / _get(a, "model", str, path, "agent")
    try:
        model = load_robot_model(model_path)
    except ScenarioError as exc:
        raise AgentConfigError(path, "agent.model", str(exc)) from None
    extent = Limits().world_extent
    if "world_extent" in a:
        extent = float(_get(a, "world_extent", (int, float), path, "agent"))
        if not (math.isfinite(extent) and 1.0 <= extent <= MAX_EXTENT):
            raise AgentConfigError(path, "agent.world_extent", f"must be in 1..{MAX_EXTENT:g} m")
    start = _get(a, "start", list, path, "agent")
    if not (
        len(start) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in start)
        and all(math.isfinite(v) for v in start)
        and abs(start[0]) <= extent
        and abs(start[1]) <= extent
        and abs(start[2]) <= 2 * math.pi
    ):
        reason = f"expected [x, y, theta]: |x|, |y| ≤ world_extent {extent:g} m, |theta| ≤ 2π"
        raise AgentConfigError(path, "agent.start", reason)
    roster = _get(a, "roster", list, path, "agent")
    if not all(valid_id(r) for r in roster) or len(set(roster)) != len(roster):
        raise AgentConfigError(path, "agent.roster", "expected distinct robot ids")
    if robot not in roster:
        raise AgentConfigError(path, "agent.roster", f"does not list this robot ({robot})")
    fleet = _get(a, "fleet", str, path, "agent") if "fleet" in a else "default"
    if not valid_id(fleet):
        raise AgentConfigError(path, "agent.fleet", f"invalid fleet name {fleet!r}")
    seed = _get(a, "seed", int, path, "agent") if "seed" in a else 0
    if not 0 <= seed < 2**63:
        raise AgentConfigError(path, "agent.seed", "must be in 0..2^63-1")
    mode = _get(a, "mode", str, path, "agent") if "mode" in a else "realtime"
    if mode not in MODES:
        raise AgentConfigError(path, "agent.mode", f"{mode!r} (known: {', '.join(MODES)})")
    period = (
        float(_get(a, "gossip_period", (int, float), path, "agent"))
        if "gossip_period" in a
        else GOSSIP_PERIOD_S
    )
    if not (math.isfinite(period) and 0.01 <= period <= 3600):
        raise AgentConfigError(path, "agent.gossip_period", "must be in 0.01..3600 s")
    window = _get(a, "window", int, path, "agent") if "window" in a else WINDOW_STEPS
    if not 1 <= window <= 100_000:
        raise AgentConfigError(path, "agent.window", "must be in 1..100000 steps")
    journal = None
    if "journal" in a:
        journal = base / _get(a, "journal", str, path, "agent")
    runtime = CoreSettings(
        mode=mode,
        gossip_period=period,
        window=window,
        publish_local=_get(a, "publish_local", bool, path, "agent")
        if "publish_local" in a
        else True,
        simulation=_get(a, "simulation", bool, path, "agent") if "simulation" in a else False,
    )
    listen = tuple(_get(z, "listen", list, path, "zenoh")) if "listen" in z else ()
    connect = tuple(_get(z, "connect", list, path, "zenoh")) if "connect" in z else ()
    for name, endpoints in (("listen", listen), ("connect", connect)):
        for e in endpoints:
            if not isinstance(e, str) or "/" not in e:
                raise AgentConfigError(
                    path, f"zenoh.{name}", f"bad endpoint {e!r} (e.g. tcp/127.0.0.1:7447)"
                )
    config_file = base / _get(z, "config_file", str, path, "zenoh") if "config_file" in z else None
    lease_ms = _get(z, "lease_ms", int, path, "zenoh") if "lease_ms" in z else 3000
    if not 100 <= lease_ms <= 3_600_000:
        raise AgentConfigError(path, "zenoh.lease_ms", "must be in 100..3600000 ms")
    zenoh_settings = ZenohSettings(
        listen=listen,
        connect=connect,
        gossip=_get(z, "gossip", bool, path, "zenoh") if "gossip" in z else True,
        shared_memory=_get(z, "shared_memory", bool, path, "zenoh")
        if "shared_memory" in z
        else False,
        lease_ms=lease_ms,
        config_file=config_file,
    )
    return AgentConfig(
        robot, fleet, model_path, model, (float(start[0]), float(start[1]), float(start[2])),
        frozenset(roster), seed, runtime, journal, zenoh_settings,
        Limits(num_classes=model.num_classes, world_extent=extent),
    )  # fmt: skip


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
