"""The wire codec (docs/wire.md): bit-exact round trips, one error class per fault with a message
that names the field, and fuzzing that proves nothing but a RemoteProtocolError escapes ``decode``.

Malformed documents are made by unpacking a valid message with msgpack, mutating one field and
repacking it, so each case exercises exactly one rule of the validator.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.models import MAX_STEP
from estimator.summary import LocalSummary, Realisation, Xi
from protocol import codec
from protocol.codec import Limits, StackMessage, decode, encode
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
    UnsupportedVersion,
)
from protocol.scan import scan
from protocol.stack import Slot, Stack
from tests.protocol import fuzz
from tests.protocol.fuzz import FUZZ, Path, field_name, get_at, pack, set_at

SPECIAL_FLOATS = (
    *(0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308),
    *(1.7976931348623157e308, -1.7976931348623157e308, 1.0, -1.0, 1e-300, 1e300),
)
BAD_ROBOT_IDS = ("", "x" * 33, "r 1", " r1", "r1 ", "r/1", "r.1", "rö", "r1\x00", "r1\n1")
DEFAULT = Limits()


# --------------------------------------------------------------------------- valid messages


def bounded(rng: np.random.Generator, shape: tuple[int, ...], bound: float) -> np.ndarray:
    """``fuzz.finite`` values (±0, subnormals, arbitrary bit patterns) with every one beyond
    ±``bound`` replaced by a uniform draw in [−bound, bound], ±``bound`` itself sprinkled in."""
    values = fuzz.finite(rng, shape, (*SPECIAL_FLOATS, bound, -bound))
    return np.where(np.abs(values) <= bound, values, rng.uniform(-bound, bound, shape))


def make_realisation(rng: np.random.Generator, n: int, num_classes: int) -> Realisation:
    """A realisation over n objects valid under the default ``Limits``: classes in
    0..num_classes−1, Λ = s·(A Aᵀ + I) exactly symmetric positive definite with s a power of two in
    2^−20..2^20 (λmax ≤ 2^20·(1 + 4·3n) < 1e9, κ < 1 + 4·3n), positions within ±world_extent,
    angles within ±2π, |log φ| within its bound, and |ηᵢ| ≤ λmin (a mean within 1 m per
    coordinate of ``lin``)."""
    a = rng.standard_normal((3 * n, 3 * n))
    b = a @ a.T + np.eye(3 * n)
    info = (b + b.T) / 2.0 * 2.0 ** int(rng.integers(-20, 21))
    classes = tuple(int(c) for c in rng.integers(0, num_classes, n))
    log_phi = float(bounded(rng, (1,), DEFAULT.max_abs_log_phi)[0])
    lin = np.concatenate(
        [bounded(rng, (n, 2), DEFAULT.world_extent), bounded(rng, (n, 1), 2.0 * math.pi)], axis=1
    )
    lam_min = float(np.linalg.eigvalsh(info)[0]) if n else 0.0
    return Realisation(classes, log_phi, Xi(lin, info, bounded(rng, (3 * n,), lam_min)))


def make_summary(
    rng: np.random.Generator,
    n: int | None = None,
    realisations: int | None = None,
    num_classes: int | None = None,
    shared: float = 0.3,
) -> LocalSummary:
    """A valid summary: n ∈ 0..6 distinct object ids, 1..4 realisations, M ∈ {2, 3} classes;
    with ``shared`` probability a realisation shares the ξ of an earlier one (docs/wire.md,
    "Shared ξ")."""
    n = int(rng.integers(0, 7)) if n is None else n
    k = int(rng.integers(1, 5)) if realisations is None else realisations
    m = int(rng.choice([2, 3])) if num_classes is None else num_classes
    ids: list[int] = []
    while len(ids) < n:
        j = int(rng.choice([0, 2**32 - 1])) if rng.random() < 0.1 else int(rng.integers(0, 2**32))
        if j not in ids:
            ids.append(j)
    reals: list[Realisation] = []
    for _ in range(k):
        r = make_realisation(rng, n, m)
        if reals and rng.random() < shared:
            r = dataclasses.replace(r, xi=reals[int(rng.integers(0, len(reals)))].xi)
        reals.append(r)
    return LocalSummary(tuple(ids), tuple(reals))


def make_message(
    rng: np.random.Generator,
    owners: tuple[str, ...] = ("r1", "r2", "r3"),
    stamps: tuple[int, ...] | None = None,
    sender: str = "r0",
    position: tuple[float, float] | None = (1.5, -2.25),
) -> StackMessage:
    """A valid stack message with one random slot per owner."""
    if stamps is None:
        stamps = tuple(int(s) for s in rng.integers(0, 1000, len(owners)))
    slots = tuple(Slot(o, s, make_summary(rng)) for o, s in zip(owners, stamps, strict=True))
    return StackMessage(sender, position, Stack(slots))


def _bits(values: Any) -> bytes:
    return np.asarray(values, dtype=np.float64).tobytes()


def assert_same_message(got: StackMessage, want: StackMessage) -> None:
    """Equal to the bit, -0.0 and subnormals included."""
    assert got.sender == want.sender and got.step == want.step
    assert got.have == want.have and got.ask == want.ask and got.age == want.age
    if want.position is None:
        assert got.position is None
    else:
        assert got.position is not None
        assert _bits(got.position) == _bits(want.position)
    assert [(s.owner, s.stamp) for s in got.stack] == [(s.owner, s.stamp) for s in want.stack]
    for g, w in zip(got.stack, want.stack, strict=True):
        assert g.summary.object_ids == tuple(w.summary.object_ids)
        assert len(g.summary.realisations) == len(w.summary.realisations)
        for i, (gr, wr) in enumerate(
            zip(g.summary.realisations, w.summary.realisations, strict=True)
        ):
            where = f"{w.owner}.real[{i}]"
            assert gr.classes == tuple(wr.classes), where
            assert gr.log_phi == wr.log_phi, where
            assert _bits(gr.log_phi) == _bits(wr.log_phi), where
            # The same realisations share a ξ on both sides (docs/wire.md, "Shared ξ").
            sharers = [j for j, r in enumerate(w.summary.realisations) if r.xi is wr.xi]
            assert [j for j, r in enumerate(g.summary.realisations) if r.xi is gr.xi] == sharers
            for name in ("lin", "info", "eta"):
                ga, wa = getattr(gr, name), getattr(wr, name)
                assert ga.dtype == np.float64 and ga.shape == wa.shape, f"{where}.{name}"
                assert np.array_equal(ga, wa), f"{where}.{name}"
                assert _bits(ga) == _bits(wa), f"{where}.{name}"


def assert_within_limits(msg: StackMessage, lim: Limits) -> None:
    """The absolute bounds of docs/wire.md ("Limits"), recomputed here from their definitions."""
    w = lim.world_extent
    assert msg.position is None or max(abs(v) for v in msg.position) <= w
    for slot in msg.stack:
        n = len(slot.summary.object_ids)
        for r in slot.summary.realisations:
            assert abs(r.log_phi) <= lim.max_abs_log_phi
            assert np.all(np.abs(r.lin[:, :2]) <= w) and np.all(np.abs(r.lin[:, 2]) <= 2 * math.pi)
            if n == 0:
                continue
            lam = np.linalg.eigvalsh(r.info)
            assert lam[-1] <= lim.max_information
            assert lam[0] >= -lim.psd_tol * np.abs(lam).max()
            floor = 1.0 / w**2
            assert lam[0] + floor > 0 and (lam[-1] + floor) / (lam[0] + floor) <= lim.max_condition
            delta_max = math.pi * math.sqrt(n * (2 * w * w + 1))  # docs: longest tangent offset
            assert np.linalg.norm(r.eta) <= max(lam[-1], 0.0) * delta_max


def _check_valid(msg: StackMessage, lim: Limits) -> None:
    """What a successful decode promises, and that it survives another round trip."""
    assert msg.position is None or all(math.isfinite(v) for v in msg.position)
    assert len(msg.stack) <= lim.max_slots
    for slot in msg.stack:
        ids = slot.summary.object_ids
        n = len(ids)
        assert n <= lim.max_objects and len(set(ids)) == n
        assert 1 <= len(slot.summary.realisations) <= lim.max_realisations
        for r in slot.summary.realisations:
            assert len(r.classes) == n and all(0 <= c < lim.num_classes for c in r.classes)
            assert math.isfinite(r.log_phi)
            assert r.lin.shape == (n, 3) and r.info.shape == (3 * n, 3 * n)
            assert r.eta.shape == (3 * n,)
            assert np.array_equal(r.info, r.info.T)
            for a in (r.lin, r.info, r.eta):
                assert np.all(np.isfinite(a))
    assert_within_limits(msg, lim)
    again = decode(encode(msg, lim), lim)
    assert_same_message(again, msg)


# --------------------------------------------------------------------------- documents

# Wire order is owner order: slots[0] is r1 (3 objects, 2 realisations, M = 2), slots[1] is r2
# (no objects, 1 realisation), slots[2] is r3 (2 objects, 3 realisations, M = 3).
REF = StackMessage(
    "r0",
    (1.5, -2.25),
    Stack(
        (
            Slot("r3", 12, make_summary(np.random.default_rng(3), 2, 3, 3, shared=0.0)),
            Slot("r1", 7, make_summary(np.random.default_rng(1), 3, 2, 2, shared=0.0)),
            Slot("r2", 0, make_summary(np.random.default_rng(2), 0, 1, 2, shared=0.0)),
        )
    ),
    13,
)
REF_BLOB = encode(REF)
REF_DOC: dict[Any, Any] = msgpack.unpackb(REF_BLOB, raw=False)
BASE_MESSAGES = (
    REF,
    StackMessage("solo", None, Stack()),
    StackMessage(
        "big",
        None,
        Stack((Slot("b", MAX_STEP, make_summary(np.random.default_rng(9), 6, 4)),)),
        MAX_STEP,
    ),
    *(make_message(np.random.default_rng(seed)) for seed in (11, 12, 13)),
)


def one_xi_summary(rng: np.random.Generator, n: int, count: int, m: int = 3) -> LocalSummary:
    """``count`` realisations sharing one ξ (the default belief's slots): realisation 0 carries
    it, every other one names it — the layout decode reads as fixed-size records."""
    first = make_realisation(rng, n, m)
    others = [
        dataclasses.replace(make_realisation(rng, n, m), xi=first.xi) for _ in range(count - 1)
    ]
    return LocalSummary(tuple(range(100, 100 + n)), (first, *others))


# Shared-ξ slots as the default belief sends them, so that the fuzzing below (truncation,
# corruption, mutation) also runs through the fixed-record path of decode.
BASE_MESSAGES += (
    StackMessage(
        "one-xi",
        (0.5, 0.25),
        Stack(
            (
                Slot("a", 3, one_xi_summary(np.random.default_rng(21), 3, 6)),
                Slot("b", 4, one_xi_summary(np.random.default_rng(22), 0, 3)),
                Slot("c", 5, one_xi_summary(np.random.default_rng(23), 2, 17)),
            )
        ),
        4,
    ),
    # Delta gossip: a slot with the sender's digest and its asks (docs/wire.md).
    StackMessage(
        "delta",
        None,
        Stack((Slot("a", 3, one_xi_summary(np.random.default_rng(24), 2, 3)),)),
        7,
        have={"a": (0, 3), "delta": (5, 7), "z-9": (2**53 - 1, 0)},
        ask={"b": "a", "c": "z-9"},
        age={"a": 1234},
    ),
)
BASE_BLOBS = tuple(encode(m) for m in BASE_MESSAGES)
BASE_DOCS = tuple(msgpack.unpackb(b, raw=False) for b in BASE_BLOBS)


WIRE = fuzz.Wire(decode, REF_DOC, Limits(), _check_valid)


def _upper(info: np.ndarray) -> bytes:
    return info[np.triu_indices(info.shape[0])].astype("<f8").tobytes()


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("index", range(len(BASE_MESSAGES)))
def test_codec_round_trip_is_bit_exact(index: int) -> None:
    blob = BASE_BLOBS[index]
    got = decode(blob)
    assert_same_message(got, BASE_MESSAGES[index])
    assert encode(got) == blob


@pytest.mark.parametrize("position", [None, (0.0, -0.0), (5e-324, -1e4), (1e4, -5e-324)])
def test_codec_round_trip_keeps_position(position: tuple[float, float] | None) -> None:
    msg = dataclasses.replace(REF, position=position)
    assert_same_message(decode(encode(msg)), msg)


def test_codec_decode_accepts_bytearray_and_memoryview() -> None:
    assert_same_message(decode(bytearray(REF_BLOB)), REF)  # type: ignore[arg-type]
    assert_same_message(decode(memoryview(REF_BLOB)), REF)  # type: ignore[arg-type]


def test_codec_wire_layout_matches_docs() -> None:
    assert set(REF_DOC) == {"v", "type", "sender", "k", "pos", "slots"}
    assert REF_DOC["k"] == REF.step
    assert REF_DOC["v"] == 1 and REF_DOC["type"] == "stack" and REF_DOC["sender"] == "r0"
    assert REF_DOC["pos"] == [1.5, -2.25]
    assert [s["owner"] for s in REF_DOC["slots"]] == ["r1", "r2", "r3"]
    for raw, slot in zip(REF_DOC["slots"], REF.stack, strict=True):
        assert set(raw) == {"owner", "stamp", "objects", "real"}
        assert raw["stamp"] == slot.stamp and raw["objects"] == list(slot.summary.object_ids)
        for r_raw, r in zip(raw["real"], slot.summary.realisations, strict=True):
            assert set(r_raw) == {"c", "phi", "lin", "info", "eta"}
            assert r_raw["c"] == bytes(r.classes)
            assert r_raw["phi"] == r.log_phi
            assert r_raw["lin"] == r.lin.astype("<f8").tobytes()
            assert r_raw["info"] == _upper(r.info)
            assert r_raw["eta"] == r.eta.astype("<f8").tobytes()


def _header(length: int) -> int:
    return 2 if length < 2**8 else 3 if length < 2**16 else 5


def documented_realisation_bytes(n: int) -> int:
    """docs/wire.md: payload n + 8 + 24n + 8·3n(3n+1)/2 + 24n = 36n² + 61n + 8, plus 21 bytes of
    map and keys, 1 float marker and the headers of the four binaries."""
    payload = n + 8 + 24 * n + 8 * (3 * n * (3 * n + 1) // 2) + 24 * n
    assert payload == 36 * n * n + 61 * n + 8
    info = 36 * n * n + 12 * n
    return payload + 21 + _header(n) + 2 * _header(24 * n) + _header(info)


@pytest.mark.parametrize("n", [0, 1, 2, 5, 6, 15, 60])
def test_codec_realisation_size_matches_docs(n: int) -> None:
    summary = make_summary(np.random.default_rng(n), n=n, realisations=2)
    one = LocalSummary(summary.object_ids, summary.realisations[:1])
    sizes = [
        len(encode(StackMessage("r0", None, Stack((Slot("r1", 1, s),))))) for s in (one, summary)
    ]
    assert sizes[1] - sizes[0] == documented_realisation_bytes(n)


def test_codec_realisation_size_at_fifteen_objects() -> None:
    assert documented_realisation_bytes(15) == 9055


def documented_reference_bytes(n: int, i: int) -> int:
    """docs/wire.md: a realisation that shares realisation i's ξ is n + 19 + h(n) + s(i)."""
    return n + 19 + _header(n) + (1 if i < 128 else 2 if i < 256 else 3)


@pytest.mark.parametrize(("n", "i"), [(0, 0), (1, 0), (15, 0), (15, 127), (15, 128), (2, 300)])
def test_codec_shared_xi_realisation_size_matches_docs(n: int, i: int) -> None:
    rng = np.random.default_rng(n + i)
    reals = [make_realisation(rng, n, 2) for _ in range(i + 1)]
    base = LocalSummary(tuple(range(n)), tuple(reals))
    shared = dataclasses.replace(make_realisation(rng, n, 2), xi=reals[i].xi)
    more = LocalSummary(base.object_ids, (*reals, shared))
    sizes = [
        len(
            encode(
                StackMessage("r0", None, Stack((Slot("r1", 1, s),))), Limits(max_realisations=4096)
            )
        )
        for s in (base, more)
    ]
    assert sizes[1] - sizes[0] == documented_reference_bytes(n, i)
    assert documented_reference_bytes(15, 0) == 37


def test_codec_a_belief_with_one_continuous_belief_sends_its_xi_once() -> None:
    """300 realisations of 15 objects sharing one ξ: one ξ on the wire, about 20 KB."""
    rng = np.random.default_rng(3)
    first = make_realisation(rng, 15, 2)
    reals = [first] + [
        dataclasses.replace(make_realisation(rng, 15, 2), xi=first.xi) for _ in range(299)
    ]
    summary = LocalSummary(tuple(range(15)), tuple(reals))
    blob = encode(StackMessage("r0", None, Stack((Slot("r1", 1, summary),))))
    assert len(blob) < 21_000
    got = decode(blob).stack.slots[0].summary
    assert len({id(r.xi) for r in got.realisations}) == 1


def _slot_body(blob: bytes, slot: int = 0) -> memoryview:
    """The ``real`` body of slot ``slot`` of an encoded message, as decode locates it."""
    frame = scan(blob)["slots"][slot]
    a, b = frame.spans["real"]
    return memoryview(blob)[a:b]


@pytest.mark.parametrize("seed", range(12))
def test_codec_shared_xi_records_read_at_once_equal_the_maps_read_one_by_one(seed: int) -> None:
    """The fixed-record path gives exactly what parsing every realisation's map gives (classes,
    log φ to the bit, every realisation on the carrier's ξ), for 0..30 objects and 2..40
    realisations — 16 or more realisations make a msgpack array16."""
    rng = np.random.default_rng(seed)
    n, count = int(rng.integers(0, 31)), int(rng.integers(2, 41))
    summary = one_xi_summary(rng, n, count, m=4)
    blob = encode(StackMessage("r0", None, Stack((Slot("r1", 1, summary),))))
    body = _slot_body(blob)
    fast = codec._shared_xi_run(body, n, DEFAULT)
    assert fast is not None
    slow = codec._realisation_maps(body, "slots[0]", n, DEFAULT)
    for f, g in zip((fast[0], fast[3]), (slow[0], slow[3]), strict=True):
        assert f.dtype == g.dtype and np.array_equal(f, g)
    assert _bits(fast[1]) == _bits(slow[1])
    assert list(fast[2]) == list(slow[2]) == [0]
    got = decode(blob).stack.slots[0].summary
    assert [r.classes for r in got.realisations] == [r.classes for r in summary.realisations]
    assert _bits([r.log_phi for r in got.realisations]) == _bits(
        [r.log_phi for r in summary.realisations]
    )


def _one_xi_doc() -> dict[str, Any]:
    summary = one_xi_summary(np.random.default_rng(5), 3, 5)
    return msgpack.unpackb(encode(StackMessage("r0", None, Stack((Slot("r1", 1, summary),)))))


@pytest.mark.parametrize(
    "change",
    [
        "int-phi",
        "key-order",
        "second-carrier",
        "ref-to-1",
        "class-too-big",
        "str-class",
    ],
)
def test_codec_a_shared_xi_body_in_any_other_form_takes_the_map_by_map_path(change: str) -> None:
    """Anything but the fixed layout is left to the map-by-map path, which accepts what is valid
    (an integer log φ, another key order, two carriers) and names the field of what is not."""
    doc = _one_xi_doc()
    reals = doc["slots"][0]["real"]
    if change == "int-phi":
        reals[2]["phi"] = 3
    elif change == "key-order":
        reals[3] = {"xi": 0, "phi": reals[3]["phi"], "c": reals[3]["c"]}
    elif change == "second-carrier":
        reals[2] = {**reals[0], "c": reals[2]["c"], "phi": reals[2]["phi"]}
    elif change == "ref-to-1":
        reals[1] = {**reals[0], "c": reals[1]["c"]}
        reals[4]["xi"] = 1
    elif change == "class-too-big":
        reals[4]["c"] = bytes([0, 9, 1])
    elif change == "str-class":
        reals[1]["c"] = "abc"
    blob = bytes(msgpack.packb(doc, use_bin_type=True))
    assert codec._shared_xi_run(_slot_body(blob), 3, Limits(num_classes=3)) is None
    if change == "class-too-big":
        with pytest.raises(InvalidValue) as info:
            decode(blob, Limits(num_classes=3))
        assert info.value.field == "slots[0].real[4].c"
        return
    if change == "str-class":
        with pytest.raises(MalformedMessage) as caught:
            decode(blob)
        assert caught.value.field == "slots[0].real[1].c"
        return
    got = decode(blob).stack.slots[0].summary.realisations
    assert [r.classes for r in got] == [tuple(r["c"]) for r in reals]
    assert [r.log_phi for r in got] == [float(r["phi"]) for r in reals]
    if change == "ref-to-1":
        assert got[4].xi is got[1].xi and got[1].xi is not got[0].xi


def _with_reference(index: int, ref: Any, carry: bool = False) -> bytes:
    """REF's wire form with r1's realisation ``index`` turned into a reference to ``ref``
    (keeping its own ξ too when ``carry``)."""
    doc = msgpack.unpackb(encode(REF), raw=False)
    real = doc["slots"][0]["real"][index]
    kept = real if carry else {"c": real["c"], "phi": real["phi"]}
    doc["slots"][0]["real"][index] = {**kept, "xi": ref}
    return bytes(msgpack.packb(doc, use_bin_type=True))


@pytest.mark.parametrize(
    ("data", "error", "field"),
    [
        pytest.param(_with_reference(0, 0), InvalidValue, "slots[0].real[0].xi", id="self"),
        pytest.param(_with_reference(1, 1), InvalidValue, "slots[0].real[1].xi", id="itself"),
        pytest.param(_with_reference(0, 1), InvalidValue, "slots[0].real[0].xi", id="later"),
        pytest.param(_with_reference(1, -1), InvalidValue, "slots[0].real[1].xi", id="negative"),
        pytest.param(_with_reference(1, 0.0), MalformedMessage, "slots[0].real[1].xi", id="float"),
        pytest.param(_with_reference(1, 0, True), MalformedMessage, "slots[0].real[1]", id="both"),
    ],
)
def test_codec_refuses_a_shared_xi_reference_that_names_no_earlier_xi(
    data: bytes, error: type[Exception], field: str
) -> None:
    with pytest.raises(error) as info:
        decode(data)
    assert info.value.field == field  # type: ignore[attr-defined]


def test_codec_refuses_a_reference_to_a_realisation_without_its_own_xi() -> None:
    doc = msgpack.unpackb(encode(REF), raw=False)
    reals = doc["slots"][2]["real"]  # r3: three realisations
    reals[1] = {"c": reals[1]["c"], "phi": reals[1]["phi"], "xi": 0}
    reals[2] = {"c": reals[2]["c"], "phi": reals[2]["phi"], "xi": 1}
    with pytest.raises(InvalidValue) as info:
        decode(bytes(msgpack.packb(doc, use_bin_type=True)))
    assert info.value.field == "slots[2].real[2].xi"


@settings(FUZZ, max_examples=2000)
@given(
    seed=st.integers(0, 2**32 - 1),
    sender=fuzz.ROBOT_IDS,
    position=st.none() | st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
    versions=st.dictionaries(
        fuzz.ROBOT_IDS,
        st.integers(0, MAX_STEP),
        max_size=4,
    ),
)
def test_codec_round_trip_is_bit_exact_fuzz(
    seed: int, sender: str, position: tuple[float, float] | None, versions: dict[str, int]
) -> None:
    msg = make_message(
        np.random.default_rng(seed), tuple(versions), tuple(versions.values()), sender, position
    )
    blob = encode(msg)
    got = decode(blob)
    assert_same_message(got, msg)
    assert encode(got) == blob


# --------------------------------------------------------------------------- truncation, noise


@pytest.mark.parametrize("index", range(len(BASE_BLOBS)))
def test_codec_every_truncated_prefix_is_malformed(index: int) -> None:
    WIRE.assert_every_prefix_malformed(BASE_BLOBS[index])


def test_codec_trailing_bytes_are_malformed() -> None:
    WIRE.assert_rejected(REF_BLOB + b"\x00", MalformedMessage, "message")
    WIRE.assert_rejected(REF_BLOB + REF_BLOB, MalformedMessage, "message")


@pytest.mark.parametrize(
    "blob", [b"", b"\xc1", b"\x93\x01\x02\x03", b"\x05", b"\xa5stack", b"\xc0", b"\x80"]
)
def test_codec_non_map_documents_are_malformed(blob: bytes) -> None:
    WIRE.assert_rejected(blob, MalformedMessage, "message")


def test_codec_decode_rejects_non_bytes_input() -> None:
    WIRE.assert_rejected("not bytes", MalformedMessage, "message")  # type: ignore[arg-type]


def test_codec_non_string_map_keys_are_malformed() -> None:
    doc = copy.deepcopy(REF_DOC)
    doc[1] = 2
    WIRE.assert_rejected(pack(doc), MalformedMessage, "message")
    doc = copy.deepcopy(REF_DOC)
    doc[b"v"] = 1
    WIRE.assert_rejected(pack(doc), MalformedMessage, "message")


@settings(FUZZ, max_examples=4000)
@given(blob=st.binary(max_size=1024))
def test_codec_random_bytes_raise_only_remote_errors(blob: bytes) -> None:
    WIRE.decode_or_reject(blob)


@settings(FUZZ, max_examples=1000)
@given(index=st.integers(0, len(BASE_BLOBS) - 1), edits=fuzz.BYTE_EDITS)
def test_codec_corrupted_bytes_raise_only_remote_errors(
    index: int, edits: list[tuple[int, int]]
) -> None:
    WIRE.decode_or_reject(fuzz.corrupt(BASE_BLOBS[index], edits))


# --------------------------------------------------------------------------- one rule at a time

REAL = ("slots", 0, "real", 1)  # r1's second realisation: 3 objects


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    ("path", "index"),
    [
        ((*REAL, "lin"), 0),
        ((*REAL, "lin"), 8),
        ((*REAL, "info"), 0),
        ((*REAL, "info"), 44),
        ((*REAL, "eta"), 0),
        ((*REAL, "eta"), 8),
        (("slots", 2, "real", 2, "info"), 3),
    ],
)
def test_codec_non_finite_blob_is_invalid(path: Path, index: int, value: float) -> None:
    WIRE.assert_rejected(WIRE.poke(path, index, value), InvalidValue, field_name(path))


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_codec_non_finite_phi_and_position_are_invalid(value: float) -> None:
    WIRE.assert_rejected(WIRE.with_((*REAL, "phi"), value), InvalidValue, "slots[0].real[1].phi")
    WIRE.assert_rejected(WIRE.with_(("pos",), [0.0, value]), InvalidValue, "pos")
    WIRE.assert_rejected(WIRE.with_(("pos",), [value, 0.0]), InvalidValue, "pos")


def _symmetric(n: int, smallest: float) -> np.ndarray:
    """A symmetric (3n, 3n) matrix with eigenvalues 1..2 except one equal to ``smallest``."""
    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.standard_normal((3 * n, 3 * n)))
    eig = np.linspace(1.0, 2.0, 3 * n)
    eig[0] = smallest
    m = q @ np.diag(eig) @ q.T
    return (m + m.T) / 2.0


@pytest.mark.parametrize("smallest", [-1.0, -1e-3, -1e-6])
def test_codec_indefinite_info_is_invalid(smallest: float) -> None:
    WIRE.assert_rejected(
        WIRE.with_((*REAL, "info"), _upper(_symmetric(3, smallest))),
        InvalidValue,
        "slots[0].real[1].info",
    )


def test_codec_negated_info_is_invalid() -> None:
    info = REF.stack.slots[0].summary.realisations[1].info
    WIRE.assert_rejected(
        WIRE.with_((*REAL, "info"), _upper(-info)), InvalidValue, "slots[0].real[1].info"
    )


def test_codec_negative_eigenvalue_within_psd_tol_is_accepted() -> None:
    decode(WIRE.with_((*REAL, "info"), _upper(_symmetric(3, -1e-13))))
    with pytest.raises(InvalidValue):
        decode(WIRE.with_((*REAL, "info"), _upper(_symmetric(3, -1e-13))), Limits(psd_tol=1e-15))


@pytest.mark.parametrize("name", ["lin", "info", "eta"])
@pytest.mark.parametrize("change", [-8, 8, -1, 1, None])
def test_codec_wrong_blob_length_is_malformed(name: str, change: int | None) -> None:
    """``change`` bytes added or cut; None empties the blob."""
    path = (*REAL, name)
    blob = get_at(REF_DOC, path)
    new = b"" if change is None else blob[:change] if change < 0 else blob + bytes(change)
    WIRE.assert_rejected(WIRE.with_(path, new), MalformedMessage, field_name(path))


@pytest.mark.parametrize("classes", [b"", b"\x00\x01", b"\x00\x01\x00\x01"])
def test_codec_wrong_class_count_is_malformed(classes: bytes) -> None:
    WIRE.assert_rejected(WIRE.with_((*REAL, "c"), classes), MalformedMessage, "slots[0].real[1].c")


def test_codec_object_count_disagreeing_with_arrays_is_malformed() -> None:
    # Drop one object id: the first realisation's class bytes no longer match.
    objects = get_at(REF_DOC, ("slots", 0, "objects"))
    WIRE.assert_rejected(
        WIRE.with_(("slots", 0, "objects"), objects[:-1]), MalformedMessage, "slots[0].real[0].c"
    )
    # Empty slot r2 given an object: its realisation has no class byte for it.
    WIRE.assert_rejected(
        WIRE.with_(("slots", 1, "objects"), [4]), MalformedMessage, "slots[1].real[0].c"
    )


WRONG_TYPES = [
    (("sender",), 5, MalformedMessage),
    (("sender",), None, MalformedMessage),
    (("sender",), b"r0", MalformedMessage),
    (("sender",), ["r0"], MalformedMessage),
    (("k",), 7.0, MalformedMessage),
    (("k",), "7", MalformedMessage),
    (("k",), True, MalformedMessage),
    (("k",), None, MalformedMessage),
    (("k",), -1, InvalidValue),
    (("k",), 2**63, InvalidValue),
    (("pos",), "xy", MalformedMessage),
    (("pos",), 1.5, MalformedMessage),
    (("pos",), {"x": 1.0, "y": 2.0}, MalformedMessage),
    (("pos",), [1.0], MalformedMessage),
    (("pos",), [1.0, 2.0, 3.0], MalformedMessage),
    (("pos",), ["1", 2.0], MalformedMessage),
    (("pos",), [True, 2.0], MalformedMessage),
    (("pos",), [None, 2.0], MalformedMessage),
    (("slots",), None, MalformedMessage),
    (("slots",), {}, MalformedMessage),
    (("slots",), b"", MalformedMessage),
    (("slots", 0), [], MalformedMessage),
    (("slots", 0), "r1", MalformedMessage),
    (("slots", 0, "owner"), 1, MalformedMessage),
    (("slots", 0, "owner"), b"r1", MalformedMessage),
    (("slots", 0, "stamp"), 7.0, MalformedMessage),
    (("slots", 0, "stamp"), "7", MalformedMessage),
    (("slots", 0, "stamp"), True, MalformedMessage),
    (("slots", 0, "stamp"), None, MalformedMessage),
    (("slots", 0, "objects"), b"\x01\x02\x03", MalformedMessage),
    (("slots", 0, "objects"), {}, MalformedMessage),
    (("slots", 0, "objects"), None, MalformedMessage),
    (("slots", 0, "objects", 1), 1.0, MalformedMessage),
    (("slots", 0, "objects", 1), "1", MalformedMessage),
    (("slots", 0, "objects", 1), False, MalformedMessage),
    (("slots", 0, "real"), {}, MalformedMessage),
    (("slots", 0, "real"), None, MalformedMessage),
    (("slots", 0, "real", 1), [], MalformedMessage),
    (("slots", 0, "real", 1), b"", MalformedMessage),
    ((*REAL, "c"), [0, 1, 0], MalformedMessage),
    ((*REAL, "c"), "\x00\x01\x00", MalformedMessage),
    ((*REAL, "c"), None, MalformedMessage),
    ((*REAL, "phi"), "0.5", MalformedMessage),
    ((*REAL, "phi"), b"\x00" * 8, MalformedMessage),
    ((*REAL, "phi"), True, MalformedMessage),
    ((*REAL, "phi"), None, MalformedMessage),
    ((*REAL, "phi"), [0.5], MalformedMessage),
    ((*REAL, "lin"), [0.0] * 9, MalformedMessage),
    ((*REAL, "lin"), "x" * 72, MalformedMessage),
    ((*REAL, "info"), None, MalformedMessage),
    ((*REAL, "info"), 1.0, MalformedMessage),
    ((*REAL, "eta"), [[0.0] * 9], MalformedMessage),
    ((*REAL, "eta"), 0, MalformedMessage),
    # The version and type are compared by value: anything but 1–4 / "stack" is unknown.
    (("v",), "1", UnsupportedVersion),
    (("v",), None, UnsupportedVersion),
    (("v",), [1], UnsupportedVersion),
    (("type",), 1, UnsupportedVersion),
    (("type",), b"stack", UnsupportedVersion),
    (("type",), None, UnsupportedVersion),
]


@pytest.mark.parametrize(
    ("path", "value", "error"),
    [pytest.param(p, v, e, id=f"{field_name(p)}={v!r}") for p, v, e in WRONG_TYPES],
)
def test_codec_wrong_type_is_rejected(
    path: Path, value: Any, error: type[RemoteProtocolError]
) -> None:
    WIRE.assert_rejected(WIRE.with_(path, value), error, field_name(path))


@pytest.mark.parametrize("value", [True, 1.0])
def test_codec_version_of_wrong_type_is_rejected(value: Any) -> None:
    with pytest.raises(RemoteProtocolError):
        decode(WIRE.with_(("v",), value))


@pytest.mark.parametrize("version", [0, 5, -1, 255])
def test_codec_unknown_version_is_unsupported(version: int) -> None:
    WIRE.assert_rejected(WIRE.with_(("v",), version), UnsupportedVersion, "v")
    with pytest.raises(UnsupportedVersion, match=r"this side speaks 1, 2, 3 and 4"):
        decode(WIRE.with_(("v",), version))


def test_codec_unknown_version_is_unsupported_whatever_its_layout() -> None:
    WIRE.assert_rejected(pack({"v": 5, "frames": []}), UnsupportedVersion, "v")


@pytest.mark.parametrize("kind", ["alive", "Stack", "", "stack "])
def test_codec_unknown_message_type_is_unsupported(kind: str) -> None:
    WIRE.assert_rejected(WIRE.with_(("type",), kind), UnsupportedVersion, "type")


@pytest.mark.parametrize(
    ("limits", "field"),
    [
        (Limits(max_slots=2), "slots"),
        (Limits(max_objects=2), "slots[0].objects"),
        (Limits(max_realisations=2), "slots[2].real"),
        (Limits(max_message_bytes=len(REF_BLOB) - 1), "message"),
    ],
)
def test_codec_over_limits_is_rejected(limits: Limits, field: str) -> None:
    WIRE.assert_rejected(REF_BLOB, LimitExceeded, field, limits)


def test_codec_exactly_at_limits_is_accepted() -> None:
    lim = Limits(
        num_classes=3,
        max_message_bytes=len(REF_BLOB),
        max_slots=3,
        max_objects=3,
        max_realisations=3,
    )
    assert_same_message(decode(REF_BLOB, lim), REF)


def test_codec_class_index_at_num_classes_is_invalid() -> None:
    blob = WIRE.with_((*REAL, "c"), bytes([0, 1, 2]))
    WIRE.assert_rejected(blob, InvalidValue, "slots[0].real[1].c", Limits(num_classes=2))
    assert decode(blob, Limits(num_classes=3)).stack.slots[0].summary.realisations[1].classes == (
        0,
        1,
        2,
    )
    WIRE.assert_rejected(
        WIRE.with_((*REAL, "c"), bytes([0, 255, 0])), InvalidValue, "slots[0].real[1].c"
    )


def test_codec_duplicate_owners_are_invalid() -> None:
    WIRE.assert_rejected(WIRE.with_(("slots", 1, "owner"), "r1"), InvalidValue, "slots")


def test_codec_duplicate_object_ids_are_invalid() -> None:
    WIRE.assert_rejected(
        WIRE.with_(("slots", 0, "objects"), [5, 6, 5]), InvalidValue, "slots[0].objects"
    )


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("slots", 0, "stamp"), -1),
        (("slots", 0, "stamp"), 2**63),
        (("slots", 0, "stamp"), 2**64 - 1),
        (("slots", 0, "objects", 2), -1),
        (("slots", 0, "objects", 2), 2**32),
    ],
)
def test_codec_integer_out_of_range_is_invalid(path: Path, value: int) -> None:
    WIRE.assert_rejected(WIRE.with_(path, value), InvalidValue, field_name(path))


def test_codec_slot_without_realisations_is_invalid() -> None:
    WIRE.assert_rejected(WIRE.with_(("slots", 1, "real"), []), InvalidValue, "slots[1].real")


def test_codec_integer_phi_and_position_are_accepted_as_floats() -> None:
    doc = copy.deepcopy(REF_DOC)
    doc["pos"] = [1, -2]
    set_at(doc, (*REAL, "phi"), 3)
    msg = decode(pack(doc))
    assert msg.position == (1.0, -2.0)
    assert msg.stack.slots[0].summary.realisations[1].log_phi == 3.0


@pytest.mark.parametrize(
    "robot_id",
    [
        *BAD_ROBOT_IDS,
        "r1\n",
    ],
)
@pytest.mark.parametrize("path", [("sender",), ("slots", 1, "owner")])
def test_codec_invalid_robot_id_is_invalid(path: Path, robot_id: str) -> None:
    WIRE.assert_rejected(WIRE.with_(path, robot_id), InvalidValue, field_name(path))


@pytest.mark.parametrize("robot_id", ["x" * 32, "A", "Robot_7-b"])
def test_codec_valid_robot_ids_are_accepted(robot_id: str) -> None:
    assert decode(WIRE.with_(("sender",), robot_id)).sender == robot_id


MAPS = [((), "message"), (("slots", 1), "slots[1]"), (("slots", 2, "real", 2), "slots[2].real[2]")]


@pytest.mark.parametrize(
    ("path", "key", "field"),
    [((*p, k), k, f) for p, f in MAPS for k in get_at(REF_DOC, p)],
)
def test_codec_missing_key_is_malformed(path: Path, key: str, field: str) -> None:
    WIRE.assert_rejected(WIRE.without(path), MalformedMessage, field)


@pytest.mark.parametrize("key", ["x", "V", "type2", ""])
@pytest.mark.parametrize(("path", "field"), MAPS)
def test_codec_extra_key_is_malformed(path: Path, field: str, key: str) -> None:
    WIRE.assert_rejected(WIRE.with_((*path, key), 0), MalformedMessage, field)


# --------------------------------------------------------------------------- structured fuzz

MUTATOR = fuzz.Mutator(
    known_keys=(
        *("v", "type", "sender", "k", "pos", "slots", "owner", "stamp", "objects", "real"),
        *("c", "phi", "lin", "info", "eta", "have", "ask", "age"),
    ),
    strings=("stack", "r1", "r1\n", ""),
    edge_ints=(-1, 0, 1, 2, 3, 255, 256, 2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1, -(2**63)),
    float_blob_size=24,
    extra_scalars=(
        st.builds(msgpack.Timestamp, st.integers(0, 2**34 - 1), st.integers(0, 999_999_999)),
    ),
)
SMALL_LIMITS = Limits(
    num_classes=2, max_message_bytes=12_000, max_slots=3, max_objects=3, max_realisations=2
)


@settings(FUZZ, max_examples=4000)
@given(
    index=st.integers(0, len(BASE_DOCS) - 1),
    edits=st.integers(1, 3),
    limits=st.sampled_from([None, None, None, SMALL_LIMITS]),
    data=st.data(),
)
def test_codec_mutated_documents_raise_only_remote_errors(
    index: int, edits: int, limits: Limits | None, data: st.DataObject
) -> None:
    WIRE.decode_or_reject(pack(MUTATOR.mutated(BASE_DOCS[index], edits, data)), limits)


# --------------------------------------------------------------------------- encode


def _message(**changes: Any) -> StackMessage:
    """REF with top-level fields changed, wrong types allowed."""
    return dataclasses.replace(REF, **changes)


def _replace_real(index: int, **changes: Any) -> StackMessage:
    """REF with r1's realisation ``index`` changed."""
    slot = REF.stack.slots[0]
    reals = list(slot.summary.realisations)
    r = reals[index]
    xi = {k: changes.pop(k) for k in ("lin", "info", "eta") if k in changes}
    reals[index] = dataclasses.replace(r, xi=dataclasses.replace(r.xi, **xi), **changes)
    summary = LocalSummary(slot.summary.object_ids, tuple(reals))
    return dataclasses.replace(REF, stack=REF.stack.with_slot(Slot("r1", slot.stamp, summary)))


def _replace_slot(**changes: Any) -> StackMessage:
    """REF with r1's slot changed; a changed owner replaces r1 by a new owner."""
    slot = dataclasses.replace(REF.stack.slots[0], **changes)
    others = tuple(s for s in REF.stack if s.owner != "r1")
    return dataclasses.replace(REF, stack=Stack((*others, slot)))


R1_REALS = REF.stack.slots[0].summary.realisations
R1 = R1_REALS[0]
UNIT_INFO = _symmetric(3, 0.5)  # eigenvalues 0.5..2
ASYMMETRIC = UNIT_INFO.copy()
ASYMMETRIC[0, 1] += 1e-3


def _with_nan(a: np.ndarray) -> np.ndarray:
    out = a.copy()
    out.flat[-1] = math.nan
    return out


@pytest.mark.parametrize(
    ("msg", "field_end"),
    [
        pytest.param(_replace_real(0, info=ASYMMETRIC), "real[0].info", id="asymmetric-info"),
        pytest.param(_replace_real(0, lin=_with_nan(R1.lin)), "real[0].lin", id="nan-lin"),
        pytest.param(_replace_real(0, info=_with_nan(R1.info)), "real[0].info", id="nan-info"),
        pytest.param(_replace_real(0, eta=_with_nan(R1.eta)), "real[0].eta", id="nan-eta"),
        pytest.param(_replace_real(0, log_phi=math.nan), "real[0].phi", id="nan-phi"),
        pytest.param(_replace_real(0, log_phi=-math.inf), "real[0].phi", id="inf-phi"),
        pytest.param(_replace_real(0, lin=R1.lin[:, :2]), "real[0]", id="lin-n-by-2"),
        pytest.param(_replace_real(0, lin=R1.lin[:2]), "real[0]", id="lin-too-few"),
        pytest.param(_replace_real(0, info=R1.info[:, :-1]), "real[0]", id="info-not-square"),
        pytest.param(_replace_real(0, info=R1.info[:6, :6]), "real[0]", id="info-too-small"),
        pytest.param(_replace_real(0, eta=np.append(R1.eta, 0.0)), "real[0]", id="eta-too-long"),
        pytest.param(_replace_real(0, classes=(0, 1)), "real[0].c", id="classes-too-few"),
        pytest.param(_replace_real(0, classes=(0, 1, 256)), "real[0].c", id="class-256"),
        pytest.param(_replace_real(0, classes=(0, -1, 0)), "real[0].c", id="class-negative"),
        pytest.param(dataclasses.replace(REF, position=(math.nan, 0.0)), "pos", id="nan-pos"),
        pytest.param(dataclasses.replace(REF, position=(0.0, math.inf)), "pos", id="inf-pos"),
        pytest.param(_message(position=(0.0, 1.0, 2.0)), "pos", id="pos-3"),
        *(
            pytest.param(dataclasses.replace(REF, sender=s), "sender", id=f"sender-{s!r}")
            for s in ("", "a b", "x" * 33, "r/1")
        ),
        pytest.param(_replace_slot(owner="a b"), "owner", id="owner-space"),
        pytest.param(dataclasses.replace(REF, step=-1), "k", id="step-negative"),
        pytest.param(dataclasses.replace(REF, step=2**63), "k", id="step-2**63"),
        pytest.param(dataclasses.replace(REF, step=True), "k", id="step-bool"),
    ],
)
def test_codec_encode_rejects_what_may_not_be_sent(msg: StackMessage, field_end: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode(msg)
    assert caught.value.field.endswith(field_end)


# Messages every receiver would reject: encode must refuse them with LocalProtocolError (not send
# them, nor fail with another exception), so a sender's bug shows up at the sender.
ENCODE_REJECTS = [
    ("sender-trailing-newline", dataclasses.replace(REF, sender="r1\n"), "ID_PATTERN `$`"),
    ("sender-int", _message(sender=5), "TypeError from re.match"),
    ("pos-str", _message(position=("a", 1.0)), "ValueError from float()"),
    ("stamp-negative", _replace_slot(stamp=-1), "decode: InvalidValue slots[0].stamp"),
    ("stamp-2**64", _replace_slot(stamp=2**64), "OverflowError from msgpack"),
    (
        "duplicate-object-ids",
        _replace_slot(summary=LocalSummary((5, 5, 6), R1_REALS)),
        "decode: InvalidValue slots[0].objects",
    ),
    (
        "negative-object-id",
        _replace_slot(summary=LocalSummary((-1, 5, 6), R1_REALS)),
        "decode: InvalidValue slots[0].objects[0]",
    ),
    (
        "no-realisations",
        _replace_slot(summary=LocalSummary(REF.stack.slots[0].summary.object_ids, ())),
        "decode: InvalidValue slots[0].real",
    ),
    (
        "indefinite-info",
        _replace_real(0, info=-R1.info),
        "decode: InvalidValue slots[0].real[0].info",
    ),
]


@pytest.mark.parametrize(
    "msg",
    [pytest.param(m, id=name) for name, m, _ in ENCODE_REJECTS],
)
def test_codec_encode_rejects_what_decode_rejects(msg: StackMessage) -> None:
    with pytest.raises(LocalProtocolError):
        encode(msg)


@pytest.mark.parametrize("scale", [1e-20, 1e-13])
def test_codec_encode_rejects_asymmetric_info_at_any_scale(scale: float) -> None:
    with pytest.raises(LocalProtocolError):
        encode(_replace_real(0, info=ASYMMETRIC * scale))


# --------------------------------------------------------------------------- absolute limits


def raw_pack(msg: StackMessage) -> bytes:
    """``msg`` laid out as docs/wire.md says, with no check at all: what a faulty peer sends."""

    def real(r: Realisation, n: int) -> dict[str, Any]:
        iu = np.triu_indices(3 * n)
        return {
            "c": bytes(r.classes),
            "phi": float(r.log_phi),
            "lin": np.asarray(r.lin, "<f8").tobytes(),
            "info": np.asarray(r.info, "<f8")[iu].tobytes(),
            "eta": np.asarray(r.eta, "<f8").tobytes(),
        }

    slots = [
        {
            "owner": s.owner,
            "stamp": s.stamp,
            "objects": list(s.summary.object_ids),
            "real": [real(r, len(s.summary.object_ids)) for r in s.summary.realisations],
        }
        for s in msg.stack
    ]
    pos = None if msg.position is None else [float(v) for v in msg.position]
    doc = {"v": 1, "type": "stack", "sender": msg.sender, "k": msg.step, "pos": pos}
    return pack({**doc, "slots": slots})


def with_eigenvalues(eig: list[float], seed: int = 5) -> np.ndarray:
    """An exactly symmetric matrix Q diag(eig) Qᵀ, Q a seeded random rotation."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((len(eig), len(eig))))
    m = q @ np.diag(eig) @ q.T
    return (m + m.T) / 2.0


R1B = R1_REALS[1]  # slots[0].real[1]: 3 objects
R1B_FIELD = "slots[0].real[1]"
ONES = [1.0] * 8
ISSUE_INFO = np.diag([1e12, 1e12, -500.0, *([1.0] * 6)])  # passed the relative check, broke GTSAM
W = DEFAULT.world_extent


def _lin(x: float = 0.0, y: float = 0.0, theta: float = 0.0) -> np.ndarray:
    lin = np.zeros((3, 3))
    lin[1] = (x, y, theta)
    return lin


def _eta_at_bound(info: np.ndarray, factor: float) -> np.ndarray:
    """η along Λ's top eigenvector with ‖η‖ = ``factor``·λmax·δmax (docs/wire.md, "Limits")."""
    lam, vec = np.linalg.eigh(info)
    delta_max = math.pi * math.sqrt(3 * (2 * W * W + 1))
    return np.asarray(vec[:, -1] * lam[-1] * delta_max * factor)


# (changes to slots[0].real[1], error decode raises or None for accepted, field suffix, limits)
NUMBER_CASES: list[tuple[str, dict[str, Any], type[RemoteProtocolError] | None, str, Limits]] = [
    ("issue-info", {"info": ISSUE_INFO}, LimitExceeded, "info", DEFAULT),
    # With room for its 1e12, the issue's Λ is still refused: κ is infinite (λmin + 1/W² < 0).
    ("issue-info-kappa", {"info": ISSUE_INFO}, LimitExceeded, "info", Limits(max_information=1e13)),
    ("lam-max-over", {"info": with_eigenvalues([2e9, *ONES])}, LimitExceeded, "info", DEFAULT),
    ("lam-max-at", {"info": np.diag([1e9] * 9)}, None, "", DEFAULT),
    ("entries-near-float-max", {"info": np.full((9, 9), 1.7e308)}, LimitExceeded, "info", DEFAULT),
    ("indefinite", {"info": with_eigenvalues([-1e-3, *ONES])}, InvalidValue, "info", DEFAULT),
    # Weak information: −5e-9 is above −1/W² = −1e-8 but below −psd_tol·λmax = −1e-9.
    ("indefinite-weak", {"info": with_eigenvalues([-5e-9, *ONES])}, InvalidValue, "info", DEFAULT),
    (
        "ill-conditioned",
        {"info": with_eigenvalues([1e-5, *[1e8] * 8])},
        LimitExceeded,
        "info",
        DEFAULT,
    ),
    ("well-conditioned", {"info": with_eigenvalues([1e-3, *[1e8] * 8])}, None, "", DEFAULT),
    # Negative within psd_tol·λmax = 1e-6, but below −1/W² = −1e-8: κ infinite.
    (
        "negative-kappa",
        {"info": with_eigenvalues([-1e-7, *[1e3] * 8])},
        LimitExceeded,
        "info",
        DEFAULT,
    ),
    # Semidefinite, no information at all in one direction: κ = (λmax + f)/f.
    ("semidefinite", {"info": with_eigenvalues([0.0, *[1e3] * 8])}, None, "", DEFAULT),
    (
        "semidefinite-strong",
        {"info": with_eigenvalues([0.0, *[1e5] * 8])},
        LimitExceeded,
        "info",
        DEFAULT,
    ),
    ("phi-huge", {"log_phi": 1.7e308}, LimitExceeded, "phi", DEFAULT),
    ("phi-over", {"log_phi": -1e6 - 1.0}, LimitExceeded, "phi", DEFAULT),
    ("phi-at", {"log_phi": -1e6}, None, "", DEFAULT),
    ("x-over", {"lin": _lin(x=W * (1 + 1e-12))}, LimitExceeded, "lin", DEFAULT),
    ("y-over", {"lin": _lin(y=-2 * W)}, LimitExceeded, "lin", DEFAULT),
    ("xy-at", {"lin": _lin(x=W, y=-W, theta=-2 * math.pi)}, None, "", DEFAULT),
    ("theta-over", {"lin": _lin(theta=7.0)}, InvalidValue, "lin", DEFAULT),
    ("eta-over", {"eta": _eta_at_bound(R1B.info, 1.001)}, LimitExceeded, "eta", DEFAULT),
    ("eta-under", {"eta": _eta_at_bound(R1B.info, 0.999)}, None, "", DEFAULT),
    ("eta-huge", {"eta": np.full(9, 1e300)}, LimitExceeded, "eta", DEFAULT),
    # √m·max|ηᵢ| overflows to inf (no warning): the scaled norm decides.
    ("eta-near-float-max", {"eta": np.full(9, 1.7e308)}, LimitExceeded, "eta", DEFAULT),
    (
        "eta-of-zero-info",
        {"info": np.zeros((9, 9)), "eta": np.full(9, 1e-300)},
        LimitExceeded,
        "eta",
        DEFAULT,
    ),
    ("tight-world", {"lin": _lin(x=60.0)}, LimitExceeded, "lin", Limits(world_extent=50.0)),
    ("tight-phi", {"log_phi": 11.0}, LimitExceeded, "phi", Limits(max_abs_log_phi=10.0)),
]


@pytest.mark.filterwarnings("error")  # a bound is decided without floating-point warnings
@pytest.mark.parametrize(
    ("changes", "error", "suffix", "limits"),
    [pytest.param(c, e, s, lim, id=name) for name, c, e, s, lim in NUMBER_CASES],
)
def test_codec_numbers_are_bounded_absolutely(
    changes: dict[str, Any], error: type[RemoteProtocolError] | None, suffix: str, limits: Limits
) -> None:
    msg = _replace_real(1, **changes)
    field = f"{R1B_FIELD}.{suffix}"
    if error is None:
        assert_same_message(decode(raw_pack(msg), limits), msg)
        assert encode(msg, limits) == raw_pack(msg)
        return
    WIRE.assert_rejected(raw_pack(msg), error, field, limits)
    with pytest.raises(LocalProtocolError) as caught:
        encode(msg, limits)
    assert caught.value.field == field


@pytest.mark.parametrize(
    ("position", "error", "limits"),
    [
        ((W, -W), None, DEFAULT),
        ((W * (1 + 1e-12), 0.0), LimitExceeded, DEFAULT),
        ((0.0, -1.7976931348623157e308), LimitExceeded, DEFAULT),
        ((51.0, 0.0), LimitExceeded, Limits(world_extent=50.0)),
    ],
)
def test_codec_position_is_within_the_world(
    position: tuple[float, float], error: type[RemoteProtocolError] | None, limits: Limits
) -> None:
    msg = dataclasses.replace(REF, position=position)
    if error is None:
        assert_same_message(decode(encode(msg, limits), limits), msg)
        return
    WIRE.assert_rejected(raw_pack(msg), error, "pos", limits)
    with pytest.raises(LocalProtocolError) as caught:
        encode(msg, limits)
    assert caught.value.field == "pos"


@pytest.mark.parametrize(
    "changes",
    [
        {"max_information": 0.0},
        {"max_information": math.inf},
        {"max_condition": 0.5},
        {"max_abs_log_phi": -1.0},
        {"world_extent": math.nan},
        {"psd_tol": -1e-9},
        {"psd_tol": 1.0},
        {"max_slots": 0},
        {"num_classes": 257},
    ],
)
def test_codec_limits_refuse_meaningless_bounds(changes: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="limits"):
        Limits(**changes)


@pytest.mark.parametrize(
    ("limits", "field"),
    [
        (Limits(max_slots=2), "slots"),
        (Limits(max_objects=2), "slots[0].objects"),
        (Limits(max_realisations=2), "slots[2].real"),
        (Limits(num_classes=2), "slots[2].real[0].c"),
        (Limits(max_message_bytes=len(REF_BLOB) - 1), "message"),
    ],
)
def test_codec_encode_applies_the_count_limits(limits: Limits, field: str) -> None:
    WIRE.assert_rejected(REF_BLOB, RemoteProtocolError, field, limits)
    with pytest.raises(LocalProtocolError) as caught:
        encode(REF, limits)
    assert caught.value.field == field


def _near_limits(rng: np.random.Generator, lim: Limits, n: int) -> Realisation:
    """A realisation whose every number lies near a bound of ``lim``: each rule is broken with
    probability ≈ 0.05, so about half the messages of a few slots are valid."""

    def pick(valid: float, broken: float) -> float:
        return broken if rng.random() < 0.05 else valid

    top = lim.max_information * pick(rng.uniform(0.01, 1.0), rng.uniform(1.0, 3.0))
    floor = 1.0 / lim.world_extent**2
    lowest = (top + floor) / lim.max_condition - floor  # κ exactly at the cap
    low = rng.choice(
        [
            lowest * rng.uniform(1.0, 10.0),
            pick(top, lowest * rng.uniform(0.01, 1.0)),
            pick(top * 0.5, -lim.psd_tol * top * rng.uniform(0.5, 2.0)),
        ]
    )
    eig = np.concatenate([[top, low], rng.uniform(max(low, 0.0), top, 3 * n - 2)])
    info = with_eigenvalues(list(eig), int(rng.integers(0, 2**32)))
    w = lim.world_extent
    lin = rng.uniform(-1, 1, (n, 3)) * [w, w, 2 * math.pi]
    lin[rng.random((n, 3)) < 0.02] *= 1.5
    delta_max = math.pi * math.sqrt(n * (2 * w * w + 1))
    direction = rng.standard_normal(3 * n)
    eta = direction / np.linalg.norm(direction) * top * delta_max * pick(rng.uniform(0, 0.9), 1.5)
    log_phi = lim.max_abs_log_phi * pick(rng.uniform(-1, 1), rng.choice([-1.01, 1.01]))
    classes = tuple(int(c) for c in rng.integers(0, int(pick(lim.num_classes, 255)), n))
    return Realisation(classes, float(log_phi), Xi(lin, info, eta))


def _message_near_limits(rng: np.random.Generator, lim: Limits) -> StackMessage:
    slots = []
    for i in range(int(rng.integers(0, min(lim.max_slots, 3) + 2))):
        n = int(rng.integers(1, min(lim.max_objects, 4) + 2))
        reals = tuple(_near_limits(rng, lim, n) for _ in range(rng.integers(1, 4)))
        slots.append(Slot(f"r{i}", i, LocalSummary(tuple(range(n)), reals)))
    w = lim.world_extent
    pos = (
        float(rng.uniform(-w, w)),
        float(rng.uniform(-w, w) * (1.5 if rng.random() < 0.05 else 1)),
    )
    return StackMessage("s", pos, Stack(tuple(slots)), 1)


PROPERTY_LIMITS = (
    DEFAULT,
    Limits(num_classes=3, max_slots=3, max_objects=3, max_realisations=2, max_message_bytes=5000),
    Limits(max_information=1e3, max_condition=1e4, max_abs_log_phi=20.0, world_extent=50.0),
)


@pytest.mark.parametrize("seed", range(6))
def test_codec_encode_accepts_exactly_what_decode_accepts(seed: int) -> None:
    """Random stacks near every bound, under several Limits: what encode accepts decodes to the
    same message under the same limits; what it refuses, decode refuses (packed without checks),
    naming the same field once the message is small enough for decode to read it."""
    rng = np.random.default_rng(seed)
    seen: dict[str, int] = {"accepted": 0}
    for _ in range(40):
        lim = PROPERTY_LIMITS[int(rng.integers(0, len(PROPERTY_LIMITS)))]
        msg = _message_near_limits(rng, lim)
        raw = raw_pack(msg)
        try:
            blob = encode(msg, lim)
        except LocalProtocolError as exc:
            with pytest.raises((InvalidValue, LimitExceeded)) as caught:
                decode(raw, lim)
            if len(raw) <= lim.max_message_bytes:
                assert caught.value.field == exc.field, (caught.value, exc)
            kind = f"{type(caught.value).__name__} {caught.value.field.split('.')[-1]}"
            seen[kind] = seen.get(kind, 0) + 1
        else:
            assert blob == raw
            got = decode(blob, lim)
            assert_same_message(got, msg)
            assert_within_limits(got, lim)
            seen["accepted"] += 1
    assert seen["accepted"] >= 5 and sum(seen.values()) - seen["accepted"] >= 5, seen


@pytest.mark.parametrize("seed", range(4))
def test_codec_cholesky_certificate_never_accepts_what_the_eigenvalues_refuse(seed: int) -> None:
    """The fast path (one Cholesky, no eigenvalues) may only accept what the eigenvalue rules
    accept: checked one realisation at a time near every bound."""
    rng = np.random.default_rng(seed)
    certified = 0
    for _ in range(300):
        lim = PROPERTY_LIMITS[int(rng.integers(0, len(PROPERTY_LIMITS)))]
        r = _near_limits(rng, lim, int(rng.integers(1, 5)))
        info, eta = r.info[None], r.eta[None]
        if codec._certified(info, eta, lim):
            certified += 1
            assert codec._spectral_problem("slots[0]", info, eta, lim, np.arange(1)) is None
    assert certified >= 30, certified
