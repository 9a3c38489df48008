"""A port already taken (issue 46, item 6), as a user meets it: `semfleet agent` started from its
`fleet init` folder (mutual TLS) and `semfleet router`, each as a real process whose listen port
another process holds. Each exits 1 with one line naming the endpoint that is taken and no path
from inside Zenoh's build, and the agent never says it is up."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from agents.transport.zenoh_errors import open_error, without_build_paths
from deploy.cli.main import main
from deploy.launch import free_ports

# Zenoh 1.x's error for a TLS listener on a taken port, as `semfleet replay` printed it before.
ZENOH_SAID = (
    "Can not create a new TLS listener on 127.0.0.1:7447: 127.0.0.1:7447: Address already in use "
    "(os error 98) at /root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/io/"
    "zenoh-link-commons/src/tcp.rs:61. at /root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/"
    "cc83980/io/zenoh-links/zenoh-link-tls/src/unicast.rs:432."
)


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A loopback port another process (here: a plain socket) listens on."""
    with socket.socket() as held:
        held.bind(("127.0.0.1", free_ports(1)[0]))
        held.listen()
        yield held.getsockname()[1]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,  # a guard against hangs, not a speed check
    )


def _says_taken(r: subprocess.CompletedProcess[str], endpoint: str) -> None:
    assert r.returncode == 1, (r.stdout, r.stderr)
    last = r.stderr.strip().splitlines()[-1]
    assert last == (
        f"semfleet: error: cannot listen on {endpoint}: the address is in use (another process "
        "listens there: stop it, or give this session another port)"
    ), r.stderr
    for leak in (".cargo", ".rs:", "Traceback"):
        assert leak not in r.stdout + r.stderr, r.stderr


def test_an_agent_on_a_taken_port_names_it_and_never_says_up(
    tmp_path: Path, taken_port: int
) -> None:
    endpoint = f"tls/127.0.0.1:{taken_port}"
    init = ["fleet", "init", "--fleet", "lab", "--robots", "r1", "--scenario", "paper"]
    assert main([*init, "--listen", f"r1={endpoint}", "-o", str(tmp_path / "lab")]) == 0
    r = _run(["agent", "--robot", "r1", "--config", "agent.toml"], tmp_path / "lab/robots/r1")
    _says_taken(r, endpoint)
    assert "up at step" not in r.stderr, r.stderr


def test_a_router_on_a_taken_port_names_it(tmp_path: Path, taken_port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{taken_port}"
    r = _run(["router", "--listen", endpoint], tmp_path)
    _says_taken(r, endpoint)
    assert "router up" not in r.stdout, r.stdout


def test_zenoh_errors_lose_their_build_paths_and_name_the_taken_endpoint() -> None:
    assert without_build_paths(ZENOH_SAID) == (
        "Can not create a new TLS listener on 127.0.0.1:7447: 127.0.0.1:7447: Address already "
        "in use (os error 98)"
    )
    said = open_error(ZENOH_SAID, ["tls/127.0.0.1:7448", "tls/127.0.0.1:7447"], [])
    assert said.startswith("cannot listen on tls/127.0.0.1:7447: the address is in use"), said
    other = open_error("Unable to connect to any of [tcp/10.0.0.1:7447]! at /x/y.rs:3.", [], ["a"])
    assert other == "Zenoh session (dialling a): Unable to connect to any of [tcp/10.0.0.1:7447]!"
