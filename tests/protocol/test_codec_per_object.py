"""Per-object slots on the wire (docs/wire.md, "Per-object slots (wire version 3 and 4)"; issue
40 item 2): a slot whose summary is per object travels as one ``real`` map — its kind, the
object dimension, M, the (n, M) class log φ as float32 and the one ξ — in a stack of wire version
3 (4 signed), while a stack of realisation tables only is still version 1 (2), byte for byte.
Every rule is refused by ``decode`` (RemoteProtocolError naming the field) and by ``encode``
(LocalProtocolError naming the same field), signatures cover the map, and the fuzzing of
test_codec runs over per-object messages too.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import struct
from typing import Any

import msgpack
import numpy as np
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.summary import LocalSummary, ObjectClasses, Realisation
from protocol.codec import Limits, StackMessage, decode, encode, sign_slot, with_wire
from protocol.errors import (
    BadSignature,
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
from tests.protocol.fuzz import FUZZ, Path, field_name, get_at, pack
from tests.protocol.test_codec import (
    DEFAULT,
    PROPERTY_LIMITS,
    REF,
    REF_DOC,
    _near_limits,
    _symmetric,
    _upper,
    assert_same_message,
    assert_within_limits,
    bounded,
    make_realisation,
    make_summary,
    raw_pack,
)

LIM = Limits(num_classes=4)
KEYS = {r: Ed25519PrivateKey.generate() for r in ("r1", "r2", "r3")}
PUBLIC = {r: k.public_key() for r, k in KEYS.items()}


# --------------------------------------------------------------------------- valid messages


def make_objects(rng: np.random.Generator, n: int, m: int) -> ObjectClasses:
    """A per-object summary's content valid under the default ``Limits``: the ξ of
    ``make_realisation`` and an (n, M) class log φ within ±max_abs_log_phi (±0, subnormals and
    arbitrary bit patterns included: float32 rounds them on the wire)."""
    xi = make_realisation(rng, n, 2).xi
    return ObjectClasses(bounded(rng, (n, m), DEFAULT.max_abs_log_phi), xi)


def objects_summary(rng: np.random.Generator, n: int, m: int) -> LocalSummary:
    return LocalSummary(tuple(range(40, 40 + n)), (), make_objects(rng, n, m))


# slots[0] is r1 (per object, 3 objects, M = 4), slots[1] r2 (per object, no object, M = 2),
# slots[2] r3 (a realisation table of 2 objects, 3 realisations, M = 3).
REF_PO = StackMessage(
    "r0",
    (1.5, -2.25),
    Stack(
        (
            Slot("r1", 7, objects_summary(np.random.default_rng(1), 3, 4)),
            Slot("r2", 0, objects_summary(np.random.default_rng(2), 0, 2), 1_764_000_000_000),
            Slot("r3", 12, make_summary(np.random.default_rng(3), 2, 3, 3, shared=0.0)),
        )
    ),
    13,
)
REF_PO_BLOB = encode(REF_PO, LIM)
REF_PO_DOC: dict[str, Any] = msgpack.unpackb(REF_PO_BLOB, raw=False)
SIGNED_PO = StackMessage(
    "r2",
    None,
    Stack(tuple(sign_slot(s, KEYS[s.owner], LIM) for s in REF_PO.stack)),
    13,
)
SIGNED_PO_BLOB = encode(SIGNED_PO, LIM)
PO = ("slots", 0, "real")  # r1's per-object map
PO_FIELD = "slots[0].real"


def rounded(phi: Any) -> np.ndarray:
    """Class log φ as it travels: float32, back as float64."""
    with np.errstate(over="ignore"):
        return np.asarray(phi, dtype=np.float64).astype("<f4").astype(np.float64)


def _bits(values: Any) -> bytes:
    return np.asarray(values, dtype=np.float64).tobytes()


def _tables(msg: StackMessage) -> StackMessage:
    table = tuple(s for s in msg.stack if s.summary.per_object is None)
    return dataclasses.replace(msg, stack=Stack(table))


def assert_same_objects(got: StackMessage, want: StackMessage) -> None:
    """``got`` is ``want`` as it travels: the table slots and the ξ to the bit, the class log φ
    to the bit of its float32 rounding, as read-only float64 arrays."""
    assert_same_message(_tables(got), _tables(want))
    assert [(s.owner, s.version, s.summary.kind) for s in got.stack] == [
        (s.owner, s.version, s.summary.kind) for s in want.stack
    ]
    for g, w in zip(got.stack, want.stack, strict=True):
        assert g.signature == w.signature
        if w.summary.per_object is None:
            continue
        assert g.summary.object_ids == tuple(w.summary.object_ids)
        assert len(g.summary.realisations) == 0
        go, wo = g.summary.per_object, w.summary.per_object
        assert go is not None
        phi = go.log_phi
        assert phi.dtype == np.float64 and phi.shape == np.shape(wo.log_phi), g.owner
        assert not phi.flags.writeable
        assert _bits(phi) == _bits(rounded(wo.log_phi)), g.owner
        assert g.summary.distinct_xi() == ([go.xi], [])
        for name in ("lin", "info", "eta"):
            ga, wa = getattr(go.xi, name), getattr(wo.xi, name)
            assert ga.dtype == np.float64 and ga.shape == np.shape(wa), f"{g.owner}.{name}"
            assert _bits(ga) == _bits(wa), f"{g.owner}.{name}"
            assert not ga.flags.writeable


def _as_table(slot: Slot) -> Slot:
    """A per-object slot's ξ as the one realisation of a table slot (for the table checks)."""
    po = slot.summary.per_object
    if po is None:
        return slot
    n = len(slot.summary.object_ids)
    table = LocalSummary(slot.summary.object_ids, (Realisation((0,) * n, 0.0, po.xi),))
    return Slot(slot.owner, slot.stamp, table, slot.epoch)


def _check_valid(msg: StackMessage, lim: Limits) -> None:
    """What a successful decode promises, per-object slots included, and that ``encode`` takes
    the decoded values back (without the received bytes) to the same message."""
    for slot in msg.stack:
        n = len(slot.summary.object_ids)
        po = slot.summary.per_object
        if po is None:
            assert 1 <= len(slot.summary.realisations) <= lim.max_realisations
            for r in slot.summary.realisations:
                assert len(r.classes) == n and all(0 <= c < lim.num_classes for c in r.classes)
                assert math.isfinite(r.log_phi)
            continue
        assert len(slot.summary.realisations) == 0 and n <= lim.max_objects
        phi = po.log_phi
        assert phi.ndim == 2 and phi.shape[0] == n and 1 <= phi.shape[1] <= lim.num_classes
        assert np.isfinite(phi).all() and np.all(np.abs(phi) <= lim.max_abs_log_phi)
        assert _bits(rounded(phi)) == _bits(phi)  # float32 values
        assert po.xi.lin.shape == (n, 3) and po.xi.info.shape == (3 * n, 3 * n)
        assert np.array_equal(po.xi.info, po.xi.info.T)
        for a in (po.xi.lin, po.xi.info, po.xi.eta):
            assert np.all(np.isfinite(a))
    as_tables = Stack(tuple(_as_table(s) for s in msg.stack))
    assert_within_limits(dataclasses.replace(msg, stack=as_tables), lim)
    # Re-encoded anew (not spliced), a mutated document may grow: an int log φ of a table
    # becomes a float64.
    roomy = dataclasses.replace(lim, max_message_bytes=DEFAULT.max_message_bytes)
    bare = Stack(tuple(dataclasses.replace(s, wire=None) for s in msg.stack))
    again = decode(encode(dataclasses.replace(msg, stack=bare), roomy), roomy)
    assert_same_objects(again, msg)


WIRE = fuzz.Wire(decode, REF_PO_DOC, LIM, _check_valid)


def raw_pack_objects(msg: StackMessage, version: int | None = None) -> bytes:
    """``msg`` laid out as docs/wire.md says, with no check at all: what a faulty peer sends
    (version 3 when a slot is per object, else 1, unless given)."""

    def table(s: Slot, n: int) -> list[dict[str, Any]]:
        iu = np.triu_indices(3 * n)
        return [
            {
                "c": bytes(r.classes),
                "phi": float(r.log_phi),
                "lin": np.asarray(r.lin, "<f8").tobytes(),
                "info": np.asarray(r.info, "<f8")[iu].tobytes(),
                "eta": np.asarray(r.eta, "<f8").tobytes(),
            }
            for r in s.summary.realisations
        ]

    def objects(po: ObjectClasses, n: int) -> dict[str, Any]:
        iu = np.triu_indices(3 * n)
        phi = np.asarray(po.log_phi)
        with np.errstate(over="ignore"):
            phi32 = phi.astype("<f4")
        return {
            "kind": "objects",
            "dim": 3,
            "m": int(phi.shape[1]),
            "phi": phi32.tobytes(),
            "lin": np.asarray(po.xi.lin, "<f8").tobytes(),
            "info": np.asarray(po.xi.info, "<f8")[iu].tobytes(),
            "eta": np.asarray(po.xi.eta, "<f8").tobytes(),
        }

    slots = []
    for s in msg.stack:
        n = len(s.summary.object_ids)
        po = s.summary.per_object
        real = table(s, n) if po is None else objects(po, n)
        slot = {"owner": s.owner, "stamp": s.stamp, "objects": list(s.summary.object_ids)}
        slots.append({**slot, "real": real, **({"epoch": s.epoch} if s.epoch else {})})
    if version is None:
        version = 3 if any(s.summary.per_object is not None for s in msg.stack) else 1
    pos = None if msg.position is None else [float(v) for v in msg.position]
    doc = {"v": version, "type": "stack", "sender": msg.sender, "k": msg.step, "pos": pos}
    return pack({**doc, "slots": slots})


def _replace_objects(
    *, phi: Any = None, reals: tuple[Realisation, ...] = (), **xi: Any
) -> StackMessage:
    """REF_PO with r1's per-object content changed (wrong shapes and types allowed)."""
    slot = REF_PO.stack.slots[0]
    po = slot.summary.per_object
    assert po is not None
    new = ObjectClasses(po.log_phi if phi is None else phi, dataclasses.replace(po.xi, **xi))
    summary = LocalSummary(slot.summary.object_ids, reals, new)
    return dataclasses.replace(REF_PO, stack=REF_PO.stack.with_slot(Slot("r1", 7, summary)))


def _r1() -> ObjectClasses:
    po = REF_PO.stack.slots[0].summary.per_object
    assert po is not None
    return po


R1 = _r1()


def _with(a: np.ndarray, at: tuple[int, ...], value: float) -> np.ndarray:
    out = np.array(a, dtype=float)
    out[at] = value
    return out


def _phi_with(value: float, at: tuple[int, int] = (1, 2)) -> np.ndarray:
    return _with(R1.log_phi, at, value)


def _poke32(path: Path, index: int, value: float) -> bytes:
    """REF_PO_DOC with float32 number ``index`` of the binary at ``path`` replaced."""
    blob = get_at(REF_PO_DOC, path)
    return WIRE.with_(path, blob[: 4 * index] + struct.pack("<f", value) + blob[4 * index + 4 :])


# --------------------------------------------------------------------------- round trips


def test_per_object_round_trip_rounds_phi_to_float32_and_keeps_xi_to_the_bit() -> None:
    got = decode(REF_PO_BLOB, LIM)
    assert_same_objects(got, REF_PO)
    assert [s.summary.kind for s in got.stack] == ["per_object", "per_object", "table"]
    r1 = got.stack.slots[0].summary.per_object
    assert r1 is not None
    assert np.allclose(r1.log_phi, R1.log_phi, rtol=2**-24, atol=1e-45)  # float32's half ulp
    assert encode(got, LIM) == REF_PO_BLOB  # the decoded values encode to the same bytes
    bare = Stack(tuple(dataclasses.replace(s, wire=None) for s in got.stack))
    assert encode(dataclasses.replace(got, stack=bare), LIM) == REF_PO_BLOB


def test_per_object_wire_layout_matches_docs() -> None:
    doc = REF_PO_DOC
    assert doc["v"] == 3
    real = doc["slots"][0]["real"]
    assert list(real) == ["kind", "dim", "m", "phi", "lin", "info", "eta"]
    assert (real["kind"], real["dim"], real["m"]) == ("objects", 3, 4)
    assert real["phi"] == np.asarray(R1.log_phi, "<f8").astype("<f4").tobytes()
    assert real["lin"] == R1.xi.lin.astype("<f8").tobytes()
    assert real["info"] == _upper(R1.xi.info)
    assert real["eta"] == R1.xi.eta.astype("<f8").tobytes()
    empty = doc["slots"][1]["real"]
    assert empty == {
        "kind": "objects",
        "dim": 3,
        "m": 2,
        "phi": b"",
        "lin": b"",
        "info": b"",
        "eta": b"",
    }
    assert doc["slots"][1]["epoch"] == 1_764_000_000_000
    assert isinstance(doc["slots"][2]["real"], list)  # the table slot, as in version 1
    assert raw_pack_objects(REF_PO) == REF_PO_BLOB


def test_a_table_only_stack_is_still_version_1_and_2_byte_for_byte() -> None:
    blob = encode(REF)
    assert msgpack.unpackb(blob)["v"] == 1
    assert blob == raw_pack(REF)  # the version-1 layout of docs/wire.md, packed by hand
    assert_same_message(decode(blob), REF)
    signed = Stack(tuple(sign_slot(s, KEYS[s.owner]) for s in REF.stack))
    assert msgpack.unpackb(encode(dataclasses.replace(REF, stack=signed)))["v"] == 2
    # The table slot of a version-3 stack is the very bytes of its version-1 slot, and sent on
    # its own (decoded from version 3, or made anew) it is version 1 again.
    r3 = REF_PO.stack.by_owner()["r3"]
    alone = encode(StackMessage("r0", None, Stack((r3,)), 13), LIM)
    assert msgpack.unpackb(alone)["v"] == 1

    def slot_bytes(blob: bytes, i: int) -> bytes:
        frame = scan(blob)["slots"][i]
        return blob[frame.start : frame.end]

    assert slot_bytes(REF_PO_BLOB, 2) == slot_bytes(alone, 0)
    relayed = decode(REF_PO_BLOB, LIM).stack.by_owner()["r3"]
    assert encode(StackMessage("r0", None, Stack((relayed,)), 13), LIM) == alone


def test_a_version_3_stack_of_tables_only_decodes_as_version_1() -> None:
    doc = copy.deepcopy(REF_DOC)
    doc["v"] = 3
    assert_same_message(decode(pack(doc)), REF)


@pytest.mark.parametrize("version", [0, 5, 6, -1, 255])
def test_versions_other_than_1_to_4_are_refused_naming_the_ones_spoken(version: int) -> None:
    WIRE.assert_rejected(WIRE.with_(("v",), version), UnsupportedVersion, "v")
    with pytest.raises(UnsupportedVersion, match=r"this side speaks 1, 2, 3 and 4"):
        decode(WIRE.with_(("v",), version), LIM)


@pytest.mark.parametrize(("n", "m"), [(0, 1), (1, 2), (3, 4), (15, 3), (15, 200), (60, 256)])
def test_per_object_size_matches_docs(n: int, m: int) -> None:
    """docs/wire.md: ``real`` is 4nM + 36n² + 60n bytes of numbers, plus
    38 + s(M) + h(4nM) + 2·h(24n) + h(36n² + 12n) of map, keys, kind, dim, M and headers."""
    lim = Limits(num_classes=256)
    summary = objects_summary(np.random.default_rng(n + m), n, m)
    blob = encode(StackMessage("r0", None, Stack((Slot("r1", 1, summary),))), lim)
    a, b = scan(blob)["slots"][0].spans["real"]

    def h(length: int) -> int:
        return 2 if length < 2**8 else 3 if length < 2**16 else 5

    s = 1 if m < 128 else 2 if m < 256 else 3
    payload = 4 * n * m + 36 * n * n + 60 * n
    assert b - a == payload + 38 + s + h(4 * n * m) + 2 * h(24 * n) + h(36 * n * n + 12 * n)
    if (n, m) == (15, 3):
        assert b - a == 9230


def test_a_per_object_slot_is_independent_of_the_number_of_hypotheses() -> None:
    """The default belief's 300 realisations of 15 objects take about 20 KB as a table; per
    object the same ξ and 15 × 3 class log φ take 9 230 bytes (a stack of 9.3 KB), whatever the
    belief's size."""
    rng = np.random.default_rng(3)
    first = make_realisation(rng, 15, 3)
    reals = [first] + [
        dataclasses.replace(make_realisation(rng, 15, 3), xi=first.xi) for _ in range(299)
    ]
    table = LocalSummary(tuple(range(15)), tuple(reals))
    objects = LocalSummary(tuple(range(15)), (), ObjectClasses(np.zeros((15, 3)), first.xi))
    sizes = [
        len(encode(StackMessage("r0", None, Stack((Slot("r1", 1, s),))))) for s in (table, objects)
    ]
    assert sizes[0] > 20_000 and sizes[1] < 9_400  # 9 230 of them its real


# --------------------------------------------------------------------------- signed slots


def test_signed_per_object_slots_are_version_4_and_a_relay_re_sends_them() -> None:
    doc = msgpack.unpackb(SIGNED_PO_BLOB)
    assert doc["v"] == 4 and all(set(s) >= {"epoch", "sig"} for s in doc["slots"])
    received = decode(SIGNED_PO_BLOB, LIM, PUBLIC)
    assert_same_objects(received, SIGNED_PO)
    relayed = encode(StackMessage("r3", (1.0, 2.0), received.stack, 14), LIM)
    again = decode(relayed, LIM, PUBLIC)
    assert_same_objects(
        again, dataclasses.replace(SIGNED_PO, sender="r3", position=(1.0, 2.0), step=14)
    )
    assert encode(dataclasses.replace(SIGNED_PO, stack=again.stack), LIM) == SIGNED_PO_BLOB
    # the table slot alone, signed, is version 2
    alone = encode(StackMessage("r3", None, Stack((received.stack.by_owner()["r3"],)), 1), LIM)
    assert msgpack.unpackb(alone)["v"] == 2
    assert decode(alone, LIM, PUBLIC).stack.slots[0].summary.kind == "table"


def test_a_tampered_phi_byte_fails_the_signature() -> None:
    phi = REF_PO_DOC["slots"][0]["real"]["phi"]
    at = SIGNED_PO_BLOB.index(phi)
    bad = bytearray(SIGNED_PO_BLOB)
    bad[at] ^= 0x01  # the lowest mantissa bit of log φ[0, 0]: still a valid number
    with pytest.raises(BadSignature, match="does not verify") as caught:
        decode(bytes(bad), LIM, PUBLIC)
    assert caught.value.field == "slots[0].sig"
    # without keys the changed number is taken: the signature is what refuses it
    got = decode(bytes(bad), LIM).stack.slots[0].summary.per_object
    assert got is not None and got.log_phi[0, 0] != rounded(R1.log_phi)[0, 0]


@pytest.mark.parametrize(
    ("key", "value"), [("kind", "object"), ("dim", 2), ("m", 3), ("phi", b"\x00" * 48)]
)
def test_kind_dim_m_and_phi_are_signed(key: str, value: Any) -> None:
    doc = msgpack.unpackb(SIGNED_PO_BLOB, raw=False)
    doc["slots"][0]["real"][key] = value
    with pytest.raises(BadSignature) as caught:
        decode(pack(doc), LIM, PUBLIC)
    assert caught.value.field == "slots[0].sig"


def test_every_changed_byte_of_a_signed_per_object_slot_is_refused() -> None:
    slot = sign_slot(REF_PO.stack.slots[0], KEYS["r1"], LIM)
    data = encode(StackMessage("r2", None, Stack((slot,)), 3), LIM)
    frame = scan(data)["slots"][0]
    for offset in range(frame.start, frame.end):
        for flip in (0x01, 0x80):
            bad = bytearray(data)
            bad[offset] ^= flip
            with pytest.raises(RemoteProtocolError):
                decode(bytes(bad), LIM, PUBLIC)


def test_a_per_object_map_in_a_version_1_or_2_stack_is_refused() -> None:
    """Maps exist from version 3: a version-1 or -2 stack whose ``real`` is one is refused, with
    keys or without, whatever the map holds."""
    doc = copy.deepcopy(REF_PO_DOC)
    doc["v"] = 1
    WIRE.assert_rejected(pack(doc), MalformedMessage, PO_FIELD)
    with pytest.raises(MalformedMessage, match="wire version 3 or 4"):
        decode(pack(doc), LIM)
    signed = msgpack.unpackb(SIGNED_PO_BLOB, raw=False)
    signed["v"] = 2  # "v" is not signed: the slot verifies, its body is refused
    for keys in (None, PUBLIC):
        with pytest.raises(MalformedMessage) as caught:
            decode(pack(signed), LIM, keys)
        assert caught.value.field == PO_FIELD
    doc["slots"][0]["real"] = {}
    WIRE.assert_rejected(pack(doc), MalformedMessage, PO_FIELD)


def test_unsigned_per_object_slots_are_refused_by_a_fleet_with_keys() -> None:
    with pytest.raises(BadSignature, match="wire version 3"):
        decode(REF_PO_BLOB, LIM, PUBLIC)


def test_a_stack_mixing_signed_and_unsigned_per_object_slots_is_refused() -> None:
    mixed = Stack((SIGNED_PO.stack.slots[0], REF_PO.stack.slots[1]))
    with pytest.raises(LocalProtocolError, match="signed and unsigned"):
        encode(StackMessage("r2", None, mixed, 3), LIM)


# --------------------------------------------------------------------------- wire forms, hooks


def test_with_wire_makes_a_per_object_slots_bytes_once() -> None:
    slot = REF_PO.stack.slots[0]
    made = with_wire(slot, LIM)
    assert made.wire is not None and made.wire.fits(made)
    msg = StackMessage("r0", None, Stack((slot,)), 1)
    blob = encode(msg, LIM)
    assert encode(dataclasses.replace(msg, stack=Stack((made,))), LIM) == blob
    frame = scan(blob)["slots"][0]
    assert made.wire.data == blob[frame.start : frame.end]
    with pytest.raises(LocalProtocolError) as caught:
        with_wire(_replace_objects(phi=_phi_with(math.nan)).stack.slots[0], LIM)
    assert caught.value.field == "slot.real.phi"


def test_decoded_per_object_slots_carry_their_bytes_and_the_hooks_work_the_same() -> None:
    got = decode(REF_PO_BLOB, LIM)
    for slot in got.stack:
        assert slot.wire is not None and slot.wire.fits(slot)
    skipped = decode(REF_PO_BLOB, LIM, wanted=lambda owner, epoch, stamp: owner != "r1")
    assert skipped.skipped == ("r1",) and [s.owner for s in skipped.stack] == ["r2", "r3"]
    held = got.stack.by_owner()
    again = decode(REF_PO_BLOB, LIM, parsed=lambda owner, epoch, stamp: held.get(owner))
    assert again.reused == ("r1", "r2", "r3")
    assert all(a is held[a.owner] for a in again.stack)
    # a per-object body that is not wanted is neither parsed nor validated
    bad = _poke32((*PO, "phi"), 0, math.nan)
    with pytest.raises(InvalidValue):
        decode(bad, LIM)
    assert decode(bad, LIM, wanted=lambda owner, epoch, stamp: owner != "r1").skipped == ("r1",)


def test_scan_locates_a_per_object_body() -> None:
    frame = scan(REF_PO_BLOB)["slots"][0]
    a, b = frame.spans["real"]
    assert msgpack.unpackb(REF_PO_BLOB[a:b], raw=False) == REF_PO_DOC["slots"][0]["real"]


# --------------------------------------------------------------------------- one rule at a time


def _resized(name: str, change: int | None) -> bytes:
    blob = get_at(REF_PO_DOC, (*PO, name))
    new = b"" if change is None else blob[:change] if change < 0 else blob + bytes(change)
    return WIRE.with_((*PO, name), new)


# (blob, error, field): every malformed per-object field, one at a time
MALFORMED: list[tuple[str, bytes, type[RemoteProtocolError], str, Limits]] = [
    ("kind-table", WIRE.with_((*PO, "kind"), "table"), InvalidValue, "kind", LIM),
    ("kind-points", WIRE.with_((*PO, "kind"), "points"), InvalidValue, "kind", LIM),
    ("kind-bin", WIRE.with_((*PO, "kind"), b"objects"), MalformedMessage, "kind", LIM),
    ("kind-nil", WIRE.with_((*PO, "kind"), None), MalformedMessage, "kind", LIM),
    # A kind or a dimension this side does not know is named before the keys are compared.
    ("kind-alone", WIRE.with_(PO, {"kind": "points"}), InvalidValue, "kind", LIM),
    ("dim-2", WIRE.with_((*PO, "dim"), 2), InvalidValue, "dim", LIM),
    ("dim-2-alone", WIRE.with_(PO, {"kind": "objects", "dim": 2}), InvalidValue, "dim", LIM),
    ("dim-4", WIRE.with_((*PO, "dim"), 4), InvalidValue, "dim", LIM),
    ("dim-float", WIRE.with_((*PO, "dim"), 3.0), MalformedMessage, "dim", LIM),
    ("dim-bool", WIRE.with_((*PO, "dim"), True), MalformedMessage, "dim", LIM),
    ("m-0", WIRE.with_((*PO, "m"), 0), InvalidValue, "m", LIM),
    ("m-negative", WIRE.with_((*PO, "m"), -1), InvalidValue, "m", LIM),
    ("m-over-num-classes", WIRE.with_((*PO, "m"), 5), InvalidValue, "m", LIM),
    ("m-over-a-smaller-num-classes", REF_PO_BLOB, InvalidValue, "m", Limits(num_classes=3)),
    ("m-str", WIRE.with_((*PO, "m"), "4"), MalformedMessage, "m", LIM),
    ("m-float", WIRE.with_((*PO, "m"), 4.0), MalformedMessage, "m", LIM),
    ("m-disagrees-with-phi", WIRE.with_((*PO, "m"), 3), MalformedMessage, "phi", LIM),
    *(
        (f"{name}-{change}", _resized(name, change), MalformedMessage, name, LIM)
        for name in ("phi", "lin", "info", "eta")
        for change in (-8, -4, -1, 1, 4, 8, None)
    ),
    ("phi-str", WIRE.with_((*PO, "phi"), "x" * 48), MalformedMessage, "phi", LIM),
    ("phi-list", WIRE.with_((*PO, "phi"), [0.0] * 12), MalformedMessage, "phi", LIM),
    ("phi-float64", WIRE.with_((*PO, "phi"), bytes(96)), MalformedMessage, "phi", LIM),
    ("lin-nil", WIRE.with_((*PO, "lin"), None), MalformedMessage, "lin", LIM),
    ("info-float", WIRE.with_((*PO, "info"), 1.0), MalformedMessage, "info", LIM),
    *(
        (f"phi-{value}-{i}", _poke32((*PO, "phi"), i, value), InvalidValue, "phi", LIM)
        for value in (math.nan, math.inf, -math.inf)
        for i in (0, 11)
    ),
    ("phi-huge", _poke32((*PO, "phi"), 5, 3e38), LimitExceeded, "phi", LIM),
    ("phi-over", _poke32((*PO, "phi"), 5, -1.0001e6), LimitExceeded, "phi", LIM),
    (
        "phi-tight",
        _poke32((*PO, "phi"), 5, 11.0),
        LimitExceeded,
        "phi",
        Limits(num_classes=4, max_abs_log_phi=10.0),
    ),
    ("lin-nan", WIRE.poke((*PO, "lin"), 4, math.nan), InvalidValue, "lin", LIM),
    ("lin-theta", WIRE.poke((*PO, "lin"), 5, 7.0), InvalidValue, "lin", LIM),
    ("lin-x", WIRE.poke((*PO, "lin"), 3, 2e4), LimitExceeded, "lin", LIM),
    ("info-nan", WIRE.poke((*PO, "info"), 44, math.inf), InvalidValue, "info", LIM),
    (
        "info-indefinite",
        WIRE.with_((*PO, "info"), _upper(_symmetric(3, -1.0))),
        InvalidValue,
        "info",
        LIM,
    ),
    ("info-huge", WIRE.with_((*PO, "info"), _upper(np.eye(9) * 2e9)), LimitExceeded, "info", LIM),
    ("eta-nan", WIRE.poke((*PO, "eta"), 8, math.nan), InvalidValue, "eta", LIM),
    ("eta-huge", WIRE.with_((*PO, "eta"), np.full(9, 1e300).tobytes()), LimitExceeded, "eta", LIM),
]


@pytest.mark.parametrize(
    ("blob", "error", "suffix", "limits"),
    [pytest.param(b, e, s, lim, id=name) for name, b, e, s, lim in MALFORMED],
)
def test_a_malformed_per_object_field_is_refused_naming_it(
    blob: bytes, error: type[RemoteProtocolError], suffix: str, limits: Limits
) -> None:
    WIRE.assert_rejected(blob, error, f"{PO_FIELD}.{suffix}", limits)


@pytest.mark.parametrize("key", ["kind", "dim", "m", "phi", "lin", "info", "eta"])
def test_a_missing_per_object_key_is_malformed(key: str) -> None:
    WIRE.assert_rejected(WIRE.without((*PO, key)), MalformedMessage, PO_FIELD)
    with pytest.raises(MalformedMessage, match=f"missing keys \\['{key}'\\]"):
        decode(WIRE.without((*PO, key)), LIM)


@pytest.mark.parametrize("key", ["x", "c", "xi", "Kind", ""])
def test_an_extra_per_object_key_is_malformed(key: str) -> None:
    WIRE.assert_rejected(WIRE.with_((*PO, key), 0), MalformedMessage, PO_FIELD)


def test_a_per_object_map_of_the_wrong_object_count_is_malformed() -> None:
    # r2 has no object: r1's map there has 3 objects' bytes
    WIRE.assert_rejected(
        WIRE.with_(("slots", 1, "real"), REF_PO_DOC["slots"][0]["real"]),
        MalformedMessage,
        "slots[1].real.phi",
    )


def test_phi_within_the_bound_is_accepted_and_decoded_read_only() -> None:
    got = decode(_poke32((*PO, "phi"), 5, -1e6), LIM).stack.slots[0].summary.per_object
    assert got is not None and got.log_phi[1, 1] == -1e6
    with pytest.raises(ValueError, match="read-only"):
        got.log_phi[0, 0] = 1.0


# --------------------------------------------------------------------------- encode


ASYMMETRIC = R1.xi.info.copy()
ASYMMETRIC[0, 1] += 1e-3

# (changes to r1, the field suffix after "slots[0].real", limits, whether decode sees it too)
ENCODE_CASES: list[tuple[str, StackMessage, str, Limits, bool]] = [
    ("phi-nan", _replace_objects(phi=_phi_with(math.nan)), ".phi", LIM, True),
    ("phi-inf", _replace_objects(phi=_phi_with(-math.inf)), ".phi", LIM, True),
    ("phi-over", _replace_objects(phi=_phi_with(2e6)), ".phi", LIM, True),
    ("phi-beyond-float32", _replace_objects(phi=_phi_with(1e300)), ".phi", LIM, True),
    # 0.1 rounds up to 0.10000000149 in float32: over a bound of exactly 0.1 as it travels
    (
        "phi-rounds-over",
        _replace_objects(phi=np.full((3, 4), 0.1)),
        ".phi",
        Limits(num_classes=4, max_abs_log_phi=0.1),
        True,
    ),
    ("m-0", _replace_objects(phi=np.zeros((3, 0))), ".m", LIM, True),
    ("m-over", _replace_objects(phi=np.zeros((3, 5))), ".m", LIM, True),
    ("lin-nan", _replace_objects(lin=_with(R1.xi.lin, (1, 1), math.nan)), ".lin", LIM, True),
    ("lin-theta", _replace_objects(lin=R1.xi.lin + np.array([0.0, 0.0, 20.0])), ".lin", LIM, True),
    ("info-indefinite", _replace_objects(info=_symmetric(3, -1.0)), ".info", LIM, True),
    ("eta-huge", _replace_objects(eta=np.full(9, 1e300)), ".eta", LIM, True),
    # what only the sender can get wrong: shapes, types, an asymmetric Λ, realisations
    ("info-asymmetric", _replace_objects(info=ASYMMETRIC), ".info", LIM, False),
    ("phi-rows", _replace_objects(phi=np.zeros((2, 4))), ".phi", LIM, False),
    ("phi-1d", _replace_objects(phi=np.zeros(3)), ".phi", LIM, False),
    ("phi-bool", _replace_objects(phi=np.zeros((3, 4), dtype=bool)), ".phi", LIM, False),
    ("phi-complex", _replace_objects(phi=np.zeros((3, 4), dtype=complex)), ".phi", LIM, False),
    ("lin-n-by-2", _replace_objects(lin=R1.xi.lin[:, :2]), "", LIM, False),
    ("info-too-small", _replace_objects(info=R1.xi.info[:6, :6]), "", LIM, False),
    ("eta-too-long", _replace_objects(eta=np.append(R1.xi.eta, 0.0)), "", LIM, False),
    (
        "with-realisations",
        _replace_objects(reals=(Realisation((0, 1, 2), 0.0, R1.xi),)),
        "",
        LIM,
        False,
    ),
]


@pytest.mark.filterwarnings("error")  # decided without floating-point warnings
@pytest.mark.parametrize(
    ("msg", "suffix", "limits", "remote"),
    [pytest.param(m, s, lim, r, id=name) for name, m, s, lim, r in ENCODE_CASES],
)
def test_encode_refuses_what_decode_refuses_naming_the_same_field(
    msg: StackMessage, suffix: str, limits: Limits, remote: bool
) -> None:
    field = f"{PO_FIELD}{suffix}"
    with pytest.raises(LocalProtocolError) as caught:
        encode(msg, limits)
    assert caught.value.field == field
    assert str(caught.value).startswith(f"{field}: ")
    if remote:  # the same values packed without checks: decode refuses the same field
        with pytest.raises(RemoteProtocolError) as refused:
            decode(raw_pack_objects(msg), limits)
        assert refused.value.field == field


def test_encode_accepts_integer_phi_and_the_bound_itself() -> None:
    msg = _replace_objects(phi=np.array([[1, -2, 3, 0]] * 3))
    got = decode(encode(msg, LIM), LIM).stack.slots[0].summary.per_object
    assert got is not None and got.log_phi.tolist() == [[1.0, -2.0, 3.0, 0.0]] * 3
    at_bound = _replace_objects(phi=_phi_with(-1e6))
    assert_same_objects(decode(encode(at_bound, LIM), LIM), at_bound)


def _objects_near_limits(rng: np.random.Generator, lim: Limits, n: int) -> ObjectClasses:
    """Per-object content whose every number lies near a bound of ``lim`` (the ξ of
    test_codec's ``_near_limits``); M beyond ``num_classes`` or a log φ over its bound, each
    with probability ≈ 0.05."""
    xi = _near_limits(rng, lim, n).xi
    m = int(rng.integers(1, lim.num_classes + 1))
    if rng.random() < 0.05:
        m = lim.num_classes + 1
    phi = lim.max_abs_log_phi * rng.uniform(-1, 1, (n, m))
    if rng.random() < 0.1:
        phi[int(rng.integers(0, n)), int(rng.integers(0, m))] = lim.max_abs_log_phi * rng.choice(
            [-1.01, 1.01, 1.0, -1.0]
        )
    return ObjectClasses(phi, xi)


@pytest.mark.parametrize("seed", range(6))
def test_encode_accepts_exactly_what_decode_accepts(seed: int) -> None:
    """Random stacks of per-object and table slots near every bound, under several Limits: what
    encode accepts is the raw layout and decodes to the same message; what it refuses, decode
    refuses naming the same field."""
    rng = np.random.default_rng(seed)
    seen: dict[str, int] = {"accepted": 0}
    for _ in range(40):
        lim = PROPERTY_LIMITS[int(rng.integers(0, len(PROPERTY_LIMITS)))]
        slots = []
        for i in range(int(rng.integers(1, min(lim.max_slots, 3) + 1))):
            n = int(rng.integers(1, min(lim.max_objects, 4) + 1))
            if rng.random() < 0.7:
                summary = LocalSummary(tuple(range(n)), (), _objects_near_limits(rng, lim, n))
            else:
                summary = LocalSummary(tuple(range(n)), (_near_limits(rng, lim, n),))
            slots.append(Slot(f"r{i}", i, summary))
        msg = StackMessage("s", None, Stack(tuple(slots)), 1)
        raw = raw_pack_objects(msg)
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
            assert_same_objects(decode(blob, lim), msg)
            seen["accepted"] += 1
    assert seen["accepted"] >= 5 and sum(seen.values()) - seen["accepted"] >= 5, seen


# --------------------------------------------------------------------------- fuzz

BLOBS = (REF_PO_BLOB, SIGNED_PO_BLOB)
DOCS = tuple(msgpack.unpackb(b, raw=False) for b in BLOBS)


@pytest.mark.parametrize("index", range(len(BLOBS)))
def test_every_truncated_prefix_of_a_per_object_stack_is_malformed(index: int) -> None:
    WIRE.assert_every_prefix_malformed(BLOBS[index])


@settings(FUZZ, max_examples=1000)
@given(index=st.integers(0, len(BLOBS) - 1), edits=fuzz.BYTE_EDITS)
def test_corrupted_per_object_stacks_raise_only_remote_errors(
    index: int, edits: list[tuple[int, int]]
) -> None:
    WIRE.decode_or_reject(fuzz.corrupt(BLOBS[index], edits))


MUTATOR = fuzz.Mutator(
    known_keys=(
        *("v", "type", "sender", "k", "pos", "slots", "owner", "stamp", "objects", "real"),
        *("epoch", "sig", "kind", "dim", "m", "c", "phi", "lin", "info", "eta", "xi"),
    ),
    strings=("stack", "objects", "table", "r1", ""),
    edge_ints=(-1, 0, 1, 2, 3, 4, 5, 255, 256, 2**32 - 1, 2**63 - 1, 2**64 - 1, -(2**63)),
    float_blob_size=24,
    numbers=fuzz.FLOAT64S | st.floats(width=32).map(lambda x: struct.pack("<ff", x, x)),
)
SMALL_LIMITS = Limits(
    num_classes=2, max_message_bytes=4_000, max_slots=3, max_objects=3, max_realisations=2
)


@settings(FUZZ, max_examples=3000)
@given(
    index=st.integers(0, len(DOCS) - 1),
    edits=st.integers(1, 3),
    limits=st.sampled_from([None, None, None, SMALL_LIMITS]),
    data=st.data(),
)
def test_mutated_per_object_documents_raise_only_remote_errors(
    index: int, edits: int, limits: Limits | None, data: st.DataObject
) -> None:
    WIRE.decode_or_reject(pack(MUTATOR.mutated(DOCS[index], edits, data)), limits)


def test_fuzz_reference_documents_decode() -> None:
    """The fuzzing starts from valid messages: both decode and pass the checks."""
    for blob in BLOBS:
        _check_valid(decode(blob, LIM), LIM)
    assert field_name(PO) == PO_FIELD
