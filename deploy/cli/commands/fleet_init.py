"""`semfleet fleet init`: parse, build a :class:`deploy.operator.fleet_init.FleetSpec`, write,
report."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console

from deploy.base.errors import UsageError
from deploy.cli.args import host_name, zenoh_endpoint
from deploy.cli.commands.scenario import model_text
from deploy.operator.fleet_init import (
    DEFAULT_PORT,
    FleetInitError,
    FleetSpec,
    init_fleet,
    loopback_spec,
)
from sim.loader import load_scenario
from sim.robot_model import parse_robot_model
from sim.scenario import ScenarioError


def run_init(args: argparse.Namespace, console: Console) -> int:
    robots = [r.strip() for r in args.robots.split(",") if r.strip()]
    if not robots:
        raise UsageError("--robots: expected robot ids, e.g. r1,r2,r3")
    model, starts = _model_and_starts(args, robots)
    try:
        spec = loopback_spec(args.fleet, robots, args.operator, starts, model, args.base_port)
        if args.listen:
            spec = _with_listen(spec, dict(_assignment(t, "--listen") for t in args.listen))
        if args.host or args.days != spec.days:
            spec = _replace(spec, hosts=(*spec.hosts, *args.host), days=args.days)
        if args.router:
            routers = dict(_assignment(t, "--router") for t in args.router)
            for endpoint in routers.values():
                zenoh_endpoint(endpoint, "--router")
            spec = _replace(spec, routers=routers)
        if args.connect:
            spec = _with_connect(spec, dict(_assignment(t, "--connect") for t in args.connect))
        folders = init_fleet(spec, Path(args.output))
    except FleetInitError as exc:
        raise UsageError(str(exc)) from None
    out = Path(args.output)
    extra = f", {len(spec.routers)} routers" if spec.routers else ""
    console.print(
        f"wrote fleet {spec.fleet} to {out}: CA, roster, {len(robots)} robots, operator{extra}"
    )
    for name, folder in folders.items():
        console.print(f"  {name}: {folder}")
    console.print(f"secret: {out}/ca/ca.key (keep offline), every tls.key and signing.key")
    return 0


def _model_and_starts(
    args: argparse.Namespace, robots: list[str]
) -> tuple[str, dict[str, tuple[float, float, float]]]:
    if args.scenario is not None:
        if args.model is not None or args.start:
            raise UsageError("--scenario gives the model and start poses: no --model or --start")
        scenario = load_scenario(args.scenario, args.variant)
        unknown = [r for r in robots if r not in scenario.robot_ids]
        if unknown:
            known = ", ".join(scenario.robot_ids)
            raise UsageError(f"--robots: {unknown[0]} is not a robot of {scenario.name} ({known})")
        poses = {r: scenario.robot(r).start for r in robots}
        return model_text(scenario), {
            r: (float(x), float(y), float(t)) for r, (x, y, t) in poses.items()
        }
    if args.model is None:
        raise UsageError(
            "fleet init needs the robots' model and start poses: --scenario NAME, or "
            "--model FILE with --start ROBOT=X,Y,THETA for every robot"
        )
    path = Path(args.model)
    try:
        text = path.read_text(encoding="utf-8")
        parse_robot_model(text, str(path))
    except OSError as exc:
        raise UsageError(f"--model {path}: {exc.strerror}") from None
    except ScenarioError as exc:
        raise UsageError(f"--model {exc}") from None
    starts = {}
    for item in args.start:
        robot, value = _assignment(item, "--start")
        try:
            x, y, theta = (float(v) for v in value.split(","))
        except ValueError:
            raise UsageError(f"--start {item!r}: expected ROBOT=X,Y,THETA") from None
        starts[robot] = (x, y, theta)
    missing = [r for r in robots if r not in starts]
    if missing:
        raise UsageError(f"--start: no start pose for {', '.join(missing)}")
    return text, starts


def _assignment(text: str, option: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise UsageError(f"{option} {text!r}: expected ROBOT=VALUE")
    return name.strip(), value.strip()


def _with_listen(spec: FleetSpec, listen: dict[str, str]) -> FleetSpec:
    """Listen endpoints given for every robot; each robot dials every robot before it."""
    missing = [r for r in spec.robots if r not in listen]
    unknown = [r for r in listen if r not in spec.robots]
    if missing or unknown:
        raise UsageError(
            f"--listen: give one endpoint per robot (missing: {', '.join(missing) or '-'}; "
            f"unknown: {', '.join(unknown) or '-'})"
        )
    for endpoint in listen.values():
        zenoh_endpoint(endpoint, "--listen")
    robots = spec.robots
    connect = {r: tuple(listen[q] for q in robots[:i]) for i, r in enumerate(robots)}
    return _replace(spec, listen=listen, connect=connect)


def _with_connect(spec: FleetSpec, given: dict[str, str]) -> FleetSpec:
    """``--connect ROBOT=E1,E2``: what those robots dial instead of the robots before them."""
    unknown = [r for r in given if r not in spec.robots]
    if unknown:
        raise UsageError(f"--connect: {unknown[0]} is not one of --robots")
    connect = dict(spec.connect)
    for robot, value in given.items():
        endpoints = tuple(e.strip() for e in value.split(",") if e.strip())
        connect[robot] = tuple(zenoh_endpoint(e, "--connect") for e in endpoints)
    return _replace(spec, connect=connect)


def _replace(spec: FleetSpec, **changes: Any) -> FleetSpec:
    fields = {name: getattr(spec, name) for name in FleetSpec.__dataclass_fields__}
    fields.update(changes)
    return FleetSpec(**fields)


def add_init_parser(actions: Any) -> None:
    p = actions.add_parser(
        "init",
        help="make a secure fleet: CA, certificates, signing keys, roster, agent and Zenoh files",
    )
    p.add_argument("--fleet", required=True, help="fleet name (the key prefix semfleet/<fleet>)")
    p.add_argument("--robots", required=True, help="robot ids, comma-separated: r1,r2,r3")
    p.add_argument("--operator", default="operator", help="the operator's name (default operator)")
    p.add_argument("-o", "--output", required=True, help="a new (or empty) folder")
    p.add_argument("--scenario", help="take the robot model and start poses from this scenario")
    p.add_argument("--variant", action="append", default=[], help="scenario variant (repeatable)")
    p.add_argument("--model", help="a robot model file (semfleet scenario model)")
    p.add_argument(
        "--start",
        action="append",
        default=[],
        metavar="ROBOT=X,Y,THETA",
        help="a robot's start pose in the fleet frame (repeatable; with --model)",
    )
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ROBOT=ENDPOINT",
        help="a robot's listen endpoint, e.g. r1=tls/10.0.0.1:7447 (repeatable; default: "
        "tls/127.0.0.1 from --base-port); each robot dials every robot listed before it",
    )
    p.add_argument(
        "--base-port",
        type=int,
        default=DEFAULT_PORT,
        help=f"loopback ports base-port, base-port+1, … (default {DEFAULT_PORT})",
    )
    p.add_argument(
        "--host",
        action="append",
        default=[],
        type=host_name,
        help="a DNS name or address every certificate names (repeatable)",
    )
    p.add_argument(
        "--router",
        action="append",
        default=[],
        metavar="NAME=ENDPOINT",
        help="a Zenoh router of the fleet and its listen endpoint (repeatable; each router dials "
        "the routers before it; `semfleet router`, docs/deploy.md)",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ROBOT=ENDPOINT,…",
        help="what a robot dials (repeatable; default: every robot listed before it), e.g. its "
        "site's router and robots",
    )
    p.add_argument("--days", type=int, default=365, help="certificate validity (default 365)")
    p.set_defaults(run=run_init)
