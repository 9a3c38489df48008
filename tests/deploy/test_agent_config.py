"""The agent config file (docs/agents.md): a valid file loads with relative paths resolved, every
bad field is an AgentConfigError naming the file and the field, and `semfleet agent` turns such
errors into one line on stderr and a non-zero exit, never a traceback."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from agents.journal import Journal
from deploy.operator.agent_config import AgentConfigError, load_agent_config
from deploy.operator.agent_service import node_factory
from estimator.hybrid import POSE_WINDOW
from sim.loader import load_scenario
from sim.robot_model import dump_robot_model

ROOT = Path(__file__).resolve().parents[2]

VALID = """\
[agent]
fleet = "f1"
model = "model.toml"
start = [1.0, -2.5, 0.3]
roster = ["r1", "r2", "r3"]
seed = 3
mode = "lockstep"
gossip_period = 0.2
journal = "journal/r1.log"
publish_local = false
simulation = true
window = 16

[zenoh]
listen = ["tcp/127.0.0.1:7447"]
connect = ["tcp/127.0.0.1:7448", "tcp/127.0.0.1:7449"]
gossip = false
lease_ms = 2000
"""
MINIMAL = '[agent]\nmodel = "model.toml"\nstart = [0, 0, 0]\nroster = ["r1", "r2"]\n'


def _write(tmp_path: Path, text: str) -> Path:
    model = tmp_path / "model.toml"
    if not model.exists():
        model.write_text(dump_robot_model(load_scenario("paper").robot_model()), encoding="utf-8")
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
    assert (c.robot, c.fleet, c.seed) == ("r1", "f1", 3)
    assert c.model_path == tmp_path / "model.toml"
    assert c.model == load_scenario("paper").robot_model()
    assert c.start == (1.0, -2.5, 0.3)
    assert c.roster == frozenset({"r1", "r2", "r3"})
    assert c.journal == tmp_path / "journal" / "r1.log"
    r = c.runtime
    assert (r.mode, r.gossip_period, r.publish_local, r.simulation, r.window) == (
        "lockstep",
        0.2,
        False,
        True,
        16,
    )
    z = c.zenoh
    assert z.listen == ("tcp/127.0.0.1:7447",)
    assert z.connect == ("tcp/127.0.0.1:7448", "tcp/127.0.0.1:7449")
    assert (z.gossip, z.lease_ms, z.shared_memory) == (False, 2000, None)  # None: not given


def test_agent_config_world_extent_sets_the_limits(tmp_path: Path) -> None:
    text = _set("agent.start", "[20000, 0, 0]", _set("agent.world_extent", "5e4"))
    c = load_agent_config(_write(tmp_path, text), "r1")
    assert c.limits.world_extent == 5e4 and c.start[0] == 20000
    assert c.limits.num_classes == c.model.num_classes


def test_agent_config_stack_gossip_is_one_of_the_known_ways_ask_by_default(tmp_path: Path) -> None:
    for way in ("delta", "ask", "full"):
        text = _set("agent.stack_gossip", f'"{way}"')
        assert load_agent_config(_write(tmp_path, text), "r1").runtime.stack_gossip == way
    assert load_agent_config(_write(tmp_path, MINIMAL), "r2").runtime.stack_gossip == "ask"


def test_agent_config_zenoh_mode_is_peer_by_default_or_a_routers_client(tmp_path: Path) -> None:
    assert load_agent_config(_write(tmp_path, VALID), "r1").zenoh.mode == "peer"
    text = _set("zenoh.listen", "[]", _set("zenoh.mode", '"client"'))
    assert load_agent_config(_write(tmp_path, text), "r1").zenoh.mode == "client"
    for bad in (_set("zenoh.mode", '"client"'), _set("zenoh.mode", '"router"')):
        with pytest.raises(AgentConfigError, match=r"zenoh\.mode"):
            load_agent_config(_write(tmp_path, bad), "r1")


def test_agent_config_keep_slots_bounds_the_slots_a_robot_keeps(tmp_path: Path) -> None:
    config = load_agent_config(_write(tmp_path, _set("agent.keep_slots", "25")), "r1")
    assert config.keep_slots == 25
    assert node_factory(config)().keep_slots == 25
    default = load_agent_config(_write(tmp_path, MINIMAL), "r2")
    assert default.keep_slots is None and node_factory(default)().keep_slots == 64


def test_agent_config_associate_on_reaches_the_nodes_track_and_the_journal(
    tmp_path: Path,
) -> None:
    """``associate_on``: the robot's association gates on its D (default) or its own L; a
    journal written under the other setting is not replayed (its frames would associate
    otherwise); a value it does not know is refused by name."""
    from deploy.operator.agent_service import journal_identity

    default = load_agent_config(_write(tmp_path, MINIMAL), "r2")
    assert default.associate_on == "fused" and node_factory(default)().track.guided
    alone = load_agent_config(_write(tmp_path, _set("agent.associate_on", '"local"')), "r1")
    assert alone.associate_on == "local" and not node_factory(alone)().track.guided
    assert "associate_on" not in journal_identity(default)
    assert journal_identity(alone)["associate_on"] == "local"
    with pytest.raises(AgentConfigError, match=r"agent\.associate_on.*'L'"):
        load_agent_config(_write(tmp_path, _set("agent.associate_on", '"L"')), "r1")


def test_agent_config_relay_is_event_by_default_or_tick(tmp_path: Path) -> None:
    text = _set("agent.relay", '"tick"')
    assert load_agent_config(_write(tmp_path, text), "r1").runtime.relay == "tick"
    assert load_agent_config(_write(tmp_path, MINIMAL), "r2").runtime.relay == "event"


def test_agent_config_classes_reach_the_beliefs_of_the_agents_node(tmp_path: Path) -> None:
    from deploy.operator.agent_config import DEFAULT_CLASSES
    from deploy.operator.agent_service import node_factory

    assert load_agent_config(_write(tmp_path, MINIMAL), "r2").classes == DEFAULT_CLASSES
    for kind in ("per_object", "joint"):
        c = load_agent_config(_write(tmp_path, _set("agent.classes", f'"{kind}"')), "r1")
        assert c.classes == kind
        node = node_factory(c)()
        assert node.local.config.classes == kind
        assert node.distributed.config.classes == kind
    with pytest.raises(AgentConfigError, match=r"agent\.classes: 'both' \(known: joint"):
        load_agent_config(_write(tmp_path, _set("agent.classes", '"both"')), "r1")


def test_agent_config_pose_window_reaches_the_beliefs_of_the_agents_node(tmp_path: Path) -> None:
    from deploy.operator.agent_service import node_factory

    assert load_agent_config(_write(tmp_path, MINIMAL), "r2").pose_window == POSE_WINDOW
    every = load_agent_config(_write(tmp_path, _set("agent.pose_window", '"all"')), "r1")
    assert every.pose_window is None
    assert node_factory(every)().distributed.config.window is None
    joint_default = load_agent_config(_write(tmp_path, _set("agent.classes", '"joint"')), "r1")
    assert joint_default.pose_window is None
    c = load_agent_config(_write(tmp_path, _set("agent.pose_window", "200")), "r1")
    assert c.pose_window == 200
    node = node_factory(c)()
    assert node.local.config.window == 200
    assert node.distributed.config.window == 200
    with pytest.raises(AgentConfigError, match=r"agent\.pose_window"):
        load_agent_config(_write(tmp_path, _set("agent.pose_window", "0")), "r1")
    with pytest.raises(AgentConfigError, match=r"agent\.pose_window: 'every'"):
        load_agent_config(_write(tmp_path, _set("agent.pose_window", '"every"')), "r1")
    with pytest.raises(AgentConfigError, match=r"agent\.pose_window: expected an integer"):
        load_agent_config(_write(tmp_path, _set("agent.pose_window", "2.5")), "r1")
    joint = _set("agent.classes", '"joint"', _set("agent.pose_window", "50"))
    with pytest.raises(AgentConfigError, match=r'agent\.pose_window: needs classes = "per_object"'):
        load_agent_config(_write(tmp_path, joint), "r1")


def test_agent_config_xi_parents_reach_the_slots_of_the_agents_node(tmp_path: Path) -> None:
    from deploy.operator.agent_service import node_factory

    assert load_agent_config(_write(tmp_path, MINIMAL), "r2").xi_parents == 2
    c = load_agent_config(_write(tmp_path, _set("agent.xi_parents", "3")), "r1")
    node = node_factory(c)()
    assert c.xi_parents == node.local.config.xi_parents == node.distributed.config.xi_parents == 3
    for bad in ("4", "-1"):
        with pytest.raises(AgentConfigError, match=r"agent\.xi_parents"):
            load_agent_config(_write(tmp_path, _set("agent.xi_parents", bad)), "r1")
    with pytest.raises(AgentConfigError, match=r"agent\.xi_parents: expected an integer"):
        load_agent_config(_write(tmp_path, _set("agent.xi_parents", '"3"')), "r1")
    joint = _set("agent.classes", '"joint"', _set("agent.xi_parents", "1"))
    with pytest.raises(AgentConfigError, match=r"agent\.xi_parents: shapes a sparse ξ: needs"):
        load_agent_config(_write(tmp_path, joint), "r1")


def test_agent_config_defaults(tmp_path: Path) -> None:
    c = load_agent_config(_write(tmp_path, MINIMAL), "r2")
    assert (c.fleet, c.seed, c.runtime.mode, c.journal) == ("default", 0, "realtime", None)
    assert (c.runtime.simulation, c.runtime.window) == (False, 64)
    doc = c.zenoh.document()  # fields left out take the defaults (no JSON5 file here)
    assert doc["scouting"]["gossip"]["enabled"] is True
    assert doc["transport"]["shared_memory"]["enabled"] is False
    assert doc["transport"]["link"]["tx"]["lease"] == 3000


BAD = [
    ("[agent\nmodel = 1\n", "toml"),
    ("agent = 3\n", "agent"),
    ("[zenoh]\nlisten = []\n", "agent.model"),
    (MINIMAL + "[radio]\npower = 1\n", "radio"),
    (_set("agent.bogus", "1"), "agent.bogus"),
    (_set("agent.scenario", '"paper"'), "agent.scenario"),  # an agent has no world
    (_set("zenoh.port", "7447"), "zenoh.port"),
    (_set("agent.model", "3"), "agent.model"),
    (_set("agent.model", '"missing.toml"'), "agent.model"),
    (_set("agent.model", '"agent.toml"'), "agent.model"),  # not a robot model
    ('[agent]\nmodel = "model.toml"\nroster = ["r1"]\n', "agent.start"),
    ('[agent]\nmodel = "model.toml"\nstart = [0, 0, 0]\n', "agent.roster"),
    (_set("agent.start", "[0, 0]"), "agent.start"),
    (_set("agent.start", '[0, 0, "a"]'), "agent.start[2]"),
    (_set("agent.start", "[0, nan, 0]"), "agent.start[1]"),
    (_set("agent.start", "[1e300, 0, 0]"), "agent.start"),
    (_set("agent.start", "[20000, 0, 0]"), "agent.start"),  # beyond the default world
    (_set("agent.start", "[0, 0, 7]"), "agent.start"),
    (_set("agent.world_extent", "0.5"), "agent.world_extent"),
    (_set("agent.world_extent", "1e8"), "agent.world_extent"),
    (_set("agent.world_extent", '"far"'), "agent.world_extent"),
    (_set("agent.start", "[true, 0, 0]"), "agent.start[0]"),
    (_set("agent.roster", '["r2", "r3"]'), "agent.roster"),  # not this robot's fleet
    (_set("agent.roster", '["r1", "r1"]'), "agent.roster"),
    (_set("agent.roster", '["r1", "r 2"]'), "agent.roster"),
    (_set("agent.roster", '"r1"'), "agent.roster"),
    (_set("agent.fleet", "3"), "agent.fleet"),
    (_set("agent.fleet", '"two words"'), "agent.fleet"),
    (_set("agent.seed", "true"), "agent.seed"),
    (_set("agent.seed", "-1"), "agent.seed"),
    (_set("agent.seed", "1.5"), "agent.seed"),
    (_set("agent.mode", '"fast"'), "agent.mode"),
    (_set("zenoh.listen", '["tcp/10.0.0.1:7447"]'), "zenoh.insecure"),  # exposed, no TLS
    (_set("zenoh.connect", '["tcp/robot7.local:7447"]'), "zenoh.insecure"),
    (_set("zenoh.listen", '["tls/10.0.0.1:7447"]'), "zenoh.insecure"),  # tls/, no mTLS config
    (_set("zenoh.insecure", '"yes"'), "zenoh.insecure"),
    (_set("zenoh.config_file", '"missing.json5"'), "zenoh.config_file"),
    (_set("agent.gossip_period", "0"), "agent.gossip_period"),
    (_set("agent.gossip_period", "nan"), "agent.gossip_period"),
    (_set("agent.gossip_period", '"1"'), "agent.gossip_period"),
    (_set("agent.window", "0"), "agent.window"),
    (_set("agent.window", '"8"'), "agent.window"),
    (_set("agent.stack_gossip", '"rumour"'), "agent.stack_gossip"),
    (_set("agent.relay", '"gossip"'), "agent.relay"),
    (_set("agent.keep_slots", "1"), "agent.keep_slots"),
    (_set("agent.keep_slots", "65"), "agent.keep_slots"),
    (_set("agent.keep_slots", '"all"'), "agent.keep_slots"),
    (_set("agent.catch_up", "-1"), "agent.catch_up"),
    (_set("agent.catch_up", "1001"), "agent.catch_up"),
    (_set("agent.simulation", '"yes"'), "agent.simulation"),
    (_set("agent.journal", "3"), "agent.journal"),
    (_set("zenoh.listen", '"tcp/127.0.0.1:7447"'), "zenoh.listen"),
    (_set("zenoh.listen", '["127.0.0.1:7447"]'), "zenoh.listen"),
    (_set("zenoh.connect", "[7448]"), "zenoh.connect[0]"),
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
    r = _agent(tmp_path, path)
    _one_line_error(r, f"{path}: agent.mode: 'fast'")
    assert r.returncode == 2  # a usage mistake, as docs/agents.md says


def test_agent_command_missing_config_file_is_one_line_error(tmp_path: Path) -> None:
    _one_line_error(_agent(tmp_path, tmp_path / "nope.toml"), "nope.toml")


def test_agent_command_robot_not_in_roster_is_one_line_error(tmp_path: Path) -> None:
    _one_line_error(_agent(tmp_path, _write(tmp_path, MINIMAL), "r9"), "does not list this robot")


def test_agent_command_journal_of_another_robot_is_one_line_error(tmp_path: Path) -> None:
    journal, _ = Journal.open(tmp_path / "r1.log", {"robot": "r2"})
    journal.close()
    path = _write(tmp_path, MINIMAL + 'journal = "r1.log"\n')
    _one_line_error(_agent(tmp_path, path), "belongs to another run")


def test_agent_command_port_taken_is_one_line_error(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = _write(tmp_path, MINIMAL + f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n')
        r = _agent(tmp_path, path)
    # The agent says it is up only once bound: the error is its only line.
    _one_line_error(r, f"cannot listen on tcp/127.0.0.1:{port}: the address is in use")
    assert r.returncode == 1 and ".cargo" not in r.stderr, r.stderr
