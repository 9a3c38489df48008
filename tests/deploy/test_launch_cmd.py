"""`semfleet launch` as a user in their own folder runs it: a world file named relative to where
they stand, one robot, a few realtime steps."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from deploy.launch.report import agents
from tests.deploy.test_launch import world_text

SEMFLEET = Path(sys.executable).with_name("semfleet")


def test_launch_scenario_path_relative_to_the_callers_folder(tmp_path: Path) -> None:
    site = tmp_path / "site"
    (site / "worlds").mkdir(parents=True)
    (site / "worlds" / "pair.toml").write_text(world_text("pair", 2, 3.0, 4, 0.1), "utf-8")
    args = ["--robots", "r1", "--mode", "realtime", "--steps", "2", "--period", "0.2"]
    r = subprocess.run(
        [str(SEMFLEET), "launch", "--scenario", "worlds/pair.toml", *args, "--out", "run"],
        capture_output=True,
        text=True,
        timeout=600,  # a guard against hangs
        cwd=site,
        env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "launching 1 agent of pair (realtime, seed 0)" in r.stdout
    doc = json.loads((site / "run" / "results.json").read_text(encoding="utf-8"))
    assert doc["scenario"] == "pair"
    assert doc["robots"] == ["r1"] and doc["communication"] == "range", doc  # which ran, how
    assert "up at step 0" in (site / "run" / "logs" / "r1.log").read_text()


def test_agents_counts_in_words() -> None:
    assert [agents(n) for n in (1, 2, 3)] == ["1 agent", "2 agents", "3 agents"]


def test_a_secure_launch_says_it_is_secure_and_an_insecure_one_says_it_is_not(
    tmp_path: Path,
) -> None:
    """Nothing else in a launch's output told a secure run from a plain one (issue 46, item 10);
    `demo` prints the same line (tests/deploy/test_cli.py)."""
    said = {}
    for secure in (True, False):
        out = tmp_path / ("secure" if secure else "plain")
        args = ["--scenario", "lanes:short", "--steps", "2", "--out", str(out)]
        r = subprocess.run(
            [str(SEMFLEET), "launch", *args, *(["--secure"] if secure else [])],
            capture_output=True,
            text=True,
            timeout=600,  # a guard against hangs
            env={"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
        )
        assert r.returncode == 0, r.stderr[-3000:]
        said[secure] = r.stdout
    fleet = tmp_path / "secure" / "fleet"
    assert (
        "secure fleet: mutual TLS, access control and owner-signed slots (a throwaway CA, "
        f"certificates and keys in {fleet})"
    ) in said[True], said[True]
    assert (fleet / "ca" / "ca.pem").is_file() and not (tmp_path / "plain" / "fleet").exists()
    insecure = "insecure fleet: plain Zenoh, no TLS or access control (--secure for mutual TLS)"
    assert insecure in said[False] and insecure not in said[True], said[False]
