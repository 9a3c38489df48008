"""No agent process outlives a test: after every test of this folder, no `deploy.cli agent` process
whose command line points into this session's temporary folder may remain (agents started by
`semfleet launch` in a subprocess are matched too, even once orphaned). Other users' agents on the
machine do not match. Leftovers are killed, by pid, and fail the test."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

GRACE_S = 2.0  # the launcher's own SIGTERM → SIGKILL grace


def agent_processes(root: Path) -> list[tuple[int, str]]:
    """(pid, command line) of every `deploy.cli agent` or `semfleet agent` process with an
    argument under ``root`` (scans /proc: psutil is not a dependency)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            raw = (entry / "cmdline").read_bytes()
        except OSError:  # gone meanwhile, or not ours to read
            continue
        args = [a.decode(errors="replace") for a in raw.split(b"\0") if a]
        command = any(a == "deploy.cli" or a.endswith("/semfleet") for a in args)
        is_agent = command and "agent" in args
        if is_agent and any(a.startswith(str(root)) for a in args):
            found.append((int(entry.name), " ".join(args)))
    return found


@pytest.fixture(autouse=True)
def no_agent_outlives_the_test(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    yield
    root = tmp_path_factory.getbasetemp()
    deadline = time.monotonic() + GRACE_S
    while (left := agent_processes(root)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid, _ in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not left, f"agent processes outlived the test: {left}"
