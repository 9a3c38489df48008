"""Holding times on the wire (issue 47, item 1; docs/wire.md, "Holding times"): a stack's
``age`` gives each of its slots the milliseconds since its owner's step made it, summed over the
robots that held it on the way. Written last, so that the sender can put in the ages of the
moment it sends (``stamp_ages``); refused, with its field, when it is not one integer in
0 … ``MAX_AGE_MS`` per slot."""

from __future__ import annotations

import dataclasses
from typing import Any

import msgpack
import numpy as np
import pytest

from protocol.codec import MAX_AGE_MS, Limits, StackMessage, decode, encode, stamp_ages
from protocol.errors import InvalidValue, LocalProtocolError, MalformedMessage
from protocol.stack import Slot, Stack
from tests.protocol.test_codec import one_xi_summary

LIM = Limits(num_classes=3)


def aged(ages: dict[str, int] | None, owners: tuple[str, ...] = ("a", "b", "c")) -> StackMessage:
    slots = tuple(
        Slot(o, 3 + i, one_xi_summary(np.random.default_rng(40 + i), 2, 3))
        for i, o in enumerate(owners)
    )
    have = {o: (0, 3 + i) for i, o in enumerate(owners)}
    return StackMessage("r9", None, Stack(slots), 7, have=have, age=ages)


def test_ages_round_trip_by_owner_and_go_last() -> None:
    data = encode(aged({"a": 0, "b": 17, "c": MAX_AGE_MS}), LIM)
    assert decode(data, LIM).age == {"a": 0, "b": 17, "c": MAX_AGE_MS}
    doc = msgpack.unpackb(data)
    assert list(doc)[-1] == "age" and doc["age"] == [0, 17, MAX_AGE_MS]  # the slots' order
    # Without ages the message is what it was before holding times.
    plain = encode(aged(None), LIM)
    assert "age" not in msgpack.unpackb(plain) and decode(plain, LIM).age is None


def test_stamp_ages_rewrites_the_placeholder_and_clamps() -> None:
    data = encode(aged({"a": 0, "b": 0, "c": 0}), LIM)
    stamped = stamp_ages(data, [5, 300_000, MAX_AGE_MS + 99])
    assert stamped is not None
    got = decode(stamped, LIM)
    assert got.age == {"a": 5, "b": 300_000, "c": MAX_AGE_MS}
    assert data[: len(data) - 8] == stamped[: len(data) - 8]  # everything before `age` kept
    assert decode(stamp_ages(data, [-3, 0, 0]) or b"", LIM).age == {"a": 0, "b": 0, "c": 0}
    # Not such a message: another count of slots, ages already stamped, or no `age` at all.
    assert stamp_ages(data, [0, 0]) is None
    assert stamp_ages(stamped, [1, 2, 3]) is None
    assert stamp_ages(encode(aged(None), LIM), [0, 0, 0]) is None


def _with_age(value: Any) -> bytes:
    doc = msgpack.unpackb(encode(aged({"a": 1, "b": 2, "c": 3}), LIM))
    doc["age"] = value
    return msgpack.packb(doc)


@pytest.mark.parametrize(
    ("value", "error", "field"),
    [
        ({"a": 1}, MalformedMessage, "age"),
        ([1, 2], MalformedMessage, "age"),
        ([1, 2, 3, 4], MalformedMessage, "age"),
        ([1, -1, 3], InvalidValue, "age[1]"),
        ([1, 2, MAX_AGE_MS + 1], InvalidValue, "age[2]"),
        ([1.0, 2, 3], MalformedMessage, "age[0]"),
        ([1, True, 3], MalformedMessage, "age[1]"),
        ([1, 2, "3"], MalformedMessage, "age[2]"),
        (None, MalformedMessage, "age"),
    ],
)
def test_bad_ages_are_refused_with_their_field(value: Any, error: type, field: str) -> None:
    with pytest.raises(error) as caught:
        decode(_with_age(value), LIM)
    assert caught.value.field == field


@pytest.mark.parametrize(
    ("ages", "field"),
    [
        ({"a": 1, "b": 2}, "age[2]"),
        ({"a": 1, "b": 2, "c": 3, "d": 4}, "age"),
        ({"a": 1, "b": -2, "c": 3}, "age[1]"),
        ({"a": 1, "b": 2, "c": MAX_AGE_MS + 1}, "age[2]"),
        ({"a": 1.5, "b": 2, "c": 3}, "age[0]"),
    ],
)
def test_encode_refuses_what_decode_would(ages: dict[str, Any], field: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode(aged(ages), LIM)
    assert caught.value.field == field


def test_ages_of_slots_the_receiver_skips_are_kept() -> None:
    """``decode`` may leave out, unparsed, the slots the receiver does not want; their ages stay
    (a relay forwards what it holds, and the digest tells the rest)."""
    data = encode(aged({"a": 10, "b": 20, "c": 30}), LIM)
    got = decode(data, LIM, wanted=lambda owner, epoch, stamp: owner != "b")
    assert got.skipped == ("b",) and got.age == {"a": 10, "b": 20, "c": 30}


def test_room_for_stamped_ages_is_kept_under_the_byte_limit() -> None:
    data = encode(aged({"a": 0, "b": 0, "c": 0}), LIM)
    tight = dataclasses.replace(LIM, max_message_bytes=len(data))
    with pytest.raises(LocalProtocolError) as caught:
        encode(aged({"a": 0, "b": 0, "c": 0}), tight)
    assert caught.value.field == "message"
    roomy = dataclasses.replace(LIM, max_message_bytes=len(data) + 12)
    stamped = stamp_ages(encode(aged({"a": 0, "b": 0, "c": 0}), roomy), [MAX_AGE_MS] * 3)
    assert stamped is not None and decode(stamped, roomy).age == {"a": MAX_AGE_MS} | {
        "b": MAX_AGE_MS,
        "c": MAX_AGE_MS,
    }
