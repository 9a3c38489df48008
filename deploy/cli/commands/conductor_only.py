"""`semfleet launch --conductor-only`: the options of a launch whose agents run on other machines
(docs/deploy.md, "A lab test of a real network"), plain or with a throwaway secure fleet."""

from __future__ import annotations

import argparse
from typing import Any

from rich.console import Console

from deploy.base.errors import UsageError
from deploy.cli.args import endpoint_type, host_name, positive_float
from deploy.launch import LaunchPlan


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--conductor-only",
        action="store_true",
        help="drive the world for agents started on other machines (docs/deploy.md)",
    )
    p.add_argument(
        "--conductor-listen",
        type=endpoint_type("--conductor-listen"),
        help="with --conductor-only: where the conductor listens (default tcp/0.0.0.0:7447, "
        "tls/0.0.0.0:7447 with --secure)",
    )
    p.add_argument(
        "--advertise",
        type=endpoint_type("--advertise"),
        help="with --conductor-only: the endpoint the agents dial, e.g. tcp/192.168.1.10:7447",
    )
    p.add_argument(
        "--agent-host",
        action="append",
        default=[],
        type=host_name,
        metavar="NAME",
        help="with --conductor-only --secure: a DNS name or address of an agent's machine, "
        "written into every certificate (repeatable; docs/deploy.md)",
    )
    p.add_argument(
        "--wait-agents",
        type=positive_float,
        default=90.0,
        help="seconds to wait for every agent to come up (default 90)",
    )


def plan_fields(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`LaunchPlan` fields these options set; a usage error for one given without
    the option it belongs with."""
    for name, value in (
        ("--advertise", args.advertise),
        ("--conductor-listen", args.conductor_listen),
        ("--agent-host", args.agent_host),
    ):
        if value and not args.conductor_only:
            raise UsageError(f"{name}: only with --conductor-only")
    if args.agent_host and not args.secure:
        raise UsageError("--agent-host: only with --secure (it names the certificates' hosts)")
    fields: dict[str, Any] = {"wait_agents": args.wait_agents}
    if args.conductor_only:
        fields |= {
            "conductor_only": True,
            "conductor_listen": _listen(args),
            "conductor_advertise": _advertise(args),
            "agent_hosts": tuple(args.agent_host),
        }
    return fields


def announce(plan: LaunchPlan, console: Console) -> None:
    """What to do on the other machines, before the launch waits for their agents."""
    if not plan.conductor_only:
        return
    waiting = f"waiting up to {plan.wait_agents:g} s for {', '.join(plan.robots)}"
    if plan.secure:
        console.print(
            f"conductor only, secure: listening on {plan.conductor_listen}; copy "
            f"{plan.out / 'fleet' / 'robots'}/<robot>/ onto each robot's machine and start its "
            f"agent there (semfleet agent --robot <robot> --config agent.toml, in that folder; "
            f"its key files are secret); {waiting}"
        )
    else:
        console.print(
            f"conductor only: listening on {plan.conductor_listen}; start each agent on its "
            f"machine with {plan.out / 'agents'}/<robot>.toml and model.toml copied there "
            f"(semfleet agent --robot <robot> --config <robot>.toml); {waiting}"
        )


def _listen(args: argparse.Namespace) -> str:
    """Where the conductor listens (TLS with --secure)."""
    if args.conductor_listen is not None:
        return str(args.conductor_listen)
    return f"{'tls' if args.secure else 'tcp'}/0.0.0.0:7447"


def _advertise(args: argparse.Namespace) -> str:
    """The endpoint the agents dial."""
    if args.advertise is not None:
        return str(args.advertise)
    listen = _listen(args)
    if "0.0.0.0" in listen or "[::]" in listen:
        raise UsageError("--conductor-only: --advertise ENDPOINT, the address agents dial")
    return listen
