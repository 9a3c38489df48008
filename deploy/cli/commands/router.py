"""`semfleet router`: a Zenoh session in router mode (no zenohd binary needed), for links between
sites or through infrastructure (docs/deploy.md, "Routers"). Peers never forward for each other
(Zenoh ≥ 1.9); a router does. It runs until SIGINT or SIGTERM and closes its session on the way
out. With a JSON5 file from `semfleet fleet init --router NAME=ENDPOINT` it has the fleet's mutual
TLS and access control; an endpoint off loopback without mutual TLS needs ``--insecure``."""

from __future__ import annotations

import argparse
import asyncio
import signal
from pathlib import Path
from typing import Any

from rich.console import Console

from agents.transport.zenoh_transport import ZenohConfigError, ZenohSettings, ZenohTransport
from deploy.base.errors import UsageError
from deploy.cli.args import zenoh_endpoint


def router_settings(args: argparse.Namespace) -> ZenohSettings:
    config_file = None
    if args.config is not None:
        config_file = Path(args.config)
        if not config_file.is_file():
            raise UsageError(f"--config {config_file}: no such file")
    settings = ZenohSettings(
        listen=tuple(zenoh_endpoint(e, "--listen") for e in args.listen),
        connect=tuple(zenoh_endpoint(e, "--connect") for e in args.connect),
        config_file=config_file,
        mode="router",
    )
    try:
        exposed, secure = settings.off_loopback(), settings.mutual_tls()
        if not settings.document().get("listen", {}).get("endpoints"):
            raise UsageError("a router needs a listen endpoint: --listen or the --config file")
    except ZenohConfigError as exc:
        raise UsageError(str(exc)) from None
    if exposed and not secure and not args.insecure:
        raise UsageError(
            f"endpoints {', '.join(exposed)} are not on loopback and the router has no mutual "
            "TLS: use a --config from `semfleet fleet init --router`, or --insecure"
        )
    return settings


async def serve(settings: ZenohSettings, console: Console) -> None:
    """Until SIGINT or SIGTERM, the router's normal stop: it closes its session and says so."""
    transport = ZenohTransport(settings)
    stopped_by: list[str] = []
    stop = asyncio.Event()

    def on_signal(sig: signal.Signals) -> None:
        stopped_by.append(sig.name)
        stop.set()

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, on_signal, sig)
    await transport.open()
    endpoints = settings.endpoints()[0]
    console.print(f"router up, listening on {', '.join(endpoints)} (Ctrl-C or SIGTERM stops it)")
    try:
        await stop.wait()
    finally:
        await transport.close()
    console.print(f"router stopped ({stopped_by[0]}), its session closed")


def run(args: argparse.Namespace, console: Console) -> int:
    asyncio.run(serve(router_settings(args), console))
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("router", help="a Zenoh router for links between sites (no zenohd needed)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    p.add_argument(
        "--config", help="a Zenoh JSON5 file (e.g. routers/NAME/zenoh.json5 of fleet init)"
    )
    p.add_argument(
        "--insecure", action="store_true", help="allow endpoints off loopback without TLS"
    )
    p.set_defaults(run=run)
