"""The one module that owns ``encode``/``decode`` of the wire format (docs/wire.md).

A message is a msgpack map ``{"v": 1, "type": "stack", "sender": str, "k": int, "pos": [x, y] | nil,
"slots": [...]}``; every float array travels as little-endian float64 bytes, Λ as its upper
triangle. ``decode`` turns every malformed input into a :class:`RemoteProtocolError` subclass that
names the field; nothing else escapes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray

from estimator.summary import LocalSummary, Realisation
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    UnsupportedVersion,
)
from protocol.stack import Slot, Stack
from protocol.validate import as_int, as_map, decode_document, need, robot_id, valid_id

Array = NDArray[np.float64]

VERSION = 1
STACK = "stack"
_F64 = np.dtype("<f8")
_MAX_STAMP = 2**63 - 1
_MAX_OBJECT_ID = 2**32 - 1
_TOP_KEYS = frozenset({"v", "type", "sender", "k", "pos", "slots"})
_SLOT_KEYS = frozenset({"owner", "stamp", "objects", "real"})
_REAL_KEYS = frozenset({"c", "phi", "lin", "info", "eta"})


@dataclass(frozen=True, slots=True)
class Limits:
    """What a receiver accepts. ``num_classes`` bounds class indices; ``symmetry_tol`` and
    ``psd_tol`` are relative to the largest |eigenvalue| of Λ."""

    num_classes: int = 64
    max_message_bytes: int = 32 * 1024 * 1024
    max_slots: int = 64
    max_objects: int = 512
    max_realisations: int = 1024
    psd_tol: float = 1e-9


@dataclass(frozen=True, slots=True, eq=False)
class StackMessage:
    """A stack as sent by ``sender`` from ``position`` (x, y), for proximity filtering, after the
    sender's step ``step`` (lets a lock-step receiver pick the version of the right round)."""

    sender: str
    position: tuple[float, float] | None
    stack: Stack
    step: int = 0


def _tri(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    return np.triu_indices(3 * n)


def encode(message: StackMessage) -> bytes:
    """Bytes of a stack message. Raises :class:`LocalProtocolError` for anything ``decode`` would
    reject: sending it would only make every receiver count an error."""
    if not valid_id(message.sender):
        raise LocalProtocolError(f"invalid robot id {message.sender!r}", "sender")
    pos = None
    if message.position is not None:
        try:
            pos = [float(v) for v in message.position]
        except (TypeError, ValueError):
            raise LocalProtocolError("must be two numbers", "pos") from None
        if len(pos) != 2 or not all(math.isfinite(v) for v in pos):
            raise LocalProtocolError("must be two finite numbers", "pos")
    step = message.step
    _local(
        isinstance(step, int) and not isinstance(step, bool) and 0 <= step <= _MAX_STAMP,
        "k",
        f"step must be an integer in 0..{_MAX_STAMP}, got {step!r}",
    )
    slots = [_encode_slot(s) for s in message.stack]
    doc = {
        "v": VERSION,
        "type": STACK,
        "sender": message.sender,
        "k": step,
        "pos": pos,
        "slots": slots,
    }
    return bytes(msgpack.packb(doc, use_bin_type=True))


def _local(cond: bool, field: str, message: str) -> None:
    if not cond:
        raise LocalProtocolError(message, field)


def _encode_slot(slot: Slot) -> dict[str, Any]:
    where = f"slots[{slot.owner}]"
    _local(valid_id(slot.owner), f"{where}.owner", f"invalid robot id {slot.owner!r}")
    stamp_ok = isinstance(slot.stamp, int | np.integer) and 0 <= slot.stamp <= _MAX_STAMP
    _local(stamp_ok, f"{where}.stamp", f"{slot.stamp!r} outside 0..{_MAX_STAMP}")
    ids = [int(j) for j in slot.summary.object_ids]
    _local(all(0 <= j <= _MAX_OBJECT_ID for j in ids), f"{where}.objects", "ids outside 0..2³²−1")
    _local(len(set(ids)) == len(ids), f"{where}.objects", "duplicate object ids")
    _local(len(slot.summary.realisations) >= 1, f"{where}.real", "no realisation")
    n = len(ids)
    rs = slot.summary.realisations
    for i, r in enumerate(rs):
        field = f"{where}.real[{i}]"
        shapes = (
            r.lin.shape == (n, 3) and r.info.shape == (3 * n, 3 * n) and r.eta.shape == (3 * n,)
        )
        _local(shapes, field, "shapes do not match the object count")
        classes_ok = len(r.classes) == n and all(0 <= c < 256 for c in r.classes)
        _local(classes_ok, f"{field}.c", "classes must be n indices in 0..255")
        _local(math.isfinite(r.log_phi), f"{field}.phi", "non-finite number")
    # One array per field for the whole slot: the checks and conversions run once, not per
    # realisation.
    lin = np.ascontiguousarray(np.stack([r.lin for r in rs]), dtype=_F64)
    info = np.ascontiguousarray(np.stack([r.info for r in rs]), dtype=_F64)
    eta = np.ascontiguousarray(np.stack([r.eta for r in rs]), dtype=_F64)
    for name, arr in (("lin", lin), ("info", info), ("eta", eta)):
        bad_rows = ~np.isfinite(arr.reshape(len(rs), -1)).all(axis=1)
        _local(not bad_rows.any(), f"{where}.real[{int(np.argmax(bad_rows))}].{name}", "non-finite")
    if n:
        scale = np.abs(info).max(axis=(1, 2))
        asymmetry = np.abs(info - info.transpose(0, 2, 1)).max(axis=(1, 2))
        bad_rows = asymmetry > 1e-12 * scale
        _local(
            not bad_rows.any(), f"{where}.real[{int(np.argmax(bad_rows))}].info", "Λ not symmetric"
        )
    bad = first_indefinite(list(info), Limits().psd_tol)
    _local(bad is None, f"{where}.real[{bad}].info", "Λ is indefinite")
    iu = _tri(n)
    upper = info[:, iu[0], iu[1]]
    reals = [
        {
            "c": bytes(bytearray(r.classes)),
            "phi": float(r.log_phi),
            "lin": lin[i].tobytes(),
            "info": upper[i].tobytes(),
            "eta": eta[i].tobytes(),
        }
        for i, r in enumerate(rs)
    ]
    return {"owner": slot.owner, "stamp": int(slot.stamp), "objects": ids, "real": reals}


def first_indefinite(infos: list[Array], tol: float) -> int | None:
    """Index of the first Λ with an eigenvalue below −tol·max|Λ|, or None.

    Λ + tol·max|Λ|·I is positive definite exactly when no eigenvalue is below that bound; one
    batched Cholesky checks every realisation of a slot at once (an eigendecomposition each was
    the codec's bottleneck).
    """
    if not infos or infos[0].size == 0:
        return None
    stack = np.stack(infos)
    scale = np.maximum(np.abs(stack).max(axis=(1, 2)), 1e-300)
    shifted = stack + (tol * scale)[:, None, None] * np.eye(stack.shape[1])
    try:
        np.linalg.cholesky(shifted)
        return None
    except np.linalg.LinAlgError:
        for i, m in enumerate(shifted):
            try:
                np.linalg.cholesky(m)
            except np.linalg.LinAlgError:
                return i
    return None


def decode(data: bytes, limits: Limits | None = None) -> StackMessage:
    """Parse and validate a stack message. Raises only :class:`RemoteProtocolError` subclasses."""
    lim = limits or Limits()
    return decode_document(data, lim.max_message_bytes, lambda doc: _decode_doc(doc, lim))


def _floats(blobs: list[Any], where: str, name: str, count: int) -> Array:
    """The float64 blobs ``name`` of every realisation of a slot as one (R, count) array."""
    for i, value in enumerate(blobs):
        field = f"{where}[{i}].{name}"
        need(isinstance(value, bytes), field, "expected binary float64 data")
        need(len(value) == 8 * count, field, f"expected {8 * count} bytes, got {len(value)}")
    arr = np.frombuffer(b"".join(blobs), dtype=_F64).astype(float).reshape(len(blobs), count)
    bad = ~np.isfinite(arr).all(axis=1)
    need(not bad.any(), f"{where}[{int(np.argmax(bad))}].{name}", "non-finite number", InvalidValue)
    return arr


def _decode_doc(doc: Any, lim: Limits) -> StackMessage:
    need(isinstance(doc, dict), "message", f"expected a map, got {type(doc).__name__}")
    version = doc.get("v")
    if "v" in doc and (type(version) is not int or version != VERSION):
        raise UnsupportedVersion(f"schema version {doc['v']!r} (this side speaks {VERSION})", "v")
    top = as_map(doc, "message", _TOP_KEYS)
    if top["type"] != STACK:
        raise UnsupportedVersion(f"message type {top['type']!r}", "type")
    sender = robot_id(top["sender"], "sender")
    step = as_int(top["k"], "k", 0, _MAX_STAMP)
    position = None
    if top["pos"] is not None:
        pos = top["pos"]
        need(isinstance(pos, list) and len(pos) == 2, "pos", "expected [x, y] or nil")
        need(
            all(isinstance(v, float | int) and not isinstance(v, bool) for v in pos),
            "pos",
            "expected numbers",
        )
        need(all(math.isfinite(v) for v in pos), "pos", "non-finite number", InvalidValue)
        position = (float(pos[0]), float(pos[1]))
    raw_slots = top["slots"]
    need(isinstance(raw_slots, list), "slots", "expected an array")
    need(
        len(raw_slots) <= lim.max_slots,
        "slots",
        f"{len(raw_slots)} > {lim.max_slots}",
        LimitExceeded,
    )
    slots = [_decode_slot(raw, f"slots[{i}]", lim) for i, raw in enumerate(raw_slots)]
    owners = [s.owner for s in slots]
    need(len(set(owners)) == len(owners), "slots", f"duplicate owners {owners}", InvalidValue)
    return StackMessage(sender, position, Stack(tuple(slots)), step)


def _decode_slot(raw: Any, where: str, lim: Limits) -> Slot:
    s = as_map(raw, where, _SLOT_KEYS)
    owner = robot_id(s["owner"], f"{where}.owner")
    stamp = as_int(s["stamp"], f"{where}.stamp", 0, _MAX_STAMP)
    objects = s["objects"]
    need(isinstance(objects, list), f"{where}.objects", "expected an array")
    n = len(objects)
    need(n <= lim.max_objects, f"{where}.objects", f"{n} > {lim.max_objects}", LimitExceeded)
    ids = tuple(
        as_int(j, f"{where}.objects[{i}]", 0, _MAX_OBJECT_ID) for i, j in enumerate(objects)
    )
    need(len(set(ids)) == n, f"{where}.objects", "duplicate object ids", InvalidValue)
    reals = s["real"]
    need(isinstance(reals, list), f"{where}.real", "expected an array")
    need(len(reals) >= 1, f"{where}.real", "a slot has at least one realisation", InvalidValue)
    need(
        len(reals) <= lim.max_realisations,
        f"{where}.real",
        f"{len(reals)} > {lim.max_realisations}",
        LimitExceeded,
    )
    iu = _tri(n)
    heads = [_decode_head(r, f"{where}.real[{i}]", n, lim) for i, r in enumerate(reals)]
    sizes = {"lin": 3 * n, "info": len(iu[0]), "eta": 3 * n}
    arrays = {
        name: _floats([h[2][name] for h in heads], f"{where}.real", name, count)
        for name, count in sizes.items()
    }
    info = np.zeros((len(heads), 3 * n, 3 * n))
    info[:, iu[0], iu[1]] = arrays["info"]
    info[:, iu[1], iu[0]] = arrays["info"]
    bad = first_indefinite(list(info), lim.psd_tol)
    need(bad is None, f"{where}.real[{bad}].info", "Λ is indefinite", InvalidValue)
    lin = arrays["lin"].reshape(len(heads), n, 3)
    out = tuple(
        Realisation(classes, phi, lin[i], info[i], arrays["eta"][i])
        for i, (classes, phi, _) in enumerate(heads)
    )
    return Slot(owner, stamp, LocalSummary(ids, out))


def _decode_head(
    raw: Any, where: str, n: int, lim: Limits
) -> tuple[tuple[int, ...], float, dict[str, Any]]:
    """Classes, log φ and the raw float blobs of one realisation."""
    r = as_map(raw, where, _REAL_KEYS)
    c = r["c"]
    need(isinstance(c, bytes) and len(c) == n, f"{where}.c", f"expected {n} class bytes")
    classes = tuple(c)
    need(
        all(v < lim.num_classes for v in classes),
        f"{where}.c",
        f"class ≥ {lim.num_classes}",
        InvalidValue,
    )
    phi = r["phi"]
    need(
        isinstance(phi, float | int) and not isinstance(phi, bool),
        f"{where}.phi",
        "expected a number",
    )
    need(math.isfinite(phi), f"{where}.phi", "non-finite number", InvalidValue)
    return classes, float(phi), r
