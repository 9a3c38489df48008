"""`semfleet replay --robot ID --frames FILE.jsonl --config AGENT.toml [--period S] [--wait]`.

Publishes a frame log (docs/wire.md, "Frame logs") on ``frames/<robot>`` to the robot's running
agent, as the robot's perception process would, through :class:`agents.perception.RobotLink`:
it answers the agent's ``ctl/need`` from the whole log. Its own Zenoh session dials the agent's
listen (and connect) endpoints from the agent's config and listens on nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import math
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.base.errors import UsageError
from deploy.operator.agent_config import load_agent_config
from deploy.operator.replay import read_frames_file, replay, replay_settings
from protocol.framelog import FrameLogError


def run(args: argparse.Namespace, console: Console) -> int:
    path = Path(args.frames)
    try:
        frames = read_frames_file(path)
    except (FrameLogError, OSError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise UsageError(f"--frames {path}: {reason}") from None
    if frames[0].robot != args.robot:
        raise UsageError(f"--frames {path}: robot {frames[0].robot}'s frames, not {args.robot}'s")
    config = load_agent_config(Path(args.config), args.robot)
    settings = replay_settings(config.zenoh)
    console.print(
        f"replaying {len(frames)} frames of {args.robot} on fleet {config.fleet} every "
        f"{args.period:g} s, dialling {', '.join(settings.endpoints()[1]) or 'no endpoint'}"
    )
    report = asyncio.run(
        replay(frames, config.fleet, settings, args.period, args.wait, args.timeout)
    )
    reached = "" if report.reached is None else f"; the agent reached step {report.reached}"
    console.print(
        f"published {report.frames} frames in {report.wall_s:.1f} s, re-sent "
        f"{report.frames_resent} for {report.need_requests} need requests{reached}"
    )
    return 0


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and 0.0 <= value <= 3600.0):
        raise argparse.ArgumentTypeError(f"{text}: seconds must be in 0..3600")
    return value


def add_parser(sub: Any) -> None:
    p = sub.add_parser("replay", help="publish a robot's frame log (JSON lines) to its agent")
    p.add_argument("--robot", required=True, help="the robot whose frames the log holds")
    p.add_argument("--frames", required=True, help="the frame log (docs/wire.md, Frame logs)")
    p.add_argument("--config", required=True, help="the agent's config TOML (fleet, endpoints)")
    p.add_argument("--period", type=_seconds, default=0.5, help="seconds between frames (0.5)")
    p.add_argument(
        "--wait",
        action="store_true",
        help="stay until the agent's estimate reaches the last step",
    )
    p.add_argument(
        "--timeout",
        type=_seconds,
        default=60.0,
        help="seconds to wait for the agent to come up, and with --wait for its last step (60)",
    )
    p.set_defaults(run=run)
