"""Issue 13's targets: the gossip latency of a secure fleet (mutual TLS, access control, owner-
signed slots verified against the roster) against the same fleet without security, for the
paper's largest stack, measured in the same run; and the time to sign and to verify one slot.

Both paths are the agent's: Zenoh thread → loop → decode (with the roster's keys when secure) →
merge. The sessions of the secure path hold the identities of a fleet made by
:func:`deploy.fleet_init.init_fleet` (robot r1 publishes, robot r2 receives).
"""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from agents.node import RobotNode, Signing
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from bench import Result
from bench.bench_agents import ROUNDS, _latencies, _paper_stacks
from deploy.commands.scenario import model_text
from deploy.fleet_init import init_fleet, loopback_spec
from deploy.launch import free_ports
from deploy.study import belief_model, belief_rng
from protocol.codec import StackMessage, decode, encode, sign_slot
from protocol.signing import SigningKeys
from protocol.stack import Slot, Stack
from sim.loader import load_scenario

TARGET_RATIO = 1.3
TARGET_SLOT_MS = 0.2


def notes() -> list[str]:
    return []


def _key(folder: Path) -> Ed25519PrivateKey:
    key = serialization.load_pem_private_key((folder / "signing.key").read_bytes(), None)
    assert isinstance(key, Ed25519PrivateKey)
    return key


def _signed(blobs: list[bytes], keys: dict[str, Ed25519PrivateKey]) -> list[bytes]:
    """The same stacks with every slot signed by a fleet key (owners renamed to fleet robots)."""
    out = []
    for data in blobs:
        m = decode(data)
        slots = [
            sign_slot(Slot(f"r{i + 1}", s.stamp, s.summary), keys[f"r{i + 1}"])
            for i, s in enumerate(m.stack)
        ]
        out.append(encode(StackMessage("r1", m.position, Stack(tuple(slots)), m.step)))
    return out


def _secure_rows(tmp: Path) -> list[Result]:
    s = load_scenario("paper")
    blobs, _ = _paper_stacks(ROUNDS)
    owners = len(decode(blobs[0]).stack)
    robots = [f"r{i + 1}" for i in range(max(owners, 2))] + ["rx"]
    port = free_ports(1)[0]
    starts = {r: (0.0, 0.0, 0.0) for r in robots}
    folders = init_fleet(loopback_spec("bench", robots, "op", starts, model_text(s), port), tmp)
    keys = {r: _key(folders[r]) for r in robots}
    signed = _signed(blobs, keys)
    model = belief_model(s)

    def receiver(signing: Signing | None) -> RobotNode:
        return RobotNode("rx", (0.0, 0.0, 0.0), model, belief_rng(0, ["rx"]),
                         belief_rng(0, ["rx"]), signing=signing)  # fmt: skip

    rx_folder, r1_folder = folders["rx"], folders["r1"]
    rx_listen = f"tls/127.0.0.1:{port + robots.index('rx')}"
    publisher = ZenohTransport(
        ZenohSettings(config_file=r1_folder / "zenoh.json5",
                      extra={"listen/endpoints": [], "connect/endpoints": [rx_listen]})
    )  # fmt: skip
    subscriber = ZenohTransport(
        ZenohSettings(config_file=rx_folder / "zenoh.json5", extra={"connect/endpoints": []})
    )
    public = {r: k.public_key() for r, k in keys.items()}
    secure = asyncio.run(
        _latencies(signed, receiver(Signing(keys["rx"], public)), (publisher, subscriber), "r1")
    )
    plain = asyncio.run(_latencies(blobs, receiver(None), None, "r1"))
    secure_ms, plain_ms = statistics.median(secure[1]), statistics.median(plain[1])
    ratio = secure_ms / plain_ms
    met = "met" if ratio <= TARGET_RATIO else "NOT met"
    rows = [
        Result(
            "secure gossip latency: put → verified and merged",
            ROUNDS,
            secure_ms,
            baseline_ms=plain_ms,
            note=f"median; baseline = the same stack unsigned over plain TCP, same run; "
            f"{len(signed[0]):,} bytes, {owners} slots; secure/plain {ratio:.2f} (target ≤ "
            f"{TARGET_RATIO}) {met}; decode with verification {statistics.median(secure[2]):.3f} "
            f"ms vs {statistics.median(plain[2]):.3f}",
        )
    ]
    return rows + _slot_rows(decode(signed[0]).stack, public, keys)


def _slot_rows(
    stack: Stack, public: SigningKeys, keys: dict[str, Ed25519PrivateKey]
) -> list[Result]:
    """Signing and verifying each slot of the stack on its own (median of 20 each)."""
    rows = []
    for slot in stack:
        unsigned = Slot(slot.owner, slot.stamp, slot.summary)
        one = encode(StackMessage("r1", None, Stack((slot,)), 0))
        plain = encode(StackMessage("r1", None, Stack((unsigned,)), 0))
        sign_ms = _median_ms(partial(sign_slot, unsigned, keys[slot.owner]))
        encode_ms = _median_ms(partial(encode, StackMessage("r1", None, Stack((unsigned,)), 0)))
        verify_ms = _median_ms(partial(decode, one, None, public))
        decode_ms = _median_ms(partial(decode, plain))
        sign_cost, verify_cost = sign_ms - encode_ms, verify_ms - decode_ms
        met = "met" if max(sign_cost, verify_cost) < TARGET_SLOT_MS else "NOT met"
        rows.append(
            Result(
                f"sign + verify one slot ({slot.owner})",
                1,
                sign_cost + verify_cost,
                note=f"{len(one):,} bytes: signing adds {sign_cost:.3f} ms to encoding "
                f"({encode_ms:.3f}), verifying {verify_cost:.3f} ms to decoding "
                f"({decode_ms:.3f}); target each < {TARGET_SLOT_MS} ms {met}",
            )
        )
    return rows


def _median_ms(fn: Callable[[], object]) -> float:
    fn()
    times = []
    for _ in range(20):
        t = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t))
    return float(np.median(times))


def run() -> list[Result]:
    with tempfile.TemporaryDirectory() as d:
        return _secure_rows(Path(d) / "fleet")
