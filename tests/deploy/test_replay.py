"""`semfleet replay` end to end: one real agent process (configured by a robot model, realtime,
Zenoh on loopback) fed only by a second process, `semfleet replay`, from a frame log that
`semfleet scenario frames` exported — no conductor, no ground truth anywhere. This test watches
the agent's estimates through :class:`agents.perception.RobotLink`, as an integrator would.
"""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import numpy as np
import pytest

from agents.perception import RobotLink
from agents.transport import Inbox, Keys, MemoryBus, MemoryTransport
from agents.transport.zenoh_transport import ZenohSettings, loopback_endpoint
from deploy.base.errors import RunFailure
from deploy.cli.main import main
from deploy.launch import free_ports, write_agent_config
from deploy.operator.replay import RESEND_S, wait_until_step
from protocol.estimate import EstimateMessage, encode_estimate
from sim.loader import load_scenario
from sim.robot_model import dump_robot_model
from sim.sensors import Simulator
from tests.protocol.test_estimate import make_snapshot

PAPER = load_scenario("paper")
ROBOT = "r1"
STEPS = 20
PERIOD = 0.05
TIMEOUT_S = 60.0  # the test; the replay waits half as long for the agent


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", *args]


def _setup(tmp_path: Path, fleet: str) -> tuple[Path, Path, str]:
    """A robot model, r1's agent config (listening on a free loopback port) and r1's frame log of
    ``STEPS`` steps: (config, log, the agent's endpoint)."""
    (tmp_path / "model.toml").write_text(dump_robot_model(PAPER.robot_model()), encoding="utf-8")
    endpoint = loopback_endpoint(free_ports(1)[0])
    config = tmp_path / f"{ROBOT}.toml"
    agent = {
        "fleet": fleet,
        "model": "model.toml",
        "start": [float(v) for v in PAPER.robot(ROBOT).start],
        "roster": [ROBOT],
        "mode": "realtime",
        "journal": f"{ROBOT}.log",
    }
    write_agent_config(config, agent, {"listen": [endpoint], "gossip": False})
    log = tmp_path / f"{ROBOT}.jsonl"
    export = ["scenario", "frames", "paper", "--seed", "0", "--robot", ROBOT, "-o", str(log)]
    assert main([*export, "--steps", str(STEPS)]) == 0
    return config, log, endpoint


def _start_agent(config: Path, out: Path) -> subprocess.Popen[bytes]:
    with open(out, "ab") as f:
        return subprocess.Popen(
            _command("agent", "--robot", ROBOT, "--config", str(config)),
            stdout=f,
            stderr=subprocess.STDOUT,
        )


def _stop(proc: subprocess.Popen[bytes]) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


async def _replay_and_watch(
    config: Path, log: Path, endpoint: str, fleet: str, on_estimate: Callable[[int], None]
) -> tuple[list[EstimateMessage], str, int]:
    """Run `semfleet replay --wait` and collect r1's estimates until step ``STEPS`` (or until the
    replay exits), calling ``on_estimate(k)`` on each. Returns the estimates, the replay's output
    (white space folded: the console wraps) and its exit code."""
    settings = ZenohSettings(connect=(endpoint,), gossip=False)
    seen: list[EstimateMessage] = []
    command = _command("replay", "--robot", ROBOT, "--frames", str(log), "--config", str(config))

    async def collect(estimates: AsyncIterator[EstimateMessage]) -> None:
        async for estimate in estimates:
            seen.append(estimate)
            on_estimate(estimate.k)
            if estimate.k >= STEPS:
                return

    async with RobotLink(ROBOT, fleet, settings) as link, asyncio.timeout(TIMEOUT_S):
        collector = asyncio.create_task(collect(link.estimates()))
        await link.wait_for_agent()
        replay = await asyncio.create_subprocess_exec(
            *command,
            *("--period", str(PERIOD), "--wait", "--timeout", str(TIMEOUT_S / 2)),
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
        )
        try:
            output, _ = await replay.communicate()
            await asyncio.wait({collector}, timeout=5)  # its last estimate may still be on its way
        finally:
            collector.cancel()
            if replay.returncode is None:
                replay.kill()
                await replay.wait()
    assert replay.returncode is not None
    return seen, " ".join(output.decode(errors="replace").split()), replay.returncode


def test_replay_drives_a_real_agent_to_the_last_step(tmp_path: Path) -> None:
    config, log, endpoint = _setup(tmp_path, "replay")
    out = tmp_path / "agent.out"
    agent = _start_agent(config, out)
    try:
        seen, output, code = asyncio.run(
            _replay_and_watch(config, log, endpoint, "replay", lambda k: None)
        )
    finally:
        agent_code = _stop(agent)
    agent_log = out.read_text(errors="replace")
    assert code == 0, output
    assert f"published {STEPS} frames" in output, output
    assert f"the agent reached step {STEPS}" in output, output
    assert seen[-1].k == STEPS and seen[-1].robot == ROBOT
    assert [e.k for e in seen] == sorted(e.k for e in seen)
    final = seen[-1]
    assert final.counters["frames_processed"] == STEPS, final.counters
    assert final.beliefs["distributed"].object_ids, "r1 sees objects in its first 20 steps"
    assert agent_code == 0 and "Traceback" not in agent_log, agent_log


def test_replay_answers_a_restarted_agents_need_for_frames(tmp_path: Path) -> None:
    """The agent is SIGKILLed at step 8 and restarted from its journal; it asks for the frames it
    missed (ctl/need) and the replay re-sends them from its log, so the agent still ends at the
    last step."""
    config, log, endpoint = _setup(tmp_path, "restart")
    out = tmp_path / "agent.out"
    agents = [_start_agent(config, out)]

    def kill_and_restart(k: int) -> None:
        if k >= 8 and len(agents) == 1:
            agents[0].send_signal(signal.SIGKILL)
            agents[0].wait()
            agents.append(_start_agent(config, out))

    try:
        seen, output, code = asyncio.run(
            _replay_and_watch(config, log, endpoint, "restart", kill_and_restart)
        )
    finally:
        codes = [_stop(a) for a in agents]
    assert code == 0, output
    assert len(agents) == 2 and codes == [-signal.SIGKILL, 0], codes
    assert seen[-1].k == STEPS
    resent = int(output.split("re-sent ")[1].split()[0])
    assert resent >= 1, output


@pytest.mark.parametrize(
    ("edit", "says"),
    [
        (lambda lines: lines[:3] + lines[4:], "line 4: k: expected 3, got 4"),
        (
            lambda lines: [*lines[:2], lines[2].replace('"z_sem":[', '"z_sem":[1e999,', 1)],
            "line 3: detections[0].z_sem: non-finite number",
        ),
        (lambda lines: [lines[0], lines[1].replace('"r1"', '"r2"')], "robot r2's frames, not r1's"),
        (lambda lines: [], "line 1: frames: the log holds no frame"),
    ],
)
def test_replay_refuses_a_bad_log_with_its_line_and_field(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    edit: Callable[[list[str]], list[str]],
    says: str,
) -> None:
    """Exit 2 and one line naming the file, line and field, before any agent is looked for."""
    config, log, _ = _setup(tmp_path, "bad")
    lines = log.read_text(encoding="utf-8").splitlines()
    assert '"z_sem":[' in lines[2], "r1 sees an object at step 2"
    log.write_text("".join(line + "\n" for line in edit(lines)), encoding="utf-8")
    capsys.readouterr()
    assert main(["replay", "--robot", ROBOT, "--frames", str(log), "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"semfleet: error: --frames {log}: "), err
    assert says in err, err


def test_replay_says_when_no_agent_comes_up(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config, log, endpoint = _setup(tmp_path, "nobody")
    args = ["replay", "--robot", ROBOT, "--frames", str(log), "--config", str(config)]
    assert main([*args, "--timeout", "1"]) == 1
    err = capsys.readouterr().err
    assert f"no agent r1 alive on fleet nobody within 1 s (dialled {endpoint})" in err, err


def _estimate_bytes(k: int) -> bytes:
    snap = make_snapshot(np.random.default_rng(k), num_classes=2)
    return encode_estimate(EstimateMessage(ROBOT, k, {"distributed": snap}))


@pytest.mark.asyncio
async def test_replay_wait_resends_the_last_frame_until_the_agent_answers() -> None:
    """The last frame (or its estimate) lost: ``--wait`` sends the last frame again every
    ``RESEND_S`` until the agent's estimate of that step arrives; without an answer it fails with
    a sentence saying so."""
    keys = Keys("wait")
    frame = Simulator(PAPER, 0).frame(ROBOT, 5)
    bus = MemoryBus()
    agent = MemoryTransport(bus)
    received = Inbox(100)
    agent.subscribe(keys.frames(ROBOT), received)
    await agent.open()

    async def agent_hears_the_second_copy() -> None:
        await received.get()  # the first copy is "lost"
        await received.get()
        agent.publish(keys.estimate(ROBOT), _estimate_bytes(frame.k))

    async with RobotLink(ROBOT, keys.fleet, transport=MemoryTransport(bus)) as link:
        answer = asyncio.create_task(agent_hears_the_second_copy())
        link.publish_frame(frame)
        assert await wait_until_step(link, link.estimates(), frame, timeout=3 * RESEND_S) == 5
        await answer
        link.publish_frame(frame)
        with pytest.raises(RunFailure, match=r"r1's agent did not reach step 5 within 0\.2 s of "):
            await wait_until_step(link, link.estimates(), frame, timeout=0.2)


SECURE_STEPS = 12


def test_replay_feeds_a_secure_fleet_from_each_robots_fleet_init_folder(tmp_path: Path) -> None:
    """docs/robots.md and docs/deploy.md as a user follows them: `fleet init` (mutual TLS,
    access control, gossip off), each agent started in its robot's folder from its own
    `agent.toml`, and each robot's frames replayed with that same `agent.toml`. Each replay
    dials its own agent only (never listens: the agents' ports are taken), both agents reach the
    last step, and the operator's status, over mutual TLS, shows them there."""
    robots = ("r1", "r2")
    ports = dict(zip(robots, free_ports(len(robots)), strict=True))
    listen = {r: f"tls/127.0.0.1:{p}" for r, p in ports.items()}
    init = ["fleet", "init", "--fleet", "lab", "--robots", ",".join(robots), "--scenario", "paper"]
    for r in robots:
        init += ["--listen", f"{r}={listen[r]}"]
    assert main([*init, "-o", str(tmp_path / "lab-fleet")]) == 0
    folders = {r: tmp_path / "lab-fleet" / "robots" / r for r in robots}
    for r in robots:
        export = ["scenario", "frames", "paper", "--seed", "0", "--robot", r, "-o"]
        assert main([*export, str(tmp_path / f"{r}.jsonl"), "--steps", str(SECURE_STEPS)]) == 0
    agents: dict[str, subprocess.Popen[bytes]] = {}
    try:
        for r in robots:
            with open(tmp_path / f"agent-{r}.out", "wb") as f:
                agents[r] = subprocess.Popen(
                    _command("agent", "--robot", r, "--config", "agent.toml"),
                    cwd=folders[r],
                    stdout=f,
                    stderr=subprocess.STDOUT,
                )
        replays = {
            r: subprocess.Popen(
                _command(
                    "replay", "--robot", r, "--frames", str(tmp_path / f"{r}.jsonl"),
                    "--config", str(folders[r] / "agent.toml"),
                    "--period", "0.1", "--wait", "--timeout", str(TIMEOUT_S / 2),
                ),
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
            )
            for r in robots
        }  # fmt: skip
        outputs = {r: p.communicate(timeout=TIMEOUT_S)[0].decode() for r, p in replays.items()}
        operator = tmp_path / "lab-fleet" / "operator" / "zenoh.json5"
        status = subprocess.run(
            _command(
                "fleet", "status", "--fleet", "lab", "--mode", "peer", "--zenoh-config",
                str(operator), *(a for r in robots for a in ("--connect", listen[r])), "--json",
            ),
            capture_output=True,
            timeout=TIMEOUT_S,
        )  # fmt: skip
    finally:
        codes = {r: _stop(a) for r, a in agents.items()}
    for r in robots:
        said = " ".join(outputs[r].split())
        assert replays[r].returncode == 0, said
        assert f"replaying {SECURE_STEPS} frames of {r} on fleet lab" in said, said
        assert f"dialling {listen[r]} " in said, said  # its own agent, not the other robot
        assert f"the agent reached step {SECURE_STEPS}" in said, said
        agent_log = (tmp_path / f"agent-{r}.out").read_text(errors="replace")
        assert codes[r] == 0 and "Traceback" not in agent_log, agent_log
        assert f"listening on {listen[r]}" in agent_log, agent_log
    assert status.returncode == 0, status.stderr
    doc = json.loads(status.stdout)
    assert {r["robot"]: r["k"] for r in doc["robots"]} == dict.fromkeys(robots, SECURE_STEPS), doc
