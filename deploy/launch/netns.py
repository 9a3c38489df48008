"""The network of a ``--net netns`` run: one network namespace per robot on a bridge this module
creates, nftables rules that drop real packets, and nothing left behind.

Layout of run ``R`` (6 hex digits) on subnet ``10.213.N.0/24`` (the first N free on this machine):

- bridge ``sfRbr`` in the root namespace, address ``10.213.N.1``: the conductor's, never cut;
- robot i (0-based, in the run's order): namespace ``semfleet-R-i``, a veth pair ``sfRv<i>`` (root
  side, on the bridge) / ``eth0`` (inside), address ``10.213.N.(i+2)``, and ``lo`` up;
- in every robot namespace, the table ``inet semfleet_R`` (:mod:`deploy.launch.packet_faults`).

Nothing outlives the run, in three lines of defence:

1. The record comes first (:mod:`deploy.launch.netns_records`): ``/run/semfleet/netns/R.json``
   names the owner (pid and start time) and everything the run will create; it is written
   before anything is created.
2. :meth:`Network.remove` runs in the launcher's ``finally``: at the end of a run, on an error,
   and on SIGINT, SIGTERM or SIGHUP (which :class:`deploy.launch.supervisor.SignalStop` turns into
   a cancellation of the run). It removes the veths, the namespaces (their nftables tables go with
   them) and the bridge, then the record.
3. A SIGKILLed or crashed launcher cannot clean up: its agents die of their parent-death signal,
   and the next ``--net netns`` run sweeps (:func:`sweep`) every recorded run whose owner is no
   longer alive before it creates its own. Until then the leftovers are inert: a bridge and
   namespaces with no process in them.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import secrets
import shutil
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from deploy.base.errors import UsageError
from deploy.launch.errors import LaunchError
from deploy.launch.netns_records import (
    first_line,
    leftovers,
    locked,
    records,
    remove_recorded,
    run,
    started,
    sweep,
    write_record,
)
from deploy.launch.packet_faults import counters, receiver_rules, ruleset

log = logging.getLogger(__name__)

SUBNETS = ipaddress.ip_network("10.213.0.0/16")  # one /24 per run, the first free one
NAMESPACE_PREFIX = "semfleet-"
LINK_PREFIX = "sf"  # bridge and veth names: 15 characters at most (IFNAMSIZ)
_SEARCH_PATH = os.pathsep.join((os.environ.get("PATH", ""), "/usr/sbin", "/sbin"))


class NetnsError(UsageError):
    """``--net netns`` cannot run on this machine (not root, no ``ip`` or ``nft``, namespaces
    unavailable): one line naming what is missing."""


@dataclass(frozen=True, slots=True)
class Tools:
    ip: str
    nft: str


def require() -> Tools:
    """The commands a netns run needs, or :class:`NetnsError` saying what is missing."""
    if not sys.platform.startswith("linux"):
        raise NetnsError("--net netns: network namespaces are Linux only")
    if os.geteuid() != 0:
        raise NetnsError(
            "--net netns needs root (it creates network namespaces, a bridge and nftables rules)"
        )
    ip = shutil.which("ip", path=_SEARCH_PATH)
    if ip is None:
        raise NetnsError("--net netns needs iproute2's `ip` (apt-get install iproute2)")
    nft = shutil.which("nft", path=_SEARCH_PATH)
    if nft is None:
        raise NetnsError("--net netns needs nftables' `nft` (apt-get install nftables)")
    if not Path("/proc/self/ns/net").exists():
        raise NetnsError("--net netns: this kernel has no network namespaces")
    return Tools(ip, nft)


@dataclass(frozen=True, slots=True)
class Layout:
    """The names and addresses of one run (see the module docstring)."""

    run: str
    subnet: int
    robots: tuple[str, ...]

    @property
    def bridge(self) -> str:
        return f"{LINK_PREFIX}{self.run}br"

    @property
    def host(self) -> str:
        """The bridge's address: the conductor's."""
        return f"10.213.{self.subnet}.1"

    @property
    def table(self) -> str:
        return f"semfleet_{self.run}"

    def index(self, robot: str) -> int:
        return self.robots.index(robot)

    def namespace(self, robot: str) -> str:
        return f"{NAMESPACE_PREFIX}{self.run}-{self.index(robot)}"

    def veth(self, robot: str) -> str:
        return f"{LINK_PREFIX}{self.run}v{self.index(robot)}"

    def address(self, robot: str) -> str:
        return f"10.213.{self.subnet}.{self.index(robot) + 2}"

    @property
    def addresses(self) -> dict[str, str]:
        return {r: self.address(r) for r in self.robots}

    def record(self, owner: int, started: str) -> dict[str, Any]:
        return {
            "run": self.run,
            "subnet": self.subnet,
            "robots": list(self.robots),
            "owner": owner,
            "owner_started": started,
            "bridge": self.bridge,
            "namespaces": [self.namespace(r) for r in self.robots],
            "veths": [self.veth(r) for r in self.robots],
        }


def _used_subnets(ip: str) -> set[int]:
    """Third octets of 10.213.N.0/24 taken by a record, an address or a route of this machine."""
    used = {int(doc["subnet"]) for _, doc in records() if isinstance(doc.get("subnet"), int)}
    for what in (["-o", "-4", "addr", "show"], ["-4", "route", "show", "table", "all"]):
        for word in run([ip, *what]).stdout.split():
            try:
                net = ipaddress.ip_network(word, strict=False)
            except ValueError:
                continue
            if net.version == 4 and net.prefixlen >= SUBNETS.prefixlen and net.overlaps(SUBNETS):
                used.add(int(str(net.network_address).split(".")[2]))
    return used


@dataclass(slots=True)
class Network:
    """The live network of one run: create with :meth:`create`, always :meth:`remove`."""

    layout: Layout
    tools: Tools
    record_path: Path
    swept: list[str] = field(default_factory=list)
    _applied: dict[str, str] = field(default_factory=dict)

    @classmethod
    def create(cls, robots: Sequence[str]) -> Network:
        """Sweep dead runs, choose a subnet, record, then build the bridge and one namespace per
        robot. On failure everything made so far is removed and :class:`NetnsError` names the
        command that failed."""
        tools = require()
        swept = sweep(tools.ip)
        owner = os.getpid()
        owner_started = started(owner)
        assert owner_started is not None
        with locked():
            free = [n for n in range(1, 255) if n not in _used_subnets(tools.ip)]
            if not free:
                raise NetnsError("--net netns: every subnet 10.213.N.0/24 is taken on this machine")
            layout = Layout(secrets.token_hex(3), free[0], tuple(robots))
            path = write_record(layout.record(owner, owner_started))
        network = cls(layout, tools, path, swept)
        try:
            network._build()
        except BaseException:
            network.remove()
            raise
        return network

    def _build(self) -> None:
        ip, lay = self.tools.ip, self.layout
        commands = [
            ["link", "add", lay.bridge, "type", "bridge"],
            ["addr", "add", f"{lay.host}/24", "dev", lay.bridge],
            ["link", "set", lay.bridge, "up"],
        ]
        for r in lay.robots:
            ns, veth = lay.namespace(r), lay.veth(r)
            commands += [
                ["netns", "add", ns],
                ["link", "add", veth, "type", "veth", "peer", "name", "eth0", "netns", ns],
                ["link", "set", veth, "master", lay.bridge, "up"],
                ["-n", ns, "addr", "add", f"{lay.address(r)}/24", "dev", "eth0"],
                ["-n", ns, "link", "set", "eth0", "up"],
                ["-n", ns, "link", "set", "lo", "up"],
            ]
        for cmd in commands:
            done = run([ip, *cmd])
            if done.returncode != 0:
                raise NetnsError(f"--net netns: `ip {' '.join(cmd)}`: {first_line(done.stderr)}")

    def exec_prefix(self, robot: str) -> tuple[str, ...]:
        """The command prefix that runs a program in ``robot``'s namespace (``ip netns exec``
        execs it in place: same pid, parent-death signal kept)."""
        return (self.tools.ip, "netns", "exec", self.layout.namespace(robot))

    def enforce(self, verdict: Mapping[str, Sequence[str]], loss: float) -> list[str]:
        """Make every robot's namespace drop what ``verdict`` (receiver → senders it hears)
        cuts and lose ``loss`` of the rest; only the namespaces whose rules changed are
        touched. The robots whose rules changed."""
        lay = self.layout
        changed = []
        for r in lay.robots:
            text = ruleset(receiver_rules(verdict, r, lay.addresses, loss, lay.table))
            if self._applied.get(r) == text:
                continue
            done = run([*self.exec_prefix(r), self.tools.nft, "-f", "-"], text)
            if done.returncode != 0:
                raise LaunchError(f"nft in {lay.namespace(r)}: {first_line(done.stderr)}")
            self._applied[r] = text
            changed.append(r)
        return changed

    def heal(self) -> None:
        """Every robot hears every other again, no loss (the counters are kept): a run that is
        over lets its agents close their sessions at once. A failure is only logged: the
        shutdown goes on, and :meth:`remove` takes the rules away with the namespaces."""
        robots = self.layout.robots
        everyone = {r: tuple(p for p in robots if p != r) for r in robots}
        try:
            self.enforce(everyone, 0.0)
        except (LaunchError, subprocess.TimeoutExpired) as exc:
            log.warning("netns run %s: could not heal the links: %s", self.layout.run, exc)

    def dropped(self) -> dict[str, dict[str, int]]:
        """Packets each robot's namespace dropped so far: {robot: {"lost": n, "cut": n}}."""
        out = {}
        for r in self._applied:
            done = run([*self.exec_prefix(r), self.tools.nft, "-j", "list", "counters"])
            if done.returncode == 0:
                out[r] = counters(done.stdout, self.layout.table)
        return out

    def remove(self) -> list[str]:
        """Remove the run's namespaces, veths and bridge, then its record; the names that could
        not be removed (none unless something else holds them; logged)."""
        doc = self.layout.record(0, "")
        remove_recorded(self.tools.ip, doc)
        left = leftovers(doc, self.tools.ip)
        if left:
            log.error("netns run %s: could not remove %s", self.layout.run, ", ".join(left))
        else:
            self.record_path.unlink(missing_ok=True)
        return left
