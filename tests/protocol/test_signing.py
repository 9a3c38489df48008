"""Owner-signed slots (wire version 2, docs/wire.md "Signed slots", issue 13 item 2): a relay can
neither forge nor alter a slot; every changed byte of a slot fails; unsigned, unknown-owner and
wrongly signed slots are refused when the receiver has keys."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from estimator.summary import LocalSummary, Realisation, Xi
from protocol import codec
from protocol.codec import Limits, StackMessage, decode, encode, sign_slot
from protocol.errors import BadSignature, LocalProtocolError, RemoteProtocolError
from protocol.signing import admitted, digest, verify_digest
from protocol.stack import Slot, Stack

LIMITS = Limits(num_classes=3)
KEYS = {r: Ed25519PrivateKey.generate() for r in ("r1", "r2", "r3")}
PUBLIC = {r: k.public_key() for r, k in KEYS.items()}


def _slot(owner: str, stamp: int, seed: int) -> Slot:
    rng = np.random.default_rng(seed)
    n = 2
    reals = []
    for c in ((0, 1), (2, 1)):
        a = rng.normal(size=(3 * n, 3 * n))
        info = a @ a.T + 3 * np.eye(3 * n)
        lin = rng.uniform(-5, 5, (n, 3))
        lin[:, 2] = rng.uniform(-3, 3, n)
        reals.append(Realisation(c, float(rng.normal()), Xi(lin, info, rng.normal(size=3 * n))))
    return Slot(owner, stamp, LocalSummary((7, 12), tuple(reals)))


def _signed(owner: str, stamp: int = 41, seed: int = 0) -> Slot:
    return sign_slot(_slot(owner, stamp, seed), KEYS[owner], LIMITS)


ED25519_ORDER = 2**252 + 27742317777372353535851937790883648493  # ℓ, the group order


def test_a_signed_stack_verifies_and_a_relay_re_sends_the_owners_signature() -> None:
    stack = Stack((_signed("r1"), _signed("r2", 7, 1)))
    data = encode(StackMessage("r2", None, stack, 7), LIMITS)
    assert msgpack.unpackb(data)["v"] == 2
    received = decode(data, LIMITS, PUBLIC)
    # r3 relays what it received: re-encoded from the decoded slots, still the owners' signatures
    relayed = encode(StackMessage("r3", (1.0, 2.0), received.stack, 9), LIMITS)
    again = decode(relayed, LIMITS, PUBLIC)
    for a, b in zip(stack, again.stack, strict=True):
        assert (a.owner, a.stamp, a.signature) == (b.owner, b.stamp, b.signature)
    assert encode(StackMessage("r2", None, again.stack, 7), LIMITS) == data


def test_every_changed_byte_of_a_signed_slot_is_refused() -> None:
    data = encode(StackMessage("r2", None, Stack((_signed("r1"),)), 3), LIMITS)
    start = data.index(b"\xa5slots") + len(b"\xa5slots")
    for offset in range(start, len(data)):
        for flip in (0x01, 0x80):
            bad = bytearray(data)
            bad[offset] ^= flip
            with pytest.raises(RemoteProtocolError):
                decode(bytes(bad), LIMITS, PUBLIC)
    # without keys a changed number decodes (nothing to check it against): the keys do the work
    last = bytearray(data)
    last[data.rindex(b"\xa3eta") + 4 + 2 + 10] ^= 0x01  # inside the last realisation's η
    assert decode(bytes(last), LIMITS).stack.slots[0].owner == "r1"


def test_forged_relayed_and_unsigned_slots_are_refused_with_keys() -> None:
    genuine = _signed("r1")
    # r2 signs a slot of r1 with its own key; r2 bumps r1's stamp and keeps r1's signature
    forged = sign_slot(_slot("r1", 41, 0), KEYS["r2"], LIMITS)
    bumped = Slot("r1", 9_999_999, genuine.summary, 0, genuine.signature)
    unknown = sign_slot(_slot("r9", 1, 0), Ed25519PrivateKey.generate(), LIMITS)
    for slot, field in (
        (forged, "slots[0].sig"),
        (bumped, "slots[0].sig"),
        (unknown, "slots[0].owner"),
    ):
        data = encode(StackMessage("r2", None, Stack((slot,)), 3), LIMITS)
        with pytest.raises(BadSignature) as err:
            decode(data, LIMITS, PUBLIC)
        assert err.value.field == field
    unsigned = encode(StackMessage("r2", None, Stack((_slot("r1", 41, 0),)), 3), LIMITS)
    with pytest.raises(BadSignature, match="unsigned"):
        decode(unsigned, LIMITS, PUBLIC)
    decode(unsigned, LIMITS)  # a fleet without keys takes it
    empty = encode(StackMessage("r2", None, Stack(), 3), LIMITS)
    assert len(decode(empty, LIMITS, PUBLIC).stack) == 0  # nothing to sign: a lock-step round


def test_a_stamp_beyond_the_range_is_refused_before_any_signature() -> None:
    doc = msgpack.unpackb(encode(StackMessage("r2", None, Stack((_signed("r1"),)), 3), LIMITS))
    doc["slots"][0]["stamp"] = 2**63 - 1
    with pytest.raises(RemoteProtocolError):
        decode(msgpack.packb(doc), LIMITS, PUBLIC)
    doc["slots"][0]["stamp"] = 41
    doc["slots"][0]["epoch"] = 2**53
    with pytest.raises(RemoteProtocolError, match="epoch"):
        decode(msgpack.packb(doc), LIMITS, PUBLIC)


def test_the_epoch_is_signed_a_relay_cannot_move_a_slot_to_another_epoch() -> None:
    slot = sign_slot(dataclasses.replace(_slot("r1", 3, 0), epoch=1_764_000_000_000), KEYS["r1"])
    data = encode(StackMessage("r2", None, Stack((slot,)), 3), LIMITS)
    received = decode(data, LIMITS, PUBLIC).stack.by_owner()["r1"]
    assert received.version == (1_764_000_000_000, 3)
    doc = msgpack.unpackb(data)
    for epoch in (0, 1_764_000_000_001):  # back to no epoch, or one past: both forged
        doc["slots"][0]["epoch"] = epoch
        with pytest.raises(BadSignature, match="does not verify"):
            decode(msgpack.packb(doc), LIMITS, PUBLIC)
    # An unsigned fleet carries the epoch too (only when it is not 0): the same version arrives.
    unsigned = dataclasses.replace(slot, signature=None)
    doc = msgpack.unpackb(encode(StackMessage("r2", None, Stack((unsigned,)), 3), LIMITS))
    assert doc["v"] == 1 and doc["slots"][0]["epoch"] == 1_764_000_000_000
    assert decode(msgpack.packb(doc), LIMITS).stack.by_owner()["r1"].version == received.version
    plain = encode(StackMessage("r2", None, Stack((_slot("r1", 3, 0),)), 3), LIMITS)
    assert "epoch" not in msgpack.unpackb(plain)["slots"][0]


def test_a_stack_is_all_signed_or_all_unsigned() -> None:
    mixed = Stack((_signed("r1"), _slot("r2", 3, 1)))
    with pytest.raises(LocalProtocolError, match="signed and unsigned"):
        encode(StackMessage("r2", None, mixed, 3), LIMITS)


def test_verification_accepts_exactly_the_owners_signature_of_the_digest() -> None:
    """Signed by `cryptography` (OpenSSL), verified by ed25519-zebra: the same Ed25519. A malleated
    signature (S + ℓ, the same point equation), a truncated one, another key's and another
    digest's are refused."""
    key = Ed25519PrivateKey.generate()
    public = key.public_key()
    other = Ed25519PrivateKey.generate().public_key()
    for seed in range(3):
        d = digest(np.random.default_rng(seed).bytes(100 + seed))
        signature = key.sign(d)
        assert verify_digest(public, d, signature)
        assert not verify_digest(other, d, signature)
        assert not verify_digest(public, digest(d), signature)
        assert not verify_digest(public, d, signature[:-1])
        assert not verify_digest(public, d, signature + b"\0")
        s = int.from_bytes(signature[32:], "little") + ED25519_ORDER
        assert not verify_digest(public, d, signature[:32] + s.to_bytes(32, "little"))


# The eight points of small order (the identity, the point of order 2, two of order 4 and four of
# order 8) and a non-canonical encoding of the identity (y = p + 1).
SMALL_ORDER = [
    bytes.fromhex(h)
    for h in (
        "0100000000000000000000000000000000000000000000000000000000000000",
        "ecffffffffffffffffffffffffffffffffffffffffffffffffffffffffffff7f",
        "0000000000000000000000000000000000000000000000000000000000000000",
        "0000000000000000000000000000000000000000000000000000000000000080",
        "26e8958fc2b227b045c3f489f2ef98f0d5dfac05d3c63339b13802886d53fc05",
        "26e8958fc2b227b045c3f489f2ef98f0d5dfac05d3c63339b13802886d53fc85",
        "c7176a703d4dd84fba3c0b760d10670f2a2053fa2c39ccc64ec7fd7792ac037a",
        "c7176a703d4dd84fba3c0b760d10670f2a2053fa2c39ccc64ec7fd7792ac03fa",
        "eeffffffffffffffffffffffffffffffffffffffffffffffffffffffffffff7f",
    )
]


def test_a_key_of_small_order_verifies_nothing() -> None:
    """Under the cofactored check (ZIP 215) a key A of small order "verifies" the signature
    (R, 0) for every message when R is of small order too: [8]·0·B = [8]R + [8]hA = 0. The key
    is refused before the signature is looked at, whatever the message."""
    for seed in range(3):
        d = digest(np.random.default_rng(seed).bytes(50 + seed))
        for point in SMALL_ORDER:
            key = Ed25519PublicKey.from_public_bytes(point)
            for r in [*SMALL_ORDER[:2], point]:
                assert not verify_digest(key, d, r + bytes(32)), point.hex()
            assert not admitted(point)
    genuine = Ed25519PrivateKey.generate().public_key().public_bytes_raw()
    assert admitted(genuine) and not admitted(genuine[:31])


def test_every_signature_is_verified_before_any_body_is_read(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A forged second slot refuses the message before the first slot's numbers are parsed, and
    before a malformed body of the first slot could be reported instead."""
    read: list[str] = []
    unpack = codec._unpack
    monkeypatch.setattr(
        codec, "_unpack", lambda body, where: read.append(where) or unpack(body, where)
    )
    forged = sign_slot(_slot("r2", 5, 1), KEYS["r3"], LIMITS)
    data = encode(StackMessage("r3", None, Stack((_signed("r1"), forged)), 3), LIMITS)
    with pytest.raises(BadSignature) as err:
        decode(data, LIMITS, PUBLIC)
    assert err.value.field == "slots[1].sig" and read == []
    genuine = encode(StackMessage("r3", None, Stack((_signed("r1"), _signed("r2", 5, 1))), 3))
    assert len(decode(genuine, LIMITS, PUBLIC).stack) == 2
    assert sorted(set(read)) == ["slots[0]", "slots[1]"]
