"""The records of ``--net netns`` runs, and the removal of what a record names.

A run writes its record (``STATE_DIR/<run>.json``: owner pid and start time, bridge, veths,
namespaces) before it creates anything, and deletes it once everything is gone. So whatever
killed a launcher, a record names every name it may have left behind, and :func:`sweep` — run
by every netns run before it creates its own network — removes the runs whose owner is no longer
alive. Runs on one machine choose subnets and sweep one at a time (a lock file next to the
records).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import signal
import subprocess
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

STATE_DIR = Path("/run/semfleet/netns")
COMMAND_TIMEOUT_S = 20.0


def write_record(doc: Mapping[str, Any]) -> Path:
    """Write (atomically) the record of run ``doc["run"]``; its path. Hold :func:`locked`."""
    path = STATE_DIR / f"{doc['run']}.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc), encoding="utf-8")
    tmp.replace(path)
    return path


def started(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks since boot), None if there is none: with
    the pid it names one process, even once the pid is reused."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return fields[19] if fields[0] != "Z" else None  # field 22 of proc(5); a zombie is dead


def run(cmd: Sequence[str], stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        list(cmd),
        input=stdin,
        capture_output=True,
        text=True,
        timeout=COMMAND_TIMEOUT_S,
        check=False,
    )


def first_line(text: str) -> str:
    return next((line.strip() for line in text.splitlines() if line.strip()), "no message")


@contextlib.contextmanager
def locked() -> Iterator[None]:
    """Runs on this machine choose subnets and sweep one at a time."""
    STATE_DIR.mkdir(parents=True, exist_ok=True, mode=0o700)
    with open(STATE_DIR / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def records() -> list[tuple[Path, dict[str, Any]]]:
    found = []
    for path in sorted(STATE_DIR.glob("*.json")):
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            log.warning("unreadable netns record %s: removed", path)
            path.unlink(missing_ok=True)
            continue
        if isinstance(doc, dict):
            found.append((path, doc))
    return found


def remove_recorded(ip: str, doc: Mapping[str, Any]) -> None:
    """Remove everything ``doc`` names, whatever of it exists; processes still inside its
    namespaces (agents of a dead launcher that ignored their SIGTERM) are killed first."""
    namespaces = [str(n) for n in doc.get("namespaces", [])]
    for ns in namespaces:
        for pid in run([ip, "netns", "pids", ns]).stdout.split():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)
    # A namespace is freed asynchronously once its name is gone; deleting the root side of each
    # veth first takes the pair down now, so no link outlives this call.
    for veth in doc.get("veths", []):
        run([ip, "link", "delete", str(veth)])
    for ns in namespaces:
        run([ip, "netns", "delete", ns])
    if doc.get("bridge"):
        run([ip, "link", "delete", str(doc["bridge"])])


def leftovers(doc: Mapping[str, Any], ip: str) -> list[str]:
    """The namespaces and links named by a run's record that still exist."""
    names = set(run([ip, "netns", "list"]).stdout.split())
    links = {
        line.split(":")[1].strip().split("@")[0]
        for line in run([ip, "-o", "link", "show"]).stdout.splitlines()
        if line.count(":") >= 2
    }
    left = [str(n) for n in doc.get("namespaces", []) if n in names]
    left += [str(v) for v in (*doc.get("veths", []), doc.get("bridge")) if v in links]
    return left


def sweep(ip: str) -> list[str]:
    """Remove every recorded run whose owner is no longer alive; their run ids."""
    if not STATE_DIR.is_dir():
        return []
    swept = []
    with locked():
        for path, doc in records():
            owner = doc.get("owner")
            if isinstance(owner, int) and started(owner) == doc.get("owner_started"):
                continue
            remove_recorded(ip, doc)
            path.unlink(missing_ok=True)
            swept.append(str(doc.get("run")))
            log.warning("removed the namespaces of run %s (its launcher is gone)", doc.get("run"))
    return swept
