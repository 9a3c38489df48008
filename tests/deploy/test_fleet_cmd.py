"""`semfleet fleet status|watch|stop`: the operator's view of a running fleet.

The end-to-end tests run real agent processes on loopback, wired as in issue 11 (r2 dials r1,
Zenoh gossip off, as on a real fleet) and fed their frames by :func:`feed`; the operator always
connects to r1 alone, so it sees r2 only because r1 routes for its Zenoh client. The rest checks
the view, the documents and the error paths in-process, against fake robots where a real one
would not misbehave on cue.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import math
import signal
import subprocess
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from agents.control import NeedFrames, Stop, decode_control
from agents.transport.base import Inbox, Keys, Message
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport, loopback_endpoint
from deploy.base.errors import UsageError
from deploy.cli import main as cli
from deploy.cli.args import zenoh_endpoint
from deploy.launch import free_ports, write_agent_config
from deploy.launch.conductor import without_truth
from deploy.operator.fleet_session import StopProgress, session_settings, stop_fleet
from deploy.operator.fleet_view import (
    FleetView,
    age_line,
    behind_line,
    estimates_doc,
    fusion_behind,
    status_doc,
)
from estimator.hybrid import BeliefSnapshot
from estimator.metrics import mixture_moments
from estimator.models import SensorFrame
from protocol.errors import RemoteProtocolError
from protocol.estimate import EstimateMessage, decode_estimate, encode_estimate
from protocol.frames import encode_frame
from sim.loader import parse_scenario
from sim.robot_model import dump_robot_model
from sim.sensors import Simulator
from tests.deploy.tables import table_cells
from tests.estimator.scenarios import fleet_text, objects_ahead
from tests.tolerance import assert_angles_close, assert_close

SEMFLEET = Path(sys.executable).with_name("semfleet")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
ROBOT_YS = (0.0, 2.0)
STEPS = 16
WORLD = parse_scenario(
    fleet_text(
        "operator", STEPS, ROBOT_YS, objects_ahead(ROBOT_YS), half_angle_deg=50.0, sensing=3.5
    )
)
OBJECTS = {o.id: np.array(o.pose) for o in WORLD.objects}


def semfleet(*args: str, columns: int = 200) -> subprocess.CompletedProcess[str]:
    env = {"COLUMNS": str(columns), "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"}
    return subprocess.run(
        [str(SEMFLEET), *args], capture_output=True, text=True, timeout=120, env=env
    )


# --------------------------------------------------------------------------- a running fleet


@dataclass
class Fleet:
    keys: Keys
    endpoints: dict[str, str]
    procs: dict[str, subprocess.Popen[bytes]]
    logs: dict[str, Path]

    def log(self, robot: str) -> str:
        return self.logs[robot].read_text(errors="replace")


def write_agent_configs(folder: Path, fleet: str, ports: Mapping[str, int]) -> dict[str, Path]:
    """The one place that knows the agent config format (docs/agents.md): the world's robot
    model, each robot's start and the roster; every robot listens on its port and dials the
    robots before it, with Zenoh gossip off (links exactly where configured)."""
    (folder / "model.toml").write_text(dump_robot_model(WORLD.robot_model()), encoding="utf-8")
    robots = list(ports)
    configs = {}
    for i, r in enumerate(robots):
        configs[r] = folder / f"{r}.toml"
        agent = {
            "fleet": fleet,
            "model": "model.toml",
            "start": [float(v) for v in WORLD.robot(r).start],
            "roster": robots,
            "mode": "realtime",
            "gossip_period": 0.2,
            "journal": f"{r}.log",
        }
        zenoh = {
            "listen": [loopback_endpoint(ports[r])],
            "connect": [loopback_endpoint(ports[p]) for p in robots[:i]],
            "gossip": False,
        }
        write_agent_config(configs[r], agent, zenoh)
    return configs


@contextlib.contextmanager
def running_fleet(tmp_path: Path, fleet: str) -> Iterator[Fleet]:
    """The world's agents as processes; whatever is still running at the end gets SIGTERM, then
    SIGKILL."""
    ports = dict(zip(WORLD.robot_ids, free_ports(len(WORLD.robot_ids)), strict=True))
    configs = write_agent_configs(tmp_path, fleet, ports)
    endpoints = {r: loopback_endpoint(p) for r, p in ports.items()}
    state = Fleet(Keys(fleet), endpoints, {}, {r: tmp_path / f"{r}.out" for r in ports})
    try:
        for r, cfg in configs.items():
            cmd = [sys.executable, "-m", "deploy.cli", "agent", "--robot", r, "--config", str(cfg)]
            with open(state.logs[r], "wb") as out:
                state.procs[r] = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
        yield state
    finally:
        for p in state.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in state.procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def frames_without_truth() -> dict[str, list[SensorFrame]]:
    frames = Simulator(WORLD, 0).all_frames()
    return {r: [without_truth(f) for f in fs] for r, fs in frames.items()}


async def feed(
    fleet: Fleet, period: float, up: asyncio.Event | None = None, timeout: float = 60.0
) -> dict[str, int]:
    """A perception stack for every robot: once every agent's token is there (then ``up`` is
    set), frame k of each robot every ``period`` s, re-sending what an agent asks for on
    ``ctl/need``; returns when every agent has published its estimate of the last step, with
    each robot's last step as its estimates said."""
    frames = frames_without_truth()
    keys = fleet.keys
    session = ZenohTransport(ZenohSettings(connect=tuple(fleet.endpoints.values()), gossip=False))
    alive, needs, estimates = Inbox(1000), Inbox(1000), Inbox(10_000)
    session.watch_alive(keys.alive("*"), alive)
    session.subscribe(keys.ctl("need", "*"), needs)
    session.subscribe(keys.estimate("*"), estimates)
    steps = dict.fromkeys(fleet.endpoints, 0)

    def publish(robot: str, first: int, last: int) -> None:
        for k in range(max(first, 1), last + 1):
            session.publish(keys.frames(robot), encode_frame(frames[robot][k - 1]))

    def pump() -> None:
        for m in estimates.drain():
            est = decode_estimate(m.payload)
            steps[est.robot] = max(steps[est.robot], est.k)
        for m in needs.drain():
            with contextlib.suppress(RemoteProtocolError):
                need = decode_control(m.payload)
                if isinstance(need, NeedFrames) and need.k <= sent:
                    publish(need.robot, need.k, sent)

    sent = 0
    await session.open()
    try:
        async with asyncio.timeout(timeout):
            seen: set[str] = set()
            while not set(fleet.endpoints) <= seen:
                await alive.wait(0.2)
                seen |= {keys.robot_of(m.key) or "" for m in alive.drain() if m.kind == "alive"}
            if up is not None:
                up.set()
            for k in range(1, STEPS + 1):
                sent = k
                for r in fleet.endpoints:
                    publish(r, k, k)
                await asyncio.sleep(period)
                pump()
            while min(steps.values()) < STEPS:
                await estimates.wait(0.2)
                pump()
    finally:
        await session.close()
    return steps


# --------------------------------------------------------------------------- the commands, for real


def test_status_sees_both_agents_alive_at_their_last_step(tmp_path: Path) -> None:
    """As in issue 11: two agents wired with listen/connect exchanged and merged stacks, then sat
    at their last step; the status shows them, their steps and their counters."""
    with running_fleet(tmp_path, "opstatus") as fleet:
        assert asyncio.run(feed(fleet, period=0.05)) == {"r1": STEPS, "r2": STEPS}
        args = ["fleet", "status", "--connect", fleet.endpoints["r1"], "--fleet", "opstatus"]
        r = semfleet(*args, columns=80)  # a pipe of 80 columns, as most terminals
        assert r.returncode == 0, r.stderr
        print(r.stdout)
        rows = one_table_at_80_columns(r.stdout)
        assert [row[:3] for row in rows] == [["r1", "yes", str(STEPS)], ["r2", "yes", str(STEPS)]]
        assert "0 on every robot: invalid, slots rej., quarantined" in r.stdout
        assert "2 alive, 2 answered" in r.stdout
        # Each fused the other's slot, whose stacks said how old it was (holding times).
        assert "age of the peers' information (holding times, transits excluded) on 2 robots" in (
            " ".join(r.stdout.split())
        )
        r = semfleet(
            "fleet", "status", "--connect", fleet.endpoints["r1"], "--fleet", "opstatus", "--json"
        )
        assert r.returncode == 0, r.stderr
        doc = json.loads(r.stdout)
        print("status answered after", doc["answered_s"], "s; command took", doc["elapsed_s"])
        robots = {row["robot"]: row for row in doc["robots"]}
        assert set(robots) == {"r1", "r2"}
        for row in robots.values():
            c = row["counters"]
            assert row["alive"] and row["k"] == STEPS == c["step"], row
            assert c["frames_processed"] == STEPS and c["stacks_merged"] > 0, c
            assert row["hypotheses"]["distributed"] == c["hypotheses_distributed"] >= 1, row
            assert row["objects"]["distributed"] == 4, row
            assert c["status_requests"] >= 1, c
            assert c["peers_aged"] == 1 and 0 < c["peer_age_median_ms"] == c["peer_age_max_ms"], c


def one_table_at_80_columns(stdout: str) -> list[list[str]]:
    """The cells of the one fleet table in ``stdout``, checked whole at 80 columns: one
    heading (not split into tables stacked below each other), every row on one line."""
    lines = stdout.splitlines()
    (rule,) = [i for i, line in enumerate(lines) if set(line.strip()) == {"─"}]
    assert lines[rule - 1].split()[:3] == ["robot", "alive", "step"], stdout
    end = next(i for i in range(rule + 1, len(lines)) if not lines[i].startswith("r"))
    assert max(len(line) for line in lines[: end + 1]) <= 80, stdout  # title to caption
    rows = table_cells(lines[rule + 1 : end])
    assert len(rows) == end - rule - 1, stdout  # no row wrapped
    return rows


def test_watch_writes_estimates_and_map_of_both_agents(tmp_path: Path) -> None:
    """A watch while the agents step: the file holds both robots' last step, every step it saw in
    the trail, and estimates where the objects are; the map is a PNG."""
    out = tmp_path / "watch"

    async def scenario(fleet: Fleet) -> tuple[int | None, bytes, bytes]:
        up = asyncio.Event()
        feeding = asyncio.create_task(feed(fleet, period=0.3, up=up))
        await up.wait()
        args = ["fleet", "watch", "--connect", fleet.endpoints["r1"], "--fleet", "opwatch"]
        watch = await asyncio.create_subprocess_exec(
            str(SEMFLEET),
            *args,
            "--duration",
            str(STEPS * 0.3 + 3.0),
            "--out",
            str(out),
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            env={"COLUMNS": "80", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
        )
        await feeding
        stdout, stderr = await asyncio.wait_for(watch.communicate(), 60)
        return watch.returncode, stdout, stderr

    with running_fleet(tmp_path, "opwatch") as fleet:
        code, stdout, stderr = asyncio.run(scenario(fleet))
    assert code == 0, stderr.decode()
    assert f"wrote {out / 'estimates.json'}, {out / 'map.png'}\n" in stdout.decode()
    rows = one_table_at_80_columns(stdout.decode())  # the live table's last frame, on a pipe
    assert [row[:3] for row in rows] == [["r1", "yes", str(STEPS)], ["r2", "yes", str(STEPS)]]
    doc = json.loads((out / "estimates.json").read_text())
    assert doc["format"] == 1 and doc["fleet"] == "opwatch" and doc["classes_seen"] == 2
    assert set(doc["robots"]) == {"r1", "r2"}
    for robot, entry in doc["robots"].items():
        assert entry["k"] == STEPS == entry["counters"]["step"], robot
        ks = [k for k, _, _ in entry["trail"]]
        assert ks == sorted(set(ks)) and ks[-1] == STEPS and len(ks) >= 5, (robot, ks)
        assert set(entry["beliefs"]) == {"distributed", "local"}
        d = entry["beliefs"]["distributed"]
        assert sorted(o["id"] for o in d["objects"]) == [1, 2, 3, 4], robot
        for o in d["objects"]:
            assert_close(sum(o["marginals"]), 1.0, what=f"{robot} object {o['id']}")
            assert o["map_class"] in (0, 1)
            # estimates in the world frame, where the objects are (σ ≈ 0.3 m)
            assert np.hypot(*(np.array(o["pose"][:2]) - OBJECTS[o["id"]][:2])) < 1.0, o
            assert np.all(np.linalg.eigvalsh(o["cov_xy"]) > 0), o
        start = WORLD.robot(robot).start
        x, y, _ = d["robot_pose"]
        assert abs(y - start[1]) < 0.5 and x > start[0] + 1.0, (robot, d["robot_pose"])
    assert (out / "map.png").read_bytes().startswith(PNG_MAGIC)


def test_stop_ends_both_agents(tmp_path: Path) -> None:
    """Both endpoints given: the client fails over to r2 if r1 goes first, so a robot that did
    not stop would be seen again."""
    with running_fleet(tmp_path, "opstop") as fleet:
        asyncio.run(feed(fleet, period=0.02))
        r = semfleet(
            "fleet", "stop", "--fleet", "opstop", "--reason", "operator test",
            "--connect", fleet.endpoints["r1"], "--connect", fleet.endpoints["r2"],
        )  # fmt: skip
        print(r.stdout)
        assert r.returncode == 0, (r.stdout, r.stderr)
        assert "stopped: r1, r2" in r.stdout
        for robot, p in fleet.procs.items():
            assert p.wait(timeout=5) == 0, fleet.log(robot)
            assert '"reason": "operator test"' in fleet.log(robot)


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--connect", "127.0.0.1:7447"], "expected PROTOCOL/ADDRESS"),
        (["--connect", "tcp/127.0.0.1"], "expected HOST:PORT"),
        (["--connect", "tcp/127.0.0.1:0"], "port in 1..65535"),
        (["--connect", "tcp/:7447"], "expected HOST:PORT"),
        (["--connect", "carrier-pigeon/7447"], "protocols: "),
        (["--connect", "tcp/127.0.0.1:7447", "--fleet", "a/b"], "--fleet 'a/b'"),
        (["--connect", "tcp/127.0.0.1:7447", "--timeout", "0"], "--timeout 0.0"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], args: list[str], fragment: str
) -> None:
    argv = ["fleet", "status", "--fleet", "f", *args]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("semfleet: error: ") and err.count("\n") == 1, err
    assert fragment in err, err


def test_endpoint_accepts_zenoh_endpoints() -> None:
    for text in ("tcp/127.0.0.1:7447", "tls/[::1]:7447", "udp/robot-3.local:7447#iface=wlan0"):
        assert zenoh_endpoint(text, "--connect") == text
    with pytest.raises(UsageError, match=r"port in 1\.\.65535"):
        zenoh_endpoint("tcp/host:99999", "--connect")


def test_unreachable_endpoint_exits_1_with_one_line() -> None:
    (port,) = free_ports(1)
    r = semfleet("fleet", "status", "--connect", loopback_endpoint(port), "--fleet", "f")
    assert r.returncode == 1, (r.stdout, r.stderr)
    assert r.stderr.startswith(f"semfleet: error: cannot reach {loopback_endpoint(port)}: ")
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr


def test_nothing_answering_within_the_timeout_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    """A peer does not fail when nobody listens: it waits for the timeout, then says so."""
    (port,) = free_ports(1)
    argv = ["fleet", "stop", "--mode", "peer", "--timeout", "0.3"]
    assert cli.main([*argv, "--connect", loopback_endpoint(port), "--fleet", "quiet"]) == 1
    err = capsys.readouterr().err
    assert "no robot of fleet 'quiet' answered within 0.3 s" in err, err


# --------------------------------------------------------------------------- fake robots


class FakeRobot:
    """A robot's Zenoh presence only: its token, an answer to ``ctl/status`` (``estimate``) and,
    if ``obeys``, leaving on ``ctl/stop``."""

    def __init__(self, keys: Keys, robot: str, estimate: EstimateMessage | None, obeys: bool):
        (self.port,) = free_ports(1)
        self.keys, self.robot, self.obeys = keys, robot, obeys
        self.estimate = estimate
        self.transport = ZenohTransport(ZenohSettings(listen=(loopback_endpoint(self.port),)))
        self.control = Inbox(100)
        self.transport.subscribe(keys.ctl("**"), self.control)
        self.transport.declare_alive(keys.alive(robot))

    async def serve(self) -> None:
        await self.transport.open()
        while self.transport.is_open:
            await self.control.wait(0.1)
            for m in self.control.drain():
                order = decode_control(m.payload)
                if isinstance(order, Stop) and self.obeys:
                    await self.transport.close()
                    return
                if self.estimate is not None and m.key == self.keys.ctl("status"):
                    self.transport.publish(
                        self.keys.estimate(self.robot), encode_estimate(self.estimate)
                    )


def test_stop_reports_a_robot_that_ignores_it() -> None:
    keys = Keys("opfake")
    good, stubborn = FakeRobot(keys, "r1", None, True), FakeRobot(keys, "r9", None, False)

    async def scenario() -> tuple[list[str], list[str], float]:
        serving = [asyncio.create_task(f.serve()) for f in (good, stubborn)]
        await asyncio.sleep(0.2)
        eps = (loopback_endpoint(good.port), loopback_endpoint(stubborn.port))
        try:
            return await stop_fleet(session_settings(eps), keys, "test", timeout=2.0)
        finally:
            await stubborn.transport.close()
            await asyncio.gather(*serving)

    stopped, still, took = asyncio.run(scenario())
    assert stopped == ["r1"] and still == ["r9"], (stopped, still)
    assert took >= 2.0


def test_stop_progress_resends_and_waits_out_a_failover() -> None:
    p = StopProgress(sent=10.0)
    assert p.step(True, 10.2) == "wait"
    assert p.step(True, 10.5) == "resend"
    assert p.step(False, 10.6) == "wait"  # every token gone: the robot we reached stopped...
    assert p.step(True, 10.7) == "wait"  # ...and the failover shows one still there
    assert p.step(True, 11.0) == "resend"
    assert p.step(False, 11.1) == "wait"
    assert p.step(False, 12.0) == "wait"
    assert p.step(False, 12.1) == "done" and p.quiet_since == 11.1


def snapshot(
    weights: Sequence[float],
    classes: Sequence[Sequence[int]],
    robot_pose: Sequence[Sequence[float]],
    object_pose: Sequence[Sequence[Sequence[float]]],
    object_ids: Sequence[int],
    cov: Sequence[float] = (0.04, 0.01, 0.001),
) -> BeliefSnapshot:
    h, n = len(weights), len(object_ids)
    c = np.diag(cov)
    return BeliefSnapshot(
        tuple(object_ids),
        np.array(weights, float),
        np.array(classes, np.int64).reshape(h, n),
        np.array(robot_pose, float),
        np.tile(c, (h, 1, 1)),
        np.array(object_pose, float).reshape(h, n, 3),
        np.tile(c, (h, n, 1, 1)),
    )


# Three hypotheses over objects 5 and 8. Object 5 is class 1 in the heaviest (w = 0.4) but class
# 0 in the other two: its MAP class is 1, its marginals (0.6, 0.4). Object 8 is always class 0.
# The robot's yaws straddle ±π.
HYP = snapshot(
    [0.4, 0.35, 0.25],
    [[1, 0], [0, 0], [0, 0]],
    [[1.0, 2.0, math.pi - 0.1], [1.4, 2.0, -math.pi + 0.1], [1.4, 2.0, -math.pi + 0.1]],
    [
        [[3.0, 0.0, 0.0], [0.0, 5.0, 0.5]],
        [[3.0, 0.4, 0.0], [0.0, 5.0, 0.5]],
        [[3.0, 0.4, 0.0], [0.0, 5.0, 0.5]],
    ],
    [5, 8],
)


def test_watch_ends_on_sigterm_and_writes_what_it_saw(tmp_path: Path) -> None:
    keys = Keys("opsig")
    robot = FakeRobot(keys, "r7", EstimateMessage("r7", 3, {"distributed": HYP}, {"step": 3}), True)
    out = tmp_path / "out"

    async def scenario() -> tuple[int | None, bytes]:
        serving = asyncio.create_task(robot.serve())
        args = ["fleet", "watch", "--connect", loopback_endpoint(robot.port), "--fleet", "opsig"]
        watch = await asyncio.create_subprocess_exec(
            str(SEMFLEET), *args, "--out", str(out), stderr=asyncio.subprocess.PIPE
        )
        try:
            async with asyncio.timeout(30):
                while True:  # until the watch has asked for the estimate and got it
                    await asyncio.sleep(0.1)
                    if robot.control.received >= 1:
                        break
                await asyncio.sleep(0.5)
                watch.send_signal(signal.SIGTERM)
                _, stderr = await watch.communicate()
        finally:
            await robot.transport.close()
            await serving
        return watch.returncode, stderr

    code, stderr = asyncio.run(scenario())
    assert code == 0, stderr.decode()
    doc = json.loads((out / "estimates.json").read_text())
    entry = doc["robots"]["r7"]
    assert entry["k"] == 3 and entry["trail"][0][0] == 3 and entry["counters"] == {"step": 3}
    d = entry["beliefs"]["distributed"]
    assert [o["id"] for o in d["objects"]] == [5, 8] and d["hypotheses"] == 3
    assert (out / "map.png").read_bytes().startswith(PNG_MAGIC)


# --------------------------------------------------------------------------- the view


def test_mixture_moments_weighted_mean_circular_yaw_and_spread() -> None:
    pose, cov = mixture_moments(HYP.weights, HYP.robot_pose, HYP.robot_cov)
    assert_close(pose[:2], [0.4 * 1.0 + 0.6 * 1.4, 2.0])
    # the yaws straddle ±π: their mean is near π, where an arithmetic mean would put it near 0
    yaws = HYP.robot_pose[:, 2]
    assert_angles_close(pose[2], np.angle(np.sum(HYP.weights * np.exp(1j * yaws))))
    assert abs(abs(pose[2]) - math.pi) < 0.1
    # within: each body-frame (0.04, 0.01) turned by its yaw; between: the 0.4 m spread in x
    expected = np.diag([0.4 * 0.6 * 0.4**2, 0.0])
    for w, yaw in zip(HYP.weights, yaws, strict=True):
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        expected += w * rot @ np.diag([0.04, 0.01]) @ rot.T
    assert_close(cov, expected)
    _, cov90 = mixture_moments(
        np.ones(1), np.array([[0.0, 0.0, math.pi / 2]]), np.diag([0.04, 0.01, 0.001])[None]
    )
    assert_close(cov90, np.diag([0.01, 0.04]), atol=1e-12)


def test_estimates_doc_marginals_map_class_and_object_means() -> None:
    view = FleetView(Keys("f"))
    est = EstimateMessage("r1", 4, {"distributed": HYP}, {"step": 4})
    view.on_message(Message("semfleet/f/estimate/r1", encode_estimate(est)), now=1.0)
    doc = estimates_doc(view, watched_s=2.0)
    assert doc["classes_seen"] == 2
    objects = doc["robots"]["r1"]["beliefs"]["distributed"]["objects"]
    assert [o["id"] for o in objects] == [5, 8]
    assert_close(objects[0]["marginals"], [0.6, 0.4])
    assert_close(objects[1]["marginals"], [1.0, 0.0])
    assert [o["map_class"] for o in objects] == [1, 0]  # the heaviest hypothesis, not the marginal
    assert_close(objects[0]["pose"], [3.0, 0.6 * 0.4, 0.0])
    assert_close(objects[1]["pose"], [0.0, 5.0, 0.5])
    json.dumps(doc, allow_nan=False)


def _per_object(probs: Sequence[Sequence[float]], classes: Sequence[int]) -> BeliefSnapshot:
    """One hypothesis over objects 5 and 8 with per-object class marginals ``probs``."""
    one = snapshot(
        [1.0], [classes], [[1.0, 2.0, 0.0]], [[[3.0, 0.0, 0.0], [0.0, 5.0, 0.5]]], [5, 8]
    )
    return dataclasses.replace(one, class_probs=np.array(probs, float))


def test_estimates_doc_reads_per_object_class_marginals() -> None:
    """A belief with per-object class marginals: its marginals and its MAP classes (the argmax
    of each object's) come from ``class_probs``, not from its one hypothesis' classes (here said
    otherwise on purpose), and its M counts in ``classes_seen``; a realisation table beside it
    gets marginals of that many classes."""
    view = FleetView(Keys("f"))
    probs = [[0.2, 0.1, 0.7], [0.5, 0.3, 0.2]]
    per_object = _per_object(probs, [0, 1])
    for robot, beliefs in (("r1", {"distributed": per_object}), ("r2", {"distributed": HYP})):
        est = EstimateMessage(robot, 4, beliefs)
        view.on_message(Message(f"semfleet/f/estimate/{robot}", encode_estimate(est)), now=1.0)
    doc = estimates_doc(view, watched_s=2.0)
    assert doc["classes_seen"] == 3  # the classes held say 2
    objects = doc["robots"]["r1"]["beliefs"]["distributed"]["objects"]
    assert [o["marginals"] for o in objects] == probs
    assert [o["map_class"] for o in objects] == [2, 0]
    table = doc["robots"]["r2"]["beliefs"]["distributed"]["objects"]
    assert_close(table[0]["marginals"], [0.6, 0.4, 0.0])
    json.dumps(doc, allow_nan=False)


def test_estimates_doc_pads_per_object_marginals_of_fewer_classes() -> None:
    """Per-object marginals over M = 2 beside a belief that holds class 2: every class past the
    belief's own M has probability 0 in it."""
    view = FleetView(Keys("f"))
    three = snapshot(
        [1.0], [[2, 0]], [[1.0, 2.0, 0.0]], [[[3.0, 0.0, 0.0], [0.0, 5.0, 0.5]]], [5, 8]
    )
    for robot, snap in (("r1", _per_object([[0.9, 0.1], [0.4, 0.6]], [0, 1])), ("r2", three)):
        est = EstimateMessage(robot, 1, {"distributed": snap})
        view.on_message(Message(f"semfleet/f/estimate/{robot}", encode_estimate(est)), now=1.0)
    doc = estimates_doc(view, watched_s=1.0)
    assert doc["classes_seen"] == 3
    objects = doc["robots"]["r1"]["beliefs"]["distributed"]["objects"]
    assert [o["marginals"] for o in objects] == [[0.9, 0.1, 0.0], [0.4, 0.6, 0.0]]
    assert [o["map_class"] for o in objects] == [0, 1]


def test_fleet_view_tokens_latest_estimate_trail_and_bad_input() -> None:
    keys = Keys("f")
    view = FleetView(keys)

    def estimate(robot: str, k: int) -> bytes:
        return encode_estimate(EstimateMessage(robot, k, {"distributed": HYP}, {"step": k}))

    assert view.on_message(Message(keys.alive("r1"), b"", "alive"), 0.0)
    assert view.unanswered() == ["r1"]
    assert view.on_message(Message(keys.estimate("r1"), estimate("r1", 2)), 1.0)
    assert view.on_message(Message(keys.estimate("r1"), estimate("r1", 3)), 2.0)
    assert view.on_message(Message(keys.estimate("r1"), estimate("r1", 3)), 3.0)  # a status answer
    assert not view.on_message(Message(keys.estimate("r1"), estimate("r1", 1)), 4.0)  # overtaken
    state = view.robots["r1"]
    assert state.estimate is not None and state.estimate.k == 3 and state.received == 3.0
    assert [k for k, _, _ in state.trail] == [2, 3]
    assert_close(state.trail[0][1:], [1.24, 2.0])
    assert not view.on_message(Message(keys.estimate("r2"), estimate("r1", 5)), 5.0)  # spoofed
    assert not view.on_message(Message(keys.estimate("r2"), b"\xc1garbage"), 5.0)
    assert not view.on_message(Message("semfleet/other/estimate/r2", estimate("r2", 1)), 5.0)
    assert view.invalid == 2 and "r2" not in view.robots
    assert view.on_message(Message(keys.alive("r1"), b"", "gone"), 6.0)
    assert view.alive() == [] and view.answered() == ["r1"]


def test_fleet_status_says_how_far_each_fusion_is_behind_its_peers_steps() -> None:
    """r1 at step 9 holds r2's version 5 (r2 is at 8: 3 behind) and r3's 7 (r3's estimate says
    6: answered a little earlier, 0 behind); r2 holds r1's 9 (0); r3 says nothing of what it
    fused (an older agent) and r4, which r2 fused, never answered."""
    keys = Keys("f")
    view = FleetView(keys)
    for robot, k, fused in (
        ("r1", 9, {"r2": 5, "r3": 7}),
        ("r2", 8, {"r1": 9, "r4": 2}),
        ("r3", 6, None),
    ):
        est = EstimateMessage(robot, k, {"distributed": HYP}, {}, fused)
        view.on_message(Message(keys.estimate(robot), encode_estimate(est)), 1.0)
    assert fusion_behind(view) == {"r1": {"r2": 3, "r3": 0}, "r2": {"r1": 0}}
    doc = status_doc(view, 1.0, 0.5)
    by_robot = {r["robot"]: r for r in doc["robots"]}
    assert by_robot["r1"]["fused"] == {"r2": 5, "r3": 7}
    assert by_robot["r1"]["behind_steps"] == {"r2": 3, "r3": 0}
    assert by_robot["r3"]["fused"] is None and by_robot["r3"]["behind_steps"] is None
    assert behind_line(view) == (
        "fusion behind the peers' latest steps over 3 (robot, peer): median 0, max 3 (r1 of r2)"
    )
    json.dumps(doc, allow_nan=False)
    assert behind_line(FleetView(keys)) == ""


def test_fleet_status_shows_the_age_of_the_peers_information_from_holding_times() -> None:
    """Each robot reports the median and largest age of its fused peers' versions (counters);
    a robot that knows no age (an older agent, or none yet) is left out."""
    keys = Keys("f")
    view = FleetView(keys)
    for robot, aged, median, largest in (
        ("r1", 2, 510, 530),
        ("r2", 3, 620, 1040),
        ("r3", 0, 0, 0),
        ("r4", 1, 505, 505),
    ):
        counters = {"peers_aged": aged, "peer_age_median_ms": median, "peer_age_max_ms": largest}
        est = EstimateMessage(robot, 4, {"distributed": HYP}, counters)
        view.on_message(Message(keys.estimate(robot), encode_estimate(est)), 1.0)
    assert age_line(view) == (
        "age of the peers' information (holding times, transits excluded) on 3 robots: "
        "median 510 ms, max 1040 ms (r2)"
    )
    assert age_line(FleetView(keys)) == ""
    # A robot that says it aged peers but leaves the figures out (a hostile or broken agent).
    odd = EstimateMessage("r5", 4, {"distributed": HYP}, {"peers_aged": 2})
    view.on_message(Message(keys.estimate("r5"), encode_estimate(odd)), 1.0)
    assert age_line(view).startswith("age of the peers' information (holding times, transits ")
