"""The supervisor of a launch: agent configs, ports, and no agent outliving `semfleet launch`.

The process tests run the real command on the paper scenario (60 lock-step steps: far longer than
a test waits), signal it once all three agents are up, and watch the agents' pids: whatever ends
the launcher — SIGTERM, SIGHUP, SIGINT, SIGKILL, or an agent that died unplanned — every agent is
gone within ``GONE_S``, having stopped the way an agent stops (its log's ``stop`` record).
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from deploy.launch import LaunchError, free_ports, write_agent_config
from deploy.launch.supervisor import AgentProcess, SignalStop, Supervisor
from tests.deploy.conftest import agent_processes

SEMFLEET = Path(sys.executable).with_name("semfleet")
ROBOTS = ("r1", "r2", "r3")
UP_S = 60.0  # a guard against hangs while three agents import and open Zenoh
# SIGTERM → ctl/stop, 0.2 s, SIGTERM, at most 2 s more; an agent closes its journal on the way.
GONE_S = 5.0


def test_write_agent_config_round_trips_through_a_toml_reader(tmp_path: Path) -> None:
    agent = {
        "fleet": 'we"ird\\fleet',
        "start": [0.0, -3.5, 1e-300],
        "roster": ["r1", "r2"],
        "seed": 2**63 - 1,
        "simulation": True,
        "journal": "../journal/r1 ü.log",
        "window": None,  # left out
    }
    zenoh = {"listen": ["tcp/127.0.0.1:7447"], "connect": [], "gossip": False}
    path = tmp_path / "agents" / "r1.toml"
    write_agent_config(path, agent, zenoh)
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    assert doc == {"agent": {k: v for k, v in agent.items() if v is not None}, "zenoh": zenoh}


def test_free_ports_are_distinct_and_bindable() -> None:
    ports = free_ports(8)
    assert len(set(ports)) == 8 and all(1024 <= p < 65536 for p in ports)


# --------------------------------------------------------------------------- processes


def _alive(pid: int) -> bool:
    """Running, or stopped but not yet dead (a zombie has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


class Launch:
    """`semfleet launch --scenario paper` in its own session, with its agents once they are up."""

    def __init__(self, tmp_path: Path) -> None:
        self.root = tmp_path
        env = {"COLUMNS": "200", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"}
        self.proc = subprocess.Popen(
            [str(SEMFLEET), "launch", "--scenario", "paper", "--out", "run"],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # a signal to the test's group does not reach it
        )
        self.agents = self._wait_up()

    def _wait_up(self) -> dict[str, int]:
        """robot → pid once every agent logged that it is up."""
        deadline = time.monotonic() + UP_S
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, self.proc.communicate()
            pids = {_robot(cmd): pid for pid, cmd in agent_processes(self.root)}
            logs = [self.root / "run" / "logs" / f"{r}.log" for r in ROBOTS]
            if set(pids) == set(ROBOTS) and all(_says(log, "up at step 0") for log in logs):
                return pids
            time.sleep(0.1)
        raise AssertionError(f"agents not up in {UP_S} s")

    def wait_gone(self) -> float:
        """Seconds until no agent of this launch is alive (by pid)."""
        start = time.monotonic()
        while any(_alive(pid) for pid in self.agents.values()):
            assert time.monotonic() - start < 30, "agents outlived their launcher"
            time.sleep(0.02)
        return time.monotonic() - start

    def finish(self) -> tuple[int, str]:
        _, err = self.proc.communicate(timeout=30)
        return self.proc.returncode, err

    def log(self, robot: str) -> str:
        return (self.root / "run" / "logs" / f"{robot}.log").read_text(errors="replace")


def _robot(cmd: str) -> str:
    args = cmd.split()
    return args[args.index("--robot") + 1]


def _says(path: Path, text: str) -> bool:
    return path.exists() and text in path.read_text(errors="replace")


@pytest.mark.parametrize(
    ("sig", "code", "message"),
    [
        (signal.SIGTERM, 143, "semfleet: error: stopped by SIGTERM; every agent was stopped"),
        (signal.SIGHUP, 129, "semfleet: error: stopped by SIGHUP; every agent was stopped"),
        (signal.SIGINT, 130, "semfleet: error: interrupted"),
    ],
)
def test_launch_stops_every_agent_when_signalled(
    tmp_path: Path, sig: signal.Signals, code: int, message: str
) -> None:
    launch = Launch(tmp_path)
    os.kill(launch.proc.pid, sig)  # the launcher only: its agents hear of it from the launcher
    gone = launch.wait_gone()
    returncode, err = launch.finish()
    print(f"{sig.name}: every agent gone {gone:.2f} s after the signal")
    assert gone <= GONE_S
    assert (returncode, err.strip()) == (code, message), err
    for r in ROBOTS:
        assert '"event": "stop"' in launch.log(r), r  # stopped, not killed: journal closed


def test_agents_die_with_a_sigkilled_launcher(tmp_path: Path) -> None:
    """Nothing can run in a SIGKILLed launcher: the agents' parent-death signal stops them."""
    launch = Launch(tmp_path)
    os.kill(launch.proc.pid, signal.SIGKILL)
    gone = launch.wait_gone()
    returncode, _ = launch.finish()
    print(f"SIGKILL: every agent gone {gone:.2f} s after the signal")
    assert returncode == -signal.SIGKILL
    assert gone <= GONE_S
    for r in ROBOTS:
        assert '"reason": "SIGTERM"' in launch.log(r), r


def test_launch_whose_agent_dies_unplanned_leaves_no_agent(tmp_path: Path) -> None:
    launch = Launch(tmp_path)
    os.kill(launch.agents["r2"], signal.SIGKILL)
    gone = launch.wait_gone()
    returncode, err = launch.finish()
    print(f"r2 SIGKILLed: every agent gone {gone:.2f} s later")
    assert returncode == 1, err
    assert err.startswith("semfleet: error: agent r2 exited unexpectedly with code -9"), err
    assert err.count("\n") == 1, err
    assert "r2: up at step 0" in err and '"ts"' not in err, err  # messages, not JSON records
    assert gone <= GONE_S


def test_supervisor_never_starts_a_second_agent_of_a_running_robot(tmp_path: Path) -> None:
    """A second r2 would find r2's journal taken and exit, and the first one would be lost to
    the launcher's shutdown (issue 12: `chaos --restart r2@3` without a kill did both)."""
    supervisor = Supervisor()
    agent = AgentProcess("r2", tmp_path / "r2.toml", tmp_path / "r2.log", 0)
    supervisor.add(agent)
    agent.proc = subprocess.Popen(["sleep", "30"])
    first = agent.proc
    try:
        with pytest.raises(LaunchError, match=r"agent r2 is already running \(pid \d+\)"):
            supervisor.start("r2")
        assert agent.proc is first and agent.starts == 0
    finally:
        supervisor.stop_all()
    assert first.returncode == -signal.SIGTERM


def test_signal_stop_cancels_again_when_wait_for_drops_the_cancellation() -> None:
    """Python 3.11's ``asyncio.wait_for`` returns the result of a future that completed just as
    its task was cancelled, dropping the cancellation — and the conductor always waits that way.
    The signal here lands exactly then; the run must still stop, within a re-cancel period."""

    async def run() -> str:
        loop = asyncio.get_running_loop()
        with SignalStop() as stop:
            try:
                done = loop.create_future()
                # result → wait_for's callback → the task's wake-up: the signal comes in between
                loop.call_soon(done.set_result, "frame")
                loop.call_soon(loop.call_soon, stop.on_signal, signal.SIGTERM)
                await asyncio.wait_for(done, 5)
                await asyncio.sleep(5)
                return "ran on"
            except asyncio.CancelledError:
                stop.hold()
                return "stopped"

    start = time.monotonic()
    assert asyncio.run(run()) == "stopped"
    assert time.monotonic() - start < 1.0
