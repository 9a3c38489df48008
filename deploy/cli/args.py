"""Argument types shared by the ``semfleet`` commands: one clear sentence for a bad value."""

from __future__ import annotations

import argparse
import ipaddress
import re
from collections.abc import Callable

from deploy.base.errors import UsageError
from estimator.models import GLOBAL_IDS, ID_KINDS
from protocol.codec import Limits
from sim.confirmable import ConfirmRule
from sim.loader import MAX_CLASSES
from sim.sensors import Detector

MAX_SEED = 2**63 - 1
MAX_SLOTS = Limits().max_slots  # a stack's most slots (docs/wire.md, "Limits")


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def positive_int(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be a positive integer")
    return value


def slot_count(text: str) -> int:
    """``--keep-slots``: the slots a robot keeps, its own included, 2 to a stack's 64."""
    value = _integer(text)
    if not 2 <= value <= MAX_SLOTS:
        raise argparse.ArgumentTypeError(f"{text}: a robot keeps 2 to {MAX_SLOTS} slots")
    return value


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (v > 0 and v < 1e6):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def class_count(text: str) -> int:
    value = _integer(text)
    if not 2 <= value <= MAX_CLASSES:
        raise argparse.ArgumentTypeError(f"{text}: need 2 to {MAX_CLASSES} classes")
    return value


def seed(text: str) -> int:
    value = _integer(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text}: seeds are non-negative integers below 2**63")
    return value


_DNS_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def host_name(text: str) -> str:
    """A name a certificate can carry: an IPv4 or IPv6 address, or a DNS name (labels of
    letters, digits and inner hyphens, 253 characters at most)."""
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        pass
    labels = text.rstrip(".").split(".")
    if not (len(text) <= 253 and all(_DNS_LABEL.fullmatch(label) for label in labels)):
        raise argparse.ArgumentTypeError(f"{text!r} is neither an IP address nor a DNS name")
    return text


_IP_PROTOCOLS = {"tcp", "udp", "tls", "quic", "ws"}
_OTHER_PROTOCOLS = {"unixsock-stream", "unixpipe", "serial", "vsock"}
_ENDPOINT = re.compile(r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<address>[^?#]+)(?P<rest>[?#].*)?$")


def zenoh_endpoint(text: str, option: str) -> str:
    """A Zenoh endpoint ``PROTOCOL/ADDRESS`` (e.g. ``tcp/127.0.0.1:7447``); IP protocols need a
    ``host:port`` with a port in 1..65535."""
    m = _ENDPOINT.fullmatch(text)
    if m is None or m["proto"] not in _IP_PROTOCOLS | _OTHER_PROTOCOLS:
        known = ", ".join(sorted(_IP_PROTOCOLS | _OTHER_PROTOCOLS))
        raise UsageError(
            f"{option} {text!r}: expected PROTOCOL/ADDRESS such as tcp/127.0.0.1:7447 "
            f"(protocols: {known})"
        )
    if m["proto"] in _IP_PROTOCOLS:
        host, colon, port = m["address"].rpartition(":")
        if not (colon and host and port.isdigit() and 1 <= int(port) <= 65535):
            raise UsageError(
                f"{option} {text!r}: expected HOST:PORT with a port in 1..65535 after {m['proto']}/"
            )
    return text


def fraction(text: str) -> float:
    """A number in [0, 1)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), got {text!r}") from None
    if not 0.0 <= v < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), got {text!r}")
    return v


def add_detector_arguments(p: argparse.ArgumentParser) -> None:
    """``--ids``, ``--clutter``, ``--miss``, ``--confirmable``: what the simulated detector
    delivers (``sim.sensors.Detector``; the defaults give the frames of before, to the bit)."""
    p.add_argument(
        "--ids",
        choices=ID_KINDS,
        default=GLOBAL_IDS,
        help="the frames' detection ids: global object ids (default), a robot-local tracker's, "
        "or none (then the robot associates them with its map)",
    )
    p.add_argument(
        "--clutter",
        type=fraction,
        default=0.0,
        metavar="R",
        help="false detections per true detection (per-frame Poisson mean R × true ones)",
    )
    p.add_argument(
        "--miss", type=fraction, default=0.0, metavar="P", help="probability of missing an object"
    )
    p.add_argument(
        "--confirmable",
        action="store_true",
        help="with global ids: only the detections of objects each robot's association would "
        "confirm (seen 3 times; the reference that separates association errors from what "
        "confirmation gives up)",
    )


def detector_from_args(args: argparse.Namespace) -> Detector:
    if not args.confirmable:
        return Detector(args.ids, args.clutter, args.miss)
    if args.ids != GLOBAL_IDS:
        raise UsageError(
            f"--confirmable needs --ids {GLOBAL_IDS} (with --ids {args.ids} each robot's "
            "association confirms objects itself)"
        )
    from estimator.association import AssociationConfig  # here: an agent's CLI never needs it

    a = AssociationConfig()
    rule = ConfirmRule(a.confirm, a.drop_after, a.forget_after)
    return Detector(args.ids, args.clutter, args.miss, rule)


def endpoint_type(option: str) -> Callable[[str], str]:
    """:func:`zenoh_endpoint` as an argparse ``type``: a bad endpoint is argparse's one-line
    error (exit 2). A ``UsageError`` raised while the arguments are parsed escaped the launcher
    as a traceback."""

    def parse(text: str) -> str:
        try:
            return zenoh_endpoint(text, option)
        except UsageError as exc:
            raise argparse.ArgumentTypeError(str(exc).removeprefix(f"{option} ")) from None

    return parse
