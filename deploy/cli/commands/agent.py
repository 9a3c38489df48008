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
import logging
import os
import sys
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.operator.agent_config import load_agent_config
from deploy.operator.agent_service import JsonLines, serve


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
