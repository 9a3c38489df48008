"""The wire codec of published estimates, key ``semfleet/<fleet>/estimate/<robot>`` (docs/wire.md).

An estimate is a msgpack map ``{"v": 3, "type": "estimate", "robot": str, "k": int, "beliefs":
{name: snapshot}, "counters": {name: int}}``; a snapshot is a :class:`BeliefSnapshot` with its
object ids as a msgpack int array and every other array as one raw little-endian binary: float64
for weights, poses and covariances; classes one unsigned byte each (version 3), or int64 (versions
1 and 2, and any message with a class over 255), decoded and checked in one ``frombuffer``
(docs/wire.md, "Estimates"). A snapshot with per-object class marginals (``class_probs`` (n, M))
adds two keys, ``num_classes`` (M) and ``class_probs`` (float64, C order), written only then: a
message without them is byte for byte what it was, and the version is unchanged (an older
decoder refuses a snapshot with them as unknown keys, but its ``decode_estimate_head`` still
reads the message). A message may also say which version of each peer's slot its robot's fusion
has integrated, ``fused`` (owner → stamp, what the launcher measures the age of information
with): a top-level key written only when :attr:`EstimateMessage.fused` is set, again without a
new version, but an older decoder refuses such a message as unknown keys, its
``decode_estimate_head`` too (field ``message``). As in ``protocol.codec``, ``decode_estimate``
raises only :class:`RemoteProtocolError` subclasses naming the field, and ``encode_estimate`` raises
:class:`LocalProtocolError` for exactly what the decoder would reject under the same limits (the
value checks are one function shared by both).

Over 300 lines for a reason: the encoder, the decoder and the head-only decoder the conductor
reads arriving estimates with must refuse exactly the same documents, so the three, and the limits
and value checks they share, are kept side by side in this one module.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from estimator.models.frames import MAX_STEP
from estimator.snapshot import BeliefSnapshot
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    ProtocolError,
    UnsupportedVersion,
)
from protocol.validate import as_int, as_map, decode_document, need, robot_id, valid_id

VERSION = 1
SHARED_VERSION = 2  # a snapshot may send a pose array once for all its hypotheses (docs/wire.md)
BYTE_CLASSES_VERSION = 3  # version 2, with one unsigned byte per class instead of int64
VERSIONS = (VERSION, SHARED_VERSION, BYTE_CLASSES_VERSION)
_BYTE_CLASS = "<u1"
ESTIMATE = "estimate"
MAX_COUNT = 2**63 - 1
MAX_OBJECT_ID = 2**32 - 1
MAX_BELIEFS = 8
# An agent reports about 60 counters, 4 more with ROS 2 (65 overflowed 64: issue 46, item 11).
MAX_COUNTERS = 128
BELIEF_NAME = re.compile(r"^[a-z_]{1,32}$")
COUNTER_NAME = re.compile(r"^[a-z_]{1,48}$")
_TOP_KEYS = frozenset({"v", "type", "robot", "k", "beliefs", "counters"})
# Optional: owner → stamp of the slot versions the robot's fusion has integrated.
_FUSED = "fused"
_FUSED_TOP_KEYS = _TOP_KEYS | {_FUSED}
# Wire dtype and per-hypothesis shape of every array of a snapshot but the object ids (n objects).
_LAYOUT: dict[str, tuple[str, tuple[str | int, ...]]] = {
    "weights": ("<f8", ()),
    "classes": ("<i8", ("n",)),
    "robot_pose": ("<f8", (3,)),
    "robot_cov": ("<f8", (3, 3)),
    "object_pose": ("<f8", ("n", 3)),
    "object_cov": ("<f8", ("n", 3, 3)),
}
_SNAPSHOT_KEYS = frozenset({"objects", *_LAYOUT})
# Optional, both or neither: a belief's per-object class marginals (n, M) and M.
_PROBS = "class_probs"
_NUM_CLASSES = "num_classes"
_PROBS_KEYS = frozenset({_NUM_CLASSES, _PROBS})
_PROBS_SNAPSHOT_KEYS = _SNAPSHOT_KEYS | _PROBS_KEYS
# Arrays that may travel once for every hypothesis: a belief whose hypotheses share one
# continuous belief (the default, docs/estimator.md) has the same poses and covariances in each,
# and sending them H times made a 300-hypothesis estimate of 50 objects 1.6 MB instead of 0.15.
_SHAREABLE = ("robot_pose", "robot_cov", "object_pose", "object_cov")


@dataclass(frozen=True, slots=True)
class EstimateLimits:
    """What a receiver accepts. Symmetry is relative to the largest |entry| of each covariance."""

    num_classes: int = 64
    max_hypotheses: int = 5000
    max_objects: int = 1024
    max_message_bytes: int = 32 * 1024 * 1024
    max_fused: int = 1024
    weight_tol: float = 1e-6
    symmetry_tol: float = 1e-9


@dataclass(frozen=True, slots=True, eq=False)
class EstimateMessage:
    """Robot ``robot``'s beliefs after its step ``k`` (0 before the first frame), by name
    (``"local"``, ``"distributed"``), and optionally its counters (name → count ≥ 0) and
    ``fused``: owner → stamp of the version of each peer's slot its distributed belief has
    integrated by the end of step ``k`` (None: not said; empty: none yet)."""

    robot: str
    k: int
    beliefs: dict[str, BeliefSnapshot]
    counters: dict[str, int] = field(default_factory=dict)
    fused: dict[str, int] | None = None


def _shape(h: int, n: int, per: tuple[str | int, ...]) -> tuple[int, ...]:
    return (h, *(n if d == "n" else int(d) for d in per))


def _check_values(
    arrays: Mapping[str, np.ndarray], where: str, lim: EstimateLimits, error: type[ProtocolError]
) -> None:
    """The value rules of a snapshot whose shapes are right; ``error`` says whose fault it is."""

    def need(cond: bool, name: str, message: str) -> None:
        if not cond:
            raise error(message, f"{where}.{name}")

    with np.errstate(over="ignore", invalid="ignore"):  # huge finite numbers: inf fails the test
        _check_arrays(arrays, lim, need)


def _check_arrays(
    arrays: Mapping[str, np.ndarray], lim: EstimateLimits, need: Callable[[bool, str, str], None]
) -> None:
    for name, (dtype, _) in _LAYOUT.items():
        if dtype == "<f8":
            need(bool(np.isfinite(arrays[name]).all()), name, "non-finite number")
    w = arrays["weights"]
    need(bool((w >= 0).all()), "weights", "negative weight")
    total = float(np.sum(w))
    need(abs(total - 1.0) <= lim.weight_tol, "weights", f"sum to {total!r}, not 1")
    c = arrays["classes"]
    need(bool(((c >= 0) & (c < lim.num_classes)).all()), "classes", "class outside 0..M−1")
    for name in ("robot_cov", "object_cov"):
        cov = arrays[name].reshape(-1, 3, 3)
        asymmetry = np.abs(cov - cov.transpose(0, 2, 1)).max(axis=(1, 2), initial=0.0)
        scale = np.abs(cov).max(axis=(1, 2), initial=0.0)
        need(bool((asymmetry <= lim.symmetry_tol * scale).all()), name, "not symmetric")
    p = arrays.get(_PROBS)
    if p is not None:  # (n, M) of the right shape
        need(bool(np.isfinite(p).all()), _PROBS, "non-finite number")
        need(bool(((p >= 0) & (p <= 1)).all()), _PROBS, "probability outside [0, 1]")
        sums = np.sum(p, axis=1)
        off = np.flatnonzero(np.abs(sums - 1.0) > lim.weight_tol)
        if off.size:
            need(False, _PROBS, f"row {int(off[0])} sums to {float(sums[off[0]])!r}, not 1")


def _local(cond: bool, field: str, message: str) -> None:
    if not cond:
        raise LocalProtocolError(message, field)


def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _names(value: Any, where: str, pattern: re.Pattern[str], most: int) -> None:
    _local(isinstance(value, Mapping), where, "expected a mapping")
    _local(len(value) <= most, where, f"{len(value)} entries > {most}")
    bad = [k for k in value if not (isinstance(k, str) and pattern.fullmatch(k))]
    _local(not bad, where, f"invalid names {bad!r}")


def encode_estimate(msg: EstimateMessage, limits: EstimateLimits | None = None) -> bytes:
    """Bytes of an estimate; beliefs and counters are written sorted by name."""
    lim = limits or EstimateLimits()
    _local(valid_id(msg.robot), "robot", f"invalid robot id {msg.robot!r}")
    _local(_is_int(msg.k) and 0 <= msg.k <= MAX_STEP, "k", f"{msg.k!r} outside 0..{MAX_STEP}")
    _names(msg.beliefs, "beliefs", BELIEF_NAME, MAX_BELIEFS)
    _local(len(msg.beliefs) >= 1, "beliefs", "no belief")
    _names(msg.counters, "counters", COUNTER_NAME, MAX_COUNTERS)
    for name, count in msg.counters.items():
        ok = _is_int(count) and 0 <= count <= MAX_COUNT
        _local(ok, f"counters.{name}", f"{count!r} outside 0..{MAX_COUNT}")
    if msg.fused is not None:
        _fused_local(msg.fused, lim)
    beliefs = {
        name: _encode_snapshot(msg.beliefs[name], f"beliefs.{name}", lim)
        for name in sorted(msg.beliefs)
    }
    shared = any([snap.pop(_SHARED) for snap in beliefs.values()])  # every flag removed
    byte = all(int(snap["classes"].max(initial=0)) <= 255 for snap in beliefs.values())  # ≥ 0
    for snap in beliefs.values():
        snap["classes"] = snap["classes"].astype(_BYTE_CLASS if byte else "<i8").tobytes()
    doc = {
        "v": BYTE_CLASSES_VERSION if byte else SHARED_VERSION if shared else VERSION,
        "type": ESTIMATE,
        "robot": msg.robot,
        "k": int(msg.k),
        "beliefs": beliefs,
        "counters": {name: int(msg.counters[name]) for name in sorted(msg.counters)},
    }
    if msg.fused is not None:
        doc[_FUSED] = {owner: int(msg.fused[owner]) for owner in sorted(msg.fused)}
    blob = bytes(msgpack.packb(doc, use_bin_type=True))
    size_ok = len(blob) <= lim.max_message_bytes
    _local(size_ok, "message", f"{len(blob)} bytes > {lim.max_message_bytes}")
    return blob


def _fused_local(fused: Any, lim: EstimateLimits) -> None:
    _local(isinstance(fused, Mapping), _FUSED, "expected a mapping")
    _local(len(fused) <= lim.max_fused, _FUSED, f"{len(fused)} entries > {lim.max_fused}")
    bad = [o for o in fused if not valid_id(o)]
    _local(not bad, _FUSED, f"invalid robot ids {bad!r}")
    for owner, stamp in fused.items():
        ok = _is_int(stamp) and 0 <= stamp <= MAX_STEP
        _local(ok, f"{_FUSED}.{owner}", f"{stamp!r} outside 0..{MAX_STEP}")


def _encode_snapshot(snap: BeliefSnapshot, where: str, lim: EstimateLimits) -> dict[str, Any]:
    ids = snap.object_ids
    n = len(ids)
    _local(n <= lim.max_objects, f"{where}.objects", f"{n} > {lim.max_objects}")
    ids_ok = all(_is_int(j) and 0 <= j <= MAX_OBJECT_ID for j in ids)
    _local(ids_ok, f"{where}.objects", "ids must be integers in 0..2³²−1")
    _local(len(set(ids)) == n, f"{where}.objects", "duplicate object ids")
    arrays = {}
    for name in _LAYOUT:
        try:
            arrays[name] = np.asarray(getattr(snap, name))
        except (TypeError, ValueError):
            raise LocalProtocolError("expected an array", f"{where}.{name}") from None
    h = arrays["weights"].shape[0] if arrays["weights"].ndim == 1 else -1
    _local(h >= 1, f"{where}.weights", "expected shape (H,) with H ≥ 1")
    _local(h <= lim.max_hypotheses, f"{where}.weights", f"{h} > {lim.max_hypotheses}")
    for name, (dtype, per) in _LAYOUT.items():
        a = arrays[name]
        shape = _shape(h, n, per)
        _local(a.shape == shape, f"{where}.{name}", f"expected shape {shape}, got {a.shape}")
        kinds = "iu" if dtype == "<i8" else "fiu"
        _local(a.dtype.kind in kinds, f"{where}.{name}", f"wrong dtype {a.dtype}")
    if snap.class_probs is not None:
        arrays[_PROBS] = _class_probs(snap.class_probs, n, where, lim)
    out: dict[str, Any] = {"objects": [int(j) for j in ids], _SHARED: False}
    for name in _SHAREABLE:
        a = arrays[name]
        if h > 1 and _same_in_every_row(a):
            arrays[name] = a[:1]  # the same in every hypothesis: checked and sent once
            out[_SHARED] = True
    _check_values(arrays, where, lim, LocalProtocolError)
    for name, (dtype, _) in _LAYOUT.items():
        out[name] = np.ascontiguousarray(arrays[name], dtype=dtype)
        if name != "classes":  # classes: bytes once the message's version is known
            out[name] = out[name].tobytes()
    if _PROBS in arrays:
        out[_NUM_CLASSES] = int(arrays[_PROBS].shape[1])
        out[_PROBS] = np.ascontiguousarray(arrays[_PROBS], dtype="<f8").tobytes()
    return out


def _class_probs(value: Any, n: int, where: str, lim: EstimateLimits) -> np.ndarray:
    """A snapshot's ``class_probs`` as (n, M) float64, 1 ≤ M ≤ ``num_classes``: the values the
    decoder will check."""
    field = f"{where}.{_PROBS}"
    try:
        p = np.asarray(value)
    except (TypeError, ValueError):
        raise LocalProtocolError("expected an array", field) from None
    ok = p.ndim == 2 and p.shape[0] == n
    _local(ok, field, f"expected shape ({n}, M), got {p.shape}")
    m = p.shape[1]
    _local(
        1 <= m <= lim.num_classes,
        f"{where}.{_NUM_CLASSES}",
        f"M = {m} outside 1..{lim.num_classes}",
    )
    _local(p.dtype.kind in "fiu", field, f"wrong dtype {p.dtype}")
    return p.astype(np.float64)


def _same_in_every_row(a: np.ndarray) -> bool:
    """Whether every row (hypothesis) of ``a`` equals its first, to the bit: at once for a
    broadcast view of one row (what a belief with one continuous belief gives)."""
    if a.strides[0] == 0:
        return True
    first = a[:1]
    return bool(np.array_equal(a, np.broadcast_to(first, a.shape))) and (
        a.dtype.kind != "f" or (np.signbit(a) == np.signbit(first)).all()
    )


_SHARED = "shared"  # (internal to encode: not a key on the wire)


# --------------------------------------------------------------------------- decode


def decode_estimate(data: bytes, limits: EstimateLimits | None = None) -> EstimateMessage:
    """Parse and validate an estimate. Raises only :class:`RemoteProtocolError` subclasses."""
    lim = limits or EstimateLimits()
    return decode_document(data, lim.max_message_bytes, lambda doc: _decode_doc(doc, lim))


def _named(value: Any, where: str, pattern: re.Pattern[str], most: int) -> dict[str, Any]:
    """A map from names matching ``pattern`` to anything, with at most ``most`` entries."""
    need(isinstance(value, dict), where, f"expected a map, got {type(value).__name__}")
    need(len(value) <= most, where, f"{len(value)} entries > {most}", LimitExceeded)
    need(all(isinstance(k, str) for k in value), where, "expected string names")
    bad = [k for k in value if not pattern.fullmatch(k)]
    need(not bad, where, f"invalid names {bad!r}", InvalidValue)
    return dict(value)


def decode_estimate_head(data: bytes, limits: EstimateLimits | None = None) -> EstimateMessage:
    """:func:`decode_estimate` without the beliefs' arrays: the robot, the step and the counters,
    validated, with ``beliefs`` empty. Every field but the arrays is checked as by
    :func:`decode_estimate` (a message it refuses, this refuses too, or it is refused for its
    arrays alone); a tenth of its cost for an estimate of 300 hypotheses."""
    lim = limits or EstimateLimits()

    def head(doc: Any) -> EstimateMessage:
        robot, k, _, counters, _, fused = _decode_head(doc, lim)
        return EstimateMessage(robot, k, {}, counters, fused)

    return decode_document(data, lim.max_message_bytes, head)


def _decode_doc(doc: Any, lim: EstimateLimits) -> EstimateMessage:
    robot, k, raw, counters, v, fused = _decode_head(doc, lim)
    beliefs = {name: _decode_snapshot(b, f"beliefs.{name}", lim, v) for name, b in raw.items()}
    return EstimateMessage(robot, k, beliefs, counters, fused)


def _decode_head(
    doc: Any, lim: EstimateLimits
) -> tuple[str, int, dict[str, Any], dict[str, int], int, dict[str, int] | None]:
    """The robot, the step, the beliefs still as received, the counters, the version and the
    fused versions (None: not said)."""
    need(isinstance(doc, dict), "message", f"expected a map, got {type(doc).__name__}")
    version = doc.get("v")
    if "v" in doc and (type(version) is not int or version not in VERSIONS):
        speaks = ", ".join(map(str, VERSIONS))
        raise UnsupportedVersion(f"schema version {doc['v']!r} (this side speaks {speaks})", "v")
    fused_said = isinstance(doc, dict) and _FUSED in doc
    top = as_map(doc, "message", _FUSED_TOP_KEYS if fused_said else _TOP_KEYS)
    if top["type"] != ESTIMATE:
        raise UnsupportedVersion(f"message type {top['type']!r}", "type")
    robot = robot_id(top["robot"], "robot")
    k = as_int(top["k"], "k", 0, MAX_STEP)
    raw = _named(top["beliefs"], "beliefs", BELIEF_NAME, MAX_BELIEFS)
    need(len(raw) >= 1, "beliefs", "no belief", InvalidValue)
    v = VERSION if version is None else version
    counters = _named(top["counters"], "counters", COUNTER_NAME, MAX_COUNTERS)
    for name, count in counters.items():
        as_int(count, f"counters.{name}", 0, MAX_COUNT)
    fused = _decode_fused(top[_FUSED], lim) if fused_said else None
    return robot, k, raw, counters, v, fused


def _decode_fused(value: Any, lim: EstimateLimits) -> dict[str, int]:
    """``fused``: a map of at most ``max_fused`` robot ids → stamps 0 … MAX_STEP."""
    need(isinstance(value, dict), _FUSED, f"expected a map, got {type(value).__name__}")
    most = lim.max_fused
    need(len(value) <= most, _FUSED, f"{len(value)} entries > {most}", LimitExceeded)
    need(all(isinstance(o, str) for o in value), _FUSED, "expected string robot ids")
    bad = [o for o in value if not valid_id(o)]
    need(not bad, _FUSED, f"invalid robot ids {bad!r}", InvalidValue)
    return {o: as_int(stamp, f"{_FUSED}.{o}", 0, MAX_STEP) for o, stamp in value.items()}


def _decode_snapshot(
    value: Any, where: str, lim: EstimateLimits, version: int = VERSION
) -> BeliefSnapshot:
    probs = isinstance(value, dict) and not _PROBS_KEYS.isdisjoint(value)
    s = as_map(value, where, _PROBS_SNAPSHOT_KEYS if probs else _SNAPSHOT_KEYS)
    objects = s["objects"]
    need(isinstance(objects, list), f"{where}.objects", "expected an array")
    n = len(objects)
    need(n <= lim.max_objects, f"{where}.objects", f"{n} > {lim.max_objects}", LimitExceeded)
    ids = tuple(as_int(j, f"{where}.objects[{i}]", 0, MAX_OBJECT_ID) for i, j in enumerate(objects))
    need(len(set(ids)) == n, f"{where}.objects", "duplicate object ids", InvalidValue)
    for name in _LAYOUT:
        need(isinstance(s[name], bytes), f"{where}.{name}", "expected binary data")
    w = s["weights"]
    need(len(w) % 8 == 0, f"{where}.weights", f"{len(w)} bytes is not a whole number of float64")
    h = len(w) // 8
    need(h >= 1, f"{where}.weights", "a belief has at least one hypothesis", InvalidValue)
    need(h <= lim.max_hypotheses, f"{where}.weights", f"{h} > {lim.max_hypotheses}", LimitExceeded)
    checked: dict[str, Any] = {}  # what the value rules read: a shared array once, not H times
    shared: dict[str, Any] = {}  # those arrays, H times: read-only views
    shares = version >= SHARED_VERSION
    for name, (dtype, per) in _LAYOUT.items():
        if name == "classes" and version == BYTE_CLASSES_VERSION:
            dtype = _BYTE_CLASS
        shape = _shape(h, n, per)
        size = np.dtype(dtype).itemsize * int(np.prod(shape))
        got = len(s[name])
        once = _shape(1, n, per)
        if shares and name in _SHAREABLE and h > 1 and got == 8 * int(np.prod(once)) != size:
            # one value for every hypothesis: a read-only view, H times without a copy
            checked[name] = np.frombuffer(s[name], dtype=dtype).astype(np.float64).reshape(once)
            shared[name] = np.broadcast_to(checked[name], shape)
            continue
        need(got == size, f"{where}.{name}", f"expected {size} bytes for {shape}, got {got}")
        native = np.float64 if dtype == "<f8" else np.int64  # classes: int64, whatever the wire
        checked[name] = np.frombuffer(s[name], dtype=dtype).astype(native).reshape(shape)
    if probs:
        m = as_int(s[_NUM_CLASSES], f"{where}.{_NUM_CLASSES}", 1, lim.num_classes)
        raw = s[_PROBS]
        need(isinstance(raw, bytes), f"{where}.{_PROBS}", "expected binary data")
        size = 8 * n * m
        got = len(raw)
        need(got == size, f"{where}.{_PROBS}", f"expected {size} bytes for {(n, m)}, got {got}")
        checked[_PROBS] = np.frombuffer(raw, dtype="<f8").astype(np.float64).reshape(n, m)
    _check_values(checked, where, lim, InvalidValue)
    return BeliefSnapshot(ids, **(checked | shared))
