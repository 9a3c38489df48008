"""`semfleet agent --robot ID --config FILE`: one robot of the fleet as an asyncio process.

The config file (TOML, docs/agents.md) names the fleet, the scenario that provides the belief model
and the link model, the seed, the run mode, the journal and the Zenoh endpoints. The process runs
until SIGINT/SIGTERM or a ``ctl/stop`` and then closes its Zenoh session and journal within 2 s.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console

from agents.journal import Journal, JournalError, Record
from agents.links import Partition
from agents.node import RobotNode
from agents.runtime import MODES, Agent, RuntimeSettings
from agents.transport.base import Keys, Message
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.fleet import COMM_MODES, link_model_for
from deploy.study import belief_model, belief_rng
from estimator.hybrid import BeliefConfig
from protocol.frames import encode_frame
from protocol.validate import valid_id
from sim.loader import load_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator

log = logging.getLogger("semfleet.agent")


class AgentConfigError(ValueError):
    """A bad agent config: names the file and field."""

    def __init__(self, path: Path, field: str, reason: str) -> None:
        super().__init__(f"{path}: {field}: {reason}")
        self.field = field


@dataclass(frozen=True, slots=True)
class AgentConfig:
    robot: str
    fleet: str
    scenario: str
    variants: tuple[str, ...]
    seed: int
    runtime: RuntimeSettings
    journal: Path | None
    comm: str | None
    drop: float
    partitions: tuple[Partition, ...]
    zenoh: ZenohSettings
    replay_period: float | None = None


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
    "fleet", "scenario", "variants", "seed", "mode", "gossip_period", "journal", "comm", "drop",
    "partitions", "publish_local", "replay_period",
}  # fmt: skip
_ZENOH_KEYS = {"listen", "connect", "gossip", "shared_memory", "lease_ms", "config_file"}


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
    if "scenario" not in a:
        raise AgentConfigError(path, "agent.scenario", "missing")
    base = path.parent
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
        else 0.5
    )
    if not (math.isfinite(period) and 0.01 <= period <= 3600):
        raise AgentConfigError(path, "agent.gossip_period", "must be in 0.01..3600 s")
    comm = _get(a, "comm", str, path, "agent") if "comm" in a else None
    if comm is not None and comm not in COMM_MODES:
        raise AgentConfigError(path, "agent.comm", f"{comm!r} (known: {', '.join(COMM_MODES)})")
    drop = float(_get(a, "drop", (int, float), path, "agent")) if "drop" in a else 0.0
    if not 0.0 <= drop <= 1.0:
        raise AgentConfigError(path, "agent.drop", "must be in [0, 1]")
    partitions = []
    for i, p in enumerate(_get(a, "partitions", list, path, "agent") if "partitions" in a else []):
        where = f"agent.partitions[{i}]"
        if not (
            isinstance(p, list)
            and len(p) == 3
            and isinstance(p[0], list)
            and all(isinstance(r, str) and valid_id(r) for r in p[0])
            and all(isinstance(v, int) and not isinstance(v, bool) for v in p[1:])
        ):
            raise AgentConfigError(path, where, "expected [[robot ids], first step, last step]")
        try:
            partitions.append(Partition(frozenset(map(str, p[0])), int(p[1]), int(p[2])))
        except (TypeError, ValueError) as exc:
            raise AgentConfigError(path, where, str(exc)) from None
    replay_period = None
    if "replay_period" in a:
        replay_period = float(_get(a, "replay_period", (int, float), path, "agent"))
        if not (math.isfinite(replay_period) and 0.001 <= replay_period <= 3600):
            raise AgentConfigError(path, "agent.replay_period", "must be in 0.001..3600 s")
        if mode != "realtime":
            raise AgentConfigError(path, "agent.replay_period", 'needs mode = "realtime"')
    journal = None
    if "journal" in a:
        journal = base / _get(a, "journal", str, path, "agent")
    variants = tuple(_get(a, "variants", list, path, "agent")) if "variants" in a else ()
    runtime = RuntimeSettings(
        mode=mode,
        gossip_period=period,
        publish_local=_get(a, "publish_local", bool, path, "agent")
        if "publish_local" in a
        else True,
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
    scenario = _get(a, "scenario", str, path, "agent")
    if scenario.endswith(".toml") and not Path(scenario).is_absolute():
        scenario = str(base / scenario)
    return AgentConfig(
        robot, fleet, scenario, tuple(map(str, variants)), seed, runtime, journal, comm, drop,
        tuple(partitions), zenoh_settings, replay_period,
    )  # fmt: skip


def build_agent(config: AgentConfig, scenario: Scenario, transport: ZenohTransport) -> Agent:
    """The node (L and D seeded exactly like the in-process runner's), its journal, the agent."""
    if config.robot not in scenario.robot_ids:
        raise AgentConfigError(
            Path(config.scenario), "--robot", f"{config.robot} is not in the scenario"
        )
    model = belief_model(scenario)
    start = scenario.robot(config.robot).start
    rng = lambda: belief_rng(config.seed, [config.robot])  # noqa: E731
    node = RobotNode(config.robot, start, model, rng(), rng(), BeliefConfig())
    links = link_model_for(scenario, config.comm, config.drop, config.seed, config.partitions)
    journal = None
    records: list[Record] = []
    if config.journal is not None:
        identity: dict[str, str | int] = {
            "robot": config.robot,
            "fleet": config.fleet,
            "scenario": scenario.name,
            "seed": config.seed,
            "mode": config.runtime.mode,
        }
        journal, records = Journal.open(config.journal, identity)
    agent = Agent(node, transport, Keys(config.fleet), links, config.runtime, journal)
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


async def _replay_frames(agent: Agent, scenario: Scenario, seed: int, period: float) -> None:
    """The simulation source without a conductor: the robot's own frames, one per period."""
    frames = Simulator(scenario, seed).all_frames()[agent.robot]
    key = agent.keys.frames(agent.robot)
    for frame in frames[agent.node.k :]:
        agent.frames.put(Message(key, encode_frame(frame)))
        await asyncio.sleep(period)


async def _log_counters(agent: Agent, every: float) -> None:
    while True:
        await asyncio.sleep(every)
        log.info("%s: counters", agent.robot, extra={"event": "counters", **agent.counter_values()})


async def serve(config: AgentConfig) -> int:
    scenario = load_scenario(config.scenario, config.variants)
    transport = ZenohTransport(config.zenoh)
    agent = build_agent(config, scenario, transport)
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
    helpers = [asyncio.create_task(_log_counters(agent, 10.0))]
    if config.replay_period is not None:
        helpers.append(
            asyncio.create_task(_replay_frames(agent, scenario, config.seed, config.replay_period))
        )
    try:
        await agent.run()
    finally:
        for task in helpers:
            task.cancel()
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
    try:
        code = asyncio.run(serve(config))
    except JournalError as exc:
        raise ValueError(f"journal: {exc}") from None
    # The Zenoh session and the journal are closed and flushed by now; tearing down the
    # interpreter (tokio's threads, GTSAM's statics) can take seconds on a loaded machine, which
    # would break the 2 s shutdown promise. Leave at once.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("agent", help="run one robot of the fleet (asyncio, Zenoh)")
    p.add_argument("--robot", required=True, help="the robot id (as in the scenario)")
    p.add_argument("--config", required=True, help="agent config TOML (docs/agents.md)")
    p.set_defaults(run=run)
