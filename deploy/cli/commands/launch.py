"""`semfleet launch` and `semfleet chaos`: multi-process runs of a scenario over loopback Zenoh.

Over 300 lines for a reason: the two commands share their options, the settings they write into
the agents' configs (and the checks that refuse those with ``--conductor-only`` or ``--attack``)
and the checks of their outputs; split, the two option sets would drift apart.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from agents.core import STACK_GOSSIP
from agents.gossip import RELAYS
from agents.links import Partition
from deploy.base.errors import UsageError
from deploy.cli.args import positive_float, positive_int, seed, slot_count
from deploy.cli.commands import conductor_only, ros2_options
from deploy.cli.outputs import add_force, new_file, new_folder
from deploy.launch import LAUNCH_METHODS, Faults, LaunchPlan
from deploy.launch.attack_report import attack_list, run_attacks_command
from deploy.launch.attacks import ATTACKS
from deploy.launch.netns import require as require_netns
from deploy.launch.report import agents, aoi_entry, counters_table, security_line, write_outputs
from deploy.launch.rerun_view import add_options as add_view_options
from deploy.launch.rerun_view import check_view, launch_recorded
from deploy.study.fleet import COMM_MODES
from deploy.study.runner import run_single
from estimator.hybrid import BeliefConfig
from estimator.models import ROBOT_ID
from sim.loader import load_scenario
from sim.scenario import Scenario

_STEP = re.compile(r"^\d{1,9}$")
_PARTITION = re.compile(r"^([A-Za-z0-9_,-]+):(\d{1,9})-(\d{1,9})$")


def robot_at(text: str) -> tuple[str, int]:
    robot, _, step = text.partition("@")
    if not (ROBOT_ID.fullmatch(robot) and _STEP.fullmatch(step)):
        raise argparse.ArgumentTypeError(f"expected ROBOT@STEP, got {text!r}")
    return robot, int(step)


def partition(text: str) -> Partition:
    m = _PARTITION.fullmatch(text)
    if not m:
        raise argparse.ArgumentTypeError(f"expected IDS:FROM-TO (e.g. r1,r2:20-30), got {text!r}")
    ids = frozenset(i for i in m.group(1).split(",") if i)
    try:
        return Partition(ids, int(m.group(2)), int(m.group(3)))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def probability(text: str) -> float:
    try:
        p = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= p <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return p


def _robots(scenario: Scenario, text: str) -> list[str]:
    if text == "all":
        return list(scenario.robot_ids)
    robots = [r for r in text.split(",") if r]
    unknown = [r for r in robots if r not in scenario.robot_ids]
    if unknown or not robots:
        known = ", ".join(scenario.robot_ids)
        raise UsageError(f"--robots: unknown robots {unknown} (scenario has {known})")
    return robots


def _steps(scenario: Scenario, steps: int | None) -> int | None:
    if steps is not None and steps > scenario.steps:
        raise UsageError(f"--steps: {steps} outside 1..{scenario.steps} (scenario {scenario.name})")
    return steps


def _agents_setting(args: argparse.Namespace, name: str, default: Any) -> Any:
    """``--stack-gossip``, ``--relay`` or ``--keep-slots``: written into the agents' configs,
    so never with ``--conductor-only`` (the agents' own configs decide)."""
    value = getattr(args, name)
    if value is not None and getattr(args, "conductor_only", False):
        flag = "--" + name.replace("_", "-")
        raise UsageError(f"{flag}: not with --conductor-only (the agents' configs decide)")
    return default if value is None else value


def check_outputs(args: argparse.Namespace) -> None:
    """``--out``, ``--record`` and ``--view`` (a display, Rerun installed) of ``demo``,
    ``launch`` and ``chaos``, before anything starts or is printed."""
    new_folder(Path(args.out), "--out", args.force)
    if args.record is not None:
        new_file(Path(args.record), "--record", args.force)
    check_view(args.view, args.record)


def run_launch(args: argparse.Namespace, console: Console) -> int:
    scenario = load_scenario(args.scenario)
    robots = _robots(scenario, args.robots)
    ros2 = ros2_options.ros2_table(args, scenario, robots)
    plan = LaunchPlan(
        scenario,
        args.seed,
        robots,
        Path(args.out),
        mode=args.mode,
        period=args.period,
        comm=args.comm,
        steps=_steps(scenario, args.steps),
        secure=args.secure,
        keep_estimates=bool(args.view or args.record or args.ros2_bag),
        stack_gossip=_agents_setting(args, "stack_gossip", "ask"),
        relay=_agents_setting(args, "relay", "event"),
        keep_slots=_agents_setting(args, "keep_slots", None),
        ros2=ros2,
        **conductor_only.plan_fields(args),
    )
    check_outputs(args)
    bag = ros2_options.bag_settings(args, scenario, robots, ros2)
    conductor_only.announce(plan, console)
    where = (
        "started elsewhere"
        if plan.conductor_only
        else f"on loopback Zenoh; logs in {plan.out / 'logs'}"
    )
    console.print(
        f"launching {agents(len(plan.robots))} of {scenario.name} ({plan.mode}, seed "
        f"{plan.seed}) {where}"
    )
    console.print(security_line(plan))
    if plan.ros2 is not None:
        console.print(ros2_options.describe(plan.ros2, plan.robots))
    start_ns = time.time_ns()
    outcome = launch_recorded(plan, console, args, f"launch {scenario.name} seed {plan.seed}")
    console.print(counters_table(outcome))
    console.print(f"run took {outcome.wall_s:.1f} s")
    if bag is not None:
        ros2_options.write_recording(args, bag, plan, outcome, start_ns, console)
    entry = {"mode": plan.mode, "wall_s": outcome.wall_s, **aoi_entry(outcome, console)}
    write_outputs(plan, outcome, console, {"launch": entry})
    return 0


def run_chaos(args: argparse.Namespace, console: Console) -> int:
    if args.attack is not None:
        if args.view or args.record:
            raise UsageError("--view/--record: not with --attack (one run per attack)")
        given = (args.stack_gossip, args.relay, args.keep_slots, args.ros2_bag)
        flags = ("--stack-gossip", "--relay", "--keep-slots", "--ros2-bag")
        for flag, value in zip(flags, given, strict=True):
            if value is not None:
                raise UsageError(f"{flag}: not with --attack (each attack sets up its fleet)")
        if args.ros2:
            raise UsageError("--ros2: not with --attack (each attack sets up its fleet)")
        check_outputs(args)
        return run_attacks_command(args, console)
    scenario = load_scenario(args.scenario)
    kills, restarts = tuple(args.kill), tuple(args.restart)
    for r, _ in (*kills, *restarts):
        if r not in scenario.robot_ids:
            raise UsageError(f"--kill/--restart: unknown robot {r!r}")
    faults = Faults(args.drop, tuple(args.partition), kills, restarts, args.garbage)
    robots = list(scenario.robot_ids)
    ros2 = ros2_options.ros2_table(args, scenario, robots)
    if ros2 is not None and args.net == "netns":
        raise UsageError(
            "--ros2: not with --net netns (an agent's localhost is its own namespace's, so it "
            "cannot dial the rmw_zenohd of this machine)"
        )
    plan = LaunchPlan(
        scenario,
        args.seed,
        robots,
        Path(args.out),
        mode="realtime",
        period=args.period,
        comm=args.comm,
        faults=faults,
        steps=_steps(scenario, args.steps),
        secure=args.secure,
        net=args.net,
        keep_estimates=bool(args.view or args.record or args.ros2_bag),
        stack_gossip=_agents_setting(args, "stack_gossip", "ask"),
        relay=_agents_setting(args, "relay", "event"),
        keep_slots=_agents_setting(args, "keep_slots", None),
        ros2=ros2,
    )
    if plan.net == "netns":
        require_netns()
    check_outputs(args)
    bag = ros2_options.bag_settings(args, scenario, robots, ros2)
    where = ", on real packets between network namespaces" if plan.net == "netns" else ""
    console.print(
        f"chaos on {scenario.name}, seed {plan.seed}: {faults.describe()} "
        f"(realtime, period {plan.period:g} s{where})"
    )
    console.print(security_line(plan))
    if plan.ros2 is not None:
        console.print(ros2_options.describe(plan.ros2, plan.robots))
    start_ns = time.time_ns()
    outcome = launch_recorded(plan, console, args, f"chaos {scenario.name} seed {plan.seed}")
    for e in outcome.events:
        console.print(f"- {e}")
    console.print(f"- garbage stacks published: {outcome.garbage_sent}")
    console.print(counters_table(outcome))
    if bag is not None:
        ros2_options.write_recording(args, bag, plan, outcome, start_ns, console)
    chaos = {"events": outcome.events, "net": plan.net, "dropped": outcome.dropped}
    chaos |= aoi_entry(outcome, console)
    doc = write_outputs(plan, outcome, console, {"chaos": chaos})
    steps = plan.run_steps
    # Frames are pure functions of (seed, robot, step): the first steps of the scenario are the
    # same run, and the steps after them (48 of the paper's 60 for --steps 12) cost minutes.
    reference = run_single(
        dataclasses.replace(scenario, steps=steps),
        ["local", "distributed"],
        plan.seed,
        BeliefConfig(),
        None,
        args.comm,
    )
    t = Table(
        title=f"final step {steps}: chaos run vs the lossless in-process run of seed {plan.seed}"
    )
    t.add_column("metric")
    for m in LAUNCH_METHODS:
        t.add_column(f"{m} chaos", justify="right")
        t.add_column(f"{m} lossless", justify="right")
    for metric in ("msde", "robot_error", "object_error", "hypotheses"):
        row = [metric]
        for m in LAUNCH_METHODS:
            got = doc["methods"][m]["mean"][metric][steps - 1]
            ref = float(np.nanmean(reference.metrics[m][metric][:, steps - 1]))
            row += ["—" if got is None else f"{got:.4f}", f"{ref:.4f}"]
        t.add_row(*row)
    console.print(t)
    return 0


SECURE_HELP = (
    "a throwaway secure fleet under OUT/fleet: mutual TLS on loopback, access control, "
    "owner-signed slots (docs/deploy.md)"
)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", required=True, help="bundled scenario name or TOML file")
    p.add_argument("--seed", type=seed, default=0, help="seed of the simulated world (default 0)")
    p.add_argument(
        "--period", type=positive_float, default=0.5, help="realtime step period in s (default 0.5)"
    )
    p.add_argument("--comm", choices=COMM_MODES, help="override the scenario's communication mode")
    p.add_argument("--steps", type=positive_int, default=None, help="run only the first N steps")
    p.add_argument("--secure", action="store_true", help=SECURE_HELP)
    p.add_argument(
        "--stack-gossip",
        choices=STACK_GOSSIP,
        default=None,
        help='what stacks carry: "ask" (default) what peers lack, and a robot asks a neighbour '
        'for the slots of robots out of its range; "delta" without asks; "full" every held '
        "slot (docs/wire.md)",
    )
    p.add_argument(
        "--relay",
        choices=RELAYS,
        default=None,
        help='when a slot a neighbour asked for goes: "event" (default) on arrival, "tick" with '
        "the next gossip tick (docs/wire.md)",
    )
    p.add_argument(
        "--keep-slots",
        type=slot_count,
        default=None,
        help="the slots each robot keeps, its own included (2 to 64, the default): beyond, a "
        "fresher robot's slot takes the stalest's place (docs/distributed.md)",
    )
    add_view_options(p)
    add_force(p)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("launch", help="run a scenario as one process per robot over Zenoh")
    _common(p)
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    p.add_argument("--robots", default="all", help="'all' or comma-separated robot ids")
    p.add_argument("--out", default="out/launch", help="folder for results, logs, journals")
    conductor_only.add_options(p)
    ros2_options.add_options(p)
    p.set_defaults(run=run_launch)

    c = sub.add_parser("chaos", help="a realtime launch with loss, partitions, kills and garbage")
    _common(c)
    c.add_argument("--drop", type=probability, default=0.0, help="probability of losing a stack")
    c.add_argument(
        "--partition", type=partition, action="append", default=[], metavar="IDS:FROM-TO"
    )
    c.add_argument("--kill", type=robot_at, action="append", default=[], metavar="ID@STEP")
    c.add_argument("--restart", type=robot_at, action="append", default=[], metavar="ID@STEP")
    c.add_argument(
        "--garbage", type=float, default=0.0, metavar="RATE", help="garbage stacks per second"
    )
    c.add_argument(
        "--attack",
        type=attack_list,
        default=None,
        metavar="LIST",
        help=f"attack the fleet instead: {','.join(ATTACKS)} or all (docs/deploy.md)",
    )
    c.add_argument("--out", default="out/chaos", help="folder for results, logs, journals")
    c.add_argument(
        "--net",
        choices=("loopback", "netns"),
        default="loopback",
        help="netns (root): each agent in its own network namespace, loss, partitions and "
        "range applied to real packets with nftables (docs/deploy.md)",
    )
    ros2_options.add_options(c)
    c.set_defaults(run=run_chaos)
