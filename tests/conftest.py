"""Which tests run alone: ``make test`` runs the suite in two phases, every test not marked
``serial`` spread over the machine's cores (pytest-xdist), then the ``serial`` ones one at a time.

A module is serial when its tests run agents in real time or measure what a loaded machine would
blur: agent processes over Zenoh in realtime mode, gossip timers and liveliness timeouts, signals
and shutdown grace periods. Their assertions do not depend on wall-clock speed, but on a machine
whose cores are all taken by the estimator tests a 12-step realtime relay can legitimately fall a
step behind before the run ends. Everything else (maths, codecs, lock-step fleets, studies) is
deterministic and runs in parallel.
"""

from __future__ import annotations

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
    "deploy/test_launch_cmd.py",
    "deploy/test_launch_supervisor.py",
    "deploy/test_launch_table.py",
    "deploy/test_replay.py",
}
# The modules whose tests take most of the suite's time (measured with --durations, slowest
# first). They are collected first: xdist hands out the first tests one by one, in turn, to its
# workers, so the long ones start at once on different cores and the short ones fill the gaps
# (longest first: the phase ends close to total work / cores instead of a long test starting
# last). A module's tests stay together, so module fixtures are built once.
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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.relative_to(HERE).as_posix() in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)
    rank = {m: i for i, m in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.relative_to(HERE).as_posix(), len(rank)))
