"""`semfleet fleet status|watch|stop`: an operator's view of a running fleet, from outside it.

The operator opens its own Zenoh session that only dials out (``--connect``, never listens). By
default it is a Zenoh *client*: the robot it reaches routes for it, so it sees that robot and every
robot linked to it, whatever the fleet's gossip settings (peers never forward for each other, but
they do for their clients). ``--mode peer`` joins as a peer instead: with gossip scouting on it
links directly to every robot the fleet's own gossip reveals, and sees only the robots it dialled
when the fleet runs without gossip.

It uses three keys of docs/agents.md: the liveliness tokens ``alive/<robot>``, the estimates
``estimate/<robot>`` (published after every step and at once on ``ctl/status``), and the
``ctl/status`` and ``ctl/stop`` it sends. This module parses, calls
:mod:`deploy.operator.fleet_session` and prints; the picture itself is
:class:`deploy.operator.fleet_view.FleetView`.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
from pathlib import Path
from typing import Any

from rich.console import Console

from agents.transport.base import Keys
from agents.transport.zenoh_transport import ZenohSettings
from deploy.base.errors import RunFailure, UsageError
from deploy.base.output import FiguresTable, figures_table, live_display
from deploy.cli.args import zenoh_endpoint
from deploy.cli.commands.fleet_init import add_init_parser
from deploy.cli.outputs import add_force, new_folder
from deploy.operator.fleet_session import collect_status, session_settings, stop_fleet, watch_fleet
from deploy.operator.fleet_view import (
    FleetView,
    age_line,
    behind_line,
    status_doc,
    write_watch_results,
)
from estimator.models import ROBOT_ID_RULE
from protocol.validate import valid_id

MODES = ("client", "peer")
# Shown when present in any robot's counters; --json and estimates.json carry every counter.
COUNTER_COLUMNS = (
    ("stacks_sent", "sent"),
    ("stacks_merged", "merged"),
    ("stacks_invalid", "invalid"),
    ("slots_rejected", "slots rej."),
    ("frames_processed", "frames"),
    ("frames_quarantined", "quarantined"),
)
# What goes wrong, shown only when it did on some robot (the caption says so otherwise): a healthy
# fleet's table then fits 80 columns in one piece.
TROUBLE = frozenset({"stacks_invalid", "slots_rejected", "frames_quarantined"})


def connection(args: argparse.Namespace) -> tuple[ZenohSettings, Keys]:
    """The session settings and the fleet's keys from the common options."""
    if not valid_id(args.fleet):
        raise UsageError(f"--fleet {args.fleet!r}: {ROBOT_ID_RULE}")
    endpoints = tuple(zenoh_endpoint(e, "--connect") for e in args.connect)
    config_file = None
    if args.zenoh_config is not None:
        config_file = Path(args.zenoh_config)
        if not config_file.is_file():
            raise UsageError(f"--zenoh-config {config_file}: no such file")
    if not (math.isfinite(args.timeout) and 0 < args.timeout <= 3600):
        raise UsageError(f"--timeout {args.timeout}: must be in (0, 3600] s")
    return session_settings(endpoints, args.mode, config_file), Keys(args.fleet)


def fleet_table(view: FleetView, title: str, now: float | None = None) -> FiguresTable:
    """Robot, token, step, hypotheses and objects of D / L, the :data:`COUNTER_COLUMNS` some
    robot reports (those of :data:`TROUBLE` only when not 0 on some robot: the caption names the
    others) and, given ``now``, the age of the latest estimate."""
    estimates = [s.estimate for s in view.robots.values() if s.estimate is not None]
    reported = [(k, h) for k, h in COUNTER_COLUMNS if any(k in e.counters for e in estimates)]
    zero = [
        h for k, h in reported if k in TROUBLE and all(not e.counters.get(k) for e in estimates)
    ]
    shown = [(k, h) for k, h in reported if h not in zero]
    headings = ["robot", "alive", "step", "hyp. D/L", "objects D/L", *(h for _, h in shown)]
    if now is not None:
        headings.append("age (s)")
    rows = []
    for robot in sorted(view.robots):
        state = view.robots[robot]
        est = state.estimate
        alive = "[green]yes[/]" if state.alive else "[red]no[/]"
        ages = ["—"] if now is not None else []
        if est is None:
            rows.append([robot, alive, "—", "—", "—", *("—" for _ in shown), *ages])
            continue
        d, loc = est.beliefs.get("distributed"), est.beliefs.get("local")
        hyp = "/".join(str(len(s.weights)) if s else "—" for s in (d, loc))
        objects = "/".join(str(len(s.object_ids)) if s else "—" for s in (d, loc))
        counters = (str(est.counters.get(k, "—")) for k, _ in shown)
        if now is not None:
            ages = [f"{now - state.received:.1f}"]
        rows.append([robot, alive, str(est.k), hyp, objects, *counters, *ages])
    caption = f"0 on every robot: {', '.join(zero)}" if zero else ""
    return figures_table(title, headings, rows, caption=caption)


def run_status(args: argparse.Namespace, console: Console) -> int:
    settings, keys = connection(args)
    view, elapsed, answered = asyncio.run(collect_status(settings, keys, args.timeout))
    if args.json:
        print(json.dumps(status_doc(view, elapsed, answered), indent=1))
        return 0
    title = f"fleet {keys.fleet} at {', '.join(settings.connect)}"
    console.print(fleet_table(view, title))
    console.print(
        f"{len(view.alive())} alive, {len(view.answered())} answered"
        + (f" (the last {answered:.3f} s after ctl/status)" if math.isfinite(answered) else "")
        + (f"; {view.invalid} invalid estimates ({view.last_error})" if view.invalid else "")
    )
    for line in (behind_line(view), age_line(view)):
        if line:
            console.print(line)
    return 0


def run_watch(args: argparse.Namespace, console: Console) -> int:
    settings, keys = connection(args)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration {args.duration}: must be a positive number")
    if args.out is not None:
        new_folder(Path(args.out), "--out", args.force)
    title = f"fleet {keys.fleet} at {', '.join(settings.connect)}"
    with live_display(console) as live:

        def show(view: FleetView, now: float) -> None:
            live.update(fleet_table(view, title, now))

        view, watched = asyncio.run(watch_fleet(settings, keys, args.duration, args.timeout, show))
    if not console.is_terminal:
        console.line()  # Live leaves its last frame without a newline outside a terminal
    if not view.answered():
        raise RunFailure(
            f"no robot of fleet {keys.fleet!r} sent an estimate during the watch ({watched:.1f} s)"
        )
    if args.out is not None:
        paths = write_watch_results(Path(args.out), view, watched)
        console.print("wrote " + ", ".join(str(p) for p in paths), soft_wrap=True)  # paths whole
    return 0


def run_stop(args: argparse.Namespace, console: Console) -> int:
    settings, keys = connection(args)
    stopped, still, took = asyncio.run(stop_fleet(settings, keys, args.reason, args.timeout))
    if stopped:
        console.print(f"stopped: {', '.join(stopped)} (tokens gone {took:.3f} s after ctl/stop)")
    if still:
        raise RunFailure(f"still alive after {args.timeout:g} s: {', '.join(still)}")
    return 0


def _common(p: argparse.ArgumentParser, timeout: float, waits_for: str) -> None:
    p.add_argument(
        "--connect",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="a robot's (or router's) Zenoh endpoint, e.g. tcp/10.0.0.5:7447; repeat for failover",
    )
    p.add_argument("--fleet", required=True, help="the fleet name (semfleet/<fleet>/...)")
    p.add_argument(
        "--mode",
        choices=MODES,
        default="client",
        help="Zenoh client (default: the reached robot routes for us) or peer (gossip scouting)",
    )
    p.add_argument("--zenoh-config", help="a Zenoh JSON5 file applied first (TLS, access control)")
    p.add_argument(
        "--timeout",
        type=float,
        default=timeout,
        help=f"seconds to wait for {waits_for} (default {timeout:g})",
    )


def add_parser(sub: Any) -> None:
    p = sub.add_parser("fleet", help="make a secure fleet; see and stop a running one (operator)")
    actions = p.add_subparsers(dest="action_name", required=True, metavar="ACTION")
    add_init_parser(actions)
    status = actions.add_parser("status", help="who is alive, steps, counters (one snapshot)")
    _common(status, 2.0, "the robots' answers")
    status.add_argument("--json", action="store_true", help="a JSON document instead of a table")
    status.set_defaults(run=run_status)
    watch = actions.add_parser("watch", help="a live table until Ctrl-C, SIGTERM or --duration")
    _common(watch, 10.0, "the first robot")
    watch.add_argument("--duration", type=float, help="stop watching after this many seconds")
    watch.add_argument("--out", help="write estimates.json and map.png here when the watch ends")
    add_force(watch)
    watch.set_defaults(run=run_watch)
    stop = actions.add_parser("stop", help="ctl/stop, then wait until every token is gone")
    _common(stop, 5.0, "every token to go")
    stop.add_argument("--reason", default="operator stop", help="the reason the agents log")
    stop.set_defaults(run=run_stop)
