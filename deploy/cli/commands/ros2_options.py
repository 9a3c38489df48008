"""`--ros2` and `--ros2-bag` of `semfleet launch` and `semfleet demo` (docs/ros2.md). With `--ros2`
every agent publishes its belief as ROS 2 topics through the machine's ``rmw_zenohd``: the
options become the ``[ros2]`` table written into each agent config the launcher generates,
checked here as the agents will read it. `--ros2-bag DIR` records the same messages of the run
as a rosbag2 / MCAP folder (:mod:`deploy.launch.ros2_bag`)."""

from __future__ import annotations

import argparse
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rich.console import Console

from agents.ros2.bridge import ROS2_ROUTER, Ros2Settings
from agents.ros2.wire import DISTROS
from agents.transport.zenoh_transport import ZenohSettings
from deploy.base.errors import UsageError
from deploy.cli.args import endpoint_type
from deploy.cli.outputs import new_folder
from deploy.launch import LaunchOutcome, LaunchPlan
from deploy.launch.ros2_bag import BAG_METADATA, write_bag
from deploy.operator.ros2_config import MAX_DOMAIN_ID, check_table, simulation_table
from sim.scenario import Scenario


def domain_id(text: str) -> int:
    if not (text.isascii() and text.isdigit() and int(text) <= MAX_DOMAIN_ID):
        raise argparse.ArgumentTypeError(
            f"expected a ROS_DOMAIN_ID in 0..{MAX_DOMAIN_ID}, got {text!r}"
        )
    return int(text)


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--ros2",
        action="store_true",
        help="every agent publishes its belief as ROS 2 topics (Path, Detection3DArray, markers, "
        "odometry, pose; no /tf: the frames are simulated) through rmw_zenohd (docs/ros2.md)",
    )
    p.add_argument(
        "--ros2-domain",
        type=domain_id,
        default=None,
        metavar="ID",
        help="with --ros2: the ROS_DOMAIN_ID (default 0)",
    )
    p.add_argument(
        "--ros2-distro",
        choices=DISTROS,
        default=None,
        help="with --ros2 or --ros2-bag: default jazzy",
    )
    p.add_argument(
        "--ros2-router",
        type=endpoint_type("--ros2-router"),
        default=None,
        metavar="ENDPOINT",
        help=f"with --ros2: the rmw_zenohd the agents dial, on this host (default {ROS2_ROUTER})",
    )
    p.add_argument(
        "--ros2-bag",
        default=None,
        metavar="DIR",
        help="record every robot's ROS 2 messages (as --ros2 publishes them) in a rosbag2 "
        "folder of one MCAP file, for ros2 bag play and Foxglove (docs/ros2.md)",
    )


def ros2_table(
    args: argparse.Namespace, scenario: Scenario, robots: list[str]
) -> dict[str, Any] | None:
    """The ``[ros2]`` table of every agent config, None without ``--ros2``; a usage error for a
    ``--ros2-*`` option without it, a router off this machine, or a robot id that makes no
    ROS 2 name."""
    if not args.ros2:
        for name, value in (
            ("--ros2-domain", args.ros2_domain),
            ("--ros2-router", args.ros2_router),
        ):
            if value is not None:
                raise UsageError(f"{name}: only with --ros2")
        if args.ros2_distro is not None and args.ros2_bag is None:
            raise UsageError("--ros2-distro: only with --ros2 or --ros2-bag")
        return None
    router = args.ros2_router or ROS2_ROUTER
    if ZenohSettings(connect=(router,)).off_loopback():
        raise UsageError(
            f"--ros2-router: {router} is not on this machine (the agents' ROS 2 session has no "
            "TLS: run rmw_zenohd where the agents run)"
        )
    table = simulation_table(
        0 if args.ros2_domain is None else args.ros2_domain, args.ros2_distro or "jazzy", router
    )
    for r in robots:
        check_table(table, "--ros2", r, scenario.robot_model().num_classes)
    return table


def bag_settings(
    args: argparse.Namespace,
    scenario: Scenario,
    robots: list[str],
    table: Mapping[str, Any] | None,
) -> dict[str, Ros2Settings] | None:
    """With ``--ros2-bag``: each robot's ROS 2 settings for the recording (``table``, the agents'
    own, or that of ``--ros2`` with its defaults), the bag folder checked as a new output."""
    if args.ros2_bag is None:
        return None
    folder = new_folder(Path(args.ros2_bag), "--ros2-bag", args.force)
    strangers = [p.name for p in folder.glob("*") if p.name != BAG_METADATA and p.suffix != ".mcap"]
    if strangers:
        raise UsageError(f"--ros2-bag {folder}: holds {strangers[0]!r}, not a bag's file")
    if table is None:
        table = simulation_table(0, args.ros2_distro or "jazzy", ROS2_ROUTER)
    num_classes = scenario.robot_model().num_classes
    return {r: check_table(table, "--ros2-bag", r, num_classes) for r in robots}


def write_recording(
    args: argparse.Namespace,
    settings: Mapping[str, Ros2Settings],
    plan: LaunchPlan,
    outcome: LaunchOutcome,
    start_ns: int,
    console: Console,
) -> None:
    """The run as a rosbag2 folder (:func:`deploy.launch.ros2_bag.write_bag`), written whole or
    not at all: in a folder of its own next to it, moved into place when complete (a
    ``--force`` replaces an earlier bag there)."""
    folder = Path(args.ros2_bag)
    part = folder.parent / f".{folder.name}.part"
    shutil.rmtree(part, ignore_errors=True)  # a stopped earlier write's
    counts = write_bag(
        part / folder.name,
        settings,
        plan.scenario.robot_model().num_classes,
        outcome.collected.estimates,
        start_ns,
        plan.period,
    )
    if folder.is_dir():
        for old in (*folder.glob("*.mcap"), folder / BAG_METADATA):
            old.unlink(missing_ok=True)
        folder.rmdir()
    (part / folder.name).rename(folder)
    part.rmdir()
    console.print(
        f"wrote the ROS 2 bag {folder} (MCAP): {len(counts)} topics, {sum(counts.values())} "
        f"messages (play it with: ros2 bag play {folder})"
    )


def describe(table: Mapping[str, Any], robots: list[str]) -> str:
    """One line: where the ROS 2 topics go."""
    return (
        f"ROS 2 ({table['distro']}, domain {table['domain_id']}): /<robot>/semfleet/{{path,"
        f"detections,objects,odometry,pose}} for {', '.join(robots)}, through rmw_zenohd at "
        f"{table['connect'][0]} (the agents wait for it)"
    )
