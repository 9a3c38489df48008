"""The run-control codec (``semfleet/<fleet>/ctl/**``): exact round trips, and every malformed
input turned into a RemoteProtocolError whose ``field`` names what is wrong — nothing else escapes
``decode_control`` (fuzzed with random bytes and random msgpack documents)."""

from __future__ import annotations

from typing import Any

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents.control import (
    MAX_STEP,
    Control,
    NeedFrames,
    Status,
    StepOrder,
    Stop,
    decode_control,
    encode_control,
)
from protocol.errors import InvalidValue, MalformedMessage, RemoteProtocolError

FUZZ = settings(derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
BAD_IDS = ("", "x" * 33, "r 1", "r/1", "rö", 7, None, b"r1")


def _pack(doc: Any) -> bytes:
    return bytes(msgpack.packb(doc, use_bin_type=True))


STEP = {"type": "step", "k": 3, "links": {"r1": ["r2"], "r2": ["r1", "r3"], "r3": []}}
NEED = {"type": "need", "robot": "r2", "k": 4}
STOP = {"type": "stop", "reason": "done"}


@pytest.mark.parametrize(
    "message",
    [
        StepOrder(1),
        StepOrder(7, {"r1": (), "r2": ("r1", "r3"), "r3": ("r2",)}),
        StepOrder(MAX_STEP, {"a" * 32: ("B_-9",)}),
        NeedFrames("r2", 0),
        NeedFrames("r_9-x", 12),
        Stop(),
        Stop("run complete ✓"),
        Status(),
    ],
)
def test_control_round_trip_is_exact(message: Control) -> None:
    decoded = decode_control(encode_control(message))
    assert type(decoded) is type(message)
    assert decoded == message


def test_control_step_order_keeps_sender_order() -> None:
    decoded = decode_control(encode_control(StepOrder(2, {"r3": ("r2", "r1")})))
    assert isinstance(decoded, StepOrder)
    assert decoded.links["r3"] == ("r2", "r1")


_DROP = object()  # as a value in _with: remove the key


def _with(doc: dict[str, Any], **changes: Any) -> dict[str, Any]:
    out = dict(doc)
    for key, value in changes.items():
        if value is _DROP:
            del out[key]
        else:
            out[key] = value
    return out


MALFORMED: list[tuple[bytes, type[RemoteProtocolError], str]] = [
    (b"", MalformedMessage, "ctl"),
    (b"\xc1", MalformedMessage, "ctl"),  # never-used msgpack byte
    (b"\x93\x01", MalformedMessage, "ctl"),  # truncated array
    (_pack([1, 2]), MalformedMessage, "ctl"),
    (_pack("step"), MalformedMessage, "ctl"),
    (_pack({}), MalformedMessage, "ctl.type"),
    (_pack({"type": "jump", "k": 1}), MalformedMessage, "ctl.type"),
    (_pack({"type": 5}), MalformedMessage, "ctl.type"),
    (_pack(_with(STEP, links=_DROP)), MalformedMessage, "ctl"),
    (_pack(_with(STEP, extra=1)), MalformedMessage, "ctl"),
    (_pack(_with(STEP, k="3")), MalformedMessage, "ctl.k"),
    (_pack(_with(STEP, k=3.0)), MalformedMessage, "ctl.k"),
    (_pack(_with(STEP, k=True)), MalformedMessage, "ctl.k"),
    (_pack(_with(STEP, k=-1)), InvalidValue, "ctl.k"),
    (_pack(_with(STEP, k=MAX_STEP + 1)), InvalidValue, "ctl.k"),
    (_pack(_with(STEP, k=2**64 - 1)), InvalidValue, "ctl.k"),
    (_pack(_with(STEP, links=["r1"])), MalformedMessage, "ctl.links"),
    (_pack(_with(STEP, links={"r1": "r2"})), MalformedMessage, "ctl.links.r1"),
    (_pack(_with(STEP, links={"r1": {"r2": 1}})), MalformedMessage, "ctl.links.r1"),
    (_pack(_with(NEED, robot=_DROP)), MalformedMessage, "ctl"),
    (_pack(_with(NEED, k=None)), MalformedMessage, "ctl.k"),
    (_pack(_with(NEED, k=-5)), InvalidValue, "ctl.k"),
    (_pack(_with(STOP, reason=3)), MalformedMessage, "ctl.reason"),
    (_pack(_with(STOP, reason=b"done")), MalformedMessage, "ctl.reason"),
    (_pack(_with(STOP, reason=_DROP)), MalformedMessage, "ctl"),
]
MALFORMED += [(_pack(_with(NEED, robot=bad)), InvalidValue, "ctl.robot") for bad in BAD_IDS]
MALFORMED += [
    (_pack(_with(STEP, links={"r1": [bad]})), InvalidValue, "ctl.links.r1") for bad in BAD_IDS
]
MALFORMED += [
    (_pack(_with(STEP, links={bad: []})), InvalidValue, "ctl.links")
    for bad in BAD_IDS
    if isinstance(bad, str)  # msgpack with strict_map_key refuses other key types: "ctl"
]
MALFORMED += [(_pack({7: 1}), MalformedMessage, "ctl"), (_pack({None: 1}), MalformedMessage, "ctl")]


@pytest.mark.parametrize(("data", "error", "field"), MALFORMED)
def test_control_malformed_input_names_the_field(
    data: bytes, error: type[RemoteProtocolError], field: str
) -> None:
    with pytest.raises(error) as info:
        decode_control(data)
    assert info.value.field == field
    assert str(info.value).startswith(f"{field}: ")


def test_control_the_valid_documents_used_for_mutation_decode() -> None:
    assert decode_control(_pack(STEP)) == StepOrder(
        3, {"r1": ("r2",), "r2": ("r1", "r3"), "r3": ()}
    )
    assert decode_control(_pack(NEED)) == NeedFrames("r2", 4)
    assert decode_control(_pack(STOP)) == Stop("done")


def _only_remote_errors(data: bytes) -> None:
    try:
        decode_control(data)
    except RemoteProtocolError as exc:
        assert exc.field.startswith("ctl"), exc
    # Any other exception type fails the test: that is the property.


@FUZZ
@given(st.binary(max_size=256))
def test_control_fuzz_random_bytes_raise_only_remote_errors(data: bytes) -> None:
    _only_remote_errors(data)


_scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True)
    | st.text(max_size=40)
    | st.binary(max_size=8)
    | st.sampled_from(["step", "need", "stop", "type", "k", "links", "robot", "reason", "r1"])
)
_keys = st.sampled_from(["type", "k", "links", "robot", "reason", "r1", "r2"]) | st.text(max_size=4)
_docs = st.recursive(
    _scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_keys, inner, max_size=4),
    max_leaves=12,
)


@FUZZ
@given(
    st.sampled_from([STEP, NEED, STOP]),
    st.sampled_from(["type", "k", "links", "robot", "reason", "extra"]),
    _docs,
)
def test_control_fuzz_mutated_documents_raise_only_remote_errors(
    base: dict[str, Any], key: str, value: Any
) -> None:
    _only_remote_errors(_pack({**base, key: value}))


@FUZZ
@given(_docs)
def test_control_fuzz_random_documents_raise_only_remote_errors(doc: Any) -> None:
    _only_remote_errors(_pack(doc))
