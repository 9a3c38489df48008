"""Which tests run alone: ``make test`` runs the suite in two phases, every test not marked
``serial`` spread over the machine's cores (pytest-xdist), then the ``serial`` ones one at a time.

A module is serial when its tests run agents in real time or measure what a loaded machine would
blur: agent processes over Zenoh in realtime mode, gossip timers and liveliness timeouts, signals
and shutdown grace periods. Their assertions do not depend on wall-clock speed, but on a machine
whose cores are all taken by the estimator tests a 12-step realtime relay can legitimately fall a
step behind before the run ends. Everything else (maths, codecs, lock-step fleets, studies) is
deterministic and runs in parallel.

The session fixture ``netns_machine`` is the bootstrap of the network-namespace tests
(tests/deploy/test_netns.py): on a root Debian machine it installs nftables with apt-get when
`nft` is missing; elsewhere those tests skip with a one-line reason.
"""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest

SERIAL_MODULES = {
    "agents/test_gossip_during_step.py",
    "agents/test_perception.py",
    "agents/test_runtime.py",
    "agents/test_transport.py",
    "deploy/test_agent_process.py",
    "deploy/test_fleet_cmd.py",
    "deploy/test_fleet_from_logs.py",
    "deploy/test_launch.py",
    "deploy/test_launch_aoi.py",
    "deploy/test_launch_cmd.py",
    "deploy/test_launch_supervisor.py",
    "deploy/test_launch_table.py",
    "deploy/test_netns.py",
    "deploy/test_replay.py",
}
# The modules whose tests take most of the suite's time (measured with --durations, slowest
# first). xdist's worksteal scheduler first hands each worker one contiguous chunk of the
# collection (worker i the i-th of k near-equal chunks) and later moves tests from the tail of a
# busy worker's queue to an idle one; the head of a chunk stays with its worker. So the long
# modules are dealt out in turn (1st, 2nd, 2nd, 1st, … worker) and each worker's share is put at
# the head of its chunk: the long ones start at once on different cores, and the short ones fill
# the gaps and are what gets stolen, so that the phase ends close to total work / cores. A
# module's tests stay together, so module fixtures and caches are built once.
LONGEST_FIRST = (
    "deploy/test_consistency.py",
    "deploy/test_fleet_calibration.py",
    "estimator/test_hybrid.py",
    "deploy/test_fleet_quiet.py",
    "estimator/test_exact_reference.py",
    "deploy/test_cli.py",
    "deploy/test_study_methods.py",
    "test_docs_commands.py",
    "protocol/test_codec.py",
    "estimator/test_distributed.py",
)
HERE = Path(__file__).parent


def pytest_configure(config: pytest.Config) -> None:
    config.pluginmanager.register(_Order(), "semfleet-test-order")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark the tests of the serial modules (before ``-m`` deselects by marker), except those
    marked ``lockstep``: lock-step launches and usage errors, whose agents wait for each round
    whatever the load (their step timeouts are minutes), so they run beside the others."""
    for item in items:
        if _module(item) in SERIAL_MODULES and item.get_closest_marker("lockstep") is None:
            item.add_marker(pytest.mark.serial)


class _Order:
    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, items: list[pytest.Item]) -> None:
        """Order what ``-m`` left (see LONGEST_FIRST); every xdist worker orders alike."""
        workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        order = dealt([_module(item) for item in items], LONGEST_FIRST, workers)
        items[:] = [items[i] for i in order]


def _module(item: pytest.Item) -> str:
    return item.path.relative_to(HERE).as_posix()


def worker_chunks(n: int, workers: int) -> list[int]:
    """The sizes of the contiguous chunks of n tests that worksteal first gives each worker."""
    sizes: list[int] = []
    for i in range(workers):
        sizes.append((n - sum(sizes)) // (workers - i))
    return sizes


def dealt(modules: list[str], longest: Sequence[str], workers: int) -> list[int]:
    """A permutation of tests (given by their modules, in collection order): the ``longest``
    modules (slowest first) dealt to the workers in turn — 1st, 2nd, …, k-th, k-th, …, 1st — and
    each worker's share at the head of the chunk worksteal gives it, the other tests after them
    in collection order. With one worker: the longest first, then the rest."""
    rank = {m: r for r, m in enumerate(longest)}
    share: list[list[int]] = [[] for _ in range(max(1, workers))]
    for r in range(len(longest)):
        turn = r % (2 * len(share))
        worker = turn if turn < len(share) else 2 * len(share) - 1 - turn
        share[worker].extend(i for i, m in enumerate(modules) if rank.get(m) == r)
    rest = iter([i for i, m in enumerate(modules) if m not in rank])
    out: list[int] = []
    for mine, size in zip(share, worker_chunks(len(modules), len(share)), strict=True):
        out.extend(mine)
        out.extend(itertools.islice(rest, max(0, size - len(mine))))
    out.extend(rest)
    return out


# --------------------------------------------------------------------------- netns bootstrap

SBIN_PATH = os.pathsep.join((os.environ.get("PATH", ""), "/usr/sbin", "/sbin"))
APT_TIMEOUT_S = 600


def _apt_install(package: str) -> str | None:
    """``apt-get install -y package`` (after an ``apt-get update`` if the first try fails);
    None when installed, else the last line apt-get wrote."""
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    last = ""
    for update in (False, True):
        if update:
            subprocess.run(
                ["apt-get", "update"], capture_output=True, env=env, timeout=APT_TIMEOUT_S
            )
        done = subprocess.run(
            ["apt-get", "install", "-y", "-o", "DPkg::Lock::Timeout=120", package],
            capture_output=True,
            text=True,
            env=env,
            timeout=APT_TIMEOUT_S,
        )
        if done.returncode == 0:
            return None
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
    return last


@pytest.fixture(scope="session")
def netns_machine() -> None:
    """What `semfleet chaos --net netns` needs, or a skip with a one-line reason: Linux, root,
    iproute2's `ip`, network namespaces, and nftables' `nft` — which this bootstrap installs
    with apt-get when it is missing on a root machine that has apt-get (Debian)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("netns: network namespaces are Linux only")
    if os.geteuid() != 0:
        pytest.skip("netns: needs root (namespaces, a bridge, nftables rules)")
    ip = shutil.which("ip", path=SBIN_PATH)
    if ip is None:
        pytest.skip("netns: no `ip` (iproute2)")
    if shutil.which("nft", path=SBIN_PATH) is None:
        if shutil.which("apt-get") is None:
            pytest.skip("netns: no `nft` (nftables) and no apt-get to install it")
        failure = _apt_install("nftables")
        if failure is not None or shutil.which("nft", path=SBIN_PATH) is None:
            pytest.skip(f"netns: apt-get install nftables failed: {failure}")
    probe = f"semfleet-probe-{os.getpid()}"
    made = subprocess.run([ip, "netns", "add", probe], capture_output=True, text=True)
    subprocess.run([ip, "netns", "delete", probe], capture_output=True)
    if made.returncode != 0:
        reason = (made.stderr.strip().splitlines() or ["no message"])[0]
        pytest.skip(f"netns: cannot create a network namespace: {reason}")
