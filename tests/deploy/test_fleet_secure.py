"""A fleet made by `semfleet fleet init` (issue 13, items 1–2): a real agent process started from
its files, real Zenoh sessions over mutual TLS on loopback, owner-signed slots.

An uncertified session and a session certified by another fleet's CA reach nothing; robot r2's
own certificate can put on its own stack (the positive control: r1 counts those puts) but not on
r1's stack, r1's frames or ``ctl/**``; the operator's certificate can ask for status and stop the
agent.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from agents.control import Status, Stop, encode_control
from agents.transport.base import Inbox, Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.cli.commands.scenario import model_text
from deploy.launch import free_ports
from deploy.operator.fleet_init import FleetSpec, init_fleet, loopback_spec
from estimator.summary import LocalSummary, ObjectClasses, Xi
from protocol.codec import Limits, StackMessage, decode, encode, sign_slot
from protocol.stack import Slot, Stack
from sim.loader import load_scenario
from tests.deploy.secure_helpers import ask_status, identity_settings

pytestmark = pytest.mark.slow

FLEET = "vault"
KEYS = Keys(FLEET)
ROBOTS = ("r1", "r2", "r3")
GARBAGE = b"\x93not a stack"
PUTS = 5


def _spec(port: int) -> FleetSpec:
    s = load_scenario("paper")
    starts = {r: tuple(float(v) for v in s.robot(r).start) for r in ROBOTS}
    return loopback_spec(FLEET, ROBOTS, "op", starts, model_text(s), port)  # type: ignore[arg-type]


@pytest.fixture
def fleet(tmp_path: Path):  # type: ignore[no-untyped-def]
    ports = free_ports(4)
    folders = init_fleet(_spec(ports[0]), tmp_path / "fleet")
    other = init_fleet(_spec(ports[0]), tmp_path / "other")  # same names, another CA
    log = open(tmp_path / "r1.log", "wb")  # noqa: SIM115 — closed below
    proc = subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", "agent", "--robot", "r1", "--config",
         str(folders["r1"] / "agent.toml")],
        stdout=log,
        stderr=subprocess.STDOUT,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )  # fmt: skip
    try:
        yield folders, other, f"tls/127.0.0.1:{ports[0]}", proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        log.close()


def _session(folder: Path, endpoint: str) -> ZenohTransport:
    return ZenohTransport(identity_settings(folder, endpoint))


async def _put_repeatedly(session: ZenohTransport, puts: list[tuple[str, bytes]]) -> None:
    for _ in range(PUTS):
        for key, payload in puts:
            session.publish(key, payload)
        await asyncio.sleep(0.2)


def test_only_the_owners_identity_puts_on_its_keys_and_only_the_operator_controls(
    fleet,  # type: ignore[no-untyped-def]
) -> None:
    folders, other, endpoint, proc = fleet

    async def scenario() -> None:
        operator = _session(folders["op"], endpoint)
        estimates = Inbox(64)
        operator.subscribe(KEYS.estimate("r1"), estimates)
        await operator.open()
        before = (await ask_status(operator, estimates, KEYS)).counters
        attacks = {
            "r2": _session(folders["r2"], endpoint),
            "foreign CA": _session(other["r2"], endpoint),
            "uncertified": ZenohTransport(
                ZenohSettings(connect=("tcp" + endpoint[3:],), gossip=False)
            ),
        }
        for session in attacks.values():
            await session.open()
        await asyncio.sleep(1.5)  # let r1's subscriptions reach the certified sessions
        forged = [
            (KEYS.stack("r1"), GARBAGE),
            (KEYS.stack_to("r3", "r1"), GARBAGE),  # a push as if from r3
            (KEYS.frames("r1"), GARBAGE),
            (KEYS.ctl("stop"), encode_control(Stop("attack"))),
            (KEYS.ctl("status"), encode_control(Status())),
        ]
        own = [(KEYS.stack("r2"), GARBAGE), (KEYS.stack_to("r2", "r1"), GARBAGE)]
        await asyncio.gather(
            _put_repeatedly(attacks["r2"], [*forged, *own]),
            _put_repeatedly(attacks["foreign CA"], [*forged, *own]),
            _put_repeatedly(attacks["uncertified"], [*forged, *own]),
        )
        await asyncio.sleep(1.0)
        assert proc.poll() is None, "an attacker's ctl/stop stopped the agent"
        after = (await ask_status(operator, estimates, KEYS)).counters
        for session in attacks.values():
            await session.close()
        # r2's puts on its own stack and its own pushes to r1 arrive (so its link works) and
        # are counted as invalid; nothing else of any attacker reaches r1.
        assert after["stacks_invalid"] - before["stacks_invalid"] == 2 * PUTS
        assert after["stacks_received"] - before["stacks_received"] == 2 * PUTS
        for name in ("frames_invalid", "frames_processed", "control_invalid"):
            assert after[name] == before[name], name
        # status requests: the operator's only (at least the two above), never an attacker's 15
        assert after["status_requests"] - before["status_requests"] < PUTS
        operator.publish(KEYS.ctl("stop"), encode_control(Stop("test")))
        await asyncio.to_thread(proc.wait, 20)
        await operator.close()

    asyncio.run(scenario())
    assert proc.returncode == 0


def _slot_of(owner: str, stamp: int) -> Slot:
    info = np.eye(3) * 4.0
    xi = Xi(np.array([[1.0, 2.0, 0.3]]), info, np.zeros(3))
    return Slot(owner, stamp, LocalSummary((900,), (), ObjectClasses(np.array([[0.0, -0.2]]), xi)))


def _signing_key(folder: Path) -> Ed25519PrivateKey:
    key = serialization.load_pem_private_key((folder / "signing.key").read_bytes(), None)
    assert isinstance(key, Ed25519PrivateKey)
    return key


def test_a_relay_cannot_forge_or_alter_a_slot_and_a_sender_must_be_its_key(
    fleet,  # type: ignore[no-untyped-def]
) -> None:
    folders, _, endpoint, proc = fleet
    limits = Limits(num_classes=2)
    genuine = sign_slot(_slot_of("r3", 4), _signing_key(folders["r3"]), limits)
    altered = Slot("r3", 5, genuine.summary, 0, genuine.signature)  # stamp bumped by the relay
    relayed = encode(StackMessage("r2", None, Stack((genuine,)), 4), limits)
    tampered = encode(StackMessage("r2", None, Stack((altered,)), 4), limits)
    unsigned = encode(StackMessage("r2", None, Stack((_slot_of("r2", 4),)), 4), limits)
    misaddressed = encode(StackMessage("r3", None, Stack((genuine,)), 4), limits)
    keys = {r: _signing_key(folders[r]).public_key() for r in ROBOTS}

    async def scenario() -> None:
        operator = _session(folders["op"], endpoint)
        estimates, stacks = Inbox(64), Inbox(64)
        operator.subscribe(KEYS.estimate("r1"), estimates)
        operator.subscribe(KEYS.stack("r1"), stacks)
        await operator.open()
        before = (await ask_status(operator, estimates, KEYS)).counters
        relay = _session(folders["r2"], endpoint)
        await relay.open()
        await asyncio.sleep(1.5)
        await _put_repeatedly(relay, [(KEYS.stack("r2"), tampered), (KEYS.stack("r2"), unsigned),
                                      (KEYS.stack("r2"), misaddressed)])  # fmt: skip
        await _put_repeatedly(relay, [(KEYS.stack("r2"), relayed)])
        await asyncio.sleep(1.0)
        after = (await ask_status(operator, estimates, KEYS)).counters
        assert after["stacks_badly_signed"] - before["stacks_badly_signed"] == 2 * PUTS
        assert after["stacks_misaddressed"] - before["stacks_misaddressed"] == PUTS
        assert after["stacks_merged"] - before["stacks_merged"] == 1  # the genuine relay, once
        # r1 now relays r3's slot with r3's signature, and signs its own (none yet: no frames).
        # Delta gossip: r1 sends a slot to a peer whose digest lacks it — r2 says it holds nothing.
        asking = encode(StackMessage("r2", None, Stack(), 4, have={}), limits)
        async with asyncio.timeout(20):
            while True:
                relay.publish(KEYS.stack("r2"), asking)
                if not await stacks.wait(0.5):
                    continue
                found = [decode(m.payload, limits, keys) for m in stacks.drain()]
                with_r3 = [m for m in found if m.stack.by_owner().get("r3") is not None]
                if with_r3:
                    message = with_r3[0]
                    break
        assert message.sender == "r1"
        assert message.stack.by_owner()["r3"].signature == genuine.signature
        await relay.close()
        operator.publish(KEYS.ctl("stop"), encode_control(Stop("test")))
        await asyncio.to_thread(proc.wait, 20)
        await operator.close()

    asyncio.run(scenario())
    assert proc.returncode == 0
