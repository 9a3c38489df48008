"""`semfleet fleet init`: the files of a secure fleet (docs/deploy.md, "A secure fleet").

One call makes a fleet CA, a TLS certificate and key per robot (CN = robot id) and for the
operator, a per-robot Ed25519 slot-signing key, the roster (robot id → signing public key), and
per robot an agent config and a Zenoh JSON5 file with mutual TLS on every endpoint and access
control. Everything a robot needs is in its own folder, with paths relative to that folder, so
the folder is copied onto the robot as it is.

Access control is enforced by every receiving session on what its direct neighbours send (Zenoh
peers never forward for each other), per the certificate common name of the link:

- a robot may put only on its own ``stack``, ``estimate``, ``frames`` and ``ctl/need`` keys and
  hold only its own ``alive`` token (``frames/<r>`` is the robot's own perception, which runs with
  the robot's identity);
- only the operator may put on ``ctl/**`` (step orders, stop, status) and ``sim/**``;
- every certified member may declare subscribers, tokens and queries under the fleet's prefix;
- everything else is denied (``default_permission: deny``).
"""

from __future__ import annotations

import base64
import dataclasses
import datetime
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tomli_w
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import NameOID

from deploy.operator.access_control import access_control
from deploy.operator.certificates import ca_certificate, cert_pem, key_pem, member_certificate
from protocol.validate import valid_id

# Key files are written owner-read/write only; certificates and the roster are public.
SECRET_MODE = 0o600
PUBLIC_MODE = 0o644
DEFAULT_PORT = 7447


class FleetInitError(ValueError):
    """A bad ``fleet init`` request (names the option and why)."""


@dataclass(frozen=True, slots=True)
class FleetSpec:
    """What ``fleet init`` makes: the fleet, its robots and operator, each robot's listen
    endpoint and the endpoints it dials, its start pose, and the robot model every agent uses
    (a TOML text, see ``semfleet scenario model``). ``hosts`` are the DNS names and IP addresses
    written into every certificate's subject alternative names."""

    fleet: str
    robots: tuple[str, ...]
    operator: str
    listen: Mapping[str, str]
    connect: Mapping[str, tuple[str, ...]]
    starts: Mapping[str, tuple[float, float, float]]
    model_toml: str
    hosts: tuple[str, ...] = ("localhost", "127.0.0.1")
    days: int = 365
    # A simulation's conductor is every robot's perception: it may also put on frames/<robot>.
    # Never for a real fleet (fleet init), where frames come from each robot's own identity.
    simulator: bool = False
    # Zenoh routers (name → listen endpoint) for links between sites: trusted infrastructure that
    # relays every member's messages (slots stay owner-signed end to end). Each router dials the
    # routers before it; robots dial what ``connect`` says (their site's router, their site's
    # robots): a Zenoh router forwards between routers and for clients, not between its peers.
    routers: Mapping[str, str] = dataclasses.field(default_factory=dict)
    # Zenoh's gossip scouting: members learn each other's endpoints from the peers they dial.
    # Off for a real fleet (Zenoh links then match the radio links ``connect`` describes); on for
    # a lab test whose agents, on machines unknown in advance, dial only the conductor.
    gossip: bool = False

    def __post_init__(self) -> None:
        names = (*self.robots, self.operator, *self.routers)
        bad = [n for n in names if not valid_id(n)]
        if bad:
            raise FleetInitError(f"invalid id {bad[0]!r} (1–32 of A–Z a–z 0–9 _ -)")
        if len(set(names)) != len(names):
            raise FleetInitError("robot and operator names must be distinct")
        if not valid_id(self.fleet):
            raise FleetInitError(f"invalid fleet name {self.fleet!r}")
        missing = [r for r in self.robots if r not in self.starts or r not in self.listen]
        if missing:
            raise FleetInitError(f"no start pose or listen endpoint for {missing[0]}")
        for r, endpoint in (*self.listen.items(), *self.routers.items()):
            if not endpoint.startswith("tls/"):
                raise FleetInitError(f"listen endpoint of {r} must be tls/HOST:PORT: {endpoint}")
        if not 1 <= self.days <= 3650:
            raise FleetInitError(f"--days {self.days}: must be in 1..3650")


def loopback_spec(
    fleet: str,
    robots: Sequence[str],
    operator: str,
    starts: Mapping[str, tuple[float, float, float]],
    model_toml: str,
    base_port: int = DEFAULT_PORT,
) -> FleetSpec:
    """A fleet on one machine: robot i listens on ``tls/127.0.0.1:base_port + i`` and dials every
    robot before it (a full mesh)."""
    listen = {r: f"tls/127.0.0.1:{base_port + i}" for i, r in enumerate(robots)}
    connect = {r: tuple(listen[q] for q in robots[:i]) for i, r in enumerate(robots)}
    return FleetSpec(fleet, tuple(robots), operator, listen, connect, starts, model_toml)


def init_fleet(spec: FleetSpec, out: Path) -> dict[str, Path]:
    """Write the fleet's files under ``out`` (which must not exist or be empty); returns the
    folder of every robot and of the operator (key ``spec.operator``)."""
    if out.exists() and any(out.iterdir()):
        raise FleetInitError(
            f"{out}: exists and is not empty (a fleet's keys are never overwritten)"
        )
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"semfleet {spec.fleet} CA")])
    ca_cert = ca_certificate(ca_key, ca_name, now, spec.days)
    _write(out / "ca" / "ca.pem", cert_pem(ca_cert), PUBLIC_MODE)
    _write(out / "ca" / "ca.key", key_pem(ca_key), SECRET_MODE)
    signing = {r: ed25519.Ed25519PrivateKey.generate() for r in spec.robots}
    roster = roster_toml(spec.fleet, {r: k.public_key() for r, k in signing.items()})
    _write(out / "roster.toml", roster, PUBLIC_MODE)
    folders: dict[str, Path] = {}
    for name in (*spec.robots, spec.operator, *spec.routers):
        if name == spec.operator:
            folder = out / "operator"
        elif name in spec.routers:
            folder = out / "routers" / name
        else:
            folder = out / "robots" / name
        key = ec.generate_private_key(ec.SECP256R1())
        hosts = _hosts(spec.hosts, spec.listen.get(name, spec.routers.get(name)))
        cert = member_certificate(key, name, ca_key, ca_name, hosts, now, spec.days)
        _write(folder / "ca.pem", cert_pem(ca_cert), PUBLIC_MODE)
        _write(folder / "tls.pem", cert_pem(cert), PUBLIC_MODE)
        _write(folder / "tls.key", key_pem(key), SECRET_MODE)
        _write(folder / "roster.toml", roster, PUBLIC_MODE)
        if name in spec.routers:  # each router dials the routers listed before it
            before = list(spec.routers)[: list(spec.routers).index(name)]
            dial = tuple(spec.routers[r] for r in before)
            zenoh_doc = zenoh_config(spec, spec.routers[name], dial, "router")
        else:
            zenoh_doc = zenoh_config(spec, spec.listen.get(name), spec.connect.get(name, ()))
        _write(folder / "zenoh.json5", _json5(zenoh_doc, name, spec.fleet), PUBLIC_MODE)
        if name in signing:
            _write(folder / "signing.key", key_pem(signing[name]), SECRET_MODE)
            _write(folder / "model.toml", spec.model_toml, PUBLIC_MODE)
            _write(folder / "agent.toml", _agent_toml(spec, name), PUBLIC_MODE)
        folders[name] = folder
    return folders


def roster_toml(fleet: str, keys: Mapping[str, ed25519.Ed25519PublicKey]) -> str:
    """The roster: fleet name and every robot's Ed25519 slot-signing public key (base64)."""
    robots = {
        r: {"signing_key": base64.b64encode(k.public_bytes_raw()).decode("ascii")}
        for r, k in sorted(keys.items())
    }
    return tomli_w.dumps({"fleet": fleet, "robots": robots})


def zenoh_config(
    spec: FleetSpec, listen: str | None, connect: Sequence[str], mode: str = "peer"
) -> dict[str, Any]:
    """The Zenoh configuration of one member (paths relative to its folder)."""
    tls = {
        "root_ca_certificate": "ca.pem",
        "listen_certificate": "tls.pem",
        "listen_private_key": "tls.key",
        "connect_certificate": "tls.pem",
        "connect_private_key": "tls.key",
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }
    doc: dict[str, Any] = {
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": spec.gossip}},
        "transport": {"link": {"tls": tls}},
        "access_control": access_control(
            spec.fleet,
            spec.robots,
            spec.operator,
            listen is None,
            spec.simulator,
            list(spec.routers),
        ),
    }
    if listen is not None:  # a robot or router; the operator's commands choose mode and endpoints
        doc["mode"] = mode
        doc["listen"] = {"endpoints": [listen]}
        doc["connect"] = {"endpoints": list(connect)}
    return doc


def _hosts(base: Sequence[str], listen: str | None) -> tuple[str, ...]:
    """Subject alternative names of a member: ``base`` and the host it listens on (unless a
    wildcard address), so that peers dialling it can verify its name."""
    hosts = list(base)
    if listen is not None:
        host = endpoint_host(listen)
        if host not in ("0.0.0.0", "::", "") and host not in hosts:
            hosts.append(host)
    return tuple(hosts)


def endpoint_host(endpoint: str) -> str:
    """The host of a Zenoh endpoint ``proto/host:port[?…][#…]`` (IPv6 without its brackets)."""
    locator = endpoint.split("/", 1)[-1].split("?", 1)[0].split("#", 1)[0]
    return locator.rsplit(":", 1)[0].strip("[]")


def _agent_toml(spec: FleetSpec, robot: str) -> str:
    doc = {
        "agent": {
            "fleet": spec.fleet,
            "model": "model.toml",
            "start": list(spec.starts[robot]),
            "roster": list(spec.robots),
            "journal": f"{robot}.journal",
        },
        "zenoh": {"config_file": "zenoh.json5"},
        "security": {"signing_key": "signing.key", "roster": "roster.toml"},
    }
    header = (
        f"# Agent {robot} of fleet {spec.fleet}; run from this folder:\n"
        f"#   semfleet agent --robot {robot} --config agent.toml\n"
        "# Endpoints, TLS and access control are in zenoh.json5 (docs/deploy.md).\n"
    )
    return header + tomli_w.dumps(doc)


def _json5(doc: dict[str, Any], name: str, fleet: str) -> str:
    header = (
        f"// Zenoh configuration of {name} in fleet {fleet}, written by `semfleet fleet init`.\n"
        "// Mutual TLS on every endpoint; access control: docs/deploy.md. Relative paths are\n"
        "// resolved against this file's folder by semfleet (not by Zenoh itself).\n"
    )
    return header + json.dumps(doc, indent=2) + "\n"


def _write(path: Path, text: str, mode: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    path.chmod(mode)
