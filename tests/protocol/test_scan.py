"""Decoding only what is new (docs/wire.md): a message is scanned without its slot bodies, a body
is parsed, validated and verified only for a version the receiver wants, a signature is checked
over the bytes as received, and a decoded slot is re-sent as those very bytes."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from protocol.codec import StackMessage, decode, encode, sign_slot, with_wire
from protocol.errors import (
    BadSignature,
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    RemoteProtocolError,
)
from protocol.scan import BODY, SlotFrame, scan
from protocol.signing import canonical_bytes, digest, digest_of_parts
from protocol.stack import Stack
from tests.protocol.test_signing import KEYS, LIMITS, PUBLIC, _slot


def _message(signed: bool = False) -> bytes:
    slots = [_slot(r, 3 + i, i) for i, r in enumerate(("r1", "r2", "r3"))]
    if signed:
        slots = [sign_slot(s, KEYS[s.owner], LIMITS) for s in slots]
    return encode(StackMessage("r2", (1.0, -2.0), Stack(tuple(slots)), 9), LIMITS)


def _unscanned(doc: object, data: bytes) -> object:
    """``scan``'s document with every frame unpacked again: what ``unpackb`` gives."""
    if isinstance(doc, dict) and isinstance(doc.get("slots"), list):
        doc = dict(doc)
        doc["slots"] = [
            msgpack.unpackb(data[f.start : f.end], raw=False) if isinstance(f, SlotFrame) else f
            for f in doc["slots"]
        ]
    return doc


@pytest.mark.parametrize("signed", [False, True])
def test_scan_locates_every_slot_and_body_of_a_message(signed: bool) -> None:
    data = _message(signed)
    doc = scan(data)
    assert _unscanned(doc, data) == msgpack.unpackb(data, raw=False)
    for frame in doc["slots"]:
        assert frame.fields["objects"] is BODY and frame.fields["real"] is BODY
        a, b = frame.spans["real"]
        whole = msgpack.unpackb(data[frame.start : frame.end], raw=False)
        assert msgpack.unpackb(data[a:b], raw=False) == whole["real"]
    for bad in (data[:-1], data + b"\x00", b"\x81\xa1v\xc1"):
        with pytest.raises(Exception):  # noqa: B017 — decode turns each into MalformedMessage
            scan(bad)


def test_a_slot_version_not_wanted_is_neither_parsed_nor_validated() -> None:
    data = _message()
    doc = msgpack.unpackb(data, raw=False)
    lin = np.frombuffer(doc["slots"][0]["real"][0]["lin"], "<f8").copy()
    lin[0] = np.nan  # r1's body is invalid
    doc["slots"][0]["real"][0]["lin"] = lin.tobytes()
    bad = bytes(msgpack.packb(doc, use_bin_type=True))
    with pytest.raises(InvalidValue, match="non-finite"):
        decode(bad, LIMITS)
    skip_r1 = decode(bad, LIMITS, wanted=lambda owner, epoch, stamp: owner != "r1")
    assert skip_r1.skipped == ("r1",) and [s.owner for s in skip_r1.stack] == ["r2", "r3"]
    with pytest.raises(InvalidValue):
        decode(bad, LIMITS, wanted=lambda owner, epoch, stamp: stamp == 3)  # r1's stamp
    # The header of a skipped slot is still checked: duplicate owners are refused.
    doc["slots"][1]["owner"] = "r1"
    twice = bytes(msgpack.packb(doc, use_bin_type=True))
    with pytest.raises(InvalidValue, match="duplicate owners"):
        decode(twice, LIMITS, wanted=lambda owner, epoch, stamp: False)


def test_signatures_are_checked_over_the_bytes_as_received() -> None:
    slot = sign_slot(_slot("r1", 5, 0), KEYS["r1"], LIMITS)
    data = encode(StackMessage("r2", None, Stack((slot,)), 5), LIMITS)
    frame = scan(data)["slots"][0]
    (oa, ob), (ra, rb) = frame.spans["objects"], frame.spans["real"]
    wire = msgpack.unpackb(data, raw=False)["slots"][0]
    canonical = canonical_bytes("r1", 0, 5, wire["objects"], wire["real"])
    assert digest_of_parts("r1", 0, 5, data[oa:ob], data[ra:rb]) == digest(canonical)
    assert digest_of_parts("r1", 0, 6, data[oa:ob], data[ra:rb]) != digest(canonical)
    decode(data, LIMITS, PUBLIC)
    # A body re-encoded in another (valid msgpack) form is not the bytes the owner signed.
    doc = msgpack.unpackb(data, raw=False)
    doc["slots"][0]["objects"] = [7, 12]
    repacked = bytes(msgpack.packb(doc, use_bin_type=True))
    assert repacked == data  # packing is canonical: the same bytes, the same verdict
    body = data[oa:ob]
    longer = data[:oa] + b"\x92\xd1\x00\x07\x0c" + data[ob:]  # 7 as int16: same value
    assert body == b"\x92\x07\x0c" and longer != data
    with pytest.raises(BadSignature, match="does not verify"):
        decode(longer, LIMITS, PUBLIC)
    with pytest.raises(BadSignature, match="does not verify"):  # wanted or not: refused whole
        decode(longer, LIMITS, PUBLIC, wanted=lambda owner, epoch, stamp: False)
    relayed = decode(longer, LIMITS)  # without keys the same message is a valid slot...
    assert encode(relayed, LIMITS) == longer  # ...and a relay re-sends it as received


def test_a_decoded_slot_is_re_sent_as_the_bytes_received_until_it_changes() -> None:
    data = _message(signed=True)
    message = decode(data, LIMITS, PUBLIC)
    again = encode(message, LIMITS)
    assert again == data
    for slot in message.stack:
        assert slot.wire is not None and slot.wire.fits(slot) and slot.wire.data in data
    changed = dataclasses.replace(message.stack.by_owner()["r1"], stamp=99, signature=None)
    assert not changed.wire.fits(changed)  # a replaced field: encoded anew
    plain = encode(StackMessage("r2", None, Stack((changed,)), 9), LIMITS)
    assert decode(plain, LIMITS).stack.by_owner()["r1"].stamp == 99
    own = with_wire(_slot("r1", 4, 0), LIMITS)
    assert own.wire is not None and own.wire.data in encode(
        StackMessage("r1", None, Stack((own,)), 4), LIMITS
    )


def test_a_digest_travels_with_a_delta_stack_and_a_bad_one_is_refused() -> None:
    slot = _slot("r1", 3, 0)
    have = {"r1": (0, 3), "r2": (17, 5), "r3": (0, 0)}
    data = encode(StackMessage("r1", None, Stack((slot,)), 3, have=have), LIMITS)
    assert decode(data, LIMITS).have == have
    assert msgpack.unpackb(data, raw=False)["have"] == [["r1", 0, 3], ["r2", 17, 5], ["r3", 0, 0]]
    assert decode(encode(StackMessage("r1", None, Stack((slot,)), 3), LIMITS)).have is None
    doc = msgpack.unpackb(data, raw=False)
    for bad, field in (
        ([["r1", 0, 3], ["r1", 0, 4]], "have[1]"),  # an owner twice
        ([["r1", -1, 3]], "have[0]"),
        ([["r1", 0]], "have[0]"),
        ("r1", "have"),
        ([["bad id!", 0, 1]], "have[0]"),
        ([["r1", 0, 3], ["r2", True, 3]], "have[1]"),  # a bool is no integer
        ([["r1", 0, 3], ["r2", 0.0, 3]], "have[1]"),
        ([["r1", 0, 10_000_000]], "have[0]"),
        ([["r1", 2**53, 3]], "have[0]"),
        ([[7, 0, 1]], "have[0]"),
        ([("r1", 0, 3), ["r2", 0, 3, 4]], "have[1]"),
    ):
        doc["have"] = bad
        with pytest.raises(RemoteProtocolError) as err:
            decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS)
        assert err.value.field == field, (bad, err.value)
    # At most max_slots entries: a receiver keeps a digest per peer, so the count bounds that.
    doc["have"] = [[f"r{i}", 0, 1] for i in range(LIMITS.max_slots + 1)]
    with pytest.raises(LimitExceeded) as over:
        decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS)
    assert over.value.field == "have"
    doc["have"] = doc["have"][:-1]
    assert len(decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS).have or {}) == len(
        doc["have"]
    )
    with pytest.raises(LocalProtocolError, match="have"):
        encode(StackMessage("r1", None, Stack(), 3, have={"r1": (0, -2)}), LIMITS)


def test_an_ask_travels_with_a_digest_and_a_bad_one_is_refused() -> None:
    """``ask`` (docs/wire.md, "Asks"): owner → relay pairs, sorted by owner, only with a digest;
    a malformed one refuses the message, naming the entry."""
    have = {"r1": (0, 3), "r2": (17, 5)}
    ask = {"r4": "r2", "r3": "r2", "r5": "r1"}
    data = encode(StackMessage("r1", None, Stack(), 3, have=have, ask=ask), LIMITS)
    got = decode(data, LIMITS)
    assert got.ask == ask and got.have == have
    assert msgpack.unpackb(data, raw=False)["ask"] == [["r3", "r2"], ["r4", "r2"], ["r5", "r1"]]
    assert decode(encode(StackMessage("r1", None, Stack(), 3, have=have), LIMITS)).ask is None
    doc = msgpack.unpackb(data, raw=False)
    for bad, field in (
        ([["r3", "r2"], ["r3", "r1"]], "ask[1]"),  # an owner twice
        ([["r3"]], "ask[0]"),
        ([["r3", "r2", "r1"]], "ask[0]"),
        ("r3", "ask"),
        ({"r3": "r2"}, "ask"),
        ([["bad id!", "r2"]], "ask[0]"),
        ([["r3", "bad id!"]], "ask[0]"),
        ([["r3", 2]], "ask[0]"),
        ([[b"r3", "r2"]], "ask[0]"),  # a robot id is a str, not a bin
    ):
        doc["ask"] = bad
        with pytest.raises(RemoteProtocolError) as err:
            decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS)
        assert err.value.field == field, (bad, err.value)
    # At most max_slots entries (a receiver keeps the asks of every peer's digest).
    doc["ask"] = [[f"r{i}", "r1"] for i in range(LIMITS.max_slots + 1)]
    with pytest.raises(LimitExceeded) as over:
        decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS)
    assert over.value.field == "ask"
    doc["ask"] = doc["ask"][:-1]
    assert len(decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS).ask or {}) == len(
        doc["ask"]
    )
    # An ask goes only with a digest: what a receiver should push depends on what is held.
    del doc["have"]
    with pytest.raises(RemoteProtocolError) as alone:
        decode(bytes(msgpack.packb(doc, use_bin_type=True)), LIMITS)
    assert alone.value.field == "ask"
    with pytest.raises(LocalProtocolError, match="ask"):
        encode(StackMessage("r1", None, Stack(), 3, ask={"r3": "r2"}), LIMITS)
    with pytest.raises(LocalProtocolError, match="ask"):
        encode(StackMessage("r1", None, Stack(), 3, have=have, ask={"r3": "no way"}), LIMITS)
    many = {f"r{i}": "r1" for i in range(LIMITS.max_slots + 1)}
    with pytest.raises(LocalProtocolError, match="ask"):
        encode(StackMessage("r1", None, Stack(), 3, have=have, ask=many), LIMITS)
