"""The agent config file (docs/agents.md): a valid file loads with relative paths resolved, every
bad field is an AgentConfigError naming the file and the field, and `semfleet agent` turns such
errors into one line on stderr and a non-zero exit, never a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from agents.journal import Journal
from deploy.agent_cmd import AgentConfigError, load_agent_config

ROOT = Path(__file__).resolve().parents[2]

VALID = """\
[agent]
fleet = "f1"
scenario = "world.toml"
variants = ["comm10"]
seed = 3
mode = "lockstep"
gossip_period = 0.2
journal = "journal/r1.log"
comm = "range"
drop = 0.1
partitions = [[["r1", "r2"], 3, 5]]
publish_local = false

[zenoh]
listen = ["tcp/127.0.0.1:7447"]
connect = ["tcp/127.0.0.1:7448", "tcp/127.0.0.1:7449"]
gossip = false
lease_ms = 2000
"""
MINIMAL = '[agent]\nscenario = "paper"\n'


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "agent.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _set(key: str, value: str, text: str = VALID) -> str:
    """``text`` with the line ``key = ...`` of its first table that has it replaced (or added to
    the table named by a dotted key)."""
    table, name = key.split(".")
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.split(" = ")[0] == name:
            start = max(j for j in range(i + 1) if lines[j].startswith("["))
            if lines[start] == f"[{table}]":
                lines[i] = f"{name} = {value}"
                return "\n".join(lines) + "\n"
    at = lines.index(f"[{table}]") + 1
    lines.insert(at, f"{name} = {value}")
    return "\n".join(lines) + "\n"


def test_agent_config_valid_file_loads_with_relative_paths_resolved(tmp_path: Path) -> None:
    path = _write(tmp_path, VALID)
    c = load_agent_config(path, "r1")
    assert (c.robot, c.fleet, c.seed, c.comm, c.drop) == ("r1", "f1", 3, "range", 0.1)
    assert c.scenario == str(tmp_path / "world.toml")
    assert c.variants == ("comm10",)
    assert c.journal == tmp_path / "journal" / "r1.log"
    assert (c.runtime.mode, c.runtime.gossip_period, c.runtime.publish_local) == (
        "lockstep",
        0.2,
        False,
    )
    assert [(sorted(p.group), p.first, p.last) for p in c.partitions] == [(["r1", "r2"], 3, 5)]
    z = c.zenoh
    assert z.listen == ("tcp/127.0.0.1:7447",)
    assert z.connect == ("tcp/127.0.0.1:7448", "tcp/127.0.0.1:7449")
    assert (z.gossip, z.lease_ms, z.shared_memory) == (False, 2000, False)


def test_agent_config_defaults(tmp_path: Path) -> None:
    c = load_agent_config(_write(tmp_path, MINIMAL), "r2")
    assert (c.fleet, c.scenario, c.seed, c.runtime.mode, c.journal) == (
        "default",
        "paper",
        0,
        "realtime",
        None,
    )
    assert (c.drop, c.partitions, c.zenoh.gossip) == (0.0, (), True)


BAD = [
    ("[agent\nscenario = 1\n", "toml"),
    ("agent = 3\n", "agent"),
    ("[zenoh]\nlisten = []\n", "agent.scenario"),
    (MINIMAL + "[radio]\npower = 1\n", "radio"),
    (_set("agent.bogus", "1"), "agent.bogus"),
    (_set("zenoh.port", "7447"), "zenoh.port"),
    (_set("agent.scenario", "3"), "agent.scenario"),
    (_set("agent.fleet", "3"), "agent.fleet"),
    (_set("agent.fleet", '"two words"'), "agent.fleet"),
    (_set("agent.seed", "true"), "agent.seed"),
    (_set("agent.seed", "-1"), "agent.seed"),
    (_set("agent.seed", "1.5"), "agent.seed"),
    (_set("agent.mode", '"fast"'), "agent.mode"),
    (_set("agent.gossip_period", "0"), "agent.gossip_period"),
    (_set("agent.gossip_period", "nan"), "agent.gossip_period"),
    (_set("agent.gossip_period", '"1"'), "agent.gossip_period"),
    (_set("agent.comm", '"radio"'), "agent.comm"),
    (_set("agent.drop", "1.5"), "agent.drop"),
    (_set("agent.drop", "true"), "agent.drop"),
    (_set("agent.partitions", '"r1:3-5"'), "agent.partitions"),
    (_set("agent.partitions", '[["r1", 3, 5]]'), "agent.partitions[0]"),
    (_set("agent.partitions", '[[["r1"], 3]]'), "agent.partitions[0]"),
    (_set("agent.partitions", '[[["r1"], 5, 3]]'), "agent.partitions[0]"),
    (_set("agent.partitions", "[[[], 3, 5]]"), "agent.partitions[0]"),
    (_set("agent.partitions", '[[["r1"], "a", 5]]'), "agent.partitions[0]"),
    (_set("agent.journal", "3"), "agent.journal"),
    (_set("agent.variants", '"comm10"'), "agent.variants"),
    (_set("agent.replay_period", "0.5"), "agent.replay_period"),  # needs realtime mode
    (_set("agent.replay_period", "0", MINIMAL), "agent.replay_period"),
    (_set("zenoh.listen", '"tcp/127.0.0.1:7447"'), "zenoh.listen"),
    (_set("zenoh.listen", '["127.0.0.1:7447"]'), "zenoh.listen"),
    (_set("zenoh.connect", "[7448]"), "zenoh.connect"),
    (_set("agent.partitions", '[[["r1"], 2.5, 5]]'), "agent.partitions[0]"),
    (_set("agent.partitions", '[[["r 1"], 2, 5]]'), "agent.partitions[0]"),
    (_set("zenoh.lease_ms", "5"), "zenoh.lease_ms"),
    (_set("zenoh.gossip", '"false"'), "zenoh.gossip"),
    (_set("zenoh.shared_memory", '"no"'), "zenoh.shared_memory"),
    (_set("agent.publish_local", '"no"'), "agent.publish_local"),
    (_set("zenoh.lease_ms", '"3s"'), "zenoh.lease_ms"),
    (_set("zenoh.config_file", "3"), "zenoh.config_file"),
]
CASES = [pytest.param(t, f, id=f"{f}={t.splitlines()[-1]}") for t, f in BAD]


@pytest.mark.parametrize(("text", "field"), CASES)
def test_agent_config_bad_field_is_named(tmp_path: Path, text: str, field: str) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(AgentConfigError) as info:
        load_agent_config(path, "r1")
    assert info.value.field == field
    assert str(info.value).startswith(f"{path}: {field}: ")


@pytest.mark.parametrize("robot", ["", "r 1", "r/1", "x" * 33])
def test_agent_config_invalid_robot_id_is_named(tmp_path: Path, robot: str) -> None:
    with pytest.raises(AgentConfigError) as info:
        load_agent_config(_write(tmp_path, MINIMAL), robot)
    assert info.value.field == "--robot"


# --------------------------------------------------------------------------- the command


def _agent(tmp_path: Path, config: Path, robot: str = "r1") -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "COLUMNS": "200"}
    return subprocess.run(
        [sys.executable, "-m", "deploy.cli", "agent", "--robot", robot, "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=120,  # a guard against hangs: every case fails before opening Zenoh
        cwd=ROOT,
        env=env,
    )


def _one_line_error(r: subprocess.CompletedProcess[str], fragment: str) -> None:
    assert r.returncode != 0, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("semfleet: error: "), lines[0]
    assert fragment in lines[0], lines[0]


def test_agent_command_bad_config_is_one_line_error(tmp_path: Path) -> None:
    path = _write(tmp_path, _set("agent.mode", '"fast"', MINIMAL))
    _one_line_error(_agent(tmp_path, path), f"{path}: agent.mode: 'fast'")


def test_agent_command_missing_config_file_is_one_line_error(tmp_path: Path) -> None:
    _one_line_error(_agent(tmp_path, tmp_path / "nope.toml"), "nope.toml")


def test_agent_command_robot_not_in_scenario_is_one_line_error(tmp_path: Path) -> None:
    _one_line_error(_agent(tmp_path, _write(tmp_path, MINIMAL), "r9"), "r9 is not in the scenario")


def test_agent_command_journal_of_another_robot_is_one_line_error(tmp_path: Path) -> None:
    journal, _ = Journal.open(tmp_path / "r1.log", {"robot": "r2"})
    journal.close()
    path = _write(tmp_path, MINIMAL + 'journal = "r1.log"\n')
    _one_line_error(_agent(tmp_path, path), "journal: ")
