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

from estimator.sparse_xi import SparseXi, Structure, sparsify
from estimator.summary import LocalSummary, ObjectClasses, Realisation, Xi
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
        assert go is not None and go.local_ids == wo.local_ids
        phi = go.log_phi
        assert phi.dtype == np.float64 and phi.shape == np.shape(wo.log_phi), g.owner
        assert not phi.flags.writeable
        assert _bits(phi) == _bits(rounded(wo.log_phi)), g.owner
        if isinstance(wo.xi, SparseXi):
            assert isinstance(go.xi, SparseXi), g.owner
            assert_same_sparse(go.xi, wo.xi, g.owner)
            (dense,), which = g.summary.distinct_xi()
            assert which == [] and _bits(dense.info) == _bits(go.xi.dense().info)
            continue
        assert g.summary.distinct_xi() == ([go.xi], [])
        for name in ("lin", "info", "eta"):
            ga, wa = getattr(go.xi, name), getattr(wo.xi, name)
            assert ga.dtype == np.float64 and ga.shape == np.shape(wa), f"{g.owner}.{name}"
            assert _bits(ga) == _bits(wa), f"{g.owner}.{name}"
            assert not ga.flags.writeable


def assert_same_sparse(got: SparseXi, want: SparseXi, owner: str) -> None:
    """A decoded sparse ξ is the sent one to the bit (its values float32 already), as read-only
    float64 arrays, the diagonal blocks mirrored from their upper entries, no structure."""
    for name in ("lin", "diag_info", "edge_info", "eta"):
        ga, wa = getattr(got, name), getattr(want, name)
        assert ga.dtype == np.float64 and ga.shape == np.shape(wa), f"{owner}.{name}"
        assert _bits(ga) == _bits(wa), f"{owner}.{name}"
        assert not ga.flags.writeable
    assert got.edges.shape == np.shape(want.edges) and got.edges.dtype.kind == "i"
    assert np.array_equal(got.edges, want.edges) and not got.edges.flags.writeable
    assert got.structure is None


def _as_table(slot: Slot) -> Slot:
    """A per-object slot's ξ (a sparse one in its dense form) as the one realisation of a table
    slot (for the table checks)."""
    po = slot.summary.per_object
    if po is None:
        return slot
    n = len(slot.summary.object_ids)
    xi = po.xi.dense() if isinstance(po.xi, SparseXi) else po.xi
    table = LocalSummary(slot.summary.object_ids, (Realisation((0,) * n, 0.0, xi),))
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
        if isinstance(po.xi, SparseXi):
            _check_valid_sparse(po.xi, n)
            continue
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


def _check_valid_sparse(sx: SparseXi, n: int) -> None:
    """What a decoded sparse ξ promises: its shapes, edges i < j < n sorted and each once, at
    most 10 per object, float32 values, symmetric diagonal blocks, Λ_s positive definite."""
    e = len(sx.edges)
    assert sx.lin.shape == (n, 3) and sx.diag_info.shape == (n, 3, 3) and sx.eta.shape == (3 * n,)
    assert sx.edges.shape == (e, 2) and sx.edge_info.shape == (e, 3, 3) and e <= 10 * n
    if e:
        i, j = sx.edges.T
        assert (i >= 0).all() and (i < j).all() and (j < n).all()
        assert (np.diff(i * n + j) > 0).all()
    for a in (sx.diag_info, sx.edge_info, sx.eta):
        assert _bits(rounded(a)) == _bits(a)
    assert np.array_equal(sx.diag_info, sx.diag_info.transpose(0, 2, 1))
    for a in (sx.lin, sx.diag_info, sx.edge_info, sx.eta):
        assert np.all(np.isfinite(a))
    if n:
        np.linalg.cholesky(sx.dense().info)  # positive definite


def _decode_lim(blob: bytes, limits: Limits | None) -> StackMessage:
    """``decode`` under ``LIM`` when given no limits: the limits the checks then hold it to (the
    fuzz once copied an object id into ``m``, 42, which the codec's own default of 64 classes
    takes and ``LIM``'s 4 do not)."""
    return decode(blob, limits or LIM)


WIRE = fuzz.Wire(_decode_lim, REF_PO_DOC, LIM, _check_valid)


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
        phi = np.asarray(po.log_phi)
        with np.errstate(over="ignore"):
            phi32 = phi.astype("<f4")
        head = {"kind": "objects", "dim": 3, "m": int(phi.shape[1]), "phi": phi32.tobytes()}
        if isinstance(po.xi, SparseXi):
            return head | sparse_fields(po.xi)
        iu = np.triu_indices(3 * n)
        return head | {
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


def sparse_fields(sx: SparseXi) -> dict[str, Any]:
    """A sparse ξ's keys of a per-object map, as docs/wire.md lays them out, unchecked."""
    iu = np.triu_indices(3)
    with np.errstate(over="ignore", invalid="ignore"):
        return {
            "lin": np.asarray(sx.lin, "<f8").tobytes(),
            "xi": "sparse",
            "diag": np.asarray(sx.diag_info)[:, iu[0], iu[1]].astype("<f4").tobytes(),
            "edges": np.asarray(sx.edges).astype("<u2").tobytes(),
            "edge_info": np.asarray(sx.edge_info).astype("<f4").tobytes(),
            "eta": np.asarray(sx.eta).astype("<f4").tobytes(),
        }


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
assert isinstance(R1.xi, Xi)
R1_XI: Xi = R1.xi  # r1's dense ξ


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
    assert real["lin"] == R1_XI.lin.astype("<f8").tobytes()
    assert real["info"] == _upper(R1_XI.info)
    assert real["eta"] == R1_XI.eta.astype("<f8").tobytes()
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
    # dimension 2 (point objects) is known: a pose slot's body then has the wrong byte counts
    ("dim-2", WIRE.with_((*PO, "dim"), 2), MalformedMessage, "lin", LIM),
    ("dim-1-alone", WIRE.with_(PO, {"kind": "objects", "dim": 1}), InvalidValue, "dim", LIM),
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


@pytest.mark.parametrize("key", ["x", "c", "diag", "Kind", ""])
def test_an_extra_per_object_key_is_malformed(key: str) -> None:
    WIRE.assert_rejected(WIRE.with_((*PO, key), 0), MalformedMessage, PO_FIELD)


def test_xi_names_the_form_of_a_per_object_xi() -> None:
    """``xi`` is the one key a dense map lacks and a sparse one has: on a dense map it is read
    first (a form this side does not know is named as such), then the sparse map's keys."""
    WIRE.assert_rejected(WIRE.with_((*PO, "xi"), 0), MalformedMessage, f"{PO_FIELD}.xi")
    WIRE.assert_rejected(WIRE.with_((*PO, "xi"), "dense"), InvalidValue, f"{PO_FIELD}.xi")
    WIRE.assert_rejected(WIRE.with_((*PO, "xi"), "sparse"), MalformedMessage, PO_FIELD)
    with pytest.raises(MalformedMessage, match=r"missing keys \['diag', 'edge_info', 'edges'\]"):
        decode(WIRE.with_((*PO, "xi"), "sparse"), LIM)


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


ASYMMETRIC = R1_XI.info.copy()
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
    ("lin-nan", _replace_objects(lin=_with(R1_XI.lin, (1, 1), math.nan)), ".lin", LIM, True),
    ("lin-theta", _replace_objects(lin=R1_XI.lin + np.array([0.0, 0.0, 20.0])), ".lin", LIM, True),
    ("info-indefinite", _replace_objects(info=_symmetric(3, -1.0)), ".info", LIM, True),
    ("eta-huge", _replace_objects(eta=np.full(9, 1e300)), ".eta", LIM, True),
    # what only the sender can get wrong: shapes, types, an asymmetric Λ, realisations
    ("info-asymmetric", _replace_objects(info=ASYMMETRIC), ".info", LIM, False),
    ("phi-rows", _replace_objects(phi=np.zeros((2, 4))), ".phi", LIM, False),
    ("phi-1d", _replace_objects(phi=np.zeros(3)), ".phi", LIM, False),
    ("phi-bool", _replace_objects(phi=np.zeros((3, 4), dtype=bool)), ".phi", LIM, False),
    ("phi-complex", _replace_objects(phi=np.zeros((3, 4), dtype=complex)), ".phi", LIM, False),
    ("lin-n-by-2", _replace_objects(lin=R1_XI.lin[:, :2]), "", LIM, False),
    ("info-too-small", _replace_objects(info=R1_XI.info[:6, :6]), "", LIM, False),
    ("eta-too-long", _replace_objects(eta=np.append(R1_XI.eta, 0.0)), "", LIM, False),
    (
        "with-realisations",
        _replace_objects(reals=(Realisation((0, 1, 2), 0.0, R1_XI),)),
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


# --------------------------------------------------------------------------- sparse ξ


def make_sparse(rng: np.random.Generator, n: int, structure: Structure | None = None) -> SparseXi:
    """A sparse ξ valid under the default ``Limits``: ``sparsify`` of ``make_realisation``'s ξ
    (on ``structure``, else a fitted net), rounded to float32 as a sender rounds it."""
    sx = sparsify(make_realisation(rng, n, 2).xi, structure=structure)
    # (SparseXi.float32 fails on no object — LAPACK refuses an empty solve; nothing to round)
    return sx.float32() if n else sx


def sparse_summary(
    rng: np.random.Generator, n: int, m: int, structure: Structure | None = None
) -> LocalSummary:
    phi = bounded(rng, (n, m), DEFAULT.max_abs_log_phi)
    return LocalSummary(
        tuple(range(70, 70 + n)), (), ObjectClasses(phi, make_sparse(rng, n, structure))
    )


# edges (0, 1) (0, 2) (0, 3) (1, 2) (2, 3) (3, 4): object 3's parents 0 and 2 are married
CHAIN5 = Structure((0, 1, 2, 3, 4), ((), (0,), (1,), (0, 2), (3,)))
# slots[0] r1: a sparse ξ of 5 objects (M = 4); slots[1] r2: a sparse ξ of no object (M = 2);
# slots[2] r3: a dense per-object slot (3 objects).
REF_SP = StackMessage(
    "r0",
    (0.5, -0.25),
    Stack(
        (
            Slot("r1", 9, sparse_summary(np.random.default_rng(11), 5, 4, CHAIN5)),
            Slot("r2", 3, sparse_summary(np.random.default_rng(12), 0, 2)),
            Slot("r3", 7, objects_summary(np.random.default_rng(13), 3, 4)),
        )
    ),
    10,
)
REF_SP_BLOB = encode(REF_SP, LIM)
REF_SP_DOC: dict[str, Any] = msgpack.unpackb(REF_SP_BLOB, raw=False)
SIGNED_SP = StackMessage(
    "r3", None, Stack(tuple(sign_slot(s, KEYS[s.owner], LIM) for s in REF_SP.stack)), 10
)
SIGNED_SP_BLOB = encode(SIGNED_SP, LIM)
SWIRE = fuzz.Wire(_decode_lim, REF_SP_DOC, LIM, _check_valid)


def _sp() -> SparseXi:
    po = REF_SP.stack.slots[0].summary.per_object
    assert po is not None and isinstance(po.xi, SparseXi)
    return po.xi


SP = _sp()
SPARSE_KEYS = ["kind", "dim", "m", "phi", "lin", "xi", "diag", "edges", "edge_info", "eta"]


def test_sparse_round_trip_is_bit_exact() -> None:
    got = decode(REF_SP_BLOB, LIM)
    assert_same_objects(got, REF_SP)
    assert [s.summary.kind for s in got.stack] == ["per_object"] * 3
    sx = got.stack.slots[0].summary.per_object
    assert sx is not None and isinstance(sx.xi, SparseXi)
    assert _bits(sx.xi.dense().info) == _bits(SP.dense().info)  # the very Λ_s the sender meant
    assert encode(got, LIM) == REF_SP_BLOB
    bare = Stack(tuple(dataclasses.replace(s, wire=None) for s in got.stack))
    assert encode(dataclasses.replace(got, stack=bare), LIM) == REF_SP_BLOB


def test_sparse_wire_layout_matches_docs() -> None:
    doc = REF_SP_DOC
    assert doc["v"] == 3
    real = doc["slots"][0]["real"]
    assert list(real) == SPARSE_KEYS
    assert (real["kind"], real["dim"], real["m"], real["xi"]) == ("objects", 3, 4, "sparse")
    assert real["lin"] == SP.lin.astype("<f8").tobytes()
    iu = np.triu_indices(3)
    assert real["diag"] == SP.diag_info[:, iu[0], iu[1]].astype("<f4").tobytes()
    assert SP.edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3], [3, 4]]
    assert real["edges"] == bytes(
        [0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 1, 0, 2, 0, 2, 0, 3, 0, 3, 0, 4, 0]
    )
    assert real["edge_info"] == SP.edge_info.astype("<f4").tobytes()  # row-major 3 × 3 blocks
    assert real["eta"] == SP.eta.astype("<f4").tobytes()
    empty = doc["slots"][1]["real"]
    assert empty == {
        "kind": "objects",
        "dim": 3,
        "m": 2,
        "phi": b"",
        "lin": b"",
        "xi": "sparse",
        "diag": b"",
        "edges": b"",
        "edge_info": b"",
        "eta": b"",
    }
    assert "xi" not in doc["slots"][2]["real"]  # a dense map as before
    assert raw_pack_objects(REF_SP) == REF_SP_BLOB


@pytest.mark.parametrize(
    ("n", "m", "extra"), [(0, 1, 2), (1, 2, 2), (4, 3, 0), (12, 4, 2), (80, 4, 2), (90, 200, 3)]
)
def test_sparse_size_matches_docs(n: int, m: int, extra: int) -> None:
    """docs/wire.md: a sparse ``real`` is 4nM + 60n + 40E bytes of numbers, plus
    64 + s(M) + h(4nM) + 2·h(24n) + h(12n) + h(4E) + h(36E) of map, keys and headers."""
    rng = np.random.default_rng(n + m)
    phi = bounded(rng, (n, m), DEFAULT.max_abs_log_phi)
    xi = sparsify(make_realisation(rng, n, 2).xi, extra_parents=extra)
    xi = xi.float32() if n else xi
    summary = LocalSummary(tuple(range(n)), (), ObjectClasses(phi, xi))
    lim = Limits(num_classes=256)
    blob = encode(StackMessage("r0", None, Stack((Slot("r1", 1, summary),))), lim)
    a, b = scan(blob)["slots"][0].spans["real"]

    def h(length: int) -> int:
        return 2 if length < 2**8 else 3 if length < 2**16 else 5

    e = len(xi.edges)
    s = 1 if m < 128 else 2 if m < 256 else 3
    payload = 4 * n * m + 60 * n + 40 * e
    headers = h(4 * n * m) + 2 * h(24 * n) + h(12 * n) + h(4 * e) + h(36 * e)
    assert b - a == payload + 64 + s + headers
    # p parents per object: at most p(p + 1)/2 moral edges per object
    assert e <= (extra + 1) * (extra + 2) // 2 * n


def test_a_sparse_slot_is_linear_in_its_objects() -> None:
    """80 objects of a single-robot tour, M = 4: a sparse ξ under 220 bytes per object where
    the dense ξ of the same objects takes 36·3·80 + … ≈ 2.9 kB per object."""
    from tests.estimator.test_sparse_xi import _tour_xi

    xi = _tour_xi(80, 0)
    sizes = []
    for shared in (xi, sparsify(xi).float32()):
        summary = LocalSummary(tuple(range(80)), (), ObjectClasses(np.zeros((80, 4)), shared))
        sizes.append(len(encode(StackMessage("r0", None, Stack((Slot("r1", 1, summary),))), LIM)))
    assert sizes[0] / 80 > 2_800 and sizes[1] / 80 < 220, sizes


def _sp_with(**changes: Any) -> StackMessage:
    """REF_SP with r1's sparse ξ changed (anything allowed)."""
    slot = REF_SP.stack.slots[0]
    po = slot.summary.per_object
    assert po is not None
    new = ObjectClasses(po.log_phi, dataclasses.replace(SP, **changes))
    summary = LocalSummary(slot.summary.object_ids, (), new)
    return dataclasses.replace(REF_SP, stack=REF_SP.stack.with_slot(Slot("r1", 9, summary)))


def _f32(values: Any) -> bytes:
    return np.asarray(values, dtype=float).astype("<f4").tobytes()


def _diag_bytes(blocks: np.ndarray) -> bytes:
    iu = np.triu_indices(3)
    return _f32(blocks[:, iu[0], iu[1]])


def _spoke32(name: str, index: int, value: float) -> bytes:
    """REF_SP_DOC with float32 number ``index`` of r1's binary ``name`` replaced."""
    blob = get_at(REF_SP_DOC, (*PO, name))
    return SWIRE.with_(
        (*PO, name), blob[: 4 * index] + struct.pack("<f", value) + blob[4 * index + 4 :]
    )


def _sresized(name: str, change: int | None) -> bytes:
    blob = get_at(REF_SP_DOC, (*PO, name))
    new = b"" if change is None else blob[:change] if change < 0 else blob + bytes(change)
    return SWIRE.with_((*PO, name), new)


def _edges_doc(edges: list[tuple[int, int]], blocks: np.ndarray | None = None) -> bytes:
    """REF_SP_DOC with r1's edges (and edge blocks, by default those of the first edges)."""
    if blocks is None:
        blocks = np.resize(SP.edge_info, (len(edges), 3, 3))
    doc = copy.deepcopy(REF_SP_DOC)
    real = doc["slots"][0]["real"]
    real["edges"] = np.array(edges, dtype="<u2").reshape(-1, 2).tobytes()
    real["edge_info"] = _f32(blocks)
    return pack(doc)


def _diag_doc(blocks: np.ndarray) -> bytes:
    return SWIRE.with_((*PO, "diag"), _diag_bytes(blocks))


LAM_MAX = float(np.linalg.eigvalsh(SP.dense().info)[-1])
SWAPPED = [(0, 2), (0, 1), (0, 3), (1, 2), (2, 3), (3, 4)]
# Λ_s positive semidefinite but singular: identity diagonal blocks, objects 0 and 1 linked by
# −I (Λ on them [[I, −I], [−I, I]], λmin = 0): within psd_tol and κ = (2 + f)/f < max_condition,
# refused only because a sparse ξ must be positive definite.
SINGULAR_DIAG = np.tile(np.eye(3), (5, 1, 1))
SINGULAR_EDGES = np.zeros((6, 3, 3))
SINGULAR_EDGES[0] = -np.eye(3)
EDGE_INDEFINITE = np.array(SP.edge_info)
EDGE_INDEFINITE[0] = 4.0 * LAM_MAX * np.eye(3)

# (name, blob, error, field suffix after "slots[0].real", limits): every malformed sparse field
MALFORMED_SPARSE: list[tuple[str, bytes, type[RemoteProtocolError], str, Limits]] = [
    ("xi-int", SWIRE.with_((*PO, "xi"), 1), MalformedMessage, ".xi", LIM),
    ("xi-bin", SWIRE.with_((*PO, "xi"), b"sparse"), MalformedMessage, ".xi", LIM),
    ("xi-dense", SWIRE.with_((*PO, "xi"), "dense"), InvalidValue, ".xi", LIM),
    ("xi-lowrank", SWIRE.with_((*PO, "xi"), "lowrank"), InvalidValue, ".xi", LIM),
    ("kind-first", SWIRE.with_((*PO, "kind"), "points"), InvalidValue, ".kind", LIM),
    ("info-extra", SWIRE.with_((*PO, "info"), b""), MalformedMessage, "", LIM),
    ("m-over", SWIRE.with_((*PO, "m"), 5), InvalidValue, ".m", LIM),
    *(
        (f"{name}-{change}", _sresized(name, change), MalformedMessage, f".{name}", LIM)
        for name in ("phi", "lin", "diag", "edge_info", "eta")
        for change in (-8, -4, -1, 1, 4, 8, None)
    ),
    *(
        (f"edges-{change}", _sresized("edges", change), MalformedMessage, ".edges", LIM)
        for change in (-3, -2, -1, 1, 2, 3)
    ),
    # a whole edge more or less: edge_info no longer has 9 numbers per edge
    *(
        (f"edges-pair-{change}", _sresized("edges", change), MalformedMessage, ".edge_info", LIM)
        for change in (-4, 4, None)
    ),
    ("edges-list", SWIRE.with_((*PO, "edges"), [0, 1]), MalformedMessage, ".edges", LIM),
    ("edge-info-float", SWIRE.with_((*PO, "edge_info"), 1.0), MalformedMessage, ".edge_info", LIM),
    ("edges-over-10n", _edges_doc([(0, 1)] * 51), LimitExceeded, ".edges", LIM),
    ("edges-j-out", _edges_doc([(0, 1), (0, 5)]), InvalidValue, ".edges", LIM),
    ("edges-i-is-j", _edges_doc([(0, 1), (2, 2)]), InvalidValue, ".edges", LIM),
    ("edges-reversed", _edges_doc([(1, 0)]), InvalidValue, ".edges", LIM),
    ("edges-unsorted", _edges_doc(SWAPPED), InvalidValue, ".edges", LIM),
    ("edges-twice", _edges_doc([(0, 1), (0, 1)]), InvalidValue, ".edges", LIM),
    ("phi-nan", _spoke32("phi", 3, math.nan), InvalidValue, ".phi", LIM),
    ("lin-nan", SWIRE.poke((*PO, "lin"), 4, math.nan), InvalidValue, ".lin", LIM),
    ("lin-x", SWIRE.poke((*PO, "lin"), 3, 2e4), LimitExceeded, ".lin", LIM),
    ("lin-theta", SWIRE.poke((*PO, "lin"), 5, 7.0), InvalidValue, ".lin", LIM),
    ("diag-nan", _spoke32("diag", 7, math.nan), InvalidValue, ".diag", LIM),
    ("edge-info-inf", _spoke32("edge_info", 10, math.inf), InvalidValue, ".edge_info", LIM),
    ("eta-nan", _spoke32("eta", 14, math.nan), InvalidValue, ".eta", LIM),
    ("diag-huge", _diag_doc(np.tile(2e9 * np.eye(3), (5, 1, 1))), LimitExceeded, ".diag", LIM),
    ("diag-indefinite", _spoke32("diag", 0, -1.0), InvalidValue, ".diag", LIM),
    (
        "diag-singular",
        _diag_doc(np.tile(np.diag([1.0, 1.0, 0.0]), (5, 1, 1))),
        InvalidValue,
        ".diag",
        LIM,
    ),
    (
        "edge-indefinite",
        _edges_doc(SP.edges.tolist(), EDGE_INDEFINITE),
        InvalidValue,
        ".edge_info",
        LIM,
    ),
    (
        "edge-huge",
        _edges_doc(SP.edges.tolist(), np.tile(2e9 * np.eye(3), (6, 1, 1))),
        LimitExceeded,
        ".edge_info",
        LIM,
    ),
    (
        "singular",
        pack(
            {
                **REF_SP_DOC,
                "slots": [
                    {
                        **REF_SP_DOC["slots"][0],
                        "real": {
                            **REF_SP_DOC["slots"][0]["real"],
                            "diag": _diag_bytes(SINGULAR_DIAG),
                            "edge_info": _f32(SINGULAR_EDGES),
                            "eta": bytes(60),
                        },
                    },
                    *REF_SP_DOC["slots"][1:],
                ],
            }
        ),
        InvalidValue,
        ".edge_info",
        LIM,
    ),
    ("eta-huge", SWIRE.with_((*PO, "eta"), _f32(np.full(15, 1e30))), LimitExceeded, ".eta", LIM),
    (
        "diag-tight",
        REF_SP_BLOB,
        LimitExceeded,
        ".diag",
        Limits(num_classes=4, max_information=0.5 * float(np.abs(SP.diag_info).max())),
    ),
]


@pytest.mark.parametrize(
    ("blob", "error", "suffix", "limits"),
    [pytest.param(b, e, s, lim, id=name) for name, b, e, s, lim in MALFORMED_SPARSE],
)
def test_a_malformed_sparse_field_is_refused_naming_it(
    blob: bytes, error: type[RemoteProtocolError], suffix: str, limits: Limits
) -> None:
    SWIRE.assert_rejected(blob, error, f"{PO_FIELD}{suffix}", limits)


@pytest.mark.parametrize("key", SPARSE_KEYS)
def test_a_missing_sparse_key_is_malformed(key: str) -> None:
    SWIRE.assert_rejected(SWIRE.without((*PO, key)), MalformedMessage, PO_FIELD)


def test_the_singular_case_passes_every_rule_of_a_dense_xi() -> None:
    """The "singular" Λ_s above is accepted as a dense ξ: positive definiteness is the one rule
    a sparse ξ adds (its factors are summed into D one by one)."""
    info = SparseXi(SP.lin, SINGULAR_DIAG, SP.edges, SINGULAR_EDGES, np.zeros(15)).dense().info
    dense = dataclasses.replace(
        REF_PO,
        stack=Stack(
            (
                Slot(
                    "r1",
                    1,
                    LocalSummary(
                        tuple(range(5)),
                        (),
                        ObjectClasses(np.zeros((5, 4)), Xi(SP.lin, info, np.zeros(15))),
                    ),
                ),
            )
        ),
    )
    assert decode(encode(dense, LIM), LIM).stack.slots[0].summary.per_object is not None
    assert float(np.linalg.eigvalsh(info)[0]) == pytest.approx(0.0, abs=1e-12)


NOT_F32 = np.array(SP.diag_info)
NOT_F32[2, 1, 1] += 1e-6 * NOT_F32[2, 1, 1]  # between two float32 values
ASYMMETRIC_DIAG = np.array(SP.diag_info)
ASYMMETRIC_DIAG[1, 0, 2] *= 2.0  # still a float32 value, now unlike [1, 2, 0]
assert ASYMMETRIC_DIAG[1, 0, 2] != 0.0

# (changes to r1's sparse ξ, the field suffix after "slots[0].real", limits, whether decode
# refuses the same values packed without checks)
SPARSE_ENCODE_CASES: list[tuple[str, StackMessage, str, Limits, bool]] = [
    ("edges-unsorted", _sp_with(edges=np.array(SWAPPED)), ".edges", LIM, True),
    ("edges-twice", _sp_with(edges=np.array([[0, 1]] * 6)), ".edges", LIM, True),
    (
        "edges-j-out",
        _sp_with(edges=np.array([[0, 1], [0, 2], [0, 3], [1, 2], [2, 3], [3, 5]])),
        ".edges",
        LIM,
        True,
    ),
    (
        "edges-over-10n",
        _sp_with(edges=np.array([[0, 1]] * 51), edge_info=np.zeros((51, 3, 3))),
        ".edges",
        LIM,
        True,
    ),
    ("lin-nan", _sp_with(lin=_with(SP.lin, (1, 1), math.nan)), ".lin", LIM, True),
    ("lin-x", _sp_with(lin=_with(SP.lin, (2, 0), 2e4)), ".lin", LIM, True),
    ("diag-nan", _sp_with(diag_info=_with(SP.diag_info, (1, 1, 1), math.nan)), ".diag", LIM, True),
    ("diag-indefinite", _sp_with(diag_info=-SP.diag_info), ".diag", LIM, True),
    (
        "edge-inf",
        _sp_with(edge_info=_with(SP.edge_info, (2, 0, 1), math.inf)),
        ".edge_info",
        LIM,
        True,
    ),
    ("edge-indefinite", _sp_with(edge_info=EDGE_INDEFINITE), ".edge_info", LIM, True),
    (
        "singular",
        _sp_with(diag_info=SINGULAR_DIAG, edge_info=SINGULAR_EDGES, eta=np.zeros(15)),
        ".edge_info",
        LIM,
        True,
    ),
    ("eta-nan", _sp_with(eta=_with(SP.eta, (4,), math.nan)), ".eta", LIM, True),
    (
        "eta-huge",
        _sp_with(eta=np.full(15, 1e30).astype(np.float32).astype(float)),
        ".eta",
        LIM,
        True,
    ),
    # what only the sender can get wrong: shapes, types, values that are not float32, an
    # asymmetric diagonal block
    ("lin-n-by-2", _sp_with(lin=SP.lin[:, :2]), "", LIM, False),
    ("diag-short", _sp_with(diag_info=SP.diag_info[:4]), "", LIM, False),
    ("edges-float", _sp_with(edges=SP.edges.astype(float)), "", LIM, False),
    ("edges-by-3", _sp_with(edges=np.zeros((6, 3), dtype=int)), "", LIM, False),
    ("edge-info-short", _sp_with(edge_info=SP.edge_info[:5]), "", LIM, False),
    ("eta-long", _sp_with(eta=np.append(SP.eta, 0.0)), "", LIM, False),
    ("diag-not-float32", _sp_with(diag_info=NOT_F32), ".diag", LIM, False),
    ("edge-not-float32", _sp_with(edge_info=SP.edge_info * (1.0 + 1e-9)), ".edge_info", LIM, False),
    ("eta-not-float32", _sp_with(eta=SP.eta + 1e-3 * np.abs(SP.eta).max()), ".eta", LIM, False),
    (
        "diag-beyond-float32",
        _sp_with(diag_info=_with(SP.diag_info, (0, 0, 0), 1e300)),
        ".diag",
        LIM,
        False,
    ),
    ("diag-asymmetric", _sp_with(diag_info=ASYMMETRIC_DIAG), ".diag", LIM, False),
]


@pytest.mark.filterwarnings("error")  # decided without floating-point warnings
@pytest.mark.parametrize(
    ("msg", "suffix", "limits", "remote"),
    [pytest.param(m, s, lim, r, id=name) for name, m, s, lim, r in SPARSE_ENCODE_CASES],
)
def test_encode_refuses_a_sparse_xi_as_decode_does(
    msg: StackMessage, suffix: str, limits: Limits, remote: bool
) -> None:
    field = f"{PO_FIELD}{suffix}"
    with pytest.raises(LocalProtocolError) as caught:
        encode(msg, limits)
    assert caught.value.field == field
    assert str(caught.value).startswith(f"{field}: ")
    if remote:
        with pytest.raises(RemoteProtocolError) as refused:
            decode(raw_pack_objects(msg), limits)
        assert refused.value.field == field


def test_a_sparse_slot_of_more_than_65535_objects_is_refused_on_both_sides() -> None:
    """Edges index objects as uint16."""
    n = 2**16
    lim = Limits(num_classes=4, max_objects=n, max_message_bytes=2**26)
    sx = SparseXi(
        np.zeros((n, 3)),
        np.tile(np.eye(3), (n, 1, 1)),
        np.zeros((0, 2), dtype=int),
        np.zeros((0, 3, 3)),
        np.zeros(3 * n),
    )
    summary = LocalSummary(tuple(range(n)), (), ObjectClasses(np.zeros((n, 1)), sx))
    msg = StackMessage("r0", None, Stack((Slot("r1", 1, summary),)), 1)
    with pytest.raises(LocalProtocolError, match="uint16") as caught:
        encode(msg, lim)
    assert caught.value.field == "slots[0].real.edges"
    with pytest.raises(LimitExceeded, match="uint16") as refused:
        decode(raw_pack_objects(msg), lim)
    assert refused.value.field == "slots[0].real.edges"


def test_signed_sparse_slots_are_version_4_and_relayed_untouched() -> None:
    doc = msgpack.unpackb(SIGNED_SP_BLOB)
    assert doc["v"] == 4
    received = decode(SIGNED_SP_BLOB, LIM, PUBLIC)
    assert_same_objects(received, SIGNED_SP)
    relayed = encode(StackMessage("r1", None, received.stack, 11), LIM)
    assert_same_objects(
        decode(relayed, LIM, PUBLIC), dataclasses.replace(SIGNED_SP, sender="r1", step=11)
    )


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("xi", "dense"),
        ("edges", bytes([0, 0, 2, 0] + [0] * 20)),
        ("diag", None),
        ("edge_info", None),
        ("eta", None),
    ],
)
def test_every_sparse_field_is_signed(key: str, value: Any) -> None:
    doc = msgpack.unpackb(SIGNED_SP_BLOB, raw=False)
    real = doc["slots"][0]["real"]
    if value is None:  # the lowest mantissa bit of the first number: still a valid value
        value = bytes([real[key][0] ^ 0x01]) + real[key][1:]
    real[key] = value
    with pytest.raises(BadSignature) as caught:
        decode(pack(doc), LIM, PUBLIC)
    assert caught.value.field == "slots[0].sig"
    if key in ("diag", "edge_info", "eta"):  # unsigned, the changed value itself is valid
        unsigned = decode(
            pack(
                {
                    **doc,
                    "v": 3,
                    "slots": [{k: v for k, v in s.items() if k != "sig"} for s in doc["slots"]],
                }
            ),
            LIM,
        )
        assert unsigned.stack.slots[0].summary.per_object is not None


def _sparse_near_limits(rng: np.random.Generator, lim: Limits) -> LocalSummary:
    """A sparse per-object summary of 1–4 objects, its numbers scaled near ``lim``'s bounds, and
    with probability ≈ 0.3 one thing broken (a number, an edge, the pattern's order)."""
    n = int(rng.integers(1, min(lim.max_objects, 4) + 1))
    m = int(rng.integers(1, lim.num_classes + 1))
    sx = make_sparse(rng, n)
    scale = 2.0 ** float(np.floor(np.log2(lim.max_information * rng.uniform(0.05, 2.0))))
    top = float(np.linalg.eigvalsh(sx.dense().info)[-1])
    scale /= 2.0 ** float(np.ceil(np.log2(top)))  # a power of two: float32 values stay exact
    diag, edges, edge_info = sx.diag_info * scale, np.array(sx.edges), sx.edge_info * scale
    eta = (sx.eta * scale).astype(np.float32).astype(float)
    lin = rng.uniform(-1, 1, (n, 3)) * [lim.world_extent, lim.world_extent, 2 * math.pi]
    broken = rng.integers(0, 10)
    if broken == 0:
        lin[rng.integers(0, n), rng.integers(0, 3)] *= 1.5
    elif broken == 1:
        diag[rng.integers(0, n)] *= -1.0
    elif broken == 2 and len(edges):
        edge_info[rng.integers(0, len(edges))] *= 64.0 * rng.choice([-1.0, 1.0])
    elif broken == 3 and len(edges) > 1:
        edges = edges[::-1].copy()
        edge_info = edge_info[::-1].copy()
    elif broken == 4:
        eta[rng.integers(0, 3 * n)] = float(np.float32(3e38))
    elif broken == 5 and len(edges):
        edges[rng.integers(0, len(edges)), 1] = n
    xi = SparseXi(lin, diag, edges, edge_info, eta)
    phi = lim.max_abs_log_phi * rng.uniform(-1, 1, (n, m))
    return LocalSummary(tuple(range(n)), (), ObjectClasses(phi, xi))


@pytest.mark.parametrize("seed", range(4))
def test_encode_accepts_exactly_what_decode_accepts_of_sparse_slots(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    seen: dict[str, int] = {"accepted": 0}
    for _ in range(40):
        lim = PROPERTY_LIMITS[int(rng.integers(0, len(PROPERTY_LIMITS)))]
        slots = [
            Slot(f"r{i}", i, _sparse_near_limits(rng, lim))
            for i in range(int(rng.integers(1, min(lim.max_slots, 3) + 1)))
        ]
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

BLOBS = (REF_PO_BLOB, SIGNED_PO_BLOB, REF_SP_BLOB, SIGNED_SP_BLOB)
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
        *("diag", "edges", "edge_info"),
    ),
    strings=("stack", "objects", "table", "sparse", "dense", "r1", ""),
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


# --------------------------------------------------------------------------- robot-local ids


def _robot_local(msg: StackMessage) -> StackMessage:
    """``msg`` with every per-object slot stating robot-local object ids (issue 45)."""
    slots = tuple(
        s if s.summary.per_object is None else Slot(s.owner, s.stamp, s.summary.robot_local())
        for s in msg.stack
    )
    return dataclasses.replace(msg, stack=Stack(slots))


@pytest.mark.parametrize("ref", [REF_PO, REF_SP], ids=["dense", "sparse"])
def test_robot_local_ids_travel_with_a_per_object_slot(ref: StackMessage) -> None:
    """A slot of robot-local ids carries ``ids = "local"`` after its ξ, and decodes as such;
    a slot of global ids has no ``ids`` (its bytes are those of before: the layout tests)."""
    local = _robot_local(ref)
    data = encode(local, LIM)
    got = decode(data, LIM)
    assert_same_objects(got, local)
    assert encode(got, LIM) == data
    doc = msgpack.unpackb(data, raw=False)
    for slot, raw in zip(local.stack, doc["slots"], strict=True):
        if slot.summary.per_object is not None:
            assert list(raw["real"])[-1] == "ids" and raw["real"]["ids"] == "local"
    assert all("ids" not in s["real"] for s in msgpack.unpackb(encode(ref, LIM))["slots"])


@pytest.mark.parametrize("value", ["global", "none", "", 1, None, b"local"])
def test_an_unknown_id_kind_is_refused_naming_it(value: Any) -> None:
    WIRE.assert_rejected(WIRE.with_((*PO, "ids"), value), InvalidValue, f"{PO_FIELD}.ids")


def test_the_id_kind_is_signed() -> None:
    """Taking ``ids`` out of a signed slot of robot-local ids (or adding it to one of global
    ids) makes a receiver read the owner's ids as the other kind: the signature refuses it."""
    signed = _robot_local(REF_PO)
    signed = dataclasses.replace(
        signed, stack=Stack(tuple(sign_slot(s, KEYS[s.owner], LIM) for s in signed.stack))
    )
    doc = msgpack.unpackb(encode(signed, LIM), raw=False)
    assert decode(pack(doc), LIM, PUBLIC).stack.slots[0].summary.per_object.local_ids
    del doc["slots"][0]["real"]["ids"]
    with pytest.raises(BadSignature) as caught:
        decode(pack(doc), LIM, PUBLIC)
    assert caught.value.field == "slots[0].sig"
    doc = msgpack.unpackb(SIGNED_PO_BLOB, raw=False)
    doc["slots"][0]["real"]["ids"] = "local"
    with pytest.raises(BadSignature):
        decode(pack(doc), LIM, PUBLIC)


def test_an_id_kind_error_shows_a_bounded_part_of_what_came() -> None:
    with pytest.raises(InvalidValue) as caught:
        decode(WIRE.with_((*PO, "ids"), "x" * 100_000), LIM)
    assert len(str(caught.value)) < 200
