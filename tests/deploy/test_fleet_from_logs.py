"""Three agent processes fed only by `semfleet replay` from JSON-lines frame logs — no simulator,
no conductor, no truth anywhere — over Zenoh links r1–r2–r3 (gossip scouting off), in realtime:
every agent runs to the last step, gossips, fuses (D knows objects L does not) and publishes its
estimates, which `semfleet fleet status` reads from outside. This is docs/robots.md, as a test."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from deploy.launch import free_ports, write_agent_config
from sim.loader import load_scenario

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = ("r1", "r2", "r3")
STEPS = 25
FLEET = "fromlogs"

pytestmark = pytest.mark.slow


def _semfleet(*args: str, **kw: object) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", *args]


def _run(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "COLUMNS": "200"}
    return subprocess.run(
        _semfleet(*args), capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env
    )


def test_three_agents_fed_only_by_replayed_logs_gossip_fuse_and_finish(tmp_path: Path) -> None:
    paper = load_scenario("paper")
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    assert _run("scenario", "model", "paper", "-o", str(fleet / "model.toml")).returncode == 0
    ports = dict(zip(ROBOTS, free_ports(len(ROBOTS)), strict=True))
    for i, r in enumerate(ROBOTS):
        log = fleet / f"{r}.jsonl"
        export = ["scenario", "frames", "paper", "--seed", "4", "--robot", r, "-o", str(log)]
        assert _run(*export, "--steps", str(STEPS)).returncode == 0
        text = log.read_text()
        assert "truth" not in text and len(text.splitlines()) == STEPS + 1  # header + frames
        write_agent_config(
            fleet / f"{r}.toml",
            {
                "fleet": FLEET,
                "model": "model.toml",
                "start": [float(v) for v in paper.robot(r).start],
                "roster": list(ROBOTS),
                "seed": 0,
                "mode": "realtime",
                "gossip_period": 0.2,
                "journal": f"journal/{r}.log",
            },
            {
                "listen": [f"tcp/127.0.0.1:{ports[r]}"],
                "connect": [f"tcp/127.0.0.1:{ports[ROBOTS[i - 1]]}"] if i else [],
                "gossip": False,
            },
        )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    agents, replays = {}, {}
    try:
        for r in ROBOTS:
            with open(tmp_path / f"{r}.agent.log", "wb") as out:
                agents[r] = subprocess.Popen(
                    _semfleet("agent", "--robot", r, "--config", str(fleet / f"{r}.toml")),
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    cwd=ROOT,
                    env=env,
                )
        for r in ROBOTS:
            replay = ["replay", "--robot", r, "--frames", str(fleet / f"{r}.jsonl")]
            replay += ["--config", str(fleet / f"{r}.toml"), "--period", "0.25", "--wait"]
            with open(tmp_path / f"{r}.replay.log", "wb") as out:
                replays[r] = subprocess.Popen(
                    _semfleet(*replay, "--timeout", "240"),
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    cwd=ROOT,
                    env=env,
                )
        for r, p in replays.items():
            assert p.wait(300) == 0, (r, (tmp_path / f"{r}.replay.log").read_text())
        connect = [arg for r in ROBOTS for arg in ("--connect", f"tcp/127.0.0.1:{ports[r]}")]
        status = _run("fleet", "status", *connect, "--fleet", FLEET, "--mode", "peer", "--json")
        assert status.returncode == 0, status.stderr
        doc = {robot["robot"]: robot for robot in json.loads(status.stdout)["robots"]}
    finally:
        for p in [*replays.values(), *agents.values()]:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in [*replays.values(), *agents.values()]:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    assert set(doc) == set(ROBOTS)
    for r in ROBOTS:
        c = doc[r]["counters"]
        assert doc[r]["alive"] and doc[r]["k"] == STEPS, doc[r]
        assert c["frames_processed"] == STEPS and c["frames_invalid"] == 0, c
        assert c["stacks_sent"] > 0 and c["stacks_merged"] > 0, c
        assert c["steps_failed"] == 0 and c["stacks_invalid"] == 0, c
        # Fused: D maps objects that the robot's own L never saw.
        assert doc[r]["objects"]["distributed"] > doc[r]["objects"]["local"], doc[r]
    for r, p in agents.items():
        log = (tmp_path / f"{r}.agent.log").read_text()
        assert p.returncode == 0 and "Traceback" not in log, log[-2000:]
