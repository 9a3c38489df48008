"""The run-control codec (``semfleet/<fleet>/ctl/**``): exact round trips, and every malformed
input turned into a RemoteProtocolError whose ``field`` names what is wrong — nothing else escapes
``decode_control`` (fuzzed with random bytes and random msgpack documents)."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agents.control import (
    MAX_CONTROL_BYTES,
    MAX_LINKS,
    MAX_STEP,
    Control,
    NeedFrames,
    NeedRound,
    Status,
    StepOrder,
    Stop,
    decode_control,
    encode_control,
)
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
)

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
        StepOrder(4, {"r1": ("r2",), "r2": ()}, waiting=("r2",)),
        StepOrder(4, {"r1": ()}, waiting=()),
        NeedFrames("r2", 0),
        NeedFrames("r_9-x", 12),
        NeedRound("r2", 4, ("r1", "r3")),
        NeedRound("r2", 0, ()),
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
    (_pack(_with(STEP, waiting="r1")), MalformedMessage, "ctl.waiting"),
    (_pack(_with(STEP, waiting=["r1"] * 1025)), LimitExceeded, "ctl.waiting"),
    (_pack(_with(NEED, robot=_DROP)), MalformedMessage, "ctl"),
    (_pack({**NEED, "type": "round"}), MalformedMessage, "ctl"),
    (_pack({**NEED, "type": "round", "senders": "r1"}), MalformedMessage, "ctl.senders"),
    (_pack({**NEED, "type": "round", "senders": ["r 1"]}), InvalidValue, "ctl.senders"),
    (_pack({**NEED, "type": "round", "senders": ["r1"] * 1025}), LimitExceeded, "ctl.senders"),
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
MALFORMED += [(_pack(_with(STEP, waiting=[bad])), InvalidValue, "ctl.waiting") for bad in BAD_IDS]
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


# --------------------------------------------------------------------------- size caps


def _ids(count: int, prefix: str = "r") -> list[str]:
    return [f"{prefix}{i}" for i in range(count)]


def _stop_of_size(size: int) -> bytes:
    """A valid stop document of exactly ``size`` bytes (≥ 64), its reason padded."""
    base = _pack({"type": "stop", "reason": ""})
    for pad in range(size - len(base), size - len(base) - 6, -1):
        data = _pack({"type": "stop", "reason": "x" * pad})
        if len(data) == size:
            return data
    raise AssertionError(size)


def test_control_message_over_max_bytes_is_refused_unread() -> None:
    assert isinstance(decode_control(_stop_of_size(MAX_CONTROL_BYTES)), Stop)
    with pytest.raises(LimitExceeded) as caught:
        decode_control(_stop_of_size(MAX_CONTROL_BYTES + 1))
    assert caught.value.field == "ctl"
    # Refused before unpacking: garbage over the cap is a LimitExceeded, not a MalformedMessage.
    with pytest.raises(LimitExceeded):
        decode_control(b"\xc1" * (MAX_CONTROL_BYTES + 1))
    with pytest.raises(LimitExceeded):
        decode_control(_pack(STEP), max_bytes=len(_pack(STEP)) - 1)
    assert isinstance(decode_control(_pack(STEP), max_bytes=len(_pack(STEP))), StepOrder)


def test_control_the_issues_ten_megabyte_step_order_is_refused() -> None:
    # Issue 11: a 9.8 MB ctl/step was accepted. 1024 robots hearing 1024 peers each.
    peers = _ids(MAX_LINKS, "peer_")
    data = _pack({"type": "step", "k": 1, "links": {r: peers for r in _ids(MAX_LINKS)}})
    assert len(data) > 9e6
    with pytest.raises(LimitExceeded) as caught:
        decode_control(data)
    assert caught.value.field == "ctl"


@pytest.mark.parametrize(
    ("links", "field"),
    [
        ({r: [] for r in _ids(MAX_LINKS + 1)}, "ctl.links"),
        ({"r1": _ids(MAX_LINKS + 1)}, "ctl.links.r1"),
    ],
)
def test_control_step_order_links_are_capped_in_entries(
    links: dict[str, list[str]], field: str
) -> None:
    data = _pack({"type": "step", "k": 1, "links": links})
    with pytest.raises(LimitExceeded) as caught:
        decode_control(data, max_bytes=len(data))
    assert caught.value.field == field
    order = StepOrder(1, {r: tuple(s) for r, s in links.items()})
    with pytest.raises(LocalProtocolError) as refused:
        encode_control(order, max_bytes=len(data))
    assert refused.value.field == field


def test_control_step_order_at_the_link_caps_is_accepted() -> None:
    links = {r: () for r in _ids(MAX_LINKS - 1)} | {"r_all": tuple(_ids(MAX_LINKS))}
    order = StepOrder(5, links)
    data = encode_control(order, max_bytes=2**20)
    assert decode_control(data, max_bytes=2**20) == order


@pytest.mark.parametrize(
    ("message", "field"),
    [
        (StepOrder(-1), "ctl.k"),
        (StepOrder(MAX_STEP + 1), "ctl.k"),
        (StepOrder(True), "ctl.k"),
        (StepOrder(1, {"r 1": ()}), "ctl.links"),
        (StepOrder(1, {"r1": ("r/2",)}), "ctl.links.r1"),
        (StepOrder(1, {}, waiting=("r 1",)), "ctl.waiting"),
        (StepOrder(1, {}, waiting=("r1",) * 1025), "ctl.waiting"),
        (NeedFrames("", 1), "ctl.robot"),
        (NeedRound("r1", 1, ("r/2",)), "ctl.senders"),
        (NeedRound("r1", -1, ()), "ctl.k"),
        (NeedFrames("r1", -1), "ctl.k"),
        (Stop(3), "ctl.reason"),  # type: ignore[arg-type]
        (Stop("x" * MAX_CONTROL_BYTES), "ctl"),
        ("stop", "ctl"),
    ],
)
def test_control_encode_refuses_what_decode_refuses(message: Control, field: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode_control(message)
    assert caught.value.field == field


# --------------------------------------------------------------------------- seeded fuzz


def _random_doc(rng: np.random.Generator, depth: int = 0) -> Any:
    """A random msgpack document, biased towards the control vocabulary and its edges."""
    kind = int(rng.integers(0, 10 if depth < 4 else 7))
    if kind == 0:
        return None
    if kind == 1:
        return bool(rng.integers(0, 2))
    if kind == 2:
        edges = [-(2**63), -1, 0, 1, 3, MAX_STEP, MAX_STEP + 1, 2**64 - 1]
        return edges[int(rng.integers(0, len(edges)))]
    if kind == 3:
        return float(rng.choice([0.0, -0.0, 1.5, np.nan, np.inf, 1e308]))
    if kind == 4:
        words = ["step", "need", "stop", "status", "type", "k", "links", "robot", "r1", "", "é"]
        return str(rng.choice(words)) * int(rng.integers(1, 3))
    if kind == 5:
        return rng.bytes(int(rng.integers(0, 9)))
    if kind == 6:
        return msgpack.ExtType(int(rng.integers(0, 128)), rng.bytes(int(rng.integers(0, 5))))
    if kind == 7:
        return [_random_doc(rng, depth + 1) for _ in range(int(rng.integers(0, 5)))]
    keys = ["type", "k", "links", "robot", "reason", "r1", "r2", "x"]
    doc = {str(rng.choice(keys)): _random_doc(rng, depth + 1) for _ in range(rng.integers(0, 5))}
    if rng.random() < 0.6:
        doc["type"] = str(rng.choice(["step", "need", "stop", "status"]))
    return doc


@pytest.mark.parametrize("seed", range(4))
def test_control_seeded_fuzz_raises_only_remote_errors(seed: int) -> None:
    rng = np.random.default_rng(seed)
    valid = [encode_control(m) for m in (StepOrder(3, {"r1": ("r2",)}), NeedFrames("r2", 4))]
    for _ in range(500):
        _only_remote_errors(rng.bytes(int(rng.integers(0, 300))))
        _only_remote_errors(_pack(_random_doc(rng)))
        blob = bytearray(valid[int(rng.integers(0, len(valid)))])
        for _ in range(int(rng.integers(1, 4))):
            blob[int(rng.integers(0, len(blob)))] = int(rng.integers(0, 256))
        _only_remote_errors(bytes(blob))


@pytest.mark.parametrize("seed", range(4))
def test_control_seeded_step_orders_round_trip_or_are_refused_by_both(seed: int) -> None:
    """Whatever encode_control accepts decodes to the same order; whatever it refuses, a
    receiver refuses too (the document packed by hand)."""
    rng = np.random.default_rng(seed)
    pool = [*_ids(6), "r 1", ""]
    for _ in range(200):
        robots = rng.choice(pool, size=int(rng.integers(0, 5)), replace=False)
        links = {
            str(r): tuple(str(s) for s in rng.choice(pool, size=rng.integers(0, 4))) for r in robots
        }
        k = [-1, 0, 7, MAX_STEP, MAX_STEP + 1][int(rng.integers(0, 5))]
        cap = int(rng.integers(10, 120))
        order = StepOrder(k, links)
        doc = {"type": "step", "k": k, "links": {r: list(s) for r, s in links.items()}}
        try:
            data = encode_control(order, max_bytes=cap)
        except LocalProtocolError as exc:
            with pytest.raises(RemoteProtocolError) as caught:
                decode_control(_pack(doc), max_bytes=cap)
            if len(_pack(doc)) <= cap:  # both read in the same order once the size fits
                assert caught.value.field == exc.field
        else:
            assert data == _pack(doc)
            assert decode_control(data, max_bytes=cap) == order
