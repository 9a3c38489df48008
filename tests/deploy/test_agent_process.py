"""A real agent process under every bad input of issue 11: it keeps running, counts each input,
stays under a stated memory bound, never holds its event loop for more than 200 ms, and a
restart afterwards replays its journal to the very belief it had. A step that raises is rolled
back and quarantined; SIGKILL and restart do not crash-loop.

One agent ``r1`` (realtime, journal, roster r1–r3) on a loopback Zenoh port; the test's own
sessions feed it truth-less frames (``RobotLink``, as a robot's perception would) and attack it.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import pytest

from agents.control import Status, encode_control
from agents.journal import read_quarantine
from agents.perception import RobotLink
from agents.transport.base import Inbox, Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport, loopback_endpoint
from deploy.launch import free_ports, write_agent_config
from estimator.models import Detection, SensorFrame
from estimator.summary import LocalSummary, ObjectClasses
from estimator.xi import Xi
from protocol.codec import Limits, StackMessage, encode
from protocol.estimate import EstimateMessage, decode_estimate
from protocol.stack import Slot, Stack
from sim.loader import load_scenario
from sim.robot_model import dump_robot_model
from sim.sensors import Simulator

ROOT = Path(__file__).resolve().parents[2]
BIG_LIMITS = Limits(num_classes=64)
SCENARIO = load_scenario("paper")
SEED = 11
FLEET = "hostile"
KEYS = Keys(FLEET)
MEMORY_BOUND_MB = 1200  # peak RSS of the agent through every attack (idle: ~300 MB)
LOOP_HOLD_S = 0.2
BLOATED, BLOATED_GROWTH_MB = 6, 12.0  # refused large versions; RSS growth from the 2nd to the last
DELIVERY_S = 30.0  # how long an attack's messages may take to reach the agent and be counted
RESEND_S = 5.0  # an attack not counted yet is sent again after this long

pytestmark = pytest.mark.slow


class AgentProcess:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.port = free_ports(1)[0]
        (tmp / "model.toml").write_text(dump_robot_model(SCENARIO.robot_model()), "utf-8")
        self.config = tmp / "r1.toml"
        write_agent_config(
            self.config,
            {
                "fleet": FLEET,
                "model": "model.toml",
                "start": [float(v) for v in SCENARIO.robot("r1").start],
                "roster": ["r1", "r2", "r3"],
                "seed": SEED,
                "mode": "realtime",
                "gossip_period": 0.2,
                "journal": "journal/r1.log",
            },
            {"listen": [loopback_endpoint(self.port)], "gossip": False},
        )
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self) -> None:
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        log = open(self.tmp / f"agent-{self.starts}.log", "wb")  # noqa: SIM115 — outlives this call
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "deploy.cli",
                "agent",
                "--robot",
                "r1",
                "--config",
                str(self.config),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            env=env,
        )
        self.starts += 1

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def peak_rss_mb(self) -> float:
        return self._status_mb("VmHWM:")

    def rss_mb(self) -> float:
        return self._status_mb("VmRSS:")

    def _status_mb(self, field: str) -> float:
        assert self.proc is not None
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) / 1024
        raise AssertionError(f"no {field}")

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        if self.alive():
            assert self.proc is not None
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _settings(port: int) -> ZenohSettings:
    return ZenohSettings(connect=(loopback_endpoint(port),), gossip=False)


class Observer:
    """The test's own session: attacks, asks for status and reads the estimates."""

    def __init__(self, port: int) -> None:
        self.transport = ZenohTransport(_settings(port))
        self.estimates = Inbox(256)
        self.transport.subscribe(KEYS.estimate("r1"), self.estimates)

    async def status(self, k: int | None = None) -> EstimateMessage:
        """The agent's estimate with its counters of now (at step ``k`` if given)."""
        async with asyncio.timeout(90):
            while True:
                self.transport.publish(KEYS.ctl("status"), encode_control(Status()))
                try:
                    m = await asyncio.wait_for(self.estimates.get(), 1.0)
                except TimeoutError:
                    continue
                est = decode_estimate(m.payload)
                if k is None or est.k == k:
                    return est

    async def until_step(self, k: int) -> EstimateMessage:
        async with asyncio.timeout(120):
            while True:
                est = await self.status()
                if est.k >= k:
                    return est
                await asyncio.sleep(0.2)


# -- forged stacks ---------------------------------------------------------------------------


def _f64(values: np.ndarray) -> bytes:
    return np.ascontiguousarray(values, dtype="<f8").tobytes()


def _real(classes: list[int], phi: float, lin: np.ndarray, info: np.ndarray) -> dict[str, object]:
    iu = np.triu_indices(info.shape[0])
    return {
        "c": bytes(classes),
        "phi": phi,
        "lin": _f64(lin),
        "info": _f64(info[iu]),
        "eta": _f64(np.zeros(info.shape[0])),
    }


def _stack(sender: str, slots: list[dict[str, object]], k: int = 1) -> bytes:
    doc = {"v": 1, "type": "stack", "sender": sender, "k": k, "pos": None, "slots": slots}
    return bytes(msgpack.packb(doc, use_bin_type=True))


def _slot(
    owner: str, stamp: int, ids: list[int], reals: list[dict[str, object]]
) -> dict[str, object]:
    return {"owner": owner, "stamp": stamp, "objects": ids, "real": reals}


def indefinite_slot() -> bytes:
    """Λ = diag(1e12, 1e12, −500): indefinite, but within 1e-9 of PSD relative to its scale."""
    info = np.diag([1e12, 1e12, -500.0])
    return _stack("r2", [_slot("r2", 5, [901], [_real([0], 0.0, np.zeros((1, 3)), info)])])


def overflowing_phi() -> bytes:
    info = np.eye(3)
    reals = [_real([0], 1.7e308, np.zeros((1, 3)), info)]
    slots = [_slot(o, 6, [902 + i], reals) for i, o in enumerate(("r2", "r3"))]
    return _stack("r2", slots)


def wide_join() -> bytes:
    """3 slots × 1024 realisations, one new object each (0.4 MB)."""
    info = np.eye(3) * 4.0
    slots = []
    for i, owner in enumerate(("r2", "r3", "r2x")):
        reals = [
            _real([c % 2], -float(c) * 1e-3, np.array([[1.0 + i, 2.0, 0.0]]), info)
            for c in range(1024)
        ]
        slots.append(_slot(owner, 7, [910 + i], reals))
    return _stack("r2", slots)


def huge_stack() -> bytes:
    """A 28 MB stack: one slot, many objects, dense Λ."""
    n = 512
    info = np.eye(3 * n)
    reals = [_real([0] * n, 0.0, np.zeros((n, 3)), info) for _ in range(3)]
    return _stack("r3", [_slot("r3", 8, list(range(1000, 1000 + n)), reals)])


def bloated_stack(stamp: int) -> bytes:
    """r3's own slot at ``stamp``, 9.4 MB on the wire: 512 objects, a dense ξ of 10⁶·I, far
    beyond what ``stamp`` steps of detections can give, so the belief gate refuses it after
    decoding it whole (finding 4 of issue 43: refused slots kept hundreds of MB)."""
    n = 512
    xi = Xi(np.tile([1.0, 1.0, 0.0], (n, 1)), 1e6 * np.eye(3 * n), np.zeros(3 * n))
    phi = np.zeros((n, SCENARIO.num_classes))
    summary = LocalSummary(tuple(range(3000, 3000 + n)), (), ObjectClasses(phi, xi))
    slot = Slot("r3", stamp, summary)
    return encode(StackMessage("r3", None, Stack((slot,)), stamp), BIG_LIMITS)


def many_owners() -> bytes:
    info = np.eye(3)
    reals = [_real([0], 0.0, np.array([[1.0, 1.0, 0.0]]), info)]
    return _stack("r2", [_slot(f"x{i}", 1, [2000 + i], reals) for i in range(64)])


REFUSED = ("stacks_invalid", "slots_rejected", "slots_refused")
# For each attack, counters of which at least ``n`` more must be counted after it.
EXPECTED: dict[str, tuple[tuple[str, ...], int]] = {
    "indefinite Λ": (REFUSED, 1),
    "log φ 1.7e308": (REFUSED, 1),
    "3 × 1024 realisations": (("slots_foreign",), 1),  # and the r2, r3 slots fused, bounded
    "28 MB stack": (REFUSED, 1),
    "64 foreign owners": (("slots_foreign",), 64),
    "5000 ctl/step": (("orders_ahead",), 4000),
    "9.8 MB ctl/step": (("control_invalid", "inbox_dropped"), 1),
    "400 × 1 MB puts": (("stacks_invalid", "inbox_dropped"), 100),
}
ATTACKS: dict[str, Callable[[], list[tuple[str, bytes]]]] = {
    "indefinite Λ": lambda: [(KEYS.stack("r2"), indefinite_slot())],
    "log φ 1.7e308": lambda: [(KEYS.stack("r2"), overflowing_phi())],
    "3 × 1024 realisations": lambda: [(KEYS.stack("r2"), wide_join())],
    "28 MB stack": lambda: [(KEYS.stack("r3"), huge_stack())],
    "64 foreign owners": lambda: [(KEYS.stack("r2"), many_owners())],
    "5000 ctl/step": lambda: [(KEYS.ctl("step"), encode_control_raw(k)) for k in range(10, 5010)],
    "9.8 MB ctl/step": lambda: [(KEYS.ctl("step"), big_control())],
    "400 × 1 MB puts": lambda: [(KEYS.stack("r2"), os.urandom(1 << 20)) for _ in range(400)],
}


def encode_control_raw(k: int) -> bytes:
    return bytes(msgpack.packb({"type": "step", "k": k, "links": {"r1": ["r2"]}}))


def big_control() -> bytes:
    links = {f"r{i}": [f"s{j}" for j in range(200)] for i in range(5000)}
    return bytes(msgpack.packb({"type": "step", "k": 3, "links": links}))


async def _publish_until_step(
    link: RobotLink, observer: Observer, frame: SensorFrame
) -> EstimateMessage:
    """Publish ``frame`` until the agent has made its step, again every RESEND_S as a robot's
    perception would go on publishing: a put made while a restarted agent's subscription is
    still being declared reaches no one (seen in 2 of 5 runs on a loaded machine: the agent at
    step 0 with 0 bytes received for 2 minutes)."""
    async with asyncio.timeout(120):
        while True:
            link.publish_frame(frame)
            deadline = time.monotonic() + RESEND_S
            while time.monotonic() < deadline:
                est = await observer.status()
                if est.k >= frame.k:
                    return est
                await asyncio.sleep(0.2)


def _poisoned(frame: SensorFrame) -> SensorFrame:
    m = SCENARIO.num_classes
    det = Detection(999, np.array([1.0, 0.0, 0.0]), -1e300 * np.ones(m))
    return SensorFrame(
        frame.robot, frame.k, frame.odometry, (*frame.detections, det), frame.true_pose
    )


def test_a_real_agent_survives_every_bad_input_and_replays_to_the_same_belief(
    tmp_path: Path,
) -> None:
    frames = Simulator(SCENARIO, SEED).all_frames()["r1"]
    agent = AgentProcess(tmp_path)
    agent.start()
    report: dict[str, tuple[float, float]] = {}
    try:
        asyncio.run(_attack(agent, frames, report))
    finally:
        agent.stop()
    for name, (hold, rss) in report.items():
        print(f"{name:24s} loop hold {1e3 * hold:6.1f} ms   peak RSS {rss:6.0f} MB")


async def _attack(
    agent: AgentProcess, frames: list[SensorFrame], report: dict[str, tuple[float, float]]
) -> None:
    observer = Observer(agent.port)
    async with RobotLink("r1", FLEET, _settings(agent.port)) as link:
        await observer.transport.open()
        try:
            await asyncio.wait_for(link.wait_for_agent(), 60)
            for f in frames[:5]:
                link.publish_frame(f)
            await observer.until_step(5)
            k = 5
            est = await observer.status(5)
            rss_before = agent.rss_mb()
            for name, make in ATTACKS.items():
                counted = est.counters
                for key, payload in make():
                    observer.transport.publish(key, payload)
                    await asyncio.sleep(0)
                await asyncio.sleep(1.0)
                k += 1
                link.publish_frame(frames[k - 1])  # and the agent still steps
                est = await observer.until_step(k)
                names, n = EXPECTED[name]
                # A 28 MB put can still be on its way when the frame (another key) has arrived,
                # or be lost by the attacker's own session (its publishers drop under congestion:
                # seen twice in loaded CI runs, the agent's bytes_received +0 after 30 s): the
                # counters are read again until they show the attack, the attack is sent again
                # every RESEND_S as an attacker would, until the delivery deadline passes.
                deadline = time.monotonic() + DELIVERY_S
                resend = time.monotonic() + RESEND_S
                while sum(est.counters[c] - counted[c] for c in names) < n:
                    if time.monotonic() > deadline:
                        break
                    if time.monotonic() > resend:
                        for key, payload in make():
                            observer.transport.publish(key, payload)
                            await asyncio.sleep(0)
                        resend = time.monotonic() + RESEND_S
                    await asyncio.sleep(0.5)
                    est = await observer.status()
                assert agent.alive(), name
                report[name] = (est.counters["loop_lag_max_us"] / 1e6, agent.peak_rss_mb())
                print(f"{name}: RSS {agent.rss_mb():.0f} MB (before the attacks {rss_before:.0f})")
                more = sum(est.counters[c] - counted[c] for c in names)
                assert more >= n, (name, {c: est.counters[c] - counted[c] for c in est.counters})
            # Finding 4 of issue 43: version after version of a large slot refused after decoding
            # leaves nothing behind. RSS settles at what the transport keeps of the largest
            # messages it has carried (a plain Zenoh subscriber, nothing decoded: 24 → 107 MB
            # over 28 MB puts, flat from the third); each refused version held would add 10 MB.
            held = []
            for v in range(BLOATED):
                refused = sum(est.counters[c] for c in REFUSED)
                payload = bloated_stack(100 + v)
                deadline = time.monotonic() + DELIVERY_S
                while sum(est.counters[c] for c in REFUSED) == refused:
                    assert time.monotonic() < deadline, est.counters
                    observer.transport.publish(KEYS.stack("r3"), payload)
                    await asyncio.sleep(1.0)
                    est = await observer.status()
                held.append(agent.rss_mb())
            del payload
            print(f"RSS after each refused 9.4 MB version: {held} MB")
            assert held[-1] - held[1] <= BLOATED_GROWTH_MB, held
            c = est.counters
            assert c["loop_lag_max_us"] <= 1e6 * LOOP_HOLD_S, c
            assert agent.peak_rss_mb() <= MEMORY_BOUND_MB
            assert c["steps_failed"] == 0, c  # every attack was refused before any step
            # A step that raises: rolled back, quarantined, taken on its odometry.
            k += 1
            link.publish_frame(_poisoned(frames[k - 1]))
            est = await observer.until_step(k)
            assert est.counters["frames_quarantined"] == 1, est.counters
            before = est
            # SIGKILL, restart: the journal replays to the same belief, no crash loop.
            agent.kill()
            agent.start()
            await asyncio.wait_for(link.wait_for_agent(), 60)
            observer.estimates.drain()  # answers of the killed process
            after = await observer.status(k)
            assert after.counters["replayed_frames"] == k
            for belief in ("distributed", "local"):
                a, b = before.beliefs[belief], after.beliefs[belief]
                assert a.object_ids == b.object_ids
                np.testing.assert_array_equal(a.weights, b.weights)
                np.testing.assert_array_equal(a.object_pose, b.object_pose)
            k += 1
            link.publish_frame(frames[k - 1])
            await observer.until_step(k)
            assert agent.alive()
            # A flipped byte in the journal's header (issue 43, finding 7): the journal is moved
            # aside with the time in its name, and the agent starts again with an empty one.
            agent.kill()
            journal = agent.tmp / "journal" / "r1.log"
            damaged = bytearray(journal.read_bytes())
            damaged[12] ^= 0x01
            journal.write_bytes(bytes(damaged))
            agent.start()
            await asyncio.wait_for(link.wait_for_agent(), 60)
            observer.estimates.drain()
            k += 1  # its frames 1…k − 1 come again from the link, asked for with ctl/need
            fresh = await _publish_until_step(link, observer, frames[k - 1])
            assert agent.alive() and fresh.counters["replayed_frames"] == 0
            (moved,) = journal.parent.glob("r1.log.bad-header-*")
            assert moved.read_bytes() == bytes(damaged)
            logged = (agent.tmp / f"agent-{agent.starts - 1}.log").read_text()
            assert logged.count("starting an empty journal") == 1
        finally:
            await observer.transport.close()
    quarantined = read_quarantine(agent.tmp / "journal" / "r1.log.quarantine")
    # The step that raised, then again in the agent that started empty (the link sent it again).
    assert [q.kind for q in quarantined] == ["frame", "frame"]
